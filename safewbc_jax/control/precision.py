"""Precision of the batched path (``BatchConfig.precision``): which parts run in float32.

``"float64"`` (default)
    Everything in float64: MJX physics, the controller's robot terms, the QP, its solver.
    The mode for CPUs and for GPUs with full-rate float64 (H100, H200, A100).

``"mixed"``
    float32 where the arithmetic is well conditioned, float64 where it is not:

    - MJX physics (``mjx.step``) in float32;
    - the JAX solver's interior-point iterations in float32 (``Settings.ipm_dtype``);
    - in float64: the robot terms and the QP build, the elimination of the equality rows
      (a Cholesky of the mass matrix, an LU of the constraint-space matrix), the
      active-set polish and the acceptance check.

    The polish solves the KKT system of the active set the float32 iterations found, in
    float64, so the torques are float64's wherever that active set is the optimum's.

    float32 is float32 on every backend: the float32 stages are traced at full float32
    matrix-product precision (``full_float32``), so a GPU's TF32 never replaces it.

Why not float32 throughout: the reduced QP in the torques has a Hessian of condition
number ~1e7 (the contact forces' small regularisation Gamma, seen through the
elimination), about 1/eps of float32. On the recorded fixture a float32 solve is off by a
large fraction of the torque limits and fails walking QPs, while the mixed solve agrees
with float64 (benchmarks/README.md, "precision.py", with the closed-loop figures and which
mode to pick).

The physics runs in float32 under ``jax.enable_x64(False)`` while it is traced: MJX makes
its constants with JAX's default dtype, so under x64 a float32 ``mjx.Data`` would come back
float64. The measurement is cast to float64 where the controller reads it, and the motor
torques to float32 where the simulator takes them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.solvers.settings import full_float32

PRECISIONS = ("float64", "mixed")


def check(precision, what: str = "precision") -> None:
    """ValueError naming ``what`` unless ``precision`` is one of ``PRECISIONS``."""
    if precision not in PRECISIONS:
        raise ValueError(f"{what} = {precision!r}: must be one of {', '.join(PRECISIONS)}")


def physics_dtype(precision: str):
    """The float dtype of the simulator state under ``precision``."""
    check(precision)
    return jnp.float32 if precision == "mixed" else jnp.float64


def qp_settings(precision: str):
    """The JAX solver's settings under ``precision`` (None: float64's defaults)."""
    from safewbc_jax.solvers.settings import Settings

    check(precision)
    return Settings(ipm_dtype="float32") if precision == "mixed" else None


def cast_floats(tree, dtype):
    """Every floating array leaf of ``tree`` as ``dtype``, numpy leaves kept numpy (MJX
    reads some model fields on the host while tracing); other leaves as they are."""
    def cast(a):
        if isinstance(a, (np.ndarray, jax.Array)) and jnp.issubdtype(a.dtype, jnp.floating):
            return a.astype(np.dtype(dtype))
        return a

    return jax.tree_util.tree_map(cast, tree)


def physics(step, dtype):
    """``step(model, data) -> data`` traced so that it keeps ``dtype`` (float32 under
    ``jax.enable_x64(False)`` and ``full_float32``, see the module docstring; float64 as it
    is) and returns each
    leaf of ``data`` in the dtype it was given, so that the data can be a loop carry:
    MJX's ``put_data`` makes the contacts' geom indices int32 and, under x64, ``mjx.step``
    returns them int64 (values that fit either). Knowing the step's dtypes beforehand
    would take an ``eval_shape`` of ``mjx.step``, seconds of tracing in every process that
    builds a plant (benchmarks/README.md, "Figures behind design choices")."""
    def keep_dtypes(model, data):
        if jnp.dtype(dtype) == jnp.float64:
            out = step(model, data)
        else:
            with jax.enable_x64(False), full_float32():
                out = step(model, data)
        return jax.tree_util.tree_map(
            lambda o, i: o if o.dtype == i.dtype else o.astype(i.dtype), out, data)

    return keep_dtypes


__all__ = ["PRECISIONS", "check", "physics_dtype", "qp_settings", "cast_floats", "full_float32",
           "physics"]
