"""A short check of a GPU machine: what the batched path gets from it, in one run that fits
a short lease. Writes one JSON file per part into OUT as each part finishes, and
``summary.json`` at the end (run by ``benchmarks/gpu_check.sh OUT``).

Parts, in this order (a part that would start after ``--budget-s`` is skipped and says so,
so the run ends in time whatever the compiles cost):

  physics     bare ``mjx.step`` of Digit (vmapped, scanned): steps/s at each
              --physics-batches, in float32 and float64
  linalg      vmapped Cholesky (``jnp.linalg.cholesky``) and LU (``jax.scipy.linalg.
              lu_factor``) at the step's matrix sizes (--sizes) and --linalg-batch, in
              float32 and float64: time per call, and from the compiled program whether
              it is one batched library call (its custom-call targets) or a loop (while
              loops in the program)
  closed      the closed loop (``run_batch``) of each --scenarios at each --batches in each
              --precisions: robot-steps/s (1 ms of motion first, which compiles; the timed
              run then reuses the program), and the ratio of its time per control step to
              bare physics' at that batch and precision where the physics part timed it
  precision   every QP of tests/data/controller_qps.npz solved in the mixed mode, as
              shipped (float32 products at "highest") and with the float32 stages left at
              JAX's default precision (TF32 on Ampere and newer): the largest torque error
              from float64 as a fraction of the torque limit, the QPs not solved and the
              interior point's mean iterations

    python benchmarks/gpu_check.py OUT                      # a GPU, the defaults (<= 8 min)
    python benchmarks/gpu_check.py OUT --physics-batches 4 --linalg-batch 8 \\
        --batches 2 --scenarios arms --precisions float64 --physics-steps 5   # a CPU, small
"""

from __future__ import annotations

import argparse
import contextlib
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SIZES = (20, 22, 36, 51, 54)      # the step's factorisations (the QP's blocks, M, nv+nc)
PARTS = ("physics", "linalg", "closed", "precision")


def _median_time(fn, *args, repeats: int = 5) -> float:
    import jax

    jax.block_until_ready(fn(*args))           # compile, first run
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def physics_part(args) -> list:
    sys.path.insert(0, str(Path(__file__).parent))
    from accelerator import bare_physics

    from safewbc_jax.sim.mjx.rollout import BatchConfig

    rows = []
    for dtype, prec in (("float32", "mixed"), ("float64", "float64")):
        for b in args.physics_batches:
            rate = bare_physics(BatchConfig("arms", precision=prec), b, args.physics_steps)
            rows.append({"dtype": dtype, "batch": b, "steps_per_s": rate})
            print(f"physics {dtype} B={b}: {rate:,.0f} mjx.step/s", flush=True)
    return rows


def _program_shape(compiled_text: str) -> dict:
    """Custom-call targets and while loops of an optimised HLO module."""
    import re

    targets = sorted(set(re.findall(r'custom_call_target="([^"]+)"', compiled_text)))
    loops = len(re.findall(r"\swhile\(", compiled_text))
    return {"custom_calls": targets, "while_loops": loops,
            "form": "loop" if loops else ("library call" if targets else "fused XLA")}


def linalg_part(args) -> list:
    import jax
    import jax.numpy as jnp
    import jax.scipy.linalg as jsl

    rows = []
    rng = np.random.default_rng(0)
    for dtype in (jnp.float32, jnp.float64):
        for n in args.sizes:
            a = rng.standard_normal((args.linalg_batch, n, n))
            spd = jnp.asarray(a @ np.swapaxes(a, 1, 2) + n * np.eye(n), dtype)
            gen = jnp.asarray(a + n * np.eye(n), dtype)
            for name, fn, x in (("cholesky", jax.jit(jax.vmap(jnp.linalg.cholesky)), spd),
                                ("lu", jax.jit(jax.vmap(lambda m: jsl.lu_factor(m)[0])), gen)):
                shape = _program_shape(fn.lower(x).compile().as_text())
                s = _median_time(fn, x)
                rows.append({"op": name, "n": n, "dtype": jnp.dtype(dtype).name,
                             "batch": args.linalg_batch, "s": s, **shape})
                print(f"linalg {name:8s} n={n:2d} {jnp.dtype(dtype).name} "
                      f"B={args.linalg_batch}: {s * 1e3:8.3f} ms  {shape['form']} "
                      f"{shape['custom_calls']}", flush=True)
    return rows


def closed_part(args, physics: list) -> list:
    sys.path.insert(0, str(Path(__file__).parent))
    from accelerator import pushes

    from safewbc_jax.sim.mjx import rollout as R

    phys = {(r["dtype"], r["batch"]): r["steps_per_s"] for r in physics}
    rows = []
    for sc in args.scenarios:
        for prec in args.precisions:
            for b in args.batches:
                cfg = R.BatchConfig(sc, duration=args.duration, precision=prec)
                params, push = R.default_params(sc, b), pushes(b, 0)
                t0 = time.perf_counter()
                R.run_batch(R.BatchConfig(sc, duration=1e-3, settle=1.0, precision=prec),
                            params, push)
                first_s = time.perf_counter() - t0
                n_steps, _ = R.plant(cfg).schedule(cfg)
                t0 = time.perf_counter()
                met, _ = R.run_batch(cfg, params, push)
                rate = b * n_steps / (time.perf_counter() - t0)
                bare = phys.get(("float32" if prec == "mixed" else "float64", b))
                n_sub = R.plant(cfg).n_sub
                ratio = bare / n_sub / rate if bare else None
                rows.append({"scenario": sc, "precision": prec, "batch": b,
                             "control_steps": n_steps, "first_call_s": first_s,
                             "robot_steps_per_s": rate, "ratio_to_physics": ratio,
                             "fell": int(np.sum(met["fell"])),
                             "qp_failed": int(np.sum(met["qp_failed"]))})
                print(f"closed {sc} {prec} B={b}: {rate:,.0f} robot-steps/s, first call "
                      f"{first_s:.1f} s, ratio to physics "
                      f"{'-' if ratio is None else f'{ratio:.2f}'}, fell "
                      f"{rows[-1]['fell']}", flush=True)
    return rows


