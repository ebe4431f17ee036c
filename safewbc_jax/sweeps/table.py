"""The results table of a sweep directory.

Layout of DIR::

    DIR/sweep.json                 manifest (``Manifest``): spec fingerprint, seed, batch, chunks
    DIR/spec.toml                  the spec as given
    DIR/chunks/chunk-000000.parquet  one file per finished chunk (rows: rollouts)
    DIR/chunks/...

A chunk file is written to a temporary name in the same folder, flushed to disk and
renamed over its final name (an atomic rename on POSIX), so at any moment the folder
holds only complete chunk files plus, at most, one temporary file of the chunk in flight,
which readers ignore and the next run removes. Reading the table is reading every
``chunk-*.parquet`` and concatenating them, sorted by rollout index.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

MANIFEST = "sweep.json"
CHUNKS = "chunks"
_CHUNK_RE = re.compile(r"^chunk-(\d{6,})\.parquet$")


class TableError(ValueError):
    """A sweep directory does not hold what was asked of it."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Manifest:
    """A sweep folder's plan (``sweep.json``): what a resumed or second host's run must
    share. The fields are the file's keys, in its order;
    ``objective_weights``, ``safe_sets`` and ``engine`` take their defaults in folders
    begun before them; ``lockstep`` and ``lanes`` (the mujoco engine's only: its lockstep
    width and its lanes' step, "c" or "xla", ``pool.lanes_engine``) are 1 and "xla" in a
    mujoco folder begun before them."""

    format: int = 1
    fingerprint: str
    seed: int
    batch: int
    n_rollouts: int
    n_chunks: int
    scenario: str
    spec_path: str
    axes: tuple[str, ...]
    barriers: tuple[str, ...]
    monitors: tuple[str, ...]
    outputs: tuple[str, ...]
    target: str | None
    violation_tol: float
    repeats: int
    objective: tuple[str, ...]
    objective_weights: dict[str, float] = dataclasses.field(default_factory=dict)
    safe_sets: tuple[str, ...] = ()
    engine: str = "mjx"
    lockstep: int | None = None
    lanes: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """The file's JSON object (``lockstep`` and ``lanes`` only where they are set)."""
        d: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name in ("lockstep", "lanes") and v is None:
                continue
            d[f.name] = (list(v) if isinstance(v, tuple) else dict(v) if isinstance(v, dict)
                         else v)
        return d

    def to_json(self) -> str:
        """The text of ``sweep.json``."""
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_json(cls, data: str | dict, source: str = "manifest") -> Manifest:
        """A manifest from the text of ``sweep.json`` or its parsed object; TableError
        naming ``source`` and the key for a missing, unknown or ill-typed key."""
        if isinstance(data, str):
            try:
                data = json.loads(data)
            except json.JSONDecodeError as e:
                raise TableError(f"{source}: unreadable manifest ({e})") from None
        if not isinstance(data, dict):
            raise TableError(f"{source}: a manifest is a JSON object, got "
                             f"{type(data).__name__}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        unknown = [k for k in data if k not in fields]
        if unknown:
            raise TableError(f"{source}: unknown manifest key {unknown[0]!r}; a manifest has "
                             f"{', '.join(fields)}")
        required = [k for k, f in fields.items() if f.default is dataclasses.MISSING
                    and f.default_factory is dataclasses.MISSING]
        missing = [k for k in required if k not in data]
        if missing:
            raise TableError(f"{source}: the manifest has no key {missing[0]!r}")
        kw: dict[str, Any] = {}
        for k, v in data.items():
            if k in _MANIFEST_LISTS:
                if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
                    raise TableError(f"{source}: manifest key {k!r} = {v!r}: expected a list "
                                     "of strings")
                v = tuple(v)
            elif k == "objective_weights" and not isinstance(v, dict):
                raise TableError(f"{source}: manifest key {k!r} = {v!r}: expected an object")
            kw[k] = v
        if kw.get("engine") == "mujoco" and "lockstep" not in kw:
            kw["lockstep"] = 1      # a mujoco table from before sim.lockstep: one at a time
        if kw.get("engine") == "mujoco" and "lanes" not in kw:
            kw["lanes"] = "xla"     # from before the C lanes
        return cls(**kw)


_MANIFEST_LISTS = ("axes", "barriers", "monitors", "outputs", "objective", "safe_sets")


def chunk_path(out: Path, k: int) -> Path:
    return Path(out) / CHUNKS / f"chunk-{k:06d}.parquet"


def plan_chunks(n_rollouts: int, batch: int) -> list[tuple[int, int]]:
    """[(start, stop)) rollout ranges of the chunks: batch rollouts each, the last one
    possibly shorter (it is padded to the batch when run, and the padding dropped)."""
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    return [(s, min(s + batch, n_rollouts)) for s in range(0, n_rollouts, batch)]


def finished_chunks(out: Path) -> set[int]:
    d = Path(out) / CHUNKS
    if not d.is_dir():
        return set()
    return {int(m.group(1)) for f in d.iterdir() if (m := _CHUNK_RE.match(f.name))}


_TMP_RE = re.compile(r"^\.chunk-(\d{6,})\.parquet\.tmp")


def remove_partial(out: Path, chunks=None) -> list[str]:
    """Delete temporary files that a killed run left (only those of ``chunks`` when given:
    on several hosts each one cleans up after itself); returns their names."""
    d = Path(out) / CHUNKS
    gone = []
    if d.is_dir():
        for f in d.iterdir():
            m = _TMP_RE.match(f.name)
            if m and (chunks is None or int(m.group(1)) in chunks):
                f.unlink(missing_ok=True)
                gone.append(f.name)
    return gone


def open_manifest(out: Path, manifest: Manifest, spec_text: str | None = None) -> Manifest:
    """Create DIR/sweep.json exclusively, or check that the existing one describes the same
    sweep (spec fingerprint, seed, batch, plan, engine); raises TableError naming what
    differs. The manifest is never overwritten: several hosts (``--hosts``) share one
    folder, and a plan written by one is the plan of all of them, also before any chunk of
    it has finished. Returns the folder's manifest."""
    out = Path(out)
    path = out / MANIFEST
    if not path.exists() and out.exists() and any(out.iterdir()) and not (out / CHUNKS).exists():
        raise TableError(f"{out} exists and is not a sweep directory; use another --out")
    (out / CHUNKS).mkdir(parents=True, exist_ok=True)
    if _create_exclusive(path, manifest.to_json()):
        if spec_text is not None:
            _atomic_write_text(out / "spec.toml", spec_text)
        return manifest
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise TableError(f"{path}: unreadable manifest ({e}); remove {out} or use another "
                         "--out") from None
    old = Manifest.from_json(data, str(path))
    empty = ("" if finished_chunks(out) else
             f"; no chunk of it has finished: removing {out} loses nothing")
    for key, what in (("fingerprint", "a different spec"), ("seed", "another --seed"),
                      ("batch", "another --batch"), ("n_rollouts", "a different plan"),
                      ("engine", "another --engine"),
                      ("lockstep", "another lockstep width: another version of the engine"),
                      ("lanes", "another step of the mujoco engine's lanes: a C compiler "
                                "found here or not, or another version of the engine")):
        was, now = getattr(old, key), getattr(manifest, key)
        if was != now:
            raise TableError(
                f"{out} holds a sweep with {key} = {was!r}, this one has "
                f"{now!r} ({what}); resume with the same spec, --seed, --batch and "
                f"--engine, or write to another --out{empty}")
    return old


def _create_exclusive(path: Path, text: str) -> bool:
    """Write ``path`` with ``text`` unless it exists (False then), atomically: the full
    text in a temporary file of this host and process, hard-linked to ``path`` (a link
    fails where the name exists, on local and network file systems alike)."""
    tmp = path.with_name(f".{path.name}.tmp-{_writer_id()}")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    try:
        os.link(tmp, path)
        return True
    except FileExistsError:
        return False
    finally:
        tmp.unlink(missing_ok=True)


def _writer_id() -> str:
    """This host and process, for temporary file names several hosts may write side by
    side in one shared folder."""
    import socket

    return f"{socket.gethostname()}-{os.getpid()}"


def read_manifest(out: Path) -> Manifest:
    """The manifest of sweep directory ``out``; TableError when it has none or it does not
    read as one."""
    path = Path(out) / MANIFEST
    if not path.is_file():
        raise TableError(f"{out} is not a sweep directory (no {MANIFEST}); run safewbc sweep "
                         "first")
    return Manifest.from_json(path.read_text(), str(path))


def _atomic_write_text(path: Path, text: str):
    tmp = path.with_name(f".{path.name}.tmp-{_writer_id()}")
    with open(tmp, "w") as f:
        f.write(text)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def write_chunk(out: Path, k: int, columns: dict, metadata: dict | None = None) -> Path:
    """Write chunk ``k`` (``columns``: name -> 1-D numpy array, all the same length) as
    one Parquet file, atomically: temp file in the same folder, fsync, rename."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    final = chunk_path(out, k)
    final.parent.mkdir(parents=True, exist_ok=True)
    lengths = {len(v) for v in columns.values()}
    if len(lengths) != 1:
        raise ValueError(f"chunk {k}: columns of different lengths {sorted(lengths)}")
    table = pa.table({name: pa.array(np.asarray(v)) for name, v in columns.items()})
    if metadata:
        table = table.replace_schema_metadata({"safewbc": json.dumps(metadata)})
    tmp = final.with_name(f".{final.name}.tmp-{_writer_id()}")
    with open(tmp, "wb") as f:
        pq.write_table(table, f)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, final)
    try:  # make the rename itself durable
        fd = os.open(final.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError:
        pass
    return final


def read_table(out: Path):
    """The sweep's rows so far as one pyarrow Table sorted by ``rollout`` (None when no
    chunk has finished)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    ks = sorted(finished_chunks(out))
    if not ks:
        return None
    tables = []
    for k in ks:
        p = chunk_path(out, k)
        try:
            tables.append(pq.read_table(p))
        except Exception as e:  # noqa: BLE001
            raise TableError(f"{p}: unreadable chunk ({e}); delete it and rerun the sweep to "
                             "redo that chunk") from None
    t = pa.concat_tables(tables, promote_options="default")
    return t.sort_by("rollout")


def read_columns(out: Path) -> dict:
    """The table as {column: numpy array} (empty dict when no chunk has finished)."""
    t = read_table(out)
    if t is None:
        return {}
    return {name: t.column(name).to_numpy(zero_copy_only=False) for name in t.column_names}
