"""The first compile a user waits for, in a fresh process with no persistent compilation
cache: wall and CPU seconds (this process's threads) of

- ``run``: ``Controller("squat").start`` at the stand (Theorem 1, the start data, the
  compile of the deployed step and its warm-up), what ``safewbc run squat`` compiles
  before its loop;
- ``mjx-arms``, ``mjx-walk``: the first ``run_batch`` call at batch 2 (trace, lowering,
  XLA compile of the MJX closed loop, then 1.05 s of rollout).

Run each case in its own process, one at a time, machine otherwise idle:

    python benchmarks/first_compile.py run|mjx-arms|mjx-walk [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import time

CASES = ("run", "mjx-arms", "mjx-walk")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", choices=CASES)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)      # no persistent cache
    t0, c0 = time.perf_counter(), os.times()
    import safewbc_jax

    safewbc_jax.enable_x64()
    if args.case == "run":
        from safewbc_jax.deploy.controller import Controller
        from safewbc_jax.sim.mujoco_loop import load_at_stand

        _, _, _, sm, d = load_at_stand()
        Controller("squat", engine="xla").start(*sm.to_controller(d.qpos, d.qvel))
    else:
        from safewbc_jax.sim.mjx import rollout as R

        scenario = args.case.split("-", 1)[1]
        R.run_batch(R.BatchConfig(scenario, duration=0.05, settle=1.0),
                    R.default_params(scenario, 2))
    c1 = os.times()
    out = {"case": args.case, "wall_s": round(time.perf_counter() - t0, 1),
           "cpu_s": round(c1.user + c1.system - c0.user - c0.system, 1)}
    print(json.dumps(out) if args.json else
          f"{args.case}: {out['wall_s']} s wall, {out['cpu_s']} CPU s (no persistent cache)")
    return out


if __name__ == "__main__":
    main()
