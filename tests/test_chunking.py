"""``chunking.chunked``: a batch run in equal chunks inside one jitted call gives, row by
row, what one vmap over the whole batch gives, with the padding stripped. The batched
closed loop (``batch.rollout._compiled``) and the JAX QP solver (``jax_qp.solve_batch``;
on recorded QPs in ``test_jax_qp.py``) both run through it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safewbc_jax.base.chunking import ByPlatform, chunk_layout, chunked, resolve_chunk


def _impl(batched, shared):
    """A vmapped function whose rows depend on their own inputs and on a shared argument,
    with a per-row while loop of row-dependent length (as a rollout's or an IPM's)."""
    x, k = batched

    def one(xi, ki):
        def body(c):
            i, acc = c
            return i + 1, acc * 1.5 + xi + shared
        _, acc = jax.lax.while_loop(lambda c: c[0] < ki, body, (0, jnp.zeros_like(xi)))
        return acc, ki * 2
    return jax.vmap(one)(x, k)


@pytest.mark.parametrize("batch,chunk", [(3, 2), (5, 2), (7, 3), (4, 4), (2, 64)])
def test_chunked_rows_equal_one_vmap(batch, chunk):
    rng = np.random.default_rng(batch * 10 + chunk)
    x = jnp.asarray(rng.normal(size=(batch, 4)))
    k = jnp.asarray(rng.integers(1, 9, size=batch), dtype=jnp.int32)
    ch = resolve_chunk(chunk, batch, None)
    assert (ch is None) == (chunk >= batch)
    want = jax.jit(_impl)((x, k), 0.25)
    got = jax.jit(chunked(_impl, ch))((x, k), 0.25)
    for w, g in zip(want, got):
        assert g.shape == w.shape
        # the same arithmetic on the same row in either layout: equal to rounding
        np.testing.assert_allclose(g, w, rtol=1e-14, atol=0)
    # the last row is not a copy of the padding's (the padding repeats the last row; a
    # shifted result would repeat a neighbour)
    if batch > 1:
        assert not np.allclose(got[0][-1], got[0][-2])


def test_chunk_layout_and_platform_choice():
    assert chunk_layout(3, 2) == (2, 2) and chunk_layout(1000, 64) == (16, 63)
    assert resolve_chunk("auto", 100, ByPlatform(64)) == ByPlatform(64)
    assert resolve_chunk("auto", 64, ByPlatform(64)) is None
    with pytest.raises(ValueError, match="chunk must be a positive int"):
        resolve_chunk(0, 4, None)
    # ByPlatform: chunked where lowered for the CPU, one vmap where lowered for CUDA
    f = jax.jit(chunked(_impl, ByPlatform(2)))
    args = ((jax.ShapeDtypeStruct((5, 4), jnp.float64), jax.ShapeDtypeStruct((5,), jnp.int32)),
            jax.ShapeDtypeStruct((), jnp.float64))
    cpu = jax.export.export(f, platforms=["cpu"])(*args).mlir_module()
    cuda = jax.export.export(f, platforms=["cuda"])(*args).mlir_module()
    assert "tensor<3x2x4xf64>" in cpu and "tensor<3x2x4xf64>" not in cuda
