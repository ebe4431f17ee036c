"""The paper's double-support scenarios: squat, bow, arms (section "Simulation and
Experimental Results").

A scenario is static data: its outputs, the barriers it enforces, the barriers it only
monitors, its reference y^d(tau) and its default parameters. Before the motion (tau < 0)
the robot stands for ``settle`` seconds while every reference is blended from the measured
start value to y^d(0) in ``blend`` seconds (quintic), so the motion starts from rest on
its own reference; the paper's tau counts from the start of the motion.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax.numpy as jnp
import numpy as np

from safewbc_jax import outputs, references
from safewbc_jax.params import ControllerParams, make_params

# Threshold of the arm barrier h = -p_z - c (m). The paper's c = 0.195 refers to its own
# torso base frame; in this model's base frame (at hip height) the fists hang at
# p_z = -0.10 m, where c = 0.195 would make the start unsafe (Theorem 1 then does not
# apply). c = 0.05 keeps the paper's situation: the start is safe by 5 cm, and the commanded
# arm motion lifts the fists to p_z = +0.05 m, 10 cm into the unsafe side.
ARM_THRESHOLD = 0.05
ARM_POLES = (10.0, 10.0)


@dataclasses.dataclass(frozen=True)
class Scenario:
    name: str
    outputs: tuple
    barriers: tuple          # enforced A-ECBFs (dropped by --no-barrier)
    monitors: tuple          # safe sets evaluated for the metrics and plots only
    reference: Callable      # (tau, start) -> {output name: y^d(tau)}
    default_params: Callable[[], ControllerParams]
    duration: float          # default length of the motion (s)
    settle: float = 1.5
    blend: float = 1.0
    in_contact: tuple = (1.0, 1.0)
    # Hooks of domain-driven scenarios (walking); None for the double-support ones.
    desired_fn: Callable | None = None    # (model, tau, start, q, v, domain) -> like desired
    weight_mask: Callable | None = None   # domain -> {output name: (dim,) 0/1}
    passive_actuators: Callable | None = None  # (model, domain) -> (nu,) 1 = zero torque

    def output(self, name):
        return next(o for o in self.outputs if o.name == name)

    def desired_at(self, model, tau, start, q, v, domain):
        """References of this control step (walking plans them from the state)."""
        if self.desired_fn is not None:
            return self.desired_fn(model, tau, start, q, v, domain)
        return self.desired(tau, start)

    def desired(self, tau, start):
        """{name: (y^d, y^d_dot, y^d_ddot)} at tau, with the settle blend for tau < 0."""
        out = {}
        for o in self.outputs:
            def ref(s, name=o.name):
                return self.reference(s, start)[name]

            def settle_ref(s, name=o.name):
                y0 = start["y0"][name]
                target = ref(jnp.zeros_like(s))
                w = references.smoothstep5((s + self.settle) / self.blend)
                return y0 + (target - y0) * w

            motion = references.with_derivatives(ref, jnp.maximum(tau, 0.0))
            settle = references.with_derivatives(settle_ref, jnp.minimum(tau, 0.0))
            out[o.name] = tuple(jnp.where(tau < 0, s, m) for s, m in zip(settle, motion))
        return out


def _double_support_outputs():
    return (outputs.CoMPosition(), outputs.TorsoOrientation(),
            outputs.JointPositions(name="arms", joints=outputs.ARM_JOINTS))


def _default_params(barrier_names=()):
    return make_params(
        {"com": (3, [100.0, 100.0, 100.0], [20.0, 20.0, 20.0], [100.0, 100.0, 100.0]),
         "torso": (3, 100.0, 20.0, 10.0),
         "arms": (8, 900.0, 60.0, 1.0)},  # stiff enough to beat the joints' friction loss
        {n: (ARM_POLES, ARM_THRESHOLD) for n in barrier_names})


def _squat_reference(tau, start):
    com = references.squat_com(tau)
    return {"com": start["origin"] + com,
            "torso": jnp.zeros(3) + 0.0 * tau, "arms": start["arm0"] + 0.0 * tau}


def _bow_reference(tau, start):
    return {"com": start["origin"] + jnp.asarray(references.BOW_COM) + 0.0 * tau,
            "torso": references.bow_torso(tau), "arms": start["arm0"] + 0.0 * tau}


def _arms_reference(tau, start):
    com0 = start["y0"]["com"]
    return {"com": jnp.array([start["origin"][0], start["origin"][1], com0[2]]) + 0.0 * tau,
            "torso": jnp.zeros(3) + 0.0 * tau,
            "arms": start["arm0"] + references.arm_offsets(tau)}


@dataclasses.dataclass(frozen=True)
class SafeSet:
    """A safe set h >= 0 whose threshold is a parameter (``ControllerParams.threshold``):
    ``h(model, q, threshold)`` (relative degree 2) or ``h(model, q, v, threshold)``
    (relative degree 1). Enforced through ``barriers.aecbf_row``."""

    name: str
    h: Callable
    relative_degree: int = 2
    active: Callable | None = None   # domain -> 1.0 where the barrier applies (None: always)

    def h_fn(self, model, threshold, domain=None):
        """The barrier as ``barriers`` takes it: h_fn(q) or h_fn(q, v)."""
        if self.relative_degree == 2:
            return lambda q: self.h(model, q, threshold, domain)
        return lambda q, v: self.h(model, q, v, threshold, domain)

    def is_active(self, domain):
        return 1.0 if self.active is None else self.active(domain)


def _fist_height(side):
    def h(model, q, threshold, domain=None):
        from safewbc_jax import robot

        return -robot.frame_position_in(model, q, f"{side}-fist", "torso")[2] - threshold
    return h


def fist_barrier(side):
    """Paper, arm task: h(q) = -p_z(q) - c >= 0, p_z the fist's height in the torso base
    frame."""
    return SafeSet(f"{side}_fist", _fist_height(side), 2)


SCENARIOS = {
    "squat": Scenario("squat", _double_support_outputs(), (), (), _squat_reference,
                      _default_params, duration=8.0),
    "bow": Scenario("bow", _double_support_outputs(), (), (), _bow_reference,
                    _default_params, duration=8.0),
    "arms": Scenario("arms", _double_support_outputs(), (fist_barrier("left"),),
                     (fist_barrier("right"),), _arms_reference,
                     lambda: _default_params(("left_fist", "right_fist")), duration=12.0),
}


WALKING = ("walk", "push")


def get_scenario(name: str, barrier: bool = True) -> Scenario:
    """A scenario by name; ``barrier`` only matters for the walking ones, whose swing-foot
    barrier is monitored instead of enforced when False."""
    if name in WALKING:
        from safewbc_jax import walking

        return walking.make_scenario(name, 20.0 if name == "walk" else 8.0, barrier)
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; available: "
                         f"{', '.join(list(SCENARIOS) + list(WALKING))}")
    return SCENARIOS[name]


def start_state(model, q) -> dict:
    """Start data measured on the robot at the beginning of the run: the stance frame
    origin (midpoint of the soles on the ground), the arm posture to hold, and y^a(q) of
    every output (the settle blend starts there)."""
    from safewbc_jax import robot

    pl, _ = robot.frame_pose(model, q, "left-sole")
    pr, _ = robot.frame_pose(model, q, "right-sole")
    origin = 0.5 * (pl + pr)
    arm0 = q[np.array([model.joint_qadr(j) for j in outputs.ARM_JOINTS])]
    return {"origin": origin.at[2].set(0.0), "arm0": arm0}