def _fixture_errors(run_mixed) -> dict:
    """Per scenario of the fixture: the largest |u - u_float64| / torque limit of the mixed
    solve ``run_mixed(qps)``, and the QPs it did not solve."""
    sys.path.insert(0, str(Path(__file__).parent))
    from precision import load_fixture

    qps, _, scen, lim, ref = load_fixture()
    nv, nu = qps.nv, qps.nu
    res = run_mixed(qps)
    x, status = np.asarray(res.x)[:, nv:nv + nu], np.asarray(res.status)
    out = {}
    for s in sorted(set(scen)):
        m = scen == s
        ok = m & ~np.isnan(x).any(axis=1)
        e = np.abs(x[ok] - ref.x[ok][:, nv:nv + nu]) / lim[ok]
        out[s] = {"qps": int(m.sum()), "max_torque_error": float(e.max()) if e.size else None,
                  "not_solved": int((status[m] != 0).sum()),
                  "ipm_iterations_mean": float(np.mean(np.asarray(res.iterations)[m])),
                  "polished": int(np.sum(np.asarray(res.polished)[m]))}
    return out


def precision_part(args) -> dict:
    import jax

    from safewbc_jax.control import precision
    from safewbc_jax.solvers import jax_qp

    def mixed(qps):
        return jax_qp.solve_batch(qps, settings=precision.qp_settings("mixed"))

    shipped = _fixture_errors(mixed)
    jax.clear_caches()
    # the float32 stages at JAX's default matrix-product precision: what the solver did
    # before it set "highest" (TF32 on an Ampere or newer GPU; plain float32 on a CPU)
    was = jax_qp.full_float32
    jax_qp.full_float32 = contextlib.nullcontext
    try:
        default = _fixture_errors(mixed)
    finally:
        jax_qp.full_float32 = was
        jax.clear_caches()
    for s in shipped:
        print(f"precision {s}: mixed, " + "; ".join(
            f"{k} {r[s]['max_torque_error']:.2e} ({r[s]['not_solved']} not solved, "
            f"{r[s]['ipm_iterations_mean']:.1f} iterations)"
            for k, r in (("highest", shipped), ("default", default))), flush=True)
    return {"highest": shipped, "default": default}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", help="folder for the JSON files (created)")
    ap.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    ap.add_argument("--budget-s", type=float, default=420.0,
                    help="no part starts after this many seconds from the start")
    ap.add_argument("--physics-batches", nargs="+", type=int, default=[4096, 16384])
    ap.add_argument("--physics-steps", type=int, default=100)
    ap.add_argument("--sizes", nargs="+", type=int, default=list(SIZES))
    ap.add_argument("--linalg-batch", type=int, default=4096)
    ap.add_argument("--scenarios", nargs="+", default=["arms", "walk"])
    ap.add_argument("--batches", nargs="+", type=int, default=[1024, 4096])
    ap.add_argument("--precisions", nargs="+", default=["mixed", "float64"])
    ap.add_argument("--duration", type=float, default=0.5, help="s of motion after settle")
    args = ap.parse_args(argv)
    for name in ("physics_batches", "sizes", "batches"):
        if any(v < 1 for v in getattr(args, name)):
            ap.error(f"--{name.replace('_', '-')}: positive integers, got {getattr(args, name)}")
    if args.linalg_batch < 1 or args.physics_steps < 1 or not args.duration > 0:
        ap.error("--linalg-batch, --physics-steps and --duration must be positive")

    import jax

    import safewbc_jax
    from safewbc_jax.control import precision
    from safewbc_jax.sim.mjx.rollout import BATCHED_SCENARIOS
    from safewbc_jax.solvers import jax_qp

    for p in args.precisions:
        precision.check(p, "--precisions")
    bad = [s for s in args.scenarios if s not in BATCHED_SCENARIOS]
    if bad:
        ap.error(f"--scenarios {bad}: not among {', '.join(BATCHED_SCENARIOS)}")
    safewbc_jax.enable_x64()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    dev = jax.devices()[0]
    head = {"device": dev.device_kind, "platform": dev.platform, "jax": jax.__version__,
            "host": platform.node(), "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
            "args": vars(args)}
    print(f"gpu_check: {dev.device_kind} ({dev.platform}), jax {jax.__version__}", flush=True)
    t_start = time.perf_counter()
    done, skipped, physics = {}, [], []
    with jax_qp.blas_threads(1):
        for part in PARTS:
            if part not in args.parts:
                continue
            if time.perf_counter() - t_start > args.budget_s:
                skipped.append(part)
                print(f"{part}: skipped, past --budget-s {args.budget_s:.0f}", flush=True)
                continue
            t0 = time.perf_counter()
            if part == "physics":
                res = physics_part(args)
            elif part == "linalg":
                res = linalg_part(args)
            elif part == "closed":
                res = closed_part(args, physics)
            else:
                res = precision_part(args)
            if part == "physics":
                physics = res
            done[part] = time.perf_counter() - t0
            (out / f"{part}.json").write_text(json.dumps({**head, part: res,
                                                          "wall_s": done[part]}, indent=1))
    summary = {**head, "parts_s": done, "skipped": skipped,
               "wall_s": time.perf_counter() - t_start}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"gpu_check: {len(done)} part(s) in {summary['wall_s']:.0f} s"
          + (f", skipped {skipped}" if skipped else "") + f"; JSON in {out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
