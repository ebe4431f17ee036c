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

    def unpack(self, flat):
        flat = np.asarray(flat)
        out = [flat[a:b].reshape(shape) for a, b, shape in self._slices]
        return jax.tree_util.tree_unflatten(self.treedef, out)
