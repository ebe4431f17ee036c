"""The results table of a sweep directory.

Layout of DIR::

    DIR/sweep.json                 manifest: spec fingerprint, seed, batch, chunk count
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

import json
import os
import re
from pathlib import Path

import numpy as np

MANIFEST = "sweep.json"
CHUNKS = "chunks"
_CHUNK_RE = re.compile(r"^chunk-(\d{6,})\.parquet$")


class TableError(ValueError):
    """A sweep directory does not hold what was asked of it."""


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


def open_manifest(out: Path, manifest: dict, spec_text: str | None = None) -> dict:
    """Create DIR/sweep.json exclusively, or check that the existing one describes the same
    sweep (spec fingerprint, seed, batch, plan, engine); raises TableError naming what
    differs. The manifest is never overwritten: several hosts (``--hosts``) share one
    folder, and a plan written by one is the plan of all of them, also before any chunk of
    it has finished."""
    out = Path(out)
    path = out / MANIFEST
    if not path.exists() and out.exists() and any(out.iterdir()) and not (out / CHUNKS).exists():
        raise TableError(f"{out} exists and is not a sweep directory; use another --out")
    (out / CHUNKS).mkdir(parents=True, exist_ok=True)
    if _create_exclusive(path, json.dumps(manifest, indent=2)):
        if spec_text is not None:
            _atomic_write_text(out / "spec.toml", spec_text)
        return manifest
    try:
        old = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise TableError(f"{path}: unreadable manifest ({e}); remove {out} or use another "
                         "--out") from None
    # a table from before the engines was written by the mjx engine
    old, new = {"engine": "mjx", **old}, {"engine": "mjx", **manifest}
    for m in (old, new):   # a mujoco table from before sim.lockstep ran one at a time
        if m["engine"] == "mujoco":
            m.setdefault("lockstep", 1)
    empty = ("" if finished_chunks(out) else
             f"; no chunk of it has finished: removing {out} loses nothing")
    for key, what in (("fingerprint", "a different spec"), ("seed", "another --seed"),
                      ("batch", "another --batch"), ("n_rollouts", "a different plan"),
                      ("engine", "another --engine"),
                      ("lockstep", "another lockstep width: another version of the engine")):
        if old.get(key) != new.get(key):
            raise TableError(
                f"{out} holds a sweep with {key} = {old.get(key)!r}, this one has "
                f"{new.get(key)!r} ({what}); resume with the same spec, --seed, --batch and "
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


def read_manifest(out: Path) -> dict:
    path = Path(out) / MANIFEST
    if not path.is_file():
        raise TableError(f"{out} is not a sweep directory (no {MANIFEST}); run safewbc sweep "
                         "first")
    return json.loads(path.read_text())


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
