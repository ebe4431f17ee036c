"""float64 against the batched path's other precisions, on the recorded QPs and in closed
loop (``safewbc_jax/control/precision.py``).

fixture     every QP of ``tests/data/controller_qps.npz`` solved by the JAX solver in
            float64, in float32 and in the "mixed" mode (float32 interior point, float64
            elimination and polish); per scenario, the largest torque difference from
            float64 as a fraction of each joint's torque limit, and the QPs not solved.
            The reduced QP's conditioning (the condition number of its Hessian, float64)
            is printed beside it.
closed      ``run_batch`` of each --scenarios in float64 and in "mixed" (MJX physics and
            the interior point in float32), --batch rollouts each with seeded lateral
            pushes (0 to 30 N, 0.15 s, 0.5 s into the motion); per scenario, the outcome
            checks of issue 33: falls, steps taken, barrier minima (m) and tracking RMS
            (relative) of mixed against float64.

    python benchmarks/precision.py [--skip-closed] [--scenarios squat arms walk push]
                                   [--batch 4] [--duration S]

--duration None (default) runs each scenario's own duration. Prints one table per part.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


FIELDS = ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")


def load_fixture():
    """The recorded controller QPs (``tests/data/controller_qps.npz``): (QP batch, the
    arrays by field, each QP's scenario, each joint's torque limit per QP, the float64
    JAX solve as numpy). A joint's limit is the largest upper bound it has in any QP (a
    walking QP fixes the passive stance ankle's torque at 0 with lb = ub = 0)."""
    import importlib.util

    import jax
    import jax.numpy as jnp

    from safewbc_jax.solvers import jax_qp
    from safewbc_jax.solvers.problem import QP

    spec = importlib.util.spec_from_file_location("qp_fixture", ROOT / "tests/data/qp_fixture.py")
    fx = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fx)
    d = fx.load(ROOT / "tests/data/controller_qps.npz")
    arr = {f: d[f"qp_{f}"] for f in FIELDS}
    scen = d["qp_scenario"].astype(str)
    nv, nu = 36, 20
    n = arr["P"].shape[-1]
    qps = QP(*(jnp.asarray(arr[f]) for f in FIELDS), nv=nv, nu=nu, nc=n - nv - nu)
    ref = jax.tree_util.tree_map(np.asarray, jax_qp.solve_batch(qps))
    lim = np.broadcast_to(arr["ub"][:, nv:nv + nu].max(axis=0), (len(scen), nu))
    return qps, arr, scen, lim, ref


def fixture_part() -> None:
    import jax.numpy as jnp

    from safewbc_jax.control import precision
    from safewbc_jax.solvers import jax_qp, reduce
    from safewbc_jax.solvers.problem import QP

    qps, arr, scen, lim, ref = load_fixture()
    nv, nu, fields = qps.nv, qps.nu, FIELDS
    n = arr["P"].shape[-1]
    runs = {"float32": jax_qp.solve_batch(qps, dtype=jnp.float32),
            "mixed": jax_qp.solve_batch(qps, settings=precision.qp_settings("mixed"))}
    cond = np.empty(len(scen))
    for i in range(len(scen)):
        red, _ = reduce.eliminate_equalities_np(
            QP(*(arr[f][i] for f in fields), nv=nv, nu=nu, nc=n - nv - nu))
        cond[i] = np.linalg.cond(red.P)
    print("\nfixture: max |u - u_float64| / torque limit, per scenario (QPs not solved)")
    print(f"{'scenario':17s} {'QPs':>5s} {'cond(P_red) p50/max':>22s} "
          + "".join(f"{k:>24s}" for k in runs))
    for s in sorted(set(scen)):
        m = scen == s
        row = f"{s:17s} {int(m.sum()):5d} {np.median(cond[m]):12.1e} /{cond[m].max():8.1e}"
        for r in runs.values():
            x = np.asarray(r.x)[m][:, nv:nv + nu]
            bad = np.asarray(r.status)[m] != 0
            ok = ~np.isnan(x).any(axis=1)
            e = np.abs(x[ok] - ref.x[m][ok][:, nv:nv + nu]) / lim[m][ok]
            row += f"{e.max() if e.size else np.nan:17.2e} ({int(bad.sum()):3d})"
        print(row)


def closed_part(scenarios, batch: int, duration) -> None:
    from safewbc_jax.sim.mjx.rollout import BatchConfig, default_params, run_batch
    from safewbc_jax.control.push import PUSH_AT, PUSH_FOR, Push

    rng = np.random.default_rng(0)
    print(f"\nclosed loop: mixed against float64, {batch} rollouts each, lateral pushes")
    print(f"{'scenario':9s} {'s':>5s} {'falls f64/mixed':>16s} {'steps equal':>12s} "
          f"{'max |d barrier min| mm':>23s} {'max d tracking RMS':>19s} {'time f64/mixed s':>17s}")
    for sc in scenarios:
        fy = -30.0 * rng.uniform(0, 1, batch)
        push = Push(np.stack([np.zeros(batch), fy, np.zeros(batch)], 1),
                    np.full(batch, PUSH_AT), np.full(batch, PUSH_FOR))
        out, secs = {}, {}
        for prec in ("float64", "mixed"):
            cfg = BatchConfig(sc, duration=duration, precision=prec)
            t = time.perf_counter()
            out[prec], _ = run_batch(cfg, default_params(sc, batch), push)
            secs[prec] = time.perf_counter() - t
        a, b = out["float64"], out["mixed"]
        bar = [k for k in a if k.startswith("barrier_min.")]
        trk = [k for k in a if k.startswith("tracking_rms.")]
        dbar = max((np.abs(a[k] - b[k]).max() for k in bar), default=0.0) * 1e3
        dtrk = max(np.max(np.abs(a[k] - b[k]) / np.abs(a[k])) for k in trk)
        steps = (np.array_equal(a["steps_taken"], b["steps_taken"])
                 if "steps_taken" in a else "-")
        dur = a.get("duration_s", [duration])[0] if duration is None else duration
        print(f"{sc:9s} {str(dur):>5s} {int(a['fell'].sum()):>7d}/{int(b['fell'].sum()):<8d} "
              f"{str(steps):>12s} {dbar:23.3f} {dtrk:19.2%} "
              f"{secs['float64']:8.1f}/{secs['mixed']:<8.1f}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--skip-fixture", action="store_true")
    ap.add_argument("--skip-closed", action="store_true")
    ap.add_argument("--scenarios", nargs="+", default=["squat", "arms", "walk", "push"])
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--duration", type=float, default=None)
    args = ap.parse_args(argv)

    import safewbc_jax
    from safewbc_jax.solvers import jax_qp

    safewbc_jax.enable_x64()
    with jax_qp.blas_threads(1):
        if not args.skip_fixture:
            fixture_part()
        if not args.skip_closed:
            closed_part(args.scenarios, args.batch, args.duration)


if __name__ == "__main__":
    main()
