"""The deployed controller's checks of what it is given, each with the reason in words: a
measurement (the tests the jitted step applies, ``control.step.state_tests``, named, plus
the shapes and types only the host can see), a start state, and Theorem 1 at the start."""

from __future__ import annotations

import numpy as np

from safewbc_jax.control import step as control_step
from safewbc_jax.control.step import MAX_RATE, MAX_SPEED, QUAT_TOL, Measurement, state_tests


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


def check_barrier_poles(model, scenario, params, q, v, cache: dict | None = None) -> None:
    """Theorem 1 (eq. 25) at the start state (q, v), before anything compiles.

    Args:
        model: the controller's ``RobotModel``.
        scenario: the ``Scenario`` whose barriers are checked (a walking barrier is
            checked where its domain first starts).
        params: ``ControllerParams`` of one robot.
        q: the start configuration.
        v: the start velocity.
        cache: keeps the jitted check of each start q across calls; without it the check
            runs eagerly.

    Raises:
        barriers.PoleError: naming the barrier, the pole and its bound.
    """
    key = np.asarray(q).tobytes()
    if cache is not None and key not in cache:
        cache[key] = control_step.StartCheck(model, scenario, q)
    check = control_step.StartCheck(model, scenario, q, jit=False) if cache is None else cache[key]
    check.check(params, v, batched=False)
