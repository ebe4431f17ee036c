"""A pure-JAX QP solver for the controller's QPs: jit- and vmap-able, fixed shapes.

Problem (the seam QP of ``safewbc_jax.qp_types``)

    minimize    1/2 x'Px + q'x
    subject to  A x = b,   G x <= h,   lb <= x <= ub

solved, per instance, in three stages.

1. Equalities out. For the controller's QP, X = [q_ddot (nv), u (nu), lambda (nc)], the
   equality rows (dynamics and constraints) fix q_ddot and lambda for every u, and
   ``reduce.eliminate_equalities`` writes every feasible X as X = x0 + N u exactly (one
   Cholesky of the mass matrix, one LU of the constraint-space matrix). What is left is a
   QP in the nu = 20 torques alone: box bounds (the torque limits) and ~23 rows (friction,
   unilateral contact, ZMP, barrier), no equalities. For a general QP without that
   structure (``solve_generic``) the equalities are eliminated through a complete QR
   factorisation of A' (x = Y R^-T b + Z y, Z an orthonormal basis of null(A), the
   classical null-space method; A must have full row rank), finite bounds becoming rows
   when there are equalities.

2. Interior point on the reduced QP. A primal-dual interior-point method with Mehrotra's
   predictor-corrector (S. Mehrotra, "On the implementation of a primal-dual interior
   point method", SIAM J. Optim. 1992; for QPs as in Nocedal & Wright, Numerical
   Optimization, ch. 16.6 and Gertz & Wright's OOQP), an infeasible start shifted into the
   positive orthant as in Nocedal & Wright (14.3), one step length for primal and dual
   (fraction to the boundary 0.99). Every inequality has a slack t >= 0 and a multiplier
   z >= 0; the bounds are kept as bounds. The Newton system is reduced to the n x n
   matrix  H = P + G' W G + diag(z_u/t_u + z_l/t_l) (+ a 1e-12 regularisation, scaled)
   and factored by a dense Cholesky, once per iteration for the predictor and the
   corrector. Every factorisation of the controller's path goes through
   ``solvers/lapack_batched.py``: under vmap, jaxlib's LAPACK kernels in sub-batches small
   enough to run inline (one big batched call can deadlock XLA's CPU thread pool). The
   problem is scaled first: variables by half their box width, each row of G to unit
   max-norm, the cost to a unit max-norm Hessian/gradient.

   The fallback's relaxed problem (``relax.relax_soft_rows``: a slack s_i >= 0 on each soft
   row, cost rho/2 s_i^2 + rho_lin s_i) is solved by the same iteration with the slacks
   as variables of their own: their block of the Newton system is diagonal and is
   eliminated, so H keeps its n x n size (W_i = D_i (rho + y_i/s_i)/(rho + D_i + y_i/s_i)
   on soft rows instead of D_i = z_i/t_i). It is the same problem as PIQP's relaxed QP in
   [x; s] (hard rows' slacks are pinned to zero there and absent here).

   Stopping (on the scaled problem; eps_abs, eps_rel from ``Settings``):
     primal  ||G u - s - h + t, u - ub + t_u, lb - u + t_l||_inf
                 <= eps_abs + eps_rel max(||G u||, ||h||, ||u||, ||s||)
     dual    ||P u + q + G'z + z_u - z_l, rho s + rho_lin - z - y||_inf
                 <= eps_abs + eps_rel max(||P u||, ||q||, ||G'z||, ||z_u - z_l||)
     gap     mean complementarity (t'z + t_u'z_u + t_l'z_l + s'y)/m <= eps_abs
   -> SOLVED. Primal infeasibility is certified by Farkas' lemma with the bounds built in:
   for y >= 0 on the rows that cannot be relaxed, with g = G'y,
       phi(y) = sum_j min(g_j lb_j, g_j ub_j) - h'y > 0
   proves that no u in the box satisfies G u <= h (a direction g_j of an infinite bound
   must be ~0). It is checked on the normalised multipliers y = z/||z||_inf at every
   iteration (the multipliers of an infeasible problem diverge along such a certificate),
   with phi > eps_inf (1 + |h|'y + sum_j |g_j| max(|lb_j|, |ub_j|)) -> INFEASIBLE. Dual
   infeasibility (unbounded below, only possible with a singular P) is certified by a
   step direction d with P d ~ 0, q'd < 0 and d feasible for the recession cone ->
   INFEASIBLE. A non-finite iterate or factor -> NUMERICAL (the last finite iterate is
   kept); ``max_iter`` iterations without either -> MAX_ITER.

3. Polish. From the converged interior point the active set is read off (t < z, likewise
   for bounds and soft-row slacks) and the equality-constrained KKT system of that active
   set is solved exactly (an (n + m) x (n + m) LU with one step of iterative refinement;
   the approach of OSQP's solution polishing, Stellato et al. 2020). The polished point
   replaces the interior point when it is primal feasible and its multipliers have the
   right signs (to 1e-9 relative, float64); otherwise the interior point stays. This takes
   the solution from the IPM's ~1e-9 to ~1e-13 of the exact optimum, which matters here:
   the reduced Hessian has a condition number ~1e7 (the internal-force directions of
   lambda cost only the small regularisation Gamma).

Fallback policy (the same as ``piqp_path.PiqpSolver``): solve; accept when SOLVED and the
full-space residuals pass ``feas_tol`` (relative to 1 + max |b| and 1 + max finite |h|,
|lb|, |ub|), else the status is NUMERICAL; when not accepted, solve the relaxed problem ->
fallback RELAXED with ``max_slack``; when that fails too, fallback FAILED and x is all NaN
(never a number that could be mistaken for a command: the caller holds its last good
torque). In a batch the relaxed solve is a second ``lax.while_loop`` whose instances
start "done" unless they need it, so a batch in which every QP solves pays for its
initial point only, not for its iterations.

Batches: every function here works on one QP and is written for ``jax.vmap``; a vmapped
``lax.while_loop`` runs until every instance of the batch has stopped, the stopped ones
frozen. ``solve_batch`` / ``solve_generic_batch`` are the jitted, vmapped versions. On a
CPU they solve a large batch in chunks (``chunk``, 64 QPs by default): the batch is cut
into equal chunks of at most that size (padded with copies of its last QP) and a
``lax.map`` runs the vmapped solver over one chunk after the other inside the same jitted
call, because one vmap over the whole batch is slower per QP there (see ``solve_batch``).

dtype: float64 by default; ``dtype=jnp.float32`` casts the QP and uses float32 settings
(``Settings.for_dtype``: eps_abs 1e-5, looser acceptance 1e-3) for accelerators; expect
~1e-3 relative agreement there, the reduced problem being ill-conditioned.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax import lax

from safewbc_jax.chunking import chunked, resolve_chunk
from safewbc_jax.qp_types import QP
from safewbc_jax.solvers import lapack_batched as lb
from safewbc_jax.solvers.relax import DEFAULT_RHO, DEFAULT_RHO_LIN
from safewbc_jax.solvers.status import INFEASIBLE, MAX_ITER, NUMERICAL, SOLVED

FALLBACK_NONE = 0      # the QP as posed was solved
FALLBACK_RELAXED = 1   # the relaxed QP (soft rows with slack) was solved instead
FALLBACK_FAILED = 2    # neither: x is all NaN, the caller must not use it
FALLBACK_NAMES = ("none", "relaxed", "failed")

_BIG = 1e20            # |h| or |bound| at or above this counts as infinite
_RUNNING = -1


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


class Result(NamedTuple):
    """Per-instance outcome (leading batch dimension on every field in a batch).

    x               (n,) the solution of the QP as posed (fallback NONE), of the relaxed
                    QP (RELAXED), or all NaN (FAILED)
    status          int32 SolveStatus of the QP as posed, after the acceptance check
    fallback        int32 FALLBACK_NONE / FALLBACK_RELAXED / FALLBACK_FAILED
    relaxed_status  int32 SolveStatus of the relaxed solve, -1 where it was not needed
    iterations      int32 interior-point iterations, both solves together
    max_slack       largest soft-row slack of the relaxed solution (0 for NONE, NaN FAILED)
    eq_residual     max |A x - b| (NaN for FAILED)
    ineq_violation  max violation of G x <= h and the bounds, soft rows included
    hard_violation  the same over hard rows and bounds only
    polished        the returned x is the active-set polish's exact KKT point (else the
                    interior point, accurate to the IPM's tolerances only)
    polish_iterations  KKT solves of the polish, both solves together
    """

    x: jax.Array
    status: jax.Array
    fallback: jax.Array
    relaxed_status: jax.Array
    iterations: jax.Array
    max_slack: jax.Array
    eq_residual: jax.Array
    ineq_violation: jax.Array
    hard_violation: jax.Array
    polished: jax.Array
    polish_iterations: jax.Array


# ---------------------------------------------------------------------- the box QP

class _Box(NamedTuple):
    """Scaled QP  min 1/2 u'Pu + q'u + sum_{sig} (rho/2 s^2 + c s)
    s.t. G u - sig*s <= h (rows with row_on), s >= 0 (sig rows), lb <= u <= ub (where on)."""

    P: jax.Array
    q: jax.Array
    G: jax.Array
    h: jax.Array
    lb: jax.Array
    ub: jax.Array
    row_on: jax.Array
    lb_on: jax.Array
    ub_on: jax.Array
    sig: jax.Array
    rho: jax.Array
    c: jax.Array


class _Scale(NamedTuple):
    sx: jax.Array   # u = sx * u~
    er: jax.Array   # row i of G multiplied by er_i
    cs: jax.Array   # cost multiplied by cs


def _scale_problem(P, q, G, h, lb, ub, sig, rho, c):
    """Variables by half the box width, rows to unit max-norm, cost to unit max-norm."""
    dt = P.dtype
    lb_on = lb > -_BIG
    ub_on = ub < _BIG
    both = lb_on & ub_on
    width = jnp.where(both, 0.5 * (ub - lb), 1.0)
    sx = jnp.clip(width, 1e-3, 1e6).astype(dt)
    sx = jnp.where(both & (width > 0), sx, 1.0)
    Ps = P * sx[:, None] * sx[None, :]
    qs = q * sx
    Gs = G * sx[None, :]
    row_on = h < _BIG
    rn = jnp.max(jnp.abs(Gs), axis=1)
    er = jnp.where(rn > 0, 1.0 / jnp.where(rn > 0, rn, 1.0), 1.0)
    Gs = Gs * er[:, None]
    hs = jnp.where(row_on, h * er, 0.0)
    cmax = jnp.maximum(jnp.max(jnp.abs(Ps)), jnp.max(jnp.abs(qs)))
    cs = 1.0 / jnp.maximum(cmax, 1e-8)
    cs = jnp.where(jnp.isfinite(cs), cs, 1.0)
    lbs = jnp.where(lb_on, lb / sx, -1.0)
    ubs = jnp.where(ub_on, ub / sx, 1.0)
    sig = sig * row_on
    box = _Box(P=Ps * cs, q=qs * cs, G=Gs, h=hs, lb=lbs, ub=ubs, row_on=row_on,
               lb_on=lb_on, ub_on=ub_on, sig=sig,
               rho=jnp.where(sig > 0, rho * cs / er ** 2, 1.0).astype(dt),
               c=jnp.where(sig > 0, c * cs / er, 0.0).astype(dt))
    return box, _Scale(sx=sx, er=er, cs=cs)


class _It(NamedTuple):
    """An interior point, unpacked (for the polish)."""
    u: jax.Array
    s: jax.Array
    t: jax.Array
    z: jax.Array
    y: jax.Array
    tu: jax.Array
    zu: jax.Array
    tl: jax.Array
    zl: jax.Array


class _Pk(NamedTuple):
    """The box QP's inequalities packed for the interior point: the constraint rows
    C u <= d with C = [G; I; -I], d = [h; ub; -lb] (slack v_c >= 0, multiplier lam_c),
    followed by the relaxed rows' slack variables s >= 0 (multiplier y). Packed vectors
    have K = 2m + 2n entries [rows | upper bounds | lower bounds | slacks]; ``on`` marks
    the entries that exist (finite h / bounds, relaxed rows). C is never formed."""
    d: jax.Array
    on: jax.Array
    sg: jax.Array
    sigf: jax.Array
    nc: jax.Array


class _PIt(NamedTuple):
    u: jax.Array     # (n,)
    v: jax.Array     # (K,) primal slacks [t | t_u | t_l | s]
    lam: jax.Array   # (K,) multipliers [z | z_u | z_l | y]


class _Carry(NamedTuple):
    x: _PIt
    k: jax.Array
    status: jax.Array


def _pack(pb: _Box) -> _Pk:
    dt = pb.P.dtype
    on_c = jnp.concatenate([pb.row_on, pb.ub_on, pb.lb_on])
    d = jnp.where(on_c, jnp.concatenate([pb.h, pb.ub, -pb.lb]), 0.0)
    sg = pb.sig > 0
    on = jnp.concatenate([on_c, sg])
    return _Pk(d=d, on=on, sg=sg, sigf=sg.astype(dt),
               nc=jnp.maximum(jnp.sum(on, dtype=dt), 1.0))


def _c(G, u):
    """C u for C = [G; I; -I]."""
    return jnp.concatenate([G @ u, u, -u])


def _ct(G, a):
    """C' a for C = [G; I; -I]."""
    m, n = G.shape
    return G.T @ a[:m] + a[m:m + n] - a[m + n:]


