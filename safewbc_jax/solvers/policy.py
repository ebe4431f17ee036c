"""What both solvers decide alike: whether a solved point is accepted, and the fallback.

Acceptance. A solver's "solved" is taken only when x is finite and its full-space
residuals pass ``feas_tol``:

    max |A x - b|                          <= feas_tol (1 + max |b|)
    max violation of G x <= h and bounds   <= feas_tol (1 + max finite |h|, |lb|, |ub|)

(entries of h and of the bounds at or above ``BIG`` in size count as absent), else the
status becomes NUMERICAL. For the relaxed QP the rows checked are G x - s <= h, s >= 0,
with the slacks s of its solution.

Fallback policy (the paper's QP may be infeasible when a barrier and the contact rows
conflict; the loop must still command something):

  (a) solve the QP as posed; accepted -> fallback NONE, x its solution;
  (b) otherwise solve the relaxed QP (``relax.relax_soft_rows``: a slack on each soft
      row, hard rows, equalities and bounds kept); accepted -> RELAXED, x its solution,
      ``max_slack`` its largest slack;
  (c) otherwise FAILED: x all NaN, and the caller holds its last good torque.

``decide`` is that rule and ``finish`` builds the ``SolveResult`` from the two attempts;
they run traced (``xp`` = jax.numpy: selections by ``where``, batches by vmap) or on the
host (``xp`` = numpy, one QP: plain Python selections). Everything here is written once
for either ``xp``.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from safewbc_jax.solvers.problem import QP
from safewbc_jax.solvers.result import (FALLBACK_FAILED, FALLBACK_NONE, FALLBACK_RELAXED,
                                        NOT_ATTEMPTED, SolveResult)
from safewbc_jax.solvers.settings import BIG
from safewbc_jax.solvers.status import NUMERICAL, SOLVED


def _select(xp):
    """where(cond, a, b) for a scalar cond: traced for jax.numpy, a Python branch on the
    host (one QP; cheaper than numpy's where on 0-d arrays)."""
    return jnp.where if xp is jnp else (lambda c, a, b: a if c else b)


def residuals(x, qp: QP, xp=np, slack=None):
    """(max |Ax - b|, max violation over G rows and bounds, the same over hard rows only,
    and the violation of the relaxed QP's rows G x - s <= h, s >= 0 when ``slack`` s is
    given, else the second again). Violations are >= 0. An absent row or bound (h, ub
    +inf or >= BIG, lb likewise) can only contribute a negative value to a maximum that
    starts at 0, so no mask is needed for it (and for a finite x none is applied)."""
    eq = xp.abs(qp.A @ x - qp.b).max(initial=0.0)
    bnd = xp.maximum((qp.lb - x).max(initial=0.0), (x - qp.ub).max(initial=0.0))
    gx = qp.G @ x - qp.h
    ineq = xp.maximum(bnd, gx.max(initial=0.0))
    hard = xp.maximum(bnd, xp.where(qp.soft > 0, -xp.inf, gx).max(initial=0.0))
    if slack is None:
        return eq, ineq, hard, ineq
    rel = xp.maximum(bnd, (gx - slack).max(initial=0.0))
    rel = xp.maximum(rel, (-slack).max(initial=0.0))
    return eq, ineq, hard, rel


def scales(qp: QP, xp=np):
    """(1 + max |b|, 1 + the largest |h|, |lb|, |ub| below BIG): the acceptance's scales.
    A row of G that is all zero constrains nothing, and its h is left out: the controller
    switches a barrier row off as 0 q_ddot >= -1e9 (``controller.build_qp``), and that
    1e9 would otherwise make the tolerance on every other row 1e9 times looser."""
    eq_scale = 1.0 + xp.abs(qp.b).max(initial=0.0)
    live = xp.any(qp.G != 0, axis=-1)
    hv = xp.abs(qp.h)
    bv = xp.abs(xp.concatenate([qp.lb, qp.ub]))
    in_scale = 1.0 + xp.maximum(xp.where(live & (hv < BIG), hv, 0.0).max(initial=0.0),
                                xp.where(bv < BIG, bv, 0.0).max(initial=0.0))
    return eq_scale, in_scale


class Checks(NamedTuple):
    """The part of the acceptance of one QP that does not depend on x (``checks``): the
    two scales of ``scales``, and every inequality of the QP as one block of rows,

        rows x <= rhs,    rows = [G; -I; I],  rhs = [h; -lb; ub],

    with ``soft_pen`` -inf on the soft rows of G and 0 on the others (hard rows and the
    bounds), so that max(rows x - rhs + soft_pen) is the hard rows' violation. It can be
    computed with the QP inside a jitted step (``xp`` = jax.numpy); the host's acceptance
    is then one matrix-vector product and three reductions
    (``residuals_checked``) instead of the dozen small numpy operations of ``scales``
    and ``residuals``."""

    eq_scale: Any
    in_scale: Any
    rows: Any
    rhs: Any
    soft_pen: Any


def checks(qp: QP, xp=np) -> Checks:
    """``Checks`` of ``qp``."""
    eq_scale, in_scale = scales(qp, xp)
    n = qp.P.shape[-1]
    eye = xp.eye(n, dtype=qp.G.dtype)
    rows = xp.concatenate([qp.G, -eye, eye], axis=0)
    rhs = xp.concatenate([qp.h, -qp.lb, qp.ub])
    soft_pen = xp.concatenate([xp.where(qp.soft > 0, -xp.inf, 0.0), xp.zeros(2 * n)])
    return Checks(eq_scale, in_scale, rows, rhs, soft_pen)


def residuals_checked(x, qp: QP, ch: Checks, xp=np):
    """(eq, ineq, hard) of ``residuals`` for x and ``ch`` = ``checks(qp)``, as ``xp``
    arrays (numpy on the host; jax.numpy in the generated acceptance of
    ``deploy.compiled``). A non-finite x gives a NaN or +inf in ineq (each x_i is in two
    rows, +x_i - ub_i and -x_i + lb_i: an infinite x_i makes one of them +inf or
    inf - inf), so that ineq's test also rejects it; ``tests/test_piqp_path.py`` holds
    the two to each other. Leading axes of x, of qp's arrays and of ch's arrays are a
    batch of QPs; the residuals then have those axes (0-d arrays for one QP)."""
    def mv(m, y):                                # m y over leading axes
        return m @ y if y.ndim == 1 else (m @ y[..., None])[..., 0]

    if qp.A.shape[-2]:
        eq = xp.abs(mv(qp.A, x) - qp.b).max(axis=-1)
    else:
        eq = xp.zeros(x.shape[:-1])
    v = mv(ch.rows, x) - ch.rhs
    ineq = xp.maximum(v.max(axis=-1, initial=-np.inf), 0.0)
    hard = xp.maximum((v + ch.soft_pen).max(axis=-1, initial=-np.inf), 0.0)
    return eq, ineq, hard


def within(eq, ineq, feas_tol, checks: Checks):
    """Whether residuals (eq, ineq) of ``residuals_checked`` pass ``feas_tol`` on the
    scales of ``checks`` (elementwise over a batch). A NaN fails both comparisons: ineq is
    NaN or inf for a non-finite x."""
    return (eq <= feas_tol * checks.eq_scale) & (ineq <= feas_tol * checks.in_scale)


def accept_batch(x, qp: QP, status, feas_tol, checks: Checks):
    """``accept`` with ``checks`` for a batch of QPs on the host:
    x (L, n), status (L,) SolveStatus codes, qp's and checks' arrays with the leading axis
    L. Returns (status (L,), (eq, ineq, hard) each (L,)); the residuals are NaN where the
    solver did not report SOLVED, as ``accept`` leaves them on the host."""
    status = np.asarray(status)
    eq, ineq, hard = residuals_checked(x, qp, checks)
    solved = status == int(SOLVED)       # an int: numpy compares an IntEnum ~5 us slower
    out = np.where(solved & ~within(eq, ineq, feas_tol, checks), int(NUMERICAL), status)
    if solved.all():
        return out, (eq, ineq, hard)
    return out, tuple(np.where(solved, r, np.nan) for r in (eq, ineq, hard))


def accept(x, qp: QP, status, feas_tol, xp=np, slack=None, checks: Checks | None = None):
    """SOLVED stays SOLVED only where x is finite and its residuals pass (module
    docstring); ``slack`` (on G's rows) checks the relaxed QP's rows instead of G's.
    ``checks`` (host only, without ``slack``): this QP's ``Checks``, computed before.
    Returns (status, (eq, ineq, hard)); on the host, where the solver did not report
    SOLVED, the residuals are not computed (NaN)."""
    if xp is not jnp and status != SOLVED:
        return status, (float("nan"),) * 3
    if checks is not None:
        eq, ineq, hard = (float(r) for r in residuals_checked(x, qp, checks))
        if status == SOLVED and not within(eq, ineq, feas_tol, checks):
            status = NUMERICAL
        return status, (eq, ineq, hard)
    eq_scale, in_scale = scales(qp, xp)
    eq, ineq, hard, chk = residuals(x, qp, xp, slack)
    good = xp.all(xp.isfinite(x)) & (eq <= feas_tol * eq_scale) & (chk <= feas_tol * in_scale)
    if xp is jnp:
        status = jnp.where((status == SOLVED) & ~good, NUMERICAL, status).astype(jnp.int32)
    elif status == SOLVED and not good:
        status = NUMERICAL
    return status, (eq, ineq, hard)


class Attempt(NamedTuple):
    """One solve of the policy (the QP as posed, or the relaxed QP): x over the QP's
    variables, its status after ``accept``, the residuals (eq, ineq, hard) ``accept``
    returned, the largest soft-row slack (0 for the QP as posed), iterations, and the
    JAX solver's polish flag and KKT-solve count (False, 0 on PIQP)."""

    x: Any
    status: Any
    res: tuple
    max_slack: Any
    iterations: Any
    polished: Any
    polish_iterations: Any


def skipped(x_like, xp=np) -> Attempt:
    """The relaxed attempt where no QP needed it (a placeholder)."""
    nan = xp.full((), xp.nan, x_like.dtype)
    zero = xp.zeros((), jnp.int32) if xp is jnp else 0
    return Attempt(x=xp.full_like(x_like, xp.nan), status=xp.full((), NUMERICAL, jnp.int32)
                   if xp is jnp else NUMERICAL, res=(nan, nan, nan), max_slack=nan,
                   iterations=zero, polished=xp.zeros((), bool) if xp is jnp else False,
                   polish_iterations=zero)


def decide(nominal_ok, relaxed_ok, xp=np):
    """The fallback code: NONE where the QP as posed was accepted, else RELAXED where the
    relaxed QP was, else FAILED."""
    sel = _select(xp)
    return sel(nominal_ok, FALLBACK_NONE, sel(relaxed_ok, FALLBACK_RELAXED, FALLBACK_FAILED))


def finish(nom: Attempt, rel: Attempt | None, xp=np) -> SolveResult:
    """The policy's outcome as a SolveResult: x of the QP as posed, else of the relaxed
    QP, else all NaN. ``rel`` None: no fallback (FAILED wherever the QP as posed fails,
    relaxed_status NOT_ATTEMPTED)."""
    sel = _select(xp)
    jx = xp is jnp
    ok = nom.status == SOLVED
    fb = decide(ok, False if rel is None else rel.status == SOLVED, xp)
    relaxed = fb == FALLBACK_RELAXED
    need = fb != FALLBACK_NONE
    nan_x = xp.full_like(nom.x, xp.nan)
    nan = xp.full((), xp.nan, nom.x.dtype) if jx else float("nan")
    zero = xp.zeros((), nom.x.dtype) if jx else 0.0
    if rel is None:
        rstatus = xp.full((), NOT_ATTEMPTED, jnp.int32) if jx else NOT_ATTEMPTED
        x_out = sel(ok, nom.x, nan_x)
        max_slack = sel(ok, zero, nan)
        iters, kp = nom.iterations, nom.polish_iterations
        polished = ok & nom.polished if jx else bool(ok and nom.polished)
        eq, ineq, hard = (sel(ok, a, nan) for a in nom.res)
    else:
        rstatus = sel(need, rel.status, NOT_ATTEMPTED)
        x_out = sel(ok, nom.x, sel(relaxed, rel.x, nan_x))
        max_slack = sel(ok, zero, sel(relaxed, rel.max_slack, nan))
        iters = nom.iterations + sel(need, rel.iterations, 0)
        kp = nom.polish_iterations + sel(need, rel.polish_iterations, 0)
        polished = sel(ok, nom.polished, relaxed & rel.polished)
        eq, ineq, hard = (sel(ok, a, sel(relaxed, b, nan)) for a, b in zip(nom.res, rel.res))
    if jx:
        i32 = jnp.int32
        return SolveResult(x=x_out, status=jnp.asarray(nom.status).astype(i32),
                           fallback=fb.astype(i32), relaxed_status=jnp.asarray(rstatus).astype(i32),
                           iterations=jnp.asarray(iters).astype(i32),
                           max_slack=max_slack.astype(nom.x.dtype), eq_residual=eq,
                           ineq_violation=ineq, hard_violation=hard, polished=polished,
                           polish_iterations=jnp.asarray(kp).astype(i32))
    return SolveResult(x=x_out, status=nom.status, fallback=fb, relaxed_status=rstatus,
                       iterations=int(iters), max_slack=float(max_slack), eq_residual=float(eq),
                       ineq_violation=float(ineq), hard_violation=float(hard),
                       polished=bool(polished), polish_iterations=int(kp))


__all__ = ["residuals", "scales", "Checks", "checks", "residuals_checked", "within", "accept",
           "accept_batch", "Attempt", "skipped", "decide", "finish"]
