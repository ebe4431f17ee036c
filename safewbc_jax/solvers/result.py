"""The one answer both QP solvers give: ``SolveResult``, and the fallback codes.

The JAX solver (``jax_qp.solve`` / ``solve_batch``: jax arrays, a leading batch axis in a
batch) and the PIQP path (``piqp_path.PiqpSolver.solve``: numpy / Python scalars, one
QP) return the same NamedTuple with the same meaning of every field. Where no usable x
exists (fallback FAILED) x is all NaN in both, never a number that could pass for a
command.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from safewbc_jax.solvers.status import SolveStatus

FALLBACK_NONE = 0      # the QP as posed was solved
FALLBACK_RELAXED = 1   # the relaxed QP (soft rows with slack) was solved instead
FALLBACK_FAILED = 2    # neither: x is all NaN, the caller must not use it
FALLBACK_NAMES = ("none", "relaxed", "failed")

NOT_ATTEMPTED = -1     # relaxed_status where the relaxed QP was not solved


class SolveResult(NamedTuple):
    """Per-QP outcome (leading batch dimension on every field in a batch).

    Attributes:
        x: (n,) the solution of the QP as posed (fallback NONE), of the relaxed QP
            (RELAXED), or all NaN (FAILED).
        status: SolveStatus code of the QP as posed, after the acceptance check.
        fallback: FALLBACK_NONE / FALLBACK_RELAXED / FALLBACK_FAILED.
        relaxed_status: SolveStatus code of the relaxed solve, NOT_ATTEMPTED (-1) where
            it was not needed.
        iterations: interior-point iterations, both solves together.
        max_slack: largest soft-row slack of the relaxed solution (0 for NONE, NaN for
            FAILED).
        eq_residual: max |A x - b| (NaN for FAILED).
        ineq_violation: max violation of G x <= h and the bounds, soft rows included
            (NaN for FAILED).
        hard_violation: the same over hard rows and bounds only (NaN for FAILED).
        polished: the returned x is the JAX solver's active-set polish (an exact KKT
            point); False on the PIQP path, which has no polish.
        polish_iterations: KKT solves of the polish, both solves together (0 on PIQP).
    """

    x: Any
    status: Any
    fallback: Any
    relaxed_status: Any
    iterations: Any
    max_slack: Any
    eq_residual: Any
    ineq_violation: Any
    hard_violation: Any
    polished: Any
    polish_iterations: Any


def row(res: SolveResult, i: int) -> SolveResult:
    """One QP's result out of a host SolveResult of arrays.

    Args:
        res: a SolveResult of numpy arrays with a leading axis L.
        i: the row, 0 <= i < L.

    Returns:
        Row ``i`` as one QP's result: x a numpy row, the other fields plain Python
        values, status a SolveStatus.
    """
    return SolveResult(
        x=res.x[i], status=SolveStatus(int(res.status[i])), fallback=int(res.fallback[i]),
        relaxed_status=int(res.relaxed_status[i]), iterations=int(res.iterations[i]),
        max_slack=float(res.max_slack[i]), eq_residual=float(res.eq_residual[i]),
        ineq_violation=float(res.ineq_violation[i]), hard_violation=float(res.hard_violation[i]),
        polished=bool(res.polished[i]), polish_iterations=int(res.polish_iterations[i]))


def failed(n: int, status: int = SolveStatus.NUMERICAL) -> SolveResult:
    """A host-side FAILED result: a step without a usable solution, e.g. one with a
    refused measurement.

    Args:
        n: the number of variables.
        status: the SolveStatus code to record (default NUMERICAL).

    Returns:
        A SolveResult with x all NaN, fallback FALLBACK_FAILED, NaN residuals and no
        iterations.
    """
    nan = float("nan")
    return SolveResult(x=np.full(n, np.nan), status=SolveStatus(int(status)),
                       fallback=FALLBACK_FAILED, relaxed_status=NOT_ATTEMPTED, iterations=0,
                       max_slack=nan, eq_residual=nan, ineq_violation=nan, hard_violation=nan,
                       polished=False, polish_iterations=0)


def fallback_name(code: int) -> str:
    """The name of a fallback code (one QP).

    Args:
        code: FALLBACK_NONE, FALLBACK_RELAXED or FALLBACK_FAILED (any integer type).

    Returns:
        "none", "relaxed" or "failed".
    """
    return FALLBACK_NAMES[int(code)]


__all__ = ["SolveResult", "row", "FALLBACK_NONE", "FALLBACK_RELAXED", "FALLBACK_FAILED",
           "FALLBACK_NAMES", "NOT_ATTEMPTED", "failed", "fallback_name"]
