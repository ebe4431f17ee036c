"""Single-robot deployment path: the controller QP through PIQP, with a fallback policy.

Two ways in:

* ``PiqpSolver`` for the real-time loop: solves a stream of same-shape QPs. The default
  backend ``"dense"`` drives ``piqp.DenseSolver`` directly: ``setup`` once, then
  ``update`` + ``solve`` each step (a new ``setup`` only when a shape changes). Backend
  ``"qpsolvers"`` goes through ``qpsolvers.solve_problem(..., solver="piqp",
  backend="dense")`` every step and is the correctness reference.
* ``solve_qp_piqp(qp, initvals=None)`` for one-off use: one plain qpsolvers/PIQP solve,
  no fallback, returns ``(x or None, SolveStatus)``.

Warm start. PIQP 0.7 (the installed version) has no way to pass an initial iterate: the
Python ``DenseSolver`` offers only ``setup``/``update``/``solve``/``settings``/``result``,
and each ``solve`` starts from its own initial point (a regularised KKT solve), so
re-solving an unchanged problem after ``update`` takes the same number of iterations as
the first solve. qpsolvers' PIQP interface accepts ``initvals`` but documents and
implements it as ignored ("warm-start values are ignored by PIQP"), and it builds a fresh
``DenseSolver`` (``setup``) on every call. ``initvals`` is still accepted here for API
parity with the JAX solver and forwarded to qpsolvers, which drops it.

What ``update`` does and does not buy (benchmarks/README.md, "Figures behind design
choices"): ``setup`` on the controller's size is cheap, so setup + solve and update + solve
cost about the same; the solve dominates. After ``update`` the Ruiz equilibration does not
end where a fresh ``setup`` would (with ``preconditioner_iter=0`` the two agree bit for
bit), so its x differs from a fresh setup's by amounts of the order of the solver tolerance
(up to ~1e-5 on these QPs at the default eps): x then depends slightly on the history of
QPs. The PIQP setting ``preconditioner_reuse_on_update=True`` (pass it as a keyword) skips
the re-equilibration, which saves part of the solve time; with ``update=False`` every call
is a setup and x is bit-identical to the qpsolvers path.

Fallback policy (``policy``: the same acceptance checks and decision as the JAX solver;
each ``PiqpSolver.solve`` returns a ``result.SolveResult``, the JAX solver's type):

  (a) solve the QP; accept x when PIQP reports solved, x is finite and its residuals pass
      ``feas_tol`` -> fallback FALLBACK_NONE;
  (b) otherwise solve ``relax_soft_rows(qp)`` (slacks on the soft rows; hard rows,
      equalities and bounds kept) -> FALLBACK_RELAXED, ``max_slack``;
  (c) if that fails too -> x all NaN, FALLBACK_FAILED: the caller holds its last good
      torque. Never raises on solver failure.

The relaxed QP is solved with the slack columns of hard rows removed (they are pinned to
zero by lb = ub = 0 in ``relax_soft_rows``, so this is the same problem, with fewer
variables for PIQP to factor).
"""

from __future__ import annotations

import copy
import time
from typing import Any

import numpy as np
import piqp
import qpsolvers

from safewbc_jax.solvers.problem import QP
from safewbc_jax.solvers import policy
from safewbc_jax.solvers.policy import Attempt
from safewbc_jax.solvers.relax import DEFAULT_RHO, DEFAULT_RHO_LIN, relax_soft_rows_np
from safewbc_jax.solvers.result import (FALLBACK_NONE, NOT_ATTEMPTED,
                                        SolveResult, row)
from safewbc_jax.solvers.status import SolveStatus

