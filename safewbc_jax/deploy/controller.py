"""The deployable controller: measurements in, motor commands out, no simulator.

    ctl = Controller("squat")            # or "walk", "push", "bow", "arms"
    ctl.start(q, v)                      # Theorem 1, start data, compile and warm-up
    cmd = ctl.step(Measurement(q, v, t, sole_force))   # every control_dt
    send(cmd.motor)                      # motor torques in the robot's motor order

``Controller.step`` runs the control step (``control_step``: the gait
from the sole forces and the controller's own forward kinematics of q, the rigid
swing-leg rates, the QP, the held torque, the metrics), with PIQP and its fallback policy
(``solvers.piqp_path``) as the solver; a failed QP holds the last good torque. A
measurement that fails ``check_measurement`` is refused: the command holds the last good
torque (zeros before the first good step), names the reason, the gait does not advance,
and it is counted. The step itself, compiled once, is a ``CompiledStep``; the controller
holds it and one robot's ``LaneState``.
"""

from __future__ import annotations

import dataclasses
import gc
import time
from typing import Any

import jax.numpy as jnp
import numpy as np

from safewbc_jax import scenarios
from safewbc_jax.base import paths
from safewbc_jax.control import metrics
from safewbc_jax.control import step as control_step
from safewbc_jax.control.params import as_float64
from safewbc_jax.control.step import Measurement
from safewbc_jax.deploy.compiled import (Command, CompiledStep, HostRecord, LaneState,
                                         resolve_engine)
from safewbc_jax.deploy.checks import check_barrier_poles, check_state
from safewbc_jax.deploy.motors import MotorMap
from safewbc_jax.model import robot
from safewbc_jax.solvers import host
from safewbc_jax.solvers.piqp_path import REDUCED_QP_SETTINGS, PiqpSolver


