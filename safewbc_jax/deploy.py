"""The deployable controller: measurements in, motor commands out, no simulator.

    ctl = Controller("squat")            # or "walk", "push", "bow", "arms"
    ctl.start(q, v)                      # Theorem 1, start data, compile and warm-up
    cmd = ctl.step(Measurement(q, v, t, sole_force))   # every control_dt
    send(cmd.motor)                      # motor torques in the robot's motor order

``Controller.step`` runs the gait (walking: touchdown from the sole forces, the soles'
positions from the controller's own forward kinematics of q), the rigid swing-leg rates
(``walking.rigid_spring_velocity``), the jitted QP (``CompiledController``) and PIQP with
its fallback policy (``solvers.piqp_path``); a failed QP holds the last good torque. A
measurement that fails ``check_measurement`` is refused: the command holds the last good
torque (zeros before the first good step), names the reason, and the gait does not
advance. ``MotorMap`` maps joint torques to motor torques from the controller model and
the published figures (``models/digit_v3_parameters.json``), not from a simulator.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax import barriers, controller, paths, robot, scenarios
from safewbc_jax.packing import Packer
from safewbc_jax.solvers import reduce
from safewbc_jax.solvers.piqp_path import PiqpSolver
from safewbc_jax.solvers.status import SolveStatus

FALL_HEIGHT = 0.55  # m: base below this counts as a fall
# Measurement bounds. |quat| is 1 to ~1e-15 from any estimator that normalises; 1e-3 is far
# above that and far below an error that changes the controller's rotation noticeably.
QUAT_TOL = 1e-3
# Angular rates (joints and base, rad/s) and base speed (m/s): in the MuJoCo runs the
# fastest joint peaks at ~7 rad/s (knees, walking at 0.2 m/s; undamped springs and
# touchdowns included) and the base at 0.4 m/s; a humanoid's joints and a fall stay well
# within 100 rad/s and 20 m/s, so an estimate beyond them is a fault, not a motion.
MAX_RATE = 100.0
MAX_SPEED = 20.0


@functools.partial(jax.tree_util.register_dataclass, data_fields=["q", "v", "sole_force", "t"],
                   meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Measurement:
    """What the robot's estimator hands over each control step (README, Conventions):
    q (37,), v (36,), the soles' normal forces on the floor (2,) in N (left, right; None is
    allowed in double-support scenarios), and the time stamp t in s (any clock that
    advances; the controller's clock starts at the first good measurement)."""

    q: np.ndarray
    v: np.ndarray
    t: float
    sole_force: np.ndarray | None = None


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["u", "motor", "latency_us"],
                   meta_fields=["solve_status", "fallback", "measurement"])
@dataclasses.dataclass(frozen=True)
class Command:
    """One step's output: joint torques u (20,), controller actuator order; motor torques
    (20,), the robot's motor order (``MotorMap``); the QP's ``SolveStatus`` (None when no QP
    ran); fallback "none" | "relaxed" | "failed" (QP failed: last good torque held) |
    "held" (measurement refused: last good torque held); measurement "ok" or the reason it
    was refused; the wall time of ``Controller.step`` in us."""

    u: np.ndarray
    motor: np.ndarray
    solve_status: SolveStatus | None
    fallback: str
    measurement: str
    latency_us: float


