"""The deployment loop: MuJoCo (C) physics of ``models/scene.xml`` with the controller
solved by PIQP at a fixed rate, as it would run on the robot.

Each control step: the simulator's state is mapped to the controller's (q, v); the jitted
robot terms and QP assembly run; PIQP solves with the fallback policy; the joint torques
u become motor commands ctrl = u / gear; the physics advances control_dt. A settle period
of standing precedes the motion (tau < 0); the paper's tau counts from its start.
"""

from __future__ import annotations

import dataclasses
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax import barriers, contacts, controller, paths, robot, statemap
from safewbc_jax.modelinfo import (control_substeps, foot_contact_ids, loop_site_pairs,
                                   sim_loop_residual)
from safewbc_jax.packing import Packer
from safewbc_jax.params import ControllerParams
from safewbc_jax.scenarios import Scenario, start_state
from safewbc_jax.solvers import reduce
from safewbc_jax.solvers.piqp_path import PiqpSolver

FALL_HEIGHT = 0.55  # m: base below this counts as a fall


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


class CompiledController:
    """One jitted function from the state to the QP (robot terms, assembly and the exact
    elimination of its equality rows, ``solvers.reduce``), and PIQP on the reduced
    20-variable QP.

    ``reduced=False`` hands PIQP the full 78-variable QP instead (the reference path).
    ``reduce_on``: "device" (default) runs the elimination inside the jitted function
    (XLA's LAPACK calls on 36 x 36 and 22 x 22 matrices), "host" in numpy after it (the
    same factorisations, plus numpy's per-call overhead on some twenty small operations:
    measured slower in the loop). Either way the jitted function returns one flat vector
    that the host splits into numpy views (``packing.Packer``).
    """

    def __init__(self, model: robot.RobotModel, scenario: Scenario, solver=None, reduced=True,
                 reduce_on="device"):
        if reduce_on not in ("host", "device"):
            raise ValueError(f"reduce_on must be 'host' or 'device', got {reduce_on!r}")
        self.model = model
        self.scenario = scenario
        self.solver = solver or PiqpSolver()
        self.reduced = reduced
        self.reduce_on = reduce_on
        self.nv, self.nu = model.nv, model.nu
        self.last_u = None
        self._fn = {}

    def _compiled(self, barrier_on, params, q, v, tau, start, in_contact, domain):
        key = bool(barrier_on)
        if key not in self._fn:
            model, scenario = self.model, self.scenario

            def full(params, q, v, tau, start, in_contact, domain):
                terms = controller.robot_terms(model, scenario, q, v, domain)
                return controller.build_qp(model, scenario, params, terms, q, v, tau, start,
                                           in_contact, barrier_on=key, domain=domain)

            full_jit = jax.jit(full)
            qp0, _ = full_jit(params, q, v, tau, start, in_contact, domain)
            bounded = reduce.bounded_variables(qp0, model.nv, model.nu)
            self._bounded = bounded
            packer = Packer()
            if self.reduce_on == "host":
                packed = jax.jit(lambda *a: packer.pack(full(*a)))
            else:
                def step(params, q, v, tau, start, in_contact, domain):
                    qpm, aux = full(params, q, v, tau, start, in_contact, domain)
                    red, rmap = reduce.eliminate_equalities(qpm, model.nv, model.nu, bounded)
                    return qpm, aux, red, rmap

                packed = jax.jit(lambda *a: packer.pack(step(*a)))
            # one flat vector out, split into numpy views on the host (one transfer)
            self._fn[key] = lambda *a: packer.unpack(packed(*a))
        return self._fn[key]

    def step(self, params, q, v, tau, start, in_contact, barrier_on=True, domain=None):
        """One control step: (u, X or None, info, aux, (t_qp, t_solve) in us)."""
        fn = self._compiled(barrier_on, params, q, v, tau, start, in_contact, domain)
        t0 = time.perf_counter()
        if self.reduce_on == "host":
            qpm, aux = fn(params, q, v, tau, start, in_contact, domain)
            if self.reduced:
                red, rmap = reduce.eliminate_equalities_np(qpm, self.nv, self.nu, self._bounded)
        else:
            qpm, aux, red, rmap = fn(params, q, v, tau, start, in_contact, domain)
        if self.reduced:
            x0, nmat = rmap.x0, rmap.N
        t1 = time.perf_counter()
        if self.reduced:
            z, info = self.solver.solve(red)
            x = None if z is None else x0 + nmat @ z
        else:
            x, info = self.solver.solve(qpm)
        t2 = time.perf_counter()
        if x is not None:
            u = x[self.nv:self.nv + self.nu]
            self.last_u = u
            if self.reduced:
                info["eq_residual"] = float(np.max(np.abs(qpm.A @ x - qpm.b)))
        else:
            u = self.last_u if self.last_u is not None else np.zeros(self.nu)
        self.last_qp = qpm
        return u, x, info, aux, ((t1 - t0) * 1e6, (t2 - t1) * 1e6)


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


