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

What ``update`` does and does not buy (measured, benchmarks/piqp_qp_bench.py, n=78,
me=58, mi=40): ``setup`` on this size is cheap, so setup + solve and update + solve cost
the same to within a few percent; the solve (~8 interior-point iterations) dominates.
After ``update`` the Ruiz equilibration does not end where a fresh ``setup`` would (with
``preconditioner_iter=0`` the two agree bit for bit), so its x differs from a fresh
setup's by amounts of the order of the solver tolerance (up to ~1e-5 on these QPs at the
default eps): x then depends slightly on the history of QPs.
The PIQP setting ``preconditioner_reuse_on_update=True`` (pass it as a keyword) skips the
re-equilibration and saves ~15-20% of the solve time; with ``update=False`` every call is
a setup and x is bit-identical to the qpsolvers path.

Fallback policy (each ``PiqpSolver.solve`` returns ``(x, info)``):

  (a) solve the QP; accept x when PIQP reports solved, x is finite and its residuals pass
      ``feas_tol`` -> fallback="none";
  (b) otherwise solve ``relax_soft_rows(qp)`` (slacks on the soft rows; hard rows,
      equalities and bounds kept) -> fallback="relaxed", info["max_slack"];
  (c) if that fails too -> x=None, fallback="failed": the caller holds its last good
      torque. Never returns a non-finite x and never raises on solver failure.

The relaxed QP is solved with the slack columns of hard rows removed (they are pinned to
zero by lb = ub = 0 in ``relax_soft_rows``, so this is the same problem, with fewer
variables for PIQP to factor).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import piqp
import qpsolvers

from safewbc_jax.qp_types import QP
from safewbc_jax.solvers.relax import DEFAULT_RHO, DEFAULT_RHO_LIN, relax_soft_rows_np
from safewbc_jax.solvers.status import SolveStatus

_FIELDS = ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")

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


def status_from_piqp(status) -> SolveStatus:
    """Map a ``piqp.Status`` to the project's ``SolveStatus``."""
    return _PIQP_STATUS.get(int(status), SolveStatus.NUMERICAL)


def qp_to_numpy(qp: QP) -> QP:
    """The QP with float64 numpy arrays (a no-op copy-wise for numpy float64 input)."""
    return QP(*(np.asarray(getattr(qp, f), dtype=np.float64) for f in _FIELDS))


def residuals(x: np.ndarray, qp: QP) -> tuple[float, float, float]:
    """(max |Ax - b|, max inequality violation over G rows and bounds, the same over hard
    rows and bounds only) of x for a numpy QP. Violations are >= 0."""
    eq = float(np.abs(qp.A @ x - qp.b).max()) if qp.A.shape[0] else 0.0
    bound = max(float((qp.lb - x).max()), float((x - qp.ub).max()), 0.0)
    ineq = hard = bound
    if qp.G.shape[0]:
        r = qp.G @ x - qp.h
        ineq = max(bound, float(r.max()))
        r_hard = r[qp.soft <= 0]
        if r_hard.size:
            hard = max(bound, float(r_hard.max()))
    return eq, ineq, hard


def _scales(qp: QP) -> tuple[float, float]:
    """1 + the largest finite |b|, and 1 + the largest finite |h|, |lb|, |ub|."""
    eq_scale = 1.0 + (float(np.abs(qp.b).max()) if qp.b.size else 0.0)
    v = np.concatenate((qp.h, qp.lb, qp.ub))
    v = np.abs(v[np.isfinite(v)])
    return eq_scale, 1.0 + (float(v.max()) if v.size else 0.0)


class _DenseBackend:
    """piqp.DenseSolver kept across calls: setup on the first call or a shape change, then
    update (``update=True``) or a fresh setup on the same object (``update=False``)."""

    def __init__(self, settings: dict[str, Any], update: bool = True):
        self.settings = settings
        self.update = update
        self.solver = None
        self.shape = None

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


