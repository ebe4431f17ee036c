"""Several deployment loops in lockstep on one core: the ``mujoco`` sweep engine's worker.

``mujoco_loop.rollout`` runs one robot: per control step one call of the deployed jitted
step, whose cost on a CPU is mostly XLA's per-kernel runtime, not arithmetic. A worker
that runs ``width`` rollouts side by side pays that runtime once per step for all of
them: the same jitted functions of ``deploy.Controller`` (its unjitted ``prepare`` and
``conclude``), vmapped over the lanes. Each lane is its own ``Controller``
(``Controller.lane``: its own counters, state and PIQP solvers) and its own ``SimRobot``
(``SimRobot.sibling``: one MjModel, one MjData per lane). The host side of the step runs
for all lanes at once where it is plain array arithmetic (``Controller.admit_lanes``: the
measurement checks; ``Controller.finish_lanes``: the acceptance, X = x0 + N u, the
held-torque rule, the motor map: the code a single robot's step runs with one lane), with
PIQP still one solve per lane by the lane's own solver (and, where a lane's QP as posed
is not accepted, its relaxed QP likewise); a lane whose measurement is refused holds its
torque for that step. So a lane runs what ``mujoco_loop.rollout`` runs, step by step:

    measurement -> admit -> [prepare, vmapped] -> finish (PIQP per lane)
    -> [conclude, vmapped] -> push -> SimRobot.advance -> plant metrics -> fall test

with one XLA call a step: step k's conclude runs vmapped in the same call as step k+1's
prepare (the two do not depend on each other; one call costs less than two), so step k's
metrics are accumulated one call later (a last call after the loop concludes the last
step), and the push at step k takes its clock tau from step k's prepared rows.

A lane whose robot fell, or whose rollout raised, stops (its row of the vmapped calls
is still computed, and ignored); unused lanes (fewer rollouts than ``width``) likewise.
Lane results agree with ``mujoco_loop.rollout`` to rounding (the vmapped XLA kernels are
not the single-robot ones; ``tests/test_lockstep.py`` holds them to it, and
``finish_lanes`` to ``_finish``), and a lane's result does not depend on the other lanes.
"""

from __future__ import annotations

import time

import jax
import numpy as np

from safewbc_jax import metrics
from safewbc_jax.control_step import fallen
from safewbc_jax.deploy import Controller
from safewbc_jax.modelinfo import loop_residual
from safewbc_jax.push import force_at
from safewbc_jax.sim.mujoco_loop import SimRobot


