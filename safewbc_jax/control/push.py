"""A push on the robot's base, defined once (a force on the base body, applied through
MuJoCo's and MJX's ``xfrc_applied``), with its defaults.

A push is a constant force (world frame, N) on the base body from ``at`` seconds after the
motion starts (tau = at) for ``duration`` seconds. The default start, 2.55 s, is 0.05 s
into the fourth step of the default walk, a right-stance step, where a push to the right
(-y) carries the CoM over the stance foot and the planner pulls the left swing foot in
towards it (the paper's collision case).
"""

from __future__ import annotations

from types import ModuleType
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

PUSH_AT = 2.55     # s after the motion starts
PUSH_FOR = 0.15    # s


class Push(NamedTuple):
    """A push on the base, or one per rollout with a leading batch axis B on every field.

    Attributes:
        force: (3,) or (B, 3) constant force on the base body, world frame, N.
        at: the time it starts, s after the motion starts; a float for one push, (B,)
            in a batch.
        duration: how long it lasts, s; a float for one push, (B,) in a batch.
    """

    force: np.ndarray
    at: np.ndarray | float          # a float for one push (``single``)
    duration: np.ndarray | float

    @staticmethod
    def none(batch: int) -> Push:
        """No push, for each rollout of a batch.

        Args:
            batch: the batch size B.

        Returns:
            A batched Push of zero force and zero duration.
        """
        return Push(np.zeros((batch, 3)), np.zeros(batch), np.zeros(batch))

    @staticmethod
    def single(force: ArrayLike, at: float = PUSH_AT, duration: float = PUSH_FOR) -> Push:
        """One push.

        Args:
            force: (3,) force on the base body, world frame, N.
            at: its start, s after the motion starts (default ``PUSH_AT``).
            duration: how long it lasts, s (default ``PUSH_FOR``).

        Returns:
            The push, its times as float64 scalars.
        """
        return Push(np.asarray(force, float), np.float64(at), np.float64(duration))


def force_at(push: Push, tau: Any, xp: ModuleType = np) -> Any:
    """The push force at motion time ``tau``: ``force`` while at <= tau < at + duration,
    else zero.

    Args:
        push: one push (no batch axis: ``vmap`` it over a batch).
        tau: the motion time, s.
        xp: the array module to compute with, ``numpy`` or ``jax.numpy``.

    Returns:
        The (3,) force, N, an array of ``xp``.
    """
    on = (tau >= push.at) & (tau < push.at + push.duration)
    return xp.where(on, push.force, 0.0)
