"""Objects from a user's own Python file, named "FILE.py:NAME": the user's safe sets
(``safesets.load``) and scenarios (``scenarios.get_scenario``). NAME is an object of the
file, or a function of no arguments that returns one. Each error names the reference,
the file and what is missing."""

from __future__ import annotations

import hashlib
import importlib.util
import re
import sys
from pathlib import Path

NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def is_ref(value) -> bool:
    """Whether ``value`` has the form "FILE.py:NAME"."""
    if not isinstance(value, str) or ":" not in value:
        return False
    path, name = value.rsplit(":", 1)
    return path.endswith(".py") and bool(NAME_RE.match(name))


def split(ref, what: str, error=ValueError) -> tuple[Path, str]:
    """"FILE.py:NAME" -> (Path, NAME), or ``error`` naming ``what`` was expected."""
    if not is_ref(ref):
        raise error(f"{what} {ref!r}: expected FILE.py:NAME (a Python file and the name of a "
                    f"{what} in it)")
    path, name = ref.rsplit(":", 1)
    return Path(path), name


def load(ref: str, cls: type, what: str, error=ValueError):
    """The ``cls`` named NAME in FILE.py (``ref`` = "FILE.py:NAME")."""
    path, name = split(ref, what, error)
    if not path.is_file():
        raise error(f"{what} {ref!r}: file {path} does not exist")
    key = "safewbc_user_" + hashlib.sha256(str(path.resolve()).encode()).hexdigest()[:16]
    spec = importlib.util.spec_from_file_location(key, path)
    if spec is None or spec.loader is None:
        raise error(f"{what} {ref!r}: {path} cannot be imported as a Python file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[key] = module
    try:
        spec.loader.exec_module(module)
    except Exception as e:  # noqa: BLE001 - the user's file: report, do not crash later
        sys.modules.pop(key, None)
        raise error(f"{what} {ref!r}: importing {path} failed: {type(e).__name__}: {e}") from e
    if not hasattr(module, name):
        found = sorted(k for k, v in vars(module).items() if isinstance(v, cls))
        raise error(f"{what} {ref!r}: {path} has no {name!r}; {cls.__name__}s there: "
                    f"{', '.join(found) or 'none'}")
    obj = getattr(module, name)
    if callable(obj) and not isinstance(obj, cls):
        obj = obj()
    if not isinstance(obj, cls):
        raise error(f"{what} {ref!r}: {name} is a {type(obj).__name__}, not a "
                    f"{cls.__module__}.{cls.__name__}")
    return obj


def absolute(ref: str, base: Path, what: str, error=ValueError) -> str:
    """``ref`` with FILE made absolute, relative to the folder ``base``."""
    path, name = split(ref, what, error)
    return f"{(Path(base) / path).resolve()}:{name}"


def digest(ref: str, what: str = "file", error=ValueError) -> str:
    """sha256 of the file a reference names."""
    path, _ = split(ref, what, error)
    return hashlib.sha256(path.read_bytes()).hexdigest()