class Lockstep:
    """``width`` lanes of one started ``Controller`` (``leader``) and its ``SimRobot``;
    ``run`` rolls out up to ``width`` rollouts at once. ``compile_s``: the seconds
    ``warm_up`` took (the vmapped step's compile)."""

    def __init__(self, leader: Controller, sim: SimRobot, width: int):
        if int(width) != width or width < 1:
            raise ValueError(f"lockstep width {width}: must be an integer >= 1")
        self.width = int(width)
        self.leader, self.sim = leader, sim
        self.lanes = [leader.lane() for _ in range(self.width)]
        self.sims = [sim.sibling() for _ in range(self.width)]
        prepare, conclude = leader.step_functions()

        def step(fixed, state, flat, tally, prev_prep, prev_sol):
            # one call a control step: the last step's conclude and this step's prepare
            # (independent of each other; one XLA call costs less than two)
            return (*prepare(fixed, state, flat), *conclude(fixed, tally, prev_prep, prev_sol))

        self._vstep = jax.jit(jax.vmap(step))
        # where tau sits in the flat Prepared vector: the push's clock, read from prepare's
        # output before that step's conclude has run (StepRecord.tau is Prepared.tau)
        self._prep_size, self._tau_at = leader.prepared_layout()
        self.compile_s = None

    def warm_up(self) -> float:
        """Compile the vmapped step with one step of every lane at the stand."""
        t0 = time.perf_counter()
        self.run([None] * self.width, 1)
        self.compile_s = time.perf_counter() - t0
        return self.compile_s

    def _no_previous_step(self, rows: int):
        """The conclude inputs of the one call a step for the step before step 0, where
        there is none (its results are not used): (prepared rows, solve records)."""
        return (np.zeros((rows, self._prep_size)),
                np.tile(self.leader.no_solution(), (rows, 1)))

    def _concluded(self, pending, tally, plant, new_tally, packed_out, sole0):
        """The tally after a step's conclude (for the lanes it ran on) and the plant
        metrics of that step's physics, with the step's record from the conclude."""
        concluded, stepped, soles, loop_res, legs = pending
        tally = np.where(concluded[:, None], np.asarray(new_tally), tally)
        rec = self.leader.unpack_record(np.asarray(packed_out))[0]
        return tally, metrics.plant_accumulate(plant, stepped, rec, soles, sole0, loop_res, legs)

    def run(self, tasks: list, n_steps: int) -> list:
        """Roll out ``tasks`` (each (params, push or None, perturb_v or None), or None to
        leave the lane at the stand with the leader's params) for ``n_steps`` control
        steps. Returns, per task, ("done", fell, fell step or -1, the finalized metric
        columns, ``metrics.finalize``) or ("failed", reason)."""
        W, n = self.width, len(tasks)
        if n > W:
            raise ValueError(f"{n} rollouts for a lockstep of width {W}")
        lanes, sims = self.lanes, self.sims
        out = [None] * n
        live = np.zeros(W, bool)
        meas = [None] * W
        for i in range(W):
            t = tasks[i] if i < n else None
            try:
                params, dv = (None, None) if t is None else (t[0], t[2])
                sims[i].reset(dv)
                lanes[i].restart(*sims[i].sm.to_controller(sims[i].d.qpos, sims[i].d.qvel),
                                 self.leader.params if params is None else params)
                meas[i] = sims[i].sense(0.0)[0]
                live[i] = i < n
            except Exception as e:  # noqa: BLE001 - this rollout fails, the others run
                out[i] = ("failed", f"{type(e).__name__}: {e}")
                lanes[i].restart(*self.leader.start_state)   # a valid row for the vmapped calls
                sims[i].reset()
                meas[i] = sims[i].sense(0.0)[0]
        fixed, state, tally = (np.stack(a) for a in zip(*[lane.flat_arrays() for lane in lanes]))
        flat = np.stack([lane.flat_measurement(m) for lane, m in zip(lanes, meas)])
        plant = jax.tree_util.tree_map(lambda *a: np.stack(a),
                                       *[metrics.plant_init() for _ in range(W)])
        sole0 = np.stack([s.sole0 for s in sims])
        sole_ids, loop_pairs = self.sim.sole_ids, self.sim.loop_pairs
        legs = np.zeros(W, bool)
        fell_step = np.full(W, -1)
        pushes = [None if i >= n or tasks[i] is None else tasks[i][1] for i in range(W)]
        no_sol = self.leader.no_solution()
        prev_prep, prev_sol = self._no_previous_step(W)
        pending = None      # the last step's (conclude mask, plant mask, soles, loop res, legs)
        for k in range(n_steps):
            if not live.any():
                break
            t_in = time.perf_counter()
            idx = np.flatnonzero(live).tolist()
            fs, rs = Controller.admit_lanes([lanes[i] for i in idx], [meas[i] for i in idx])
            reasons = dict(zip(idx, rs))
            for i, f in zip(idx, fs):
                if f is None:     # from a simulator this cannot happen: a lane fault
                    out[i], live[i] = ("failed", f"measurement refused: {reasons[i]}"), False
                else:
                    flat[i] = f
            new_state, prep, packed, new_tally, packed_out = self._vstep(
                fixed, state, flat, tally, prev_prep, prev_sol)
            prep_np, packed = np.asarray(prep), np.asarray(packed)
            state = np.where(live[:, None], np.asarray(new_state), state)
            if pending is not None:
                tally, plant = self._concluded(pending, tally, plant, new_tally, packed_out, sole0)
            sols = np.tile(no_sol, (W, 1))
            cmds = {}
            idx = np.flatnonzero(live)
            every = idx.size == W
            try:
                if idx.size:
                    got, sols[idx] = Controller.finish_lanes(
                        [lanes[i] for i in idx], prep_np if every else prep_np[idx],
                        packed if every else packed[idx], [reasons[i] for i in idx],
                        [meas[i].t for i in idx], t_in)
                    cmds = dict(zip(idx.tolist(), got))
            except Exception as e:  # noqa: BLE001 - these rollouts fail, with the reason
                for i in idx.tolist():
                    out[i], live[i] = ("failed", f"{type(e).__name__}: {e}"), False
            prev_prep, prev_sol, concluded = prep_np, sols, live.copy()
            tau = prep_np[:, self._tau_at]
            for i in np.flatnonzero(live):
                try:
                    p = pushes[i]
                    force = force_at(p, float(tau[i])) if p is not None else 0.0
                    meas[i], legs[i], _ = sims[i].advance(cmds[i].motor, force, k, False)
                except Exception as e:  # noqa: BLE001
                    out[i], live[i] = ("failed", f"{type(e).__name__}: {e}"), False
            sites = np.stack([s.d.site_xpos for s in sims])
            pending = (concluded, live.copy(), sites[:, sole_ids],
                       loop_residual(sites, loop_pairs), legs.copy())
            idx = np.flatnonzero(live)
            if idx.size:
                down = idx[fallen(np.stack([meas[i].q for i in idx]),
                                  np.stack([meas[i].v for i in idx]))]
                fell_step[down], live[down] = k, False
        if pending is not None:     # the last step's conclude (the prepare's rows unused)
            *_, new_tally, packed_out = self._vstep(fixed, state, flat, tally, prev_prep,
                                                    prev_sol)
            tally, plant = self._concluded(pending, tally, plant, new_tally, packed_out, sole0)
        for i in range(n):
            if out[i] is not None:
                continue
            lane = lanes[i]
            lane.set_flat_arrays(state[i], tally[i])
            fell = bool(fell_step[i] >= 0)
            acc = jax.tree_util.tree_map(lambda a: a[i], plant)
            flat_cols = metrics.finalize(lane.tally.acc, acc, fell,
                                         lane.state.gait if lane.walking else None)
            out[i] = ("done", fell, int(fell_step[i]), flat_cols)
        return out
