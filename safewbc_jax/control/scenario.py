"""A scenario: the tasks a controller tracks and the safe sets it keeps, as data.

    Scenario(name, tasks=(Task(...), ...), safe_sets=(SafeSet(...), ...), duration=8.0)

Its default ``ControllerParams`` come from the tasks (K_p, K_d, W) and the safe sets (poles,
threshold); nothing else has to be edited to add a task or a safe set
(``with_safe_sets`` adds them to an existing scenario). A domain-driven scenario
(walking) also has a ``gait`` (the protocol of ``control.gait``) that advances its domains
from the measurement; the double-support scenarios have none. A scenario may carry a
``push`` (``control.push.Push``), applied unless the run gives its own.

Before the motion (tau < 0) the robot stands for ``settle`` seconds while every
time-based reference is blended from the measured start value to y^d(0) in ``blend``
seconds (quintic), so the motion starts from rest on its own reference; the paper's tau
counts from the start of the motion.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.control import references
from safewbc_jax.control.params import ControllerParams, make_params
from safewbc_jax.control.push import Push
from safewbc_jax.control.safesets import SafeSet, SafeSetError
from safewbc_jax.control.tasks import Task
from safewbc_jax.model import digit


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["origin", "arm0", "y0", "settle", "gait"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Start:
    """The references' start data, measured at the start pose (``control_step.start_data``):
    what a task's ``reference(tau, start)`` and ``planned(model, tau, start, q, v, domain)``
    read. ``origin`` (3,): the stance frame's origin, the soles' midpoint on the floor
    (z = 0); ``arm0`` (8,): the arm joint angles to hold (``outputs.ARM_JOINTS``); ``y0``:
    {output name: its value at the start}; ``settle``: the seconds of standing before the
    motion (the run's; None until it is set); ``gait``: a gait's
    own start data (``walking.WalkStart``), None without a gait."""

    origin: jax.Array
    arm0: jax.Array
    y0: dict = dataclasses.field(default_factory=dict)
    settle: jax.Array | None = None
    gait: Any = None


@dataclasses.dataclass(frozen=True)
class Scenario:
    name: str
    tasks: tuple
    safe_sets: tuple = ()
    duration: float = 8.0     # default length of the motion (s)
    settle: float = 1.5
    blend: float = 1.0
    in_contact: tuple = (1.0, 1.0)
    gait: Any | None = None
    scalars: tuple = ()       # (name, value) overrides of ControllerParams' scalars
    push: Any | None = None   # the push (control.push.Push) of every simulated run, unless
                              # the run sets its own; None: no push

    def __post_init__(self):
        object.__setattr__(self, "tasks", tuple(self.tasks))
        if self.push is not None:   # plain floats: a scenario is hashed (a static argument)
            f, at, dur = self.push
            object.__setattr__(self, "push", Push(tuple(float(x) for x in np.ravel(f)),
                                                  float(at), float(dur)))
        object.__setattr__(self, "safe_sets", tuple(self.safe_sets))
        for t in self.tasks:
            if not isinstance(t, Task):
                raise TypeError(f"scenario {self.name!r}: {t!r} is not a Task")
        for s in self.safe_sets:
            if not isinstance(s, SafeSet):
                raise SafeSetError(f"scenario {self.name!r}: {s!r} is not a SafeSet")
        for kind, names in (("task", [t.name for t in self.tasks]),
                            ("safe set", [s.name for s in self.safe_sets])):
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                err = SafeSetError if kind == "safe set" else ValueError
                raise err(f"scenario {self.name!r}: {kind} names repeated: {dup}")

    # -- what the controller iterates over
    @property
    def outputs(self) -> tuple:
        return tuple(t.output for t in self.tasks)

    @property
    def barriers(self) -> tuple:
        """The enforced safe sets (one A-ECBF row each)."""
        return tuple(s for s in self.safe_sets if s.enforce)

    @property
    def monitors(self) -> tuple:
        """Safe sets evaluated for the metrics and plots only."""
        return tuple(s for s in self.safe_sets if not s.enforce)

    @property
    def walking(self) -> bool:
        return self.gait is not None

    def task(self, name) -> Task:
        return next(t for t in self.tasks if t.name == name)

    def output(self, name):
        return self.task(name).output

    def default_params(self) -> ControllerParams:
        return make_params({t.name: t.params_entry() for t in self.tasks},
                           {s.name: (s.poles, s.threshold) for s in self.safe_sets},
                           **dict(self.scalars))

    # -- composition
    def with_safe_sets(self, *safe_sets: SafeSet) -> "Scenario":
        """This scenario with more safe sets (names must be new); itself when none (a
        scenario is a compile key by identity)."""
        if not safe_sets:
            return self
        return dataclasses.replace(self, safe_sets=self.safe_sets + tuple(safe_sets))

    def without_barriers(self) -> "Scenario":
        """Every safe set monitored only."""
        return dataclasses.replace(self, safe_sets=tuple(s.monitored() for s in self.safe_sets))

    def theorem_domain(self, model, safe_set: SafeSet, q):
        """The domain where Theorem 1 is checked for ``safe_set`` from the start pose q:
        its own ``check_domain``; else, for a barrier active only in some domains of a
        gait, where the gait's first step begins; else the start state's (a gait's
        standing domain; None without a gait)."""
        if safe_set.check_domain is not None:
            return safe_set.check_domain(model, q)
        if self.gait is None:
            return None
        if safe_set.active is not None:
            return self.gait.first_domain(model, q)
        return self.gait.start_domain(model, q)

    # -- references
    def desired_at(self, model, tau, start, q, v, domain):
        """{name: (y^d, y^d_dot, y^d_ddot)} of every task at this control step."""
        out = {}
        for t in self.tasks:
            if t.planned is not None:
                out[t.name] = t.planned(model, tau, start, q, v, domain)
            else:
                out[t.name] = self._timed(t, tau, start)
        return out

    def _timed(self, task: Task, tau, start):
        """A time-based reference with its AD derivatives, with the settle blend for tau < 0."""
        reference = task.reference
        assert reference is not None       # a timed task (not planned)

        def settle_ref(s):
            y0 = start.y0[task.name]
            target = reference(jnp.zeros_like(s), start)
            w = references.smoothstep5((s + self.settle) / self.blend)
            return y0 + (target - y0) * w

        motion = references.with_derivatives(lambda s: reference(s, start),
                                              jnp.maximum(tau, 0.0))
        settle = references.with_derivatives(settle_ref, jnp.minimum(tau, 0.0))
        return tuple(jnp.where(tau < 0, s, m) for s, m in zip(settle, motion))

    def masks(self, domain) -> dict:
        """{name: (dim,) 0/1} of the tasks with a domain mask (walking); {} without a domain."""
        if domain is None:
            return {}
        return {t.name: t.mask(domain) for t in self.tasks if t.mask is not None}


def start_state(model, q) -> Start:
    """Start data measured on the robot at the beginning of the run: the stance frame
    origin (midpoint of the soles on the ground) and the arm posture to hold (the
    outputs' start values y0 are added by ``control_step.start_data``)."""
    from safewbc_jax.control import outputs
    from safewbc_jax.model import robot

    pl, _ = robot.frame_pose(model, q, digit.LEFT_SOLE)
    pr, _ = robot.frame_pose(model, q, digit.RIGHT_SOLE)
    origin = 0.5 * (pl + pr)
    arm0 = q[np.array([model.joint_qadr(j) for j in outputs.ARM_JOINTS])]
    return Start(origin=origin.at[2].set(0.0), arm0=arm0)