_PIQP_STATUS = {
    int(piqp.PIQP_SOLVED): SolveStatus.SOLVED,
    int(piqp.PIQP_PRIMAL_INFEASIBLE): SolveStatus.INFEASIBLE,
    # dual infeasible = unbounded below; cannot happen with P > 0, but it is a certificate
    # that the problem as posed has no solution, not a numerical accident.
    int(piqp.PIQP_DUAL_INFEASIBLE): SolveStatus.INFEASIBLE,
    int(piqp.PIQP_MAX_ITER_REACHED): SolveStatus.MAX_ITER,
    int(piqp.PIQP_NUMERICS): SolveStatus.NUMERICAL,
    int(piqp.PIQP_UNSOLVED): SolveStatus.NUMERICAL,
    int(piqp.PIQP_INVALID_SETTINGS): SolveStatus.NUMERICAL,
}

DEFAULT_SETTINGS: dict[str, Any] = {
    # PIQP 0.7's own defaults, spelled out so that every path here solves to the same
    # tolerances whatever a future PIQP changes.
    "eps_abs": 1e-8,
    "eps_rel": 1e-9,
    "max_iter": 250,
}


# The deployment's reduced QP (20 torques, box bounds, the contact and barrier rows in u)
# without PIQP's Ruiz equilibration: on squat and walking QPs of the MuJoCo loop it then
# takes 7 instead of 11 iterations on the squat (about 45 vs 90 us bare), and its x is as
# close to a tight solve (eps 1e-12) as with the equilibration (max |dx| 1.7e-4 vs 1.1e-4
# N m on the squat, 0.11 vs 0.15 on walking, whose QP is flat in some directions;
# objective excess <= 5e-6). Not for the full 78-variable QP (there, up to 168
# iterations) nor the relaxed QP, whose slack weights need the equilibration.
REDUCED_QP_SETTINGS: dict[str, Any] = {"preconditioner_iter": 0}


def status_from_piqp(status) -> SolveStatus:
    """Map a ``piqp.Status`` to the project's ``SolveStatus``."""
    return _PIQP_STATUS.get(int(status), SolveStatus.NUMERICAL)


def qp_to_numpy(qp: QP) -> QP:
    """The QP with float64 numpy arrays (a no-op copy-wise for numpy float64 input), the
    block sizes kept."""
    return qp.with_arrays(lambda a: np.asarray(a, dtype=np.float64))


def residuals(x: np.ndarray, qp: QP) -> tuple[float, float, float]:
    """(max |Ax - b|, max inequality violation over G rows and bounds, the same over hard
    rows and bounds only) of x for a numpy QP (``policy.residuals``). Violations are
    >= 0."""
    eq, ineq, hard = (float(r) for r in policy.residuals(x, qp, np)[:3])
    return eq, ineq, hard


class _DenseBackend:
    """piqp.DenseSolver kept across calls: setup on the first call or a shape change, then
    update (``update=True``) or a fresh setup on the same object (``update=False``)."""

    def __init__(self, settings: dict[str, Any], update: bool = True):
        self.settings = settings
        self.update = update
        self.solver: Any = None          # a piqp solver, made at the first solve
        self.shape: tuple | None = None

    def _new_solver(self):
        s = piqp.DenseSolver()
        for k, v in self.settings.items():
            setattr(s.settings, k, v)
        return s

    def solve(self, qp: QP, initvals=None):
        n, me, mi = qp.P.shape[0], qp.A.shape[0], qp.G.shape[0]
        # DenseSolver wants Fortran-ordered matrices; P is symmetric, so P.T is the same
        # matrix and (for C-ordered P) already Fortran-ordered: no copy.
        P = qp.P.T if qp.P.flags.c_contiguous else qp.P
        A = np.asfortranarray(qp.A) if me else None
        G = np.asfortranarray(qp.G) if mi else None
        b = qp.b if me else None
        h = qp.h if mi else None
        shape = (n, me, mi)
        if self.solver is None or shape != self.shape:
            self.solver = self._new_solver()
            self.shape = None
        if self.update and self.shape is not None:
            self.solver.update(P=P, c=qp.q, A=A, b=b, G=G, h_u=h, x_l=qp.lb, x_u=qp.ub)
        else:
            self.solver.setup(P, qp.q, A, b, G, None, h, qp.lb, qp.ub)
            self.shape = shape
        status = self.solver.solve()
        res = self.solver.result
        return np.array(res.x, dtype=np.float64), status_from_piqp(status), int(res.info.iter)


