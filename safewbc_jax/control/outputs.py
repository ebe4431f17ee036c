"""Task-space outputs y^a(q) with their Jacobian J_y(q) and drift J_y_dot(q, v) v.

Paper, "Task Space Inverse dynamics": y(t, q) = y^a(q) - y^d(t), y_dot = J_y v - y^d_dot,
y_ddot = J_y_dot v + J_y q_ddot - y^d_ddot (eqs. 10-12). Each output is one small object with
the same interface, ``evaluate(model, q, v) -> (y^a, J_y, J_y_dot v)``; a new output is a
new class here, nothing else changes.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.model import robot, spatial


class StepTerms(NamedTuple):
    """What a control step has computed at (q, v) already, for the outputs to reuse
    (``controller.robot_terms``): the dynamics and CoM terms, the forward kinematics and
    the body motion (the frame outputs take their closed forms from these), the domain
    (walking's swing outputs). An output computes a field left None itself.

    Attributes:
        dyn: M, h and the CoM terms (``robot.dynamics``), or None.
        kin: ``(xpos, xrot)`` of ``robot.forward_kinematics``, or None.
        motion: the bodies' velocities and bias accelerations (``robot.body_motion``),
            or None.
        domain: the gait's ``walking.Domain`` in walking, else None.
    """

    dyn: robot.Dynamics | None = None
    kin: tuple[jax.Array, jax.Array] | None = None
    motion: robot.BodyMotion | None = None
    domain: Any = None


@dataclasses.dataclass(frozen=True)
class Output:
    """Base: an output of dimension ``dim``; subclasses give ``value``.

    The default Jacobian and drift are taken by forward-mode AD along the configuration
    manifold (``spatial.tangent_jacobian`` and ``spatial.second_derivative_along``).

    Args:
        name: the output's name: its key in ``ControllerParams``' kp, kd and weight
            tables, and in the metrics.
    """

    name: str

    @property
    def dim(self) -> int:
        """The output's dimension."""
        raise NotImplementedError

    @property
    def labels(self) -> tuple[str, ...]:
        """One label per component (``name[i]`` unless a subclass names them)."""
        return tuple(f"{self.name}[{i}]" for i in range(self.dim))

    # components whose maxima over the motion (y and y^d) a run reports, as the metrics
    # "{label}_max_reached" and "{label}_ref_max" (``metrics.finalize``)
    extremes: ClassVar[tuple[int, ...]] = ()

    def value(self, model: robot.RobotModel, q: jax.Array) -> jax.Array:
        """The output y^a(q).

        Args:
            model: the robot model.
            q: (nq,) configuration.

        Returns:
            (dim,) y^a(q).
        """
        raise NotImplementedError

    def evaluate(self, model: robot.RobotModel, q: jax.Array, v: jax.Array,
                 terms: StepTerms | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
        """The output, its Jacobian and its drift at (q, v).

        Outputs that have a closed form from ``terms`` use it; the default takes the AD of
        ``value``.

        Args:
            model: the robot model.
            q: (nq,) configuration.
            v: (nv,) generalized velocity.
            terms: what the control step has computed at (q, v) already, or None.

        Returns:
            ``(y^a, J_y, J_y_dot v)``: (dim,), (dim, nv), (dim,).
        """
        f = lambda qq: self.value(model, qq)  # noqa: E731
        return (f(q), spatial.tangent_jacobian(f, q, model.nv),
                spatial.second_derivative_along(f, q, v))


@dataclasses.dataclass(frozen=True)
class CoMPosition(Output):
    """p_CoM(q) in the world frame (3).

    Args:
        name: the output's name.
    """

    name: str = "com"
    dim = 3
    labels = ("com_x", "com_y", "com_z")

    def value(self, model: robot.RobotModel, q: jax.Array) -> jax.Array:
        """The whole-body centre of mass (``robot.com_position``).

        Args:
            model: the robot model.
            q: (nq,) configuration.

        Returns:
            (dim,) y^a(q).
        """
        return robot.com_position(model, q)

    def evaluate(self, model: robot.RobotModel, q: jax.Array, v: jax.Array,
                 terms: StepTerms | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
        """p_CoM, J_CoM and J_CoM_dot v: ``terms.dyn`` where given, else
        ``robot.dynamics_and_com``.

        Args:
            model: the robot model.
            q: (nq,) configuration.
            v: (nv,) generalized velocity.
            terms: what the control step has computed at (q, v) already, or None.

        Returns:
            ``(y^a, J_y, J_y_dot v)``: (dim,), (dim, nv), (dim,).
        """
        d = (terms.dyn if terms is not None and terms.dyn is not None
             else robot.dynamics_and_com(model, q, v))
        return d.com, d.J_com, d.Jdot_v_com


@dataclasses.dataclass(frozen=True)
class TorsoOrientation(Output):
    """theta_torso(q): base orientation as Euler ZYX angles [roll, pitch, yaw] (3).

    Args:
        name: the output's name.
    """

    name: str = "torso"
    dim = 3
    labels = ("torso_roll", "torso_pitch", "torso_yaw")
    extremes = (1,)       # the pitch: how far the robot bows (paper, eq. 32)

    def value(self, model: robot.RobotModel, q: jax.Array) -> jax.Array:
        """The torso's Euler angles (``robot.torso_euler``).

        Args:
            model: the robot model.
            q: (nq,) configuration.

        Returns:
            (dim,) y^a(q).
        """
        return robot.torso_euler(model, q)

    def evaluate(self, model: robot.RobotModel, q: jax.Array, v: jax.Array,
                 terms: StepTerms | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
        """The torso's Euler angles, Jacobian and drift in closed form
        (``robot.torso_euler_terms``; ``terms`` is not used).

        Args:
            model: the robot model.
            q: (nq,) configuration.
            v: (nv,) generalized velocity.
            terms: what the control step has computed at (q, v) already, or None.

        Returns:
            ``(y^a, J_y, J_y_dot v)``: (dim,), (dim, nv), (dim,).
        """
        return robot.torso_euler_terms(model, q, v)


@dataclasses.dataclass(frozen=True)
class JointPositions(Output):
    """Joint angles q_j of the named hinges (e.g. the 8 arm joints): J_y is a selection
    and J_y_dot v = 0.

    Args:
        joints: the hinges' joint names, in the output's order.
        name: the output's name.
    """

    joints: tuple[str, ...] = ()
    name: str = "joints"

    @property
    def dim(self) -> int:
        """The number of joints."""
        return len(self.joints)

    @property
    def labels(self) -> tuple[str, ...]:
        """The joint names."""
        return self.joints

    def value(self, model: robot.RobotModel, q: jax.Array) -> jax.Array:
        """The joints' angles.

        Args:
            model: the robot model.
            q: (nq,) configuration.

        Returns:
            (dim,) the angles, rad.

        Raises:
            KeyError: a joint name the model does not have.
        """
        return q[np.array([model.joint_qadr(j) for j in self.joints])]

    def evaluate(self, model: robot.RobotModel, q: jax.Array, v: jax.Array,
                 terms: StepTerms | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
        """The joints' angles, their selection Jacobian and a zero drift (``terms`` is
        not used).

        Args:
            model: the robot model.
            q: (nq,) configuration.
            v: (nv,) generalized velocity.
            terms: not used.

        Returns:
            ``(y^a, J_y, J_y_dot v)``: (dim,), (dim, nv), (dim,) zeros.

        Raises:
            KeyError: a joint name the model does not have.
        """
        sel = np.zeros((self.dim, model.nv))
        for i, j in enumerate(self.joints):
            sel[i, model.joint_dadr(j)] = 1.0
        return self.value(model, q), jnp.asarray(sel, q.dtype), jnp.zeros(self.dim, q.dtype)


@dataclasses.dataclass(frozen=True)
class FramePosition(Output):
    """World position of a site (3), e.g. the swing foot's sole.

    Args:
        frame: the site's name.
        name: the output's name.
    """

    frame: str = ""
    name: str = "frame_pos"
    dim = 3

    @property
    def labels(self) -> tuple[str, ...]:
        """``<name>_x``, ``<name>_y``, ``<name>_z``."""
        return tuple(f"{self.name}_{a}" for a in "xyz")

    def value(self, model: robot.RobotModel, q: jax.Array) -> jax.Array:
        """The site's world position (``robot.frame_pose``).

        Args:
            model: the robot model.
            q: (nq,) configuration.

        Returns:
            (dim,) y^a(q).
        """
        return robot.frame_pose(model, q, self.frame)[0]

    def evaluate(self, model: robot.RobotModel, q: jax.Array, v: jax.Array,
                 terms: StepTerms | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
        """The site's position, Jacobian and drift: in closed form from ``terms.kin`` and
        ``terms.motion`` where given (``robot.site_point_terms``), else from the site's
        Jacobian and its forward-mode tangent.

        Args:
            model: the robot model.
            q: (nq,) configuration.
            v: (nv,) generalized velocity.
            terms: what the control step has computed at (q, v) already, or None.

        Returns:
            ``(y^a, J_y, J_y_dot v)``: (dim,), (dim, nv), (dim,).
        """
        if terms is not None and terms.kin is not None and terms.motion is not None:
            # closed form, from this step's kinematics
            return robot.site_point_terms(model, terms.kin, terms.motion, self.frame)
        j, jdv = spatial.with_drift(lambda qq: robot.frame_jacobian(model, qq, self.frame)[:3],
                                    q, v)
        return self.value(model, q), j, jdv


@dataclasses.dataclass(frozen=True)
class FrameOrientation(Output):
    """Orientation of a site as Euler ZYX angles [roll, pitch, yaw] (3), e.g. the swing
    foot kept flat.

    Args:
        frame: the site's name.
        name: the output's name.
    """

    frame: str = ""
    name: str = "frame_rot"
    dim = 3

    @property
    def labels(self) -> tuple[str, ...]:
        """``<name>_roll``, ``<name>_pitch``, ``<name>_yaw``."""
        return tuple(f"{self.name}_{a}" for a in ("roll", "pitch", "yaw"))

    def value(self, model: robot.RobotModel, q: jax.Array) -> jax.Array:
        """The site's Euler ZYX angles.

        Args:
            model: the robot model.
            q: (nq,) configuration.

        Returns:
            (dim,) y^a(q).
        """
        return spatial.euler_zyx(robot.frame_pose(model, q, self.frame)[1])

    def evaluate(self, model: robot.RobotModel, q: jax.Array, v: jax.Array,
                 terms: StepTerms | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
        """The site's Euler angles, Jacobian and drift: in closed form from ``terms.kin``
        and ``terms.motion`` where given (``robot.frame_orientation_terms``), else by AD
        (``Output.evaluate``).

        Args:
            model: the robot model.
            q: (nq,) configuration.
            v: (nv,) generalized velocity.
            terms: what the control step has computed at (q, v) already, or None.

        Returns:
            ``(y^a, J_y, J_y_dot v)``: (dim,), (dim, nv), (dim,).
        """
        if terms is not None and terms.kin is not None and terms.motion is not None:
            # closed form, from this step's kinematics
            return robot.frame_orientation_terms(model, terms.kin, terms.motion, self.frame)
        return super().evaluate(model, q, v, terms)


ARM_JOINTS = tuple(f"{s}-{j}" for s in ("left", "right")
                   for j in ("shoulder-roll", "shoulder-pitch", "shoulder-yaw", "elbow"))
