"""The deployable controller: measurements in, motor commands out, no simulator.

    ctl = Controller("squat")            # or "walk", "push", "bow", "arms"
    ctl.start(q, v)                      # Theorem 1, start data, compile and warm-up
    cmd = ctl.step(Measurement(q, v, t, sole_force))   # every control_dt
    send(cmd.motor)                      # motor torques in the robot's motor order

``Controller.step`` runs the control step every loop shares (``control_step``: the gait
from the sole forces and the controller's own forward kinematics of q, the rigid
swing-leg rates, the QP, the held torque, the metrics), with PIQP and its fallback policy
(``solvers.piqp_path``) as the solver; a failed QP holds the last good torque. A
measurement that fails ``check_measurement`` is refused: the command holds the last good
torque (zeros before the first good step), names the reason, the gait does not advance,
and it is counted. ``MotorMap`` maps joint torques to motor torques from the controller
model and the published figures (``models/digit_v3_parameters.json``), not from a
simulator.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax import scenarios
from safewbc_jax.base import paths
from safewbc_jax.control import step as control_step, metrics
from safewbc_jax.model import robot
from safewbc_jax.deploy.packing import FlatTree, Packer
from safewbc_jax.control.params import as_float64
from safewbc_jax.solvers import host, policy, reduce
from safewbc_jax.solvers.piqp_path import REDUCED_QP_SETTINGS, PiqpSolver
from safewbc_jax.solvers.result import (FALLBACK_FAILED, FALLBACK_RELAXED,
                                        SolveResult, fallback_name, failed, row)
from safewbc_jax.solvers.status import SolveStatus

# the measurement bounds and the fall test are the control step's (one definition)
from safewbc_jax.control.step import (FALL_HEIGHT, MAX_RATE, MAX_SPEED, QUAT_TOL,  # noqa: E402,F401
                                      Measurement, fallen, state_ok, state_tests)


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

    def arrays(self) -> control_step.MotorArrays:
        return self._arrays

    @functools.cached_property
    def _arrays(self) -> control_step.MotorArrays:
        return control_step.MotorArrays(self.u_index, self.gear, self.motor_limit)

    def to_motor(self, u) -> np.ndarray:
        """Joint torques u (controller actuator order) -> motor torques u / gear, in motor
        order, clipped to the motor limits (``control_step.MotorArrays.to_motor``)."""
        return self._arrays.to_motor(np.asarray(u, float))


def check_state(q, v, nq: int, nv: int) -> str:
    """"ok", or why (q, v) is no state of the robot with ``nq`` positions and ``nv``
    velocities: a shape, or the first of the control step's ``state_tests`` that fails
    (NaN/inf, quaternion norm, base speed, rates), with its values."""
    for name, x, n in (("q", q, nq), ("v", v, nv)):
        if np.shape(x) != (n,):
            return f"{name} has shape {np.shape(x)}, expected ({n},)"
    finite, unit, speed, rates = (bool(t) for t in state_tests(q, v))
    if not finite:
        name, x = ("q", q) if not np.all(np.isfinite(q)) else ("v", v)
        return f"{name} not finite at {np.flatnonzero(~np.isfinite(x)).tolist()}"
    if not unit:
        return (f"base quaternion |q| = {np.linalg.norm(q[3:7]):.6g}, not unit (tolerance "
                f"{QUAT_TOL:g})")
    if not speed:
        return f"base speed {np.linalg.norm(v[:3]):.4g} m/s above {MAX_SPEED:g} m/s"
    if not rates:
        k = int(np.argmax(np.abs(v[3:])))
        return f"rate {v[3 + k]:.4g} rad/s at dof {3 + k}, above {MAX_RATE:g} rad/s"
    return "ok"


def check_measurement(m: Measurement, walking: bool, nq: int, nv: int) -> str:
    """"ok", or why the measurement is refused (``check_state`` with the sizes ``nq``,
    ``nv``; t not finite; walking:
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
        return check_state(np.asarray(m.q, float), np.asarray(m.v, float), nq, nv)
    except (TypeError, ValueError) as e:
        return f"malformed measurement: {e}"


def check_barrier_poles(model, scenario, params, q, v, cache: dict | None = None):
    """Theorem 1 at the start state (q, v), before anything compiles: raises
    barriers.PoleError naming the barrier, the pole and its bound
    (``control_step.StartCheck``; a walking barrier is checked where its domain first
    starts). ``cache``: keeps the jitted check of each start q (``start``, ``restart``);
    without it the check runs eagerly (arms, a fresh process: 3.1 s, jitted 1.9 s)."""
    key = np.asarray(q).tobytes()
    if cache is not None and key not in cache:
        cache[key] = control_step.StartCheck(model, scenario, q)
    check = control_step.StartCheck(model, scenario, q, jit=False) if cache is None else cache[key]
    check.check(params, v, batched=False)


@dataclasses.dataclass(frozen=True)
class HostRecord:
    """A good step, for logs: the control step's ``StepRecord`` (numpy), the state the QP
    saw (v with the rigid swing-leg rates), the domain, X or None, the solver's
    ``SolveResult`` (x over the full X, NaN where failed; eq_residual of the full QP, the
    other residuals of the reduced QP PIQP solved; None where the measurement was
    refused), the wall times of the QP's preparation and of the solve (us)."""

    step: Any
    q: np.ndarray
    v: np.ndarray
    domain: Any          # walking.Domain, or None
    x: np.ndarray | None
    solve: Any
    t_qp: float
    t_solve: float

    @property
    def tau(self) -> float:
        return float(self.step.tau)


class Controller:
    """The deployable controller of one scenario (module docstring). ``scenario``: a name
    (``scenarios.get_scenario``) or a Scenario; ``params``: ControllerParams (the
    scenario's defaults when None); ``settle``: s of standing before the motion (the
    scenario's default when None); ``speed``: walking's commanded mean speed (m/s);
    ``duration``: the planned s of motion, where known (walking's ``avg_forward_speed`` is
    measured over its second half; None: not measured); ``keep_metrics``: False leaves out
    ``conclude`` altogether (no metrics, no ``record``: the command alone); ``solver``:
    "piqp" (a ``PiqpSolver``) or any object of the ``solvers.host`` protocol.

    Each ``step`` is ``control_step.prepare`` (jitted, with the exact elimination of the
    QP's equality rows, ``solvers.reduce``), PIQP on the reduced QP (``solver``), and the
    held-torque rule; ``control_step.conclude`` (jitted: metrics, record) runs after the
    command is out (``flush``).

    Attributes: ``steps`` (calls of ``step``), ``qp_failed``, ``fallbacks`` (relaxed QPs),
    ``bad_measurements``; ``compile_s``; ``gait`` (walking.GaitState, walking only);
    ``record`` (HostRecord of the last step);
    ``last_times`` ((prepare, solve) of the last good step in us); ``motors``
    (MotorMap); ``state`` (control_step.ControllerState) and ``tally``
    (control_step.Tally); ``metrics()``."""

    def __init__(self, scenario, params=None, control_dt=control_step.DEFAULT_CONTROL_DT,
                 solver="piqp", barrier=True,
                 speed=control_step.DEFAULT_SPEED, settle=None, duration=None,
                 keep_metrics=True):
        import mujoco

        sc = scenarios.get_scenario(scenario, barrier)
        n_steps, settle, _ = control_step.schedule(sc, duration, settle, control_dt)
        self.walking = sc.gait is not None
        if self.walking:
            speed = sc.gait.check_speed(speed)
        if isinstance(solver, str) and solver == "piqp":
            solver = PiqpSolver(nominal_settings=REDUCED_QP_SETTINGS)
        host.check(solver)          # the protocol of solvers.host
        self.solver = solver
        self.scenario = dataclasses.replace(sc, settle=settle)
        self.params = sc.default_params() if params is None else as_float64(params)
        self.control_dt, self.barrier, self.speed = float(control_dt), bool(barrier), speed
        self.keep_metrics = bool(keep_metrics)
        t_half = (metrics.NO_HALF if duration is None else
                  metrics.half_time(n_steps, settle, control_dt))
        mc = mujoco.MjModel.from_xml_path(str(paths.controller_xml()))
        self.model = robot.from_mujoco(mc)
        self.motors = MotorMap.build(mc)
        self.ctx = control_step.Context(self.model, self.scenario, self.control_dt,
                                        self.motors.arrays())
        self.run_values = control_step.RunValues(jnp.asarray(settle), jnp.asarray(float(speed)),
                                                 jnp.asarray(t_half))
        self.start_data = self.compile_s = self._start_qv = None
        self._start_checks = {}      # start's and restart's Theorem-1 checks (lanes share it)
        self._prepare = self._conclude = None

    def start(self, q, v, warm_up: bool = True) -> float:
        """Check the start state and Theorem 1 (barriers.PoleError), measure the
        references' start data, compile and warm up the step (``warm_up`` False: no
        warm-up, the step compiles at its first call; ``sim.lockstep`` runs it vmapped
        only); returns (and keeps in ``compile_s``) the seconds it took. Leaves the
        controller as ``reset`` does."""
        q, v = np.asarray(q, float), np.asarray(v, float)
        reason = check_state(q, v, self.model.nq, self.model.nv)
        if reason != "ok":
            raise ValueError(f"start state refused: {reason}")
        t0 = time.perf_counter()
        model, sc = self.model, self.scenario
        qj, vj = jnp.asarray(q), jnp.asarray(v)
        if self.barrier:
            check_barrier_poles(model, sc, self.params, qj, vj, self._start_checks)
        self.start_data = control_step.start_data(model, sc, qj)
        self._start_qv = (q, v)
        self._compile(q, v)
        self.reset()
        force = np.zeros(2)
        for k in range(2 if warm_up else 0):  # compiles, then the jit's fast path (tau < 0)
            self.step(Measurement(q, v, k * self.control_dt, force))
            self.flush()
        self.reset()
        self.compile_s = time.perf_counter() - t0
        return self.compile_s

    def restart(self, q, v, params=None):
        """Start again from the state (q, v), with ``params`` (ControllerParams of the same
        shapes; None: keep the current ones), without compiling: the checks of ``start``
        (the state, Theorem 1 for these poles at this start), the references' start data
        at q, then ``reset``. A sweep's worker (``sweeps.pool``) runs its rollouts one
        after the other this way through one compiled controller."""
        if self._prepare is None:
            raise RuntimeError("Controller.restart before start(q, v)")
        q, v = np.asarray(q, float), np.asarray(v, float)
        reason = check_state(q, v, self.model.nq, self.model.nv)
        if reason != "ok":
            raise ValueError(f"start state refused: {reason}")
        params = self.params if params is None else as_float64(params)
        if self.barrier:
            check_barrier_poles(self.model, self.scenario, params, jnp.asarray(q), jnp.asarray(v),
                                self._start_checks)
        if not np.array_equal(q, self._start_qv[0]):
            self.start_data = control_step.start_data(self.model, self.scenario, jnp.asarray(q))
        self.params = params
        self._fixed = jnp.asarray(self._flat["fixed"].pack((params, self.start_data,
                                                             self.run_values)))
        self._start_qv = (q, v)
        self.reset()

    def lane(self) -> "Controller":
        """Another controller of this compiled step (no compile) with its own solver
        (``solvers.host.lane``), counters and state: a lane of ``sim.lockstep``."""
        import copy

        if self._prepare is None:
            raise RuntimeError("Controller.lane before start(q, v)")
        other = copy.copy(self)
        other.solver = host.lane(self.solver)
        other.reset()
        return other

    def _compile(self, q, v):
        """The jitted prepare (with the elimination) and conclude, on flat vectors: every
        argument and result of a step is one float64 vector (``packing.FlatTree``), not a
        pytree of some forty arrays, each of which costs microseconds at the boundary."""
        ctx = self.ctx
        fixed = (self.params, self.start_data, self.run_values)
        state0, tally0 = control_step.init_state(ctx, q, v, np, np.float64)
        meas0 = Measurement(q, v, 0.0, np.zeros(2))
        qp0 = jax.jit(lambda *a: control_step.prepare(ctx, *a)[2])(*fixed, state0, meas0)
        # static data of the elimination, from the QP itself (its block sizes, which of
        # its variables outside u are bounded, whether P has cross blocks)
        bounded = reduce.bounded_variables(qp0)
        p_blockdiag = reduce.p_block_diagonal(qp0)
        self._nx = int(qp0.P.shape[0])
        self._no_sol = self.flat_solution(failed(self._nx))     # conclude's "no solution"
        prep0 = jax.eval_shape(lambda *a: control_step.prepare(ctx, *a)[1], *fixed, state0, meas0)
        sol0 = failed(self._nx)
        self._flat = {k: FlatTree(t) for k, t in (("fixed", fixed), ("state", state0),
                                                  ("tally", tally0), ("meas", meas0),
                                                  ("prep", prep0), ("sol", sol0))}
        F = self._flat
        qp_packer, out_packer = Packer(), Packer()

        def prepare(fixed, state, meas):
            state, prep, qpm = control_step.prepare(
                ctx, *F["fixed"].unpack(fixed, jnp), F["state"].unpack(state, jnp),
                F["meas"].unpack(meas, jnp))
            red, rmap = reduce.eliminate_equalities(qpm, bounded, p_blockdiag)
            return (F["state"].pack(state, jnp), F["prep"].pack(prep, jnp),
                    qp_packer.pack((qpm, red, rmap, policy.checks(red, jnp))))

        def conclude(fixed, tally, prep, sol):
            prep = F["prep"].unpack(prep, jnp)
            tally, out = control_step.conclude(ctx, F["fixed"].unpack(fixed, jnp)[2],
                                               F["tally"].unpack(tally, jnp), prep,
                                               F["sol"].unpack(sol, jnp))
            return (F["tally"].pack(tally, jnp),
                    out_packer.pack((out.record, prep.q, prep.v, prep.domain)))

        self._prepare_fn, self._conclude_fn = prepare, conclude   # unjitted: sim.lockstep
        self._prepare, self._conclude = jax.jit(prepare), jax.jit(conclude)
        # the lane API, after start: packed QP -> (full QP, reduced QP, map back to X, Checks);
        # packed record -> (StepRecord, q, v, domain); numpy views, leading axes kept
        self.unpack_qp, self.unpack_record = qp_packer.unpack, out_packer.unpack
        self._fixed = jnp.asarray(F["fixed"].pack(fixed))

    def reset(self):
        """Back to the state after ``start``: counters zero, metrics empty, gait standing,
        no torque held, the clock restarting at the next good measurement, PIQP set up
        afresh."""
        self.steps = self.qp_failed = self.fallbacks = self.bad_measurements = 0
        self._record = self._pending = self._last_qp = None
        self._last_u = np.zeros(self.model.nu)
        self._prev_t = None
        if self._start_qv is not None:
            state, tally = control_step.init_state(self.ctx, *self._start_qv, np, np.float64)
            self._state = jnp.asarray(self._flat["state"].pack(state))
            self._tally = jnp.asarray(self._flat["tally"].pack(tally))
            host.reset(self.solver)

    def last_qp(self):
        """The full QP (``qp_types.QP``, numpy) of the last good step."""
        if self._last_qp is None:
            return None
        qpm, j = self._last_qp
        return qpm.row(j)

    @property
    def state(self) -> control_step.ControllerState:
        """The control step's ControllerState (numpy)."""
        return self._flat["state"].unpack(np.asarray(self._state))

    @property
    def tally(self) -> control_step.Tally:
        """The control step's Tally (numpy: last good torque, metric accumulators), with
        every step's ``conclude`` done (``flush``)."""
        self.flush()
        return self._flat["tally"].unpack(np.asarray(self._tally))

    @property
    def gait(self):
        return self.state.gait if self.walking else None

    def flush(self):
        """Run the last step's ``conclude`` (metrics, record) if it has not run yet. ``step``
        leaves it pending so that the command is out first; it runs at the latest at the
        start of the next ``step`` (counted in that step's latency), or when ``record``,
        ``tally`` or ``metrics()`` is read. A loop that reads ``record`` after sending the
        command, as the MuJoCo loop does, keeps it off the command's path."""
        if self._pending is not None:
            prep, sol, x, res, t_qp, t_solve = self._pending
            self._pending = None
            self._tally, out = self._conclude(self._fixed, self._tally, prep, sol)
            self._record = (out, x, res, t_qp, t_solve)

    @property
    def record(self) -> HostRecord | None:
        """The last step's HostRecord: ``step.ok`` False where the measurement was refused
        (then x is None and the torque is the held one); None before the first step and
        where the measurement could not enter the step at all (shapes, types, sole forces
        missing while walking)."""
        self.flush()
        r = self._record
        if r is not None and not isinstance(r, HostRecord):
            packed, x, res, t_qp, t_solve = r
            rec, q, v, domain = self.unpack_record(packed)
            r = self._record = HostRecord(rec, q, v, domain, x,
                                          None if res is None else row(res, 0), t_qp, t_solve)
        return r

    def kernels(self, cost: bool = False) -> dict:
        """Per call of the jitted step (``prepare`` with the elimination), after ``start``:
        its kernels by kind (``kernels.count``), or XLA's ``cost`` analysis (``kernels.cost``)."""
        from safewbc_jax.deploy import kernels
        if self._prepare is None:
            raise RuntimeError("Controller.kernels before start(q, v)")
        q, v = self._start_qv
        meas = self.flat_measurement(Measurement(q, v, 0.0, np.zeros(2)))
        return (kernels.cost if cost else kernels.count)(self._prepare, self._fixed,
                                                         self._state, meas)

    def prepare_flat(self, state: control_step.ControllerState, meas: Measurement):
        """The deployed step's jitted ``prepare`` (with the elimination) at a given
        ControllerState and measurement, as ``step`` calls it (flat vectors in and out):
        returns (state after it, the full QP, the reduced QP, the map back to X), numpy.
        For tests and tools that hold the deployment to the pure functions; it changes
        nothing in the controller."""
        if self._prepare is None:
            raise RuntimeError("Controller.prepare_flat before start(q, v)")
        flat_state = jnp.asarray(self._flat["state"].pack(state))
        new, _, packed = self._prepare(self._fixed, flat_state, self.flat_measurement(meas))
        return (self._flat["state"].unpack(np.asarray(new)), *self.unpack_qp(packed)[:3])

    def metrics(self) -> dict:
        """The controller-side metric columns so far (``metrics.finalize``)."""
        return metrics.finalize(self.tally.acc, None, False,
                                self.state.gait if self.walking else None)

    def step(self, meas: Measurement) -> Command:
        """One control step (module docstring). Never raises on the measurement's content."""
        t_in = time.perf_counter()
        if self._prepare is None:
            raise RuntimeError("Controller.step before start(q, v)")
        self.flush()               # the last step's metrics, if nobody ran them yet
        t_step = time.perf_counter()
        flat_meas, reason = self._admit(meas)
        if flat_meas is None:      # cannot enter the step: counted here
            tally = self._flat["tally"].unpack(np.asarray(self._tally))
            tally = tally._replace(acc=metrics.control_refused(tally.acc, True, np))
            self._tally = jnp.asarray(self._flat["tally"].pack(tally))
            return self._command(self._last_u, None, "held", reason, t_in)
        self._state, prep, packed = self._prepare(self._fixed, self._state, flat_meas)
        return self._finish(prep, packed, reason, meas.t, t_in, t_step)

    def _admit(self, meas: Measurement):
        """The host side of a step before the jitted prepare: count it, check the
        measurement. Returns (its flat vector, or None where it cannot enter the step;
        "ok" or the reason it is refused)."""
        self.steps += 1
        reason = check_measurement(meas, self.walking, self.model.nq, self.model.nv)
        if reason == "ok" and self._prev_t is not None and not meas.t > self._prev_t:
            reason = f"t = {meas.t} does not advance (last step at {self._prev_t})"
        if reason != "ok":
            self.bad_measurements += 1
            self._record = None
        return self.flat_measurement(meas), reason

    def _finish(self, prep, packed, reason: str, t, t_in: float, t_step: float) -> Command:
        """The host side of one robot's step after the jitted prepare (its ``prep`` and
        packed QP): ``_solve_lanes`` with this one lane, its ``conclude`` left pending
        (``flush``). A refused measurement (``reason`` not "ok", which the jitted step
        refused too) holds the last good torque (``_hold``)."""
        if reason != "ok":
            return self._hold(prep, reason, t_in)
        cmds, sols, res, x, usable = Controller._solve_lanes(
            [self], np.asarray(packed)[None], (t,), t_in, t_step)
        if self.keep_metrics:
            self._pending = (prep, sols[0], x[0] if usable[0] else None, res,
                             *self.last_times)
        return cmds[0]

    def _hold(self, prep, reason: str, t_in: float) -> Command:
        """A refused measurement's step: no solve, the last good torque held."""
        self.last_times = (np.nan, np.nan)
        if self.keep_metrics:
            self._pending = (prep, self._no_sol, None, None, np.nan, np.nan)
        return self._command(self._last_u, None, "held", reason, t_in)

    @staticmethod
    def _solve_lanes(lanes: list, packed, ts, t_in: float, t_step: float):
        """The host side of a step for L lanes with accepted measurements (one robot: L =
        1, ``_finish``), from the jitted prepare's packed QPs (leading axis L, numpy): each
        lane's reduced QP by its own solver (``solvers.host.solve_lanes``), X = x0 + N u,
        the usable test, the held-torque rule, the motor map and each lane's counters.
        Returns (the Commands; the conclude's flat solve records (L, .); the SolveResult
        (x over the full X, NaN where not usable; eq_residual of the full QP); X; usable)."""
        lead = lanes[0]
        qpm, red, rmap, checks = lead.unpack_qp(packed)
        t1 = time.perf_counter()
        res = host.solve_lanes([lane.solver for lane in lanes], red, checks)
        x = reduce.expand(res.x, rmap)
        usable = (res.fallback != FALLBACK_FAILED) & np.isfinite(x).all(axis=-1)
        eq = np.abs((qpm.A @ x[..., None])[..., 0] - qpm.b).max(axis=-1)
        res = res._replace(x=x, eq_residual=eq)
        if not usable.all():      # rare: failed()'s fields on those rows, with the
            res = SolveResult(*(np.array(f) for f in res))   # solver's status, or
            for i in np.flatnonzero(~usable).tolist():       # NUMERICAL for a non-finite X
                status = (res.status[i] if res.fallback[i] == FALLBACK_FAILED
                          else SolveStatus.NUMERICAL)
                bad = failed(lead._nx, status)._replace(iterations=res.iterations[i])
                for f, v in zip(res, bad):
                    f[i] = v
        t2 = time.perf_counter()
        last_u = (lead._last_u[None] if len(lanes) == 1
                  else np.stack([lane._last_u for lane in lanes]))
        u = control_step.hold_torque(res.x, usable[:, None], last_u, qpm.blocks)
        motor = lead.motors.arrays().to_motor(u)
        sols = lead.flat_solution(res)
        times = ((t1 - t_step) * 1e6, (t2 - t1) * 1e6 / len(lanes))
        t_out = (time.perf_counter() - t_in) * 1e6
        cmds = []
        for j, lane in enumerate(lanes):
            fb = int(res.fallback[j])
            lane.last_times, lane._last_qp = times, (qpm, j)
            lane.qp_failed += fb == FALLBACK_FAILED
            lane.fallbacks += fb == FALLBACK_RELAXED
            lane._last_u, lane._prev_t = u[j], ts[j]
            cmds.append(Command(u[j].copy(), motor[j], SolveStatus(int(res.status[j])),
                                fallback_name(fb), "ok", t_out))
        return cmds, sols, res, x, usable

    @staticmethod
    def admit_lanes(lanes: list, meas: list):
        """``_admit`` for several lanes of one compiled step (``lane``; ``sim.lockstep``):
        the control step's state test (``state_ok``) and the time tests run once over the
        stacked measurements; a lane whose measurement fails one of them, or cannot be
        stacked, goes through its own ``_admit``, which names the reason. Returns (the
        flat measurements (L, .), or None where a lane's cannot enter the step; the
        reasons, "ok" or why)."""
        lead = lanes[0]
        try:
            flat = np.stack([lead.flat_measurement(m) for m in meas])
        except (TypeError, ValueError):      # some measurement cannot be a flat vector
            flat = None
        if flat is None or flat.dtype != np.float64:
            out = [lane._admit(m) for lane, m in zip(lanes, meas)]
            return [f for f, _ in out], [r for _, r in out]
        nq, nv = lead.model.nq, lead.model.nv
        t = flat[:, -1]
        prev = np.array([-np.inf if lane._prev_t is None else lane._prev_t for lane in lanes])
        good = (state_ok(flat[:, :nq], flat[:, nq:nq + nv]) & np.isfinite(t) & (t > prev)
                & np.isfinite(flat[:, nq + nv:-1]).all(axis=1))
        reasons = ["ok"] * len(lanes)
        for i, lane in enumerate(lanes):
            if good[i]:       # (a walking lane without sole forces could not be stacked)
                lane.steps += 1
            else:
                reasons[i] = lane._admit(meas[i])[1]
        return list(flat), reasons

    @staticmethod
    def finish_lanes(lanes: list, prep, packed, reasons: list, ts, t_in: float):
        """The host side of a step for several lanes of one compiled step (``lane``;
        ``sim.lockstep``), from the rows of a vmapped prepare (``prep``, ``packed``:
        leading axis L): the lanes whose measurement was accepted through
        ``_solve_lanes`` together (one robot's step runs the same, L = 1), the others
        hold their torque (``_hold``). ``ts``: the measurements' times. Returns (the
        Commands, the solve records as the conclude's flat vectors (L, .)); no conclude is
        left pending (the caller runs it, vmapped)."""
        sols = np.tile(lanes[0]._no_sol, (len(lanes), 1))
        cmds = [None] * len(lanes)
        ok = np.array([r == "ok" for r in reasons])
        for i in np.flatnonzero(~ok).tolist():
            cmds[i] = lanes[i]._hold(prep[i], reasons[i], t_in)
            lanes[i]._pending = None
        idx = np.flatnonzero(ok)
        if idx.size:
            every = idx.size == len(lanes)
            got, sols[idx], *_ = Controller._solve_lanes(
                lanes if every else [lanes[i] for i in idx], packed if every else packed[idx],
                ts if every else [ts[i] for i in idx], t_in, t_in)
            for i, c in zip(idx.tolist(), got):
                cmds[i] = c
        return cmds, sols

    # -- the lane API (sim.lockstep: lanes of one step, vmapped), with admit/finish_lanes
    @property
    def start_state(self) -> tuple:
        """(q, v) of the last ``start`` or ``restart``."""
        return self._start_qv

    def step_functions(self, jitted: bool = False) -> tuple:
        """(prepare, conclude) on flat vectors after ``start``: prepare(fixed, state, meas)
        -> (state, prepared, packed QP: ``unpack_qp``); conclude(fixed, tally, prepared,
        solve) -> (tally, packed record: ``unpack_record``). Unjitted, to vmap over lanes;
        ``jitted``: the compiled ones ``step`` calls."""
        return (self._prepare, self._conclude) if jitted else (self._prepare_fn,
                                                                self._conclude_fn)

    def flat_arrays(self) -> tuple:
        """(fixed, state, tally): this controller's flat vectors (numpy)."""
        return (np.asarray(self._fixed), np.asarray(self._state), np.asarray(self._tally))

    def set_flat_arrays(self, state, tally) -> None:
        """Take the state and tally a vmapped step computed for this lane."""
        self._state, self._tally = np.array(state), np.array(tally)

    def no_solution(self) -> np.ndarray:
        """The flat solve record of a step with no solution."""
        return self._no_sol

    def prepared_layout(self) -> tuple[int, int]:
        """(size of prepare's flat Prepared vector, where tau sits in it)."""
        flat = self._flat["prep"]
        return flat.size, int(flat.unpack(np.arange(flat.size, dtype=float)).tau)

    def flat_solution(self, res) -> np.ndarray:
        """A host SolveResult (one QP's, or L's with a leading axis) as conclude's flat
        vector(s): x, then each scalar field (``FlatTree``'s layout), filled in place."""
        out = np.empty(np.shape(res.x)[:-1] + (self._nx + len(res) - 1,))
        out[..., :self._nx] = res.x
        for k, f in enumerate(res[1:]):
            out[..., self._nx + k] = f
        return out

    def flat_measurement(self, meas: Measurement):
        """The measurement as the step's flat vector (q, v, sole forces, t), or None where
        it cannot be one (shapes, types; sole forces missing while walking)."""
        try:
            q, v = np.asarray(meas.q, float), np.asarray(meas.v, float)
            f = (np.zeros(2) if meas.sole_force is None and not self.walking
                 else np.asarray(meas.sole_force, float))
            if q.shape != (self.model.nq,) or v.shape != (self.model.nv,) or f.shape != (2,):
                return None
            return np.concatenate([q, v, f, [float(meas.t)]])
        except (TypeError, ValueError):
            return None

    def _command(self, u, status, fallback, reason, t_in) -> Command:
        u = np.array(u)
        return Command(u, self.motors.to_motor(u), status, fallback, reason,
                       (time.perf_counter() - t_in) * 1e6)