def check_barrier_poles(model, scenario, params, q, v):
    """Theorem 1 at the start state, before anything compiles: raises barriers.PoleError
    naming the barrier, the pole and its bound. A barrier active only in some domains
    (the swing-foot barrier) is checked at the start of the first step, from this state
    (``walking.first_step_domain``)."""
    for b in scenario.barriers:
        domain = None
        if b.active is not None:   # a walking barrier: where its domain first starts
            from safewbc_jax.walking import first_step_domain

            domain = first_step_domain(model, q)
        eta0 = barriers.barrier_lie_derivatives(b.h_fn(model, params.threshold[b.name], domain),
                                                q, v, b.relative_degree)[0]
        barriers.check_poles(b.name, np.asarray(eta0), np.asarray(params.poles[b.name]))


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
    before the first control step (which compiles the controller), then after every control
    step with k the steps done of n and the phase of that step: "standing" (the settle,
    tau < 0) or "motion". It runs outside the timed part of the step (t_qp, t_solve), and
    must be cheap (``progress.Progress.update_to`` is: a few microseconds).
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
    if settle < scenario.blend:
        raise ValueError(f"settle ({settle} s) must cover the reference blend ({scenario.blend} s)")
    scenario = dataclasses.replace(scenario, settle=settle)

    q0, v0 = (jnp.asarray(a) for a in sm.to_controller(d.qpos, d.qvel))
    if cfg.barrier_on:
        check_barrier_poles(model, scenario, params, q0, v0)
    start = start_state(model, q0)
    start["y0"] = controller.output_start_values(model, scenario, q0)
    walking = scenario.desired_fn is not None
    gait = rigid_fn = None
    if walking:
        from safewbc_jax.walking import Gait, walking_start
        from safewbc_jax.walking import diagnostics as walking_diag
        from safewbc_jax.walking import rigid_spring_velocity as walking_rigid

        start.update(walking_start(model, q0, start, scenario.blend), settle=jnp.asarray(settle))
        gait = Gait(v_des=cfg.speed)
        diag_fn = jax.jit(partial(walking_diag, model))
        rigid_fn = jax.jit(partial(walking_rigid, model)) if cfg.rigid_swing_leg else None
    ids = foot_contact_ids(ms)
    sole_geoms = dict(zip(("left", "right"), ids["sole_geoms"].tolist()))
    floor_geom = ids["floor"]
    leg_geoms = {s: set(g.tolist()) for s, g in zip(("left", "right"), ids["legs"])}
    ctl = CompiledController(model, scenario)
    in_contact = jnp.asarray(scenario.in_contact)
    ctrl_lo, ctrl_hi = ms.actuator_ctrlrange[:, 0], ms.actuator_ctrlrange[:, 1]
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
    compile_t0 = time.perf_counter()
    compile_s = 0.0
    for k in range(n_steps):
        t = k * cfg.control_dt
        tau = t - settle
        q, v = (jnp.asarray(a) for a in sm.to_controller(d.qpos, d.qvel))
        domain = gait.domain() if walking else None
        t_rigid = 0.0
        if walking and rigid_fn is not None:
            t0r = time.perf_counter()
            v = rigid_fn(q, v, domain["stance"]).block_until_ready()
            t_rigid = (time.perf_counter() - t0r) * 1e6
        u, x, info, aux, (tq, ts) = ctl.step(params, q, v, jnp.asarray(tau), start,
                                                 in_contact, barrier_on=cfg.barrier_on,
                                                 domain=domain)
        tq += t_rigid  # the swing leg's rigid-spring velocity is part of the control step
        if cfg.record_qps_every and k % cfg.record_qps_every == 0:
            recorded.append((k, ctl.last_qp, int(info["status"]), info["fallback"]))
        if k == 0:
            compile_s = time.perf_counter() - compile_t0
        d.ctrl[:] = np.clip(sm.to_ctrl(u), ctrl_lo, ctrl_hi)
        lam = x[model.nv + model.nu + nc_chain:] if x is not None else np.full(12, np.nan)
        log["t"].append(t), log["tau"].append(tau), log["u"].append(np.asarray(u))
        log["status"].append(int(info["status"])), log["fallback"].append(info["fallback"])
        log["t_qp"].append(tq), log["t_solve"].append(ts)
        log["eq_residual"].append(info["eq_residual"] if x is not None else np.nan)
        log["lambda"].append(lam)
        # the support polygon of the domain the QP ran in (single support: the stance sole)
        log["zmp_margin"].append(float(zmp_fn(q, jnp.asarray(lam),
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
        contacts_now = _floor_and_leg_contacts(ms, d, sole_geoms, floor_geom, leg_geoms)
        soles = {s: d.site_xpos[i].copy() for s, i in zip(("left", "right"), sole_ids)}
        log["leg_contact"].append(contacts_now["legs"])
        log["clearance"].append(float(soles["left"][1] - soles["right"][1]))
        if walking:
            log["alip"].append(np.asarray(diag_fn(q, v, domain)))
            swing = "right" if gait.stance > 0 else "left"
            gait.update(tau, cfg.control_dt, soles, contacts_now[swing],
                        -float(model.gravity[2]) * model.total_mass)
            log["stance"].append(gait.stance)
            log["missed_touchdowns"].append(gait.missed_touchdowns)
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
        if not np.all(np.isfinite(d.qpos)) or d.xpos[base_id][2] < FALL_HEIGHT:
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
    return arrays, dict(fell=fell, settle=settle, duration=duration, n_sub=n_sub,
                        steps_taken=gait.steps if walking else 0, walking=walking,
                        sim_dt=float(ms.opt.timestep), torque_limit=np.asarray(model.torque_limit),
                        outputs=names, barriers=[b.name for b in scenario.barriers],
                        monitors=[b.name for b in scenario.monitors])
