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
   corrector. The problem is scaled first: variables by half their box width, each row of
   G to unit max-norm, the cost to a unit max-norm Hessian/gradient.

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
frozen. ``solve_batch`` / ``solve_generic_batch`` are the jitted, vmapped versions.

dtype: float64 by default; ``dtype=jnp.float32`` casts the QP and uses float32 settings
(``Settings.for_dtype``: eps_abs 1e-5, looser acceptance 1e-3) for accelerators; expect
~1e-3 relative agreement there, the reduced problem being ill-conditioned.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jax import lax

from safewbc_jax.qp_types import QP
from safewbc_jax.solvers import reduce
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
    feas_tol: float = 1e-6
    reg: float = 1e-13
    fallback: bool = True
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
    u: jax.Array
    s: jax.Array
    t: jax.Array
    z: jax.Array
    y: jax.Array
    tu: jax.Array
    zu: jax.Array
    tl: jax.Array
    zl: jax.Array


class _Carry(NamedTuple):
    it: _It
    k: jax.Array
    status: jax.Array


def _mask_it(it: _It, pb: _Box) -> _It:
    """Pin the variables of absent rows/bounds (t=1, z=0) and of non-relaxed rows (s=y=0)."""
    on, sg = pb.row_on, pb.sig > 0
    return _It(u=it.u, s=jnp.where(sg, it.s, 0.0), t=jnp.where(on, it.t, 1.0),
               z=jnp.where(on, it.z, 0.0), y=jnp.where(sg, it.y, 0.0),
               tu=jnp.where(pb.ub_on, it.tu, 1.0), zu=jnp.where(pb.ub_on, it.zu, 0.0),
               tl=jnp.where(pb.lb_on, it.tl, 1.0), zl=jnp.where(pb.lb_on, it.zl, 0.0))


def _residuals(it: _It, pb: _Box):
    Gu = pb.G @ it.u
    Pu = pb.P @ it.u
    Gz = pb.G.T @ it.z
    rd = Pu + pb.q + Gz + it.zu - it.zl
    rs = pb.sig * (pb.rho * it.s + pb.c - it.z - it.y)
    rp = jnp.where(pb.row_on, Gu - pb.sig * it.s - pb.h + it.t, 0.0)
    ru = jnp.where(pb.ub_on, it.u - pb.ub + it.tu, 0.0)
    rl = jnp.where(pb.lb_on, pb.lb - it.u + it.tl, 0.0)
    return rd, rs, rp, ru, rl, Gu, Pu, Gz


def _n_compl(pb: _Box):
    dt = pb.P.dtype
    return jnp.maximum(jnp.sum(pb.row_on, dtype=dt) + jnp.sum(pb.sig, dtype=dt)
                       + jnp.sum(pb.lb_on, dtype=dt) + jnp.sum(pb.ub_on, dtype=dt), 1.0)


def _mu(it: _It, pb: _Box):
    return (it.t @ it.z + it.s @ it.y + it.tu @ it.zu + it.tl @ it.zl) / _n_compl(pb)


def _inf_norm(*vs):
    return jnp.max(jnp.stack([jnp.max(jnp.abs(v), initial=0.0) for v in vs]))


def _converged(it: _It, pb: _Box, res, st: Settings):
    rd, rs, rp, ru, rl, Gu, Pu, Gz = res
    pres = _inf_norm(rp, ru, rl)
    dres = _inf_norm(rd, rs)
    pscale = _inf_norm(jnp.where(pb.row_on, Gu, 0.0), pb.h, it.u, it.s)
    dscale = _inf_norm(Pu, pb.q, Gz, it.zu - it.zl)
    return ((pres <= st.eps_abs + st.eps_rel * pscale)
            & (dres <= st.eps_abs + st.eps_rel * dscale)
            & (_mu(it, pb) <= st.eps_abs))


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


def _max_step(v, dv, on):
    ratio = jnp.where(on & (dv < 0), -v / jnp.where(dv < 0, dv, -1.0), jnp.inf)
    return jnp.min(ratio, initial=jnp.inf)


