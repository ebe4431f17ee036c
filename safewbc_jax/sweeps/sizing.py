"""``--batch auto``: how many rollouts a chunk holds, from the sweep folder (a sweep
already begun keeps its batch) or from the device's memory."""

from __future__ import annotations

import sys
from pathlib import Path

from safewbc_jax.sweeps import table as table_mod
from safewbc_jax.sweeps.spec import SweepSpec


def resumed_batch(out) -> int | None:
    """The batch of the sweep begun in ``out`` (its manifest's), or None."""
    if (Path(out) / table_mod.MANIFEST).exists():
        try:
            return int(table_mod.read_manifest(out).batch)
        except (TypeError, ValueError):       # TableError is a ValueError
            pass
    return None


def auto_batch(spec: SweepSpec, out: Path, engine: str, quiet=False) -> int:
    """``--batch auto``: rollouts per chunk. A sweep already begun in ``out`` keeps its
    manifest's batch (it resumes); the mujoco engine and a CPU take the spec's
    ``sweep.batch``; on accelerators, the most rollouts whose closed loop fits in 90% of
    one device's memory (``rollout.memory_model``: the compiled program's memory analysis
    at 256 and 1,024 rollouts, two compiles), times the process's devices (``run_batch``
    gives each device an equal share and its own loops), at most the sweep's rollouts."""
    import jax

    resumed = resumed_batch(out)
    if resumed is not None:
        return resumed
    dev = jax.local_devices()[0]
    if engine == "mujoco" or dev.platform == "cpu":
        return spec.batch
    from safewbc_jax.sim.mjx.rollout import BatchConfig, largest_batch, memory_model

    cfg = BatchConfig.of(spec.run, precision=spec.precision)
    fixed, per = memory_model(cfg)
    limit = (dev.memory_stats() or {}).get("bytes_limit", 0)
    ndev = len(jax.local_devices())
    batch = max(1, min(spec.n_rollouts, ndev * largest_batch(fixed, per, limit)))
    if not quiet:
        print(f"[sweep] --batch auto: {batch} rollouts per chunk ({per / 1e6:.2f} MB each, "
              f"{limit / 1e9:.0f} GB on each of {ndev} {dev.device_kind})", file=sys.stderr,
              flush=True)
    return batch