@dataclasses.dataclass(frozen=True)
class MotorMap:
    """The robot's motors in its motor order (``actuators`` of the published figures):
    name, index of each motor's joint torque in u, gear ratio, joint-side torque limit."""

    names: tuple
    u_index: np.ndarray
    gear: np.ndarray
    joint_limit: np.ndarray      # N m, joint side
    motor_limit: np.ndarray      # N m, motor side (published motor_torque_limit)

    @classmethod
    def build(cls, ctrl_model=None, figures: dict | None = None) -> "MotorMap":
        """From the controller MjModel (``paths.controller_xml()``) and the published
        figures the models were written from (``paths.figures_json()``, installed with the
        package); raises ValueError where the two disagree."""
        import json

        import mujoco

        mc = (mujoco.MjModel.from_xml_path(str(paths.controller_xml())) if ctrl_model is None
              else ctrl_model)
        if figures is None:
            figures = json.loads(paths.figures_json().read_text())
        acts = figures["actuators"]
        idx = []
        for a in acts:
            i = mujoco.mj_name2id(mc, mujoco.mjtObj.mjOBJ_ACTUATOR, a["name"])
            if i < 0 or mc.joint(int(mc.actuator_trnid[i, 0])).name != a["joint"]:
                raise ValueError(f"motor {a['name']!r} (joint {a['joint']!r}) is not an "
                                 "actuator of the controller model on that joint")
            if not np.isclose(mc.actuator_gear[i, 0], a["gear"], rtol=1e-9):
                raise ValueError(f"motor {a['name']!r}: gear {a['gear']} published, "
                                 f"{mc.actuator_gear[i, 0]} in the controller model")
            idx.append(i)
        if sorted(idx) != list(range(mc.nu)):
            raise ValueError("the published motors do not cover the controller's actuators")
        f = lambda k: np.array([float(a[k]) for a in acts])  # noqa: E731
        gear, lim_j, lim_m = f("gear"), f("joint_torque_limit"), f("motor_torque_limit")
        if not np.allclose(lim_m * gear, lim_j, rtol=1e-9):
            raise ValueError("published motor torque limit x gear != joint torque limit")
        return cls(tuple(a["name"] for a in acts), np.array(idx), gear, lim_j, lim_m)

    def to_motor(self, u) -> np.ndarray:
        """Joint torques u (controller actuator order) -> motor torques u / gear, in motor
        order, clipped to the motor limits."""
        m = np.asarray(u, float)[..., self.u_index] / self.gear
        return np.clip(m, -self.motor_limit, self.motor_limit)


def check_state(q, v) -> str:
    """"ok", or why (q, v) is no state of the robot (shapes, NaN/inf, a quaternion off unit
    length by more than QUAT_TOL, rates above MAX_RATE or a base speed above MAX_SPEED)."""
    if np.shape(q) == (37,) and np.shape(v) == (36,):   # fast path (a few us): all good
        n2, s2 = float(q[3:7] @ q[3:7]), float(v[:3] @ v[:3])
        if (math.isfinite(float(np.sum(q))) and abs(math.sqrt(n2) - 1.0) <= QUAT_TOL
                and s2 <= MAX_SPEED ** 2 and float(np.max(np.abs(v[3:]))) <= MAX_RATE):
            return "ok"     # a finite sum has no NaN or inf; NaN fails every comparison
    for name, x, n in (("q", q, 37), ("v", v, 36)):
        if np.shape(x) != (n,):
            return f"{name} has shape {np.shape(x)}, expected ({n},)"
        if not np.all(np.isfinite(x)):
            return f"{name} not finite at {np.flatnonzero(~np.isfinite(x)).tolist()}"
    nq = float(np.linalg.norm(q[3:7]))
    if abs(nq - 1.0) > QUAT_TOL:
        return f"base quaternion |q| = {nq:.6g}, not unit (tolerance {QUAT_TOL:g})"
    if np.linalg.norm(v[:3]) > MAX_SPEED:
        return f"base speed {np.linalg.norm(v[:3]):.4g} m/s above {MAX_SPEED:g} m/s"
    k = int(np.argmax(np.abs(v[3:])))
    if abs(v[3 + k]) > MAX_RATE:
        return f"rate {v[3 + k]:.4g} rad/s at dof {3 + k}, above {MAX_RATE:g} rad/s"
    return "ok"


def check_measurement(m: Measurement, walking: bool) -> str:
    """"ok", or why the measurement is refused (``check_state``; t not finite; walking:
    sole forces missing, of the wrong shape or not finite; anything not numeric)."""
    try:
        if not np.isfinite(float(m.t)):
            return f"t = {m.t} not finite"
        if m.sole_force is not None or walking:
            f = m.sole_force
            if f is None or np.shape(f) != (2,):
                return (f"sole_force {None if f is None else np.shape(f)}: expected (2,) "
                        "(left, right)")
            if not np.all(np.isfinite(np.asarray(f, float))):
                return f"sole_force {np.asarray(f).tolist()} not finite"
        return check_state(np.asarray(m.q, float), np.asarray(m.v, float))
    except (TypeError, ValueError) as e:
        return f"malformed measurement: {e}"


def fallen(qpos, base_z) -> bool:
    """The fall test: a non-finite state, or the base below FALL_HEIGHT."""
    return bool(not np.all(np.isfinite(qpos)) or base_z < FALL_HEIGHT)


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


