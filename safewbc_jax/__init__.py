"""safewbc-jax: safe whole-body task-space control (A-ECBF inverse-dynamics QP) for Digit."""
