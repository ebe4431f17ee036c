"""The QP at the seam between the controller and its solvers.

    minimize    1/2 x^T P x + q^T x
    subject to  A x = b,   G x <= h,   lb <= x <= ub

with fixed shapes, as one pytree. ``soft`` marks the rows of G that the fallback policy
may relax with a heavily weighted slack (barrier and ZMP rows); the others (friction,
unilateral contact) are never relaxed. Everything left of this pytree is pure JAX;
the JAX solver and the PIQP path both take it.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax


@partial(jax.tree_util.register_dataclass,
         data_fields=["P", "q", "A", "b", "G", "h", "lb", "ub", "soft"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class QP:
    P: jax.Array   # (n, n) symmetric positive semidefinite
    q: jax.Array   # (n,)
    A: jax.Array   # (me, n)
    b: jax.Array   # (me,)
    G: jax.Array   # (mi, n)
    h: jax.Array   # (mi,)
    lb: jax.Array  # (n,)   -inf where unbounded
    ub: jax.Array  # (n,)   +inf where unbounded
    soft: jax.Array  # (mi,) 1.0 where the fallback may relax the row, else 0.0

    @property
    def n(self) -> int:
        return self.P.shape[-1]