def _newton_factory(it: _It, pb: _Box, st: Settings):
    """Factor the reduced Newton matrix at ``it``; return a solver for right-hand sides."""
    dt = pb.P.dtype
    n = pb.P.shape[0]
    on, sg = pb.row_on, pb.sig > 0
    t_s = jnp.where(on, it.t, 1.0)
    s_s = jnp.where(sg, it.s, 1.0)
    D = jnp.where(on, it.z / t_s, 0.0)
    Du = jnp.where(pb.ub_on, it.zu / it.tu, 0.0)
    Dl = jnp.where(pb.lb_on, it.zl / it.tl, 0.0)
    ys = jnp.where(sg, it.y / s_s, 0.0)
    E = jnp.where(sg, pb.rho + D + ys, 1.0)
    W = jnp.where(sg, D * (pb.rho + ys) / E, D)
    H = pb.P + (pb.G.T * W[None, :]) @ pb.G + jnp.diag(Du + Dl)
    H = H + st.reg * jnp.eye(n, dtype=dt)
    L = jnp.linalg.cholesky(H)

    def solve(rd, rs, rp, ru, rl, rc, rcu, rcl, rcs):
        a = jnp.where(on, (it.z * rp - rc) / t_s, 0.0)
        rhs_s = jnp.where(sg, -rs + a - rcs / s_s, 0.0)
        bu = jnp.where(pb.ub_on, (it.zu * ru - rcu) / it.tu, 0.0)
        bl = jnp.where(pb.lb_on, (it.zl * rl - rcl) / it.tl, 0.0)
        rhs = -rd - pb.G.T @ a - bu + bl + pb.G.T @ jnp.where(sg, D * rhs_s / E, 0.0)
        du = jsl.cho_solve((L, True), rhs)
        Gdu = pb.G @ du
        ds = jnp.where(sg, (D * Gdu + rhs_s) / E, 0.0)
        dz = jnp.where(on, D * (Gdu - pb.sig * ds) + a, 0.0)
        dt_ = jnp.where(on, -rp - Gdu + pb.sig * ds, 0.0)
        dy = jnp.where(sg, (-rcs - it.y * ds) / s_s, 0.0)
        dtu = jnp.where(pb.ub_on, -ru - du, 0.0)
        dzu = jnp.where(pb.ub_on, Du * du + bu, 0.0)
        dtl = jnp.where(pb.lb_on, -rl + du, 0.0)
        dzl = jnp.where(pb.lb_on, -Dl * du + bl, 0.0)
        return _It(u=du, s=ds, t=dt_, z=dz, y=dy, tu=dtu, zu=dzu, tl=dtl, zl=dzl)

    return L, solve


def _step_length(it: _It, d: _It, pb: _Box):
    on, sg = pb.row_on, pb.sig > 0
    a = jnp.minimum(_max_step(it.t, d.t, on), _max_step(it.z, d.z, on))
    a = jnp.minimum(a, jnp.minimum(_max_step(it.s, d.s, sg), _max_step(it.y, d.y, sg)))
    a = jnp.minimum(a, jnp.minimum(_max_step(it.tu, d.tu, pb.ub_on),
                                   _max_step(it.zu, d.zu, pb.ub_on)))
    a = jnp.minimum(a, jnp.minimum(_max_step(it.tl, d.tl, pb.lb_on),
                                   _max_step(it.zl, d.zl, pb.lb_on)))
    return a


def _axpy(it: _It, d: _It, a) -> _It:
    return jax.tree_util.tree_map(lambda v, dv: v + a * dv, it, d)