class CompiledController:
    """One jitted function from the state to the QP (robot terms, assembly and the exact
    elimination of its equality rows, ``solvers.reduce``), and PIQP on the reduced
    20-variable QP.

    ``reduced=False`` hands PIQP the full 78-variable QP instead (the reference path).
    ``reduce_on``: "device" (default) runs the elimination inside the jitted function
    (XLA's LAPACK calls on 36 x 36 and 22 x 22 matrices), "host" in numpy after it (the
    same factorisations, plus numpy's per-call overhead on some twenty small operations:
    measured slower in the loop). Either way the jitted function returns one flat vector
    that the host splits into numpy views (``packing.Packer``). A solution with a
    non-finite entry counts as failed.
    """

    def __init__(self, model: robot.RobotModel, scenario, solver=None, reduced=True,
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

            qp0, _ = jax.jit(full)(params, q, v, tau, start, in_contact, domain)
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
        t1 = time.perf_counter()
        if self.reduced:
            z, info = self.solver.solve(red)
            x = None if z is None else rmap.x0 + rmap.N @ z
        else:
            x, info = self.solver.solve(qpm)
        t2 = time.perf_counter()
        if x is not None and not np.all(np.isfinite(x)):
            x, info["fallback"], info["status"] = None, "failed", SolveStatus.NUMERICAL
        if x is not None:
            u = x[self.nv:self.nv + self.nu]
            self.last_u = u
            if self.reduced:
                info["eq_residual"] = float(np.max(np.abs(qpm.A @ x - qpm.b)))
        else:
            u = self.last_u if self.last_u is not None else np.zeros(self.nu)
        self.last_qp = qpm
        return u, x, info, aux, ((t1 - t0) * 1e6, (t2 - t1) * 1e6)


@dataclasses.dataclass(frozen=True)
class StepRecord:
    """A good step, for logs: the state the QP saw (v with the rigid swing-leg rates), tau,
    the domain, X or None, solver info, aux (outputs, barrier values), times in us."""

    q: np.ndarray
    v: object
    tau: float
    domain: dict | None
    x: np.ndarray | None
    info: dict
    aux: dict
    t_qp: float
    t_solve: float


def _walking_sense(model, q, v):
    """Both soles' positions (FK of q), and v in left stance (the right leg's springs rigid)
    and in right stance (``walking.rigid_spring_velocity``): one jitted call."""
    from safewbc_jax.walking import rigid_spring_velocity

    return (robot.frame_pose(model, q, "left-sole")[0], robot.frame_pose(model, q, "right-sole")[0],
            rigid_spring_velocity(model, q, v, 1.0), rigid_spring_velocity(model, q, v, -1.0))


class Controller:
    """The deployable controller of one scenario (module docstring). ``scenario``: a name
    (``scenarios.get_scenario``) or a Scenario; ``params``: ControllerParams (the
    scenario's defaults when None); ``settle``: s of standing before the motion (the
    scenario's default when None); ``speed``: walking's commanded mean speed (m/s);
    ``rigid_swing_leg``: walking, the swing leg's rates with rigid springs.

    Attributes: ``steps`` (calls of ``step``), ``qp_failed``, ``fallbacks`` (relaxed QPs),
    ``bad_measurements``; ``compile_s``; ``gait`` (walking.Gait, walking only); ``record``
    (StepRecord of the last step, None when it was refused); ``motors`` (MotorMap)."""

    def __init__(self, scenario, params=None, control_dt=1e-3, solver="piqp", barrier=True,
                 speed=0.2, settle=None, rigid_swing_leg=True):
        import mujoco

        sc = scenarios.get_scenario(scenario, barrier) if isinstance(scenario, str) else scenario
        settle = sc.settle if settle is None else float(settle)
        if settle < sc.blend:
            raise ValueError(f"settle ({settle} s) must cover the reference blend ({sc.blend} s)")
        if not control_dt > 0:
            raise ValueError(f"control_dt must be positive, got {control_dt}")
        self.walking = sc.desired_fn is not None
        if self.walking:
            from safewbc_jax.walking import check_speed

            speed = check_speed(speed)
        if isinstance(solver, str) and solver != "piqp":
            raise ValueError(f"solver {solver!r}: 'piqp' or a PiqpSolver-like object (the JAX "
                             "solver runs batched, batch.rollout)")
        self.solver = PiqpSolver() if solver == "piqp" else solver
        self.scenario = dataclasses.replace(sc, settle=settle)
        self.params = sc.default_params() if params is None else params
        self.control_dt, self.barrier, self.speed = float(control_dt), bool(barrier), speed
        self.rigid_swing_leg = rigid_swing_leg
        mc = mujoco.MjModel.from_xml_path(str(paths.controller_xml()))
        self.model = robot.from_mujoco(mc)
        self.motors = MotorMap.build(mc)
        self._weight = -float(self.model.gravity[2]) * float(self.model.total_mass)
        self._ctl = self.start_data = self.compile_s = None
        self.reset()

    def start(self, q, v) -> float:
        """Check the start state and Theorem 1 (barriers.PoleError), measure the
        references' start data, compile and warm up the step; returns (and keeps in
        ``compile_s``) the seconds it took. Leaves the controller as ``reset`` does."""
        q, v = np.asarray(q, float), np.asarray(v, float)
        reason = check_state(q, v)
        if reason != "ok":
            raise ValueError(f"start state refused: {reason}")
        t0 = time.perf_counter()
        model, sc = self.model, self.scenario
        qj, vj = jnp.asarray(q), jnp.asarray(v)
        if self.barrier:
            check_barrier_poles(model, sc, self.params, qj, vj)
        start = scenarios.start_state(model, qj)
        start["y0"] = controller.output_start_values(model, sc, qj)
        if self.walking:
            from safewbc_jax.walking import walking_start

            start.update(walking_start(model, qj, start, sc.blend), settle=jnp.asarray(sc.settle))
            self._sense = jax.jit(partial(_walking_sense, model))
        self.start_data = start
        self._ctl = CompiledController(model, sc, self.solver)
        self._in_contact = jnp.asarray(sc.in_contact)
        self.reset()
        force = np.zeros(2) if self.walking else None
        for k in range(2):  # compiles, then the jit's fast path; at tau < 0 the gait stays
            self.step(Measurement(q, v, k * self.control_dt, force))
        self.reset()
        self.compile_s = time.perf_counter() - t0
        return self.compile_s

    def reset(self):
        """Back to the state after ``start``: counters zero, gait standing, no torque held,
        the clock restarting at the next good measurement, PIQP set up afresh."""
        from safewbc_jax.walking import Gait

        self.gait = Gait(v_des=self.speed) if self.walking else None
        self.steps = self.qp_failed = self.fallbacks = self.bad_measurements = 0
        self.record: StepRecord | None = None
        self._last_u = np.zeros(self.model.nu)
        self._t0 = self._prev = None        # clock origin; (t, tau) of the last good step
        if self._ctl is not None:
            self._ctl.last_u = None
            getattr(self.solver, "reset", lambda: None)()

    def step(self, meas: Measurement) -> Command:
        """One control step (module docstring). Never raises on the measurement's content."""
        t_in = time.perf_counter()
        if self._ctl is None:
            raise RuntimeError("Controller.step before start(q, v)")
        self.steps += 1
        reason = check_measurement(meas, self.walking)
        if reason == "ok" and self._prev is not None and not meas.t > self._prev[0]:
            reason = f"t = {meas.t} does not advance (last step at {self._prev[0]})"
        if reason != "ok":
            self.bad_measurements += 1
            self.record = None
            return self._command(self._last_u, None, "held", reason, t_in)
        if self._t0 is None:
            self._t0 = meas.t
        tau = (meas.t - self._t0) - self.scenario.settle
        q, v = np.asarray(meas.q, float), np.asarray(meas.v, float)
        domain = None
        if self.walking:
            pl, pr, v_lstance, v_rstance = self._sense(q, v)
            g = self.gait
            if self._prev is not None:   # the gait over the control periods since then
                n = max(1, round((meas.t - self._prev[0]) / self.control_dt))
                swing = meas.sole_force[1] if g.stance > 0 else meas.sole_force[0]
                g.update(self._prev[1], n * self.control_dt, {"left": pl, "right": pr},
                         float(swing), self._weight)
            domain = g.domain()
            if self.rigid_swing_leg and g.stance != 0:
                v = v_lstance if g.stance > 0 else v_rstance
        t_pre = (time.perf_counter() - t_in) * 1e6
        u, x, info, aux, (tq, ts) = self._ctl.step(self.params, q, v, jnp.asarray(tau),
                                                   self.start_data, self._in_contact,
                                                   barrier_on=self.barrier, domain=domain)
        fb = info["fallback"]
        self.qp_failed += fb == "failed"
        self.fallbacks += fb == "relaxed"
        if x is not None:
            self._last_u = np.array(u)
        self._prev = (meas.t, tau)
        self.record = StepRecord(q, v, tau, domain, x, info, aux, t_pre + tq, ts)
        return self._command(self._last_u, SolveStatus(int(info["status"])), fb, "ok", t_in)

    def _command(self, u, status, fallback, reason, t_in) -> Command:
        u = np.array(u)
        return Command(u, self.motors.to_motor(u), status, fallback, reason,
                       (time.perf_counter() - t_in) * 1e6)
