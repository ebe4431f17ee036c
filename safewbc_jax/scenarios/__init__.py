"""The paper's scenarios by name: squat, bow, arms (section "Simulation and Experimental
Results", double support) and walk, push (``walking``).

Each is a ``scenario.Scenario``: a list of ``tasks.Task`` and ``safesets.SafeSet``.
``get_scenario(name, barrier, safe_sets)`` adds a user's safe sets (objects, or
"FILE.py:NAME" references loaded by ``safesets.load``).
"""

from __future__ import annotations

import jax.numpy as jnp

from safewbc_jax.base import userfile
from safewbc_jax.control import outputs, references, walking
from safewbc_jax.control.push import Push
from safewbc_jax.control.safesets import SafeSet, SafeSetError, load
from safewbc_jax.control.scenario import Scenario, start_state  # noqa: F401  (re-exported)
from safewbc_jax.control.tasks import Task
from safewbc_jax.model import digit

# Threshold of the arm barrier h = -p_z - c (m). The paper's c = 0.195 (eq. 33) refers to its own
# torso base frame; in this model's base frame (at hip height) the fists hang at
# p_z = -0.10 m, where c = 0.195 would make the start unsafe (Theorem 1 then does not
# apply). c = 0.05 keeps the paper's situation: the start is safe by 5 cm, and the commanded
# arm motion lifts the fists to p_z = +0.05 m, 10 cm into the unsafe side.
ARM_THRESHOLD = 0.05
ARM_POLES = (10.0, 10.0)


def _fist_height(side):
    def h(model, q, threshold, domain=None):
        from safewbc_jax.model import robot

        return -robot.frame_position_in(model, q, digit.fist(side), digit.TORSO)[2] - threshold
    return h


def _fist_height_terms(side):
    def terms(model, kin, motion, threshold, domain=None):
        from safewbc_jax.model import robot

        y, jy, jdv = robot.position_in_terms(model, kin, motion, digit.fist(side), digit.TORSO)
        return -y[2] - threshold, -jy[2], -jdv[2]
    return terms


def fist_barrier(side, enforce=True):
    """Paper, arm task, eq. 33: h(q) = -p_z(q) - c >= 0, p_z the fist's height in the torso base
    frame; its row from the closed-form terms of that position (``robot.position_in_terms``)."""
    return SafeSet(f"{side}_fist", _fist_height(side), 2, ARM_POLES, ARM_THRESHOLD,
                   enforce=enforce, terms=_fist_height_terms(side))


def _double_support_tasks(com, torso, arms):
    """CoM, torso and arm tasks with the references (tau, start) -> y^d given."""
    return (Task(outputs.CoMPosition(), 100.0, 20.0, 100.0, reference=com),
            Task(outputs.TorsoOrientation(), 100.0, 20.0, 10.0, reference=torso),
            # stiff enough to beat the joints' friction loss
            Task(outputs.JointPositions(name="arms", joints=outputs.ARM_JOINTS), 900.0, 60.0,
                 1.0, reference=arms))


def _held_arms(tau, start):
    return start.arm0 + 0.0 * tau


def _level_torso(tau, start):
    return jnp.zeros(3) + 0.0 * tau


def squat() -> Scenario:
    return Scenario("squat", _double_support_tasks(
        lambda tau, start: start.origin + references.squat_com(tau), _level_torso,
        _held_arms), duration=8.0)


def bow() -> Scenario:
    return Scenario("bow", _double_support_tasks(
        lambda tau, start: start.origin + jnp.asarray(references.BOW_COM) + 0.0 * tau,
        lambda tau, start: references.bow_torso(tau), _held_arms), duration=8.0)


def _arms_com(tau, start):
    com0 = start.y0["com"]
    return jnp.array([start.origin[0], start.origin[1], com0[2]]) + 0.0 * tau


def arms() -> Scenario:
    return Scenario("arms", _double_support_tasks(
        _arms_com, _level_torso,
        lambda tau, start: start.arm0 + references.arm_offsets(tau)),
        safe_sets=(fist_barrier("left"), fist_barrier("right", enforce=False)), duration=12.0)


SCENARIOS = {"squat": squat(), "bow": bow(), "arms": arms()}
WALKING = ("walk", "push")
PAPER_PUSH = (0.0, -30.0, 0.0)   # N: the paper's lateral push (to the right), at PUSH_AT


def names() -> tuple:
    """The scenarios that have a name: the paper's."""
    return tuple(SCENARIOS) + WALKING


def get_scenario(name, barrier: bool = True, safe_sets=()) -> Scenario:
    """A scenario by name, a user's Scenario from a "FILE.py:NAME" reference
    (``userfile.load``), or a Scenario itself. ``barrier`` False: every safe set (the
    user's too) monitored instead of enforced (``Scenario.without_barriers``: no A-ECBF
    row in the QP, h still recorded), the one way the barriers are turned off.
    ``safe_sets``: SafeSets or "FILE.py:NAME" references (``safesets.load``) to add."""
    if isinstance(name, Scenario):
        sc = name
    elif name in WALKING:
        sc = (walking.make_scenario(name, 20.0) if name == "walk" else
              walking.make_scenario(name, 8.0, Push.single(PAPER_PUSH)))
    elif name in SCENARIOS:
        sc = SCENARIOS[name]
    elif userfile.is_ref(name):
        sc = userfile.load(name, Scenario, "scenario")
    else:
        raise ValueError(f"unknown scenario {name!r}; available: {', '.join(names())}, or "
                         "a Scenario of your own as FILE.py:NAME")
    if isinstance(safe_sets, (str, SafeSet)):
        safe_sets = (safe_sets,)
    extra = tuple(load(s) if isinstance(s, str) else s for s in safe_sets)
    taken = {s.name for s in sc.safe_sets}
    for s in extra:
        if s.name in taken:
            raise SafeSetError(f"safe set {s.name!r}: scenario {sc.name!r} already has a safe "
                               f"set of that name ({', '.join(sorted(taken))})")
    sc = sc.with_safe_sets(*extra)
    if not barrier:
        sc = sc.without_barriers()
    return sc
