"""Reference implementations that only the tests use: every drift term of the controller by
forward-mode AD of its Jacobian along q_dot (J_dot v = d/dt (J(q(t)) v), q(t) =
integrate(q, v t)), the twins the closed forms of ``robot.body_motion`` and
``controller.constraint_drift`` are checked against (and which are themselves checked
against finite differences of MuJoCo's kinematics)."""

import jax
import jax.numpy as jnp

from safewbc_jax.model import robot, spatial
from safewbc_jax.model.chains import chain_jacobian
from safewbc_jax.model.contacts import contact_jacobian, stacked_contact_jacobian
from safewbc_jax.control.terms import Terms, constraint_jacobian
from safewbc_jax.control.outputs import StepTerms
from safewbc_jax.model.robot import Dynamics, RobotModel, _com_jacobians


def _dynamics(model, jp, jr, irot, com, acc, alpha, omega):
    """M, h and the CoM terms as the virtual-work sum over the bodies' CoM Jacobians,
    M = sum_b m_b Jc_b^T Jc_b + Jw_b^T I_b Jw_b + diag(armature), h = sum_b Jc_b^T m_b
    (a_b - g) + Jw_b^T (I_b alpha_b + omega_b x I_b omega_b): the reference the composite
    rigid-body form of ``robot.dynamics`` is checked against."""
    iworld = jnp.einsum("bij,bj,bkj->bik", irot, model.body_inertia, irot)
    mass = jnp.einsum("b,bin,bim->nm", model.body_mass, jp, jp)
    mass = mass + jnp.einsum("bin,bij,bjm->nm", jr, iworld, jr) + jnp.diag(model.armature)
    force = model.body_mass[:, None] * (acc - model.gravity[None])
    iw = jnp.einsum("bij,bj->bi", iworld, omega)
    torque = jnp.einsum("bij,bj->bi", iworld, alpha) + jnp.cross(omega, iw)
    h = jnp.einsum("bin,bi->n", jp, force) + jnp.einsum("bin,bi->n", jr, torque)
    mtot = jnp.sum(model.body_mass)
    return Dynamics(M=mass, h=h, com=model.body_mass @ com / mtot,
                    J_com=jnp.einsum("b,bin->in", model.body_mass, jp) / mtot,
                    Jdot_v_com=model.body_mass @ acc / mtot)


def dynamics_from_jacobians(model: RobotModel, bodies, dbodies, v):
    """M, h and the CoM terms from the body Jacobians ``bodies`` = com_jacobians(...) and
    their tangent ``dbodies`` along q_dot (forward-mode AD)."""
    jp, jr, irot, com = bodies
    djp, djr = dbodies[0], dbodies[1]
    return _dynamics(model, jp, jr, irot, com, djp @ v, djr @ v, jr @ v)


def bias_forces_ad(model: RobotModel, q, v):
    """``bias_forces`` with the body accelerations by forward-mode AD of the Jacobians (the
    reference the closed-form ``body_motion`` is checked against)."""
    def jv(qq):
        jp, jr, _ = _com_jacobians(model, qq)
        return jp @ v, jr @ v

    jp, jr, irot = _com_jacobians(model, q)
    omega = jr @ v
    acc, alpha = spatial.derivative_along(jv, q, v)
    iworld = jnp.einsum("bij,bj,bkj->bik", irot, model.body_inertia, irot)
    force = model.body_mass[:, None] * (acc - model.gravity[None])
    iw = jnp.einsum("bij,bj->bi", iworld, omega)
    torque = jnp.einsum("bij,bj->bi", iworld, alpha) + jnp.cross(omega, iw)
    return jnp.einsum("bin,bi->n", jp, force) + jnp.einsum("bin,bi->n", jr, torque)


def chain_drift(model: RobotModel, q, v):
    """J_chain_dot(q, v) v."""
    return spatial.derivative_along(lambda qq: chain_jacobian(model, qq) @ v, q, v)


def contact_drift(model: RobotModel, q, v, frame: str):
    """J_cont_dot v of eq. 3: d/dt (J_cont(q) v) along q(t) = integrate(q, v t). It
    includes the rotation of the contact frame itself, so it is not R^T times
    robot.frame_drift unless the sole is at rest (J_cont v = 0)."""
    return spatial.derivative_along(lambda qq: contact_jacobian(model, qq, frame) @ v, q, v)


def stacked_contact_drift(model: RobotModel, q, v):
    """[J_cont_dot^left v; J_cont_dot^right v] (12), eq. 3's drift for both feet."""
    return spatial.derivative_along(lambda qq: stacked_contact_jacobian(model, qq) @ v, q, v)


def robot_terms_ad(model: RobotModel, scenario, q, v, domain=None) -> Terms:
    """``robot_terms`` with every drift term by one forward-mode tangent of the kinematics
    and Jacobians along q_dot (the reference the closed form is tested against)."""
    def jacobians(qq):
        kin = robot.forward_kinematics(model, qq)
        return robot.com_jacobians(model, kin), constraint_jacobian(model, qq, kin), kin

    (bodies, J, kin), (dbodies, dJ, _) = jax.jvp(jacobians, (q,), (spatial.config_rate(q, v),))
    dyn = dynamics_from_jacobians(model, bodies, dbodies, v)
    step = StepTerms(dyn=dyn, domain=domain)
    outs = {o.name: o.evaluate(model, q, v, step) for o in scenario.outputs}
    return Terms(dyn.M, dyn.h, J, dJ @ v, outs, kin, robot.body_motion(model, kin, v))
