"""Amortized time per controller QP: the batched JAX solver against PIQP, side by side.

For each batch size B (default 1 256 1024) a batch of B recorded controller QPs
(tests/data/controller_qps.npz, cycled; or QPs generated at random states when the
fixture is absent) is solved, alternately and repeatedly:

  jax         safewbc_jax.solvers.jax_qp.solve_batch(batch, chunk=None): equality
              elimination, Mehrotra interior point, active-set polish and fallback for the
              whole batch as one vmap in one jitted call (compiled before timing; float64).
              Time per call / B.
  jax_chunkN  the same with chunk=N: the batch cut into equal chunks of at most N QPs
              (padded with copies of its last QP) and solved one chunk after the other
              (lax.map over the chunks) inside the jitted call; one column per --chunks
              value (default: the solver's CPU default, jax_qp.CPU_CHUNK). The same
              compiled function as jax when B <= N. Its largest |x - x_jax| over the
              batch is reported (the chunked solve must reproduce the unchunked one).
  jax_f32     float32 with the solver's default chunk (--f32; accuracy is only ~1e-2 on
              these QPs)
  piqp        PiqpSolver().solve(qp) on the full 78-variable QP, one QP after the other
              (the reference path of the deployment loop). Loop time / B.
  piqp_red    the deployment path: reduce.eliminate_equalities_np + PiqpSolver().solve on
              the 20-variable QP + x = x0 + N u, one QP after the other. Loop time / B.

The batch of size B is the fixture's first B QPs (cycled), so rows of different B solve
different QPs: the fixture is ordered by scenario (squat, bow, arms, arms without
barrier, walking) and its first 256 QPs (squat and bow) are easier (at most 8
interior-point iterations) than the first 1,024 (up to 22); --limit N cycles the first N
only, to compare batch sizes on the same QPs.

Every figure is the median over --reps repetitions of amortized microseconds per QP
(the PIQP loops solve one QP at a time and are timed on the same QPs as the JAX solver,
at most --piqp-max-batch of them, alternating with it so that both see the same machine
load). The agreement of the JAX solutions with PIQP's (max |dx| relative
to max |x|) is printed too.

OpenBLAS threads: this script sets OPENBLAS_NUM_THREADS=1 before numpy loads (override
with --blas-threads N). On this 2-core machine OpenBLAS worker threads left spinning by
one LAPACK call compete with XLA's thread pool and slow both paths by up to 50x.

    python benchmarks/jax_qp_bench.py [--batches 1 256 1024] [--chunks 64 128 256]
                                      [--reps 7] [--json]

With --json the last line of stdout is one JSON object (the rows, medians in us per QP).
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

    from safewbc_jax import scenarios
    from safewbc_jax.base import paths
    from safewbc_jax.control import step as control_step, terms as controller
    from safewbc_jax.model import robot

    mj = mujoco.MjModel.from_xml_path(str(paths.controller_xml()))
    rm = robot.from_mujoco(mj)
    sc = scenarios.get_scenario("arms")
    params = sc.default_params()
    q0 = jnp.asarray(mj.key_qpos[0])
    start = control_step.start_data(rm, sc, q0)

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
    import safewbc_jax

    safewbc_jax.enable_x64()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 256, 1024])
    ap.add_argument("--chunks", type=int, nargs="+", default=None,
                    help="chunk sizes of the chunked solver (default: jax_qp.CPU_CHUNK)")
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
    if min(args.batches) < 1 or args.reps < 1 or min(args.chunks or [1]) < 1:
        ap.error("batch sizes, chunk sizes and --reps must be >= 1")
    os.environ["OPENBLAS_NUM_THREADS"] = str(args.blas_threads)
    if "numpy" in sys.modules:
        print("warning: numpy was imported before OPENBLAS_NUM_THREADS was set",
              file=sys.stderr)

    import jax
    import jax.numpy as jnp
    import numpy as np
    import piqp

    from safewbc_jax.solvers.problem import QP
    from safewbc_jax.solvers import jax_qp, reduce
    from safewbc_jax.solvers.piqp_path import PiqpSolver

    data, source = load_qps(args.qps, args.limit, args.generate)
    pool = data["P"].shape[0]

    # the recorded QPs are the controller's: X = [q_ddot (nv), u (nu), lambda]
    NV, NU = 36, 20
    sized = lambda arrays: QP(*arrays, nv=NV, nu=NU, nc=arrays[0].shape[-1] - NV - NU)  # noqa: E731

    def batch_np(B):
        idx = np.arange(B) % pool
        return {f: np.ascontiguousarray(data[f][idx]) for f in FIELDS}

    piqp_full = PiqpSolver()
    piqp_red = PiqpSolver()

    def run_piqp_full(qps_np):
        xs = []
        for i in range(qps_np["P"].shape[0]):
            xs.append(piqp_full.solve(sized([qps_np[f][i] for f in FIELDS])).x)
        return xs

    def run_piqp_red(qps_np):
        xs = []
        for i in range(qps_np["P"].shape[0]):
            red, rmap = reduce.eliminate_equalities_np(sized([qps_np[f][i] for f in FIELDS]))
            xs.append(reduce.expand(piqp_red.solve(red).x, rmap))
        return xs

    chunks = args.chunks if args.chunks is not None else [jax_qp.CPU_CHUNK]
    # (name, dtype, chunk): "jax" is the unchunked reference of the chunked columns
    variants = ([("jax", jnp.float64, None)]
                + [(f"jax_chunk{c}", jnp.float64, c) for c in chunks]
                + ([("jax_f32", jnp.float32, "auto")] if args.f32 else []))
    jax_names = [name for name, _, _ in variants]
    rows = []
    for B in args.batches:
        qnp = batch_np(B)
        qj = sized([jnp.asarray(qnp[f]) for f in FIELDS])
        Bp = min(B, args.piqp_max_batch)
        qnp_p = {f: qnp[f][:Bp] for f in FIELDS}
        compile_s = {}
        for name, dt, ch in variants:              # compile + warm up
            t0 = time.perf_counter()
            jax.block_until_ready(jax_qp.solve_batch(qj, dtype=dt, chunk=ch))
            compile_s[name] = time.perf_counter() - t0
        run_piqp_full(qnp_p)
        run_piqp_red(qnp_p)
        times = {name: [] for name in jax_names}
        times["piqp"], times["piqp_red"] = [], []
        res = {}
        for _ in range(args.reps):
            for name, dt, ch in variants:
                t0 = time.perf_counter()
                res[name] = jax.block_until_ready(jax_qp.solve_batch(qj, dtype=dt, chunk=ch))
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
        x_ref = np.asarray(res["jax"].x)
        for name in jax_names:
            r = res[name]
            if name.startswith("jax_chunk"):
                xc = np.asarray(r.x)
                same_nan = bool(np.array_equal(np.isnan(xc), np.isnan(x_ref)))
                fin = ~np.isnan(x_ref)
                row[f"{name}_max_abs_dx_vs_jax"] = (
                    float(np.abs(xc[fin] - x_ref[fin]).max(initial=0.0)) if same_nan else None)
                row[f"{name}_bit_identical_to_jax"] = bool(np.array_equal(xc, x_ref,
                                                                          equal_nan=True))
            x = np.asarray(r.x[:Bp], np.float64)
            dx = []
            for i, xp in enumerate(xs_full):
                if np.all(np.isfinite(xp)) and np.all(np.isfinite(x[i])):
                    dx.append(np.abs(x[i] - xp).max() / max(1.0, np.abs(xp).max()))
            row[f"{name}_max_rel_dx_vs_piqp"] = float(max(dx)) if dx else None
            row[f"{name}_solved"] = int(np.sum(np.asarray(r.status) == 0))
            row[f"{name}_max_iterations"] = int(np.max(r.iterations))
            row[f"{name}_compile_s"] = compile_s[name]
        for name in jax_names:                     # > 1: the JAX solver is faster
            sfx = "" if name == "jax" else name[3:]
            row[f"speedup{sfx}_vs_piqp"] = row["piqp_us_per_qp"] / row[f"{name}_us_per_qp"]
            row[f"speedup{sfx}_vs_piqp_red"] = (row["piqp_red_us_per_qp"]
                                                / row[f"{name}_us_per_qp"])
        rows.append(row)
        if len(rows) == 1:
            print("us per QP (median of %d)   " % args.reps
                  + "".join(f"{n:>14s}" for n in jax_names + ["piqp", "piqp_red"])
                  + "   max|dx|/|x| vs piqp (jax)", flush=True)
        print(f"B={B:5d}                    "
              + "".join(f"{row[f'{n}_us_per_qp']:14.1f}" for n in jax_names + ["piqp", "piqp_red"])
              + f"   {row['jax_max_rel_dx_vs_piqp'] or float('nan'):.1e}", flush=True)

    out = {
        "bench": "jax_qp", "source": source, "reps": args.reps, "statistic": "median",
        "unit": "us per QP (amortized over the batch)",
        "jax": jax.__version__, "piqp": piqp.__version__, "backend": jax.default_backend(),
        "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
        "openblas_threads": args.blas_threads, "loadavg_1min": os.getloadavg()[0],
        "cpu_affinity": sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
        else None,
        "chunks": chunks, "default_chunk": jax_qp.default_chunk(),
        "rows": rows,
    }
    if args.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