def _unpack(x: _PIt, m: int, n: int) -> _It:
    v, lam = x.v, x.lam
    return _It(u=x.u, s=v[m + 2 * n:], t=v[:m], z=lam[:m], y=lam[m + 2 * n:],
               tu=v[m:m + n], zu=lam[m:m + n], tl=v[m + n:m + 2 * n], zl=lam[m + n:m + 2 * n])


def _residuals(x: _PIt, pb: _Box, pk: _Pk):
    m, n = pb.G.shape[0], pb.P.shape[0]
    mc = m + 2 * n
    s, y = x.v[mc:], x.lam[mc:]
    Cu = _c(pb.G, x.u)
    Pu = pb.P @ x.u
    Cl = _ct(pb.G, x.lam[:mc])
    rd = Pu + pb.q + Cl
    rs = jnp.where(pk.sg, pb.rho * s + pb.c - x.lam[:m] - y, 0.0)
    sig_s = jnp.concatenate([pk.sigf * s, jnp.zeros(2 * n, s.dtype)])
    rp = jnp.where(pk.on[:mc], Cu - sig_s - pk.d + x.v[:mc], 0.0)
    return rd, rs, rp, Cu, Pu, Cl


def _mu(x: _PIt, pk: _Pk):
    return jnp.sum(jnp.where(pk.on, x.v * x.lam, 0.0)) / pk.nc


def _inf_norm(*vs):
    return jnp.max(jnp.stack([jnp.max(jnp.abs(v), initial=0.0) for v in vs]))


def _primal_infeasible(z, pb: _Box, eps):
    """Farkas certificate with the bounds built in, on y = z / ||z|| over hard rows."""
    y = jnp.where(pb.row_on & (pb.sig <= 0), jnp.maximum(z, 0.0), 0.0)
    ymax = jnp.max(y)
    y = y / jnp.where(ymax > 0, ymax, 1.0)
    g = pb.G.T @ y
    lo = jnp.where(pb.lb_on, g * pb.lb, 0.0)
    hi = jnp.where(pb.ub_on, g * pb.ub, 0.0)
    # direction g_j > 0 needs lb_j finite, g_j < 0 needs ub_j finite
    unbounded = jnp.where(g > 0, ~pb.lb_on, ~pb.ub_on) & (g != 0)
    gmax = jnp.max(jnp.abs(g), initial=0.0)
    term = jnp.where(g > 0, lo, hi)
    phi = jnp.sum(term) - pb.h @ y
    scale = 1.0 + jnp.abs(pb.h) @ y + jnp.sum(jnp.abs(g) * jnp.maximum(jnp.abs(pb.lb),
                                                                        jnp.abs(pb.ub)))
    ok_dir = jnp.max(jnp.where(unbounded, jnp.abs(g), 0.0), initial=0.0) <= eps * (1 + gmax)
    return (ymax > 0) & ok_dir & (phi > eps * scale)


