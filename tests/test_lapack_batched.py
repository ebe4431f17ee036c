"""solvers/lapack_batched.py: the same results as one batched LAPACK call, and batched
graphs free of the LAPACK calls that can deadlock XLA's CPU thread pool.

Each matrix goes through the same LAPACK routine whether it is in a sub-batch or in one
big call, so the results agree to rounding of the copies (asserted to 1e-12 relative,
far above that and far below any error of the method). Against numpy's own LAPACK on
random matrices of condition number <= 1e2 the bound is 1e4 * cond * eps relative.
"""

from __future__ import annotations

import re

import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
import pytest

from safewbc_jax.solvers import lapack_batched as lb

EPS = np.finfo(float).eps


def _spd(rng, n, cond=100.0):
    q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (q * np.geomspace(1.0, 1.0 / cond, n)) @ q.T


def _lapack_calls(hlo: str):
    """(target, operand shapes) of each LAPACK custom call of a lowered module."""
    out = []
    for line in hlo.splitlines():
        m = re.search(r"custom_call @(lapack_\w+)\(.*:\s*\(([^)]*)\)\s*->", line)
        if m:
            shapes = [tuple(int(d) for d in t.split("x")[:-1])
                      for t in re.findall(r"tensor<([0-9x]+f\d+)>", m.group(2))]
            out.append((m.group(1), shapes))
    return out


def _work(target: str, shapes) -> int:
    """batch x jaxlib 0.10's FLOP estimate of one call (its formulas, lapack_kernels.cc)."""
    if "potrf" in target:
        *batch, n, _ = shapes[0]
        cost = n ** 3 // 3
    elif "getrf" in target:
        *batch, n, _ = shapes[0]
        cost = n ** 3
    elif "trsm" in target:
        *batch, r, c = shapes[1]
        cost = r * c * r
    else:
        raise AssertionError(f"unexpected LAPACK call {target} {shapes}")
    return int(np.prod(batch or [1])) * cost


def _fns():
    return {
        "cholesky": (lb.cholesky, jnp.linalg.cholesky),
        "cho_solve": (lambda L, b: lb.cho_solve(L, b), lambda L, b: jsl.cho_solve((L, True), b)),
        "solve_lower": (lb.solve_lower,
                        lambda L, b: jsl.solve_triangular(L, b, lower=True)),
        "cholesky_lower": (lb.cholesky_lower,
                           lambda a: jnp.linalg.cholesky(a, symmetrize_input=False)),
        "solve": (lb.solve, jnp.linalg.solve),
    }


@pytest.mark.parametrize("batch,n,k", [(64, 36, 43), (67, 22, 21), (5, 20, 1), (64, 20, 0)])
def test_sub_batches_equal_one_batched_call(batch, n, k):
    """Sub-batched under vmap == one batched call == numpy, for every function; k = 0:
    vector right-hand sides. (64, 36, 43) is the controller's elimination at the CPU
    chunk; 67 is not a multiple of any sub-batch (padding)."""
    rng = np.random.default_rng(batch + n + k)
    S = jnp.asarray(np.stack([_spd(rng, n) for _ in range(batch)]))
    G = jnp.asarray(rng.normal(size=(batch, n, n)) + n * np.eye(n))
    B = jnp.asarray(rng.normal(size=(batch, n, k) if k else (batch, n)))
    L = jnp.linalg.cholesky(S)
    args = {"cholesky": (S,), "cho_solve": (L, B), "solve_lower": (L, B),
            "cholesky_lower": (S,), "solve": (G, B)}
    for name, (f, ref) in _fns().items():
        got = np.asarray(jax.jit(jax.vmap(f))(*args[name]))
        want = np.asarray(jax.vmap(ref)(*args[name]))
        scale = np.max(np.abs(want))
        assert np.max(np.abs(got - want)) <= 1e-12 * scale, name
        # and one unbatched call is the plain function
        one = np.asarray(f(*(a[0] for a in args[name])))
        assert np.max(np.abs(one - want[0])) <= 1e-12 * scale, name
    x = np.asarray(jax.vmap(lb.solve)(G, B))
    xr = np.linalg.solve(np.asarray(G), np.asarray(B)[..., None] if not k else np.asarray(B))
    xr = xr[..., 0] if not k else xr
    cond = max(np.linalg.cond(np.asarray(g)) for g in G)
    assert np.max(np.abs(x - xr)) <= 1e4 * cond * EPS * np.max(np.abs(xr))


def test_unbatched_argument_is_broadcast():
    rng = np.random.default_rng(1)
    L = jnp.linalg.cholesky(jnp.asarray(_spd(rng, 30)))
    B = jnp.asarray(rng.normal(size=(70, 30, 12)))
    got = jax.vmap(lb.cho_solve, in_axes=(None, 0))(L, B)
    want = jax.vmap(lambda b: jsl.cho_solve((L, True), b))(B)
    assert np.max(np.abs(np.asarray(got - want))) <= 1e-12 * np.max(np.abs(np.asarray(want)))


