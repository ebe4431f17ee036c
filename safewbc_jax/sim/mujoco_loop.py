"""The deployment loop: MuJoCo (C) physics of ``models/scene.xml`` around the deployable
controller (``safewbc_jax.deploy.Controller``), as it would run on the robot.

Each control step: sense (MjData -> ``deploy.Measurement``: the controller's (q, v) through
the StateMap, the soles' normal forces from the contacts) -> ``Controller.step`` (gait,
rigid swing-leg rates, QP, PIQP with its fallback) -> the motor torques into d.ctrl ->
push -> the physics advances control_dt -> log. A settle period of standing precedes the
motion (tau < 0); the paper's tau counts from its start.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax import contacts, controller, paths, robot, statemap
# CompiledController, check_barrier_poles and FALL_HEIGHT live in deploy; imported from
# here by the benchmarks, the batched rollouts and the tests
from safewbc_jax.deploy import (FALL_HEIGHT, CompiledController, Controller,  # noqa: F401
                                Measurement, check_barrier_poles, fallen)
from safewbc_jax.modelinfo import (control_substeps, foot_contact_ids, loop_site_pairs,
                                   sim_loop_residual)
from safewbc_jax.params import ControllerParams
from safewbc_jax.scenarios import Scenario


@dataclasses.dataclass
class RunConfig:
    duration: float | None = None      # s of motion (scenario default when None)
    control_dt: float = 1e-3           # s
    barrier_on: bool = True
    settle: float | None = None        # s of standing before the motion (scenario default)
    record_qps_every: int = 0          # keep every k-th QP (full matrices) in the log; 0: none
    speed: float = 0.2                 # walking: commanded forward speed (m/s)
    push_force: tuple | None = None    # (FX, FY, FZ) N on the torso, world frame
    push_at: float = 2.0               # s after the motion starts
    push_for: float = 0.15             # s
    rigid_swing_leg: bool = True       # walking: swing-leg rates with rigid springs (walking.py)


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


def run(scenario: Scenario, params: ControllerParams, cfg: RunConfig, progress=None):
    """Run one scenario in MuJoCo; returns (log dict of arrays, summary dict).

    ``progress(k, n, phase)``, when given, is called with k = 0 and phase "compiling" just
    before the controller starts (Theorem 1, compile, warm-up: ``Controller.start``), then
    after every control step with k the steps done of n and the phase of that step:
    "standing" (the settle, tau < 0) or "motion". It runs outside the timed part of the
    step (t_qp, t_solve), and must be cheap (``progress.Progress.update_to`` is: a few
    microseconds).

    The log's ``stance`` and ``missed_touchdowns`` at step k are the gait after step k's
    physics (the domain of step k + 1): the controller advances its gait from the
    measurement at the start of step k + 1, so they are logged then; the last step's are
    the gait of its own domain (there is no next measurement).
    """
    import mujoco

    ms, mc, model, sm, d = load_at_stand()
    n_sub = control_substeps(ms, cfg.control_dt)
    if n_sub is None:
        raise ValueError(f"control_dt {cfg.control_dt} must be a positive multiple of the "
                         f"simulation step {ms.opt.timestep}")
    duration = scenario.duration if cfg.duration is None else cfg.duration
    settle = scenario.settle if cfg.settle is None else cfg.settle
    if duration <= 0:
        raise ValueError(f"duration must be positive, got {duration}")
    ctl = Controller(scenario, params, cfg.control_dt, barrier=cfg.barrier_on, speed=cfg.speed,
                     settle=settle, rigid_swing_leg=cfg.rigid_swing_leg)
    scenario, walking = ctl.scenario, ctl.walking
    if walking:
        from safewbc_jax.walking import diagnostics as walking_diag

        diag_fn = jax.jit(partial(walking_diag, model))
    ids = foot_contact_ids(ms)
    sole_geoms = dict(zip(("left", "right"), ids["sole_geoms"].tolist()))
    floor_geom = ids["floor"]
    leg_geoms = {s: set(g.tolist()) for s, g in zip(("left", "right"), ids["legs"])}
    in_contact = jnp.asarray(scenario.in_contact)
    motor_ids = np.array([ms.actuator(n).id for n in ctl.motors.names])  # motor -> d.ctrl
    sole_ids = ids["sole_sites"].tolist()
    sole0 = np.array([d.site_xpos[i][:2] for i in sole_ids])
    base_id = ms.body("base").id
    loop_pairs = loop_site_pairs(ms)

    n_steps = int(round((settle + duration) / cfg.control_dt))
    names = [o.name for o in scenario.outputs]
    log = {k: [] for k in ("t", "tau", "u", "status", "fallback", "t_qp",
                           "t_solve", "zmp_margin", "eq_residual", "slip", "loop_residual", "base_z",
                           "lambda", "qpos", "stance", "leg_contact", "clearance",
                           "missed_touchdowns", "alip")}
    for nm in names:
        log[f"y_{nm}"], log[f"yd_{nm}"] = [], []
    hnames = [b.name for b in scenario.barriers + scenario.monitors]
    for hn in hnames:
        log[f"h_{hn}"] = []
    fell = False
    zmp_fn = jax.jit(partial(contacts.zmp_margin, model))
    nc_chain = controller.n_chain_rows(model)
    recorded = []
    if progress is not None:
        progress(0, n_steps, "compiling")
    compile_s = ctl.start(*sm.to_controller(d.qpos, d.qvel))

    def sense(t):
        f = _floor_and_leg_contacts(ms, d, sole_geoms, floor_geom, leg_geoms)
        q, v = sm.to_controller(d.qpos, d.qvel)
        return Measurement(q, v, t, np.array([f["left"], f["right"]])), f["legs"]

    meas, _ = sense(0.0)
    for k in range(n_steps):
        t = k * cfg.control_dt
        cmd = ctl.step(meas)
        rec = ctl.record
        if rec is None:   # a state the controller refused (a diverged simulation)
            fell = True
            break
        if walking and k > 0:   # the gait after step k - 1's physics (docstring)
            log["stance"].append(ctl.gait.stance)
            log["missed_touchdowns"].append(ctl.gait.missed_touchdowns)
        tau, x, info, aux, domain = rec.tau, rec.x, rec.info, rec.aux, rec.domain
        if cfg.record_qps_every and k % cfg.record_qps_every == 0:
            recorded.append((k, ctl._ctl.last_qp, int(info["status"]), info["fallback"]))
        d.ctrl[motor_ids] = cmd.motor
        lam = x[model.nv + model.nu + nc_chain:] if x is not None else np.full(12, np.nan)
        log["t"].append(t), log["tau"].append(tau), log["u"].append(cmd.u)
        log["status"].append(int(info["status"])), log["fallback"].append(info["fallback"])
        log["t_qp"].append(rec.t_qp), log["t_solve"].append(rec.t_solve)
        log["eq_residual"].append(info["eq_residual"] if x is not None else np.nan)
        log["lambda"].append(lam)
        # the support polygon of the domain the QP ran in (single support: the stance sole)
        log["zmp_margin"].append(float(zmp_fn(rec.q, jnp.asarray(lam),
                                              domain["in_contact"] if walking else in_contact))
                                 if x is not None else np.nan)
        mask = ({k: np.asarray(m_) for k, m_ in scenario.weight_mask(domain).items()}
                if walking and scenario.weight_mask is not None else {})
        for nm in names:
            ya, yd = aux["outputs"][nm]
            yd = np.asarray(yd, float)
            if nm in mask:  # components not tracked in this domain have no reference
                yd = np.where(mask[nm] > 0, yd, np.nan)
            log[f"y_{nm}"].append(np.asarray(ya)), log[f"yd_{nm}"].append(yd)
        for hn in hnames:
            log[f"h_{hn}"].append(float(aux["barrier_h"][hn]))
        push_on = (cfg.push_force is not None and cfg.push_at <= tau < cfg.push_at + cfg.push_for)
        d.xfrc_applied[base_id, :3] = cfg.push_force if push_on else 0.0
        for _ in range(n_sub):
            mujoco.mj_step(ms, d)
        meas, legs = sense((k + 1) * cfg.control_dt)
        soles = {s: d.site_xpos[i].copy() for s, i in zip(("left", "right"), sole_ids)}
        log["leg_contact"].append(legs)
        log["clearance"].append(float(soles["left"][1] - soles["right"][1]))
        if walking:
            log["alip"].append(np.asarray(diag_fn(rec.q, rec.v, domain)))
        else:
            log["alip"].append(np.zeros(0))
            log["stance"].append(0.0)
            log["missed_touchdowns"].append(0)
        if walking and domain["stance"] != 0:
            # walking: how far the stance sole has moved since its step began
            st_id = sole_ids[0] if domain["stance"] > 0 else sole_ids[1]
            slip = np.linalg.norm(d.site_xpos[st_id][:2] - domain["stance0"][:2])
        else:
            slip = np.linalg.norm(np.array([d.site_xpos[i][:2] for i in sole_ids]) - sole0,
                                  axis=1).max()
        log["slip"].append(slip), log["loop_residual"].append(sim_loop_residual(ms, d, loop_pairs))
        log["base_z"].append(float(d.xpos[base_id][2]))
        log["qpos"].append(d.qpos.copy())
        if progress is not None:
            progress(k + 1, n_steps, "standing" if tau < 0 else "motion")
        if fallen(d.qpos, d.xpos[base_id][2]):
            fell = True
            break
    if walking and len(log["stance"]) < len(log["t"]):  # the last step: its own domain
        log["stance"].append(ctl.gait.stance)
        log["missed_touchdowns"].append(ctl.gait.missed_touchdowns)
    arrays = {k: np.asarray(v) for k, v in log.items()}
    arrays["compile_s"] = np.asarray(compile_s)
    if recorded:
        fields = ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")
        for f in fields:
            arrays[f"qp_{f}"] = np.stack([np.asarray(getattr(r[1], f)) for r in recorded])
        arrays["qp_step"] = np.array([r[0] for r in recorded])
        arrays["qp_status"] = np.array([r[2] for r in recorded])
        arrays["qp_fallback"] = np.array([r[3] for r in recorded])
    return arrays, dict(fell=fell, settle=settle, duration=duration, n_sub=n_sub,
                        steps_taken=ctl.gait.steps if walking else 0, walking=walking,
                        sim_dt=float(ms.opt.timestep), torque_limit=np.asarray(model.torque_limit),
                        outputs=names, barriers=[b.name for b in scenario.barriers],
                        monitors=[b.name for b in scenario.monitors],
                        bad_measurements=ctl.bad_measurements)
