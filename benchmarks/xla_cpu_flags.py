"""The batched closed loop compiled with XLA:CPU's fusion emitters on (XLA's default) and
off (the classic emitters: the default ``import safewbc_jax`` sets, ``CPU_XLA_FLAGS``),
side by side: the CPU seconds of the first ``run_batch`` call less those of the second
(tracing, lowering and compiling), and the second call's robot-steps/s.

Each setting runs in a fresh process (XLA reads ``XLA_FLAGS`` once, when JAX starts its
CPU backend) without the persistent compilation cache, the settings alternating for
``--reps`` rounds; the medians and the ratios (off / on) are printed. The metrics of the
two programs are compared too: they are the same computation, so they agree to rounding.

    python benchmarks/xla_cpu_flags.py [--scenario arms] [--batches 2 64] [--duration 0.5]
        [--reps 1] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

SETTINGS = {"on": "--xla_cpu_use_fusion_emitters=true",
            "off": "--xla_cpu_use_fusion_emitters=false"}

CHILD = r"""
import json, os, sys, time
import numpy as np
import safewbc_jax
from safewbc_jax.sim.mjx.rollout import BatchConfig, default_params, plant, run_batch

def cpu():
    t = os.times()
    return t.user + t.system

safewbc_jax.enable_x64()
sc, b, duration = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
cfg = BatchConfig(sc, duration=duration)
params = default_params(sc, b)
n_steps, _ = plant(cfg).schedule(cfg)
c0 = cpu()
run_batch(cfg, params)                     # trace, lower, compile, run
c1, w1 = cpu(), time.perf_counter()
m, _ = run_batch(cfg, params)              # run (the step count is a run-time value)
c2, w2 = cpu(), time.perf_counter()
print(json.dumps({"flags": os.environ.get("XLA_FLAGS"),
                  "compile_cpu_s": (c1 - c0) - (c2 - c1),
                  "robot_steps_s": b * n_steps / (w2 - w1),
                  "metrics": {k: np.asarray(v, float).tolist() for k, v in m.items()
                              if np.asarray(v).dtype.kind in "fbiu"}}))
"""


def run_child(setting: str, scenario: str, batch: int, duration: float) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR",)}
    env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split()
                                if "fusion_emitters" not in f) + " " + SETTINGS[setting]
    proc = subprocess.run([sys.executable, "-c", CHILD, scenario, str(batch), str(duration)],
                          env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{setting}, batch {batch}: the child failed\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="arms")
    ap.add_argument("--batches", type=int, nargs="+", default=[2, 64])
    ap.add_argument("--duration", type=float, default=0.5, help="s of motion after settle")
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if any(b < 1 for b in args.batches) or args.reps < 1 or not args.duration > 0:
        ap.error("--batches and --reps: positive integers; --duration: positive")
    out = []
    for b in args.batches:
        runs = {"on": [], "off": []}
        for _ in range(args.reps):
            for s in ("on", "off"):
                runs[s].append(run_child(s, args.scenario, b, args.duration))
        med = {s: {k: float(np.median([r[k] for r in rs]))
                   for k in ("compile_cpu_s", "robot_steps_s")}
               for s, rs in runs.items()}
        a, z = runs["on"][0]["metrics"], runs["off"][0]["metrics"]
        diff = max(float(np.nanmax(np.abs(np.asarray(a[k]) - np.asarray(z[k])), initial=0.0))
                   for k in a if not k.startswith(("fell_time", "eq_residual")))
        row = {"scenario": args.scenario, "batch": b, "reps": args.reps, **{
            f"{s}_{k}": round(v, 2) for s, m in med.items() for k, v in m.items()},
            "compile_cpu_ratio": round(med["off"]["compile_cpu_s"] / med["on"]["compile_cpu_s"], 3),
            "speed_ratio": round(med["off"]["robot_steps_s"] / med["on"]["robot_steps_s"], 3),
            "max_metric_diff": diff}
        out.append(row)
        if not args.json:
            print(f"{args.scenario} B={b} ({args.reps} rep(s), medians): trace + compile "
                  f"{med['on']['compile_cpu_s']:.1f} CPU s with the fusion emitters, "
                  f"{med['off']['compile_cpu_s']:.1f} without (ratio "
                  f"{row['compile_cpu_ratio']:.2f}); robot-steps/s "
                  f"{med['on']['robot_steps_s']:,.0f} / {med['off']['robot_steps_s']:,.0f} "
                  f"(ratio {row['speed_ratio']:.2f}); metrics within {diff:.2g}", flush=True)
    if args.json:
        print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
