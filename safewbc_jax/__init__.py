"""safewbc-jax: safe whole-body task-space control (A-ECBF inverse-dynamics QP) for Digit.

Importing the package switches JAX to 64-bit floats (``jax_enable_x64``): the controller's
robot terms and QPs are float64 on the CPU. Arrays made with an explicit float32 dtype
(the accelerator option of the batched path) stay float32.
"""

import os

# OpenBLAS (numpy's, and scipy's, which jaxlib's CPU LAPACK kernels call) spins worker
# threads after each call; on a small CPU they compete with XLA's own thread pool. Measured
# on a 2-core machine: closed-loop MJX rollouts with the JAX QP solver ran 70x slower per
# step (71 ms against 1.1 ms at batch 2). The controller's matrices are far too small to
# gain from threaded BLAS, so one thread is the default unless the user set it. (Only
# effective when numpy is not imported yet; ``solvers.jax_qp.blas_threads`` sets it at
# run time.)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
