"""Latency of one controller step of the deployment path, with its breakdown.

Runs a scenario closed-loop in MuJoCo (the squat by default) and times, at every control
step and side by side: the robot terms (jitted), the QP assembly (jitted, given the
terms), the exact elimination of the equality rows (numpy), the PIQP solve of the
reduced 20-variable QP (the deployment default) and, for comparison, the PIQP solve of
the full 78-variable QP. The pieces are separate calls here (the elimination in numpy),
so their sum is above the fused step; the deployment step itself (``deploy.Controller.step``,
which drives the robot here: one jitted ``control_step.prepare`` with the elimination,
PIQP, ``control_step.conclude`` dispatched without waiting) is timed at every step too,
on the same measurement: as ``safewbc run`` records it in step_latency_us (prepare +
solve) and as the caller sees it (the whole ``step``, measurement check and motor map
included). A second controller without metrics (``Controller(keep_metrics=False)``: no
``conclude``) takes the same measurements, interleaved step by step.

    python benchmarks/controller_step.py [--scenario squat] [--steps 2000] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import time


def main(argv=None) -> dict:
    import safewbc_jax

    safewbc_jax.enable_x64()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="squat")
    ap.add_argument("--steps", type=int, default=2000, help="control steps (1 kHz)")
    ap.add_argument("--cpu", type=int, default=None, help="pin to this core (-1: no pinning)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.steps < 50:
        ap.error("--steps must be at least 50")
    from safewbc_jax.cli import pin_to_cpu

    pinned = pin_to_cpu(args.cpu)

    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np

    from safewbc_jax import controller, scenarios
    from safewbc_jax.deploy import Controller, Measurement
    from safewbc_jax.sim.mujoco_loop import load_at_stand
    from safewbc_jax.packing import Packer
    from safewbc_jax.solvers import reduce
    from safewbc_jax.solvers.piqp_path import PiqpSolver

    sc = scenarios.get_scenario(args.scenario)
    params = sc.default_params()
    ms, _, model, sm, d = load_at_stand()
    q0, _ = sm.to_controller(d.qpos, d.qvel)
    start = scenarios.start_state(model, jnp.asarray(q0))
    start["y0"] = controller.output_start_values(model, sc, jnp.asarray(q0))
    ic = jnp.asarray(sc.in_contact)

    pk_terms, pk_qp = Packer(), Packer()
    terms_fn = jax.jit(lambda q, v: pk_terms.pack(controller.robot_terms(model, sc, q, v)))
    asm_fn = jax.jit(lambda flat_terms, q, v, tau: pk_qp.pack(controller.build_qp(
        model, sc, params, flat_terms, q, v, tau, start, ic)))
    solver_red, solver_full = PiqpSolver(), PiqpSolver()
    ctl = Controller(sc, params)                    # drives the robot; metrics on
    ctl.start(q0, d.qvel[sm.qvel_idx])
    bare = Controller(sc, params, keep_metrics=False)    # the same step, no metrics
    bare.start(q0, d.qvel[sm.qvel_idx])
    motor_ids = np.array([ms.actuator(n).id for n in ctl.motors.names])
    n_sub = int(round(1e-3 / ms.opt.timestep))
    rec = {k: [] for k in ("terms", "assembly", "reduce", "solve_reduced", "solve_full",
                           "iters_reduced", "iters_full", "fused_step", "fused_jit",
                           "command", "bare_step", "bare_command")}
    t_compile = time.perf_counter()
    for k in range(args.steps):
        tau = k * 1e-3 - sc.settle
        q, v = sm.to_controller(d.qpos, d.qvel)
        t0 = time.perf_counter()
        tflat = terms_fn(q, v)
        terms = pk_terms.unpack(tflat)
        t1 = time.perf_counter()
        qpm, _ = pk_qp.unpack(asm_fn(terms, q, v, tau))
        t2 = time.perf_counter()
        if k == 0:
            bounded = reduce.bounded_variables(qpm)
            compile_s = time.perf_counter() - t_compile
        red, rmap = reduce.eliminate_equalities_np(qpm, bounded)
        t3 = time.perf_counter()
        res_r = solver_red.solve(red)
        t4 = time.perf_counter()
        res_f = solver_full.solve(qpm)
        t5 = time.perf_counter()
        meas = Measurement(q, v, k * 1e-3)
        cmd = ctl.step(meas)
        ctl.flush()                    # its metrics, off the command's path
        rec["fused_step"].append(sum(ctl.last_times))
        rec["fused_jit"].append(ctl.last_times[0])
        rec["command"].append(cmd.latency_us)
        rec["bare_command"].append(bare.step(meas).latency_us)
        rec["bare_step"].append(sum(bare.last_times))
        d.ctrl[motor_ids] = cmd.motor
        for _ in range(n_sub):
            mujoco.mj_step(ms, d)
        for key, val in zip(("terms", "assembly", "reduce", "solve_reduced", "solve_full"),
                            (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)):
            rec[key].append(val * 1e6)
        rec["iters_reduced"].append(res_r.iterations)
        rec["iters_full"].append(res_f.iterations)
    skip = 20
    arr = {k: np.asarray(v[skip:]) for k, v in rec.items()}
    step = arr["terms"] + arr["assembly"] + arr["reduce"] + arr["solve_reduced"]
    step_full = arr["terms"] + arr["assembly"] + arr["solve_full"]
    stats = lambda a: {"p50": round(float(np.percentile(a, 50)), 1),  # noqa: E731
                       "p99": round(float(np.percentile(a, 99)), 1)}
    res = {
        "scenario": args.scenario, "steps": args.steps, "pinned_cpu": pinned,
        "compile_s": round(compile_s, 2),
        "step_us": stats(step),
        "fused_step_us": stats(arr["fused_step"]),
        "fused_jit_us": stats(arr["fused_jit"]),
        "command_us": stats(arr["command"]),
        "no_metrics_step_us": stats(arr["bare_step"]),
        "no_metrics_command_us": stats(arr["bare_command"]),
        "breakdown_us": {k: stats(arr[k]) for k in ("terms", "assembly", "reduce", "solve_reduced")},
        "step_full_qp_us": stats(step_full),
        "solve_full_qp_us": stats(arr["solve_full"]),
        "solve_ratio_full_over_reduced_p50": round(float(np.median(arr["solve_full"]) /
                                                         np.median(arr["reduce"] + arr["solve_reduced"])), 2),
        "piqp_iterations_p50": {"reduced": float(np.median(arr["iters_reduced"])),
                                "full": float(np.median(arr["iters_full"]))},
        "cpu_count": os.cpu_count(),
    }
    if args.json:
        print(json.dumps(res))
    else:
        print(f"controller step, {args.scenario}, {args.steps} steps (pinned to core {pinned}):")
        print(f"  step (terms + assembly + reduce + PIQP reduced): p50 {res['step_us']['p50']} us, "
              f"p99 {res['step_us']['p99']} us")
        print(f"  fused step as safewbc run times it (one jitted call incl. the elimination, "
              f"then PIQP): p50 {res['fused_step_us']['p50']} us, p99 {res['fused_step_us']['p99']} us"
              f" (jitted part p50 {res['fused_jit_us']['p50']} us); the whole "
              f"Controller.step: p50 {res['command_us']['p50']} us, p99 "
              f"{res['command_us']['p99']} us")
        print(f"  the same without metrics (Controller(keep_metrics=False)): step p50 "
              f"{res['no_metrics_step_us']['p50']} us, p99 {res['no_metrics_step_us']['p99']}"
              f" us; whole step p50 {res['no_metrics_command_us']['p50']} us")
        for k, v in res["breakdown_us"].items():
            print(f"    {k:<14s} p50 {v['p50']:8.1f} us   p99 {v['p99']:8.1f} us")
        print(f"  PIQP on the full 78-variable QP: p50 {res['solve_full_qp_us']['p50']} us "
              f"({res['solve_ratio_full_over_reduced_p50']}x reduce + reduced solve); "
              f"iterations {res['piqp_iterations_p50']}")
    return res


if __name__ == "__main__":
    main()
