"""Batched factorisations that fit the backend: on the CPU, jaxlib's LAPACK kernels under
vmap issued in sub-batches small enough to run inline; on every other platform (CUDA,
ROCm, TPU) one batched call over the whole vmap.

Why: on the CPU, jaxlib 0.10's batched LAPACK kernels (``lapack_dpotrf_ffi``,
``lapack_dtrsm_ffi``, ``lapack_dgetrf_ffi``, ...) split a batch whose work (batch x jaxlib's
FLOP estimate per matrix) is ``MIN_WORK`` or more into tasks on XLA's intra-op thread pool,
and then block the pool thread that runs them until the tasks are done (``ParallelBatchMap``
in ``jaxlib/cpu/lapack_kernels.cc``). When XLA's thunk executor runs as many such calls at
once as the pool has threads, every thread waits for tasks no thread is free to run, and the
program never returns, every thread idle. On a CPU with two threads in the pool, two
independent batched factorisations are enough. It hung the batched closed loop at 64 and 256
rollouts per chunk (native stacks: both ``tf_XLAEigen`` threads in
``absl::BlockingCounter::Wait`` under ``ParallelBatchMap``, one in ``dpotrf``, one in
``dtrsm``). jaxlib 0.11.2 compiles that parallel path out; the pinned MJX needs 0.10.

So each function here is the plain ``jnp.linalg`` / ``jax.scipy.linalg`` call for one
matrix and, under vmap (``jax.custom_batching.custom_vmap``), the same LAPACK call on
sub-batches of at most ``k`` matrices, ``k`` below the threshold for the matrix sizes,
one after the other (``lax.map``; the last sub-batch padded with copies of the first
matrix). Each matrix goes through the same routine as in one big call, so the results are
the same; the calls run on the calling thread and never wait on the pool, at the speed
of one batched call (benchmarks/README.md, "Figures behind design choices").

One vmap level: under a second vmap the outer one batches the inner one's sub-batch
calls again (``tests/test_lapack_batched.py`` checks the rollout's graph).

Backends: the sub-batching is a workaround for the CPU thread pool alone. On a GPU it
would serialise each factorisation into hundreds of small cuSOLVER calls per
interior-point iteration. The choice is made by ``lax.platform_dependent``, so by the
platform the program is lowered for, not by the machine that traces it: a CUDA lowering
made on a CPU machine (``jax.export.export(f, platforms=["cuda"])``) holds one batched
call per factorisation, as the GPU would run it (``tests/test_cuda_lowering.py``), and the
CPU program is the sub-batched one, its conditional resolved before XLA compiles.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
from jax import lax
from jax.custom_batching import custom_vmap

MIN_WORK = 200_000
"""jaxlib 0.10's ``kMinWorkPerTask``: a call with less work than this runs inline."""


def sub_batch(cost: int, axis_size: int) -> int:
    """Matrices per LAPACK call for a FLOP estimate ``cost`` per matrix: the most whose
    work stays under ``MIN_WORK`` (at least 1, at most the batch)."""
    return max(1, min(axis_size, (MIN_WORK - 1) // max(int(cost), 1)))


def _map_sub_batches(fn, cost, axis_size, args):
    k = sub_batch(cost, axis_size)
    if k >= axis_size:
        return fn(*args)
    nb = -(-axis_size // k)
    pad = nb * k - axis_size

    def blocks(a):
        if pad:
            a = jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad,) + a.shape[1:])], axis=0)
        return a.reshape((nb, k) + a.shape[1:])

    out = lax.map(lambda xs: fn(*xs), tuple(blocks(a) for a in args))
    return jax.tree_util.tree_map(lambda o: o.reshape((nb * k,) + o.shape[2:])[:axis_size],
                                  out)


def _broadcast(args, in_batched, axis_size):
    return tuple(a if b else jnp.broadcast_to(a, (axis_size,) + a.shape)
                 for a, b in zip(args, in_batched))


def _as_matrix(fn):
    """fn(a, B) for B a (stack of) matrices, applied to a (stack of) vectors too."""
    def g(a, b):
        return fn(a, b) if b.ndim == a.ndim else fn(a, b[..., None])[..., 0]
    return g


def _sub_batched(plain, cost):
    """``plain`` as a custom_vmap function whose vmap rule runs it on sub-batches;
    ``cost(*batched args)``: jaxlib's FLOP estimate per matrix of the call it makes."""
    f = custom_vmap(plain)

    @f.def_vmap
    def _rule(axis_size, in_batched, *args):
        args = _broadcast(args, in_batched, axis_size)
        sub = lambda *a: _map_sub_batches(plain, cost(*a), axis_size, a)  # noqa: E731
        whole = lambda *a: jax.vmap(plain)(*a)                              # noqa: E731
        return lax.platform_dependent(*args, cpu=sub, default=whole), True

    return f


def _rhs_columns(b) -> int:
    """Right-hand sides of a batched b: (batch, n) one, (batch, n, k) k."""
    return 1 if b.ndim == 2 else b.shape[-1]


def _cholesky(a):
    """Lower Cholesky factor of the symmetric part (a + a')/2 of a positive definite
    matrix (NaN where it is not positive definite): ``jnp.linalg.cholesky``."""
    return jnp.linalg.cholesky(a)


def _cholesky_lower(a):
    """Lower Cholesky factor of a symmetric positive definite matrix, read from its lower
    triangle only (no symmetrisation; NaN where it is not positive definite)."""
    return jnp.linalg.cholesky(a, symmetrize_input=False)


@_as_matrix
def _cho_solve(L, b):
    """a^-1 b from the lower Cholesky factor L of a; b a vector or a matrix."""
    return jsl.cho_solve((L, True), b)


@_as_matrix
def _solve_lower(L, b):
    """L^-1 b for lower-triangular L; b a vector or a matrix."""
    return lax.linalg.triangular_solve(L, b, left_side=True, lower=True)


@_as_matrix
def _solve(a, b):
    """a^-1 b for a square matrix a (LU with partial pivoting); b a vector or a matrix."""
    return jnp.linalg.solve(a, b)


def _tri_cost(L, b):
    return L.shape[-1] ** 2 * _rhs_columns(b)


_chol_cost = lambda a: a.shape[-1] ** 3 // 3  # noqa: E731
cholesky = _sub_batched(_cholesky, _chol_cost)
cholesky_lower = _sub_batched(_cholesky_lower, _chol_cost)
cho_solve = _sub_batched(_cho_solve, _tri_cost)
solve_lower = _sub_batched(_solve_lower, _tri_cost)
solve = _sub_batched(_solve, lambda a, b: max(a.shape[-1] ** 3, _tri_cost(a, b)))
