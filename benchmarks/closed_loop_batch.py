"""Closed-loop robot-steps per second of the batched path against batch size, side by side
with bare MJX physics at the same batch and with the single-robot deployment loop
(MuJoCo C + PIQP) on the same machine.

For each batch size B:
  closed_loop   ``batch.rollout.run_batch``: controller (robot terms, QP assembly, the JAX
                QP solver) + MJX physics, B rollouts of the arms scenario (barrier on), one
                compiled call; timed on a second call (the step count is a run-time value,
                so the first call's compile is reused). robot-steps/s = B * steps / time.
                Once per --chunks value (rollouts per chunk; "none": one vmap over the
                batch; default: run_batch's default, rollout.CPU_CHUNK on a CPU).
  physics       ``jit(scan(vmap(mjx.step)))`` of the same model and batch, --physics-steps
                steps, timed on a second call.
and once:
  single_loop   the deployment step of the same scenario without the run's logging:
                deploy.Controller.step (the shared control step; PIQP) and
                mj_step, one robot, pinned to one core as `safewbc run` is (compile
                excluded).

Each figure is the median of --reps timed calls. The ratio closed_loop / single_loop is
the batched path's speed per robot-step relative to one robot in real time.

    python benchmarks/closed_loop_batch.py --batches 1 16 128 1024 [--chunks 16 none] [--json]
"""

from __future__ import annotations

import argparse
import json
import time


def single_robot_loop(n_steps: int, settle: float) -> tuple[float, float]:
    """The deployment step without the run's logging: state map, ``deploy.Controller.step``
    (the shared control step with PIQP), motor commands, mj_step. Returns (robot-steps/s
    after the first step, p50 controller step in us)."""
    import os
    import time

    import mujoco
    import numpy as np

    from safewbc_jax.deploy.controller import Controller, Measurement
    from safewbc_jax.sim.mujoco_loop import load_at_stand

    cpus = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {max(cpus)})     # pinned to one core, as `safewbc run` is
    ms, _, _, sm, d = load_at_stand()
    ctl = Controller("arms", settle=settle, engine="xla")
    ctl.start(*sm.to_controller(d.qpos, d.qvel))
    motor_ids = np.array([ms.actuator(n).id for n in ctl.motors.names])
    lat = []
    for k in range(n_steps):
        if k == 1:
            t0 = time.perf_counter()
        q, v = sm.to_controller(d.qpos, d.qvel)
        cmd = ctl.step(Measurement(q, v, k * 1e-3))
        lat.append(cmd.latency_us)
        d.ctrl[motor_ids] = cmd.motor
        mujoco.mj_step(ms, d)
    rate = (n_steps - 1) / (time.perf_counter() - t0)
    os.sched_setaffinity(0, cpus)
    return rate, float(np.median(lat[20:]))


def main(argv=None) -> dict:
    import safewbc_jax

    safewbc_jax.enable_x64()
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16, 128, 1024])
    ap.add_argument("--duration", type=float, default=0.05,
                    help="seconds of motion after the 1 s settle (default 0.05)")
    ap.add_argument("--physics-steps", type=int, default=100)
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--chunks", nargs="+", default=["auto"],
                    help="rollouts per chunk of the batched path, each timed: positive "
                         "ints, 'none' (one vmap), 'auto' (run_batch's default)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if min(args.batches) < 1 or args.reps < 1 or args.duration <= 0:
        ap.error("--batches and --reps must be positive, --duration > 0")
    chunks = []
    for c in args.chunks:
        if c in ("auto", "none"):
            chunks.append(None if c == "none" else c)
        elif c.isdigit() and int(c) > 0:
            chunks.append(int(c))
        else:
            ap.error(f"--chunks: {c!r} is not a positive int, 'none' or 'auto'")

    import jax
    import numpy as np

    from safewbc_jax.control import precision
    from safewbc_jax.sim.mjx.rollout import (BatchConfig, default_chunk, default_params, plant,
                                           run_batch)
    from safewbc_jax.base.chunking import resolve_chunk
    from safewbc_jax.sim.mjx.imports import import_mjx

    mjx = import_mjx()
    settle = 1.0      # the arms scenario's reference blend
    cfg = BatchConfig("arms", duration=args.duration, settle=settle)
    pl = plant(cfg)
    n_steps, _ = pl.schedule(cfg)
    say = (lambda *a: None) if args.json else (lambda *a: print(*a, flush=True))  # noqa: E731

    def median_time(fn, reps):
        ts = []
        for _ in range(reps):
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            ts.append(time.perf_counter() - t0)
        return float(np.median(ts))

    single, step_us = single_robot_loop(n_steps, settle)
    say(f"single-robot MuJoCo + PIQP loop: {single:.0f} robot-steps/s "
        f"(p50 controller step {step_us:.0f} us)")

    rows = []
    for b in args.batches:
        params = default_params("arms", b)
        step = jax.vmap(precision.physics(mjx.step, pl.data0.qvel.dtype), in_axes=(None, 0))
        d0 = jax.tree_util.tree_map(lambda a: np.broadcast_to(a, (b,) + a.shape), pl.data0)
        phys = jax.jit(lambda d: jax.lax.scan(lambda c, _: (step(pl.mjx_model, c), None), d,
                                              None, length=args.physics_steps)[0].qpos)
        t0 = time.perf_counter()
        jax.block_until_ready(phys(d0))
        phys_compile = time.perf_counter() - t0
        t_phys = median_time(lambda: phys(d0), args.reps)
        ph = b * args.physics_steps / t_phys
        seen = set()
        for chunk in chunks:
            used = resolve_chunk(chunk, b, default_chunk())    # as run_batch resolves it
            if used in seen:         # the same compiled function as one already timed
                continue
            seen.add(used)
            t0 = time.perf_counter()
            met, _ = run_batch(cfg, params, chunk=chunk)
            first = time.perf_counter() - t0
            t_run = median_time(lambda: run_batch(cfg, params, chunk=chunk)[0]["qp_solved"],
                                args.reps)
            cl = b * n_steps / t_run
            row = {"batch": b, "chunk": used, "steps": n_steps, "first_call_s": round(first, 1),
                   "run_s": round(t_run, 2), "closed_loop_robot_steps_per_s": round(cl, 1),
                   "physics_steps_per_s": round(ph, 1),
                   "physics_compile_s": round(phys_compile, 1),
                   "closed_loop_over_physics": round(cl / ph, 3),
                   "closed_loop_over_single_loop": round(cl / single, 3),
                   "fell": int(np.sum(met["fell"])), "qp_failed": int(np.sum(met["qp_failed"]))}
            rows.append(row)
            say(f"batch {b:5d} chunk {str(used):>4}: closed loop {cl:9.1f} robot-steps/s, "
                f"physics {ph:9.1f} steps/s, closed/physics {cl / ph:.3f}, "
                f"closed/single-loop {cl / single:.2f} (first call {first:.0f} s, "
                f"run {t_run:.1f} s, falls {row['fell']}, failed QPs {row['qp_failed']})")
    res = {"scenario": "arms", "single_loop_robot_steps_per_s": round(single, 1),
           "backend": jax.default_backend(), "rows": rows}
    if args.json:
        print(json.dumps(res))
    return res


if __name__ == "__main__":
    main()
