"""Rotations and the configuration manifold of a floating-base robot, as pure JAX functions.

Conventions are MuJoCo's: quaternions (w, x, y, z); the free joint's qpos is
[position (world), orientation quaternion] and its qvel is [linear velocity of the body
origin (world frame), angular velocity (body frame)]; hinge qpos and qvel are scalars.
"""

from __future__ import annotations

from typing import Any, Callable

import jax
import jax.numpy as jnp


def skew(w: jax.Array) -> jax.Array:
    """Cross-product matrix: skew(w) @ x == cross(w, x).

    Args:
        w: (3,) vector.

    Returns:
        (3, 3) skew-symmetric matrix.
    """
    return jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def quat_to_mat(q: jax.Array) -> jax.Array:
    """Rotation matrix of a quaternion.

    Args:
        q: (4,) quaternion (w, x, y, z), not necessarily of unit norm (normalised here).

    Returns:
        (3, 3) rotation matrix.
    """
    q = q / jnp.linalg.norm(q)
    w, x, y, z = q
    return jnp.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
    """Hamilton product a * b.

    Args:
        a: (4,) quaternion (w, x, y, z).
        b: (4,) quaternion (w, x, y, z).

    Returns:
        (4,) their product.
    """
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return jnp.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


def quat_exp(w: jax.Array) -> jax.Array:
    """Unit quaternion of a rotation vector.

    Written in the squared angle so that it, and its derivatives of any order, are smooth
    at w = 0 (the tangent Jacobians below differentiate it exactly there).

    Args:
        w: (3,) rotation vector, axis * angle (rad).

    Returns:
        (4,) unit quaternion (w, x, y, z).
    """
    s = w @ w
    small = s < 1e-6
    s_safe = jnp.where(small, 1.0, s)
    theta = jnp.sqrt(s_safe)
    c = jnp.where(small, 1.0 - s / 8.0 + s * s / 384.0, jnp.cos(0.5 * theta))
    k = jnp.where(small, 0.5 - s / 48.0 + s * s / 3840.0, jnp.sin(0.5 * theta) / theta)
    return jnp.concatenate([c[None], k * w])


def euler_zyx(r: jax.Array) -> jax.Array:
    """Euler ZYX angles of a rotation matrix, r = Rz(yaw) Ry(pitch) Rx(roll).

    Args:
        r: (3, 3) rotation matrix.

    Returns:
        (3,) [roll, pitch, yaw] (rotation about x, y, z), rad: index 1 is the pitch of the
            paper's bowing reference.
    """
    roll = jnp.arctan2(r[2, 1], r[2, 2])
    pitch = -jnp.arcsin(jnp.clip(r[2, 0], -1.0, 1.0))
    yaw = jnp.arctan2(r[1, 0], r[0, 0])
    return jnp.stack([roll, pitch, yaw])


def integrate(q: jax.Array, v: jax.Array, dt: float | jax.Array = 1.0) -> jax.Array:
    """Configuration reached from q by holding the generalized velocity v for dt.

    The same rule as MuJoCo's ``mj_integratePos``. Along t -> integrate(q, v, t) the
    generalized velocity stays v, i.e. the generalized acceleration is zero; this is what
    makes the drift terms below second derivatives along that curve.

    Args:
        q: (nq,) configuration [p (3), quat (4), joints].
        v: (nv,) generalized velocity [p_dot (3, world), omega (3, body), joint rates],
            nv = nq - 1.
        dt: the time, s.

    Returns:
        (nq,) the configuration reached.
    """
    pos = q[:3] + dt * v[:3]
    quat = quat_mul(q[3:7], quat_exp(dt * v[3:6]))
    return jnp.concatenate([pos, quat, q[7:] + dt * v[6:]])


def tangent_jacobian(f: Callable[[jax.Array], jax.Array], q: jax.Array,
                     nv: int) -> jax.Array:
    """Jacobian of f(q) with respect to the generalized velocity: d f(integrate(q, d)) / d d
    at d = 0, by forward-mode AD.

    For a position-like output y(q) this is J_y(q), with y_dot = J_y v.

    Args:
        f: a function of the configuration.
        q: (nq,) configuration.
        nv: the size of the generalized velocity.

    Returns:
        f's output shape + (nv,).
    """
    return jax.jacfwd(lambda d: f(integrate(q, d)))(jnp.zeros(nv, q.dtype))


def second_derivative_along(f: Callable[[jax.Array], jax.Array], q: jax.Array,
                            v: jax.Array) -> jax.Array:
    """d^2/dt^2 f(integrate(q, v, t)) at t = 0: the drift J_y_dot v of an output y = f(q),
    the second directional derivative along v (forward mode, twice).

    Args:
        f: a function of the configuration.
        q: (nq,) configuration.
        v: (nv,) generalized velocity.

    Returns:
        f's output shape.
    """
    def g(t):
        return f(integrate(q, v, t))

    def dg(t):
        return jax.jvp(g, (t,), (jnp.ones_like(t),))[1]

    t0 = jnp.zeros((), q.dtype)
    return jax.jvp(dg, (t0,), (jnp.ones_like(t0),))[1]


def derivative_along(f: Callable[[jax.Array], jax.Array], q: jax.Array,
                     v: jax.Array) -> jax.Array:
    """d/dt f(integrate(q, v, t)) at t = 0, by forward-mode AD.

    With f(q) = J(q) v this is J_dot v for any Jacobian, angular ones included.

    Args:
        f: a function of the configuration.
        q: (nq,) configuration.
        v: (nv,) generalized velocity.

    Returns:
        f's output shape.
    """
    t0 = jnp.zeros((), q.dtype)
    return jax.jvp(lambda t: f(integrate(q, v, t)), (t0,), (jnp.ones_like(t0),))[1]


def config_rate(q: jax.Array, v: jax.Array) -> jax.Array:
    """q_dot = d/dt integrate(q, v, t) at t = 0 (the quaternion part is 1/2 quat * (0, w)).

    Args:
        q: (nq,) configuration.
        v: (nv,) generalized velocity.

    Returns:
        (nq,) the configuration's rate.
    """
    t0 = jnp.zeros((), q.dtype)
    return jax.jvp(lambda t: integrate(q, v, t), (t0,), (jnp.ones_like(t0),))[1]


def with_drift(jac_fn: Callable[[jax.Array], Any], q: jax.Array,
               v: jax.Array) -> tuple[Any, Any]:
    """(J(q), J_dot(q, v) v) of a Jacobian-valued function in one forward-mode pass: the
    tangent of J along q_dot, applied to v (one pass where J and ``derivative_along(J v)``
    take two).

    Args:
        jac_fn: q -> J(q), (m, nv), or a pytree of such Jacobians.
        q: (nq,) configuration.
        v: (nv,) generalized velocity.

    Returns:
        ``(J, J_dot v)``: J(q), and (m,) J_dot v of each Jacobian (as a pytree like J's).
    """
    jac, djac = jax.jvp(jac_fn, (q,), (config_rate(q, v),))
    return jac, jax.tree_util.tree_map(lambda d: d @ v, djac)
