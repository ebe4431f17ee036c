"""The deployment loop: MuJoCo (C) physics of ``models/scene.xml`` around the deployable
controller (``safewbc_jax.deploy.controller.Controller``), as it would run on the robot.

The loop is ``sim.loop.simulate`` with one lane. Each control step: sense (``SimRobot``:
MjData -> ``deploy.Measurement``, the controller's (q, v) through the StateMap, the soles'
normal forces from the contacts) -> ``Controller.step`` (the control step,
``control_step``; ``OneRobot``) -> the motor torques into d.ctrl -> push
(``push.force_at``) -> the physics advances control_dt -> sense again: the plant metrics
(``metrics.plant_accumulate``), the fall test (``control_step.fallen``) -> log (``run``).
A settle period of standing precedes the motion (tau < 0); the paper's tau counts from
its start.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import numpy as np

from safewbc_jax.control import metrics
from safewbc_jax.model import robot, statemap
from safewbc_jax.control.step import Measurement
from safewbc_jax.deploy.controller import Controller
from safewbc_jax.model.modelinfo import control_substeps, foot_contact_ids, loop_site_pairs
from safewbc_jax.control.params import ControllerParams
from safewbc_jax.control.push import Push
from safewbc_jax.sim.runlog import RunLog
from safewbc_jax.sim.runspec import RunSpec
from safewbc_jax.sim.loop import LaneControl, LaneStep, simulate
from safewbc_jax.solvers.result import fallback_name
from safewbc_jax.model import digit


@dataclasses.dataclass(frozen=True)
class RunConfig(RunSpec):
    """The run (``runspec.RunSpec``: scenario, barrier, durations, control period, speed,
    the user's safe sets) and this loop's options."""

    record_qps_every: int = 0          # keep every k-th QP (full matrices) in the log; 0: none
    push: Push | None = None           # a push on the base (push.Push.single(force, at, for))
    count_kernels: bool = False        # the jitted step's kernels in the info ("kernels")
    engine: str = "auto"               # the deployed step: "c", "xla" or "auto"
    native: bool = False               # the C engine built for this CPU (-march=native)


class ContactSensing:
    """What the loop reads from MuJoCo's contact list each step: the normal force (N) of
    each sole on the floor (``mj_contactForce``, summed over that sole's contacts in
    MuJoCo's order) and whether a collision geom of one leg touches one of the other leg.
    ``ids``: ``modelinfo.foot_contact_ids``. Each contact's pair of geoms is looked up in
    one table built once (ngeom x ngeom: 1 left sole on the floor, 2 right sole on the
    floor, 4 a leg on the other leg, 0 anything else), one gather for all contacts; then
    a Python loop over the few contacts. Per-contact Python objects or ``np.isin`` cost
    ~50-90 us a step, per-column numpy tests ~18 us, this ~8 us: a measurable part of a
    loop step."""

    LEFT, RIGHT, LEGS = 1, 2, 4

    def __init__(self, ms, ids):
        code = np.zeros(ms.ngeom, np.int64)
        code[ids["floor"]] = 1
        code[ids["sole_geoms"][0]], code[ids["sole_geoms"][1]] = 2, 4
        side = np.zeros(ms.ngeom, np.int64)
        side[ids["legs"][0]], side[ids["legs"][1]] = 1, 2
        pair = code[:, None] + code[None, :]          # 3: left sole-floor, 5: right
        table = np.where(pair == 3, self.LEFT, np.where(pair == 5, self.RIGHT, 0))
        table[(side[:, None] | side[None, :]) == 3] = self.LEGS
        self._table = table
        self._f6 = np.zeros(6)

    def __call__(self, ms, d) -> tuple[float, float, bool]:
        """(left sole force, right sole force, legs touching) of MjData ``d``."""
        import mujoco

        if d.ncon == 0:
            return 0.0, 0.0, False
        g = d.contact.geom                      # (ncon, 2)
        force, legs, f6 = [0.0, 0.0, 0.0], False, self._f6
        for i, c in enumerate(self._table[g[:, 0], g[:, 1]].tolist()):
            if c == self.LEGS:
                legs = True
            elif c:
                mujoco.mj_contactForce(ms, d, i, f6)
                force[c] += abs(f6[0])
        return force[1], force[2], legs


def load_at_stand():
    """(simulation model, controller MjModel, RobotModel, StateMap, MjData at ``stand``)."""
    ms, mc, sm, d = statemap.load_stand()
    return ms, mc, robot.from_mujoco(mc), sm, d


class SimRobot:
    """The simulated robot of the loop (``models/scene.xml`` in C MuJoCo), loaded once and
    reset for each rollout: the state map to the controller, the sensing (sole forces,
    leg-on-leg contact), the motor commands and the push, one control period of physics
    (``advance``); ``sibling`` gives another on the same MjModel."""

    def __init__(self, motor_names, control_dt: float):
        import mujoco

        self.ms, mc, self.model, self.sm, self.d = load_at_stand()
        self.n_sub = control_substeps(self.ms, control_dt)
        if self.n_sub is None:
            raise ValueError(f"control_dt {control_dt} must be a positive multiple of the "
                             f"simulation step {self.ms.opt.timestep}")
        self.control_dt = float(control_dt)
        ms = self.ms
        ids = foot_contact_ids(ms)
        self.contacts = ContactSensing(ms, ids)
        self.motor_ids = np.array([ms.actuator(n).id for n in motor_names])  # motor -> ctrl
        self.sole_ids = ids["sole_sites"]
        self.sole0 = self.d.site_xpos[self.sole_ids, :2].copy()
        self.base_id = ms.body(digit.BASE).id
        self.loop_pairs = loop_site_pairs(ms)
        self._key = ms.key("stand").id
        self._mj = mujoco

    def reset(self, perturb_v=None):
        """Back to the stand keyframe, plus ``perturb_v`` (simulator nv) on the velocity, as
        the batched rollouts start (``batch.rollout``)."""
        mj, ms, d = self._mj, self.ms, self.d
        mj.mj_resetDataKeyframe(ms, d, self._key)
        mj.mj_forward(ms, d)
        if perturb_v is not None:
            d.qvel[:] += np.asarray(perturb_v, float)

    def sense(self, t):
        """(Measurement at time t, whether a leg touches the other leg)."""
        left, right, legs = self.contacts(self.ms, self.d)
        q, v = self.sm.to_controller(self.d.qpos, self.d.qvel)
        return Measurement(q, v, t, np.array([left, right])), legs

    def sibling(self) -> "SimRobot":
        """Another simulated robot on the same (read-only) MjModel with its own MjData at
        the stand keyframe."""
        import copy

        other = copy.copy(self)
        other.d = self._mj.MjData(self.ms)
        other.reset()
        return other

    def advance(self, motor, push_force, k):
        """Apply the motor torques and the push, advance one control period, sense step k's
        outcome: returns (next Measurement, legs touching)."""
        d = self.d
        d.ctrl[self.motor_ids] = motor
        d.xfrc_applied[self.base_id, :3] = push_force
        for _ in range(self.n_sub):
            self._mj.mj_step(self.ms, d)
        return self.sense((k + 1) * self.control_dt)


class OneRobot(LaneControl):
    """The control step of one robot (a ``LaneControl`` of one lane): ``Controller.step``,
    then ``observer(meas)`` and the step's record (``Controller.record``: its conclude,
    after the command is out). ``last``: (measurement, Command, HostRecord) of the last
    step."""

    def __init__(self, ctl: Controller, observer=None):
        super().__init__()
        self.ctl, self.observer = ctl, observer
        self.last: tuple | None = None

    def step(self, meas: list, live) -> LaneStep:
        ctl = self.ctl
        cmd = ctl.step(meas[0])
        if self.observer is not None:
            self.observer(meas[0])
        hr = ctl.record
        if hr is None:      # from a simulator this cannot happen
            raise RuntimeError(f"measurement refused: {cmd.measurement}")
        self.last = (meas[0], cmd, hr)
        self.conclude(hr.step)
        return LaneStep({0: cmd.motor}, np.array([hr.step.tau]), {})


def rollout(sim: SimRobot, ctl: Controller, n_steps: int, push: Push | None = None,
            on_step=None, observer=None):
    """One rollout of the deployment loop (``loop.simulate`` with one lane) from the
    robot's present state (``sim.reset`` and ``ctl.start``/``ctl.restart`` before).
    ``observer(meas)`` runs right after each ``Controller.step``;
    ``on_step(k, meas, cmd, record, legs, loop_residual)`` after each step's physics.
    Both are outside ``Controller.step``'s timing.
    Returns (fell, the step it fell at or -1, plant metrics)."""
    one = OneRobot(ctl, observer)
    log = None
    if on_step is not None:
        def log(k, rec, legs, loop_res):
            meas, cmd, hr = one.last
            on_step(k, meas, cmd, hr, bool(legs[0]), float(loop_res[0]))
    out = simulate([sim], one, n_steps, [push], [True], log, catch=False)
    fell_step = int(out.fell_step[0])
    return fell_step >= 0, fell_step, jax.tree_util.tree_map(lambda a: a[0], out.plant)


def run(cfg: RunConfig, params: ControllerParams | None = None, progress=None,
        observer=None):
    """Run ``cfg`` (its scenario; ``params`` None: the scenario's defaults) in MuJoCo;
    returns (log dict of arrays, summary dict with the finalized metric columns under
    "metrics", ``metrics.finalize``, and with
    ``cfg.count_kernels`` the kernels XLA runs for the jitted step under "kernels",
    ``Controller.kernels``).

    ``progress(k, n, phase)``, when given, is called with k = 0 and phase "compiling" just
    before the controller starts (Theorem 1, compile, warm-up: ``Controller.start``), then
    after every control step with k the steps done of n and the phase of that step:
    "standing" (the settle, tau < 0) or "motion". It runs outside the timed part of the
    step (t_qp, t_solve), and must be cheap (``progress.Progress.update_to`` is: a few
    microseconds).

    ``observer(meas)``, when given, is called once per control step with the measurement
    the step's command was computed from, after the command is out and outside every
    timed part.

    The log's ``stance`` and the gait's record fields at step k are those of the domain
    step k's QP ran in (the gait advanced from step k's measurement); with a gait that
    has ``diagnostics`` (the ALIP gait), its values per step are ``gait_diagnostics``.
    """
    n_steps, settle, duration = cfg.schedule()
    ctl = cfg.controller(params, engine=cfg.engine, native=cfg.native)
    sim = SimRobot(ctl.motors.names, cfg.control_dt)
    ms, model, d = sim.ms, sim.model, sim.d
    scenario, walking, gait = ctl.scenario, ctl.walking, ctl.scenario.gait
    diagnostics = getattr(gait, "diagnostics", None)
    diag_fn = None if diagnostics is None else jax.jit(partial(diagnostics, model))
    names = [o.name for o in scenario.outputs]
    hnames = [b.name for b in scenario.barriers + scenario.monitors]
    log = RunLog(n_steps)
    recorded = []
    if progress is not None:
        progress(0, n_steps, "compiling")
    compile_s = ctl.start(*sim.sm.to_controller(d.qpos, d.qvel))

    def on_step(k, meas, cmd, hr, legs, loop_res):
        rec = hr.step
        fb = fallback_name(rec.fallback) if rec.ok else "held"
        if cfg.record_qps_every and k % cfg.record_qps_every == 0:
            recorded.append((k, ctl.last_qp(), int(rec.status), fb))
        log.put(k, t=k * cfg.control_dt, tau=float(rec.tau), u=cmd.u, status=int(rec.status),
                fallback=fb, t_qp=hr.t_qp, t_solve=hr.t_solve, latency=cmd.latency_us,
                zmp_margin=float(rec.zmp_margin), eq_residual=float(rec.eq_residual),
                loop_residual=loop_res, base_z=float(d.xpos[sim.base_id][2]),
                qpos=d.qpos, stance=float(rec.stance), leg_contact=legs, **rec.gait,
                **{"lambda": rec.lam})
        log.put(k, **{f"y_{nm}": rec.y[nm] for nm in names},
                **{f"yd_{nm}": rec.yd[nm] for nm in names},
                **{f"h_{hn}": float(rec.h[hn]) for hn in hnames})
        if diag_fn is not None:
            log.put(k, gait_diagnostics=np.asarray(diag_fn(hr.q, hr.v, hr.domain)))
        if progress is not None:
            progress(k + 1, n_steps, "standing" if rec.tau < 0 else "motion")

    fell, _, plant = rollout(sim, ctl, n_steps, cfg.push, on_step, observer)
    arrays = log.arrays()
    arrays["compile_s"] = np.asarray(compile_s)
    if recorded:
        fields = ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")
        for f in fields:
            arrays[f"qp_{f}"] = np.stack([np.asarray(getattr(r[1], f)) for r in recorded])
        arrays["qp_step"] = np.array([r[0] for r in recorded])
        arrays["qp_status"] = np.array([r[2] for r in recorded])
        arrays["qp_fallback"] = np.array([r[3] for r in recorded])
    st = ctl.state
    flat = metrics.finalize(scenario, ctl.tally.acc, plant, fell, st.gait)
    tau = arrays["tau"]
    return arrays, dict(fell=fell, settle=settle, duration=duration, n_sub=sim.n_sub,
                        duration_s=float(max(tau[-1], 0.0) + cfg.control_dt) if tau.size else 0.0,
                        walking=walking, engine=ctl.engine,
                        sim_dt=float(ms.opt.timestep), torque_limit=np.asarray(model.torque_limit),
                        outputs=names, barriers=[b.name for b in scenario.barriers],
                        monitors=[b.name for b in scenario.monitors],
                        bad_measurements=ctl.bad_measurements, metrics=flat,
                        t_qp=arrays["t_qp"], t_solve=arrays["t_solve"], compile_s=compile_s,
                        **({"kernels": ctl.kernels()} if cfg.count_kernels else {}))
