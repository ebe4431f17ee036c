"""Several deployment loops in lockstep on one core.

``width`` rollouts side by side, each with its own ``LaneState`` (counters, held torque,
PIQP solver), its own flat state vectors and its own ``SimRobot`` (``SimRobot.sibling``:
one MjModel, one MjData per lane), all of the leader controller's ``CompiledStep``. How
the lanes' control step runs follows the leader's engine:

- ``engine="c"`` (``CLanes``): each lane runs one robot's deployed step as
  ``Controller.step`` does (``CompiledStep.prepare_lane``, ``solve_one``, the generated
  ``conclude``), lane by lane. Its generated C has no per-call runtime to share, and a
  lane that stopped costs nothing.
- ``engine="xla"`` (``Lanes``): one robot's jitted step pays per call mostly XLA's
  per-kernel runtime, not arithmetic; the lanes pay it once a step for all of them: the
  ``CompiledStep``'s unjitted ``prepare`` and ``conclude``, vmapped over the lanes, then
  the host side of the step for all lanes at once (``CompiledStep.finish``: the
  acceptance, X = x0 + N u, the held-torque rule, the motor map), PIQP one solve per lane
  by the lane's own solver.

The loop is ``sim.loop.simulate`` (measurement -> control step -> push -> physics -> plant
metrics -> fall test); the measurement checks of all lanes run at once
(``CompiledStep.admit``). A lane whose measurement is refused holds its torque for that
step.

One XLA call a step: step k's conclude runs vmapped in the same call as step k+1's prepare
(the two do not depend on each other; one call costs less than two), so step k's record,
and with it step k's plant metrics, comes one call later (a last call after the loop
concludes the last step); the C lanes conclude each step in its own iteration. The push
at step k takes its clock tau from step k's prepared rows.

A lane whose robot fell, or whose rollout raised, stops (XLA: its row of the vmapped
calls is still computed, and ignored); unused lanes (fewer rollouts than ``width``)
likewise. Lane results agree with ``mujoco_loop.rollout``: the C lanes run the same
generated functions on the same inputs as one robot, the vmapped XLA kernels round
differently from the single-robot ones (``tests/test_lockstep.py`` holds both), and a
lane's result does not depend on the other lanes.
"""

from __future__ import annotations

import operator
import time
from typing import Any, NamedTuple

import jax
import numpy as np

from safewbc_jax.control import metrics
from safewbc_jax.deploy.compiled import LaneState
from safewbc_jax.deploy.controller import Controller
from safewbc_jax.sim.loop import LaneControl, LaneStep, simulate
from safewbc_jax.sim.mujoco_loop import SimRobot


class RolloutTask(NamedTuple):
    """One rollout of a lockstep group: its ControllerParams, its push (``Push.single``,
    or None) and its initial velocity perturbation of the simulator (nv,) (or None)."""

    params: Any
    push: Any
    perturb_v: Any


class Outcome(NamedTuple):
    """A rollout's result: its metric columns, whether it fell and at which control step
    (-1: it did not); or, with ``columns`` None, why it has none (``error``)."""

    columns: dict | None
    fell: bool = False
    fell_step: int = -1
    error: str = ""

    @staticmethod
    def failed(reason: str) -> "Outcome":
        return Outcome(None, error=reason)