def _initial_point(pb: _Box, st: Settings) -> _It:
    """Least-squares start u0 (cost + squared row residuals + pull to the box centre),
    then slacks and multipliers shifted into the positive orthant (Nocedal & Wright 14.3)."""
    dt = pb.P.dtype
    n = pb.P.shape[0]
    on, sg = pb.row_on, pb.sig > 0
    box_on = pb.lb_on | pb.ub_on
    centre = jnp.where(pb.lb_on & pb.ub_on, 0.5 * (pb.lb + pb.ub),
                       jnp.where(pb.lb_on, pb.lb + 1.0, jnp.where(pb.ub_on, pb.ub - 1.0, 0.0)))
    Gon = jnp.where(on[:, None], pb.G, 0.0)
    H0 = pb.P + Gon.T @ Gon + jnp.diag(box_on.astype(dt)) + (st.reg + 1e-8) * jnp.eye(n, dtype=dt)
    r0 = -pb.q + Gon.T @ jnp.where(on, pb.h, 0.0) + jnp.where(box_on, centre, 0.0)
    u0 = jnp.linalg.solve(H0, r0)
    Gu = pb.G @ u0
    s0 = jnp.where(sg, jnp.maximum(Gu - pb.h, 0.0), 0.0)
    t0 = pb.h - Gu + pb.sig * s0
    tu0 = pb.ub - u0
    tl0 = u0 - pb.lb
    prim = [(t0, on), (s0, sg), (tu0, pb.ub_on), (tl0, pb.lb_on)]
    pmin = jnp.min(jnp.stack([jnp.min(jnp.where(m, v, jnp.inf)) for v, m in prim]))
    dp = jnp.maximum(-1.5 * jnp.where(jnp.isfinite(pmin), pmin, 0.0), 0.0)
    prim = [(jnp.where(m, v + dp, 0.0), m) for v, m in prim]
    nprod = sum(jnp.sum(v) for v, _ in prim)          # duals are all 1 here
    ncount = _n_compl(pb)
    dp2 = 0.5 * nprod / ncount
    dd2 = 0.5 * nprod / jnp.maximum(sum(jnp.sum(v) for v, _ in prim) + dp2 * ncount, 1e-30)
    dd2 = jnp.maximum(dd2, 0.0)
    one = jnp.ones_like
    it = _It(u=u0, s=prim[1][0] + dp2, t=prim[0][0] + dp2, z=one(t0) * (1.0 + dd2),
             y=one(s0) * (1.0 + dd2), tu=prim[2][0] + dp2, zu=one(tu0) * (1.0 + dd2),
             tl=prim[3][0] + dp2, zl=one(tl0) * (1.0 + dd2))
    # make the starting multipliers of the slack block consistent in size with rho
    return _mask_it(it, pb)


def _ipm(pb: _Box, st: Settings, active):
    """Mehrotra predictor-corrector on the scaled box QP; ``active`` False: do nothing."""
    it0 = _initial_point(pb, st)
    res0 = _residuals(it0, pb)
    status0 = jnp.where(active, _RUNNING, NUMERICAL).astype(jnp.int32)
    eta = 0.99

    def cond(c: _Carry):
        return (c.status == _RUNNING) & (c.k < st.max_iter)

    def body(c: _Carry):
        it = c.it
        rd, rs, rp, ru, rl, _, _, _ = _residuals(it, pb)
        L, solve = _newton_factory(it, pb, st)
        mu = _mu(it, pb)
        # predictor (affine scaling)
        d_aff = solve(rd, rs, rp, ru, rl, it.t * it.z, it.tu * it.zu, it.tl * it.zl,
                      it.s * it.y)
        a_aff = jnp.minimum(1.0, _step_length(it, d_aff, pb))
        it_aff = _axpy(it, d_aff, a_aff)
        mu_aff = _mu(_mask_it(it_aff, pb), pb)
        sigma = jnp.clip(mu_aff / mu, 0.0, 1.0) ** 3
        smu = sigma * mu
        on, sg = pb.row_on, pb.sig > 0
        rc = jnp.where(on, it.t * it.z + d_aff.t * d_aff.z - smu, 0.0)
        rcu = jnp.where(pb.ub_on, it.tu * it.zu + d_aff.tu * d_aff.zu - smu, 0.0)
        rcl = jnp.where(pb.lb_on, it.tl * it.zl + d_aff.tl * d_aff.zl - smu, 0.0)
        rcs = jnp.where(sg, it.s * it.y + d_aff.s * d_aff.y - smu, 0.0)
        d = solve(rd, rs, rp, ru, rl, rc, rcu, rcl, rcs)
        a = jnp.minimum(1.0, eta * _step_length(it, d, pb))
        new = _mask_it(_axpy(it, d, a), pb)
        finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(v)) for v in new])) & jnp.all(jnp.isfinite(L))
        res = _residuals(new, pb)
        conv = _converged(new, pb, res, st)
        pinf = _primal_infeasible(new.z, pb, st.eps_inf)
        dinf = _dual_infeasible(d.u, pb, st.eps_inf) & (a > 0.5)
        status = jnp.where(~finite, NUMERICAL,
                           jnp.where(conv, SOLVED,
                                     jnp.where(pinf | dinf, INFEASIBLE, _RUNNING))).astype(jnp.int32)
        it_out = jax.tree_util.tree_map(lambda n_, o: jnp.where(finite, n_, o), new, it)
        return _Carry(it=it_out, k=c.k + 1, status=status)

    conv0 = _converged(it0, pb, res0, st)
    status0 = jnp.where(active & conv0, SOLVED, status0).astype(jnp.int32)
    out = lax.while_loop(cond, body, _Carry(it=it0, k=jnp.zeros((), jnp.int32), status=status0))
    status = jnp.where(out.status == _RUNNING, MAX_ITER, out.status).astype(jnp.int32)
    return out.it, status, out.k


