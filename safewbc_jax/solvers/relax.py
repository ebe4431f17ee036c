"""Soft-row relaxation of the controller QP: the fallback when the QP as posed is infeasible.

Given the QP (see ``safewbc_jax.solvers.problem``)

    minimize    1/2 x'Px + q'x
    subject to  A x = b,   G x <= h,   lb <= x <= ub

``relax_soft_rows`` returns the QP in z = [x; s], with one slack s_i per inequality row:

    minimize    1/2 x'Px + q'x + rho/2 ||s||^2 + rho_lin * sum_{i soft} s_i
    subject to  A x = b,   G x - s <= h,   lb <= x <= ub,
                0 <= s_i <= +inf  for soft rows,   s_i = 0 (lb = ub = 0)  for hard rows.

Every row gets a slack so that the shape depends only on the shape of G, never on the
values of ``soft``: it can be ``jit``-ed and ``vmap``-ped over robots whose soft masks
differ. Hard rows keep their slack pinned to zero, so for them the relaxed row is the
original row.

Feasibility. Let H = {x : A x = b, lb <= x <= ub, G_i x <= h_i for every hard row i}.
* If H is non-empty the relaxed QP is feasible, whatever the soft rows say: take any x in H
  and s_i = max(0, G_i x - h_i) on the soft rows. With P positive definite the relaxed cost
  is strictly convex (its Hessian is blockdiag(P, rho I)), so the relaxed solution is unique.
* If H is empty (the hard rows, the equalities or the bounds conflict among themselves)
  the relaxation cannot help: the relaxed QP is infeasible too. A solver then reports
  INFEASIBLE (or MAX_ITER / NUMERICAL when it cannot certify it), and the caller must treat
  the step as failed and hold its last good command (the PIQP path returns x=None with
  fallback="failed").

Exactness. The KKT conditions of the relaxed QP give, for a soft row with multiplier
mu_i >= 0, s_i = max(0, mu_i - rho_lin) / rho. With the pure quadratic penalty
(rho_lin = 0) every active soft row is therefore violated by mu_i / rho even when the
original QP is feasible: the relaxed QP is a fallback, not a replacement. With
rho_lin >= max_i mu_i (an exact L1 penalty) a feasible original QP is solved exactly,
and when it is infeasible the violation is concentrated on the rows that must give.

Everything here is pure ``jax.numpy`` on a single QP; use ``jax.vmap`` for a batch.
``strip_slack`` and ``split_slack`` also work on leading batch dimensions.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from safewbc_jax.solvers.problem import QP

DEFAULT_RHO = 1e6
DEFAULT_RHO_LIN = 0.0


def _relax(qp: QP, xp, rho, rho_lin) -> QP:
    """The construction, written once for an array namespace ``xp`` (jax.numpy or numpy) so
    that numpy (no dispatch overhead) and JAX build the same QP."""
    P, q, A, b, G, h, lb, ub, soft = (qp.P, qp.q, qp.A, qp.b, qp.G, qp.h, qp.lb, qp.ub,
                                      qp.soft)
    dtype = P.dtype
    n = P.shape[-1]
    me = A.shape[0]
    mi = G.shape[0]
    is_soft = soft > 0

    zeros_n_mi = xp.zeros((n, mi), dtype=dtype)
    P_r = xp.concatenate([
        xp.concatenate([P, zeros_n_mi], axis=1),
        xp.concatenate([zeros_n_mi.T, rho * xp.eye(mi, dtype=dtype)], axis=1),
    ], axis=0)
    q_s = xp.where(is_soft, xp.asarray(rho_lin, dtype=dtype), xp.asarray(0.0, dtype=dtype))
    q_r = xp.concatenate([q, q_s.astype(dtype)])
    A_r = xp.concatenate([A, xp.zeros((me, mi), dtype=dtype)], axis=1)
    G_r = xp.concatenate([G, -xp.eye(mi, dtype=dtype)], axis=1)
    lb_r = xp.concatenate([lb, xp.zeros((mi,), dtype=dtype)])
    ub_r = xp.concatenate([ub, xp.where(is_soft, xp.inf, 0.0).astype(dtype)])
    # Every row of the relaxed QP is satisfiable through its slack or is a hard row, so
    # nothing is left to relax: a second relaxation would only add inert variables.
    soft_r = xp.zeros_like(soft)
    return QP(P=P_r, q=q_r, A=A_r, b=b, G=G_r, h=h, lb=lb_r, ub=ub_r, soft=soft_r)


def relax_soft_rows(qp: QP, rho=DEFAULT_RHO, rho_lin=DEFAULT_RHO_LIN) -> QP:
    """The relaxed QP in z = [x; s] (n + mi variables), see the module docstring.

    rho:     weight of rho/2 ||s||^2 (scalar; may be a traced value).
    rho_lin: weight of the linear term rho_lin * s_i on the soft rows (scalar or (mi,)
             array; may be traced). 0 gives the pure quadratic penalty.
    """
    return _relax(qp, jnp, rho, rho_lin)


def relax_soft_rows_np(qp: QP, rho=DEFAULT_RHO, rho_lin=DEFAULT_RHO_LIN) -> QP:
    """``relax_soft_rows`` on numpy arrays (same code path), for where a JAX
    dispatch per fallback would cost more than the construction itself."""
    qp_np = QP(**{f: np.asarray(getattr(qp, f), dtype=np.float64)  # type: ignore[arg-type]
                  for f in ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")})
    return _relax(qp_np, np, rho, rho_lin)


def strip_slack(z, qp: QP):
    """x from a solution z = [x; s] of ``relax_soft_rows(qp)``. ``qp`` is the ORIGINAL
    (unrelaxed) QP: only its size n is used. Works on leading batch dimensions."""
    return z[..., :qp.P.shape[-1]]


def split_slack(z, qp: QP):
    """(x, s) from a solution z = [x; s] of ``relax_soft_rows(qp)``; ``qp`` is the
    original QP. Works on leading batch dimensions."""
    n = qp.P.shape[-1]
    return z[..., :n], z[..., n:]


__all__ = ["relax_soft_rows", "relax_soft_rows_np", "strip_slack", "split_slack",
           "DEFAULT_RHO", "DEFAULT_RHO_LIN"]