class Lockstep:
    """``width`` lanes of the ``CompiledStep`` of one started ``Controller`` (``leader``,
    which also checks each rollout's start) and its ``SimRobot``; ``run`` rolls out up to
    ``width`` rollouts at once, the lanes' control step ``CLanes`` or ``Lanes`` by the
    leader's engine. ``compile_s``: the seconds ``warm_up`` took (XLA: the vmapped step's
    compile)."""

    def __init__(self, leader: Controller, sim: SimRobot, width: int):
        if int(width) != width or width < 1:
            raise ValueError(f"lockstep width {width}: must be an integer >= 1")
        self.width = int(width)
        if leader.compiled is None:
            raise RuntimeError("Lockstep of a controller before its start(q, v)")
        self.leader, self.step = leader, leader.compiled
        self.lanes: list[LaneState] = [leader.lane.sibling() for _ in range(self.width)]
        self.sims = [sim.sibling() for _ in range(self.width)]
        prepare, conclude = self.step.prepare_fn, self.step.conclude_fn

        def step(fixed, state, flat, tally, prev_prep, prev_sol):
            # one call a control step: the last step's conclude and this step's prepare
            # (independent of each other; one XLA call costs less than two)
            return (*prepare(fixed, state, flat), *conclude(fixed, tally, prev_prep, prev_sol))

        self.vstep = jax.jit(jax.vmap(step))    # the XLA lanes' (traced at their first call)
        self.compile_s: float | None = None

    def warm_up(self) -> float:
        """Compile the vmapped step with one step of every lane at the stand."""
        t0 = time.perf_counter()
        self.run([None] * self.width, 1)
        self.compile_s = time.perf_counter() - t0
        return self.compile_s

    def run(self, tasks: list, n_steps: int) -> list:
        """Roll out ``tasks`` (each a ``RolloutTask``, or None to leave the lane at the stand
        with the leader's params) for ``n_steps`` control steps. Returns an ``Outcome`` per
        task: the finalized metric columns (``metrics.finalize``), or why it has none."""
        W, n = self.width, len(tasks)
        if n > W:
            raise ValueError(f"{n} rollouts for a lockstep of width {W}")
        lanes, sims = self.lanes, self.sims
        out: list = [None] * n
        live = np.zeros(W, bool)
        arrays: list = [None] * W       # each lane's flat (fixed, state, tally)
        for i in range(W):
            t = tasks[i] if i < n else None
            try:
                params, dv = (None, None) if t is None else (t.params, t.perturb_v)
                sims[i].reset(dv)
                q, v = sims[i].sm.to_controller(sims[i].d.qpos, sims[i].d.qvel)
                arrays[i] = self.leader.lane_start(q, v, params)
                live[i] = i < n
            except Exception as e:  # noqa: BLE001 - this rollout fails, the others run
                out[i] = Outcome.failed(f"{type(e).__name__}: {e}")
                arrays[i] = self.leader.lane_start(*self.leader.start_state)  # a valid row
                sims[i].reset()
            lanes[i].reset()
        pushes = [None if i >= n or tasks[i] is None else tasks[i].push for i in range(W)]
        control = (CLanes if self.step.engine == "c" else Lanes)(self, lanes, arrays)
        lay = self.step.layouts
        res = simulate(sims, control, n_steps, pushes, live)
        for i in range(n):
            if out[i] is not None:
                continue
            if res.failed[i] is not None:
                out[i] = Outcome.failed(res.failed[i])
                continue
            tally, state = lay.tally.unpack(control.tally[i]), lay.state.unpack(control.state[i])
            fell = bool(res.fell_step[i] >= 0)
            acc = jax.tree_util.tree_map(operator.itemgetter(i), res.plant)
            flat_cols = metrics.finalize(self.leader.scenario, tally.acc, acc, fell, state.gait)
            out[i] = Outcome(flat_cols, fell, int(res.fell_step[i]))
        return out


class Lanes(LaneControl):
    """The control step of a ``Lockstep``'s lanes (a ``loop.LaneControl``), one rollout each:
    ``CompiledStep.admit``, the one vmapped call a step (this step's prepare, the last
    step's conclude), ``CompiledStep.finish``. A step's record comes one step later
    (``concluded``); ``drain`` runs the last step's conclude. ``arrays``: each lane's flat
    (fixed, state, tally) at its start; ``state``, ``tally``: the lanes' flat vectors
    (W, .) as the steps go."""

    def __init__(self, lock: Lockstep, lanes: list[LaneState], arrays: list):
        super().__init__()
        self.lock, self.lanes, self.cs = lock, lanes, lock.step
        W = len(lanes)
        self.fixed, self.state, self.tally = (np.stack(a) for a in zip(*arrays))
        self.flat: np.ndarray | None = None
        self.prev_prep = np.zeros((W, self.cs.layouts.prep.size))
        self.prev_sol = np.tile(self.cs.no_solution, (W, 1))
        self.pending = None     # the lanes the last step's conclude is for
        # where tau sits in the flat Prepared vector: the push's clock, read from prepare's
        # output before that step's conclude has run (StepRecord.tau is Prepared.tau)
        self.tau_at = self.cs.tau_index

    def _call(self):
        return self.lock.vstep(self.fixed, self.state, self.flat, self.tally,
                               self.prev_prep, self.prev_sol)

    def _take(self, concluded, new_tally, packed_out):
        """The tally after a step's conclude (for the lanes it ran on), and its record."""
        self.tally = np.where(concluded[:, None], np.asarray(new_tally), self.tally)
        self.conclude(self.cs.unpack_record(np.asarray(packed_out))[0])

    def step(self, meas: list, live) -> LaneStep:
        t_in = time.perf_counter()
        lanes, W, cs = self.lanes, len(self.lanes), self.cs
        if self.flat is None:          # every lane's row, unused lanes' included
            rows = [cs.flat_measurement(m) for m in meas]
            if any(r is None for r in rows):
                raise RuntimeError("a simulator's measurement is no flat vector of the step")
            self.flat = np.stack(rows)  # type: ignore[arg-type]
        failed: dict[int, str] = {}
        live_ids = np.flatnonzero(live).tolist()
        fs, rs = cs.admit([lanes[i] for i in live_ids], [meas[i] for i in live_ids])
        reasons = dict(zip(live_ids, rs))
        for i, f in zip(live_ids, fs):
            if f is None:     # from a simulator this cannot happen: a lane fault
                failed[i] = f"measurement refused: {reasons[i]}"
            else:
                self.flat[i] = f
        live = live.copy()
        live[list(failed)] = False
        new_state, prep, packed, new_tally, packed_out = self._call()
        prep_np, packed = np.asarray(prep), np.asarray(packed)
        self.state = np.where(live[:, None], np.asarray(new_state), self.state)
        if self.pending is not None:
            self._take(self.pending, new_tally, packed_out)
        sols = np.tile(cs.no_solution, (W, 1))
        motor = {}
        idx = np.flatnonzero(live)
        ids = idx.tolist()
        every = idx.size == W
        try:
            if idx.size:
                got, sols[idx] = cs.finish(
                    [lanes[i] for i in idx], prep_np if every else prep_np[idx],
                    packed if every else packed[idx], [reasons[i] for i in ids],
                    [meas[i].t for i in ids], t_in)
                motor = {i: c.motor for i, c in zip(idx.tolist(), got)}
        except Exception as e:  # noqa: BLE001 - these rollouts fail, with the reason
            for i in idx.tolist():
                failed[i], live[i] = f"{type(e).__name__}: {e}", False
        self.prev_prep, self.prev_sol, self.pending = prep_np, sols, live
        return LaneStep(motor, prep_np[:, self.tau_at], failed)

    def drain(self) -> list:
        if self.pending is not None:     # the last step's conclude (the prepare's rows unused)
            *_, new_tally, packed_out = self._call()
            self._take(self.pending, new_tally, packed_out)
            self.pending = None
        return self.concluded()