def _tri(L, b, trans=False):
    """L^-1 b (or L^-T b) for lower-triangular L; b a vector or a matrix."""
    vec = b.ndim == 1
    bb = b[:, None] if vec else b
    x = lax.linalg.triangular_solve(L, bb, left_side=True, lower=True, transpose_a=trans)
    return x[:, 0] if vec else x


def _kkt_active(pb: _Box, rstate, bstate, dreg):
    """Exact solution of the equality-constrained QP of a working set (fixed shapes):
    rstate per row 0 inactive (z = 0), 1 active (G u = h, s = 0), 2 relaxed (G u - s = h
    with s free: the row's cost rho/2 s^2 + c s enters the Hessian); bstate per variable
    0 free, 1 at ub, 2 at lb. Range-space method: with the fixed variables substituted,
    H~ = P_FF + G_F' diag(rho_R) G_F (Cholesky), S = G_A H~^-1 G_A' (Cholesky, with a
    -dreg relative shift on its diagonal for degenerate sets), and two steps of iterative
    refinement against the unshifted system. Returns (u, z, s, g = P u + q + G'z)."""
    dt = pb.P.dtype
    n = pb.P.shape[0]
    on = pb.row_on
    F = bstate == 0
    f0 = jnp.where(bstate == 1, pb.ub, jnp.where(bstate == 2, pb.lb, 0.0))
    act = on & (rstate == 1)
    rel = on & (rstate == 2)
    rho_r = jnp.where(rel, pb.rho, 0.0)
    c_r = jnp.where(rel, pb.c, 0.0)
    GF = jnp.where(F[None, :], pb.G, 0.0)
    Ht = jnp.where(F[:, None] & F[None, :], pb.P, 0.0) + jnp.diag(jnp.where(F, 0.0, 1.0))
    Ht = Ht + (GF.T * rho_r[None, :]) @ GF
    Gf0 = pb.G @ f0
    r1 = jnp.where(F, -(pb.P @ f0 + pb.q + pb.G.T @ (rho_r * (Gf0 - pb.h) + c_r)), 0.0)
    GA = jnp.where(act[:, None], GF, 0.0)
    r2 = jnp.where(act, pb.h - Gf0, 0.0)
    L = jnp.linalg.cholesky(Ht)
    C = _tri(L, GA.T)                                   # L^-1 G_A'
    S = C.T @ C
    shift = dreg * (1.0 + jnp.max(jnp.abs(jnp.diag(S))))
    S = S + jnp.diag(jnp.where(act, shift, 1.0))
    Ls = jnp.linalg.cholesky(S)

    def kkt_solve(e1, e2):
        w = _tri(L, e1)
        z = jsl.cho_solve((Ls, True), C.T @ w - e2)
        v = _tri(L, w - C @ z, trans=True)
        return v, jnp.where(act, z, 0.0)

    v, z = kkt_solve(r1, r2)
    for _ in range(2):
        e1 = r1 - (Ht @ v + GA.T @ z)
        e2 = r2 - GA @ v
        dv, dz = kkt_solve(e1, e2)
        v, z = v + dv, z + dz
    u = jnp.where(F, v, f0)
    gu = pb.G @ u - pb.h
    z = jnp.where(act, z, jnp.where(rel, rho_r * gu + c_r, 0.0))
    s = jnp.where(rel, gu, 0.0)
    g = pb.P @ u + pb.q + pb.G.T @ z
    return u, z, s, g


