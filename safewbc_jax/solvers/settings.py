"""Settings of the JAX QP solver (``jax_qp``), shared by its stages (interior point,
polish, acceptance, fallback)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from safewbc_jax.solvers.relax import DEFAULT_RHO, DEFAULT_RHO_LIN

BIG = 1e20
"""|h| or |bound| at or above this counts as infinite (both solvers' checks, the scaling)."""


@dataclasses.dataclass(frozen=True)
class Settings:
    """Solver settings (hashable: a static argument of the jitted entry points).

    eps_abs, eps_rel   stopping tolerances of the interior point (scaled problem)
    eps_inf            relative margin of the infeasibility certificates
    max_iter           interior-point iteration limit (per solve: nominal, relaxed)
    polish             solve the KKT system of the detected active set at the end
    polish_tol         relative tolerance of the polished point's feasibility/sign checks
    feas_tol           acceptance of a solved point's full-space residuals (PIQP path: 1e-6)
    reg                Tikhonov term on the scaled Newton matrix
    fallback           re-solve the not-accepted instances with their soft rows relaxed
    relax_rho, relax_rho_lin   weights of the relaxation (``relax.relax_soft_rows``)
    """

    eps_abs: float = 1e-10
    eps_rel: float = 1e-12
    eps_inf: float = 1e-9
    max_iter: int = 60
    polish: bool = True
    polish_iter: int = 12
    polish_tol: float = 1e-9
    polish_dual_tol: float = 1e-13
    feas_tol: float = 1e-6
    reg: float = 1e-13
    fallback: bool = True
    ipm_dtype: str | None = None
    relax_rho: float = DEFAULT_RHO
    relax_rho_lin: float = DEFAULT_RHO_LIN

    @staticmethod
    def for_dtype(dtype, **overrides) -> "Settings":
        """Defaults for float64 (the above) or float32 (tolerances scaled to its epsilon)."""
        if jnp.dtype(dtype) == jnp.float32:
            base = dict(eps_abs=1e-5, eps_rel=1e-6, eps_inf=1e-4, max_iter=60,
                        polish_tol=1e-4, feas_tol=1e-3, reg=1e-7)
        else:
            base = {}
        return Settings(**{**base, **overrides})


def full_float32():
    """A context in which every matrix product traced is at full float32 precision
    (``jax.default_matmul_precision("highest")``), for the float32 stages of the mixed
    mode (``ipm_dtype``; ``precision.physics``): on Ampere and newer GPUs JAX's default
    lets float32 products run in TF32 (a 10-bit mantissa), too coarse for the interior
    point's reduced Hessians (condition numbers of 1e7-5e8). XLA:CPU computes float32
    products in float32 either way."""
    return jax.default_matmul_precision("highest")


def settings_for(dtype, settings: Settings | None) -> Settings:
    """``settings``, or the defaults of ``dtype`` (``Settings.for_dtype``) when None."""
    return settings if settings is not None else Settings.for_dtype(dtype)


__all__ = ["Settings", "settings_for", "full_float32", "BIG"]