class CLanes(LaneControl):
    """The control step of a C-engine ``Lockstep``'s lanes (a ``loop.LaneControl``), one
    rollout each: the measurement checks of all lanes at once (``CompiledStep.admit``),
    then each live lane's step as one robot's ``Controller.step`` runs it
    (``CompiledStep.prepare_lane`` into the lane's own output arrays, then
    ``CompiledStep.solve_lane``: PIQP and the generated acceptance, another solver's
    ``solve``, or the torque held where the measurement is refused)
    and the lane's generated ``conclude`` in the same iteration. The step's record
    (leading axis W) goes to ``conclude`` at once; the rows of lanes that did not step
    keep their last values, which the plant metrics do not read (``live``). An exception
    in a lane's step stops that lane alone, with the reason. ``arrays``: each lane's flat
    (fixed, state, tally) at its start; ``state``, ``tally``: the lanes' flat vectors
    (W, .) as the steps go."""

    def __init__(self, lock: Lockstep, lanes: list[LaneState], arrays: list):
        super().__init__()
        self.lanes, self.cs = lanes, lock.step
        self.fixed, self.state, self.tally = (np.stack(a) for a in zip(*arrays))
        self.records: np.ndarray | None = None    # (W, .) the packed records, at the first
        self.ok_at, self.tau_at = self.cs.ok_index, self.cs.tau_index

    def _prepare(self, i: int, flat, reason: str, meas) -> tuple:
        """Lane i's prepare from its admitted measurement: (its Prepared, packed QPs, their
        views, the reason it is refused or "ok", the time it started)."""
        cs, lane = self.cs, self.lanes[i]
        t_step = time.perf_counter()
        new, prep, packed, views = cs.prepare_lane(lane, self.fixed[i], self.state[i], flat)
        self.state[i] = new
        if reason == "ok" and not prep[self.ok_at]:    # the step's state tests
            reason = cs.refused(lane, meas)
        return prep, packed, views, reason, t_step

    def _finish(self, i: int, prepared: tuple, meas, t_in: float):
        """Lane i's step after its prepare: (its motor torques, tau, packed record)."""
        cs, lane = self.cs, self.lanes[i]
        prep, packed, views, reason, t_step = prepared
        cmd, sol, _ = cs.solve_lane(lane, reason, packed, views, meas.t, t_in, t_step)
        self.tally[i], record = cs.conclude(self.fixed[i], self.tally[i], prep, sol)
        return cmd.motor, float(prep[self.tau_at]), record

    def step(self, meas: list, live) -> LaneStep:
        t_in = time.perf_counter()
        W = len(self.lanes)
        failed: dict[int, str] = {}
        motor: dict = {}
        tau = np.zeros(W)
        live_ids = np.flatnonzero(live).tolist()
        fs, rs = self.cs.admit([self.lanes[i] for i in live_ids], [meas[i] for i in live_ids])
        # every lane's prepare, then every lane's solve and conclude: the generated step's
        # code, constants and work buffers stay in cache from one lane to the next
        prepared = {}
        for i, flat, reason in zip(live_ids, fs, rs):
            if flat is None:     # from a simulator this cannot happen: a lane fault
                failed[i] = f"measurement refused: {reason}"
                continue
            try:
                prepared[i] = self._prepare(i, flat, reason, meas[i])
            except Exception as e:  # noqa: BLE001 - this rollout fails, with the reason
                failed[i] = f"{type(e).__name__}: {e}"
        for i, got in prepared.items():
            try:
                motor[i], tau[i], record = self._finish(i, got, meas[i], t_in)
            except Exception as e:  # noqa: BLE001 - this rollout fails, with the reason
                failed[i] = f"{type(e).__name__}: {e}"
                continue
            if self.records is None:
                self.records = np.zeros((W, record.size))
            self.records[i] = record
        if self.records is not None:
            self.conclude(self.cs.unpack_record(self.records.copy())[0])
        return LaneStep(motor, tau, failed)