def _polish(it: _It, pb: _Box, st: Settings, active):
    """Finish on the exact optimum with a primal active-set method (Nocedal & Wright,
    Algorithm 16.3) started at the interior point: the working set is guessed from the
    IPM (t < z), each iteration solves the KKT system of the working set exactly
    (``_kkt_active``) and steps towards its solution until a constraint outside the set
    blocks (ratio test; that constraint joins the set); after a full step the multipliers
    are checked and the most wrong-signed one leaves the set. It stops when a full step
    has multipliers of the right sign (to ``polish_tol`` relative): that point satisfies
    the KKT conditions and is the optimum. At most ``polish_iter`` KKT solves.

    Why: the reduced Hessian is very flat (condition ~1e7: the internal-force directions
    of lambda cost only the regularisation Gamma), so an interior point at mu ~1e-11 can
    still be ~1e-2 (scaled) away from a weakly active bound; reading the active set off
    it and solving once (OSQP-style polishing) misses such bounds, and adding every
    violated row at once overshoots along the flat directions.
    Returns (u, s, ok, iterations)."""
    dt = pb.P.dtype
    on, sg = pb.row_on, pb.sig > 0
    c_pos = pb.c > 0
    tol = st.polish_tol
    inf = jnp.asarray(jnp.inf, dt)
    rs0 = jnp.where(on & (it.z > it.t),
                    jnp.where(sg & ((it.s > it.y) | ~c_pos), 2, 1), 0).astype(jnp.int32)
    bs0 = jnp.where(pb.ub_on & (it.zu > it.tu), 1,
                    jnp.where(pb.lb_on & (it.zl > it.tl), 2, 0)).astype(jnp.int32)
    s0 = jnp.where(rs0 == 2, jnp.maximum(it.s, 0.0), 0.0)
    u0 = jnp.clip(it.u, jnp.where(pb.lb_on, pb.lb, -inf), jnp.where(pb.ub_on, pb.ub, inf))
    dreg = jnp.asarray(1e3 * jnp.finfo(dt).eps, dt)
    pscale = 1.0 + _inf_norm(jnp.where(on, pb.h, 0.0), jnp.where(pb.lb_on, pb.lb, 0.0),
                             jnp.where(pb.ub_on, pb.ub, 0.0))

    def body(c):
        rstate, bstate, u, s, k, _, _ = c
        ue, z, se, g = _kkt_active(pb, rstate, bstate, dreg)
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
        add_r = rstate.at[ir].set(1)             # row active, its slack (if any) at 0
        add_s = rstate.at[is_].set(1)            # relaxed row's slack hits 0
        add_u = bstate.at[iu].set(1)
        add_l = bstate.at[il].set(2)
        which = jnp.argmin(jnp.stack([ar, as_, au, al]))
        r_blk = jnp.where(which == 0, add_r, jnp.where(which == 1, add_s, rstate))
        b_blk = jnp.where(which == 2, add_u, jnp.where(which == 3, add_l, bstate))
        # full step: multipliers; > 0 means wrong sign
        zscale = 1.0 + _inf_norm(z, g)
        bad_hard = jnp.where((rstate == 1) & ~sg, -z, -inf)
        bad_s1 = jnp.where((rstate == 1) & sg, jnp.maximum(-z, z - pb.c), -inf)
        bad_r = jnp.maximum(bad_hard, bad_s1) / zscale
        bad_b = jnp.where(bstate == 1, g, jnp.where(bstate == 2, -g, -inf)) / zscale
        worst_r, worst_b = jnp.max(bad_r), jnp.max(bad_b)
        jr, jb = jnp.argmax(bad_r), jnp.argmax(bad_b)
        zj = z[jr]
        to_r = jnp.where(sg[jr] & (zj > pb.c[jr]), 2, 0).astype(jnp.int32)  # drop row or s-bound
        drop_r = rstate.at[jr].set(to_r)
        drop_b = bstate.at[jb].set(0)
        optimal = (worst_r <= tol) & (worst_b <= tol)
        use_r = worst_r >= worst_b
        r_full = jnp.where(optimal, rstate, jnp.where(use_r, drop_r, rstate))
        b_full = jnp.where(optimal, bstate, jnp.where(use_r, bstate, drop_b))
        nr = jnp.where(blocked, r_blk, r_full).astype(jnp.int32)
        nb = jnp.where(blocked, b_blk, b_full).astype(jnp.int32)
        finite = jnp.all(jnp.isfinite(ue)) & jnp.all(jnp.isfinite(z))
        rv = jnp.where(on, pb.G @ ue - pb.sig * se - pb.h, -inf)
        feas = (jnp.max(rv) <= tol * pscale) & jnp.all(se >= -tol * pscale)
        feas &= jnp.all(jnp.where(pb.ub_on, ue <= pb.ub + tol * pscale, True))
        feas &= jnp.all(jnp.where(pb.lb_on, ue >= pb.lb - tol * pscale, True))
        ok = finite & ~blocked & optimal & feas
        stop = ok | ~finite
        return (nr, nb, jnp.where(finite, un, u), jnp.where(finite, sn, s), k + 1, stop, ok)

    def cond(c):
        return (~c[5]) & (c[4] < st.polish_iter)

    # instances with nothing to polish start stopped (a vmapped loop runs to the slowest)
    init = (rs0, bs0, u0, s0, jnp.zeros((), jnp.int32), ~active, jnp.zeros((), bool))
    _, _, u, s, k, _, ok = lax.while_loop(cond, body, init)
    return u, s, ok, k


