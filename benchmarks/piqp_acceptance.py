"""PIQP wrapper time with and without the precomputed acceptance checks, on the reduced
QPs of a real closed-loop run, side by side.

The deployed step computes ``policy.checks`` of the reduced QP inside its jitted call, and
``PiqpSolver.solve(qp, checks=...)`` then tests the solution with one matvec and three
reductions (``policy.residuals_checked``) instead of recomputing scales and residuals in
numpy. This times both calls of ``PiqpSolver.solve`` on the same reduced QP at every step
of a ``safewbc run``-style MuJoCo rollout, each with its own fresh solver (so both keep
their own warm PIQP setup, as the controller's does), the order alternating per step.
The checks are computed outside the timing, in numpy (the same ``policy.checks`` the step
runs in JAX). It also asserts that the two give the same status, fallback and x.

    python benchmarks/piqp_acceptance.py [--scenario squat] [--steps 7000] [--cpu 0]
        [--json]

Pin to one core and keep the machine otherwise idle; quote the medians.
"""

from __future__ import annotations

import argparse
import json
import os
import time


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default="squat")
    ap.add_argument("--steps", type=int, default=7000)
    ap.add_argument("--skip", type=int, default=200, help="first steps left out of the figures")
    ap.add_argument("--cpu", type=int, default=0, help="pin to this core (-1: no pinning)")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.steps <= a.skip:
        ap.error(f"--steps {a.steps} must exceed --skip {a.skip}")
    if a.cpu >= 0:
        os.sched_setaffinity(0, {a.cpu})

    import numpy as np
    import safewbc_jax

    safewbc_jax.enable_x64()
    from safewbc_jax.deploy import controller as deploy
    from safewbc_jax.solvers import policy
    from safewbc_jax.solvers.piqp_path import REDUCED_QP_SETTINGS, PiqpSolver
    from safewbc_jax.sim.mujoco_loop import SimRobot, rollout

    ctl = deploy.Controller(a.scenario, duration=a.steps * 1e-3)
    sim = SimRobot(ctl.motors.names, 1e-3)
    sim.reset()
    ctl.start(*sim.sm.to_controller(sim.d.qpos, sim.d.qvel))
    plain = PiqpSolver(nominal_settings=REDUCED_QP_SETTINGS)
    checked = PiqpSolver(nominal_settings=REDUCED_QP_SETTINGS)
    times = {"plain": [], "checked": []}
    before = [ctl.state]          # the controller state each step starts from
    worst = [0.0]

    def observer(meas):
        # the step's own reduced QP: prepare again from the state it started at
        _, _, red, _ = ctl.prepare_flat(before[0], meas)
        before[0] = ctl.state
        ch = policy.checks(red, np)
        calls = {"plain": lambda: plain.solve(red),
                 "checked": lambda: checked.solve(red, checks=ch)}
        order = list(calls) if len(times["plain"]) % 2 == 0 else list(calls)[::-1]
        out = {}
        for name in order:
            t = time.perf_counter_ns()
            out[name] = calls[name]()
            times[name].append((time.perf_counter_ns() - t) / 1e3)
        p, c = out["plain"], out["checked"]
        step = len(times["plain"])
        if (int(p.status), int(p.fallback)) != (int(c.status), int(c.fallback)):
            raise AssertionError(f"step {step}: status/fallback differ: "
                                 f"{p.status}/{p.fallback} vs {c.status}/{c.fallback}")
        finite = np.isfinite(p.x)
        if not np.array_equal(finite, np.isfinite(c.x)):
            raise AssertionError(f"step {step}: x finite in one solve and not the other")
        if finite.any():
            worst[0] = max(worst[0], float(np.max(np.abs(p.x[finite] - c.x[finite]))))

    fell, _, _ = rollout(sim, ctl, a.steps, observer=observer)
    res = {"scenario": a.scenario, "steps": len(times["plain"]), "fell": bool(fell),
           "max_abs_x_difference": worst[0]}
    for name, ts in times.items():
        ts = np.asarray(ts[a.skip:])
        res[name] = {"p50_us": round(float(np.median(ts)), 1),
                     "p90_us": round(float(np.percentile(ts, 90)), 1)}
    res["ratio_p50"] = round(res["checked"]["p50_us"] / res["plain"]["p50_us"], 3)
    if a.json:
        print(json.dumps(res))
    else:
        print(f"{a.scenario}: {res['steps']} steps (fell {fell}); PiqpSolver.solve p50 / p90: "
              f"without checks {res['plain']['p50_us']} / {res['plain']['p90_us']} us, "
              f"with checks {res['checked']['p50_us']} / {res['checked']['p90_us']} us; "
              f"ratio {res['ratio_p50']}; max |x difference| {worst[0]:.1e}")


if __name__ == "__main__":
    main()