def test_cholesky_lower_reads_only_the_lower_triangle():
    """cholesky_lower (the elimination's, of M as built) ignores the strict upper
    triangle; cholesky factors the symmetric part, as jnp.linalg.cholesky does."""
    rng = np.random.default_rng(2)
    S = np.stack([_spd(rng, 12) for _ in range(70)])
    junk = jnp.asarray(S + np.triu(rng.normal(size=S.shape), 1) * 1e-3)
    want = np.linalg.cholesky(S)
    got = np.asarray(jax.vmap(lb.cholesky_lower)(junk))
    assert np.max(np.abs(got - want)) <= 1e4 * 100 * EPS
    sym = np.asarray(jax.vmap(lb.cholesky)(junk))
    np.testing.assert_array_equal(sym, np.asarray(jax.vmap(jnp.linalg.cholesky)(junk)))
    assert np.max(np.abs(sym - want)) > 1e-6    # the upper triangle did count there


def test_failures_are_nan_not_exceptions():
    bad = jnp.asarray(np.stack([np.diag([1.0, -1.0, 1.0])] * 3))
    L = np.asarray(jax.vmap(lb.cholesky)(bad))
    assert np.all(np.isnan(L[:, np.tril_indices(3)[0], np.tril_indices(3)[1]]))
    np.testing.assert_array_equal(L, np.asarray(jax.vmap(jnp.linalg.cholesky)(bad)))
    # a singular matrix: whatever jnp.linalg.solve gives, never an exception
    z = np.asarray(jax.vmap(lb.solve)(jnp.zeros((3, 3, 3)), jnp.ones((3, 3))))
    zr = np.asarray(jax.vmap(jnp.linalg.solve)(jnp.zeros((3, 3, 3)), jnp.ones((3, 3))))
    np.testing.assert_array_equal(z, zr)


@pytest.mark.parametrize("batch", [64, 256, 1024])
def test_every_call_runs_inline(batch):
    """At any batch, the lowered calls are all under jaxlib's threshold: none can wait on
    the thread pool. The plain batched call is over it (what this module is for)."""
    n, k = 36, 43
    S = jax.ShapeDtypeStruct((batch, n, n), jnp.float64)
    B = jax.ShapeDtypeStruct((batch, n, k), jnp.float64)
    f = jax.jit(jax.vmap(lambda s, b: lb.cho_solve(lb.cholesky(s), b) + lb.solve(s, b)))
    calls = _lapack_calls(f.lower(S, B).as_text())
    assert {t for t, _ in calls} >= {"lapack_dpotrf_ffi", "lapack_dtrsm_ffi", "lapack_dgetrf_ffi"}
    assert max(_work(t, s) for t, s in calls) < lb.MIN_WORK
    plain = jax.jit(jax.vmap(lambda s, b: jsl.cho_solve((jnp.linalg.cholesky(s), True), b)))
    assert max(_work(t, s) for t, s in _lapack_calls(plain.lower(S, B).as_text())) >= lb.MIN_WORK


@pytest.mark.slow
def test_batched_rollout_has_no_controller_call_that_waits_on_the_pool():
    """The walking closed loop at the CPU chunk (64 rollouts): every LAPACK call of the
    controller runs inline, so none of them can hold a pool thread. The only ones over
    the threshold are MJX's own factorisations of the simulation model's nv x nv matrices
    (one after the other in its solver; physics alone at batch 256: test_mjx_batch.py).
    Before the controller's factorisations went through lapack_batched, its elimination
    (36 x 36 Cholesky with 43 right-hand sides, 22 x 22 LU) and the polish set-up were
    over it, and this closed loop hung at 64 and 256 rollouts per chunk."""
    from safewbc_jax.sim.mjx import rollout as R
    from safewbc_jax.control.push import Push

    b = R.CPU_CHUNK
    cfg = R.BatchConfig("walk", duration=0.05, settle=1.0)
    pl = R.plant(cfg)
    n_steps, settle = pl.schedule(cfg)
    fn = R._compiled(pl, 0, 0, b)
    hlo = fn.lower(R.default_params("walk", b), Push.none(b), np.zeros((b, pl.nv_sim)),
                   jnp.asarray(n_steps, jnp.int32), jnp.asarray(settle),
                   jnp.asarray(cfg.speed), jnp.asarray(1.0)).as_text()
    calls = _lapack_calls(hlo)
    assert len(calls) > 5, "the parser no longer finds the LAPACK calls in the lowered text"
    waiting = [(t, s) for t, s in calls if _work(t, s) >= lb.MIN_WORK]
    assert all(s[0][-1] == pl.nv_sim for _, s in waiting), waiting
