"""How a host-side QP solver meets the deployed controller (``deploy.Controller``): a small
protocol, not a type test. ``piqp_path.PiqpSolver`` implements all of it; a user's solver
needs ``solve`` alone.

    solve(qp, checks=None) -> SolveResult   the step's reduced QP (float64 numpy); checks:
                                             ``policy.checks`` of that QP, computed in the
                                             jitted step (a solver may use or ignore them)
    reset()                                  optional: forget set-up state
    lane() -> solver                         optional: an independent solver of the same
                                             settings for another lane (without it,
                                             a deep copy)
    solve_lanes(solvers, qp, checks)         optional, on the class: L QPs of one shape at
                                             once, row l as ``solvers[l].solve`` gives it
                                             (without it, one ``solve`` per lane)

``solve_lanes`` of this module solves a step's QPs, one robot's (L = 1) or several lanes'.
"""

from __future__ import annotations

import copy
from typing import Protocol, runtime_checkable

import numpy as np

from safewbc_jax.solvers.problem import QP
from safewbc_jax.solvers.result import SolveResult


@runtime_checkable
class HostSolver(Protocol):
    def solve(self, qp: QP, checks=None) -> SolveResult: ...


def check(solver) -> None:
    """Raise ValueError unless ``solver`` has a callable ``solve``."""
    if not callable(getattr(solver, "solve", None)):
        raise ValueError(f"solver {solver!r}: 'piqp' or an object with solve(qp, checks=None) "
                         "-> SolveResult (solvers.host; the JAX solver runs batched, "
                         "batch.rollout)")


def reset(solver) -> None:
    """``solver.reset()`` where it has one."""
    getattr(solver, "reset", lambda: None)()


def lane(solver):
    """An independent solver for another lane: ``solver.lane()``, else a deep copy."""
    make = getattr(solver, "lane", None)
    return make() if callable(make) else copy.deepcopy(solver)


def solves_lanes(solver) -> bool:
    """Whether ``solver``'s class solves several lanes' QPs at once (``solve_lanes``)."""
    return callable(getattr(type(solver), "solve_lanes", None))


def solve_lanes(solvers: list, qp: QP, checks) -> SolveResult:
    """The QP of each lane l (``qp``'s and ``checks``' arrays with the leading axis L) by
    its own solver ``solvers[l]``: the class's ``solve_lanes`` where all L solvers are of
    one class that has it, else one ``solve`` per lane. Returns one SolveResult whose
    fields are numpy arrays with the leading axis L."""
    kind = type(solvers[0])
    if solves_lanes(solvers[0]) and all(type(s) is kind for s in solvers):
        return kind.solve_lanes(solvers, qp, checks)
    rows = [s.solve(qp.row(i), checks=type(checks)(*(c[i] for c in checks)))
            for i, s in enumerate(solvers)]
    return SolveResult(*(np.stack([np.asarray(getattr(r, f)) for r in rows])
                         for f in SolveResult._fields))