def _solve_box(P, q, G, h, lb, ub, sig, st: Settings, active, relax: bool):
    """Scale, IPM, polish; (u, s [unscaled], status, iterations)."""
    dt = P.dtype
    if relax:
        rho = jnp.full(h.shape, st.relax_rho, dt)
        c = jnp.full(h.shape, st.relax_rho_lin, dt)
    else:
        sig = jnp.zeros_like(h)
        rho = jnp.ones_like(h)
        c = jnp.zeros_like(h)
    pb, sc = _scale_problem(P, q, G, h, lb, ub, sig, rho, c)
    it, status, k = _ipm(pb, st, active)
    u, s = it.u, it.s
    if st.polish:
        up, sp, ok, _ = _polish(it, pb, st, active & (status != INFEASIBLE))
        # a point that passes the KKT checks is the optimum, whatever the IPM's status
        # (it may have stopped on a failed factorisation near the end); a certificate
        # of infeasibility stands (no point can pass then)
        use = ok & active & (status != INFEASIBLE)
        u = jnp.where(use, up, u)
        s = jnp.where(use, sp, s)
        status = jnp.where(use, SOLVED, status).astype(jnp.int32)
    return u * sc.sx, s / sc.er, status, k


# ---------------------------------------------------------------------- full-space checks

def _full_residuals(x, qp: QP):
    """(max |Ax - b|, max violation over G rows and bounds, the same over hard rows)."""
    eq = jnp.max(jnp.abs(qp.A @ x - qp.b), initial=0.0)
    bnd = jnp.maximum(jnp.max(jnp.where(qp.lb > -_BIG, qp.lb - x, 0.0), initial=0.0),
                      jnp.max(jnp.where(qp.ub < _BIG, x - qp.ub, 0.0), initial=0.0))
    bnd = jnp.maximum(bnd, 0.0)
    r = jnp.where(qp.h < _BIG, qp.G @ x - qp.h, -jnp.inf)
    ineq = jnp.maximum(bnd, jnp.max(r, initial=0.0))
    hard = jnp.maximum(bnd, jnp.max(jnp.where(qp.soft > 0, -jnp.inf, r), initial=0.0))
    return eq, ineq, hard


def _scales(qp: QP):
    eq_scale = 1.0 + jnp.max(jnp.abs(qp.b), initial=0.0)
    v = jnp.concatenate([qp.h, qp.lb, qp.ub])
    in_scale = 1.0 + jnp.max(jnp.where(jnp.abs(v) < _BIG, jnp.abs(v), 0.0), initial=0.0)
    return eq_scale, in_scale


