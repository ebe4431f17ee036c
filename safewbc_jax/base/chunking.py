"""Running a batched function on a large batch in equal chunks, one after the other, inside
one jitted call (``lax.map`` over the batch reshaped to (n_chunks, size, ...)).

Why: on a CPU, one ``vmap`` over a large batch is slower per instance than the same work
in smaller pieces. Its working set outgrows the caches, and a vmapped loop runs until the
slowest instance of its whole batch stops, while a chunk stops at its own slowest. The
measurements behind the default chunk sizes: benchmarks/README.md, "Figures behind design
choices". On an accelerator the widest vmap is what fills the device, so
the defaults are ``ByPlatform`` chunks: chunked on the CPU, one vmap elsewhere, decided by
the platform the program is lowered for rather than by the machine that traces it.

The batch is cut into the fewest chunks of at most ``chunk`` instances, all of one size
(1000 with chunk 64: 16 chunks of 63), so there is one compiled chunk body and no
remainder path, and padded with copies of its last instance (less than one per chunk).
Copies of a real instance, not zeros: a zero QP or a zero robot state would fail, and a
failure in a chunk can make the whole chunk take a slower branch. The padding is stripped
from the results. The result for an instance does not depend on the other instances of
its chunk as long as the function is a vmap (which only freezes the lanes that have
stopped), so chunked and unchunked results agree.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax import lax


@dataclasses.dataclass(frozen=True)
class ByPlatform:
    """A chunk chosen by the platform the program is lowered for: chunks of ``cpu``
    instances on the CPU, one vmap over the whole batch on every other platform
    (``lax.platform_dependent``: a CUDA lowering made on a CPU machine shows the GPU's
    one-vmap program, and each compiled program holds only its own branch)."""

    cpu: int


def chunk_layout(batch: int, chunk: int) -> tuple[int, int]:
    """(n_chunks, size): the fewest chunks of at most ``chunk`` instances, all of one size,
    that hold ``batch`` instances (size * n_chunks - batch < n_chunks of padding)."""
    n_chunks = -(-batch // chunk)
    return n_chunks, -(-batch // n_chunks)


def check_chunk(chunk) -> None:
    """Raise ValueError unless ``chunk`` is a positive int, None or "auto"."""
    if chunk is None or chunk == "auto":
        return
    try:
        ok = not isinstance(chunk, (bool, str)) and int(chunk) == chunk and chunk >= 1
    except (TypeError, ValueError, OverflowError):     # NaN, inf, a list, ...
        ok = False
    if not ok:
        raise ValueError(f"chunk must be a positive int, None or 'auto', got {chunk!r}")


def resolve_chunk(chunk, batch: int, default):
    """The chunk a batch of ``batch`` instances runs with: "auto" -> ``default`` (an int,
    None or a ``ByPlatform``); None, and any chunk >= the batch, -> None (one vmap: the
    same compiled function whatever the chunk asked for)."""
    check_chunk(chunk)
    if chunk == "auto":
        chunk = default
    if chunk is None:
        return None
    if isinstance(chunk, ByPlatform):
        return None if chunk.cpu >= batch else chunk
    return None if chunk >= batch else int(chunk)


def chunked(impl, chunk: int | None):
    """``impl(batched, *shared)`` (a function of a pytree with a leading batch axis on every
    leaf, and of arguments shared by the whole batch) run on the batch in chunks of at most
    ``chunk`` instances; None: ``impl`` itself; a ``ByPlatform``: by the platform lowered
    for. To be traced inside ``jit``. A batch of at most ``chunk`` is one chunk; for ``impl``
    itself there (the same compiled function as no chunking), pass ``resolve_chunk``'s
    answer."""
    if chunk is None:
        return impl
    if isinstance(chunk, ByPlatform):
        on_cpu = chunked(impl, chunk.cpu)
        return lambda batched, *shared: lax.platform_dependent(batched, *shared, cpu=on_cpu,
                                                               default=impl)

    def run(batched, *shared):
        B = jax.tree_util.tree_leaves(batched)[0].shape[0]
        n_chunks, size = chunk_layout(B, chunk)
        pad = n_chunks * size - B

        def split(a):
            if pad:
                a = jnp.concatenate([a, jnp.broadcast_to(a[-1:], (pad,) + a.shape[1:])])
            return a.reshape((n_chunks, size) + a.shape[1:])

        out = lax.map(lambda part: impl(part, *shared), jax.tree_util.tree_map(split, batched))
        return jax.tree_util.tree_map(
            lambda y: y.reshape((n_chunks * size,) + y.shape[2:])[:B], out)
    return run
