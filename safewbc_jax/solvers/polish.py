"""Stage 3 of the JAX QP solver: the polish, from the interior point to the exact optimum.

From the converged interior point the active set is guessed (t < z, likewise for the
bounds and the relaxed rows' slacks), and a primal active-set method (Nocedal & Wright,
Algorithm 16.3) finishes from there, each iteration solving the equality-constrained KKT
system of its working set exactly; the idea of polishing an interior solution on its
active set is OSQP's (Stellato et al. 2020). The polished point replaces the interior
point when it is primal feasible and its multipliers have the right signs (to 1e-9
relative, float64); otherwise the interior point stays. This takes the solution from the
IPM's ~1e-9 to ~1e-13 of the exact optimum, which matters here: the reduced Hessian has a
condition number ~1e7 (the internal-force directions of lambda cost only the small
regularisation Gamma).
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax

from safewbc_jax.solvers import lapack_batched as lb
from safewbc_jax.solvers.ipm import Box, Iterate, inf_norm
from safewbc_jax.solvers.settings import Settings


def kkt_factory(pb: Box, dreg, refine: int = 2):
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


def polish(it: Iterate, pb: Box, st: Settings, active, kmax: int):
    """Finish on the exact optimum with a primal active-set method (Nocedal & Wright,
    Algorithm 16.3) started at the interior point: the working set is guessed from the
    IPM (t < z), each iteration solves the KKT system of the working set exactly
    (``kkt_factory``) and steps towards its solution until a constraint outside the set
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
    pscale = 1.0 + inf_norm(jnp.where(on, pb.h, 0.0), jnp.where(pb.lb_on, pb.lb, 0.0),
                             jnp.where(pb.ub_on, pb.ub, 0.0))

    kkt_solve = kkt_factory(pb, dreg)

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
        zscale = 1.0 + inf_norm(z, g)
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


__all__ = ["polish", "kkt_factory"]
