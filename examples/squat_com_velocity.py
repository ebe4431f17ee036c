"""The squat with a limit on the CoM's horizontal speed: a barrier of relative degree 1,
the paper's "excessive (centroidal) momentum" kind of safe set, as a user's file.

    h(q, v) = (v_max^2 - |v_CoM,xy(q, v)|^2) / (2 v_max) >= 0

v_CoM,xy = J_CoM,xy(q) v is the CoM's horizontal velocity. The square keeps h smooth where
|v| = 0 (|v| is not differentiable there); near the boundary h ~ v_max - |v_xy|. h depends on
v, so it has relative degree 1 in q_ddot: eta = [h], and the A-ECBF row (eq. 28 with r_b = 1)
is dh/dv q_ddot >= -p_1 h - L_F h, with L_F h the rate of h along q_dot at q_ddot = 0. One
pole; Theorem 1 (eq. 25) needs h(x0) >= 0, i.e. a start slower than v_max.

The squat's reference keeps the CoM 2 cm behind the stance origin; the robot moves there in
the settle blend, at up to 0.040 m/s (50 ms average; 0.046 m/s peak) without this safe set.
With v_max = 0.03 m/s the barrier holds the CoM back. How close it holds the limit is set
by the model, not by the QP: the QP's rows are met at every step, but the MuJoCo plant's CoM
acceleration differs from the one the QP plans (its springs, held rigid in the controller,
and its soft contacts: a ~20 Hz mode of about +-1 m/s^2, and a mean error of ~0.15 m/s^2).
A velocity barrier has no integrator to absorb that: h settles where the pole's restoring
acceleration p_1 (|v| - v_max) meets the error, so the speed overshoots v_max by about
e_a / p_1 (measured: 0.037 m/s at p_1 = 20, 0.033 m/s at p_1 = 60, 50 ms averages). Hence
the large default pole.

    safewbc run squat --safe-set examples/squat_com_velocity.py:COM_SPEED
"""

import jax.numpy as jnp

from safewbc_jax import SafeSet, robot, spatial


def com_velocity_xy(model, q, v):
    """J_CoM,xy(q) v: the CoM's horizontal velocity (m/s), by the derivative of p_CoM along
    q_dot on the configuration manifold."""
    return spatial.derivative_along(lambda qq: robot.com_position(model, qq)[:2], q, v)


def com_speed(model, q, v, threshold, domain=None):
    """h(q, v) = (v_max^2 - |v_xy|^2) / (2 v_max); threshold is v_max (m/s)."""
    vxy = com_velocity_xy(model, q, v)
    return (threshold * threshold - jnp.sum(vxy * vxy)) / (2.0 * threshold)


COM_SPEED = SafeSet("com_speed", com_speed, relative_degree=1, poles=(60.0,), threshold=0.03,
                    unit="m/s")


if __name__ == "__main__":
    import safewbc_jax
    from safewbc_jax import format_summary, run_scenario

    safewbc_jax.enable_x64()
    m = run_scenario("squat", safe_sets=(COM_SPEED,), out="runs/squat_com_speed")
    print(format_summary(m))
