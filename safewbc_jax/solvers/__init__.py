"""QP solvers of the controller: a qpsolvers-style entry point over the PIQP path and the
batched JAX solver, and the status codes they share.

    x, status = solve_qp(P, q, G, h, A, b, lb, ub, solver="jax")     # or solver="piqp"

minimizes 1/2 x'Px + q'x subject to G x <= h, A x = b, lb <= x <= ub (the argument order
and the None-for-absent convention of ``qpsolvers.solve_qp``), for one QP (P of shape
(n, n)) or a batch (P of shape (B, n, n), every given array with the same leading B).

Returns ``(x, status)``:
  one QP    x a float64 numpy array, or None when there is no usable solution;
            status a ``SolveStatus`` (SOLVED, INFEASIBLE, MAX_ITER, NUMERICAL)
  a batch   x of shape (B, n) with all-NaN rows where there is no usable solution;
            status an int32 numpy array of the codes

Accepted parts (each combination qpsolvers accepts; tests/test_solve_qp_parts.py):
  * any subset of {G and h (together), A and b (together), lb, ub} may be None, all 16,
    for one QP and for a batch, with either solver, fallback and structure "auto" /
    "generic": no inequalities, no equalities, box bounds only, unconstrained, ... An
    absent part is a zero-row G / A or an infinite bound; given bounds may have
    infinite entries (-inf in lb, +inf in ub: unbounded there), h may have +inf entries.
  * one QP may also use qpsolvers' other forms: a 1-D G or A is one row, a scalar h or
    b one entry, a (1, k) or (k, 1) vector is flat, P, G, A may be scipy.sparse (made
    dense) or nested lists.
  * lb_j > ub_j for some j (an empty box): status INFEASIBLE and no x, whatever the
    solver and ``fallback`` (the fallback relaxes soft rows of G, never bounds); in a
    batch only those QPs. Decided here from the data, for both solvers alike.
  * unbounded below (P singular along a feasible direction of decreasing cost, e.g. an
    equality-only QP with P singular on null(A) and q not orthogonal to it): INFEASIBLE
    (dual infeasibility), no x. A singular P with a finite minimum is solved (x one of
    the minimisers).
  * solver="jax", generic path: A must have full row rank. As many rows as variables is
    fine (x = A^-1 b, then checked against G and the bounds); more rows than variables
    is refused (ValueError); a rank-deficient A with fewer rows gives NUMERICAL.
  * structure="controller" needs the block sizes ``nv`` and ``nu`` of X = [q_ddot (nv),
    u (nu), lambda (nc)] as keyword arguments (no defaults: a plain QP does not say
    them); without them, or on a QP without that structure for them, it is refused
    (ValueError saying what the structure is). structure="auto" takes the controller's
    path only where nv and nu are given and the QP has the structure, else the generic
    one.
  * a shape that does not match (n from P, mi from G, me from A, B from P in a batch):
    ValueError naming the argument.

``status`` always describes the QP as posed. With ``fallback=False`` (default, plain
qpsolvers semantics) x is returned only where status is SOLVED. With ``fallback=True``
the project's fallback policy applies (``piqp_path.PiqpSolver``): where the QP is not
solved, the QP with its ``soft`` rows relaxed (``relax.relax_soft_rows``) is solved and
its x returned (status then still says why the original failed, e.g. INFEASIBLE); x is
None / NaN only when that fails too ("failed": hold the last good command).

solver="piqp"  the PIQP path (``piqp_path``): ``PiqpSolver`` with the fallback,
               ``solve_qp_piqp`` without; a batch is solved one QP after the other.
               Extra keyword arguments are PIQP settings (eps_abs, max_iter, ...).
solver="jax"   ``jax_qp`` (pure JAX, batched). ``structure="auto"`` uses the controller's
               structure (``jax_qp.solve_batch``: the equalities eliminated through the
               actuated rows, a QP in the nu torques) when ``nv`` and ``nu`` are given
               and the QP has it (``reduce.has_controller_structure``), else the generic
               null-space path (``jax_qp.solve_generic_batch``, A of full row rank);
               "controller" / "generic" force one. ``dtype`` float64 (default) or float32;
               ``settings`` a ``jax_qp.Settings``. Compiled once per shape, dtype and
               settings; a batch is solved in one call.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np

from safewbc_jax.solvers.status import INFEASIBLE, MAX_ITER, NUMERICAL, SOLVED, SolveStatus

if TYPE_CHECKING:
    from numpy.typing import ArrayLike, DTypeLike

    from safewbc_jax.solvers.settings import Settings

SOLVERS = ("jax", "piqp")


def _dense(v):
    """A scipy.sparse matrix as a dense array (qpsolvers accepts sparse P, G, A)."""
    if v is not None and hasattr(v, "toarray") and not isinstance(v, np.ndarray):
        return v.toarray()
    return v


def _as_qp(P, q, G, h, A, b, lb, ub, soft):
    """Stacked float64 numpy QP (leading batch axis added for one QP); (qp, batched).

    Absent parts become zero-row G, h (and soft) / A, b, and infinite bounds. For one QP
    the shapes qpsolvers also accepts are normalised as it does: a 1-D G or A is one row,
    a scalar h or b one entry, a vector of shape (1, k) or (k, 1) flat. Every mismatch is
    a ValueError naming the argument."""
    from safewbc_jax.solvers.problem import QP

    if (G is None) != (h is None):
        raise ValueError("G and h must be given together")
    if (A is None) != (b is None):
        raise ValueError("A and b must be given together")
    P = np.asarray(_dense(P), dtype=np.float64)
    if P.ndim not in (2, 3) or P.shape[-1] != P.shape[-2]:
        raise ValueError(f"P must be (n, n) or (B, n, n), got shape {P.shape}")
    if P.shape[-1] == 0:
        raise ValueError("P: a QP needs at least one variable, got shape (0, 0)")
    batched = P.ndim == 3
    if not batched:
        P = P[None]
    nb, n = P.shape[0], P.shape[-1]

    def as_array(v, name, matrix):
        try:
            v = np.asarray(_dense(v), dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{name}: not an array of numbers ({e})") from None
        if not batched:
            if matrix and v.ndim == 1:
                v = v[None, :]                       # qpsolvers: a 1-D matrix is one row
            elif not matrix and v.ndim == 0:
                v = v[None]
            elif not matrix and v.ndim == 2 and 1 in v.shape:
                v = v.ravel()                        # qpsolvers flattens (1, k) / (k, 1)
        return v

    def rows(M, name):
        M = as_array(M, name, True)
        want = 3 if batched else 2
        if M.ndim != want:
            raise ValueError(f"{name}: expected a matrix of shape "
                             f"{'(B, m, n)' if batched else '(m, n)'} with n = {n}, "
                             f"got shape {M.shape}")
        return M, M.shape[-2]

    def arr(v, trailing, fill, name, matrix=False):
        if v is None:
            return np.full((nb,) + trailing, fill, dtype=np.float64)
        v = as_array(v, name, matrix)
        if not batched:
            v = v[None]
        if v.shape[1:] != trailing or v.shape[0] != nb:
            raise ValueError(f"{name}: expected shape {(nb,) + trailing if batched else trailing}, "
                             f"got {v.shape if batched else v.shape[1:]}")
        return v

    mi = me = 0
    if G is not None:
        G, mi = rows(G, "G")
    if A is not None:
        A, me = rows(A, "A")
    qp = QP(P=P, q=arr(q, (n,), 0.0, "q"),
            A=arr(A, (me, n), 0.0, "A", True), b=arr(b, (me,), 0.0, "b"),
            G=arr(G, (mi, n), 0.0, "G", True), h=arr(h, (mi,), 0.0, "h"),
            lb=arr(lb, (n,), -np.inf, "lb"), ub=arr(ub, (n,), np.inf, "ub"),
            soft=arr(soft, (mi,), 0.0, "soft"))
    return qp, batched


def _crossed_bounds(qp) -> np.ndarray:
    """(B,) True where some lb_j > ub_j: the QP has no feasible point (INFEASIBLE, decided
    here rather than by the solvers: the JAX solver's certificate of infeasibility is over
    the rows of G and cannot see a box that is empty on its own)."""
    return np.any(qp.lb > qp.ub, axis=-1)


def _piqp(qp, fallback, settings, skip):
    from safewbc_jax.solvers.piqp_path import PiqpSolver, solve_qp_piqp
    from safewbc_jax.solvers.result import FALLBACK_FAILED

    nb, n = qp.P.shape[0], qp.P.shape[-1]
    xs = np.full((nb, n), np.nan)
    st = np.zeros(nb, dtype=np.int32)
    solver = PiqpSolver(update=False, **settings) if fallback else None
    for i in range(nb):
        if skip[i]:
            continue
        qpi = qp.row(i)
        if fallback:
            res = solver.solve(qpi)
            status = res.status
            x = None if res.fallback == FALLBACK_FAILED else res.x
        else:
            x, status = solve_qp_piqp(qpi, **settings)
        st[i] = int(status)
        if x is not None:
            xs[i] = x
    return xs, st


def _jax(qp, fallback, structure, nv, nu, dtype, settings):
    import jax.numpy as jnp

    from safewbc_jax.solvers import jax_qp, reduce
    from safewbc_jax.solvers.result import FALLBACK_FAILED

    if structure not in ("auto", "controller", "generic"):
        raise ValueError(f"structure must be 'auto', 'controller' or 'generic', got {structure!r}")
    if dtype is None or jnp.dtype(dtype) == jnp.float64:
        from safewbc_jax.base.runtime import require_x64

        require_x64("solve_qp(solver='jax') in float64 (dtype=float32 runs without it)")
    if (nv is None) != (nu is None):
        raise ValueError("nv and nu must be given together")
    if structure == "controller" and nv is None:
        raise ValueError("structure='controller' needs the block sizes of X = [q_ddot (nv), "
                         "u (nu), lambda (nc)]: pass nv= and nu= (or use structure='auto' "
                         "or 'generic')")
    if nv is not None:
        n = qp.P.shape[-1]
        qp = dataclasses.replace(qp, nv=int(nv), nu=int(nu),
                                 nc=int(n - nv - nu) if n >= nv + nu else None)
    has_ctrl = structure != "generic" and reduce.has_controller_structure(qp)
    if structure == "controller" and not has_ctrl:
        raise ValueError(
            f"structure='controller' needs the controller's QP: X = [q_ddot (nv={nv}), "
            f"u (nu={nu}), lambda (nc)] with nv + nc equality rows, the constraint rows "
            f"of A zero on u and a symmetric mass-matrix block; this QP has "
            f"n={qp.P.shape[-1]} variables and {qp.A.shape[-2]} equality rows (pass its nv "
            "and nu, or use structure='auto' or 'generic')")
    use_ctrl = structure == "controller" or (structure == "auto" and has_ctrl)
    qpj = qp.with_arrays(jnp.asarray)
    if use_ctrl:
        bounded = reduce.bounded_variables(qp)
        # bounds must be finite at the same places in every QP of the batch
        fin = np.isfinite(qp.lb) | np.isfinite(qp.ub)
        if not np.all(fin == fin[0]):
            raise ValueError("structure='controller' needs the finite bounds at the same "
                             "indices in every QP of the batch")
        res = jax_qp.solve_batch(qpj, bounded=bounded, dtype=dtype, settings=settings)
    else:
        res = jax_qp.solve_generic_batch(dataclasses.replace(qpj, nv=None, nu=None, nc=None,
                                                                     ng_lambda=None),
                                         dtype=dtype, settings=settings)
    x = np.asarray(res.x, dtype=np.float64)
    status = np.asarray(res.status, dtype=np.int32)
    usable = (np.asarray(res.fallback) != FALLBACK_FAILED) if fallback else status == SOLVED
    x = np.where(usable[:, None], x, np.nan)
    return x, status


def solve_qp(P: ArrayLike, q: ArrayLike, G: ArrayLike | None = None,
             h: ArrayLike | None = None, A: ArrayLike | None = None,
             b: ArrayLike | None = None, lb: ArrayLike | None = None,
             ub: ArrayLike | None = None, solver: str = "jax", *,
             soft: ArrayLike | None = None, fallback: bool = False, structure: str = "auto",
             nv: int | None = None, nu: int | None = None, dtype: DTypeLike | None = None,
             settings: Settings | None = None, initvals: Any = None,
             **solver_settings: Any,
             ) -> tuple[np.ndarray | None, SolveStatus] | tuple[np.ndarray, np.ndarray]:
    """Solve one QP or a batch: minimize 1/2 x'Px + q'x subject to G x <= h, A x = b,
    lb <= x <= ub.

    The arguments are ``qpsolvers.solve_qp``'s, in its order, None for an absent part;
    the module docstring lists the forms accepted and the outcome of each edge case. In a
    batch every given array has the same leading axis B.

    Args:
        P: (n, n) symmetric positive semidefinite cost matrix, or (B, n, n) for a batch;
            for one QP also a scipy.sparse matrix or nested lists.
        q: (n,) linear cost, (B, n) in a batch.
        G: (mi, n) inequality rows, (B, mi, n) in a batch; given with ``h``.
        h: (mi,) their bounds (+inf entries allowed), (B, mi) in a batch.
        A: (me, n) equality rows, (B, me, n) in a batch; given with ``b``.
        b: (me,) their right-hand sides, (B, me) in a batch.
        lb: (n,) lower bounds on x (-inf entries: unbounded), (B, n) in a batch.
        ub: (n,) upper bounds on x (+inf entries: unbounded), (B, n) in a batch.
        solver: "jax" (``jax_qp``, batched, pure JAX) or "piqp" (the PIQP path, one QP
            after the other).
        soft: (mi,) 1.0 on the rows of G that the fallback may relax (default none).
        fallback: False: x only where the QP as posed is solved (qpsolvers' semantics);
            True: the project's fallback policy (the QP with its ``soft`` rows relaxed
            where the QP as posed is not solved).
        structure: solver "jax": "auto" (the controller's structure where ``nv`` and
            ``nu`` are given and the QP has it, else generic), "controller" or "generic".
        nv: the q_ddot block size of the controller's X = [q_ddot (nv), u (nu),
            lambda (nc)], with ``nu``; None: a plain QP.
        nu: the torque block size of X, with ``nv``.
        dtype: solver "jax": float64 (None, the default; needs ``enable_x64``) or float32.
        settings: solver "jax": a ``jax_qp.Settings`` (None: the defaults).
        initvals: accepted for qpsolvers compatibility and ignored (neither solver warm
            starts: PIQP 0.7 has no initial-iterate input, the JAX solver starts each
            batch cold).
        **solver_settings: solver "piqp": PIQP settings (eps_abs, max_iter, ...).

    Returns:
        ``(x, status)``. One QP: x a float64 (n,) numpy array, or None where there is no
            usable solution, and status a ``SolveStatus`` of the QP as posed. A batch:
            x of shape (B, n), all-NaN rows where there is no usable solution, and status
            an int32 (B,) numpy array of the codes.

    Raises:
        ValueError: an unknown ``solver`` or ``structure``; a shape that does not match
            (the message names the argument); G without h or A without b (or the
            reverse); ``nv`` without ``nu``; structure "controller" without ``nv`` and
            ``nu`` or on a QP without that structure; solver "jax"'s generic path with
            more equality rows than variables; ``dtype`` or ``settings`` with solver
            "piqp", PIQP settings with solver "jax".
        RuntimeError: solver "jax" in float64 without JAX's 64-bit floats.
    """
    del initvals
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}; expected one of {SOLVERS}")
    qp, batched = _as_qp(P, q, G, h, A, b, lb, ub, soft)
    crossed = _crossed_bounds(qp)
    if solver == "piqp":
        if dtype is not None or settings is not None:
            raise ValueError("dtype and settings apply to solver='jax' only "
                             "(PIQP settings go as keyword arguments)")
        x, status = _piqp(qp, fallback, solver_settings, crossed)
    else:
        if solver_settings:
            raise ValueError(f"unknown arguments for solver='jax': {sorted(solver_settings)} "
                             "(pass a jax_qp.Settings as settings=)")
        if np.any(crossed):
            # their results are replaced below; uncrossed bounds (same finite pattern)
            # keep them from holding up the batch's loop until max_iter
            lo, hi = np.minimum(qp.lb, qp.ub), np.maximum(qp.lb, qp.ub)
            qp = dataclasses.replace(qp, lb=lo, ub=hi)
        x, status = _jax(qp, fallback, structure, nv, nu, dtype, settings)
    x = np.where(crossed[:, None], np.nan, x)
    status = np.where(crossed, int(INFEASIBLE), status).astype(np.int32)
    if batched:
        return x, status
    x0 = x[0]
    return (None if not np.all(np.isfinite(x0)) else x0), SolveStatus(int(status[0]))


__all__ = ["solve_qp", "SOLVERS", "SolveStatus", "SOLVED", "INFEASIBLE", "MAX_ITER",
           "NUMERICAL"]
