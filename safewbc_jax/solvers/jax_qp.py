"""A pure-JAX QP solver for the controller's QPs: jit- and vmap-able, fixed shapes; the
public entry of the JAX path.

Problem (the seam QP of ``safewbc_jax.solvers.problem``)

    minimize    1/2 x'Px + q'x
    subject to  A x = b,   G x <= h,   lb <= x <= ub

solved, per instance, in three stages, each in its own module:

1. Equalities out (``reduce``). For the controller's QP, X = [q_ddot (nv), u (nu),
   lambda (nc)] with the block sizes the QP carries, the equality rows (dynamics and
   constraints) fix q_ddot and lambda for every u: X = x0 + N u exactly (one Cholesky of
   the mass matrix, one LU of the constraint-space matrix), leaving a QP in the nu
   torques alone: box bounds (the torque limits) and the friction, unilateral contact,
   ZMP and barrier rows, no equalities. It is the same elimination the PIQP path uses
   (``reduce.eliminate``, here with ``reduce.BATCHED`` factorisations). For a general QP
   without that structure (``solve_generic``) the null-space method
   (``reduce.reduce_generic``; A of full row rank).

2. Interior point on the reduced QP (``ipm``): Mehrotra's predictor-corrector on the
   scaled problem, with infeasibility certificates.

3. Polish (``polish``): an active-set method from the interior point to the exact KKT
   point of the detected active set.

Then the full-space acceptance check and the fallback policy (``policy``, the same code
as the PIQP path's): accept when SOLVED and the residuals pass ``feas_tol``, else the
relaxed QP, else FAILED with x all NaN. The answer is a ``result.SolveResult`` (``Result``
here is the same type). In a batch the relaxed solve is a second ``lax.while_loop`` whose
instances start "done" unless they need it, under one batch-level ``lax.cond``, so a
batch in which every QP solves pays for its initial point only, not for its iterations.

Batches: every function here works on one QP and is written for ``jax.vmap``; a vmapped
``lax.while_loop`` runs until every instance of the batch has stopped, the stopped ones
frozen. ``solve_batch`` / ``solve_generic_batch`` are the jitted, vmapped versions. On a
CPU they solve a large batch in chunks (``chunk``, 64 QPs by default): the batch is cut
into equal chunks of at most that size (padded with copies of its last QP) and a
``lax.map`` runs the vmapped solver over one chunk after the other inside the same jitted
call, because one vmap over the whole batch is slower per QP there (see ``solve_batch``).

dtype: float64 by default; ``dtype=jnp.float32`` casts the QP and uses float32 settings
(``Settings.for_dtype``: eps_abs 1e-5, looser acceptance 1e-3) for accelerators; expect
~1e-3 relative agreement there, the reduced problem being ill-conditioned.

``blas_threads`` (``blas``) limits OpenBLAS's threads around host-side LAPACK work.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from safewbc_jax.base.chunking import ByPlatform, chunked, resolve_chunk
from safewbc_jax.solvers.problem import QP
from safewbc_jax.solvers import policy, reduce
from safewbc_jax.solvers.blas import blas_threads
from safewbc_jax.solvers.ipm import interior_point, scale_problem
from safewbc_jax.solvers.policy import Attempt
from safewbc_jax.solvers.polish import polish
from safewbc_jax.solvers.reduce import (has_controller_structure, p_block_diagonal,
                                        p_structure)
from safewbc_jax.solvers.result import (FALLBACK_FAILED, FALLBACK_NAMES, FALLBACK_NONE,
                                        FALLBACK_RELAXED, SolveResult)
from safewbc_jax.solvers.settings import Settings, full_float32, settings_for
from safewbc_jax.solvers.status import INFEASIBLE, NUMERICAL, SOLVED

Result = SolveResult
"""The JAX solver's answer: ``result.SolveResult`` (the name of earlier versions)."""


