"""A push on the robot's base: the one definition every loop applies (the MuJoCo loop on
``xfrc_applied`` of the base body, the batched rollouts on MJX's), with its defaults.

A push is a constant force (world frame, N) on the base body from ``at`` seconds after the
motion starts (tau = at) for ``duration`` seconds. The default start, 2.55 s, is 0.05 s
into the fourth step of the default walk, a right-stance step, where a push to the right
(-y) carries the CoM over the stance foot and the planner pulls the left swing foot in
towards it (the paper's collision case).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

PUSH_AT = 2.55     # s after the motion starts
PUSH_FOR = 0.15    # s


class Push(NamedTuple):
    """force (..., 3) N, at (...) s after the motion starts, duration (...) s; a leading
    batch axis in the batched path."""

    force: np.ndarray
    at: np.ndarray | float          # a float for one push (``single``)
    duration: np.ndarray | float

    @staticmethod
    def none(batch: int) -> "Push":
        return Push(np.zeros((batch, 3)), np.zeros(batch), np.zeros(batch))

    @staticmethod
    def single(force, at: float = PUSH_AT, duration: float = PUSH_FOR) -> "Push":
        return Push(np.asarray(force, float), np.float64(at), np.float64(duration))


def force_at(push: Push, tau, xp=np):
    """The push force (3,) at motion time tau: ``force`` while at <= tau < at + duration,
    else zero."""
    on = (tau >= push.at) & (tau < push.at + push.duration)
    return xp.where(on, push.force, 0.0)
