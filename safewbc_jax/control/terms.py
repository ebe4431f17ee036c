"""The safe whole-body controller, closed over a scenario: state -> QP matrices -> torques.

``robot_terms`` evaluates everything that depends on the robot (M, h, B, the chain and
contact Jacobians with their drifts, every output's y^a, J_y, J_y_dot v);
``build_qp`` turns them, the references and ``ControllerParams`` into the QP pytree (the
seam). Both are pure JAX (jit, vmap). The control step built on them is ``control_step``; the
deployable controller (PIQP, the fallback policy, the last good torque held) is
``deploy.Controller``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.control import barriers, qp
from safewbc_jax.model import chains, contacts, robot
from safewbc_jax.control import outputs as outputs_mod
from safewbc_jax.control.params import ControllerParams


class QPAux(NamedTuple):
    """What ``build_qp`` evaluated beside the QP, for the step's record: per output name
    (y^a, y^d) (eq. 10's two sides), per barrier name its h (eq. 20)."""

    outputs: dict
    barrier_h: dict


class Terms(NamedTuple):
    M: jax.Array
    h: jax.Array
    J: jax.Array        # [J_chain (10); J_cont left (6); J_cont right (6)]
    Jdot_v: jax.Array
    outputs: dict       # name -> (y^a, J_y, J_y_dot v)
    kin: tuple          # forward kinematics (xpos, xrot) of q
    motion: robot.BodyMotion  # body motion at (q, v): the closed-form terms use it


def constraint_jacobian(model: robot.RobotModel, q, kin=None):
    """J(q) = [J_chain; J_cont] (eqs. 2-3): chains, then left and right sole (6D each)."""
    return jnp.concatenate([chains.chain_jacobian(model, q, kin),
                            contacts.stacked_contact_jacobian(model, q, kin)], axis=0)


def constraint_drift(model: robot.RobotModel, kin, motion: robot.BodyMotion):
    """J_dot v of [J_chain; J_cont] (22 rows) in closed form (``constraint_terms``)."""
    return constraint_terms(model, kin, motion)[1]


def constraint_terms(model: robot.RobotModel, kin, motion: robot.BodyMotion):
    """J = [J_chain; J_cont] (eqs. 2-3) and its drift J_dot v in closed form, from the
    world points of every rod end and both soles taken together (one set of point
    Jacobians, velocities and bias accelerations: XLA on the CPU pays per operation).

    A rod row is u^T (J_a - J_b) with u = d / |d|, d = p_a - p_b: its drift is
    (|d_dot|^2 - (u . d_dot)^2) / |d| + u . (a_a - a_b), a the points' bias
    accelerations; a spring row is constant (e_k; drift 0). A contact row block is
    [R^T J_p; R^T J_w] with R the sole frame (R_dot = omega x R): its drift is
    [R^T (a - omega x x_dot); R^T alpha]."""
    xpos, xrot = kin
    nr = len(model.rod_sites)
    feet = [model.site_id(f) for f in contacts.FEET]
    sites = np.array([a for a, _ in model.rod_sites] + [b for _, b in model.rod_sites] + feet)
    bodies = np.array([model.site_body[s] for s in sites])
    p = xpos[bodies] + jnp.einsum("nij,nj->ni", xrot[bodies], model.site_pos[sites])
    jp, jw = robot.point_jacobians(model, xpos, xrot, bodies, p)
    vel = motion.point_velocity(bodies, p)
    acc = motion.point_bias(bodies, p, vel)
    d, dd = p[:nr] - p[nr:2 * nr], vel[:nr] - vel[nr:2 * nr]
    dist = jnp.linalg.norm(d, axis=1)
    u = d / dist[:, None]
    u_dd = jnp.sum(u * dd, axis=1)
    rod_j = jnp.einsum("ni,nik->nk", u, jp[:nr] - jp[nr:2 * nr])
    rod_d = ((jnp.sum(dd * dd, axis=1) - u_dd * u_dd) / dist
             + jnp.sum(u * (acc[:nr] - acc[nr:2 * nr]), axis=1))
    order = chains.row_order(model)
    springs = [i for kind, i in order if kind == "spring"]
    # the rows in n_kc's order: rods from rod_j, springs from the constant rows after them
    perm = np.array([i if kind == "rod" else nr + springs.index(i) for kind, i in order])
    chain_j = jnp.concatenate([rod_j, jnp.asarray(np.eye(model.nv)[springs], p.dtype)])[perm]
    chain_d = jnp.concatenate([rod_d, jnp.zeros(len(springs), p.dtype)])[perm]
    rt = jnp.swapaxes(xrot[bodies[2 * nr:]] @ model.site_rot[np.array(feet)], 1, 2)  # R^T
    cont_j = jnp.concatenate([rt @ jp[2 * nr:], rt @ jw[2 * nr:]], axis=1).reshape(-1, model.nv)
    w = motion.omega[bodies[2 * nr:]]
    world = jnp.stack([acc[2 * nr:] - jnp.cross(w, vel[2 * nr:]),
                       motion.alpha[bodies[2 * nr:]]], axis=1)          # [foot, 2, 3]
    cont_d = jnp.einsum("nij,nkj->nki", rt, world).reshape(-1)
    return (jnp.concatenate([chain_j, cont_j], axis=0),
            jnp.concatenate([chain_d, cont_d]))


def robot_terms(model: robot.RobotModel, scenario, q, v, domain=None) -> Terms:
    """Every robot-dependent term of one control step: one forward-kinematics pass gives
    the body, chain and contact Jacobians, and the closed-form body motion
    (``robot.body_motion``) all their drift terms: XLA on the CPU pays per operation, and
    a forward-mode tangent of the kinematics and Jacobians would triple their count."""
    kin = robot.forward_kinematics(model, q)
    motion = robot.body_motion(model, kin, v)
    dyn = robot.dynamics(model, kin, motion)
    step = outputs_mod.StepTerms(dyn, kin, motion, domain)
    outs = {o.name: o.evaluate(model, q, v, step) for o in scenario.outputs}
    jac, drift = constraint_terms(model, kin, motion)
    return Terms(dyn.M, dyn.h, jac, drift, outs, kin, motion)


def n_chain_rows(model) -> int:
    return len(model.rod_names) + len(model.spring_dofs)


def build_qp(model, scenario, params: ControllerParams, terms: Terms, q, v, tau, start,
             in_contact, domain=None):
    """QP matrices of one control step and its ``QPAux`` (outputs and references, barrier values).

    ``domain`` (walking): the gait state (stance side, step time, feet at step start,
    commands) as data, so one compiled function serves every domain; its ``in_contact``
    replaces the argument."""
    if domain is not None:
        in_contact = domain.in_contact
    desired = scenario.desired_at(model, tau, start, q, v, domain)
    mask = scenario.masks(domain)
    jac, drift, ystar, w, err = [], [], [], [], {}
    for o in scenario.outputs:
        ya, jy, jdv = terms.outputs[o.name]
        yd, yd_dot, yd_ddot = desired[o.name]
        y = ya - yd
        ydot = jy @ v - yd_dot
        ystar.append(-params.kp[o.name] * y - params.kd[o.name] * ydot + yd_ddot)
        jac.append(jy)
        drift.append(jdv)
        w.append(params.weight[o.name] * mask.get(o.name, 1.0))
        err[o.name] = (ya, yd)
    task_J, task_w, task_q = qp.task_cost(jac, drift, ystar, w, model.nv)

    nc_chain = n_chain_rows(model)
    nc = terms.J.shape[0]
    contact_rows = np.arange(nc) >= nc_chain
    in_contact = jnp.asarray(in_contact, q.dtype)
    in_rows = jnp.concatenate([jnp.ones(nc_chain, q.dtype), jnp.repeat(in_contact, 6)])
    g_lam, h_lam, soft_lam = contacts.contact_inequalities(
        model, q, in_contact, params.mu, params.gamma_torsion, params.f_min, params.zmp_margin,
        kin=terms.kin)
    g_full = jnp.concatenate([jnp.zeros((g_lam.shape[0], nc_chain), q.dtype), g_lam], axis=1)

    rows, bs, hvals = [], [], {}
    for b in scenario.barriers:
        if b.terms is not None:     # closed form from this step's kinematics
            r = barriers.aecbf_row_from_terms(  # type: ignore[call-arg]  # h, J_h, J_h_dot v
                *b.terms(model, terms.kin, terms.motion, params.threshold[b.name], domain),
                v, params.poles[b.name])
        else:                       # automatic differentiation of h
            r = barriers.aecbf_row(b.h_fn(model, params.threshold[b.name], domain), q, v,
                                   params.poles[b.name], b.relative_degree)
        on = jnp.asarray(b.is_active(domain), q.dtype)
        rows.append(on * r.a_row)
        bs.append(jnp.where(on > 0, r.b, -1e9))
        hvals[b.name] = r.eta[0]
    for b in scenario.monitors:
        hvals[b.name] = (b.terms(model, terms.kin, terms.motion, params.threshold[b.name],
                                 domain)[0] if b.terms is not None else
                         b.value(model, q, v, params.threshold[b.name], domain))
    brow = jnp.stack(rows) if rows else jnp.zeros((0, model.nv), q.dtype)
    bb = jnp.stack(bs) if bs else jnp.zeros((0,), q.dtype)

    nu = model.nu
    tangential = np.zeros(nc, bool)
    for foot in range(2):  # f_x, f_y, m_z of each contact wrench
        tangential[nc_chain + 6 * foot + np.array([0, 1, 5])] = True
    gamma_lam = jnp.where(tangential, params.gamma_lambda + params.gamma_tangential,
                          params.gamma_lambda)
    gamma = jnp.concatenate([jnp.full(model.nv, params.gamma_qdd), jnp.full(nu, params.gamma_u),
                             gamma_lam])
    _, u_max = contacts.torque_limit_bounds(model)
    if scenario.gait is not None:
        # A passive joint (the stance ankle of the ALIP gait) is one whose motors give no
        # torque: its bounds become 0 <= u <= 0.
        u_max = u_max * (1.0 - scenario.gait.passive_actuators(model, domain))
    # Holonomic rows J q_ddot = -J_dot v - kd J v: kd = 0 is eqs. 2-3 as written.
    jdot_v = terms.Jdot_v + params.kd_constraint * (terms.J @ v)
    qpm = qp.assemble(M=terms.M, h=terms.h, B=model.B, J=terms.J, Jdot_v=jdot_v,
                      contact_rows=contact_rows, in_contact_rows=in_rows, task_J=task_J,
                      task_w=task_w, task_q=task_q, gamma=gamma, G_lambda=g_full, h_lambda=h_lam,
                      soft_lambda=soft_lam, barrier_rows=brow, barrier_b=bb, u_max=u_max)
    return qpm, QPAux(err, hvals)


def output_start_values(model, scenario, q):
    return {o.name: o.value(model, q) for o in scenario.outputs}
