"""Assembly of the safe inverse-dynamics QP of the paper's section III.

Decision variable X = [q_ddot (nv), u (nu), lambda (nc)]. The program (paper, the QP after
eq. 15, with the A-ECBF rows of eq. 28):

    min_X  sum_o || J_o q_ddot + J_o_dot v - y*_o ||^2_{W_o} + X^T Gamma X
    s.t.   D_eq X = [M  -B  -J^T] X = -h(q, v)          (dynamics, eq. 13)
           C_eq X = [J   0   0 ] X = -J_dot v           (chains and contacts, eq. 14)
           G_lambda lambda <= h_lambda                  (friction, torsion, ZMP: eqs. 4-7, 9)
           L_G L_F h q_ddot >= -K_alpha eta - L_F^2 h   (A-ECBF, eq. 28, one row per barrier)
           -u_max <= u <= u_max                         (torque limits)

written as the seam pytree ``QP`` (min 1/2 x'Px + q'x, Ax = b, Gx <= h, lb <= x <= ub),
which carries the block sizes nv, nu, nc of X as static data for the solvers.
This module is pure algebra on arrays; ``controller`` computes the terms.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from safewbc_jax.solvers.problem import QP, PFactor


P_STRUCTURE = "diagonal"
"""What ``assemble``'s P is by construction, as ``solvers.reduce.p_structure`` names it: no
cross blocks between q_ddot, u and lambda, and diagonal u and lambda blocks (Gamma). Its
bounds on q_ddot and lambda are infinite, so no variable outside u is bounded
(``reduce.bounded_variables`` is empty). The solvers' elimination takes both as static
data; ``tests/test_deploy_same_qp.py`` holds them on every scenario's QP."""


def task_cost(task_jacobians, task_drifts, y_star, weights, nv):
    """sum_o ||J_o q_ddot + J_o_dot v - y*_o||^2_{W_o} (the paper's task cost, after eq. 15)
    in the 1/2 x'Px + q'x form, with its Hessian in task form: the outputs' stacked rows
    J (m, nv), their weights w = 2 diag(W_o) (m,), and the gradient q = J' diag(w)
    (J_dot v - y*), so that P = J' diag(w) J (``assemble`` forms it)."""
    if not task_jacobians:
        return jnp.zeros((0, nv)), jnp.zeros(0), jnp.zeros(nv)
    J = jnp.concatenate(task_jacobians, axis=0)
    w = 2.0 * jnp.concatenate([jnp.broadcast_to(w, (j.shape[0],))
                               for w, j in zip(weights, task_jacobians)])
    r = jnp.concatenate(task_drifts) - jnp.concatenate(y_star)
    return J, w, J.T @ (w * r)


def _diag(d):
    """diag(d) as d times a constant identity (no iota in the program)."""
    return np.eye(d.shape[0], dtype=d.dtype) * d[None, :]


def _block_diagonal(blocks):
    """The block-diagonal matrix of square ``blocks``, by concatenation."""
    sizes = [b.shape[0] for b in blocks]
    rows = []
    for k, b in enumerate(blocks):
        left = jnp.zeros((sizes[k], sum(sizes[:k])), b.dtype)
        right = jnp.zeros((sizes[k], sum(sizes[k + 1:])), b.dtype)
        rows.append(jnp.concatenate([left, b, right], axis=1))
    return jnp.concatenate(rows, axis=0)


def assemble(*, M, h, B, J, Jdot_v, contact_rows, in_contact_rows, task_J, task_w, task_q,
             gamma, G_lambda, h_lambda, soft_lambda, barrier_rows, barrier_b, u_max) -> QP:
    """The QP matrices. Shapes: M (nv, nv), h (nv), B (nv, nu), J (nc, nv), Jdot_v (nc);
    ``contact_rows`` (nc,) bool marks the rows of J that belong to a foot contact and
    ``in_contact_rows`` (nc,) float is 1 where that foot is in contact: a row of a foot in
    the air becomes lambda_row = 0 (shapes stay fixed across domains).
    task_J (m, nv), task_w (m,), task_q (nv): the task cost (``task_cost``), whose
    Hessian J' diag(w) J the QP also carries in that form (``PFactor``).
    gamma: (nv + nu + nc,) diagonal of Gamma. G_lambda (m, nc) rows on lambda;
    barrier_rows (nb, nv) and barrier_b (nb,) mean barrier_rows q_ddot >= barrier_b."""
    nv, nu = B.shape
    nc = J.shape[0]
    n = nv + nu + nc
    dtype = M.dtype
    active = jnp.where(contact_rows, in_contact_rows, 1.0)
    # Dynamics D_eq X = -h.
    d_eq = jnp.concatenate([M, -B, -J.T], axis=1)
    # Constraint kinematics C_eq X = -J_dot v; rows of feet in the air pin lambda to 0.
    c_eq = jnp.concatenate([active[:, None] * J, jnp.zeros((nc, nu), dtype),
                            jnp.diag(1.0 - active)], axis=1)
    A = jnp.concatenate([d_eq, c_eq], axis=0)
    b = jnp.concatenate([-h, -active * Jdot_v])
    # Inequalities: contact rows on lambda, then A-ECBF rows on q_ddot.
    g_lam = jnp.concatenate([jnp.zeros((G_lambda.shape[0], nv + nu), dtype), G_lambda], axis=1)
    g_bar = jnp.concatenate([-barrier_rows, jnp.zeros((barrier_rows.shape[0], nu + nc), dtype)],
                            axis=1)
    G = jnp.concatenate([g_lam, g_bar], axis=0)
    hv = jnp.concatenate([h_lambda, -barrier_b])
    soft = jnp.concatenate([soft_lambda, jnp.ones(barrier_rows.shape[0], dtype)])
    # P block by block (concatenations, no scatter, no n x n iota): the elimination
    # slices its q_ddot, u and lambda blocks back out, and a slice of a concatenation is
    # the operand itself, not a recomputation of all of P
    d = 2.0 * gamma[:nv]
    P = _block_diagonal([task_J.T @ (task_w[:, None] * task_J) + _diag(d),
                         _diag(2.0 * gamma[nv:nv + nu]), _diag(2.0 * gamma[nv + nu:])])
    q = jnp.concatenate([task_q, jnp.zeros(n - nv, dtype)])
    inf = jnp.full(nv, jnp.inf, dtype)
    lb = jnp.concatenate([-inf, -u_max, jnp.full(nc, -jnp.inf, dtype)])
    ub = jnp.concatenate([inf, u_max, jnp.full(nc, jnp.inf, dtype)])
    return QP(P=P, q=q, A=A, b=b, G=G, h=hv, lb=lb, ub=ub, soft=soft, nv=nv, nu=nu, nc=nc,
              ng_lambda=G_lambda.shape[0], p_factor=PFactor(task_J, task_w, d))
