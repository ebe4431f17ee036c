"""Where the package finds its model files."""

from __future__ import annotations

from pathlib import Path

_PKG = Path(__file__).resolve().parents[1]   # safewbc_jax/


def models_dir() -> Path:
    """The ``models/`` folder: in the repository next to the package, or installed inside
    the package as ``safewbc_jax/models``."""
    for cand in (_PKG.parent / "models", _PKG / "models"):
        if (cand / "digit.xml").is_file():
            return cand
    raise FileNotFoundError(f"models/digit.xml not found next to {_PKG}")


def scene_xml() -> Path:
    return models_dir() / "scene.xml"


def controller_xml() -> Path:
    return models_dir() / "digit_controller.xml"


def figures_json() -> Path:
    """The published Digit figures the models were written from (``models/``, installed
    with the package)."""
    return models_dir() / "digit_v3_parameters.json"