def _accept(x, qp: QP, status, feas_tol, slack=None):
    """SOLVED stays SOLVED only when x is finite and its residuals pass (PIQP path's rule);
    ``slack`` (on G's rows) turns the check into the relaxed QP's."""
    eq_scale, in_scale = _scales(qp)
    if slack is None:
        eq, ineq, _ = _full_residuals(x, qp)
    else:
        eq, _, _ = _full_residuals(x, qp)
        shifted = QP(P=qp.P, q=qp.q, A=qp.A, b=qp.b, G=qp.G, h=qp.h + slack, lb=qp.lb,
                     ub=qp.ub, soft=qp.soft)
        _, ineq, _ = _full_residuals(x, shifted)
        ineq = jnp.maximum(ineq, jnp.max(-slack, initial=0.0))
    good = jnp.all(jnp.isfinite(x)) & (eq <= feas_tol * eq_scale) & (ineq <= feas_tol * in_scale)
    return jnp.where((status == SOLVED) & ~good, NUMERICAL, status).astype(jnp.int32)


def _with_fallback(qp: QP, to_full, box, st: Settings) -> Result:
    """The fallback policy around ``_solve_box`` on the reduced problem ``box``
    (P, q, G, h, lb, ub, soft); ``to_full`` maps the reduced variable to x."""
    P, q, G, h, lb, ub, soft = box
    true = jnp.ones((), bool)
    u, _, status, k = _solve_box(P, q, G, h, lb, ub, soft, st, true, relax=False)
    x = to_full(u)
    status = _accept(x, qp, status, st.feas_tol)
    ok = status == SOLVED
    nan = jnp.full_like(x, jnp.nan)
    if st.fallback:
        need = ~ok
        ur, sr, rstatus, kr = _solve_box(P, q, G, h, lb, ub, soft, st, need, relax=True)
        xr = to_full(ur)
        sr = jnp.where(soft > 0, jnp.maximum(sr, 0.0), 0.0)
        rstatus = _accept(xr, qp, rstatus, st.feas_tol, slack=sr[:qp.G.shape[0]])
        rok = need & (rstatus == SOLVED)
        rstatus = jnp.where(need, rstatus, -1).astype(jnp.int32)
        x_out = jnp.where(ok, x, jnp.where(rok, xr, nan))
        fallback = jnp.where(ok, FALLBACK_NONE, jnp.where(rok, FALLBACK_RELAXED, FALLBACK_FAILED))
        max_slack = jnp.where(ok, 0.0, jnp.where(rok, jnp.max(sr, initial=0.0), jnp.nan))
        iters = k + jnp.where(need, kr, 0)
    else:
        rstatus = jnp.full((), -1, jnp.int32)
        x_out = jnp.where(ok, x, nan)
        fallback = jnp.where(ok, FALLBACK_NONE, FALLBACK_FAILED)
        max_slack = jnp.where(ok, 0.0, jnp.nan)
        iters = k
    eq, ineq, hard = _full_residuals(x_out, qp)
    return Result(x=x_out.astype(x.dtype), status=status.astype(jnp.int32),
                  fallback=fallback.astype(jnp.int32), relaxed_status=rstatus,
                  iterations=iters.astype(jnp.int32), max_slack=max_slack.astype(x.dtype),
                  eq_residual=eq, ineq_violation=ineq, hard_violation=hard)


