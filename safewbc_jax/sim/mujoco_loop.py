"""The deployment loop: MuJoCo (C) physics of ``models/scene.xml`` around the deployable
controller (``safewbc_jax.deploy.Controller``), as it would run on the robot.

Each control step: sense (MjData -> ``deploy.Measurement``: the controller's (q, v) through
the StateMap, the soles' normal forces from the contacts) -> ``Controller.step`` (the
control step every loop shares, ``control_step``) -> the motor torques into d.ctrl ->
push (``push.force_at``) -> the physics advances control_dt -> sense again: the plant
metrics (``metrics.plant_accumulate``), the fall test (``control_step.fallen``) -> log.
A settle period of standing precedes the motion (tau < 0); the paper's tau counts from
its start.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import numpy as np

from safewbc_jax import metrics, paths, robot, statemap
from safewbc_jax.control_step import fallen, schedule
from safewbc_jax.deploy import Controller, Measurement
from safewbc_jax.modelinfo import (control_substeps, foot_contact_ids, loop_site_pairs,
                                   sim_loop_residual)
from safewbc_jax.params import ControllerParams
from safewbc_jax.push import Push, force_at
from safewbc_jax.scenarios import Scenario
from safewbc_jax.solvers.result import fallback_name


@dataclasses.dataclass
class RunConfig:
    duration: float | None = None      # s of motion (scenario default when None)
    control_dt: float = 1e-3           # s
    barrier_on: bool = True
    settle: float | None = None        # s of standing before the motion (scenario default)
    record_qps_every: int = 0          # keep every k-th QP (full matrices) in the log; 0: none
    speed: float = 0.2                 # walking: commanded forward speed (m/s)
    push: Push | None = None           # a push on the base (push.Push.single(force, at, for))


def _floor_and_leg_contacts(ms, d, sole_geoms, floor_geom, leg_geoms):
    """Normal force (N) of each sole on the floor, and whether any geom of one leg touches
    one of the other leg."""
    import mujoco

    force = {"left": 0.0, "right": 0.0}
    legs = False
    f6 = np.zeros(6)
    for i in range(d.ncon):
        c = d.contact[i]
        pair = {int(c.geom1), int(c.geom2)}
        for side, g in sole_geoms.items():
            if pair == {g, floor_geom}:
                mujoco.mj_contactForce(ms, d, i, f6)
                force[side] += abs(f6[0])
        if (pair & leg_geoms["left"]) and (pair & leg_geoms["right"]):
            legs = True
    return {**force, "legs": legs}


def load_at_stand():
    """(simulation model, controller MjModel, RobotModel, StateMap, MjData at ``stand``)."""
    import mujoco

    ms = mujoco.MjModel.from_xml_path(str(paths.scene_xml()))
    mc = mujoco.MjModel.from_xml_path(str(paths.controller_xml()))
    sm = statemap.build_state_map(ms, mc)
    d = mujoco.MjData(ms)
    mujoco.mj_resetDataKeyframe(ms, d, ms.key("stand").id)
    mujoco.mj_forward(ms, d)
    return ms, mc, robot.from_mujoco(mc), sm, d


def run(scenario: Scenario, params: ControllerParams, cfg: RunConfig, progress=None,
        observer=None):
    """Run one scenario in MuJoCo; returns (log dict of arrays, summary dict with the
    finalized metric columns under "metrics", ``metrics.finalize``, and the deployed
    ``Controller`` that ran under "controller").

    ``progress(k, n, phase)``, when given, is called with k = 0 and phase "compiling" just
    before the controller starts (Theorem 1, compile, warm-up: ``Controller.start``), then
    after every control step with k the steps done of n and the phase of that step:
    "standing" (the settle, tau < 0) or "motion". It runs outside the timed part of the
    step (t_qp, t_solve), and must be cheap (``progress.Progress.update_to`` is: a few
    microseconds).

    ``observer(meas)``, when given, is called once per control step with the measurement
    the step's command was computed from, after the command is out and outside every
    timed part (``benchmarks/controller_step.py`` runs TSID there, on the same states).

    The log's ``stance`` and ``missed_touchdowns`` at step k are the domain step k's QP ran
    in (the gait advanced from step k's measurement).
    """
    import mujoco

    n_steps, settle, duration = schedule(scenario, cfg.duration, cfg.settle, cfg.control_dt)
    ms, mc, model, sm, d = load_at_stand()
    n_sub = control_substeps(ms, cfg.control_dt)
    if n_sub is None:
        raise ValueError(f"control_dt {cfg.control_dt} must be a positive multiple of the "
                         f"simulation step {ms.opt.timestep}")
    ctl = Controller(scenario, params, cfg.control_dt, barrier=cfg.barrier_on, speed=cfg.speed,
                     settle=settle, duration=duration)
    scenario, walking = ctl.scenario, ctl.walking
    if walking:
        from safewbc_jax.walking import diagnostics as walking_diag

        diag_fn = jax.jit(partial(walking_diag, model))
    ids = foot_contact_ids(ms)
    sole_geoms = dict(zip(("left", "right"), ids["sole_geoms"].tolist()))
    floor_geom = ids["floor"]
    leg_geoms = {s: set(g.tolist()) for s, g in zip(("left", "right"), ids["legs"])}
    motor_ids = np.array([ms.actuator(n).id for n in ctl.motors.names])  # motor -> d.ctrl
    sole_ids = ids["sole_sites"]
    sole0 = d.site_xpos[sole_ids, :2].copy()
    base_id = ms.body("base").id
    loop_pairs = loop_site_pairs(ms)

    names = [o.name for o in scenario.outputs]
    hnames = [b.name for b in scenario.barriers + scenario.monitors]
    log = {k: [] for k in ("t", "tau", "u", "status", "fallback", "t_qp", "t_solve", "latency",
                           "zmp_margin", "eq_residual", "loop_residual", "base_z", "lambda",
                           "qpos", "stance", "leg_contact", "missed_touchdowns", "alip")}
    for nm in names:
        log[f"y_{nm}"], log[f"yd_{nm}"] = [], []
    for hn in hnames:
        log[f"h_{hn}"] = []
    fell = False
    recorded = []
    plant = metrics.plant_init()
    if progress is not None:
        progress(0, n_steps, "compiling")
    compile_s = ctl.start(*sm.to_controller(d.qpos, d.qvel))

    def sense(t):
        f = _floor_and_leg_contacts(ms, d, sole_geoms, floor_geom, leg_geoms)
        q, v = sm.to_controller(d.qpos, d.qvel)
        return Measurement(q, v, t, np.array([f["left"], f["right"]])), f["legs"]

    meas, _ = sense(0.0)
    for k in range(n_steps):
        cmd = ctl.step(meas)
        if observer is not None:
            observer(meas)
        hr = ctl.record
        if hr is None:   # a measurement that could not enter the step (not from this loop)
            fell = True
            break
        rec = hr.step
        fb = fallback_name(rec.fallback) if rec.ok else "held"
        if cfg.record_qps_every and k % cfg.record_qps_every == 0:
            recorded.append((k, ctl.last_qp(), int(rec.status), fb))
        d.ctrl[motor_ids] = cmd.motor
        d.xfrc_applied[base_id, :3] = (force_at(cfg.push, rec.tau) if cfg.push is not None
                                       else 0.0)
        for _ in range(n_sub):
            mujoco.mj_step(ms, d)
        meas, legs = sense((k + 1) * cfg.control_dt)
        loop_res = sim_loop_residual(ms, d, loop_pairs)
        plant = metrics.plant_accumulate(plant, True, rec, d.site_xpos[sole_ids], sole0,
                                         loop_res, legs)
        log["t"].append(k * cfg.control_dt), log["tau"].append(float(rec.tau))
        log["u"].append(cmd.u), log["status"].append(int(rec.status))
        log["fallback"].append(fb)
        log["t_qp"].append(hr.t_qp), log["t_solve"].append(hr.t_solve)
        log["latency"].append(cmd.latency_us)
        log["eq_residual"].append(float(rec.eq_residual)), log["lambda"].append(rec.lam)
        log["zmp_margin"].append(float(rec.zmp_margin))
        log["stance"].append(float(rec.stance)), log["missed_touchdowns"].append(int(rec.missed))
        for nm in names:
            log[f"y_{nm}"].append(rec.y[nm]), log[f"yd_{nm}"].append(rec.yd[nm])
        for hn in hnames:
            log[f"h_{hn}"].append(float(rec.h[hn]))
        log["alip"].append(np.asarray(diag_fn(hr.q, hr.v, hr.domain)) if walking
                           else np.zeros(0))
        log["leg_contact"].append(legs), log["loop_residual"].append(loop_res)
        log["base_z"].append(float(d.xpos[base_id][2]))
        log["qpos"].append(d.qpos.copy())
        if progress is not None:
            progress(k + 1, n_steps, "standing" if rec.tau < 0 else "motion")
        if fallen(meas.q, meas.v):
            fell = True
            break
    arrays = {k: np.asarray(v) for k, v in log.items()}
    arrays["compile_s"] = np.asarray(compile_s)
    if recorded:
        fields = ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")
        for f in fields:
            arrays[f"qp_{f}"] = np.stack([np.asarray(getattr(r[1], f)) for r in recorded])
        arrays["qp_step"] = np.array([r[0] for r in recorded])
        arrays["qp_status"] = np.array([r[2] for r in recorded])
        arrays["qp_fallback"] = np.array([r[3] for r in recorded])
    st = ctl.state
    flat = metrics.finalize(ctl.tally.acc, plant, fell, st.gait if walking else None)
    tau = arrays["tau"]
    return arrays, dict(fell=fell, settle=settle, duration=duration, n_sub=n_sub,
                        duration_s=float(max(tau[-1], 0.0) + cfg.control_dt) if tau.size else 0.0,
                        steps_taken=int(st.gait.steps) if walking else 0, walking=walking,
                        sim_dt=float(ms.opt.timestep), torque_limit=np.asarray(model.torque_limit),
                        outputs=names, barriers=[b.name for b in scenario.barriers],
                        monitors=[b.name for b in scenario.monitors],
                        bad_measurements=ctl.bad_measurements, metrics=flat,
                        t_qp=arrays["t_qp"], t_solve=arrays["t_solve"], compile_s=compile_s,
                        controller=ctl)