def _dual_infeasible(du, pb: _Box, eps):
    """A recession direction of strictly decreasing cost (only with a singular P)."""
    nrm = jnp.max(jnp.abs(du))
    d = du / jnp.where(nrm > 0, nrm, 1.0)
    Pd = pb.P @ d
    Gd = pb.G @ d
    qd = pb.q @ d
    pscale = jnp.maximum(jnp.max(jnp.abs(pb.P)), 1e-30)
    # relaxed rows never limit a direction (their slack absorbs it, at a quadratic cost
    # in s that a direction with G d > 0 would pay): only hard rows count
    rows_ok = jnp.all(jnp.where(pb.row_on & (pb.sig <= 0), Gd <= eps, True))
    rows_relaxed_ok = jnp.all(jnp.where(pb.sig > 0, Gd <= eps, True))
    box_ok = jnp.all(jnp.where(pb.ub_on, d <= eps, True) & jnp.where(pb.lb_on, d >= -eps, True))
    return ((nrm > 0) & (jnp.max(jnp.abs(Pd)) <= eps * pscale) & (qd < -eps * (1 + jnp.max(jnp.abs(pb.q))))
            & rows_ok & rows_relaxed_ok & box_ok)


def _converged(x: _PIt, pb: _Box, pk: _Pk, res, st: Settings):
    rd, rs, rp, Cu, Pu, Cl = res
    mc = pk.d.shape[0]
    pres = _inf_norm(rp)
    dres = _inf_norm(rd, rs)
    pscale = _inf_norm(jnp.where(pk.on[:mc], Cu, 0.0), pk.d, x.v[mc:])
    dscale = _inf_norm(Pu, pb.q, Cl)
    return ((pres <= st.eps_abs + st.eps_rel * pscale)
            & (dres <= st.eps_abs + st.eps_rel * dscale)
            & (_mu(x, pk) <= st.eps_abs))


def _newton_factory(x: _PIt, pb: _Box, pk: _Pk, st: Settings):
    """Factor the reduced Newton matrix at ``x``; return a solver for right-hand sides.

    With D = lam_c / v_c, the slacks and multipliers are eliminated from the Newton
    system, and so are the relaxed rows' slack variables s (their block is diagonal:
    E = rho + D + y/s), leaving H du = r with H = P + C' diag(W) C (+ reg I), W = D except
    on relaxed rows, W = D (rho + y/s) / E."""
    dt = pb.P.dtype
    n, m = pb.P.shape[0], pb.G.shape[0]
    mc = m + 2 * n
    on_c, sg = pk.on[:mc], pk.sg
    vc = jnp.where(on_c, x.v[:mc], 1.0)
    lc = x.lam[:mc]
    Dc = jnp.where(on_c, lc / vc, 0.0)
    s = x.v[mc:]
    y = x.lam[mc:]
    s_s = jnp.where(sg, s, 1.0)
    ys = jnp.where(sg, y / s_s, 0.0)
    DG = Dc[:m]
    E = jnp.where(sg, pb.rho + DG + ys, 1.0)
    W = jnp.concatenate([jnp.where(sg, DG * (pb.rho + ys) / E, DG), Dc[m:]])
    H = (pb.P + (pb.G.T * W[None, :m]) @ pb.G
         + jnp.diag(W[m:m + n] + W[m + n:] + st.reg))
    L = lb.cholesky(H)
    zeros2n = jnp.zeros(2 * n, dt)

    def solve(rd, rs, rp, rc):
        rc_c, rcs = rc[:mc], rc[mc:]
        a = jnp.where(on_c, (lc * rp - rc_c) / vc, 0.0)
        rhs_s = jnp.where(sg, -rs + a[:m] - rcs / s_s, 0.0)
        corr = jnp.concatenate([jnp.where(sg, DG * rhs_s / E, 0.0), zeros2n])
        du = lb.cho_solve(L, -rd - _ct(pb.G, a - corr))
        Cdu = _c(pb.G, du)
        ds = jnp.where(sg, (DG * Cdu[:m] + rhs_s) / E, 0.0)
        sds = jnp.concatenate([pk.sigf * ds, zeros2n])
        dv_c = jnp.where(on_c, -rp - Cdu + sds, 0.0)
        dl_c = jnp.where(on_c, Dc * (Cdu - sds) + a, 0.0)
        dy = jnp.where(sg, (-rcs - y * ds) / s_s, 0.0)
        return _PIt(u=du, v=jnp.concatenate([dv_c, ds]), lam=jnp.concatenate([dl_c, dy]))

    return L, solve


def _step_length(x: _PIt, d: _PIt, pk: _Pk):
    """Largest step keeping the packed slacks and multipliers non-negative."""
    xv = jnp.concatenate([x.v, x.lam])
    dv = jnp.concatenate([d.v, d.lam])
    on = jnp.concatenate([pk.on, pk.on])
    neg = on & (dv < 0)
    return jnp.min(jnp.where(neg, -xv / jnp.where(neg, dv, -1.0), jnp.inf))


def _initial_point(pb: _Box, pk: _Pk, st: Settings) -> _PIt:
    """Least-squares start u0 (cost + squared row residuals + pull to the box centre),
    then slacks and multipliers shifted into the positive orthant (Nocedal & Wright 14.3)."""
    dt = pb.P.dtype
    n, m = pb.P.shape[0], pb.G.shape[0]
    on, sg = pb.row_on, pk.sg
    box_on = pb.lb_on | pb.ub_on
    centre = jnp.where(pb.lb_on & pb.ub_on, 0.5 * (pb.lb + pb.ub),
                       jnp.where(pb.lb_on, pb.lb + 1.0, jnp.where(pb.ub_on, pb.ub - 1.0, 0.0)))
    Gon = jnp.where(on[:, None], pb.G, 0.0)
    H0 = (pb.P + Gon.T @ Gon + jnp.diag(box_on.astype(dt))
          + (st.reg + 1e-8) * jnp.eye(n, dtype=dt))
    r0 = -pb.q + Gon.T @ jnp.where(on, pb.h, 0.0) + jnp.where(box_on, centre, 0.0)
    u0 = lb.cho_solve(lb.cholesky(H0), r0)
    Cu = _c(pb.G, u0)
    s0 = jnp.where(sg, jnp.maximum(Cu[:m] - pb.h, 0.0), 0.0)
    sig_s = jnp.concatenate([pk.sigf * s0, jnp.zeros(2 * n, dt)])
    v = jnp.concatenate([pk.d - Cu + sig_s, s0])
    pmin = jnp.min(jnp.where(pk.on, v, jnp.inf))
    dp = jnp.maximum(-1.5 * jnp.where(jnp.isfinite(pmin), pmin, 0.0), 0.0)
    v = jnp.where(pk.on, v + dp, 0.0)
    nprod = jnp.sum(v)                                # multipliers are all 1 here
    v = jnp.where(pk.on, v + 0.5 * nprod / pk.nc, 1.0)
    lam = jnp.where(pk.on, 1.5, 0.0).astype(dt)
    return _PIt(u=u0, v=v, lam=lam)


