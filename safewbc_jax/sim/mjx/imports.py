"""Import ``mujoco.mjx`` without the message it prints when the optional Warp backend is
absent (this project uses MJX's JAX implementation only)."""

from __future__ import annotations

import contextlib
import io


def import_mjx():
    with contextlib.redirect_stdout(io.StringIO()):
        from mujoco import mjx
    return mjx
