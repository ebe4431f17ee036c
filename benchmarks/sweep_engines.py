"""The two engines of ``safewbc sweep`` on the same spec, one after the other in one run:
``mjx`` (batched MJX closed loop, JAX QP solver) and ``mujoco`` (a pool of deployment
loops, C MuJoCo + PIQP, one pinned worker per CPU).

For each engine the spec's first ``--chunks`` chunks run into a fresh folder
(``run_sweep``, as ``safewbc sweep`` runs them), and the script prints the wall time to
the first finished chunk (compilation included: what a user waits for) and the
robot-steps/s of the later chunks (control steps actually run, from the table's
``control_steps`` column, over their wall time), and the ratio mujoco / mjx. The tables
of the two engines are compared rollout by rollout (the largest barrier-minimum
difference, the falls).

    python benchmarks/sweep_engines.py [SPEC] [--duration S] [--batch B] [--chunks N]
        [--workers N] [--engines mjx mujoco] [--json]

The default spec is sweeps/kalpha_poles.toml (arms, 10 s, batch 64); ``--duration``
shortens its rollouts for a quicker figure (the step rate does not depend on it after
the 1 s settle). Keep the machine otherwise idle: the engines take both cores.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_engine(spec, engine: str, chunks: int, batch: int, workers, out: Path) -> dict:
    import numpy as np

    from safewbc_jax.sweeps.run import run_sweep
    from safewbc_jax.sweeps.table import chunk_path, read_columns

    marks = []

    def progress(msg):
        if "rollouts/s" in msg:       # one line per finished chunk
            marks.append(time.perf_counter())

    t0 = time.perf_counter()
    run_sweep(spec, out, batch=batch, progress=progress, max_chunks=chunks, engine=engine,
              workers=workers, check_poles=True)
    cols = read_columns(out)
    steps = [int(np.sum(cols["control_steps"][cols["chunk"] == k])) for k in range(chunks)
             if chunk_path(out, k).exists()]
    first = marks[0] - t0
    later = [(marks[k] - marks[k - 1]) for k in range(1, len(marks))]
    rate = sum(steps[1:]) / sum(later) if later else float("nan")
    return {"engine": engine, "first_chunk_s": round(first, 1),
            "robot_steps_per_s": round(rate, 1), "chunks": len(marks),
            "rollouts": int(len(cols["rollout"])), "cols": cols}


def main(argv=None) -> dict:
    import safewbc_jax

    safewbc_jax.enable_x64()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("spec", nargs="?", default=str(ROOT / "sweeps" / "kalpha_poles.toml"))
    ap.add_argument("--duration", type=float, default=None, help="s of motion (default: the spec's)")
    ap.add_argument("--batch", type=int, default=None, help="rollouts per chunk (default: the spec's)")
    ap.add_argument("--chunks", type=int, default=2, help="chunks per engine (>= 2: the first "
                    "includes compilation, the rate is of the later ones)")
    ap.add_argument("--workers", type=int, default=None, help="mujoco workers (default: one per CPU)")
    ap.add_argument("--engines", nargs="+", choices=("mjx", "mujoco"), default=["mjx", "mujoco"],
                    help="the engines to run (default both; one alone: its figures, no ratio)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.chunks < 2:
        ap.error("--chunks must be >= 2")
    import jax
    import numpy as np

    from safewbc_jax.sweeps.pool import check_workers
    from safewbc_jax.sweeps.spec import load_spec

    workers = check_workers(args.workers)
    spec = load_spec(args.spec)
    if args.duration is not None:
        spec = dataclasses.replace(spec, duration=float(args.duration))
    batch = spec.batch if args.batch is None else args.batch
    say = (lambda *a: None) if args.json else (lambda *a: print(*a, flush=True))  # noqa: E731
    say(f"spec {args.spec}: {spec.scenario}, {spec.duration} s of motion, chunks of {batch}, "
        f"{args.chunks} chunks per engine; {workers} mujoco workers; jax on "
        f"{jax.default_backend()}")
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for engine in dict.fromkeys(args.engines):
            r = run_engine(spec, engine, args.chunks, batch, workers if engine == "mujoco" else None,
                           Path(tmp) / engine)
            rows[engine] = r
            say(f"{engine:7s}: first chunk {r['first_chunk_s']:7.1f} s (compilation included), "
                f"then {r['robot_steps_per_s']:8.1f} robot-steps/s")
    res = {"spec": args.spec, "duration": spec.duration, "batch": batch, "workers": workers,
           **{e: {k: v for k, v in r.items() if k != "cols"} for e, r in rows.items()}}
    if len(rows) < 2:
        if args.json:
            print(json.dumps(res))
        return res
    a, b = rows["mujoco"]["cols"], rows["mjx"]["cols"]
    hmax = max(float(np.max(np.abs(a[k] - b[k]))) for k in a if k.startswith("barrier_min."))
    res.update({"ratio_mujoco_over_mjx": round(rows["mujoco"]["robot_steps_per_s"]
                                               / rows["mjx"]["robot_steps_per_s"], 3),
                "barrier_min_max_difference_m": hmax,
                "falls": {"mjx": int(b["fell"].sum()), "mujoco": int(a["fell"].sum())},
                "errors_mujoco": int(np.sum(a["error"] != ""))})
    say(f"mujoco / mjx robot-steps/s: {res['ratio_mujoco_over_mjx']:.2f}; barrier minima differ "
        f"by up to {hmax * 1e3:.3f} mm; falls mjx {res['falls']['mjx']}, mujoco "
        f"{res['falls']['mujoco']}; failed rollouts (mujoco) {res['errors_mujoco']}")
    if args.json:
        print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