def _ipm(pb: _Box, st: Settings, active):
    """Mehrotra predictor-corrector on the scaled box QP; ``active`` False: do nothing.
    Returns (unpacked iterate, status, iterations)."""
    n, m = pb.P.shape[0], pb.G.shape[0]
    pk = _pack(pb)
    x0 = _initial_point(pb, pk, st)
    status0 = jnp.where(active, _RUNNING, NUMERICAL).astype(jnp.int32)
    eta = 0.99

    def cond(c: _Carry):
        return (c.status == _RUNNING) & (c.k < st.max_iter)

    def body(c: _Carry):
        x = c.x
        rd, rs, rp, _, _, _ = _residuals(x, pb, pk)
        L, solve = _newton_factory(x, pb, pk, st)
        mu = _mu(x, pk)
        # predictor (affine scaling)
        d_aff = solve(rd, rs, rp, jnp.where(pk.on, x.v * x.lam, 0.0))
        a_aff = jnp.minimum(1.0, _step_length(x, d_aff, pk))
        mu_aff = jnp.sum(jnp.where(pk.on, (x.v + a_aff * d_aff.v) * (x.lam + a_aff * d_aff.lam),
                                   0.0)) / pk.nc
        sigma = jnp.clip(mu_aff / mu, 0.0, 1.0) ** 3
        # corrector (Mehrotra's second-order term, centring sigma * mu)
        rc = jnp.where(pk.on, x.v * x.lam + d_aff.v * d_aff.lam - sigma * mu, 0.0)
        d = solve(rd, rs, rp, rc)
        a = jnp.minimum(1.0, eta * _step_length(x, d, pk))
        new = _PIt(u=x.u + a * d.u, v=x.v + a * d.v, lam=x.lam + a * d.lam)
        finite = jnp.isfinite(jnp.sum(new.u) + jnp.sum(new.v) + jnp.sum(new.lam))
        res = _residuals(new, pb, pk)
        conv = _converged(new, pb, pk, res, st)
        pinf = _primal_infeasible(new.lam[:m], pb, st.eps_inf)
        dinf = _dual_infeasible(d.u, pb, st.eps_inf) & (a > 0.5)
        status = jnp.where(~finite, NUMERICAL,
                           jnp.where(conv, SOLVED,
                                     jnp.where(pinf | dinf, INFEASIBLE, _RUNNING))).astype(jnp.int32)
        x_out = jax.tree_util.tree_map(lambda n_, o: jnp.where(finite, n_, o), new, x)
        return _Carry(x=x_out, k=c.k + 1, status=status)

    conv0 = _converged(x0, pb, pk, _residuals(x0, pb, pk), st)
    status0 = jnp.where(active & conv0, SOLVED, status0).astype(jnp.int32)
    out = lax.while_loop(cond, body, _Carry(x=x0, k=jnp.zeros((), jnp.int32), status=status0))
    status = jnp.where(out.status == _RUNNING, MAX_ITER, out.status).astype(jnp.int32)
    return _unpack(out.x, m, n), status, out.k


def _kkt_factory(pb: _Box, dreg, refine: int = 2):
    """Range-space solver for the equality-constrained QPs of working sets (fixed shapes).

    The constraints are the rows of G and the bounds (rows e_j of I), indexed 0..m+n-1;
    a working set is a list ``widx`` of at most k of them (-1 pads). P is the same for
    every working set (a relaxed row's slack cost enters through the Schur complement),
    so one Cholesky P = L L' and C = L^-1 [G' I] are computed once; a working set then
    costs one k x k Cholesky of S = C_W' C_W + D (D = 1/rho on relaxed rows, a relative
    shift of ``dreg`` of S's diagonal on the others against degenerate sets, 1 on
    padding) and a triangular-solve pair for the solve and for each of the ``refine``
    steps of iterative refinement against the exact system.

    ``solve(widx, rstate, bstate)``: rstate per row 0 inactive (z = 0), 1 active (G u = h,
    s = 0), 2 relaxed (G u - s = h, s = (z - c)/rho free); bstate per variable 0 free,
    1 at ub, 2 at lb. Returns (u, z, s, g = P u + q + G'z)."""
    dt = pb.P.dtype
    n, m = pb.P.shape[0], pb.G.shape[0]
    eye = jnp.eye(n, dtype=dt)
    pn = jnp.max(jnp.abs(pb.P))
    L = lb.cholesky(pb.P + 10 * dreg * jnp.maximum(pn, 1e-30) * eye)
    Li = lb.solve_lower(L, eye)
    A = jnp.concatenate([pb.G, eye], axis=0)            # rows, then bounds: (m + n, n)
    C = Li @ A.T                                        # (n, m + n)
    gdiag = jnp.max(jnp.sum(C * C, axis=0))
    w = Li @ (-pb.q)

    def solve(widx, rstate, bstate):
        valid = widx >= 0
        ii = jnp.where(valid, widx, 0)
        is_row = ii < m
        ri = jnp.minimum(ii, m - 1)
        bj = jnp.clip(ii - m, 0, n - 1)
        rel = valid & is_row & (rstate[ri] == 2)
        act = valid & ~rel
        rho_w = jnp.where(rel, pb.rho[ri], 1.0)
        d = jnp.where(is_row, jnp.where(rel, pb.h[ri] - pb.c[ri] / rho_w, pb.h[ri]),
                      jnp.where(bstate[bj] == 1, pb.ub[bj], pb.lb[bj]))
        d = jnp.where(valid, d, 0.0)
        Cw = jnp.where(valid[None, :], C[:, ii], 0.0)  # (n, k)
        Aw = jnp.where(valid[:, None], A[ii], 0.0)     # (k, n)
        Dex = jnp.where(rel, 1.0 / rho_w, 0.0)
        S = Cw.T @ Cw
        dg = jnp.where(act, dreg * (jnp.diagonal(S) + 1e-30 * gdiag), jnp.where(rel, Dex, 1.0))
        Ls = lb.cholesky(S + jnp.diag(dg))

        def kkt(wv, e2):
            zw = lb.cho_solve(Ls, jnp.where(valid, Cw.T @ wv - e2, 0.0))
            zw = jnp.where(valid, zw, 0.0)
            return Li.T @ (wv - Cw @ zw), zw

        u, zw = kkt(w, d)
        for _ in range(refine):
            r1 = -(pb.P @ u + pb.q + Aw.T @ zw)
            r2 = jnp.where(valid, d - (Aw @ u - Dex * zw), 0.0)
            du, dz = kkt(Li @ r1, r2)
            u, zw = u + du, zw + dz
        u = jnp.where(bstate == 1, pb.ub, jnp.where(bstate == 2, pb.lb, u))
        zall = jnp.zeros(m + n, dt).at[ii].add(jnp.where(valid, zw, 0.0))
        zr = jnp.where(pb.row_on, zall[:m], 0.0)
        s = jnp.where(pb.row_on & (rstate == 2), (zr - pb.c) / pb.rho, 0.0)
        g = pb.P @ u + pb.q + pb.G.T @ zr
        return u, zr, s, g

    return solve


def _wset_add(widx, idx):
    """Put constraint ``idx`` in the first free slot; (widx, overflow)."""
    free = widx < 0
    slot = jnp.argmax(free)
    return jnp.where(jnp.arange(widx.shape[0]) == slot, idx, widx), ~jnp.any(free)


