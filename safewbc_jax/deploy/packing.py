"""Move a pytree of arrays from a jitted function to numpy in one transfer.

On the CPU each device-to-host conversion costs several microseconds; a control step
returns about thirty arrays (the QP and the logged outputs), so the jitted function
returns them as one flat vector and the host splits it into numpy views.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np


class Packer:
    """``pack`` (inside jit) flattens a pytree into one vector; ``unpack`` (host) rebuilds
    it from numpy views. The structure is recorded by the first ``pack`` trace, with each
    leaf's slice of the vector as plain Python integers: the host side then costs one
    slice and one reshape per leaf (a per-call ``np.prod`` of each shape tuple cost more
    than the rest of the split together)."""

    def __init__(self):
        self.treedef = None
        self.shapes = None
        self._slices = None

    def pack(self, tree):
        leaves, treedef = jax.tree_util.tree_flatten(tree)
        self.treedef = treedef
        self.shapes = [tuple(int(d) for d in jnp.shape(x)) for x in leaves]
        slices, i = [], 0
        for shape in self.shapes:
            n = math.prod(shape)
            slices.append((i, i + n, shape))
            i += n
        self._slices = slices
        return jnp.concatenate([jnp.ravel(jnp.asarray(x, jnp.float64)) for x in leaves])

    @property
    def size(self) -> int:
        """The packed vector's length (after the first ``pack``)."""
        return self._slices[-1][1] if self._slices else 0

    def unpack(self, flat, xp=np):
        """numpy views of the leaves (``xp`` jax.numpy: slices of a traced vector); leading
        axes of ``flat`` (a stack of packed vectors, e.g. from a vmapped function) stay in
        front of each leaf's shape."""
        flat = xp.asarray(flat)
        lead = flat.shape[:-1]
        out = [flat[..., a:b].reshape(lead + shape) for a, b, shape in self._slices]
        return jax.tree_util.tree_unflatten(self.treedef, out)


class FlatTree:
    """A pytree of fixed structure as one float64 vector, in both directions and on both
    sides of a jit boundary: ``pack`` (numpy on the host, jax.numpy inside jit) and
    ``unpack`` (``xp`` numpy or jax.numpy), each leaf back in its own dtype (integers and
    booleans round-trip exactly: they are far below 2**53). Passing a state of some forty
    small arrays into and out of a jitted call costs ~4 us per array on the CPU; as one
    vector, ~10 us in all."""

    def __init__(self, template):
        leaves, self.treedef = jax.tree_util.tree_flatten(template)
        # leaves may be arrays or jax.ShapeDtypeStruct (``jax.eval_shape``)
        self.dtypes = [np.dtype(x.dtype) if hasattr(x, "dtype") else np.asarray(x).dtype
                       for x in leaves]
        self.slices, i = [], 0
        for x in leaves:
            shape = tuple(int(d) for d in (x.shape if hasattr(x, "shape") else np.shape(x)))
            n = math.prod(shape)
            self.slices.append((i, i + n, shape))
            i += n
        self.size = i

    def pack(self, tree, xp=np):
        leaves = self.treedef.flatten_up_to(tree)
        if not leaves:
            return xp.zeros(0)
        return xp.concatenate([xp.ravel(xp.asarray(x, xp.float64)) for x in leaves])

    def unpack(self, flat, xp=np):
        out = []
        for (a, b, shape), dt in zip(self.slices, self.dtypes):
            x = flat[a:b].reshape(shape)
            out.append(x != 0 if dt == np.bool_ else x.astype(dt))
        return jax.tree_util.tree_unflatten(self.treedef, out)