def _accept(x, status: SolveStatus, qp: QP, feas_tol: float):
    """(status, x or None, residuals) after the finiteness and residual checks."""
    if status != SolveStatus.SOLVED:
        return status, None, None
    if x is None or not np.isfinite(x).all():
        return SolveStatus.NUMERICAL, None, None
    res = residuals(x, qp)
    eq_scale, in_scale = _scales(qp)
    if not (res[0] <= feas_tol * eq_scale and res[1] <= feas_tol * in_scale):
        return SolveStatus.NUMERICAL, None, None
    return status, x, res


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
        x, info = solver.solve(qp)            # x: (n,) float64 numpy array, or None

    info (plain Python values, cheap to log):
        status          SolveStatus of the QP as posed (after the acceptance checks)
        fallback        "none" | "relaxed" | "failed"
        relaxed_status  SolveStatus of the relaxed solve, or None when not attempted
        max_slack       largest soft-row slack of the relaxed solution; 0.0 for "none",
                        None for "failed"
        iterations      PIQP iterations, both solves together
        solve_time_us   wall time of the whole call (conversion, solves, checks), in us
        eq_residual     max |A x - b| of the returned x, None when x is None
        ineq_violation  max violation of G x <= h and of the bounds (soft rows included),
                        None when x is None
        hard_violation  the same over hard rows and bounds only, None when x is None

    Arguments:
        backend   "dense" (default) or "qpsolvers" (reference path, a setup per call)
        update    dense backend only: True (default) sets up once and then calls
                  ``DenseSolver.update``; False calls ``setup`` every time on the same
                  object, which makes x a function of this QP alone (bit-identical to the
                  qpsolvers path). See the module docstring for what each costs.
        feas_tol  acceptance tolerance on the residuals of a "solved" point, relative to
                  1 + the largest finite |b| (equalities) or |h|, |lb|, |ub| (inequalities)
        relax_rho, relax_rho_lin   penalty weights passed to ``relax_soft_rows``
        **settings  PIQP settings (eps_abs, eps_rel, max_iter, ...), applied to both the
                  nominal and the relaxed solver
    """

    def __init__(self, backend: str = "dense", *, update: bool = True,
                 feas_tol: float = 1e-6, relax_rho: float = DEFAULT_RHO,
                 relax_rho_lin: float = DEFAULT_RHO_LIN, **settings):
        self.backend = backend
        self.update = bool(update)
        self.settings = {**DEFAULT_SETTINGS, **settings}
        self.feas_tol = float(feas_tol)
        self.relax_rho = relax_rho
        self.relax_rho_lin = relax_rho_lin
        self._nominal = _make_backend(backend, self.settings, self.update)
        self._relaxed = _make_backend(backend, self.settings, self.update)

    def reset(self) -> None:
        """Forget the set-up solvers (the next call does a fresh setup)."""
        self._nominal = _make_backend(self.backend, self.settings, self.update)
        self._relaxed = _make_backend(self.backend, self.settings, self.update)

    def solve(self, qp: QP, initvals=None) -> tuple[np.ndarray | None, dict[str, Any]]:
        t0 = time.perf_counter_ns()
        qp = qp_to_numpy(qp)
        n = qp.P.shape[0]
        info: dict[str, Any] = {
            "status": SolveStatus.NUMERICAL, "fallback": "failed", "relaxed_status": None,
            "max_slack": None, "iterations": 0, "solve_time_us": 0.0,
            "eq_residual": None, "ineq_violation": None, "hard_violation": None,
        }
        x_out = None

        # (a) the QP as posed
        try:
            x, status, iters = self._nominal.solve(qp, initvals)
        except Exception:  # noqa: BLE001 - a solver exception is a failed step, not a crash
            self._nominal = _make_backend(self.backend, self.settings, self.update)
            x, status, iters = None, SolveStatus.NUMERICAL, 0
        info["iterations"] += iters
        status, x, res = _accept(x, status, qp, self.feas_tol)
        info["status"] = status
        if x is not None:
            x_out = x
            info["fallback"] = "none"
            info["max_slack"] = 0.0
        else:
            # (b) the relaxed QP
            rstatus = SolveStatus.NUMERICAL
            try:
                qp_r = relax_soft_rows_np(qp, self.relax_rho, self.relax_rho_lin)
                qp_c, _ = _compact_relaxed(qp_r, n, qp.soft)
                z, rstatus, iters = self._relaxed.solve(qp_c)
                info["iterations"] += iters
                rstatus, z, _ = _accept(z, rstatus, qp_c, self.feas_tol)
            except Exception:  # noqa: BLE001
                self._relaxed = _make_backend(self.backend, self.settings, self.update)
                z = None
            info["relaxed_status"] = rstatus
            if z is not None:
                x_out = np.array(z[:n])
                s = z[n:]
                info["fallback"] = "relaxed"
                info["max_slack"] = float(np.max(s, initial=0.0))
                res = residuals(x_out, qp)
            # (c) else: x_out stays None, fallback "failed"

        if x_out is not None:
            info["eq_residual"], info["ineq_violation"], info["hard_violation"] = res
        info["solve_time_us"] = (time.perf_counter_ns() - t0) / 1e3
        return x_out, info


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
    status, x, _ = _accept(x, status, qp, 1e-6)
    return x, status


__all__ = ["PiqpSolver", "solve_qp_piqp", "status_from_piqp", "qp_to_numpy", "residuals",
           "DEFAULT_SETTINGS"]
