"""PIQP solve time on a stream of slowly varying controller-size QPs, path by path.

Paths, timed side by side on the same QP at every step (in a shuffled order per step):

  qpsolvers          qpsolvers.solve_problem(Problem(...), solver="piqp", backend="dense")
  dense_cold         piqp.DenseSolver(): setup + solve, a new solver every step
  dense_warm         one piqp.DenseSolver: setup once, update + solve every step
  dense_warm_precond as dense_warm with preconditioner_reuse_on_update=True
  class_numpy        PiqpSolver().solve(qp) on numpy arrays (checks and info included)
  class_jax          PiqpSolver().solve(qp) on JAX arrays (adds the conversion to numpy)

"warm" here means set up once and updated: PIQP 0.7 has no way to start from a previous
iterate (see safewbc_jax/solvers/piqp_path.py). Then the fallback cost: PiqpSolver on QPs
whose soft row contradicts a bound (-> "relaxed") and whose hard row does (-> "failed").

    python benchmarks/piqp_qp_bench.py --steps 2000 --json
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import random
import time

import numpy as np

N, ME = 78, 58
U = slice(36, 56)


def base_qp(rng, n, me, mi, n_soft):
    L = rng.normal(size=(n, n)) / np.sqrt(n)
    P = L @ L.T + 1e-2 * np.eye(n)
    x0 = rng.normal(size=n)
    A = rng.normal(size=(me, n))
    G = rng.normal(size=(mi, n))
    gap = np.abs(rng.normal(size=mi)) * (rng.random(mi) < 0.6)
    lb = np.full(n, -np.inf)
    ub = np.full(n, np.inf)
    lb[U] = x0[U] - rng.uniform(0.05, 1.0, U.stop - U.start)
    ub[U] = x0[U] + rng.uniform(0.05, 1.0, U.stop - U.start)
    soft = np.zeros(mi)
    soft[mi - n_soft:] = 1.0
    return dict(P=P, q=3.0 * rng.normal(size=n), A=A, G=G, gap=gap, lb=lb, ub=ub, soft=soft,
                x0=x0)


def qp_stream(rng, steps, n, me, mi, n_soft, eps):
    """Slowly varying QPs: matrices do a small random walk, vectors drift smoothly; every QP
    stays feasible at a drifting x0 (b = A x0, h = G x0 + gap)."""
    from safewbc_jax.solvers.problem import QP

    s = base_qp(rng, n, me, mi, n_soft)
    P, A, G = s["P"], s["A"], s["G"]
    phase = rng.uniform(0, 2 * np.pi, n)
    for k in range(steps):
        E = eps * rng.normal(size=(n, 4))
        P = P + E @ E.T                       # stays positive definite
        A = A + eps * rng.normal(size=A.shape)
        G = G + eps * rng.normal(size=G.shape)
        wave = np.sin(2 * np.pi * k / 500.0 + phase)
        x0 = s["x0"] + 0.05 * wave
        q = s["q"] + 0.3 * wave
        lb = s["lb"] + 0.05 * wave
        ub = s["ub"] + 0.05 * wave
        yield QP(P=P, q=q, A=A, b=A @ x0, G=G, h=G @ x0 + s["gap"], lb=lb, ub=ub,
                 soft=s["soft"])


def stats(ts_ns):
    a = np.asarray(ts_ns, dtype=float) / 1e3
    return {"median_us": float(np.median(a)), "p99_us": float(np.percentile(a, 99)),
            "mean_us": float(a.mean()), "max_us": float(a.max()), "n": int(a.size)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--warmup", type=int, default=50)
    ap.add_argument("--mi", type=int, default=40, help="inequality rows (default 40)")
    ap.add_argument("--soft", type=int, default=16, help="soft rows among them (default 16)")
    ap.add_argument("--eps", type=float, default=1e-3, help="per-step matrix drift")
    ap.add_argument("--fallback-steps", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.steps < 1 or args.mi < 1 or not 0 <= args.soft <= args.mi:
        ap.error("need --steps >= 1, --mi >= 1, 0 <= --soft <= --mi")

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import piqp
    import qpsolvers

    from safewbc_jax.solvers.problem import QP
    from safewbc_jax.solvers.piqp_path import PiqpSolver
    from safewbc_jax.solvers.result import fallback_name

    rng = np.random.default_rng(args.seed)
    order_rng = random.Random(args.seed)

    warm = piqp.DenseSolver()
    warm_pre = piqp.DenseSolver()
    warm_pre.settings.preconditioner_reuse_on_update = True
    cls_np, cls_jax = PiqpSolver(), PiqpSolver()

    def run_qpsolvers(qp, _):
        sol = qpsolvers.solve_problem(qpsolvers.Problem(qp.P, qp.q, qp.G, qp.h, qp.A, qp.b,
                                                        qp.lb, qp.ub),
                                      solver="piqp", backend="dense")
        return sol.x, sol.extras["info"].iter

    def run_cold(qp, _):
        s = piqp.DenseSolver()
        s.setup(qp.P, qp.q, qp.A, qp.b, qp.G, None, qp.h, qp.lb, qp.ub)
        s.solve()
        return s.result.x, s.result.info.iter

    def make_warm(s):
        is_setup = [False]

        def run(qp, _):
            if is_setup[0]:
                s.update(P=qp.P, c=qp.q, A=qp.A, b=qp.b, G=qp.G, h_u=qp.h, x_l=qp.lb,
                         x_u=qp.ub)
            else:
                s.setup(qp.P, qp.q, qp.A, qp.b, qp.G, None, qp.h, qp.lb, qp.ub)
                is_setup[0] = True
            s.solve()
            return s.result.x, s.result.info.iter
        return run

    def run_cls_np(qp, _):
        r = cls_np.solve(qp)
        return r.x, r.iterations

    def run_cls_jax(_, qpj):
        r = cls_jax.solve(qpj)
        return r.x, r.iterations

    paths = {
        "qpsolvers": run_qpsolvers,
        "dense_cold": run_cold,
        "dense_warm": make_warm(warm),
        "dense_warm_precond": make_warm(warm_pre),
        "class_numpy": run_cls_np,
        "class_jax": run_cls_jax,
    }
    times = {k: [] for k in paths}
    iters = {k: [] for k in paths}
    max_dx = {k: 0.0 for k in paths}
    failures = {k: 0 for k in paths}

    gc.collect()
    stream = qp_stream(rng, args.warmup + args.steps, N, ME, args.mi, args.soft, args.eps)
    for k, qp in enumerate(stream):
        qpj = QP(*(jnp.asarray(getattr(qp, f)) for f in
                   ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")))
        jax.block_until_ready(qpj)
        names = list(paths)
        order_rng.shuffle(names)
        xs = {}
        for name in names:
            t0 = time.perf_counter_ns()
            x, it = paths[name](qp, qpj)
            dt = time.perf_counter_ns() - t0
            xs[name] = x
            if k >= args.warmup:
                times[name].append(dt)
                iters[name].append(it)
        ref = xs["qpsolvers"]
        for name, x in xs.items():
            if x is None or ref is None or not (np.all(np.isfinite(x)) and np.all(np.isfinite(ref))):
                failures[name] += k >= args.warmup
            else:
                max_dx[name] = max(max_dx[name], float(np.max(np.abs(x - ref))))

    results = {}
    for name in paths:
        results[name] = {**stats(times[name]), "mean_iter": float(np.mean(iters[name])),
                         "max_abs_dx_vs_qpsolvers": max_dx[name],
                         "failures": failures[name]}

    # ------------------------------------------------------------ fallback cost
    def conflict(qp, row, j, amount=0.5):
        G, h = qp.G.copy(), qp.h.copy()
        G[row] = 0.0
        G[row, j] = -1.0
        h[row] = -(qp.ub[j] + amount)
        return QP(P=qp.P, q=qp.q, A=qp.A, b=qp.b, G=G, h=h, lb=qp.lb, ub=qp.ub, soft=qp.soft)

    fb = {}
    if args.fallback_steps > 0 and args.soft > 0:
        for label, row, expect in (("relaxed", args.mi - 1, "relaxed"),
                                   ("failed", 0 if args.soft < args.mi else None, "failed")):
            if row is None:
                continue
            solver = PiqpSolver()
            ts, its, ok = [], [], 0
            stream = qp_stream(np.random.default_rng(args.seed + 1), args.fallback_steps + 5,
                               N, ME, args.mi, args.soft, args.eps)
            for k, qp in enumerate(stream):
                r = solver.solve(conflict(qp, row, 40))
                if k >= 5:
                    ts.append(solver.last_solve_time_us * 1e3)
                    its.append(r.iterations)
                    ok += fallback_name(r.fallback) == expect
            fb[label] = {**stats(ts), "mean_iter": float(np.mean(its)),
                         "as_expected": ok}

    out = {
        "bench": "piqp_qp",
        "n": N, "me": ME, "mi": args.mi, "soft": args.soft, "steps": args.steps,
        "eps": args.eps, "seed": args.seed,
        "piqp": piqp.__version__, "qpsolvers": qpsolvers.__version__,
        "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
        "loadavg_1min": os.getloadavg()[0],
        "paths": results,
        "ratio_qpsolvers_over_dense_warm": {
            "median": results["qpsolvers"]["median_us"] / results["dense_warm"]["median_us"],
            "p99": results["qpsolvers"]["p99_us"] / results["dense_warm"]["p99_us"],
        },
        "ratio_dense_cold_over_dense_warm": {
            "median": results["dense_cold"]["median_us"] / results["dense_warm"]["median_us"],
            "p99": results["dense_cold"]["p99_us"] / results["dense_warm"]["p99_us"],
        },
        "fallback": fb,
    }

    print(f"PIQP {piqp.__version__} / qpsolvers {qpsolvers.__version__}: n={N} me={ME} "
          f"mi={args.mi} ({args.soft} soft), {args.steps} steps, drift eps={args.eps}; "
          f"{os.cpu_count()} CPUs, load {out['loadavg_1min']:.2f}")
    print(f"{'path':<20}{'median us':>11}{'p99 us':>10}{'max us':>10}{'iter':>7}"
          f"{'|dx| vs qpsolvers':>20}")
    for name, r in results.items():
        print(f"{name:<20}{r['median_us']:>11.1f}{r['p99_us']:>10.1f}{r['max_us']:>10.1f}"
              f"{r['mean_iter']:>7.2f}{r['max_abs_dx_vs_qpsolvers']:>20.1e}")
    rq = out["ratio_qpsolvers_over_dense_warm"]
    rc = out["ratio_dense_cold_over_dense_warm"]
    print(f"qpsolvers / dense_warm: median {rq['median']:.3f}, p99 {rq['p99']:.3f}")
    print(f"dense_cold / dense_warm: median {rc['median']:.3f}, p99 {rc['p99']:.3f}")
    for label, r in fb.items():
        print(f"fallback '{label}' (PiqpSolver, whole call): median {r['median_us']:.1f} us, "
              f"p99 {r['p99_us']:.1f} us, {r['mean_iter']:.1f} iterations, "
              f"{r['as_expected']}/{r['n']} as expected")
    if args.json:
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
