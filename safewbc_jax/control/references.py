"""The paper's reference trajectories y^d(tau) and the settle phase before them.

Time tau counts from the start of the motion (paper: tau = t - t0). Each reference is a
pure JAX function of tau; ``with_derivatives`` gives (y^d, y^d_dot, y^d_ddot) by
forward-mode AD in tau.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def with_derivatives(fn, tau):
    """(y, dy/dtau, d2y/dtau2) of a reference function at tau."""
    tau = jnp.asarray(tau, jnp.result_type(float))

    def d1(s):
        return jax.jvp(fn, (s,), (jnp.ones_like(s),))

    (y, yd), (_, ydd) = d1(tau), jax.jvp(lambda s: d1(s)[1], (tau,), (jnp.ones_like(tau),))
    return y, yd, ydd


def squat_com(tau):
    """Paper, "Task: Squatting and bowing", eq. 31: p^d_CoM(tau) =
    [-0.02, 0, 1 - 0.12 (1 - e^-tau) + 0.03 sin(pi tau)] (m; x, y relative to the stance
    frame, z above the ground)."""
    z = 1.0 - 0.12 * (1.0 - jnp.exp(-tau)) + 0.03 * jnp.sin(jnp.pi * tau)
    return jnp.stack([-0.02 + 0.0 * tau, 0.0 * tau, z])


def bow_torso(tau):
    """Paper, bowing, eq. 32: theta^d_torso(tau) = [0, 0.45 max(3 - |tau - 3|, 0), 0] (rad)."""
    pitch = 0.45 * jnp.maximum(3.0 - jnp.abs(tau - 3.0), 0.0)
    return jnp.stack([0.0 * tau, pitch, 0.0 * tau])


BOW_COM = (0.0, 0.0, 0.95)


def arm_offsets(tau):
    """Paper, "Task: Arm motion with height limits", eqs. 35-36: q^d_arm_L = [0, 0.3 s, 0, 0.2 s],
    q^d_arm_R = -q^d_arm_L with s = sin(pi tau / 5), joints (shoulder roll, pitch, yaw,
    elbow). Applied as offsets from the held arm posture (see ``scenarios``)."""
    s = jnp.sin(jnp.pi * tau / 5.0)
    left = jnp.stack([0.0 * s, 0.3 * s, 0.0 * s, 0.2 * s])
    return jnp.concatenate([left, -left])


def smoothstep5(x):
    """Quintic 0 -> 1 on [0, 1] with zero first and second derivatives at both ends."""
    x = jnp.clip(x, 0.0, 1.0)
    return x * x * x * (10.0 - 15.0 * x + 6.0 * x * x)
