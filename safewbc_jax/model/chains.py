"""Closed kinematic chains of the controller model as holonomic constraints.

Paper, "Closed kinematic chain constraints" and "Simulation and Experimental Results":
each rod is virtually disconnected and its length n_k(q) held constant, and the shin and
heel springs are held rigid, giving per leg

    n_kc = [n_ach, n_rA, n_rB, q_shin, q_heel-spring]      (eq. 29; left leg, then right leg)

and the constraint rows J_chain(q) q_ddot + J_chain_dot(q, v) v = 0 (eq. 2).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from safewbc_jax.model.robot import RobotModel, forward_kinematics, point_jacobians


def _site_points(model: RobotModel, xpos, xrot, sites):
    bodies = np.array([model.site_body[s] for s in sites])
    pts = xpos[bodies] + jnp.einsum("nij,nj->ni", xrot[bodies], model.site_pos[np.array(sites)])
    return bodies, pts


def row_order(model: RobotModel):
    """The rows of n_kc as ("rod", rod index) or ("spring", dof): per leg its rods (in
    model order), then its springs; left leg first."""
    rows = []
    for side in ("left", "right"):
        for i, r in enumerate(model.rod_names):
            if r.startswith(side):
                rows.append(("rod", i))
        for k in model.spring_dofs:
            name = model.joint_names[model.body_dadr.index(k)]
            if name.startswith(side):
                rows.append(("spring", k))
    return rows


def chain_names(model: RobotModel) -> list[str]:
    """Names of the rows of n_kc, in order."""
    out = []
    for kind, i in row_order(model):
        out.append(model.rod_names[i] if kind == "rod"
                   else model.joint_names[model.body_dadr.index(i)])
    return out


def n_kc(model: RobotModel, q):
    """The holonomic constraint functions n_kc(q): rod anchor distances and spring angles."""
    xpos, xrot = forward_kinematics(model, q)
    a = [s for s, _ in model.rod_sites]
    b = [s for _, s in model.rod_sites]
    _, pa = _site_points(model, xpos, xrot, a)
    _, pb = _site_points(model, xpos, xrot, b)
    lengths = jnp.linalg.norm(pa - pb, axis=1)
    out = []
    for kind, i in row_order(model):
        out.append(lengths[i] if kind == "rod" else q[i + 1])  # hinge qpos = dof + 1
    return jnp.stack(out)


def n_kc_target(model: RobotModel):
    """The values n_kc is held at: rod lengths and zero spring deflection."""
    out = [model.rod_length[i] if kind == "rod" else jnp.zeros((), model.rod_length.dtype)
           for kind, i in row_order(model)]
    return jnp.stack(out)


def chain_residual(model: RobotModel, q):
    """n_kc(q) - n_kc*: how far the chains are from closed (m for rods, rad for springs)."""
    return n_kc(model, q) - n_kc_target(model)


def chain_jacobian(model: RobotModel, q, kin=None):
    """J_chain(q) = d n_kc / d q in the tangent space (rows of eq. 2). ``kin``: the
    forward kinematics of q when already computed."""
    xpos, xrot = forward_kinematics(model, q) if kin is None else kin
    a = [s for s, _ in model.rod_sites]
    b = [s for _, s in model.rod_sites]
    ba, pa = _site_points(model, xpos, xrot, a)
    bb, pb = _site_points(model, xpos, xrot, b)
    ja, _ = point_jacobians(model, xpos, xrot, ba, pa)
    jb, _ = point_jacobians(model, xpos, xrot, bb, pb)
    d = pa - pb
    u = d / jnp.linalg.norm(d, axis=1, keepdims=True)
    jrod = jnp.einsum("ni,nik->nk", u, ja - jb)
    rows = []
    for kind, i in row_order(model):
        rows.append(jrod[i] if kind == "rod" else jnp.asarray(np.eye(model.nv)[i], q.dtype))
    return jnp.stack(rows)
