"""The C MuJoCo simulation loop, for one robot or several side by side.

Each control step, for every lane (a robot) still running:

    measurement -> the lanes' control step (``LaneControl.step``) -> push (``push.force_at``
    at the step's tau) -> physics (``SimRobot.advance``) -> the plant metrics
    (``metrics.plant_accumulate``, once the step's record has come) -> the fall test
    (``control_step.fallen``)

The control step is the lanes' business (a ``LaneControl``): one deployed ``Controller``
(``mujoco_loop.OneRobot``) or the lanes of one compiled step, vmapped (``lockstep.Lanes``).
A step's record (the
``StepRecord`` the plant metrics read the domain from) may come in the same loop iteration
(one robot) or in the next one (the lockstep concludes step k in the call that prepares
step k + 1): the loop keeps each step's physics until its record has come, in order. The
MJX rollout (``batch.rollout``) scans the same definitions of a step: ``force_at``,
``plant_accumulate``, ``fallen``, ``modelinfo.loop_residual``.
"""

from __future__ import annotations

import collections
from typing import Callable, NamedTuple

import jax
import numpy as np

from safewbc_jax.control import metrics
from safewbc_jax.control.step import fallen
from safewbc_jax.model.modelinfo import loop_residual
from safewbc_jax.control.push import force_at


class LaneStep(NamedTuple):
    """What a control step hands the loop: ``motor`` {lane: motor torques} for the lanes
    that go on to the physics; ``tau`` (W,) each lane's tau (the push's clock); ``failed``
    {lane: reason} for the lanes that stop here."""

    motor: dict
    tau: np.ndarray
    failed: dict


class LaneControl:
    """The control step of W lanes (a subclass gives ``step``). A step's record goes to
    ``conclude`` when it comes; the loop takes them with ``concluded``."""

    def __init__(self):
        self._ready = []

    def step(self, meas: list, live: np.ndarray) -> LaneStep:
        """One control step of the ``live`` lanes from their measurements."""
        raise NotImplementedError

    def conclude(self, record) -> None:
        """A step's record has come: a ``StepRecord`` of the W lanes (leading axis W, or
        scalars where W = 1), in step order."""
        self._ready.append(record)

    def concluded(self) -> list:
        """The records that came since the last call, oldest first."""
        out, self._ready = self._ready, []
        return out

    def drain(self) -> list:
        """After the last step: the records still to come (``concluded``)."""
        return self.concluded()


class Outcome(NamedTuple):
    """A loop's result per lane: the step it fell at (-1: it did not), why it stopped
    early (None: it did not), the plant metrics (``metrics.PlantAcc``, leading axis W)."""

    fell_step: np.ndarray
    failed: list
    plant: metrics.PlantAcc


def simulate(sims: list, control: LaneControl, n_steps: int, pushes: list, live,
             on_step: Callable | None = None, catch: bool = True) -> Outcome:
    """Run W lanes (``sims``: ``SimRobot``, each at its start state; ``control``: their
    control step, started) for ``n_steps`` control steps, or until none is running.
    ``pushes[i]``: lane i's ``Push`` or None; ``live`` (W,): the lanes that run.
    ``on_step(k, record, legs, loop_residual)``, when given, runs once each step's record
    has come, with that step's physics outcome of every lane ((W,) arrays); the lanes'
    MjData still hold that step's state when the record comes in the same iteration. With
    ``catch``, an exception in a lane's physics stops that lane with its reason; without,
    it propagates (one robot)."""
    W = len(sims)
    live = np.array(live, bool)
    failed: list = [None] * W
    meas = [s.sense(0.0)[0] for s in sims]
    plant = jax.tree_util.tree_map(lambda *a: np.stack(a), *[metrics.plant_init()] * W)
    sole0 = np.stack([s.sole0 for s in sims])
    sole_ids, pairs = sims[0].sole_ids, sims[0].loop_pairs
    legs = np.zeros(W, bool)
    fell_step = np.full(W, -1)
    # (k, physics) of the steps whose record has not come
    waiting: collections.deque = collections.deque()

    def accumulate(plant, rec):
        k, (stepped, soles, loop_res, legs_k) = waiting.popleft()
        if on_step is not None:
            on_step(k, rec, legs_k, loop_res)
        return metrics.plant_accumulate(plant, stepped, rec, soles, sole0, loop_res, legs_k)

    for k in range(n_steps):
        if not live.any():
            break
        out = control.step(meas, live)
        for i, reason in out.failed.items():
            failed[i], live[i] = reason, False
        for i in np.flatnonzero(live).tolist():
            try:
                p = pushes[i]
                force = force_at(p, float(out.tau[i])) if p is not None else 0.0
                meas[i], legs[i] = sims[i].advance(out.motor[i], force, k)
            except Exception as e:  # noqa: BLE001 - this lane stops, with the reason
                if not catch:
                    raise
                failed[i], live[i] = f"{type(e).__name__}: {e}", False
        sites = np.stack([s.d.site_xpos for s in sims])
        waiting.append((k, (live.copy(), sites[:, sole_ids], loop_residual(sites, pairs),
                            legs.copy())))
        for rec in control.concluded():
            plant = accumulate(plant, rec)
        idx = np.flatnonzero(live)
        if idx.size:
            down = idx[fallen(np.stack([meas[i].q for i in idx]),
                              np.stack([meas[i].v for i in idx]))]
            fell_step[down], live[down] = k, False
    for rec in control.drain():
        plant = accumulate(plant, rec)
    return Outcome(fell_step, failed, plant)