def _solve_box(P, q, G, h, lb, ub, sig, st: Settings, active, relax: bool):
    """Scale, IPM, polish; (u, s [unscaled], status, iterations, polished).

    A problem without rows (G of shape (0, n): no inequalities and no equalities, or the
    controller's QP without G rows and bounded variables) gets one row that is switched
    off (0 u <= 1e30, which ``scale_problem`` marks ``row_on`` False), so that the
    iteration's reductions over rows never see an empty array; its slack is dropped from
    the result. Static shapes: the other problems compile as before."""
    dt = P.dtype
    m0 = G.shape[0]
    if m0 == 0:
        G = jnp.zeros((1, P.shape[0]), dt)
        h = jnp.full((1,), 1e30, dt)
        sig = jnp.zeros((1,), dt)
    if relax:
        rho = jnp.full(h.shape, st.relax_rho, dt)
        c = jnp.full(h.shape, st.relax_rho_lin, dt)
    else:
        sig = jnp.zeros_like(h)
        rho = jnp.ones_like(h)
        c = jnp.zeros_like(h)
    pb, sc = scale_problem(P, q, G, h, lb, ub, sig, rho, c)
    if st.ipm_dtype is not None and jnp.dtype(st.ipm_dtype) != dt:
        # mixed precision: the iterations in ipm_dtype, the polish in the problem's dtype
        lo = jnp.dtype(st.ipm_dtype)
        pb_lo = jax.tree_util.tree_map(lambda a: a.astype(lo) if a.dtype == dt else a, pb)
        st_lo = Settings.for_dtype(lo, max_iter=st.max_iter, fallback=st.fallback)
        with full_float32():        # no TF32 on a GPU (precision.full_float32)
            it, status, k = interior_point(pb_lo, st_lo, active)
        it = jax.tree_util.tree_map(lambda a: a.astype(dt), it)
    else:
        it, status, k = interior_point(pb, st, active)
    u, s = it.u, it.s
    use = jnp.zeros((), bool)
    kp = jnp.zeros((), jnp.int32)
    if st.polish:
        up, sp, ok, kp = polish(it, pb, st, active & (status != INFEASIBLE),
                                kmax=P.shape[0] + (G.shape[0] if relax else 0))
        # a point that passes the KKT checks is the optimum, whatever the IPM's status
        # (it may have stopped on a failed factorisation near the end); a certificate
        # of infeasibility stands (no point can pass then)
        use = ok & active & (status != INFEASIBLE)
        u = jnp.where(use, up, u)
        s = jnp.where(use, sp, s)
        status = jnp.where(use, SOLVED, status).astype(jnp.int32)
    return u * sc.sx, (s / sc.er)[:m0], status, k, use, kp


def _cast(qp: QP, dtype) -> QP:
    """Every array of the QP in ``dtype``, the block sizes kept."""
    return qp.with_arrays(lambda a: jnp.asarray(a, dtype))


def _nominal(qp: QP, red: QP, lift, st: Settings) -> Attempt:
    """The QP as posed, through its reduced problem ``red``; ``lift`` maps the reduced
    variable back (``reduce.expand``)."""
    u, _, status, k, pol, kp = _solve_box(red.P, red.q, red.G, red.h, red.lb, red.ub,
                                          red.soft, st, jnp.ones((), bool), relax=False)
    x = reduce.expand(u, lift)
    status, res = policy.accept(x, qp, status, st.feas_tol, jnp)
    return Attempt(x=x, status=status, res=res, max_slack=jnp.zeros((), x.dtype),
                   iterations=k, polished=pol, polish_iterations=kp)


def _relaxed(qp: QP, red: QP, lift, st: Settings, need) -> Attempt:
    """The relaxed QP (soft rows with slack) for the instances with ``need``; the others
    start stopped."""
    ur, sr, rstatus, kr, rpol, kpr = _solve_box(red.P, red.q, red.G, red.h, red.lb, red.ub,
                                                red.soft, st, need, relax=True)
    xr = reduce.expand(ur, lift)
    sr = jnp.where(red.soft > 0, jnp.maximum(sr, 0.0), 0.0)[:qp.G.shape[0]]
    rstatus, res = policy.accept(xr, qp, rstatus, st.feas_tol, jnp, slack=sr)
    return Attempt(x=xr, status=rstatus, res=res, max_slack=jnp.max(sr, initial=0.0),
                   iterations=kr, polished=rpol, polish_iterations=kpr)