class _QpsolversBackend:
    """qpsolvers' PIQP interface: a fresh DenseSolver (setup) every call."""

    def __init__(self, settings: dict[str, Any]):
        self.settings = settings

    def solve(self, qp: QP, initvals=None):
        problem = qpsolvers.Problem(qp.P, qp.q, qp.G if qp.G.shape[0] else None,
                                    qp.h if qp.G.shape[0] else None,
                                    qp.A if qp.A.shape[0] else None,
                                    qp.b if qp.A.shape[0] else None, qp.lb, qp.ub)
        sol = qpsolvers.solve_problem(problem, solver="piqp", backend="dense",
                                      initvals=initvals, **self.settings)
        info = sol.extras.get("info")
        status = status_from_piqp(info.status) if info is not None else SolveStatus.NUMERICAL
        iters = int(info.iter) if info is not None else 0
        x = np.array(sol.x, dtype=np.float64) if sol.x is not None else None
        return x, status, iters


def _make_backend(backend: str, settings: dict[str, Any], update: bool = True):
    if backend == "dense":
        return _DenseBackend(settings, update)
    if backend == "qpsolvers":
        return _QpsolversBackend(settings)
    raise ValueError(f"unknown backend {backend!r} (expected 'dense' or 'qpsolvers')")


def _compact_relaxed(qp_r: QP, n: int, soft: np.ndarray) -> tuple[QP, np.ndarray]:
    """Drop the slack columns of hard rows (pinned to 0) from the relaxed QP."""
    keep = np.concatenate([np.ones(n, dtype=bool), soft > 0])
    if keep.all():
        return qp_r, keep
    return QP(P=np.ascontiguousarray(qp_r.P[np.ix_(keep, keep)]), q=qp_r.q[keep],
              A=np.ascontiguousarray(qp_r.A[:, keep]), b=qp_r.b,
              G=np.ascontiguousarray(qp_r.G[:, keep]), h=qp_r.h,
              lb=qp_r.lb[keep], ub=qp_r.ub[keep], soft=qp_r.soft), keep


