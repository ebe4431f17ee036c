"""Solve status codes shared by every QP solver of the project (PIQP path, JAX solver).

Plain integers (an ``IntEnum``) so that JAX returns them as an int32 array and the host
compares them with ``==`` against the same names.
"""

from __future__ import annotations

import enum


class SolveStatus(enum.IntEnum):
    SOLVED = 0       # converged to the requested tolerances; the solution passed the checks
    INFEASIBLE = 1   # the solver certified (primal or dual) infeasibility
    MAX_ITER = 2     # iteration limit reached before convergence
    # factorisation failure, non-finite iterate, or a "solved" point that failed the
    # caller's residual check
    NUMERICAL = 3


SOLVED = SolveStatus.SOLVED
INFEASIBLE = SolveStatus.INFEASIBLE
MAX_ITER = SolveStatus.MAX_ITER
NUMERICAL = SolveStatus.NUMERICAL

__all__ = ["SolveStatus", "SOLVED", "INFEASIBLE", "MAX_ITER", "NUMERICAL"]
