"""The QP at the seam between the controller and its solvers.

    minimize    1/2 x^T P x + q^T x
    subject to  A x = b,   G x <= h,   lb <= x <= ub

with fixed shapes, as one pytree. ``soft`` marks the rows of G that the fallback policy
may relax with a heavily weighted slack (barrier and ZMP rows); the others (friction,
unilateral contact) are never relaxed. Everything left of this pytree (the controller
side) is pure JAX.

Block sizes. The controller's QP (``qp.assemble``) is over X = [q_ddot (nv), u (nu),
lambda (nc)] and says so: ``nv``, ``nu``, ``nc`` are static data of the pytree (part of
its tree structure, not leaves: they survive ``jit``, ``vmap`` and ``tree_map``, and a
change of them is a new compile). They are all None for a QP without that structure (a
generic QP, e.g. from ``solvers.solve_qp``, or a relaxed QP in [x; s]). The solvers take
every size they need from here; nothing beside the QP tells them Digit's.

``ng_lambda`` (static too) states where G is zero by construction: its first
``ng_lambda`` rows have entries in the lambda block only (contacts: friction, centre of
pressure, ZMP), the rest in the q_ddot block only (A-ECBF rows), as ``qp.assemble`` lays
them out. The elimination multiplies only those blocks. None: no such layout is claimed.

``p_factor`` (optional leaves, ``PFactor``) states P's q_ddot block in the task form it
has by construction, J' diag(w) J + diag(d) with the task Jacobians' rows J: the
elimination applies it as such, never forming the nv x nv block. None: P alone.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, Callable, NamedTuple

import jax

FIELDS = ("P", "q", "A", "b", "G", "h", "lb", "ub", "soft")
"""The array fields, in the order of the positional constructor."""


# a QP's arrays: JAX arrays in the jitted step, NumPy ones on the host (PIQP's) path
Array = Any


class PFactor(NamedTuple):
    """P's q_ddot block as J' diag(w) J + diag(d): the task Jacobians' m rows J (m, nv),
    their weights w (m,) and the diagonal d (nv,) (paper: the tasks' sum of
    ||J_o q_ddot + ...||^2_{W_o} and Gamma's q_ddot part)."""

    J: Array
    w: Array
    d: Array


class Blocks(NamedTuple):
    """The block sizes of X = [q_ddot (nv), u (nu), lambda (nc)].

    Attributes:
        nv: size of the q_ddot block.
        nu: size of the torques' block u.
        nc: size of the contact forces' block lambda; None: the rest of X.
    """

    nv: int
    nu: int
    nc: int | None = None

    @property
    def u_slice(self) -> slice:
        """The torques' entries of X."""
        return slice(self.nv, self.nv + self.nu)

    def split(self, x: Array) -> tuple[Array, Array, Array]:
        """Split X into its blocks.

        Args:
            x: (..., n) values of X, with any leading batch dimensions.

        Returns:
            ``(q_ddot, u, lambda)``, each with x's leading dimensions.
        """
        nv, nu = self.nv, self.nu
        return x[..., :nv], x[..., nv:nv + nu], x[..., nv + nu:]


@partial(jax.tree_util.register_dataclass, data_fields=[*FIELDS, "p_factor"],
         meta_fields=["nv", "nu", "nc", "ng_lambda"])
@dataclasses.dataclass(frozen=True)
class QP:
    """One QP (or a batch of them, a leading axis on every array), at fixed shapes.

    minimize 1/2 x^T P x + q^T x subject to A x = b, G x <= h, lb <= x <= ub. The
    arrays are JAX arrays in the jitted step, NumPy ones on the host (PIQP's) path; the
    block sizes are static (the module docstring).

    Args:
        P: (n, n) symmetric positive semidefinite cost matrix.
        q: (n,) linear cost.
        A: (me, n) equality rows.
        b: (me,) their right-hand sides.
        G: (mi, n) inequality rows.
        h: (mi,) their bounds.
        lb: (n,) lower bounds on x, -inf where unbounded.
        ub: (n,) upper bounds on x, +inf where unbounded.
        soft: (mi,) 1.0 where the fallback may relax the row of G, else 0.0.
        nv: for the controller's X = [q_ddot (nv), u (nu), lambda (nc)]: the q_ddot
            block's size; None: no such blocks.
        nu: the torques' block size (None with ``nv``).
        nc: the contact forces' block size (None: the rest, or no blocks).
        ng_lambda: the first ``ng_lambda`` rows of G are on lambda only, the rest on
            q_ddot only; None: no such layout is claimed.
        p_factor: P's q_ddot block as ``PFactor`` (task form), or None.
    """

    P: Array   # (n, n) symmetric positive semidefinite
    q: Array   # (n,)
    A: Array   # (me, n)
    b: Array   # (me,)
    G: Array   # (mi, n)
    h: Array   # (mi,)
    lb: Array  # (n,)   -inf where unbounded
    ub: Array  # (n,)   +inf where unbounded
    soft: Array  # (mi,) 1.0 where the fallback may relax the row, else 0.0
    nv: int | None = None   # X = [q_ddot (nv), u (nu), lambda (nc)]; None: no such blocks
    nu: int | None = None
    nc: int | None = None
    ng_lambda: int | None = None   # rows of G on lambda only, then rows on q_ddot only
    p_factor: PFactor | None = None    # P's q_ddot block in task form (module docstring)

    @property
    def n(self) -> int:
        """The number of variables."""
        return self.P.shape[-1]

    @property
    def has_blocks(self) -> bool:
        """True where the QP carries the controller's block sizes."""
        return self.nv is not None and self.nu is not None

    @property
    def blocks(self) -> Blocks:
        """The block sizes.

        Raises:
            ValueError: the QP carries none (``has_blocks`` False).
        """
        if not self.has_blocks:
            raise ValueError("this QP carries no block sizes (nv, nu): it is not the "
                             "controller's QP of qp.assemble")
        assert self.nv is not None and self.nu is not None      # has_blocks
        return Blocks(self.nv, self.nu, self.nc)

    def split(self, x: Array) -> tuple[Array, Array, Array]:
        """Split X at the QP's block sizes.

        Args:
            x: (..., n) values of X, with any leading batch dimensions.

        Returns:
            ``(q_ddot, u, lambda)``, each with x's leading dimensions.

        Raises:
            ValueError: the QP carries no block sizes.
        """
        return self.blocks.split(x)

    def arrays(self) -> tuple[Array, ...]:
        """The array fields.

        Returns:
            The arrays in ``FIELDS`` order (the positional constructor's).
        """
        return tuple(getattr(self, f) for f in FIELDS)

    def row(self, i: int) -> QP:
        """One QP of a batch of them (one lane's, or one recorded step's).

        Args:
            i: its index on each array's leading axis.

        Returns:
            The i-th QP, with this QP's block sizes.
        """
        return self.with_arrays(lambda a: a[i])

    def with_arrays(self, fn: Callable[[Array], Array]) -> QP:
        """Map every array field, the block sizes kept (``tree_map``'s result, without its
        flattening).

        Args:
            fn: applied to each array field (e.g. ``jnp.asarray``, ``np.asarray``).

        Returns:
            The QP of ``fn``'s results.
        """
        pf = self.p_factor
        return QP(*(fn(getattr(self, f)) for f in FIELDS),  # type: ignore[misc]
                  nv=self.nv, nu=self.nu, nc=self.nc, ng_lambda=self.ng_lambda,
                  p_factor=None if pf is None else PFactor(*(fn(a) for a in pf)))
