"""Stage 2 of the JAX QP solver: a primal-dual interior point on the reduced "box" QP.

The problem (``Box``, after ``scale_problem``) is the reduced QP of ``reduce`` in its
variable u, with the fallback's slacks when relaxed:

    min 1/2 u'Pu + q'u + sum_{relaxed rows} (rho/2 s^2 + c s)
    s.t. G u - sig * s <= h,  s >= 0 (relaxed rows),  lb <= u <= ub.

Method: Mehrotra's predictor-corrector (S. Mehrotra, "On the implementation of a
primal-dual interior point method", SIAM J. Optim. 1992; for QPs as in Nocedal & Wright,
Numerical Optimization, ch. 16.6 and Gertz & Wright's OOQP), an infeasible start shifted
into the positive orthant as in Nocedal & Wright (14.3), one step length for primal and
dual (fraction to the boundary 0.99). Every inequality has a slack t >= 0 and a
multiplier z >= 0; the bounds are kept as bounds. The Newton system is reduced to the
n x n matrix  H = P + G' W G + diag(z_u/t_u + z_l/t_l) (+ a 1e-12 regularisation, scaled)
and factored by a dense Cholesky, once per iteration for the predictor and the
corrector. Every factorisation goes through ``lapack_batched`` (under vmap, jaxlib's
LAPACK kernels in sub-batches small enough to run inline: one big batched call can
deadlock XLA's CPU thread pool). The problem is scaled first: variables by half their
box width, each row of G to unit max-norm, the cost to a unit max-norm Hessian/gradient.

The relaxed problem (``relax.relax_soft_rows``: a slack s_i >= 0 on each soft row, cost
rho/2 s_i^2 + rho_lin s_i) is solved by the same iteration with the slacks as variables
of their own: their block of the Newton system is diagonal and is eliminated, so H keeps
its n x n size (W_i = D_i (rho + y_i/s_i)/(rho + D_i + y_i/s_i) on soft rows instead of
D_i = z_i/t_i). It is the same problem as PIQP's relaxed QP in [x; s] (hard rows' slacks
are pinned to zero there and absent here).

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
infeasibility (unbounded below, only possible with a singular P) is certified by a step
direction d with P d ~ 0, q'd < 0 and d feasible for the recession cone -> INFEASIBLE.
A non-finite iterate or factor -> NUMERICAL (the last finite iterate is kept);
``max_iter`` iterations without either -> MAX_ITER.

Every function works on one problem and is written for ``jax.vmap``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from safewbc_jax.solvers import lapack_batched as lb
from safewbc_jax.solvers.settings import BIG, Settings
from safewbc_jax.solvers.status import INFEASIBLE, MAX_ITER, NUMERICAL, SOLVED

_RUNNING = -1


class Box(NamedTuple):
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


class Scale(NamedTuple):
    sx: jax.Array   # u = sx * u~
    er: jax.Array   # row i of G multiplied by er_i
    cs: jax.Array   # cost multiplied by cs


def scale_problem(P, q, G, h, lb, ub, sig, rho, c):
    """Variables by half the box width, rows to unit max-norm, cost to unit max-norm."""
    dt = P.dtype
    lb_on = lb > -BIG
    ub_on = ub < BIG
    both = lb_on & ub_on
    width = jnp.where(both, 0.5 * (ub - lb), 1.0)
    sx = jnp.clip(width, 1e-3, 1e6).astype(dt)
    sx = jnp.where(both & (width > 0), sx, 1.0)
    Ps = P * sx[:, None] * sx[None, :]
    qs = q * sx
    Gs = G * sx[None, :]
    row_on = h < BIG
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
    box = Box(P=Ps * cs, q=qs * cs, G=Gs, h=hs, lb=lbs, ub=ubs, row_on=row_on,
               lb_on=lb_on, ub_on=ub_on, sig=sig,
               rho=jnp.where(sig > 0, rho * cs / er ** 2, 1.0).astype(dt),
               c=jnp.where(sig > 0, c * cs / er, 0.0).astype(dt))
    return box, Scale(sx=sx, er=er, cs=cs)


class Iterate(NamedTuple):
    """An interior point, unpacked."""
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


def _pack(pb: Box) -> _Pk:
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


def _unpack(x: _PIt, m: int, n: int) -> Iterate:
    v, lam = x.v, x.lam
    return Iterate(u=x.u, s=v[m + 2 * n:], t=v[:m], z=lam[:m], y=lam[m + 2 * n:],
               tu=v[m:m + n], zu=lam[m:m + n], tl=v[m + n:m + 2 * n], zl=lam[m + n:m + 2 * n])


def _residuals(x: _PIt, pb: Box, pk: _Pk):
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


def inf_norm(*vs):
    return jnp.max(jnp.stack([jnp.max(jnp.abs(v), initial=0.0) for v in vs]))


def _primal_infeasible(z, pb: Box, eps):
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


def _dual_infeasible(du, pb: Box, eps):
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
    return ((nrm > 0) & (jnp.max(jnp.abs(Pd)) <= eps * pscale)
            & (qd < -eps * (1 + jnp.max(jnp.abs(pb.q)))) & rows_ok & rows_relaxed_ok & box_ok)


def _converged(x: _PIt, pb: Box, pk: _Pk, res, st: Settings):
    rd, rs, rp, Cu, Pu, Cl = res
    mc = pk.d.shape[0]
    pres = inf_norm(rp)
    dres = inf_norm(rd, rs)
    pscale = inf_norm(jnp.where(pk.on[:mc], Cu, 0.0), pk.d, x.v[mc:])
    dscale = inf_norm(Pu, pb.q, Cl)
    return ((pres <= st.eps_abs + st.eps_rel * pscale)
            & (dres <= st.eps_abs + st.eps_rel * dscale)
            & (_mu(x, pk) <= st.eps_abs))


def _newton_factory(x: _PIt, pb: Box, pk: _Pk, st: Settings):
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


def _initial_point(pb: Box, pk: _Pk, st: Settings) -> _PIt:
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


def interior_point(pb: Box, st: Settings, active):
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
                           jnp.where(conv, SOLVED, jnp.where(pinf | dinf, INFEASIBLE, _RUNNING))
                           ).astype(jnp.int32)
        x_out = jax.tree_util.tree_map(lambda n_, o: jnp.where(finite, n_, o), new, x)
        return _Carry(x=x_out, k=c.k + 1, status=status)

    conv0 = _converged(x0, pb, pk, _residuals(x0, pb, pk), st)
    status0 = jnp.where(active & conv0, SOLVED, status0).astype(jnp.int32)
    out = lax.while_loop(cond, body, _Carry(x=x0, k=jnp.zeros((), jnp.int32), status=status0))
    status = jnp.where(out.status == _RUNNING, MAX_ITER, out.status).astype(jnp.int32)
    return _unpack(out.x, m, n), status, out.k


__all__ = ["Box", "Scale", "Iterate", "scale_problem", "interior_point", "inf_norm"]
