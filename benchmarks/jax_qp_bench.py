"""Amortized time per controller QP: the batched JAX solver against PIQP, side by side.

For each batch size B (default 1 4 16 64 256 1024) a batch of B recorded controller QPs
(tests/data/controller_qps.npz, cycled; or QPs generated at random states when the
fixture is absent) is solved, alternately and repeatedly:

  jax         safewbc_jax.solvers.jax_qp.solve_batch(batch): equality elimination,
              Mehrotra interior point, active-set polish and fallback for the whole batch
              in one jitted call (compiled before timing; float64). Time per call / B.
  jax_f32     the same in float32 (--f32; accuracy is only ~1e-2 on these QPs)
  piqp        PiqpSolver().solve(qp) on the full 78-variable QP, one QP after the other
              (the reference path of the deployment loop). Loop time / B.
  piqp_red    the deployment path: reduce.eliminate_equalities_np + PiqpSolver().solve on
              the 20-variable QP + x = x0 + N u, one QP after the other. Loop time / B.

Every figure is the median over --reps repetitions of amortized microseconds per QP
(the PIQP loops do not depend on B; they are re-timed at every B so that both sides see
the same machine load). The agreement of the JAX solutions with PIQP's (max |dx| relative
to max |x|) is printed too.

OpenBLAS threads: this script sets OPENBLAS_NUM_THREADS=1 before numpy loads (override
with --blas-threads N). On this 2-core machine OpenBLAS worker threads left spinning by
one LAPACK call compete with XLA's thread pool and slow both paths by up to 50x.

    python benchmarks/jax_qp_bench.py [--batches 1 16 256 1024] [--reps 7] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

FIELDS = ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")
FIXTURE = Path(__file__).resolve().parents[1] / "tests" / "data" / "controller_qps.npz"


def load_qps(path, limit, generate_n):
    """Stacked numpy QP fields (dict) from the fixture, or generated when absent."""
    if path is not None and Path(path).exists():
        import importlib.util

        spec = importlib.util.spec_from_file_location(
            "qp_fixture", Path(path).with_name("qp_fixture.py"))
        fixture = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(fixture)
        d = fixture.load(path)           # float64, P full (stored float32, upper triangle)
        n = d["qp_P"].shape[0] if limit is None else min(limit, d["qp_P"].shape[0])
        return {f: d[f"qp_{f}"][:n] for f in FIELDS}, f"{path} ({n} QPs)"
    return generate(generate_n), f"generated ({generate_n} QPs, arms scenario)"


def generate(n):
    """Controller QPs of the arms scenario at random states near the stand pose."""
    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np

    from safewbc_jax import controller, paths, robot, scenarios

    mj = mujoco.MjModel.from_xml_path(str(paths.controller_xml()))
    rm = robot.from_mujoco(mj)
    sc = scenarios.get_scenario("arms")
    params = sc.default_params()
    q0 = jnp.asarray(mj.key_qpos[0])
    start = scenarios.start_state(rm, q0)
    start["y0"] = controller.output_start_values(rm, sc, q0)

    def fn(q, v, tau):
        terms = controller.robot_terms(rm, sc, q, v)
        return controller.build_qp(rm, sc, params, terms, q, v, tau, start, jnp.ones(2))[0]

    rng = np.random.default_rng(0)
    qs = np.tile(mj.key_qpos[0], (n, 1))
    qs[:, 7:] += rng.uniform(-0.05, 0.05, (n, mj.nq - 7))
    vs = rng.normal(0, 1, (n, rm.nv)) * rng.uniform(0.05, 1.0, (n, 1))
    taus = rng.uniform(-1.5, sc.duration, n)
    qp = jax.jit(jax.vmap(fn))(qs, vs, taus)
    return {f: np.asarray(getattr(qp, f)) for f in FIELDS}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 4, 16, 64, 256, 1024])
    ap.add_argument("--reps", type=int, default=7, help="timed repetitions per batch size")
    ap.add_argument("--qps", default=str(FIXTURE), help="fixture .npz (default: tests/data)")
    ap.add_argument("--limit", type=int, default=None, help="use the first N QPs of the file")
    ap.add_argument("--generate", type=int, default=256,
                    help="QPs to generate when the fixture is absent")
    ap.add_argument("--piqp-max-batch", type=int, default=1024,
                    help="time the PIQP loops on at most this many QPs per repetition")
    ap.add_argument("--f32", action="store_true", help="also time the float32 solver")
    ap.add_argument("--blas-threads", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="print one JSON object last")
    args = ap.parse_args(argv)
    if min(args.batches) < 1 or args.reps < 1:
        ap.error("batch sizes and --reps must be >= 1")
    os.environ["OPENBLAS_NUM_THREADS"] = str(args.blas_threads)
    if "numpy" in sys.modules:
        print("warning: numpy was imported before OPENBLAS_NUM_THREADS was set",
              file=sys.stderr)

    import jax
    import jax.numpy as jnp
    import numpy as np
    import piqp

    from safewbc_jax.qp_types import QP
    from safewbc_jax.solvers import jax_qp, reduce
    from safewbc_jax.solvers.piqp_path import PiqpSolver

    data, source = load_qps(args.qps, args.limit, args.generate)
    pool = data["P"].shape[0]

    def batch_np(B):
        idx = np.arange(B) % pool
        return {f: np.ascontiguousarray(data[f][idx]) for f in FIELDS}

    piqp_full = PiqpSolver()
    piqp_red = PiqpSolver()

    def run_piqp_full(qps_np):
        xs = []
        for i in range(qps_np["P"].shape[0]):
            x, _ = piqp_full.solve(QP(*(qps_np[f][i] for f in FIELDS)))
            xs.append(x)
        return xs

    def run_piqp_red(qps_np):
        xs = []
        for i in range(qps_np["P"].shape[0]):
            qp = QP(*(qps_np[f][i] for f in FIELDS))
            red, rmap = reduce.eliminate_equalities_np(qp, 36, 20)
            z, _ = piqp_red.solve(red)
            xs.append(None if z is None else rmap.x0 + rmap.N @ z)
        return xs

    variants = [("jax", jnp.float64)] + ([("jax_f32", jnp.float32)] if args.f32 else [])
    rows = []
    for B in args.batches:
        qnp = batch_np(B)
        qj = QP(*(jnp.asarray(qnp[f]) for f in FIELDS))
        Bp = min(B, args.piqp_max_batch)
        qnp_p = {f: qnp[f][:Bp] for f in FIELDS}
        compile_s = {}
        for name, dt in variants:                  # compile + warm up
            t0 = time.perf_counter()
            jax.block_until_ready(jax_qp.solve_batch(qj, dtype=dt))
            compile_s[name] = time.perf_counter() - t0
        run_piqp_full(qnp_p)
        run_piqp_red(qnp_p)
        times = {name: [] for name, _ in variants}
        times["piqp"], times["piqp_red"] = [], []
        res = {}
        for _ in range(args.reps):
            for name, dt in variants:
                t0 = time.perf_counter()
                res[name] = jax.block_until_ready(jax_qp.solve_batch(qj, dtype=dt))
                times[name].append((time.perf_counter() - t0) / B * 1e6)
            t0 = time.perf_counter()
            xs_full = run_piqp_full(qnp_p)
            times["piqp"].append((time.perf_counter() - t0) / Bp * 1e6)
            t0 = time.perf_counter()
            run_piqp_red(qnp_p)
            times["piqp_red"].append((time.perf_counter() - t0) / Bp * 1e6)
        row = {"batch": B, "piqp_timed_on": Bp}
        for name, ts in times.items():
            row[f"{name}_us_per_qp"] = float(np.median(ts))
        for name, _ in variants:
            r = res[name]
            x = np.asarray(r.x[:Bp], np.float64)
            dx = []
            for i, xp in enumerate(xs_full):
                if xp is not None and np.all(np.isfinite(x[i])):
                    dx.append(np.abs(x[i] - xp).max() / max(1.0, np.abs(xp).max()))
            row[f"{name}_max_rel_dx_vs_piqp"] = float(max(dx)) if dx else None
            row[f"{name}_solved"] = int(np.sum(np.asarray(r.status) == 0))
            row[f"{name}_max_iterations"] = int(np.max(r.iterations))
            row[f"{name}_compile_s"] = compile_s[name]
        row["speedup_vs_piqp"] = row["piqp_us_per_qp"] / row["jax_us_per_qp"]
        row["speedup_vs_piqp_red"] = row["piqp_red_us_per_qp"] / row["jax_us_per_qp"]
        rows.append(row)
        print(f"B={B:5d}  jax {row['jax_us_per_qp']:9.1f} us/QP"
              + (f"  jax_f32 {row['jax_f32_us_per_qp']:9.1f}" if args.f32 else "")
              + f"  | piqp {row['piqp_us_per_qp']:7.1f}  piqp_red {row['piqp_red_us_per_qp']:7.1f}"
              f"  | speed-up x{row['speedup_vs_piqp']:.2f} (full), x{row['speedup_vs_piqp_red']:.2f}"
              f" (reduced)  max|dx|/|x| {row['jax_max_rel_dx_vs_piqp']:.1e}", flush=True)

    out = {
        "bench": "jax_qp", "source": source, "reps": args.reps, "statistic": "median",
        "unit": "us per QP (amortized over the batch)",
        "jax": jax.__version__, "piqp": piqp.__version__, "backend": jax.default_backend(),
        "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
        "openblas_threads": args.blas_threads, "loadavg_1min": os.getloadavg()[0],
        "rows": rows,
    }
    if args.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