class PiqpSolver:
    """Repeated PIQP solves of same-shape QPs with the fallback policy of this module.

        solver = PiqpSolver()                 # backend="dense": DenseSolver setup/update
        res = solver.solve(qp)                # a result.SolveResult

    The result's fields are plain Python values and a float64 numpy x (all NaN where
    fallback is FAILED), cheap to log: status (SolveStatus of the QP as posed, after the
    acceptance checks), fallback (result.FALLBACK_*), relaxed_status (SolveStatus, or
    result.NOT_ATTEMPTED), max_slack, iterations (PIQP's, both solves together),
    eq_residual, ineq_violation, hard_violation (NaN where FAILED); polished False and
    polish_iterations 0 (PIQP has no polish). ``last_solve_time_us``: the wall time of
    the last call (conversion, solves, checks), in us.

    Arguments:
        backend   "dense" (default) or "qpsolvers" (reference path, a setup per call)
        update    dense backend only: True (default) sets up once and then calls
                  ``DenseSolver.update``; False calls ``setup`` every time on the same
                  object, which makes x a function of this QP alone (bit-identical to the
                  qpsolvers path). See the module docstring for what each costs.
        feas_tol  acceptance tolerance on the residuals of a "solved" point, relative to
                  1 + the largest finite |b| (equalities) or |h|, |lb|, |ub| (inequalities)
        relax_rho, relax_rho_lin   penalty weights passed to ``relax_soft_rows``
        nominal_settings  PIQP settings for the QP as posed only, over ``settings``
                  (e.g. ``REDUCED_QP_SETTINGS``, for a reduced QP)
        **settings  PIQP settings (eps_abs, eps_rel, max_iter, ...), applied to both the
                  nominal and the relaxed solver
    """

    def __init__(self, backend: str = "dense", *, update: bool = True,
                 feas_tol: float = 1e-6, relax_rho: float = DEFAULT_RHO,
                 relax_rho_lin: float = DEFAULT_RHO_LIN, nominal_settings=None, **settings):
        self.backend = backend
        self.update = bool(update)
        self.settings = {**DEFAULT_SETTINGS, **settings}
        self.nominal_settings = {**self.settings, **(nominal_settings or {})}
        self.feas_tol = float(feas_tol)
        self.relax_rho = relax_rho
        self.relax_rho_lin = relax_rho_lin
        self._nominal = _make_backend(backend, self.nominal_settings, self.update)
        self._relaxed = _make_backend(backend, self.settings, self.update)
        self.last_solve_time_us = float("nan")

    def reset(self) -> None:
        """Forget the set-up solvers (the next call does a fresh setup)."""
        self._nominal = _make_backend(self.backend, self.nominal_settings, self.update)
        self._relaxed = _make_backend(self.backend, self.settings, self.update)

    def lane(self) -> "PiqpSolver":
        """A solver of the same settings with backends of its own (``solvers.host``)."""
        other = copy.copy(self)
        other.reset()
        return other

    @staticmethod
    def solve_lanes(solvers: list, qp: QP, checks: policy.Checks,
                    nominal: tuple | None = None) -> SolveResult:
        """The policy's outcome for L QPs of one shape, each with its own ``PiqpSolver``
        (``solvers[l]``; L may be 1): PIQP solves each QP as posed, the acceptance of all L
        runs at once (``policy.accept_batch``), and the relaxed QP (b) is solved, per QP,
        only where the QP as posed failed. ``qp`` and ``checks``: float64 numpy arrays with
        the leading axis L. Returns one SolveResult whose fields are numpy arrays with the
        leading axis L; a row does not depend on the other QPs (``tests/test_lockstep.py``).
        ``nominal``: (x (L, n), status (L,), iterations (L,)) of the QPs as posed, where
        ``solve_nominal`` has already solved them; they are then not solved again."""
        L, n, mi = len(solvers), qp.P.shape[-1], qp.G.shape[-2]
        rows = [qp.row(k) for k in range(L)]
        if nominal is None:
            X = np.empty((L, n))
            status, iters = np.empty(L, np.int64), np.zeros(L, np.int64)
            for k, s in enumerate(solvers):
                t0 = time.perf_counter_ns()
                X[k], status[k], iters[k] = s.solve_nominal(rows[k])
                s.last_solve_time_us = (time.perf_counter_ns() - t0) / 1e3
        else:
            X, status, iters = (np.array(a) for a in nominal)
        tol = np.array([s.feas_tol for s in solvers])
        status, (eq, ineq, hard) = policy.accept_batch(X, qp, status, tol, checks)
        ok = status == int(SolveStatus.SOLVED)
        # the accepted QPs' fields; each other row is set whole below
        out = SolveResult(
            x=X, status=status, fallback=np.full(L, FALLBACK_NONE),
            relaxed_status=np.full(L, NOT_ATTEMPTED), iterations=iters, max_slack=np.zeros(L),
            eq_residual=eq, ineq_violation=ineq, hard_violation=hard, polished=np.zeros(L, bool),
            polish_iterations=np.zeros(L, np.int64))
        for k in ([] if ok.all() else np.flatnonzero(~ok).tolist()):   # (b), then (c): rare
            s, t0 = solvers[k], time.perf_counter_ns()
            nom = Attempt(x=X[k], status=int(status[k]), res=(eq[k], ineq[k], hard[k]),
                          max_slack=0.0, iterations=int(iters[k]), polished=False,
                          polish_iterations=0)
            r = policy.finish(nom, s.solve_relaxed(rows[k], n, mi), np)
            for field, a in zip(SolveResult._fields, out):
                a[k] = getattr(r, field)
            s.last_solve_time_us += (time.perf_counter_ns() - t0) / 1e3
        return out

    def solve(self, qp: QP, initvals=None, checks: policy.Checks | None = None) -> SolveResult:
        """The policy's outcome for ``qp`` (class docstring): ``solve_lanes`` with this one
        solver (one QP is one lane). ``checks``: ``policy.checks`` of this QP computed
        before; qp's arrays must then be float64 numpy already (they are not converted);
        without them they are computed here. ``initvals``: accepted and ignored (PIQP's
        interfaces ignore it: module docstring)."""
        del initvals
        t0 = time.perf_counter_ns()
        if checks is None:
            qp = qp_to_numpy(qp)
            checks = policy.checks(qp)
        one = PiqpSolver.solve_lanes([self], qp.with_arrays(lambda a: a[None]),
                          policy.Checks(*(np.asarray(c)[None] for c in checks)))
        self.last_solve_time_us = (time.perf_counter_ns() - t0) / 1e3
        return row(one, 0)

    def solve_nominal(self, qp: QP, initvals=None):
        """(a): PIQP on the QP as posed: (x, all NaN where PIQP gave none; its status;
        iterations). A solver exception is a failed solve (NUMERICAL) and a fresh backend,
        never a crash."""
        try:
            x, status, iters = self._nominal.solve(qp, initvals)
        except Exception:  # noqa: BLE001 - a solver exception is a failed step, not a crash
            self._nominal = _make_backend(self.backend, self.nominal_settings, self.update)
            x, status, iters = None, SolveStatus.NUMERICAL, 0
        return (np.full(qp.P.shape[0], np.nan) if x is None else x), status, iters

    def solve_relaxed(self, qp: QP, n: int, mi: int) -> Attempt:
        """(b): the relaxed QP, its slack columns of hard rows left out."""
        try:
            qp_r = relax_soft_rows_np(qp, self.relax_rho, self.relax_rho_lin)
            qp_c, keep = _compact_relaxed(qp_r, n, qp.soft)
            z, rstatus, iters = self._relaxed.solve(qp_c)
        except Exception:  # noqa: BLE001
            self._relaxed = _make_backend(self.backend, self.settings, self.update)
            z, rstatus, iters = None, SolveStatus.NUMERICAL, 0
        if z is None:
            z = np.full(n + int(np.count_nonzero(qp.soft > 0)), np.nan)
        xr, s = np.array(z[:n]), z[n:]
        slack = np.zeros(mi)
        slack[qp.soft > 0] = s
        rstatus, res = policy.accept(xr, qp, rstatus, self.feas_tol, np, slack=slack)
        return Attempt(x=xr, status=rstatus, res=res, max_slack=float(np.max(s, initial=0.0)),
                       iterations=iters, polished=False, polish_iterations=0)


def solve_qp_piqp(qp: QP, initvals=None, **settings) -> tuple[np.ndarray | None, SolveStatus]:
    """One plain solve through qpsolvers' PIQP interface (dense backend), no fallback.

    Returns (x, status): x is a finite float64 numpy array when status is SOLVED, else None.
    ``initvals`` is forwarded to qpsolvers, whose PIQP interface ignores it. ``settings``
    are PIQP settings (defaults: ``DEFAULT_SETTINGS``). "Solved" includes the finiteness
    and residual checks of ``PiqpSolver`` with its default ``feas_tol``.
    """
    qp = qp_to_numpy(qp)
    try:
        x, status, _ = _QpsolversBackend({**DEFAULT_SETTINGS, **settings}).solve(qp, initvals)
    except Exception:  # noqa: BLE001
        return None, SolveStatus.NUMERICAL
    x = np.full(qp.P.shape[0], np.nan) if x is None else x
    status, _ = policy.accept(x, qp, status, 1e-6, np)
    return (x if status == SolveStatus.SOLVED else None), status


__all__ = ["PiqpSolver", "solve_qp_piqp", "status_from_piqp", "qp_to_numpy",
           "residuals", "DEFAULT_SETTINGS", "REDUCED_QP_SETTINGS"]
