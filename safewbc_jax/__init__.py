"""safewbc-jax: safe whole-body task-space control (A-ECBF inverse-dynamics QP) for Digit.

Importing the package switches JAX to 64-bit floats (``jax_enable_x64``): the controller's
robot terms and QPs are float64 on the CPU. Arrays made with an explicit float32 dtype
(the accelerator option of the batched path) stay float32.
"""

import jax

jax.config.update("jax_enable_x64", True)