def _relaxed_skipped(qp: QP) -> Attempt:
    """What ``_relaxed`` returns when no instance needs it (for a batch-level cond)."""
    return policy.skipped(jnp.zeros(qp.P.shape[0], qp.P.dtype), jnp)


def _reduce_controller(qp: QP, bounded, p_blockdiag: bool | str):
    red, lift = reduce.eliminate(qp, bounded, p_blockdiag, xp=jnp, la=reduce.BATCHED)
    return red, lift, jnp.ones((), bool)


def _single(qp: QP, red: QP, lift, ok_red, st: Settings) -> Result:
    nom = _nominal(qp, red, lift, st)
    nom = nom._replace(status=jnp.where(ok_red, nom.status, NUMERICAL).astype(jnp.int32))
    rel = None
    if st.fallback:
        rel = _relaxed(qp, red, lift, st, (nom.status != SOLVED) & ok_red)
    return policy.finish(nom, rel, jnp)


_settings = settings_for


# ---------------------------------------------------------------------- public API

def solve(qp: QP, *, bounded=None, dtype=None, settings: Settings | None = None,
          p_blockdiag: bool | str = False) -> Result:
    """One controller QP (X = [q_ddot (nv), u (nu), lambda], the block sizes the QP
    carries: a QP from ``qp.assemble``; ValueError for a QP without them, which
    ``solve_generic`` solves) through the reduced problem in u; pure JAX, jit/vmap-able
    (the relaxed solve runs with zero iterations where it is not needed).
    ``bounded``: static indices outside u with finite bounds
    (``reduce.bounded_variables``; none for the controller's QP). ``p_blockdiag``: P has
    no cross terms between q_ddot, u and lambda (true of the controller's QP; static:
    only P's diagonal blocks are then used, ``p_block_diagonal`` checks it); "diagonal":
    also its u and lambda blocks are diagonal (``reduce.p_structure``)."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qp.P).dtype
    st = _settings(dtype, settings)
    qp = _cast(qp, dtype)
    red, lift, ok_red = _reduce_controller(qp, bounded, p_blockdiag)
    return _single(qp, red, lift, ok_red, st)


def solve_generic(qp: QP, *, dtype=None, settings: Settings | None = None) -> Result:
    """Any QP of the seam's form (convex; A of full row rank, else NUMERICAL): the
    equalities eliminated by the null-space method, then the same interior point, polish
    and fallback as ``solve``. Finite bounds become rows when there are equalities.
    Slower than ``solve`` on the controller's QP (no structure used). The polish needs P
    positive definite on the reduced space; with a singular P the interior point's
    solution is returned (``polished`` False)."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qp.P).dtype
    st = _settings(dtype, settings)
    qp = _cast(qp, dtype)
    red, lift, ok_red = reduce.reduce_generic(qp)
    return _single(qp, red, lift, ok_red, st)


def _batch_impl(qps: QP, reducer, st: Settings) -> Result:
    """vmap of the stages, with the relaxed solve under one batch-level ``lax.cond``: a
    batch in which every QP solves pays nothing for the fallback."""
    red, lift, ok_red = jax.vmap(reducer)(qps)
    nom = jax.vmap(lambda qp, r, lf: _nominal(qp, r, lf, st))(qps, red, lift)
    nom = nom._replace(status=jnp.where(ok_red, nom.status, NUMERICAL).astype(jnp.int32))
    rel = None
    if st.fallback:
        need = (nom.status != SOLVED) & ok_red
        rel = lax.cond(
            jnp.any(need),
            lambda: jax.vmap(lambda qp, r, lf, nd: _relaxed(qp, r, lf, st, nd))(
                qps, red, lift, need),
            lambda: jax.vmap(_relaxed_skipped)(qps))
    return jax.vmap(lambda n_, r_: policy.finish(n_, r_, jnp))(nom, rel) if rel is not None \
        else jax.vmap(lambda n_: policy.finish(n_, None, jnp))(nom)