def _cast(qp: QP, dtype) -> QP:
    return QP(*(jnp.asarray(getattr(qp, f), dtype) for f in
                ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")))


# ---------------------------------------------------------------------- public API

def solve(qp: QP, *, nv: int = 36, nu: int = 20, bounded=None, dtype=None,
          settings: Settings | None = None) -> Result:
    """One controller QP (X = [q_ddot (nv), u (nu), lambda]) through the reduced problem
    in u; pure JAX, jit/vmap-able. ``bounded``: static indices outside u with finite
    bounds (``reduce.bounded_variables``; none for the controller's QP)."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qp.P).dtype
    st = settings if settings is not None else Settings.for_dtype(dtype)
    qp = _cast(qp, dtype)
    bounded = np.zeros(0, int) if bounded is None else np.asarray(bounded, int)
    red, rmap = reduce.eliminate_equalities(qp, nv, nu, bounded)
    box = (red.P, red.q, red.G, red.h, red.lb, red.ub, red.soft)
    return _with_fallback(qp, lambda u: rmap.x0 + rmap.N @ u, box, st)


def _nullspace(qp: QP):
    """x = xp + Z y with Z an orthonormal basis of null(A) (complete QR of A')."""
    n, me = qp.P.shape[0], qp.A.shape[0]
    Q, R = jnp.linalg.qr(qp.A.T, mode="complete")
    R1 = R[:me, :]
    Y, Z = Q[:, :me], Q[:, me:]
    w = jsl.solve_triangular(R1, qp.b, trans="T", lower=False)
    xp = Y @ w
    d = jnp.abs(jnp.diag(R1))
    rank_ok = jnp.min(d) > 1e3 * jnp.finfo(qp.P.dtype).eps * jnp.maximum(jnp.max(d), 1.0)
    return xp, Z, rank_ok


def solve_generic(qp: QP, *, dtype=None, settings: Settings | None = None) -> Result:
    """Any QP of the seam's form (strictly or merely convex; A of full row rank): the
    equalities eliminated by the null-space method, then the same interior point, polish
    and fallback as ``solve``. Finite bounds become rows when there are equalities.
    Slower than ``solve`` on the controller's QP (no structure used)."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qp.P).dtype
    st = settings if settings is not None else Settings.for_dtype(dtype)
    qp = _cast(qp, dtype)
    n, me = qp.P.shape[0], qp.A.shape[0]
    if me == 0:
        box = (qp.P, qp.q, qp.G, jnp.where(jnp.isfinite(qp.h), qp.h, 1e30),
               jnp.where(jnp.isfinite(qp.lb), qp.lb, -1e30),
               jnp.where(jnp.isfinite(qp.ub), qp.ub, 1e30), qp.soft)
        return _with_fallback(qp, lambda u: u, box, st)
    xp, Z, rank_ok = _nullspace(qp)
    nz = n - me
    Pz = Z.T @ qp.P @ Z
    Pz = 0.5 * (Pz + Pz.T)
    qz = Z.T @ (qp.P @ xp + qp.q)
    lbf = qp.lb > -_BIG
    ubf = qp.ub < _BIG
    Gz = jnp.concatenate([qp.G @ Z, Z, -Z], axis=0)
    hz = jnp.concatenate([qp.h - qp.G @ xp, jnp.where(ubf, qp.ub - xp, 1e30),
                          jnp.where(lbf, xp - qp.lb, 1e30)])
    hz = jnp.where(jnp.isfinite(hz), hz, 1e30)
    soft = jnp.concatenate([qp.soft, jnp.zeros(2 * n, dtype)])
    inf = jnp.full(nz, 1e30, dtype)
    box = (Pz, qz, Gz, hz, -inf, inf, soft)
    res = _with_fallback(qp, lambda y: xp + Z @ y, box, st)
    bad = ~rank_ok
    nan = jnp.full_like(res.x, jnp.nan)
    return res._replace(x=jnp.where(bad, nan, res.x),
                        status=jnp.where(bad, NUMERICAL, res.status).astype(jnp.int32),
                        fallback=jnp.where(bad, FALLBACK_FAILED, res.fallback).astype(jnp.int32))


@functools.lru_cache(maxsize=64)
def _batched(kind: str, nv: int, nu: int, bounded: tuple, dtype, settings):
    if kind == "controller":
        fn = functools.partial(solve, nv=nv, nu=nu, bounded=np.asarray(bounded, int),
                               dtype=dtype, settings=settings)
    else:
        fn = functools.partial(solve_generic, dtype=dtype, settings=settings)
    return jax.jit(jax.vmap(fn))


def solve_batch(qps: QP, *, nv: int = 36, nu: int = 20, bounded=None, dtype=None,
                settings: Settings | None = None) -> Result:
    """``solve`` jitted and vmapped over a leading batch dimension of every field."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qps.P).dtype
    st = settings if settings is not None else Settings.for_dtype(dtype)
    b = tuple(int(i) for i in (np.zeros(0, int) if bounded is None else np.asarray(bounded)))
    return _batched("controller", nv, nu, b, dtype, st)(qps)


def solve_generic_batch(qps: QP, *, dtype=None, settings: Settings | None = None) -> Result:
    """``solve_generic`` jitted and vmapped over a leading batch dimension."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qps.P).dtype
    st = settings if settings is not None else Settings.for_dtype(dtype)
    return _batched("generic", 0, 0, (), dtype, st)(qps)


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
           "solve_generic_batch", "has_controller_structure", "FALLBACK_NONE",
           "FALLBACK_RELAXED", "FALLBACK_FAILED", "FALLBACK_NAMES"]
