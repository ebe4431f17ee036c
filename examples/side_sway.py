"""A scenario of your own, in a file of your own: sway the CoM from side to side over the
feet in double support, torso level, arms held, and keep the CoM within a lateral limit
with a safe set of your own. Nothing in the package is edited.

    y^d_CoM(tau) = origin + [0, A sin(2 pi tau / T), 0],   A = 6 cm, T = 4 s
    h(q) = c - (y_CoM(q) - y_mid(q)) >= 0,                  c = 4 cm

y_mid is the midpoint of the two soles, so h is a function of q alone (relative degree 2:
eta = [h, -J v], the A-ECBF row of eq. 28). The reference sways 6 cm to the left at tau = 1 s;
the barrier stops the CoM at 4 cm while the other tasks go on. Theorem 1 (eq. 25) holds at
any start at rest with the CoM between the feet (h(x0) = c > 0).

Run it, sweep it:

    safewbc run examples/side_sway.py:SIDE_SWAY --duration 4
    # a sweep spec beside this file:  [sweep] scenario = "side_sway.py:SIDE_SWAY"
"""

import jax.numpy as jnp

from safewbc_jax import SafeSet, Scenario, Task, outputs, robot

AMPLITUDE = 0.06     # m
PERIOD = 4.0         # s


def com_reference(tau, start):
    """The CoM over the stance origin at its start height, swaying sideways."""
    y = AMPLITUDE * jnp.sin(2.0 * jnp.pi * tau / PERIOD)
    com0 = start.y0["com"]
    return jnp.array([start.origin[0], start.origin[1] + y, com0[2]])


def com_side(model, q, threshold, domain=None):
    """h(q) = threshold - (y_CoM - y_mid): the CoM's lateral offset from the soles'
    midpoint, at most ``threshold`` (m) to the left."""
    left, _ = robot.frame_pose(model, q, "left-sole")
    right, _ = robot.frame_pose(model, q, "right-sole")
    return threshold - (robot.com_position(model, q)[1] - 0.5 * (left[1] + right[1]))


COM_SIDE = SafeSet("com_side", com_side, relative_degree=2, poles=(10.0, 10.0),
                   threshold=0.04, unit="m")

SIDE_SWAY = Scenario(
    "side_sway",
    (Task(outputs.CoMPosition(), 100.0, 20.0, 100.0, reference=com_reference),
     Task(outputs.TorsoOrientation(), 100.0, 20.0, 10.0,
          reference=lambda tau, start: jnp.zeros(3) + 0.0 * tau),
     Task(outputs.JointPositions(name="arms", joints=outputs.ARM_JOINTS), 900.0, 60.0, 1.0,
          reference=lambda tau, start: start.arm0 + 0.0 * tau)),
    safe_sets=(COM_SIDE,), duration=8.0)


if __name__ == "__main__":
    import safewbc_jax
    from safewbc_jax import format_summary, run_scenario

    safewbc_jax.enable_x64()
    m = run_scenario(f"{__file__}:SIDE_SWAY", out="runs/side_sway", duration=4.0)
    print(format_summary(m))