def _polish(it: _It, pb: _Box, st: Settings, active, kmax: int):
    """Finish on the exact optimum with a primal active-set method (Nocedal & Wright,
    Algorithm 16.3) started at the interior point: the working set is guessed from the
    IPM (t < z), each iteration solves the KKT system of the working set exactly
    (``_kkt_factory``) and steps towards its solution until a constraint outside the set
    blocks (ratio test; that constraint joins the set); after a full step the multipliers
    are checked and the most wrong-signed one leaves the set. It stops when a full step
    has multipliers of the right sign (to ``polish_dual_tol`` relative) and is feasible
    (to ``polish_tol``): that point satisfies the KKT conditions and is the optimum. At
    most ``polish_iter`` KKT solves and ``kmax`` constraints in the set (n for the
    nominal QP: more active constraints than variables is a degenerate set anyway).

    Why: the reduced Hessian is very flat (condition ~1e7: the internal-force directions
    of lambda cost only the regularisation Gamma), so an interior point at mu ~1e-11 can
    still be ~1e-2 (scaled) away from a weakly active bound; reading the active set off
    it and solving once (OSQP-style polishing) misses such bounds, and adding every
    violated row at once overshoots along the flat directions.
    Returns (u, s, ok, iterations)."""
    dt = pb.P.dtype
    n, m = pb.P.shape[0], pb.G.shape[0]
    on, sg = pb.row_on, pb.sig > 0
    c_pos = pb.c > 0
    tol = st.polish_tol
    inf = jnp.asarray(jnp.inf, dt)
    rs0 = jnp.where(on & (it.z > it.t),
                    jnp.where(sg & ((it.s > it.y) | ~c_pos), 2, 1), 0).astype(jnp.int32)
    bs0 = jnp.where(pb.ub_on & (it.zu > it.tu), 1,
                    jnp.where(pb.lb_on & (it.zl > it.tl), 2, 0)).astype(jnp.int32)
    member = jnp.concatenate([rs0 > 0, bs0 > 0])
    pos = jnp.cumsum(member) - 1                       # slot of each member
    kept = member & (pos < kmax)
    widx0 = jnp.full(kmax + 1, -1, jnp.int32).at[jnp.where(kept, pos, kmax)].set(
        jnp.arange(m + n, dtype=jnp.int32))[:kmax]
    rs0 = jnp.where(kept[:m], rs0, 0)
    bs0 = jnp.where(kept[m:], bs0, 0)
    s0 = jnp.where(rs0 == 2, jnp.maximum(it.s, 0.0), 0.0)
    u0 = jnp.clip(it.u, jnp.where(pb.lb_on, pb.lb, -inf), jnp.where(pb.ub_on, pb.ub, inf))
    dreg = jnp.asarray(1e2 * jnp.finfo(dt).eps, dt)
    pscale = 1.0 + _inf_norm(jnp.where(on, pb.h, 0.0), jnp.where(pb.lb_on, pb.lb, 0.0),
                             jnp.where(pb.ub_on, pb.ub, 0.0))

    kkt_solve = _kkt_factory(pb, dreg)

    def body(c):
        widx, rstate, bstate, u, s, k, _, _ = c
        ue, z, se, g = kkt_solve(widx, rstate, bstate)
        pu, ps = ue - u, se - s
        # ratio test over the constraints outside the working set
        gp = pb.G @ pu - pb.sig * ps
        room = jnp.maximum(pb.h - (pb.G @ u - pb.sig * s), 0.0)
        tiny = 1e3 * jnp.finfo(dt).eps * pscale
        a_r = jnp.where(on & (rstate == 0) & (gp > tiny), room / jnp.where(gp > tiny, gp, 1.0), inf)
        a_s = jnp.where((rstate == 2) & (ps < -tiny), s / jnp.where(ps < -tiny, -ps, 1.0), inf)
        free = bstate == 0
        a_u = jnp.where(free & pb.ub_on & (pu > tiny),
                        jnp.maximum(pb.ub - u, 0.0) / jnp.where(pu > tiny, pu, 1.0), inf)
        a_l = jnp.where(free & pb.lb_on & (pu < -tiny),
                        jnp.maximum(u - pb.lb, 0.0) / jnp.where(pu < -tiny, -pu, 1.0), inf)
        ar, as_, au, al = jnp.min(a_r), jnp.min(a_s), jnp.min(a_u), jnp.min(a_l)
        amin = jnp.minimum(jnp.minimum(ar, as_), jnp.minimum(au, al))
        blocked = amin < 1.0
        alpha = jnp.minimum(amin, 1.0)
        un = jnp.where(blocked, u + alpha * pu, ue)
        sn = jnp.where(blocked, jnp.maximum(s + alpha * ps, 0.0), se)
        # the blocking constraint joins the working set
        ir, is_ = jnp.argmin(a_r), jnp.argmin(a_s)
        iu, il = jnp.argmin(a_u), jnp.argmin(a_l)
        which = jnp.argmin(jnp.stack([ar, as_, au, al]))
        r_blk = jnp.where(which == 0, rstate.at[ir].set(1),       # row active, slack 0
                          jnp.where(which == 1, rstate.at[is_].set(1), rstate))  # s hits 0
        b_blk = jnp.where(which == 2, bstate.at[iu].set(1),
                          jnp.where(which == 3, bstate.at[il].set(2), bstate))
        new_idx = jnp.where(which == 0, ir, jnp.where(which == 2, m + iu, m + il))
        w_add, overflow = _wset_add(widx, new_idx.astype(jnp.int32))
        w_blk = jnp.where(which == 1, widx, w_add)
        overflow = overflow & (which != 1)
        # full step: multipliers; > 0 means wrong sign
        zscale = 1.0 + _inf_norm(z, g)
        bad_hard = jnp.where((rstate == 1) & ~sg, -z, -inf)
        bad_s1 = jnp.where((rstate == 1) & sg, jnp.maximum(-z, z - pb.c), -inf)
        bad_r = jnp.maximum(bad_hard, bad_s1) / zscale
        bad_b = jnp.where(bstate == 1, g, jnp.where(bstate == 2, -g, -inf)) / zscale
        worst_r, worst_b = jnp.max(bad_r), jnp.max(bad_b)
        jr, jb = jnp.argmax(bad_r), jnp.argmax(bad_b)
        to_r = jnp.where(sg[jr] & (z[jr] > pb.c[jr]), 2, 0).astype(jnp.int32)  # drop row or s-bound
        optimal = (worst_r <= st.polish_dual_tol) & (worst_b <= st.polish_dual_tol)
        use_r = worst_r >= worst_b
        r_full = jnp.where(optimal | ~use_r, rstate, rstate.at[jr].set(to_r))
        b_full = jnp.where(optimal | use_r, bstate, bstate.at[jb].set(0))
        drop_idx = jnp.where(use_r, jnp.where(to_r == 0, jr, -2), m + jb)
        w_full = jnp.where(optimal, widx, jnp.where(widx == drop_idx, -1, widx))
        nr = jnp.where(blocked, r_blk, r_full).astype(jnp.int32)
        nb = jnp.where(blocked, b_blk, b_full).astype(jnp.int32)
        nw = jnp.where(blocked, w_blk, w_full).astype(jnp.int32)
        finite = jnp.all(jnp.isfinite(ue)) & jnp.all(jnp.isfinite(z))
        rv = jnp.where(on, pb.G @ ue - pb.sig * se - pb.h, -inf)
        feas = (jnp.max(rv) <= tol * pscale) & jnp.all(se >= -tol * pscale)
        feas &= jnp.all(jnp.where(pb.ub_on, ue <= pb.ub + tol * pscale, True))
        feas &= jnp.all(jnp.where(pb.lb_on, ue >= pb.lb - tol * pscale, True))
        ok = finite & ~blocked & optimal & feas
        stop = ok | ~finite | (blocked & overflow)
        return (nw, nr, nb, jnp.where(finite, un, u), jnp.where(finite, sn, s), k + 1, stop, ok)

    def cond(c):
        return (~c[6]) & (c[5] < st.polish_iter)

    # instances with nothing to polish start stopped (a vmapped loop runs to the slowest)
    init = (widx0, rs0, bs0, u0, s0, jnp.zeros((), jnp.int32), ~active, jnp.zeros((), bool))
    _, _, _, u, s, k, _, ok = lax.while_loop(cond, body, init)
    return u, s, ok, k


def _solve_box(P, q, G, h, lb, ub, sig, st: Settings, active, relax: bool):
    """Scale, IPM, polish; (u, s [unscaled], status, iterations, polished).

    A problem without rows (G of shape (0, n): no inequalities and no equalities, or the
    controller's QP without G rows and bounded variables) gets one row that is switched
    off (0 u <= 1e30, which ``_scale_problem`` marks ``row_on`` False), so that the
    iteration's reductions over rows never see an empty array; its slack is dropped from
    the result. Static shapes: the other problems compile as before."""
    dt = P.dtype
    m0 = G.shape[0]
    if m0 == 0:
        G = jnp.zeros((1, P.shape[0]), dt)
        h = jnp.full((1,), 1e30, dt)
        sig = jnp.zeros((1,), dt)
    if relax:
        rho = jnp.full(h.shape, st.relax_rho, dt)
        c = jnp.full(h.shape, st.relax_rho_lin, dt)
    else:
        sig = jnp.zeros_like(h)
        rho = jnp.ones_like(h)
        c = jnp.zeros_like(h)
    pb, sc = _scale_problem(P, q, G, h, lb, ub, sig, rho, c)
    if st.ipm_dtype is not None and jnp.dtype(st.ipm_dtype) != dt:
        # mixed precision: the iterations in ipm_dtype, the polish in the problem's dtype
        lo = jnp.dtype(st.ipm_dtype)
        pb_lo = jax.tree_util.tree_map(lambda a: a.astype(lo) if a.dtype == dt else a, pb)
        st_lo = Settings.for_dtype(lo, max_iter=st.max_iter, fallback=st.fallback)
        it, status, k = _ipm(pb_lo, st_lo, active)
        it = jax.tree_util.tree_map(lambda a: a.astype(dt), it)
    else:
        it, status, k = _ipm(pb, st, active)
    u, s = it.u, it.s
    use = jnp.zeros((), bool)
    kp = jnp.zeros((), jnp.int32)
    if st.polish:
        up, sp, ok, kp = _polish(it, pb, st, active & (status != INFEASIBLE),
                                kmax=P.shape[0] + (G.shape[0] if relax else 0))
        # a point that passes the KKT checks is the optimum, whatever the IPM's status
        # (it may have stopped on a failed factorisation near the end); a certificate
        # of infeasibility stands (no point can pass then)
        use = ok & active & (status != INFEASIBLE)
        u = jnp.where(use, up, u)
        s = jnp.where(use, sp, s)
        status = jnp.where(use, SOLVED, status).astype(jnp.int32)
    return u * sc.sx, (s / sc.er)[:m0], status, k, use, kp