@functools.lru_cache(maxsize=64)
def _batched(kind: str, bounded: tuple, dtype, settings, pbd=False, chunk=None):
    """The jitted batch solver (the block sizes come with the QP's tree structure: jit
    compiles once per sizes and shapes)."""
    if kind == "controller":
        b = np.asarray(bounded, int)
        reducer = lambda qp: _reduce_controller(qp, b, pbd)  # noqa: E731
    else:
        reducer = reduce.reduce_generic
    impl = chunked(lambda qps: _batch_impl(qps, reducer, settings), chunk)
    return jax.jit(lambda qps: impl(_cast(qps, dtype)))


CPU_CHUNK = 64
"""Default ``chunk`` of the batched solvers on the CPU backend (QPs per chunk)."""


def default_chunk(backend: str | None = None) -> int | None:
    """The batched solvers' default ``chunk``: ``CPU_CHUNK`` on the CPU backend, None (one
    vmap over the whole batch) on an accelerator, whose parallelism wants the largest
    batch. ``backend`` None: ``jax.default_backend()``."""
    backend = jax.default_backend() if backend is None else backend
    return CPU_CHUNK if backend == "cpu" else None


def _resolve_chunk(chunk, batch: int):
    """The chunk a batch of ``batch`` QPs is solved with (``chunking.resolve_chunk``; "auto"
    is ``ByPlatform(CPU_CHUNK)``: ``default_chunk`` of the platform lowered for)."""
    return resolve_chunk(chunk, batch, ByPlatform(CPU_CHUNK))


def solve_batch(qps: QP, *, bounded=None, dtype=None, settings: Settings | None = None,
                p_blockdiag: bool | str | None = None, chunk: int | str | None = "auto") -> Result:
    """``solve`` over a leading batch dimension of every field, jitted (compiled once per
    shape, block sizes, dtype, settings, structure flags and chunk). ``p_blockdiag`` None:
    checked on the data (``reduce.p_structure``) when it is concrete, else False.

    ``chunk``: solve the batch at most ``chunk`` QPs at a time, the chunks one after the
    other in the same jitted call (``chunking.chunked``: equal chunks, padded by copies of
    the last QP; results equal to the unchunked solve's; each chunk runs the batch-level
    ``lax.cond`` of the relaxed solve on its own); None: one vmap over the whole batch;
    "auto" (default): ``CPU_CHUNK`` = 64 when lowered for a CPU, one vmap when lowered for
    an accelerator (``chunking.ByPlatform``). A batch of at most ``chunk`` QPs is one vmap
    (the same compiled function as chunk None).

    Why: on a CPU one vmap over a large batch costs more per QP: a larger vmap is slower
    per QP on identical work, and a vmapped loop runs until the slowest QP of its batch
    stops, while a chunk stops at its own slowest. 64 was the fastest chunk in most runs
    (benchmarks/README.md, "Figures behind design choices", ``benchmarks/jax_qp_bench.py``)."""
    if not qps.has_blocks:
        reduce.bounded_variables(qps)          # raises, naming what is missing
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qps.P).dtype
    b = tuple(int(i) for i in (np.zeros(0, int) if bounded is None else np.asarray(bounded)))
    if p_blockdiag is None:
        p_blockdiag = _concrete(qps.P) and p_structure(qps)
    return _batched("controller", b, dtype, _settings(dtype, settings),
                    p_blockdiag if p_blockdiag == "diagonal" else bool(p_blockdiag),
                    _resolve_chunk(chunk, qps.P.shape[0]))(qps)


def _concrete(a) -> bool:
    return not isinstance(a, jax.core.Tracer)


def solve_generic_batch(qps: QP, *, dtype=None, settings: Settings | None = None,
                        chunk: int | str | None = "auto") -> Result:
    """``solve_generic`` over a leading batch dimension, jitted; ``chunk`` as in
    ``solve_batch``."""
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.asarray(qps.P).dtype
    return _batched("generic", (), dtype, _settings(dtype, settings), False,
                    _resolve_chunk(chunk, qps.P.shape[0]))(qps)


__all__ = ["Settings", "Result", "SolveResult", "solve", "solve_batch", "solve_generic",
           "solve_generic_batch", "default_chunk", "CPU_CHUNK", "has_controller_structure",
           "p_block_diagonal", "blas_threads", "FALLBACK_NONE", "FALLBACK_RELAXED",
           "FALLBACK_FAILED", "FALLBACK_NAMES"]