class Controller:
    """The deployable controller of one scenario (module docstring).

    Args:
        scenario: a scenario's name (``scenarios.get_scenario``) or a ``Scenario``.
        params: ``ControllerParams``; None: the scenario's defaults.
        control_dt: the control period (s).
        solver: "piqp" (a ``PiqpSolver``) or any object of the ``solvers.host`` protocol.
        barrier: False leaves the scenario's barriers out of the QP.
        speed: walking's commanded mean forward speed (m/s).
        settle: s of standing before the motion; None: the scenario's default.
        duration: the planned s of motion, where known (walking's ``avg_forward_speed`` is
            measured over its second half); None: not measured.
        keep_metrics: False leaves out ``conclude`` altogether (no metrics, no
            ``record``: the command alone).
        engine: "c" (the step generated as C, ``deploy.codegen``, built with the system
            compiler), "xla" (jitted by XLA) or "auto" (C where a compiler exists).
        native: with the C engine, build with ``-march=native``.

    Raises:
        ValueError: for a settle, duration, control period or speed out of range, or a
            solver without ``solve``.

    Each ``step`` is the ``CompiledStep``'s jitted ``prepare`` (with the exact elimination
    of the QP's equality rows), the solver on the reduced QP, and the held-torque rule;
    its ``conclude`` (metrics, record) runs after the command is out (``flush``).

    Attributes: ``steps``, ``qp_failed``, ``fallbacks``, ``bad_measurements``, ``last_times``
    ((prepare, solve) of the last good step in us), ``compile_s``, ``engine`` ("c" or
    "xla"), ``compiled`` (the ``CompiledStep``), ``motors``, ``state``, ``tally``, ``gait``,
    ``record``; ``metrics()``.
    """

    def __init__(self, scenario, params=None, control_dt: float = control_step.DEFAULT_CONTROL_DT,
                 solver: Any = "piqp", barrier: bool = True,
                 speed: float = control_step.DEFAULT_SPEED, settle: float | None = None,
                 duration: float | None = None, keep_metrics: bool = True,
                 engine: str = "auto", native: bool = False):
        import mujoco

        sc = scenarios.get_scenario(scenario, barrier)
        n_steps, settle, _ = control_step.schedule(sc, duration, settle, control_dt)
        self.walking = sc.gait is not None
        if sc.gait is not None:
            speed = sc.gait.check_speed(speed)
        if isinstance(solver, str) and solver == "piqp":
            solver = PiqpSolver(nominal_settings=REDUCED_QP_SETTINGS)
        host.check(solver)          # the protocol of solvers.host
        self.scenario = dataclasses.replace(sc, settle=settle)
        self.params = sc.default_params() if params is None else as_float64(params)
        self.control_dt, self.barrier, self.speed = float(control_dt), bool(barrier), speed
        self.keep_metrics = bool(keep_metrics)
        self.engine, self.native = resolve_engine(engine), bool(native)
        t_half = (metrics.NO_HALF if duration is None else
                  metrics.half_time(n_steps, settle, control_dt))
        mc = mujoco.MjModel.from_xml_path(str(paths.controller_xml()))
        self.model = robot.from_mujoco(mc)
        self.motors = MotorMap.build(mc)
        self.ctx = control_step.Context(self.model, self.scenario, self.control_dt,
                                        self.motors.arrays())
        self.run_values = control_step.RunValues(jnp.asarray(settle), jnp.asarray(float(speed)),
                                                 jnp.asarray(t_half))
        self.lane = LaneState(solver, self.model.nu)
        self.compiled: CompiledStep | None = None
        self.start_data: Any = None
        self.compile_s: float | None = None
        self.start_state: Any = None       # (q, v) of the last start or restart
        self._start_checks: dict = {}      # Theorem-1 checks of start and restart
        self._record: Any = None
        self._pending: tuple | None = None

    # the lane's counters and times, as attributes of the controller
    solver = property(lambda self: self.lane.solver)
    steps = property(lambda self: self.lane.steps)
    qp_failed = property(lambda self: self.lane.qp_failed)
    fallbacks = property(lambda self: self.lane.fallbacks)
    bad_measurements = property(lambda self: self.lane.bad_measurements)
    last_times = property(lambda self: self.lane.last_times)

    def start(self, q, v, warm_up: bool = True) -> float:
        """Check the start state and Theorem 1, measure the references' start data, compile
        and warm up the step; leaves the controller as ``reset`` does. Ends with a full
        garbage collection and ``gc.freeze()``: what exists then is never walked again by
        Python's collector, whose full passes would otherwise stall a control step.

        Args:
            q: the robot's configuration now (the controller model's coordinates).
            v: its velocity.
            warm_up: False: no warm-up, the step compiles at its first call.

        Returns:
            The seconds it took (also kept in ``compile_s``).

        Raises:
            ValueError: the start state is refused (``check_state``'s reason).
            barriers.PoleError: a barrier's poles fail Theorem 1 at this state.
        """
        t0 = time.perf_counter()
        q, v = np.asarray(q, float), np.asarray(v, float)
        self.start_data = self._checked_start(q, v, self.params)
        fixed = (self.params, self.start_data, self.run_values)
        self.compiled = CompiledStep(self.ctx, fixed, q, v, self.engine, self.native)
        self._fixed = self.compiled.asarray(self.compiled.pack_fixed(*fixed))
        self._ok_at = self.compiled.ok_index
        self.start_state = (q, v)
        self.reset()
        force = np.zeros(2)
        for k in range(2 if warm_up else 0):  # compiles, then the jit's fast path (tau < 0)
            self.step(Measurement(q, v, k * self.control_dt, force))
            self.flush()
        self.reset()
        # what the start built stays: out of the garbage collector's way, so that a full
        # collection in the loop walks only the loop's own objects (tens of ms otherwise)
        gc.collect()
        gc.freeze()
        self.compile_s = time.perf_counter() - t0
        return self.compile_s

    def restart(self, q, v, params=None) -> None:
        """Start again from the state (q, v) without compiling: the checks of ``start``, the
        references' start data at q, then ``reset``.

        Args:
            q: the new start configuration.
            v: the new start velocity.
            params: ``ControllerParams`` of the same shapes; None: keep the current ones.

        Raises:
            RuntimeError: before ``start``.
            ValueError, barriers.PoleError: as ``start``.
        """
        params = self.params if params is None else as_float64(params)
        self.start_data, fixed, _, _ = self._start_arrays(q, v, params)
        self.params, self._fixed = params, self._cs.asarray(fixed)
        self.start_state = (np.asarray(q, float), np.asarray(v, float))
        self.reset()

    def lane_start(self, q, v, params=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The flat (fixed, state, tally) of a rollout of the compiled step from (q, v) with
        ``params`` (None: this controller's), after the checks of ``start``; nothing in
        the controller changes. Raises as ``restart``."""
        params = self.params if params is None else as_float64(params)
        return self._start_arrays(q, v, params)[1:]

    def _start_arrays(self, q, v, params):
        """(start data, flat fixed, state, tally) of a start from (q, v) with ``params``."""
        if self.compiled is None:
            raise RuntimeError("Controller.restart before start(q, v)")
        q, v = np.asarray(q, float), np.asarray(v, float)
        same = np.array_equal(q, self.start_state[0])
        start = self._checked_start(q, v, params, self.start_data if same else None)
        return (start, self.compiled.pack_fixed(params, start, self.run_values),
                *self.compiled.initial(q, v))

    def _checked_start(self, q, v, params, start=None):
        """The start checks (the state, Theorem 1 where barriers are on) and the references'
        start data at q (``start`` where known)."""
        reason = check_state(q, v, self.model.nq, self.model.nv)
        if reason != "ok":
            raise ValueError(f"start state refused: {reason}")
        if self.barrier:
            check_barrier_poles(self.model, self.scenario, params, jnp.asarray(q),
                                jnp.asarray(v), self._start_checks)
        return (control_step.start_data(self.model, self.scenario, jnp.asarray(q))
                if start is None else start)

    def reset(self) -> None:
        """Back to the state after ``start``: counters zero, metrics empty, gait standing,
        no torque held, the clock restarting at the next good measurement, the solver set
        up afresh."""
        self._record = self._pending = None
        if self.compiled is not None:
            self.lane.reset()
            self._state, self._tally = (self.compiled.asarray(a) for a in
                                        self.compiled.initial(*self.start_state))

    @property
    def _cs(self) -> CompiledStep:
        if self.compiled is None:
            raise RuntimeError("Controller used before start(q, v)")
        return self.compiled

    def last_qp(self):
        """The full QP (``solvers.problem.QP``, numpy) of the last good step, or None:
        computed again from that step's state and measurement (``CompiledStep.full_qp``),
        since the step writes only the reduced QP and the full QP's equality rows."""
        if self.lane.last_inputs is None:
            return None
        return self._cs.full_qp(self._fixed, *self.lane.last_inputs)

    @property
    def state(self) -> control_step.ControllerState:
        """The control step's ControllerState (numpy, a copy)."""
        return self._cs.layouts.state.unpack(np.array(self._state))

    @property
    def tally(self) -> control_step.Tally:
        """The control step's Tally (numpy: last good torque, metric accumulators), with
        every step's ``conclude`` done (``flush``)."""
        self.flush()
        return self._cs.layouts.tally.unpack(np.asarray(self._tally))

    @property
    def gait(self):
        """The gait's state (walking), or None."""
        return self.state.gait if self.walking else None

    def flush(self) -> None:
        """Run the last step's ``conclude`` (metrics, record) if it has not run yet. ``step``
        leaves it pending so that the command is out first; it runs at the latest at the
        start of the next ``step`` (counted in that step's latency), or when ``record``,
        ``tally`` or ``metrics()`` is read. A loop that reads ``record`` after sending the
        command keeps it off the command's path."""
        if self._pending is not None:
            prep, sol, x, solved, t_qp, t_solve = self._pending
            self._pending = None
            self._tally, out = self._cs.conclude(self._fixed, self._tally, prep, sol)
            self._record = (out, x, sol if solved else None, t_qp, t_solve)

    @property
    def record(self) -> HostRecord | None:
        """The last step's HostRecord: ``step.ok`` False where the measurement was refused
        (then x is None and the torque is the held one); None before the first step and
        where the measurement could not enter the step at all (shapes, types, sole forces
        missing while walking)."""
        self.flush()
        r = self._record
        if r is not None and not isinstance(r, HostRecord):
            packed, x, sol, t_qp, t_solve = r
            rec, q, v, domain = self._cs.unpack_record(packed)
            r = self._record = HostRecord(rec, q, v, domain, x, None if sol is None
                                          else self._cs.solve_result(sol), t_qp, t_solve)
        return r

    def kernels(self, cost: bool = False) -> dict:
        """Per call of the step as XLA compiles it (whatever the engine), after ``start``:
        its kernels by kind (``kernels.count``), or XLA's ``cost`` analysis."""
        import jax

        from safewbc_jax.deploy import kernels
        cs, (q, v) = self._cs, self.start_state
        fn = cs.prepare if cs.engine == "xla" else jax.jit(cs.prepare_fn)
        meas = cs.flat_measurement(Measurement(q, v, 0.0, np.zeros(2)))
        return (kernels.cost if cost else kernels.count)(fn, self._fixed, self._state, meas)

    def prepare_flat(self, state: control_step.ControllerState, meas: Measurement):
        """The jitted ``prepare`` (with the elimination) at a given ControllerState and
        measurement, as ``step`` calls it: returns (state after it, the full QP, the
        reduced QP, the map back to X), numpy. Changes nothing in the controller."""
        if self.compiled is None:
            raise RuntimeError("Controller.prepare_flat before start(q, v)")
        cs, lay = self.compiled, self.compiled.layouts
        flat_state, flat_meas = lay.state.pack(state), cs.flat_measurement(meas)
        new, _, packed = cs.prepare(self._fixed, cs.asarray(flat_state), flat_meas)
        return (lay.state.unpack(np.asarray(new)), cs.full_qp(self._fixed, flat_state, flat_meas),
                *cs.unpack_qp(packed)[1:3])

    def metrics(self) -> dict:
        """The controller-side metric columns so far (``metrics.finalize``)."""
        return metrics.finalize(self.scenario, self.tally.acc, None, False, self.state.gait)

    def step(self, meas: Measurement) -> Command:
        """One control step (module docstring). Never raises on the measurement's content.

        Args:
            meas: the robot's measurement now.

        Returns:
            The ``Command``: torques, motor torques, the solve's status and fallback, and
            whether the measurement was accepted.

        Raises:
            RuntimeError: before ``start``.
        """
        t_in = time.perf_counter()
        cs = self.compiled
        if cs is None:
            raise RuntimeError("Controller.step before start(q, v)")
        self.flush()               # the last step's metrics, if nobody ran them yet
        t_step = time.perf_counter()
        flat, reason = cs.admit_fast(self.lane, meas), "ok"
        if flat is None:           # a host-only test fails: named and counted here
            flat, reason = cs.admit_one(self.lane, meas)
            self._record = None
        if flat is None:           # cannot enter the step: counted here
            tally = cs.layouts.tally.unpack(np.asarray(self._tally))
            tally = tally._replace(acc=metrics.control_refused(tally.acc, True, np))
            self._tally = cs.asarray(cs.layouts.tally.pack(tally))
            return cs.command(self.lane.last_u, None, "held", reason, t_in)
        # for last_qp: C writes the state in place (an XLA result is never written)
        state_in = np.copy(self._state) if cs.engine == "c" else self._state
        self._state, prep, packed, views = cs.prepare_lane(self.lane, self._fixed,
                                                           self._state, flat)
        if reason == "ok" and not np.asarray(prep)[self._ok_at]:   # the state tests
            reason, self._record = cs.refused(self.lane, meas), None
        cmd, sol, x = cs.solve_lane(self.lane, reason, packed, views, meas.t, t_in, t_step)
        if reason == "ok":
            self.lane.last_inputs = (state_in, flat)
        if self.keep_metrics:
            self._pending = (prep, sol, x, reason == "ok", *self.lane.last_times)
        return cmd