# ---------------------------------------------------------------------- full-space checks

def _full_residuals(x, qp: QP, slack=None):
    """(max |Ax - b|, max violation over G rows and bounds, the same over hard rows, and
    the violation of the relaxed QP's rows G x - s <= h when ``slack`` s is given)."""
    eq = jnp.max(jnp.abs(qp.A @ x - qp.b), initial=0.0)
    bnd = jnp.maximum(jnp.max(jnp.where(qp.lb > -_BIG, qp.lb - x, 0.0), initial=0.0),
                      jnp.max(jnp.where(qp.ub < _BIG, x - qp.ub, 0.0), initial=0.0))
    bnd = jnp.maximum(bnd, 0.0)
    on = qp.h < _BIG
    gx = qp.G @ x - qp.h
    r = jnp.where(on, gx, -jnp.inf)
    ineq = jnp.maximum(bnd, jnp.max(r, initial=0.0))
    hard = jnp.maximum(bnd, jnp.max(jnp.where(qp.soft > 0, -jnp.inf, r), initial=0.0))
    if slack is None:
        return eq, ineq, hard, ineq
    rel = jnp.maximum(bnd, jnp.max(jnp.where(on, gx - slack, -jnp.inf), initial=0.0))
    rel = jnp.maximum(rel, jnp.max(-slack, initial=0.0))
    return eq, ineq, hard, rel


def _scales(qp: QP):
    eq_scale = 1.0 + jnp.max(jnp.abs(qp.b), initial=0.0)
    v = jnp.concatenate([qp.h, qp.lb, qp.ub])
    in_scale = 1.0 + jnp.max(jnp.where(jnp.abs(v) < _BIG, jnp.abs(v), 0.0), initial=0.0)
    return eq_scale, in_scale


def _accept(x, qp: QP, status, feas_tol, slack=None):
    """SOLVED stays SOLVED only when x is finite and its residuals pass (the PIQP path's
    rule, relative to 1 + max |b| and 1 + max finite |h|, |lb|, |ub|); ``slack`` (on G's
    rows) checks the relaxed QP's rows instead. Returns (status, (eq, ineq, hard))."""
    eq_scale, in_scale = _scales(qp)
    eq, ineq, hard, chk = _full_residuals(x, qp, slack)
    good = jnp.all(jnp.isfinite(x)) & (eq <= feas_tol * eq_scale) & (chk <= feas_tol * in_scale)
    status = jnp.where((status == SOLVED) & ~good, NUMERICAL, status).astype(jnp.int32)
    return status, (eq, ineq, hard)


class _Nominal(NamedTuple):
    x: jax.Array
    u: jax.Array
    res: tuple
    status: jax.Array
    iterations: jax.Array
    polished: jax.Array
    polish_iterations: jax.Array


class _Relaxed(NamedTuple):
    x: jax.Array
    res: tuple
    slack: jax.Array
    status: jax.Array
    iterations: jax.Array
    polished: jax.Array
    polish_iterations: jax.Array


def _to_full(u, lift):
    x0, N = lift
    return x0 + N @ u


def _nominal(qp: QP, box, lift, st: Settings) -> _Nominal:
    """The QP as posed, through its reduced problem ``box`` (P, q, G, h, lb, ub, soft);
    ``lift`` = (x0, N) maps the reduced variable back: x = x0 + N u."""
    P, q, G, h, lb, ub, soft = box
    u, _, status, k, pol, kp = _solve_box(P, q, G, h, lb, ub, soft, st,
                                          jnp.ones((), bool), relax=False)
    x = _to_full(u, lift)
    status, res = _accept(x, qp, status, st.feas_tol)
    return _Nominal(x=x, u=u, res=res, status=status, iterations=k, polished=pol,
                    polish_iterations=kp)


def _relaxed(qp: QP, box, lift, st: Settings, need) -> _Relaxed:
    """The relaxed QP (soft rows with slack) for the instances with ``need``; the others
    start stopped."""
    P, q, G, h, lb, ub, soft = box
    ur, sr, rstatus, kr, rpol, kpr = _solve_box(P, q, G, h, lb, ub, soft, st, need, relax=True)
    xr = _to_full(ur, lift)
    sr = jnp.where(soft > 0, jnp.maximum(sr, 0.0), 0.0)[:qp.G.shape[0]]
    rstatus, res = _accept(xr, qp, rstatus, st.feas_tol, slack=sr)
    return _Relaxed(x=xr, res=res, slack=sr, status=rstatus, iterations=kr, polished=rpol,
                    polish_iterations=kpr)


def _relaxed_skipped(qp: QP) -> _Relaxed:
    """What ``_relaxed`` returns when no instance needs it (for a batch-level cond)."""
    dt = qp.P.dtype
    zi = jnp.zeros((), jnp.int32)
    nan = jnp.full((), jnp.nan, dt)
    return _Relaxed(x=jnp.full(qp.P.shape[0], jnp.nan, dt), res=(nan, nan, nan),
                    slack=jnp.zeros(qp.G.shape[0], dt),
                    status=jnp.full((), NUMERICAL, jnp.int32), iterations=zi,
                    polished=jnp.zeros((), bool), polish_iterations=zi)


def _finish(qp: QP, nom: _Nominal, rel: _Relaxed | None) -> Result:
    """The fallback policy's outcome: x of the QP as posed, else of the relaxed QP, else
    all NaN (FAILED)."""
    ok = nom.status == SOLVED
    nan = jnp.full_like(nom.x, jnp.nan)
    if rel is not None:
        need = ~ok
        rok = need & (rel.status == SOLVED)
        rstatus = jnp.where(need, rel.status, -1).astype(jnp.int32)
        x_out = jnp.where(ok, nom.x, jnp.where(rok, rel.x, nan))
        fallback = jnp.where(ok, FALLBACK_NONE, jnp.where(rok, FALLBACK_RELAXED, FALLBACK_FAILED))
        max_slack = jnp.where(ok, 0.0, jnp.where(rok, jnp.max(rel.slack, initial=0.0), jnp.nan))
        iters = nom.iterations + jnp.where(need, rel.iterations, 0)
        polished = jnp.where(ok, nom.polished, rok & rel.polished)
        kp = nom.polish_iterations + jnp.where(need, rel.polish_iterations, 0)
    else:
        rstatus = jnp.full((), -1, jnp.int32)
        x_out = jnp.where(ok, nom.x, nan)
        fallback = jnp.where(ok, FALLBACK_NONE, FALLBACK_FAILED)
        max_slack = jnp.where(ok, 0.0, jnp.nan)
        iters = nom.iterations
        polished = ok & nom.polished
        kp = nom.polish_iterations
    nan = jnp.full((), jnp.nan, nom.x.dtype)
    if rel is not None:
        eq, ineq, hard = (jnp.where(ok, a, jnp.where(rok, b, nan)) for a, b in zip(nom.res, rel.res))
    else:
        eq, ineq, hard = (jnp.where(ok, a, nan) for a in nom.res)
    return Result(x=x_out, status=nom.status.astype(jnp.int32),
                  fallback=fallback.astype(jnp.int32), relaxed_status=rstatus,
                  iterations=iters.astype(jnp.int32), max_slack=max_slack.astype(nom.x.dtype),
                  eq_residual=eq, ineq_violation=ineq, hard_violation=hard,
                  polished=polished, polish_iterations=kp.astype(jnp.int32))


