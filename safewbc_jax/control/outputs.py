"""Task-space outputs y^a(q) with their Jacobian J_y(q) and drift J_y_dot(q, v) v.

Paper, "Task Space Inverse dynamics": y(t, q) = y^a(q) - y^d(t), y_dot = J_y v - y^d_dot,
y_ddot = J_y_dot v + J_y q_ddot - y^d_ddot (eqs. 10-12). Each output is one small object with
the same interface, ``evaluate(model, q, v) -> (y^a, J_y, J_y_dot v)``; a new output is a
new class here, nothing else changes.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from safewbc_jax.model import robot, spatial


class StepTerms(NamedTuple):
    """What a control step has computed at (q, v) already, for the outputs to reuse
    (``controller.robot_terms``): the dynamics and CoM terms, the forward kinematics and
    the body motion (the frame outputs take their closed forms from these), the domain
    (walking's swing outputs). An output computes a field left None itself."""

    dyn: robot.Dynamics | None = None
    kin: tuple | None = None
    motion: robot.BodyMotion | None = None
    domain: Any = None


@dataclasses.dataclass(frozen=True)
class Output:
    """Base: an output of dimension ``dim`` named ``name``; subclasses give ``value``.

    The default Jacobian and drift are taken by forward-mode AD along the configuration
    manifold (``spatial.tangent_jacobian`` and ``spatial.second_derivative_along``)."""

    name: str

    @property
    def dim(self) -> int:
        raise NotImplementedError

    @property
    def labels(self) -> tuple[str, ...]:
        return tuple(f"{self.name}[{i}]" for i in range(self.dim))

    def value(self, model: robot.RobotModel, q):
        raise NotImplementedError

    def evaluate(self, model: robot.RobotModel, q, v, terms: StepTerms | None = None):
        """(y^a, J_y, J_y_dot v). ``terms``: the ``StepTerms`` already computed at this
        (q, v), or None (outputs that can reuse them do)."""
        f = lambda qq: self.value(model, qq)  # noqa: E731
        return (f(q), spatial.tangent_jacobian(f, q, model.nv),
                spatial.second_derivative_along(f, q, v))


@dataclasses.dataclass(frozen=True)
class CoMPosition(Output):
    """p_CoM(q) in the world frame (3)."""

    name: str = "com"
    dim = 3
    labels = ("com_x", "com_y", "com_z")

    def value(self, model, q):
        return robot.com_position(model, q)

    def evaluate(self, model, q, v, terms=None):
        d = (terms.dyn if terms is not None and terms.dyn is not None
             else robot.dynamics_and_com(model, q, v))
        return d.com, d.J_com, d.Jdot_v_com


@dataclasses.dataclass(frozen=True)
class TorsoOrientation(Output):
    """theta_torso(q): base orientation as Euler ZYX angles [roll, pitch, yaw] (3)."""

    name: str = "torso"
    dim = 3
    labels = ("torso_roll", "torso_pitch", "torso_yaw")

    def value(self, model, q):
        return robot.torso_euler(model, q)

    def evaluate(self, model, q, v, terms=None):
        return robot.torso_euler_terms(model, q, v)


@dataclasses.dataclass(frozen=True)
class JointPositions(Output):
    """Joint angles q_j of the named hinges (e.g. the 8 arm joints): J_y is a selection
    and J_y_dot v = 0."""

    joints: tuple[str, ...] = ()
    name: str = "joints"

    @property
    def dim(self):
        return len(self.joints)

    @property
    def labels(self):
        return self.joints

    def value(self, model, q):
        return q[np.array([model.joint_qadr(j) for j in self.joints])]

    def evaluate(self, model, q, v, terms=None):
        sel = np.zeros((self.dim, model.nv))
        for i, j in enumerate(self.joints):
            sel[i, model.joint_dadr(j)] = 1.0
        return self.value(model, q), jnp.asarray(sel, q.dtype), jnp.zeros(self.dim, q.dtype)


@dataclasses.dataclass(frozen=True)
class FramePosition(Output):
    """World position of a site (3), e.g. the swing foot's sole."""

    frame: str = ""
    name: str = "frame_pos"
    dim = 3

    @property
    def labels(self):
        return tuple(f"{self.name}_{a}" for a in "xyz")

    def value(self, model, q):
        return robot.frame_pose(model, q, self.frame)[0]

    def evaluate(self, model, q, v, terms=None):
        if terms is not None and terms.motion is not None:   # closed form, this step's
            return robot.site_point_terms(model, terms.kin, terms.motion, self.frame)
        j, jdv = spatial.with_drift(lambda qq: robot.frame_jacobian(model, qq, self.frame)[:3],
                                    q, v)
        return self.value(model, q), j, jdv


@dataclasses.dataclass(frozen=True)
class FrameOrientation(Output):
    """Orientation of a site as Euler ZYX angles [roll, pitch, yaw] (3), e.g. the swing
    foot kept flat."""

    frame: str = ""
    name: str = "frame_rot"
    dim = 3

    @property
    def labels(self):
        return tuple(f"{self.name}_{a}" for a in ("roll", "pitch", "yaw"))

    def value(self, model, q):
        return spatial.euler_zyx(robot.frame_pose(model, q, self.frame)[1])

    def evaluate(self, model, q, v, terms=None):
        if terms is not None and terms.motion is not None:   # closed form, this step's
            return robot.frame_orientation_terms(model, terms.kin, terms.motion, self.frame)
        return super().evaluate(model, q, v, terms)


ARM_JOINTS = tuple(f"{s}-{j}" for s in ("left", "right")
                   for j in ("shoulder-roll", "shoulder-pitch", "shoulder-yaw", "elbow"))
