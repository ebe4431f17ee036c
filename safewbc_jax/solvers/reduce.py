"""Exact elimination of the equality rows of the controller's QP (pure JAX).

The seam QP over X = [q_ddot (nv), u (nu), lambda (nc)] has the equality rows

    M q_ddot - B u - J^T lambda = -h          (dynamics, nv rows)
    J~ q_ddot + D lambda        = r           (chains and contacts, nc rows; a foot in
                                               the air has J~ row 0 and D = 1: lambda = 0)

For any u they fix q_ddot and lambda: with a = M^-1 B, c = M^-1 J^T, e = M^-1 h and
K = J~ c + D (the constraint-space inverse inertia, plus D),

    lambda  = lambda0 + L u,        lambda0 = K^-1 (r + J~ e),   L = -K^-1 J~ a
    q_ddot  = (c lambda0 - e) + (a + c L) u

so every feasible X is X = x0 + N u, and the QP becomes one in the nu = 20 joint torques
alone, with their torque limits as plain bounds and the contact, ZMP and barrier rows
G N u <= h - G x0. It is the same problem (the equalities hold exactly), solved in 20
variables instead of 78 with no equality rows; PIQP's work per iteration grows with the
cube of the variable count. The factorisations are one Cholesky of M (36 x 36) and one LU
of K (22 x 22); the QP itself keeps the paper's form (no mass-matrix inverse appears in
it) and this reduction is a solver-side step that both solvers may use.

Bounds on q_ddot or lambda, if any are finite, are turned into rows of G (``bounded``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from safewbc_jax.qp_types import QP


class Reduction(NamedTuple):
    x0: object   # (n,) the solution for u = 0
    N: object    # (n, nu) d X / d u


def bounded_variables(qp: QP, nv: int, nu: int) -> np.ndarray:
    """Indices outside u with a finite bound (static data for :func:`eliminate_equalities`;
    empty for the controller's QP)."""
    lb, ub = np.asarray(qp.lb), np.asarray(qp.ub)
    idx = np.flatnonzero(np.isfinite(lb) | np.isfinite(ub))
    return idx[(idx < nv) | (idx >= nv + nu)]


def eliminate_equalities(qp: QP, nv: int, nu: int, bounded=np.zeros(0, int)) -> tuple[QP, Reduction]:
    """The reduced QP in u and the map back X = x0 + N u (JAX: jit, vmap)."""
    return _eliminate(qp, nv, nu, bounded, jnp, jsl)


def eliminate_equalities_np(qp: QP, nv: int, nu: int, bounded=np.zeros(0, int)) -> tuple[QP, Reduction]:
    """The same computation in numpy/scipy, for the single-robot path (a handful of
    LAPACK calls on the host cost less than their XLA CPU dispatch)."""
    qp = QP(*(np.asarray(getattr(qp, f)) for f in ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")))
    return _eliminate(qp, nv, nu, bounded, np, _ScipyFast)


class _ScipyFast:
    """scipy.linalg's factorisations without their input checks (the inputs come from the
    jitted assembly; a non-finite QP is caught by the solver's acceptance checks)."""

    @staticmethod
    def cho_factor(a, lower=True):
        import scipy.linalg as sl

        return sl.cho_factor(a, lower=lower, check_finite=False)

    @staticmethod
    def cho_solve(c, b):
        import scipy.linalg as sl

        return sl.cho_solve(c, b, check_finite=False)

    @staticmethod
    def lu_factor(a):
        import scipy.linalg as sl

        return sl.lu_factor(a, check_finite=False)

    @staticmethod
    def lu_solve(lu, b):
        import scipy.linalg as sl

        return sl.lu_solve(lu, b, check_finite=False)


def _eliminate(qp: QP, nv, nu, bounded, xp, linalg):
    """Shared body; ``xp`` is jax.numpy or numpy, ``linalg`` jax.scipy.linalg or scipy.linalg."""
    a_mat = qp.A
    M = a_mat[:nv, :nv]
    B = -a_mat[:nv, nv:nv + nu]
    Jt = -a_mat[:nv, nv + nu:]
    Jr = a_mat[nv:, :nv]
    D = a_mat[nv:, nv + nu:]
    h = -qp.b[:nv]
    r = qp.b[nv:]
    chol = linalg.cho_factor(0.5 * (M + M.T), lower=True)
    sol = linalg.cho_solve(chol, xp.concatenate([B, Jt, h[:, None]], axis=1))
    a, c, e = sol[:, :nu], sol[:, nu:-1], sol[:, -1]
    K = Jr @ c + D
    lu = linalg.lu_factor(K)
    rhs = linalg.lu_solve(lu, xp.concatenate([(r + Jr @ e)[:, None], -(Jr @ a)], axis=1))
    lam0, L = rhs[:, 0], rhs[:, 1:]
    dtype = qp.P.dtype
    x0 = xp.concatenate([c @ lam0 - e, xp.zeros(nu, dtype), lam0])
    N = xp.concatenate([a + c @ L, xp.eye(nu, dtype=dtype), L], axis=0)
    p_r = N.T @ qp.P @ N
    p_r = 0.5 * (p_r + p_r.T)
    q_r = N.T @ (qp.P @ x0 + qp.q)
    g_rows, h_rows = [qp.G @ N], [qp.h - qp.G @ x0]
    soft = [qp.soft]
    if bounded.size:
        e_b = xp.asarray(np.eye(x0.shape[0])[bounded], dtype)
        g_rows += [e_b @ N, -(e_b @ N)]
        h_rows += [qp.ub[bounded] - e_b @ x0, -(qp.lb[bounded] - e_b @ x0)]
        soft.append(xp.zeros(2 * bounded.size, dtype))
    hh = xp.concatenate(h_rows)
    red = QP(P=p_r, q=q_r, A=xp.zeros((0, nu), dtype), b=xp.zeros(0, dtype),
             G=xp.concatenate(g_rows, axis=0), h=xp.where(xp.isfinite(hh), hh, 1e30),
             lb=qp.lb[nv:nv + nu], ub=qp.ub[nv:nv + nu], soft=xp.concatenate(soft))
    return red, Reduction(x0=x0, N=N)


def expand(u, red: Reduction):
    """X = x0 + N u."""
    return red.x0 + red.N @ u