def _cast(qp: QP, dtype) -> QP:
    return QP(*(jnp.asarray(getattr(qp, f), dtype) for f in
                ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")))


def _reduce_controller(qp: QP, nv: int, nu: int, bounded, p_blockdiag: bool = False):
    """The exact elimination of ``reduce.eliminate_equalities`` (same formulas: Cholesky
    of M, LU of K = J~ M^-1 J' + D, X = x0 + N u with N = [a + c L; I; L]), arranged for
    batches: M is used as is (symmetric by construction; LAPACK reads its lower
    triangle), the identity block of N is never multiplied, and with ``p_blockdiag``
    (P has no q_ddot/u/lambda cross blocks, as the controller's) only P's diagonal
    blocks are. Returns (box, lift = (x0, N), ok)."""
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
    Lm = lb.cholesky_lower(M)
    sol = lb.cho_solve(Lm, jnp.concatenate([Bm, Jt, hq[:, None]], axis=1))
    a, c, e = sol[:, :nu], sol[:, nu:-1], sol[:, -1]
    rhs = lb.solve(Jr @ c + D, jnp.concatenate([(r + Jr @ e)[:, None], -(Jr @ a)], axis=1))
    lam0, L = rhs[:, 0], rhs[:, 1:]
    Nq = a + c @ L
    x0q = c @ lam0 - e

    def n_t(v):                       # N' v for v over X
        return Nq.T @ v[iq] + v[iu] + L.T @ v[il]

    if p_blockdiag:
        PNq, PNl = P[iq, iq] @ Nq, P[il, il] @ L
        p_r = Nq.T @ PNq + P[iu, iu] + L.T @ PNl
        px0 = jnp.concatenate([P[iq, iq] @ x0q, jnp.zeros(nu, dt), P[il, il] @ lam0])
    else:
        PN = P[:, iq] @ Nq + P[:, iu] + P[:, il] @ L
        p_r = Nq.T @ PN[iq] + PN[iu] + L.T @ PN[il]
        px0 = P[:, iq] @ x0q + P[:, il] @ lam0
    p_r = 0.5 * (p_r + p_r.T)
    q_r = n_t(px0 + qp.q)
    g_rows = [G[:, iq] @ Nq + G[:, iu] + G[:, il] @ L]
    h_rows = [qp.h - (G[:, iq] @ x0q + G[:, il] @ lam0)]
    soft = [qp.soft]
    x0 = jnp.concatenate([x0q, jnp.zeros(nu, dt), lam0])
    N = jnp.concatenate([Nq, jnp.eye(nu, dtype=dt), L], axis=0)
    if bounded.size:
        Nb, xb = N[bounded], x0[bounded]
        g_rows += [Nb, -Nb]
        h_rows += [qp.ub[bounded] - xb, -(qp.lb[bounded] - xb)]
        soft.append(jnp.zeros(2 * bounded.size, dt))
    hh = jnp.concatenate(h_rows)
    box = (p_r, q_r, jnp.concatenate(g_rows, axis=0), jnp.where(jnp.isfinite(hh), hh, 1e30),
           qp.lb[iu], qp.ub[iu], jnp.concatenate(soft))
    return box, (x0, N), jnp.ones((), bool)


def _nullspace(qp: QP):
    """x = xp + Z y with Z an orthonormal basis of null(A) (complete QR of A')."""
    me = qp.A.shape[0]
    Q, R = jnp.linalg.qr(qp.A.T, mode="complete")
    R1 = R[:me, :]
    Y, Z = Q[:, :me], Q[:, me:]
    w = jsl.solve_triangular(R1, qp.b, trans="T", lower=False)
    xp = Y @ w
    d = jnp.abs(jnp.diag(R1))
    rank_ok = jnp.min(d) > 1e3 * jnp.finfo(qp.P.dtype).eps * jnp.maximum(jnp.max(d), 1.0)
    return xp, Z, rank_ok


def _reduce_generic(qp: QP):
    """(box, lift, ok) of a general QP: no equalities -> the QP itself (bounds as
    bounds); else the null-space method, finite bounds becoming hard rows. A with as many
    rows as variables (full rank: x fixed by A x = b, null(A) = {0}) gets a reduced
    problem in one dummy variable y that x does not depend on (Z = 0, cost y^2/2), so
    that the rows and bounds are still checked at x = xp (their rows 0 y <= h - G xp).
    More rows than variables cannot be of full row rank: ValueError."""
    dtype = qp.P.dtype
    n, me = qp.P.shape[0], qp.A.shape[0]
    if me > n:
        raise ValueError(f"the generic JAX path needs A of full row rank: A has {me} rows "
                         f"for {n} variables (remove the redundant equalities, or use "
                         "solver='piqp')")
    if me == 0:
        box = (qp.P, qp.q, qp.G, jnp.where(jnp.isfinite(qp.h), qp.h, 1e30),
               jnp.where(jnp.isfinite(qp.lb), qp.lb, -1e30),
               jnp.where(jnp.isfinite(qp.ub), qp.ub, 1e30), qp.soft)
        return box, (jnp.zeros(n, dtype), jnp.eye(n, dtype=dtype)), jnp.ones((), bool)
    xp, Z, rank_ok = _nullspace(qp)
    nz = n - me
    Pz = Z.T @ qp.P @ Z
    Pz = 0.5 * (Pz + Pz.T)
    qz = Z.T @ (qp.P @ xp + qp.q)
    if nz == 0:                       # x = xp: a dummy variable, absent from x
        nz = 1
        Z = jnp.zeros((n, 1), dtype)
        Pz = jnp.ones((1, 1), dtype)
        qz = jnp.zeros(1, dtype)
    lbf = qp.lb > -_BIG
    ubf = qp.ub < _BIG
    Gz = jnp.concatenate([qp.G @ Z, Z, -Z], axis=0)
    hz = jnp.concatenate([qp.h - qp.G @ xp, jnp.where(ubf, qp.ub - xp, 1e30),
                          jnp.where(lbf, xp - qp.lb, 1e30)])
    hz = jnp.where(jnp.isfinite(hz), hz, 1e30)
    soft = jnp.concatenate([qp.soft, jnp.zeros(2 * n, dtype)])
    inf = jnp.full(nz, 1e30, dtype)
    return (Pz, qz, Gz, hz, -inf, inf, soft), (xp, Z), rank_ok


def _single(qp: QP, box, lift, ok_red, st: Settings) -> Result:
    nom = _nominal(qp, box, lift, st)
    nom = nom._replace(status=jnp.where(ok_red, nom.status, NUMERICAL).astype(jnp.int32))
    rel = None
    if st.fallback:
        rel = _relaxed(qp, box, lift, st, (nom.status != SOLVED) & ok_red)
    return _finish(qp, nom, rel)


def _settings(dtype, settings):
    return settings if settings is not None else Settings.for_dtype(dtype)


# ---------------------------------------------------------------------- public API

def solve(qp: QP, *, nv: int = 36, nu: int = 20, bounded=None, dtype=None,
          settings: Settings | None = None, p_blockdiag: bool = False) -> Result:
    """One controller QP (X = [q_ddot (nv), u (nu), lambda]) through the reduced problem
    in u; pure JAX, jit/vmap-able (the relaxed solve runs with zero iterations where it
    is not needed; ``solve_batch`` skips it for a whole batch that does not need it).
    ``bounded``: static indices outside u with finite bounds
    (``reduce.bounded_variables``; none for the controller's QP). ``p_blockdiag``: P has
    no cross terms between q_ddot, u and lambda (true of the controller's QP; static:
    only P's diagonal blocks are then used, ``p_block_diagonal`` checks it)."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qp.P).dtype
    st = _settings(dtype, settings)
    qp = _cast(qp, dtype)
    bounded = np.zeros(0, int) if bounded is None else np.asarray(bounded, int)
    box, lift, ok_red = _reduce_controller(qp, nv, nu, bounded, p_blockdiag)
    return _single(qp, box, lift, ok_red, st)


def solve_generic(qp: QP, *, dtype=None, settings: Settings | None = None) -> Result:
    """Any QP of the seam's form (convex; A of full row rank, else NUMERICAL): the
    equalities eliminated by the null-space method, then the same interior point, polish
    and fallback as ``solve``. Finite bounds become rows when there are equalities.
    Slower than ``solve`` on the controller's QP (no structure used). The polish needs P
    positive definite on the reduced space; with a singular P the interior point's
    solution is returned (``polished`` False)."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qp.P).dtype
    st = _settings(dtype, settings)
    qp = _cast(qp, dtype)
    box, lift, ok_red = _reduce_generic(qp)
    return _single(qp, box, lift, ok_red, st)


def _batch_impl(qps: QP, reducer, st: Settings) -> Result:
    """vmap of the stages, with the relaxed solve under one batch-level ``lax.cond``: a
    batch in which every QP solves pays nothing for the fallback."""
    box, lift, ok_red = jax.vmap(reducer)(qps)
    nom = jax.vmap(lambda qp, b, l: _nominal(qp, b, l, st))(qps, box, lift)
    nom = nom._replace(status=jnp.where(ok_red, nom.status, NUMERICAL).astype(jnp.int32))
    rel = None
    if st.fallback:
        need = (nom.status != SOLVED) & ok_red
        rel = lax.cond(
            jnp.any(need),
            lambda: jax.vmap(lambda qp, b, l, nd: _relaxed(qp, b, l, st, nd))(
                qps, box, lift, need),
            lambda: jax.vmap(_relaxed_skipped)(qps))
    return jax.vmap(_finish)(qps, nom, rel) if rel is not None else \
        jax.vmap(lambda qp, n_: _finish(qp, n_, None))(qps, nom)


@functools.lru_cache(maxsize=64)
def _batched(kind: str, nv: int, nu: int, bounded: tuple, dtype, settings, pbd=False,
             chunk=None):
    if kind == "controller":
        b = np.asarray(bounded, int)
        reducer = lambda qp: _reduce_controller(qp, nv, nu, b, pbd)  # noqa: E731
    else:
        reducer = _reduce_generic
    impl = chunked(lambda qps: _batch_impl(qps, reducer, settings), chunk)
    return jax.jit(lambda qps: impl(_cast(qps, dtype)))


CPU_CHUNK = 64
"""Default ``chunk`` of the batched solvers on the CPU backend (QPs per chunk)."""


def default_chunk(backend: str | None = None) -> int | None:
    """The batched solvers' default ``chunk``: ``CPU_CHUNK`` on the CPU backend, None (one
    vmap over the whole batch) on an accelerator, whose parallelism wants the largest
    batch. ``backend`` None: ``jax.default_backend()``."""
    backend = jax.default_backend() if backend is None else backend
    return CPU_CHUNK if backend == "cpu" else None


def _resolve_chunk(chunk, batch: int):
    """The chunk a batch of ``batch`` QPs is solved with (``chunking.resolve_chunk`` with
    ``default_chunk()`` for "auto")."""
    return resolve_chunk(chunk, batch, default_chunk())


def solve_batch(qps: QP, *, nv: int = 36, nu: int = 20, bounded=None, dtype=None,
                settings: Settings | None = None, p_blockdiag: bool | None = None,
                chunk: int | str | None = "auto") -> Result:
    """``solve`` over a leading batch dimension of every field, jitted (compiled once per
    shape, dtype, settings, structure flags and chunk). ``p_blockdiag`` None: checked on
    the data (``p_block_diagonal``) when it is concrete, else False.

    ``chunk``: solve the batch at most ``chunk`` QPs at a time, the chunks one after the
    other in the same jitted call (``chunking.chunked``: equal chunks, padded by copies of
    the last QP; results equal to the unchunked solve's; each chunk runs the batch-level
    ``lax.cond`` of the relaxed solve on its own); None: one vmap over the whole batch;
    "auto" (default): ``default_chunk()``, ``CPU_CHUNK`` = 64 on a CPU, None on an
    accelerator. A batch of at most ``chunk`` QPs is one vmap (the same compiled function
    as chunk None).

    Why: on a CPU one vmap over a large batch costs more per QP. Measured with
    ``benchmarks/jax_qp_bench.py`` on the recorded controller QPs (float64, one core of a
    2-core x86-64 machine shared with other work, jaxlib 0.10.2, medians of 9): 1,024 QPs
    took 378 us per QP as one vmap, 164 / 173 / 205 us in chunks of 64 / 128 / 256; 256 QPs
    217 us as one vmap, 196 us in chunks of 64. Two causes: the same 256 QPs repeated to
    1,024 took 234 us per QP as one vmap against 158 us for the 256 (another run: a larger
    vmap is slower per QP on identical work), and a vmapped loop runs until the slowest QP of its
    batch stops (up to 22 interior-point iterations in the first 1,024 recorded QPs, 8 in
    the first 256), while a chunk stops at its own slowest. Chunks of 32 to 256 were within
    ~30% of each other at batch 1,024 in four runs; 64 was the fastest in three of them
    (in the first, 128 and 32 were ~15% faster), 256 never."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qps.P).dtype
    b = tuple(int(i) for i in (np.zeros(0, int) if bounded is None else np.asarray(bounded)))
    if p_blockdiag is None:
        p_blockdiag = _concrete(qps.P) and p_block_diagonal(qps.P, nv, nu)
    return _batched("controller", nv, nu, b, dtype, _settings(dtype, settings),
                    bool(p_blockdiag), _resolve_chunk(chunk, qps.P.shape[0]))(qps)


_OPENBLAS_API = (("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
                 ("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                 ("openblas_get_num_threads", "openblas_set_num_threads"),
                 ("openblas_get_num_threads64_", "openblas_set_num_threads64_"))


def _openblas_handles():
    """(get, set) functions of every OpenBLAS library loaded in this process (Linux)."""
    import ctypes

    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line.lower()
                     and ".so" in line}
    except OSError:
        return []
    out = []
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for get, set_ in _OPENBLAS_API:
            if hasattr(lib, get) and hasattr(lib, set_):
                out.append((getattr(lib, get), getattr(lib, set_)))
                break
    return out


@contextlib.contextmanager
def blas_threads(n: int = 1):
    """Limit every loaded OpenBLAS (scipy's, which jaxlib's CPU LAPACK kernels call, and
    numpy's) to ``n`` threads inside the block; the previous counts are restored after.

    Why: on a small CPU, OpenBLAS worker threads left spinning after a LAPACK call compete
    with XLA's thread pool; measured here (2 cores): a batch of controller QPs took 16 ms
    per QP instead of 0.2 ms. Setting OPENBLAS_NUM_THREADS=1 before numpy is imported does
    the same for a whole process. A no-op where no OpenBLAS is found."""
    handles = _openblas_handles()
    old = [get() for get, _ in handles]
    for _, set_ in handles:
        set_(int(n))
    try:
        yield len(handles)
    finally:
        for (_, set_), k in zip(handles, old):
            set_(int(k))


def _concrete(a) -> bool:
    return not isinstance(a, jax.core.Tracer)


def p_block_diagonal(P, nv: int = 36, nu: int = 20) -> bool:
    """Host-side check (concrete P, one or a batch) that P has no cross terms between the
    q_ddot (nv), u (nu) and lambda blocks."""
    P = np.asarray(P)
    s = [slice(0, nv), slice(nv, nv + nu), slice(nv + nu, P.shape[-1])]
    return not any(np.any(P[..., s[i], s[j]]) for i in range(3) for j in range(3) if i != j)


def solve_generic_batch(qps: QP, *, dtype=None, settings: Settings | None = None,
                        chunk: int | str | None = "auto") -> Result:
    """``solve_generic`` over a leading batch dimension, jitted; ``chunk`` as in
    ``solve_batch``."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qps.P).dtype
    return _batched("generic", 0, 0, (), dtype, _settings(dtype, settings), False,
                    _resolve_chunk(chunk, qps.P.shape[0]))(qps)


def has_controller_structure(qp: QP, nv: int = 36, nu: int = 20) -> bool:
    """Host-side check (concrete arrays, one QP or a batch) that ``solve`` applies: the
    shapes of X = [q_ddot (nv), u (nu), lambda (nc)] with nv + nc equality rows, the
    constraint rows free of u, and symmetric mass-matrix blocks."""
    P, A = np.asarray(qp.P), np.asarray(qp.A)
    n, me = P.shape[-1], A.shape[-2]
    nc = n - nv - nu
    if nc < 0 or me != nv + nc or A.shape[-1] != n:
        return False
    if np.any(A[..., nv:, nv:nv + nu] != 0):
        return False
    M = A[..., :nv, :nv]
    return bool(np.allclose(M, np.swapaxes(M, -1, -2), rtol=1e-10, atol=1e-12))


__all__ = ["Settings", "Result", "solve", "solve_batch", "solve_generic",
           "solve_generic_batch", "default_chunk", "CPU_CHUNK", "has_controller_structure",
           "p_block_diagonal", "blas_threads", "FALLBACK_NONE", "FALLBACK_RELAXED",
           "FALLBACK_FAILED", "FALLBACK_NAMES"]
