"""jaxlib's LAPACK kernels under vmap, issued in sub-batches small enough to run inline.

Why: on the CPU, jaxlib 0.10's batched LAPACK kernels (``lapack_dpotrf_ffi``,
``lapack_dtrsm_ffi``, ``lapack_dgetrf_ffi``, ...) split a batch whose work (batch x
jaxlib's FLOP estimate per matrix) is ``MIN_WORK`` or more into tasks on XLA's intra-op
thread pool, and then block the pool thread that runs them until the tasks are done
(``ParallelBatchMap`` in ``jaxlib/cpu/lapack_kernels.cc``). When XLA's thunk executor runs
as many such calls at once as the pool has threads, every thread waits for tasks no
thread is free to run, and the program never returns, every thread idle. On the 2-core
CI machine that is two independent batched factorisations. It hung the batched closed
loop at 64 and 256 rollouts per chunk (native stacks: both ``tf_XLAEigen`` threads in
``absl::BlockingCounter::Wait`` under ``ParallelBatchMap``, one in ``dpotrf``, one in
``dtrsm``). jaxlib 0.11.2 compiles that parallel path out; the pinned MJX needs 0.10.

So each function here is the plain ``jnp.linalg`` / ``jax.scipy.linalg`` call for one
matrix and, under vmap (``jax.custom_batching.custom_vmap``), the same LAPACK call on
sub-batches of at most ``k`` matrices, ``k`` below the threshold for the matrix sizes,
one after the other (``lax.map``; the last sub-batch padded with copies of the first
matrix). Each matrix goes through the same routine as in one big call, so the results are
the same; the calls run on the calling thread and never wait on the pool. Measured
against one batched call (vmap over 64 SPD 36 x 36 matrices, Cholesky and a solve with 43
right-hand sides): 3.58 against 3.61 ms, where the same in unrolled jax.numpy took 9.0 ms.

One vmap level: under a second vmap the outer one batches the inner one's sub-batch
calls again (``tests/test_lapack_batched.py`` checks the rollout's graph).
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


def _batched(args, in_batched, axis_size):
    return tuple(a if b else jnp.broadcast_to(a, (axis_size,) + a.shape)
                 for a, b in zip(args, in_batched))


def _columns(b, batched: bool) -> int:
    return 1 if b.ndim == (2 if batched else 1) else b.shape[-1]


def _as_matrix(fn):
    """fn(a, B) for B a stack of matrices, applied to a stack of vectors too."""
    def g(a, b):
        return fn(a, b) if b.ndim == a.ndim else fn(a, b[..., None])[..., 0]
    return g


# ------------------------------------------------------------------------ Cholesky

@custom_vmap
def cholesky(a):
    """Lower Cholesky factor of a symmetric positive definite matrix (NaN where it is
    not), ``jnp.linalg.cholesky``."""
    return jnp.linalg.cholesky(a)


@cholesky.def_vmap
def _cholesky_vmap(axis_size, in_batched, a):
    (a,) = _batched((a,), in_batched, axis_size)
    n = a.shape[-1]
    return _map_sub_batches(jnp.linalg.cholesky, n ** 3 // 3, axis_size, (a,)), True


# ------------------------------------------------------------------ triangular solves

def _cho(L, b):
    return jsl.cho_solve((L, True), b)


@custom_vmap
def cho_solve(L, b):
    """a^-1 b from the lower Cholesky factor L of a; b a vector or a matrix."""
    return _cho(L, b)


@cho_solve.def_vmap
def _cho_solve_vmap(axis_size, in_batched, L, b):
    L, b = _batched((L, b), in_batched, axis_size)
    n, k = L.shape[-1], _columns(b, True)
    return _map_sub_batches(_as_matrix(_cho), n * n * k, axis_size, (L, b)), True


def _tri(L, b):
    return lax.linalg.triangular_solve(L, b, left_side=True, lower=True)


def _tri_t(L, b):
    return lax.linalg.triangular_solve(L, b, left_side=True, lower=True, transpose_a=True)


@custom_vmap
def solve_lower(L, b):
    """L^-1 b for lower-triangular L; b a vector or a matrix."""
    return _as_matrix(_tri)(L, b)


@solve_lower.def_vmap
def _solve_lower_vmap(axis_size, in_batched, L, b):
    L, b = _batched((L, b), in_batched, axis_size)
    n, k = L.shape[-1], _columns(b, True)
    return _map_sub_batches(_as_matrix(_tri), n * n * k, axis_size, (L, b)), True


@custom_vmap
def solve_lower_t(L, b):
    """L'^-1 b for lower-triangular L; b a vector or a matrix."""
    return _as_matrix(_tri_t)(L, b)


@solve_lower_t.def_vmap
def _solve_lower_t_vmap(axis_size, in_batched, L, b):
    L, b = _batched((L, b), in_batched, axis_size)
    n, k = L.shape[-1], _columns(b, True)
    return _map_sub_batches(_as_matrix(_tri_t), n * n * k, axis_size, (L, b)), True


# --------------------------------------------------------------------- general solve

def _lu(a, b):
    return jnp.linalg.solve(a, b)


@custom_vmap
def solve(a, b):
    """a^-1 b for a square matrix a (LU with partial pivoting); b a vector or a matrix."""
    return _as_matrix(_lu)(a, b)


@solve.def_vmap
def _solve_vmap(axis_size, in_batched, a, b):
    a, b = _batched((a, b), in_batched, axis_size)
    n, k = a.shape[-1], _columns(b, True)
    return _map_sub_batches(_as_matrix(_lu), max(n ** 3, n * n * k), axis_size, (a, b)), True
