"""Stage 1 of both solvers: the equality rows out, exactly (the controller's QP), or by
the null-space method (any QP, JAX solver only).

The controller's QP over X = [q_ddot (nv), u (nu), lambda (nc)] (block sizes from the
QP, ``qp_types.QP``) has the equality rows

    M q_ddot - B u - J^T lambda = -h          (dynamics, nv rows; paper eq. 1)
    J~ q_ddot + D lambda        = r           (chains and contacts, nc rows, eqs. 2-3; a
                                               foot in the air has J~ row 0 and D = 1:
                                               lambda = 0)

For any u they fix q_ddot and lambda: with a = M^-1 B, c = M^-1 J^T, e = M^-1 h and
K = J~ c + D (the constraint-space inverse inertia, plus D),

    lambda  = lambda0 + L u,        lambda0 = K^-1 (r + J~ e),   L = -K^-1 J~ a
    q_ddot  = (c lambda0 - e) + (a + c L) u

so every feasible X is X = x0 + N u, N = [a + c L; I; L], and the QP becomes one in the
nu joint torques alone, with their torque limits as plain bounds and the contact, ZMP and
barrier rows G N u <= h - G x0. It is the same problem (the equalities hold exactly),
solved in nu variables instead of n with no equality rows; PIQP's work per iteration
grows with the cube of the variable count. The factorisations are one Cholesky of M and
one LU of K; the QP itself keeps the paper's form (no mass-matrix inverse appears in it)
and this reduction is a solver-side step that both solvers use. Bounds on q_ddot or
lambda, if any are finite, are turned into rows of G (``bounded_variables``).

``eliminate`` is written once against ``xp`` (numpy or jax.numpy) and a set of
factorisations (``HOST``: scipy on the host; ``JAX``: jax.scipy, for jit; ``BATCHED``:
``lapack_batched``, safe under vmap). N's identity block is never multiplied, and with
``p_blockdiag`` (P without q_ddot/u/lambda cross blocks, as the controller's;
``p_block_diagonal`` checks it) only P's diagonal blocks are; with ``p_blockdiag=
"diagonal"`` (as ``p_structure`` finds for the controller's QP, whose u and lambda blocks
are the diagonal Gamma) the lambda block is applied as its diagonal. A QP that carries its
q_ddot block in task form (``QP.p_factor``: J' diag(w) J + diag(d), the task rows J) has
it applied as J' (w (J y)) + d y: with m task rows, 2 m nv products per column against
nv^2, and the nv x nv block itself is never formed.

``reduce_generic``: a QP without that structure (JAX solver, ``jax_qp.solve_generic``):
x = Y R^-T b + Z y with Z an orthonormal basis of null(A) from a complete QR of A' (the
classical null-space method; A must have full row rank), finite bounds becoming rows.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np

from safewbc_jax.solvers.problem import QP
from safewbc_jax.solvers import lapack_batched as lbt
from safewbc_jax.solvers.settings import BIG


class Reduction(NamedTuple):
    x0: Any   # (n,) the solution for u = 0
    N: Any    # (n, nu) d X / d u


class Factorisations(NamedTuple):
    """chol(M) -> a factor of symmetric positive definite M (its lower triangle read);
    chol_solve(factor, B) -> M^-1 B; solve(K, B) -> K^-1 B (LU with partial pivoting)."""

    chol: Any
    chol_solve: Any
    solve: Any


def _scipy_fast():
    """scipy.linalg's factorisations without their input checks (the inputs come from the
    jitted assembly; a non-finite QP is caught by the acceptance checks)."""
    import scipy.linalg as sl

    return Factorisations(
        chol=lambda M: sl.cho_factor(M, lower=True, check_finite=False),
        chol_solve=lambda c, B: sl.cho_solve(c, B, check_finite=False),
        solve=lambda K, B: sl.lu_solve(sl.lu_factor(K, check_finite=False), B,
                                       check_finite=False))


# M as is: the robot model's M is exactly symmetric by construction (``robot._joint_space``
# mirrors one triangle), and LAPACK and the generated C read its lower triangle only, so
# symmetrising it, (M + M')/2, would change no bit and cost a transpose and two passes
JAX = Factorisations(chol=lambda M: jsl.cho_factor(M, lower=True),
                     chol_solve=jsl.cho_solve,
                     solve=lambda K, B: jsl.lu_solve(jsl.lu_factor(K), B))
BATCHED = Factorisations(chol=lbt.cholesky_lower, chol_solve=lbt.cho_solve, solve=lbt.solve)


def _blocks(qp: QP) -> tuple[int, int]:
    if not qp.has_blocks:
        raise ValueError("the controller's elimination needs the QP's block sizes nv, nu "
                         "(a QP from qp.assemble carries them); for another QP use the "
                         "generic path (jax_qp.solve_generic)")
    return qp.blocks.nv, qp.blocks.nu


def bounded_variables(qp: QP) -> np.ndarray:
    """Indices outside u with a finite bound (static data of the elimination; empty for
    the controller's QP). Concrete arrays; one QP, or a batch whose QPs share it."""
    nv, nu = _blocks(qp)
    lb, ub = np.asarray(qp.lb), np.asarray(qp.ub)
    fin = np.isfinite(lb) | np.isfinite(ub)
    idx = np.flatnonzero(fin.reshape(-1, fin.shape[-1])[0])
    return idx[(idx < nv) | (idx >= nv + nu)]


def _diagonal(a):
    """The diagonal of square ``a`` as a strided slice of its flat view (numpy or JAX; no
    gather, no iota)."""
    return a.reshape(-1)[::a.shape[0] + 1]


def eliminate(qp: QP, bounded=None, p_blockdiag: bool | str = False, *, xp=jnp,
              la: Factorisations = JAX) -> tuple[QP, Reduction]:
    """The reduced QP in u (no block sizes, no equality rows) and the map back
    X = x0 + N u (module docstring); one QP (vmap it for a batch)."""
    nv, nu = _blocks(qp)
    bounded = np.zeros(0, int) if bounded is None else np.asarray(bounded, int)
    dt = qp.P.dtype
    A, P, G = qp.A, qp.P, qp.G
    n = P.shape[0]
    iq, iu, il = slice(0, nv), slice(nv, nv + nu), slice(nv + nu, n)
    M = A[:nv, :nv]
    Bm = -A[:nv, iu]
    Jt = -A[:nv, il]
    Jr = A[nv:, :nv]
    D = A[nv:, il]
    hq = -qp.b[:nv]
    r = qp.b[nv:]
    # Each product below carries the u = 0 column beside N's nu columns ([x0 | N] per
    # block): a handful of larger products instead of twice as many small ones (XLA on
    # the CPU pays per operation).
    # M is factored in reverse order, the tree's leaves first (Featherstone's order for
    # the L'L factorisation): its factor then has no fill-in beyond M's own sparsity
    # (Digit: 335 of 666 entries, against 660 in the model's root-first order), which
    # the generated C's triangular solves skip
    rv = slice(None, None, -1)
    rhs = xp.concatenate([-hq[:, None], Bm, Jt], axis=1)
    sol = la.chol_solve(la.chol(M[rv, rv]), rhs[rv])[rv]
    js = Jr @ sol                                   # [-J e, J a, J c]
    lam = la.solve(js[:, nu + 1:] + D, xp.concatenate([r[:, None], xp.zeros_like(js[:, :nu])],
                                                      axis=1) - js[:, :nu + 1])
    y = sol[:, nu + 1:] @ lam + sol[:, :nu + 1]    # [x0 | N] on q_ddot; lam: on lambda
    x0q, Nq, lam0, L = y[:, 0], y[:, 1:], lam[:, 0], lam[:, 1:]
    yl = xp.concatenate([y, lam], axis=0)
    x0 = xp.concatenate([x0q, xp.zeros(nu, dt), lam0])
    if p_blockdiag:                   # [x0 | N]' P [x0 | N] and N' q in one product
        p_ll = P[il, il]
        plam = (_diagonal(p_ll)[:, None] * lam if p_blockdiag == "diagonal" else p_ll @ lam)
        pf = qp.p_factor              # P_qq y in task form: J' (w * (J y)) + d * y
        pqq_y = (P[iq, iq] @ y if pf is None
                 else pf.J.T @ (pf.w[:, None] * (pf.J @ y)) + pf.d[:, None] * y)
        py = xp.concatenate([pqq_y, plam], axis=0)
        ql = xp.concatenate([qp.q[iq], qp.q[il]])[:, None]
        hh_ = yl.T @ xp.concatenate([py, ql], axis=1)
        p_r = hh_[1:, 1:-1] + P[iu, iu]
        q_r = hh_[1:, 0] + hh_[1:, -1] + qp.q[iu]
    else:
        PN = P[:, iq] @ Nq + P[:, iu] + P[:, il] @ L
        p_r = Nq.T @ PN[iq] + PN[iu] + L.T @ PN[il]
        px0 = P @ x0 + qp.q
        q_r = Nq.T @ px0[iq] + px0[iu] + L.T @ px0[il]
    p_r = 0.5 * (p_r + p_r.T)
    k = qp.ng_lambda
    if k is None:
        gx = G[:, iq] @ y + G[:, il] @ lam
        g_rows = [gx[:, 1:] + G[:, iu]]
    else:                             # zero blocks by construction (qp_types: ng_lambda)
        gx = xp.concatenate([G[:k, il] @ lam, G[k:, iq] @ y], axis=0)
        g_rows = [gx[:, 1:]]
    h_rows = [qp.h - gx[:, 0]]
    soft = [qp.soft]
    N = xp.concatenate([Nq, xp.eye(nu, dtype=dt), L], axis=0)
    if bounded.size:
        Nb, xb = N[bounded], x0[bounded]
        g_rows += [Nb, -Nb]
        h_rows += [qp.ub[bounded] - xb, -(qp.lb[bounded] - xb)]
        soft.append(xp.zeros(2 * bounded.size, dt))
    hh = xp.concatenate(h_rows)
    red = QP(P=p_r, q=q_r, A=xp.zeros((0, nu), dt), b=xp.zeros(0, dt),
             G=xp.concatenate(g_rows, axis=0), h=xp.where(xp.isfinite(hh), hh, 1e30),
             lb=qp.lb[iu], ub=qp.ub[iu], soft=xp.concatenate(soft))
    return red, Reduction(x0=x0, N=N)


def eliminate_equalities(qp: QP, bounded=None, p_blockdiag: bool | str = False):
    """``eliminate`` in JAX (jax.scipy factorisations; for jit, not for large vmaps:
    those take ``BATCHED``)."""
    return eliminate(qp, bounded, p_blockdiag, xp=jnp, la=JAX)


def eliminate_equalities_np(qp: QP, bounded=None, p_blockdiag: bool | str = False):
    """``eliminate`` in numpy/scipy on the host (a handful of LAPACK calls on the host
    cost less than their XLA CPU dispatch)."""
    qp = qp.with_arrays(lambda a: np.asarray(a))
    return eliminate(qp, bounded, p_blockdiag, xp=np, la=_scipy_fast())


def expand(u, red: Reduction):
    """X = x0 + N u; leading axes of u and of red's arrays are a batch."""
    if u.ndim == 1:
        return red.x0 + red.N @ u
    return red.x0 + (red.N @ u[..., None])[..., 0]


def has_controller_structure(qp: QP) -> bool:
    """Host-side check (concrete arrays, one QP or a batch) that the controller's
    elimination applies: block sizes carried, n = nv + nu + nc with nv + nc equality
    rows, the constraint rows free of u, and symmetric mass-matrix blocks."""
    if not qp.has_blocks:
        return False
    nv, nu = qp.blocks.nv, qp.blocks.nu
    P, A = np.asarray(qp.P), np.asarray(qp.A)
    n, me = P.shape[-1], A.shape[-2]
    nc = n - nv - nu
    if nc < 0 or me != nv + nc or A.shape[-1] != n or (qp.nc is not None and qp.nc != nc):
        return False
    if np.any(A[..., nv:, nv:nv + nu] != 0):
        return False
    M = A[..., :nv, :nv]
    return bool(np.allclose(M, np.swapaxes(M, -1, -2), rtol=1e-10, atol=1e-12))


def p_structure(qp: QP) -> bool | str:
    """Host-side check (concrete P, one QP or a batch) of what ``eliminate`` may assume of
    P: "diagonal" (no cross blocks, and the u and lambda blocks diagonal), True (no cross
    blocks) or False."""
    if not p_block_diagonal(qp):
        return False
    P = np.asarray(qp.P)
    nv = qp.blocks.nv
    rest = P[..., nv:, nv:]
    off = rest - rest * np.eye(rest.shape[-1])
    return "diagonal" if not np.any(off) else True


def p_block_diagonal(qp: QP) -> bool:
    """Host-side check (concrete P, one QP or a batch) that P has no cross terms between
    the q_ddot, u and lambda blocks (False for a QP without block sizes)."""
    if not qp.has_blocks:
        return False
    P = np.asarray(qp.P)
    nv, nu = qp.blocks.nv, qp.blocks.nu
    s = [slice(0, nv), slice(nv, nv + nu), slice(nv + nu, P.shape[-1])]
    return not any(np.any(P[..., s[i], s[j]]) for i in range(3) for j in range(3) if i != j)


# ------------------------------------------------------------------ any QP (JAX solver)

def _nullspace(qp: QP):
    """x = xp + Z y with Z an orthonormal basis of null(A) (complete QR of A')."""
    me = qp.A.shape[0]
    Q, R = jnp.linalg.qr(qp.A.T, mode="complete")
    R1 = R[:me, :]
    Y, Z = Q[:, :me], Q[:, me:]
    w = jsl.solve_triangular(R1, qp.b, trans="T", lower=False)
    xp_ = Y @ w
    d = jnp.abs(jnp.diag(R1))
    rank_ok = jnp.min(d) > 1e3 * jnp.finfo(qp.P.dtype).eps * jnp.maximum(jnp.max(d), 1.0)
    return xp_, Z, rank_ok


def reduce_generic(qp: QP) -> tuple[QP, Reduction, jax.Array]:
    """(reduced QP, Reduction, rank ok) of a general QP, in JAX: no equalities -> the QP
    itself (bounds as bounds, infinite entries as +-1e30); else the null-space method,
    finite bounds becoming hard rows. A with as many rows as variables (full rank: x
    fixed by A x = b, null(A) = {0}) gets a reduced problem in one dummy variable y that
    x does not depend on (Z = 0, cost y^2/2), so that the rows and bounds are still
    checked at x = xp (their rows 0 y <= h - G xp). More rows than variables cannot be
    of full row rank: ValueError."""
    dtype = qp.P.dtype
    n, me = qp.P.shape[0], qp.A.shape[0]
    if me > n:
        raise ValueError(f"the generic JAX path needs A of full row rank: A has {me} rows "
                         f"for {n} variables (remove the redundant equalities, or use "
                         "solver='piqp')")
    fin = lambda v, big: jnp.where(jnp.isfinite(v), v, big)  # noqa: E731
    if me == 0:
        red = QP(P=qp.P, q=qp.q, A=qp.A, b=qp.b, G=qp.G, h=fin(qp.h, 1e30),
                 lb=fin(qp.lb, -1e30), ub=fin(qp.ub, 1e30), soft=qp.soft)
        return red, Reduction(jnp.zeros(n, dtype), jnp.eye(n, dtype=dtype)), jnp.ones((), bool)
    xp_, Z, rank_ok = _nullspace(qp)
    nz = n - me
    Pz = Z.T @ qp.P @ Z
    Pz = 0.5 * (Pz + Pz.T)
    qz = Z.T @ (qp.P @ xp_ + qp.q)
    if nz == 0:                       # x = xp: a dummy variable, absent from x
        nz = 1
        Z = jnp.zeros((n, 1), dtype)
        Pz = jnp.ones((1, 1), dtype)
        qz = jnp.zeros(1, dtype)
    lbf = qp.lb > -BIG
    ubf = qp.ub < BIG
    Gz = jnp.concatenate([qp.G @ Z, Z, -Z], axis=0)
    hz = jnp.concatenate([qp.h - qp.G @ xp_, jnp.where(ubf, qp.ub - xp_, 1e30),
                          jnp.where(lbf, xp_ - qp.lb, 1e30)])
    inf = jnp.full(nz, 1e30, dtype)
    red = QP(P=Pz, q=qz, A=jnp.zeros((0, nz), dtype), b=jnp.zeros(0, dtype), G=Gz,
             h=fin(hz, 1e30), lb=-inf, ub=inf,
             soft=jnp.concatenate([qp.soft, jnp.zeros(2 * n, dtype)]))
    return red, Reduction(xp_, Z), rank_ok


__all__ = ["Reduction", "Factorisations", "JAX", "BATCHED", "bounded_variables", "eliminate",
           "eliminate_equalities", "eliminate_equalities_np", "expand",
           "has_controller_structure", "p_block_diagonal", "p_structure", "reduce_generic"]
