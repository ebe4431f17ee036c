"""The bow with a torso-lean limit: the paper's "leaning the torso excessively" as a user's
safe set, added without editing the package.

    h(q) = theta_max - theta_pitch(q) >= 0,   theta_max = 0.9 rad

theta_pitch is the torso's pitch (the middle Euler ZYX angle of ``outputs.TorsoOrientation``,
positive bending forward). The bow's reference (paper eq. 32) bends the torso to 1.35 rad at
tau = 3 s; with this safe set enforced the A-ECBF row (eq. 28) stops the torso at 0.9 rad
while the CoM and arm tasks go on. Relative degree 2: eta = [h, -J_pitch v], and Theorem 1
(eq. 25) holds at any start at rest with the torso upright (h(x0) = 0.9 > 0).

Run it:

    safewbc run bow --safe-set examples/bow_torso_lean.py:TORSO_LEAN

or from Python: ``python examples/bow_torso_lean.py``.
"""

from safewbc_jax import SafeSet, robot


def torso_lean(model, q, threshold, domain=None):
    """h(q) = threshold - pitch(q) (rad); threshold is theta_max."""
    return threshold - robot.torso_euler(model, q)[1]


TORSO_LEAN = SafeSet("torso_lean", torso_lean, relative_degree=2, poles=(10.0, 10.0),
                     threshold=0.9, unit="rad")


if __name__ == "__main__":
    import safewbc_jax
    from safewbc_jax import format_summary, run_scenario

    safewbc_jax.enable_x64()
    m = run_scenario("bow", safe_sets=(TORSO_LEAN,), out="runs/bow_torso_lean", duration=4.0)
    print(format_summary(m))
