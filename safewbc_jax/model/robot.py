"""Robot terms of the controller model as pure JAX functions.

The controller model is Digit's floating base plus its 30 hinges (36 DoF), rods left out
(``models/digit_controller.xml``). Its equations of motion are the paper's eq. 1,

    M(q) q_ddot + C(q, v) v + G(q) = B u + J(q)^T lambda,

with q in MuJoCo's layout (nq = 37: base position, base quaternion, 30 hinge angles) and
v, q_ddot in its tangent space (nv = 36). ``h(q, v) = C(q, v) v + G(q)``.

Everything here takes a :class:`RobotModel` (a pytree of arrays with its tree structure as
static metadata) and plain arrays, so it jit-compiles and vmaps; the model's arrays can be
batched too (for example to sweep a mass).

M and h follow the tree's structure (``dynamics``): each dof's subtree is one composite
rigid body about the world origin (the subtree sums are one product with a static 0/1
matrix, not a pass level by level), M[i, j] = S_i . I^c_j S_j where dof i moves dof j's
body and zero elsewhere (the composite rigid-body algorithm), and h_k = S_k . F^c_k with
F^c_k the subtree's Newton-Euler forces at the bias accelerations (the recursive
Newton-Euler algorithm's backward pass). The body velocities and bias accelerations come
in closed form from the per-dof axes (``body_motion``); the drift terms J_dot v of frames
follow from them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from functools import partial
from typing import TYPE_CHECKING, Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.model import spatial

if TYPE_CHECKING:
    from jax.typing import ArrayLike, DTypeLike

FREE, HINGE, FIXED = 0, 1, 2


@partial(jax.tree_util.register_dataclass,
         data_fields=["body_pos", "body_rot", "body_ipos", "body_irot", "body_mass",
                      "body_inertia", "jnt_axis", "armature", "gravity", "site_pos",
                      "site_rot", "B", "gear", "torque_limit", "ancestor_dof", "rod_length"],
         meta_fields=["body_names", "body_parent", "body_jtype", "body_qadr", "body_dadr",
                      "site_names", "site_body", "joint_names", "actuator_names",
                      "actuator_dof", "rod_names", "rod_sites", "spring_dofs", "nq", "nv",
                     "nu"])
@dataclasses.dataclass(frozen=True)
class RobotModel:
    """Kinematic tree and inertias of the controller model (world body excluded).

    Arrays (leaves): per body its frame in the parent at q = 0 (``body_pos``,
    ``body_rot``), its centre of mass and principal inertia frame (``body_ipos``,
    ``body_irot``), ``body_mass``, principal ``body_inertia``; ``jnt_axis`` (hinge axis in
    the body frame); ``armature`` per dof; sites; the actuation matrix ``B`` (nv x nu,
    joint torques u), ``gear`` and joint ``torque_limit`` (N m) per actuator;
    ``ancestor_dof[b, k]`` is 1 where dof k moves body b.

    Closed chains (the paper's n_kc, eq. 29): each rod left out of the tree is the pair of sites
    ``<rod>-anchor`` / ``<rod>-ball`` (``rod_sites``) held ``rod_length`` apart (their
    distance in the zero configuration, where every published loop closes); each spring
    joint (``spring_dofs``) is held at 0."""

    body_pos: jax.Array
    body_rot: jax.Array
    body_ipos: jax.Array
    body_irot: jax.Array
    body_mass: jax.Array
    body_inertia: jax.Array
    jnt_axis: jax.Array
    armature: jax.Array
    gravity: jax.Array
    site_pos: jax.Array
    site_rot: jax.Array
    B: jax.Array
    gear: jax.Array
    torque_limit: jax.Array
    ancestor_dof: jax.Array
    rod_length: jax.Array
    body_names: tuple
    body_parent: tuple
    body_jtype: tuple
    body_qadr: tuple
    body_dadr: tuple
    site_names: tuple
    site_body: tuple
    joint_names: tuple
    actuator_names: tuple
    actuator_dof: tuple
    rod_names: tuple
    rod_sites: tuple
    spring_dofs: tuple
    nq: int
    nv: int
    nu: int

    def body_id(self, name: str) -> int:
        """The index of a body (world body excluded).

        Args:
            name: the body's name in the MJCF model.

        Returns:
            Its row in the per-body arrays.

        Raises:
            ValueError: no body has that name.
        """
        return self.body_names.index(name)

    def site_id(self, name: str) -> int:
        """The index of a site.

        Args:
            name: the site's name in the MJCF model (e.g. ``left-sole``).

        Returns:
            Its row in the per-site arrays.

        Raises:
            KeyError: no site has that name; the message lists the sites.
        """
        if name not in self.site_names:
            raise KeyError(f"unknown frame {name!r}; sites are {self.site_names}")
        return self.site_names.index(name)

    def joint_qadr(self, name: str) -> int:
        """The qpos index of a hinge.

        Args:
            name: the joint's name in the MJCF model.

        Returns:
            Its index in q.

        Raises:
            KeyError: no joint has that name.
        """
        if name not in self.joint_names:
            raise KeyError(f"unknown joint {name!r}")
        return self.body_qadr[self.joint_names.index(name)]

    def joint_dadr(self, name: str) -> int:
        """The qvel index of a hinge.

        Args:
            name: the joint's name in the MJCF model.

        Returns:
            Its index in v (and in q_ddot, and a column of the Jacobians).

        Raises:
            KeyError: no joint has that name.
        """
        if name not in self.joint_names:
            raise KeyError(f"unknown joint {name!r}")
        return self.body_dadr[self.joint_names.index(name)]

    @property
    def total_mass(self) -> jax.Array:
        """The sum of the bodies' masses, kg."""
        return jnp.sum(self.body_mass)


def _mat(quat) -> np.ndarray:
    import mujoco

    out = np.zeros(9)
    mujoco.mju_quat2Mat(out, np.asarray(quat, float))
    return out.reshape(3, 3)


SPRING_SUFFIXES = ("-shin", "-heel-spring")


def from_mujoco(m: Any, dtype: DTypeLike = jnp.float64,
                spring_suffixes: Sequence[str] = SPRING_SUFFIXES) -> RobotModel:
    """Build the JAX model from a compiled MuJoCo model of a floating-base hinge tree.

    Rods are found as site pairs ``<rod>-anchor`` / ``<rod>-ball``, their lengths
    measured in ``m``'s ``qpos0``.

    Args:
        m: the ``mujoco.MjModel``: a free joint on its first body (a child of the world),
            at most one hinge (at the body's origin) on every other body, joint
            actuators only (e.g. ``models/digit_controller.xml``).
        dtype: the dtype of the model's arrays; float64 (the default) needs JAX's 64-bit
            floats (``safewbc_jax.enable_x64``).
        spring_suffixes: name suffixes of the spring joints, held at 0 as closed-chain
            constraints.

    Returns:
        The model.

    Raises:
        RuntimeError: ``dtype`` is float64 and JAX's 64-bit floats are off.
        ValueError: ``m`` is not such a tree (the message names the body, joint, actuator
            or site), or a ``<rod>-anchor`` site has no ``<rod>-ball``.
    """
    import mujoco

    if jnp.dtype(dtype) == jnp.float64:
        from safewbc_jax.base.runtime import require_x64

        require_x64("the controller model (robot.from_mujoco)")

    nb = m.nbody - 1
    jtype: list[int] = []
    qadr: list[int] = []
    dadr: list[int] = []
    jnames: list[str | None] = []
    axis = np.zeros((nb, 3))
    for b in range(1, m.nbody):
        n = m.body_jntnum[b]
        if n == 0:
            jtype.append(FIXED)
            qadr.append(-1)
            dadr.append(-1)
            jnames.append(None)
            continue
        if n > 1:
            raise ValueError(f"body {m.body(b).name!r} has {n} joints; one at most is supported")
        j = m.body_jntadr[b]
        t = m.jnt_type[j]
        if t == mujoco.mjtJoint.mjJNT_FREE:
            if b != 1 or m.body_parentid[b] != 0:
                raise ValueError("the free joint must be on the first body, a child of the world")
            jtype.append(FREE)
        elif t == mujoco.mjtJoint.mjJNT_HINGE:
            jtype.append(HINGE)
            axis[b - 1] = m.jnt_axis[j]
            if np.linalg.norm(m.jnt_pos[j]) > 0:
                raise ValueError(f"joint {m.joint(j).name!r} is not at its body's origin")
        else:
            raise ValueError(f"joint {m.joint(j).name!r}: only free and hinge joints are supported"
                             " in the controller model (leave the rods out)")
        qadr.append(int(m.jnt_qposadr[j]))
        dadr.append(int(m.jnt_dofadr[j]))
        jnames.append(m.joint(j).name)
    if jtype[0] != FREE:
        raise ValueError("the controller model needs a free joint on its first body")
    parent = tuple(int(m.body_parentid[b]) - 1 for b in range(1, m.nbody))
    anc = np.zeros((nb, m.nv))
    for b in range(nb):
        c = b
        while c >= 0:
            if jtype[c] == FREE:
                anc[b, dadr[c]:dadr[c] + 6] = 1
            elif jtype[c] == HINGE:
                anc[b, dadr[c]] = 1
            c = parent[c]
    B = np.zeros((m.nv, m.nu))
    act_dof = []
    for a in range(m.nu):
        if m.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
            raise ValueError(f"actuator {m.actuator(a).name!r} is not a joint actuator")
        k = int(m.jnt_dofadr[m.actuator_trnid[a, 0]])
        B[k, a] = 1.0
        act_dof.append(k)
    gear = m.actuator_gear[:, 0].copy()
    torque_limit = gear * np.abs(m.actuator_ctrlrange).max(axis=1)
    site_names = [m.site(i).name for i in range(m.nsite)]
    rods = [n[:-len("-anchor")] for n in site_names if n.endswith("-anchor")]
    rods = sorted(rods, key=lambda r: (not r.startswith("left"), site_names.index(r + "-anchor")))
    rod_sites = []
    for r in rods:
        if r + "-ball" not in site_names:
            raise ValueError(f"site {r}-anchor has no matching {r}-ball")
        rod_sites.append((site_names.index(r + "-anchor"), site_names.index(r + "-ball")))
    d0 = mujoco.MjData(m)
    d0.qpos[:] = m.qpos0
    mujoco.mj_kinematics(m, d0)
    rod_length = np.array([np.linalg.norm(d0.site_xpos[a] - d0.site_xpos[b]) for a, b in rod_sites])
    springs = tuple(dadr[i] for i, n in enumerate(jnames)
                    if n is not None and n.endswith(tuple(spring_suffixes)))
    f = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    return RobotModel(
        body_pos=f(m.body_pos[1:]), body_rot=f(np.stack([_mat(q) for q in m.body_quat[1:]])),
        body_ipos=f(m.body_ipos[1:]), body_irot=f(np.stack([_mat(q) for q in m.body_iquat[1:]])),
        body_mass=f(m.body_mass[1:]), body_inertia=f(m.body_inertia[1:]), jnt_axis=f(axis),
        armature=f(m.dof_armature), gravity=f(m.opt.gravity),
        site_pos=f(m.site_pos), site_rot=f(np.stack([_mat(q) for q in m.site_quat])),
        B=f(B), gear=f(gear), torque_limit=f(torque_limit), ancestor_dof=f(anc),
        rod_length=f(rod_length), rod_names=tuple(rods), rod_sites=tuple(rod_sites),
        spring_dofs=springs,
        body_names=tuple(m.body(b).name for b in range(1, m.nbody)), body_parent=parent,
        body_jtype=tuple(jtype), body_qadr=tuple(qadr), body_dadr=tuple(dadr),
        site_names=tuple(site_names),
        site_body=tuple(int(m.site_bodyid[s]) - 1 for s in range(m.nsite)),
        joint_names=tuple(jnames), actuator_names=tuple(m.actuator(a).name for a in range(m.nu)),
        actuator_dof=tuple(act_dof), nq=int(m.nq), nv=int(m.nv), nu=int(m.nu))


# --------------------------------------------------------------------------------------
# Kinematics
# --------------------------------------------------------------------------------------

def _hinges(model: RobotModel):
    """Body indices of the hinge joints and their dof and qpos addresses (static)."""
    hb = [b for b, t in enumerate(model.body_jtype) if t == HINGE]
    return (np.array(hb), np.array([model.body_dadr[b] for b in hb]),
            np.array([model.body_qadr[b] for b in hb]))


def _axis_angle_batch(axes, angles):
    """Rodrigues for a batch of unit axes [n, 3] and angles [n]."""
    x, y, z = axes[:, 0], axes[:, 1], axes[:, 2]
    zero = jnp.zeros_like(x)
    k = jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1),
                   jnp.stack([-y, x, zero], -1)], -2)
    s, c = jnp.sin(angles)[:, None, None], jnp.cos(angles)[:, None, None]
    return jnp.eye(3, dtype=axes.dtype) + s * k + (1.0 - c) * (k @ k)


def _paths(model: RobotModel):
    """Per body, the bodies below the root on its path from the root, root side first,
    padded at the end with the index nb (an identity transform) to the tree's depth
    (static [nb, depth])."""
    nb = len(model.body_names)
    paths = []
    for b in range(nb):
        path, c = [], b
        while model.body_parent[c] >= 0:
            path.append(c)
            c = model.body_parent[c]
        paths.append(path[::-1])
    depth = max(1, max(len(p) for p in paths))
    return np.array([p + [nb] * (depth - len(p)) for p in paths])


def _mat3(a, b):
    """Batched 3 x 3 products written as sums of elementwise products (XLA fuses chains
    of them into a few kernels, where a dot is one kernel each)."""
    return (a[..., :, 0:1] * b[..., 0:1, :] + a[..., :, 1:2] * b[..., 1:2, :]
            + a[..., :, 2:3] * b[..., 2:3, :])


def _matvec3(a, x):
    return a[..., :, 0] * x[..., 0:1] + a[..., :, 1] * x[..., 1:2] + a[..., :, 2] * x[..., 2:3]


def _kinematics_of(model: RobotModel, q, bodies):
    """World position and rotation of the given body frames (static indices)."""
    nb = len(model.body_names)
    if model.body_jtype[0] != FREE or model.body_parent[0] != -1:
        raise ValueError("the first body must carry the free joint")
    hb, _, hq = _hinges(model)
    # a static-index gather (bodies without a hinge read the appended 0), not a scatter
    slot = np.full(nb, len(hb))
    slot[hb] = np.arange(len(hb))
    angles = jnp.concatenate([q[hq], jnp.zeros(1, q.dtype)])[slot]
    local = model.body_rot @ _axis_angle_batch(model.jnt_axis, angles)  # fixed: axis 0 -> I
    local = jnp.concatenate([local, jnp.eye(3, dtype=q.dtype)[None]], axis=0)
    offset = jnp.concatenate([model.body_pos, jnp.zeros((1, 3), q.dtype)], axis=0)
    paths = _paths(model)[np.asarray(bodies)]
    rot_path, pos_path = local[paths], offset[paths]  # [n, depth, 3, 3], [n, depth, 3]
    n = paths.shape[0]
    xrot = jnp.broadcast_to(spatial.quat_to_mat(q[3:7]), (n, 3, 3))
    xpos = jnp.broadcast_to(q[0:3], (n, 3))
    if n == 1:      # one frame: its own path only, no padding, a product per joint
        xr, xp = xrot[0], xpos[0]
        for k in range(int((paths[0] < nb).sum())):
            xp = xp + xr @ pos_path[0, k]
            xr = xr @ rot_path[0, k]
        return xp[None], xr[None]
    for k in range(paths.shape[1]):
        xpos = xpos + _matvec3(xrot, pos_path[:, k])
        xrot = _mat3(xrot, rot_path[:, k])
    return xpos, xrot


def forward_kinematics(model: RobotModel, q: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World position and rotation of every body frame.

    Every body composes the transforms along its own path from the root, all bodies at
    once and depth by depth (the paths are padded with identities), written as
    elementwise products that XLA fuses into a few kernels. The products are the same, in
    the same order, as composing parent then child.

    Args:
        model: the robot model.
        q: (nq,) configuration.

    Returns:
        ``(xpos, xrot)``: positions [nb, 3] and rotation matrices [nb, 3, 3], world frame;
            the ``kin`` argument of the closed-form functions below.
    """
    return _kinematics_of(model, q, np.arange(len(model.body_names)))


def _dof_motion(model: RobotModel, xpos, xrot):
    """Per dof: world rotation axis w_k (zero for translations), anchor point o_k, and
    translation direction t_k (zero for rotations). A point x of a body moved by dof k
    gets velocity w_k x (x - o_k) + t_k per unit of v_k."""
    hb, hd, _ = _hinges(model)
    k0 = model.body_dadr[0]
    # rows gathered with static indices from [0; free joint's 3 rows; hinges' rows]: dofs
    # of neither kind (the free joint's translations) read the leading zero row
    slot = np.zeros(model.nv, int)
    slot[k0 + 3:k0 + 6] = 1 + np.arange(3)
    slot[hd] = 4 + np.arange(len(hd))
    zero = jnp.zeros((1, 3), xpos.dtype)
    # free joint: its rotation axes are the base's body-frame axes (MuJoCo's convention)
    w = jnp.concatenate([zero, xrot[0].T,
                         jnp.einsum("nij,nj->ni", xrot[hb], model.jnt_axis[hb])])[slot]
    o = jnp.concatenate([zero, jnp.broadcast_to(xpos[0], (3, 3)), xpos[hb]])[slot]
    t = np.zeros((model.nv, 3))
    t[k0:k0 + 3] = np.eye(3)
    return w, o, jnp.asarray(t, xpos.dtype)


def point_jacobians(model: RobotModel, xpos: jax.Array, xrot: jax.Array,
                    bodies: ArrayLike, points: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Linear and angular Jacobians of world points rigidly attached to bodies.

    Args:
        model: the robot model.
        xpos: [nb, 3] body positions (``forward_kinematics``).
        xrot: [nb, 3, 3] body rotations (``forward_kinematics``).
        bodies: (n,) the body index of each point.
        points: [n, 3] the points, world frame.

    Returns:
        ``(J_p, J_r)``: [n, 3, nv] each, the points' linear velocities and their bodies'
            angular velocities (world frame) per unit of v.
    """
    w, o, t = _dof_motion(model, xpos, xrot)
    mask = model.ancestor_dof[jnp.asarray(bodies)]  # [n, nv]
    lin = jnp.cross(w[None], points[:, None, :] - o[None]) + t[None]  # [n, nv, 3]
    jp = jnp.swapaxes(lin * mask[..., None], 1, 2)
    jr = jnp.swapaxes(w[None] * mask[..., None], 1, 2)
    return jp, jr


def body_com(model: RobotModel, xpos: jax.Array,
             xrot: jax.Array) -> tuple[jax.Array, jax.Array]:
    """World centre of mass of every body and the rotation of its principal axes.

    Args:
        model: the robot model.
        xpos: [nb, 3] body positions (``forward_kinematics``).
        xrot: [nb, 3, 3] body rotations (``forward_kinematics``).

    Returns:
        ``(com, irot)``: [nb, 3] centres of mass and [nb, 3, 3] principal-axis
            rotations, world frame.
    """
    com = xpos + jnp.einsum("bij,bj->bi", xrot, model.body_ipos)
    irot = xrot @ model.body_irot
    return com, irot


def _dof_bodies(model: RobotModel) -> np.ndarray:
    """The body each dof moves with its own joint (static): the free joint's six dofs
    belong to the root body, a hinge's dof to the hinge's body."""
    out = np.zeros(model.nv, dtype=int)
    for b, (t, d) in enumerate(zip(model.body_jtype, model.body_dadr)):
        if t == FREE:
            out[d:d + 6] = b
        elif t == HINGE:
            out[d] = b
    return out


class BodyMotion(NamedTuple):
    """Velocity and bias acceleration of every body, as world-frame twists about the
    world origin [nb, 3] each: a point x fixed on body b moves with

        x_dot = omega_b x x + c_b,      J_p_dot v = alpha_b x x + gamma_b + omega_b x x_dot,

    and J_r_dot v = alpha_b (the bias terms: q_ddot = 0).

    Attributes:
        omega: [nb, 3] angular velocities.
        c: [nb, 3] velocity of the point of each body at the world origin.
        alpha: [nb, 3] angular bias accelerations.
        gamma: [nb, 3] bias acceleration of the point of each body at the world origin,
            less omega x c.
    """

    omega: jax.Array
    c: jax.Array
    alpha: jax.Array
    gamma: jax.Array

    def _of(self, field, bodies):
        return field if bodies is None else field[bodies]

    def point_velocity(self, bodies: ArrayLike | None, x: jax.Array) -> jax.Array:
        """Velocities of points fixed on bodies.

        Args:
            bodies: (n,) the body index of each point; None: one point per body, in
                body order.
            x: [n, 3] the points, world frame.

        Returns:
            [n, 3] their velocities, world frame.
        """
        return jnp.cross(self._of(self.omega, bodies), x) + self._of(self.c, bodies)

    def point_bias(self, bodies: ArrayLike | None, x: jax.Array,
                   xdot: jax.Array | None = None) -> jax.Array:
        """Bias accelerations J_p_dot v of points fixed on bodies.

        Args:
            bodies: (n,) the body index of each point; None: one point per body, in
                body order.
            x: [n, 3] the points, world frame.
            xdot: [n, 3] their velocities where already computed (``point_velocity``);
                None: computed here.

        Returns:
            [n, 3] their accelerations at q_ddot = 0, world frame.
        """
        w = self._of(self.omega, bodies)
        xdot = self.point_velocity(bodies, x) if xdot is None else xdot
        return (jnp.cross(self._of(self.alpha, bodies), x) + self._of(self.gamma, bodies)
                + jnp.cross(w, xdot))


def body_motion(model: RobotModel, kin: tuple[jax.Array, jax.Array],
                v: jax.Array) -> BodyMotion:
    """Body velocities and the drift (bias) accelerations of every body in closed form.

    With the per-dof motion of ``_dof_motion`` (axis w_k, anchor o_k, translation t_k),
    a point x of body b has J_p v = sum_k m_bk (w_k x (x - o_k) + t_k) v_k, m the
    ancestor mask. Along the motion with v held fixed, the axis of dof k turns with its
    body, w_k_dot = omega_(b(k)) x w_k, and its anchor moves with that body's origin,
    o_k_dot = omega_(b(k)) x o_k + c_(b(k)); t_k is fixed. Differentiating J_p v gives

        J_p_dot v = sum_k m_bk v_k (w_k_dot x (x - o_k) + w_k x (x_dot - o_k_dot))
                  = alpha_b x x + omega_b x x_dot + gamma_b,
        alpha_b = sum_k m_bk v_k w_k_dot,
        gamma_b = -sum_k m_bk v_k (w_k_dot x o_k + w_k x o_k_dot),

    two products with the mask instead of a forward-mode tangent of the kinematics.

    Args:
        model: the robot model.
        kin: ``(xpos, xrot)`` of ``forward_kinematics`` at q.
        v: (nv,) generalized velocity.

    Returns:
        Every body's velocity and bias acceleration.
    """
    xpos, xrot = kin
    w, o, t = _dof_motion(model, xpos, xrot)
    mask = model.ancestor_dof
    vv = v[:, None]
    vel = mask @ jnp.concatenate([w * vv, _spatial_axes(w, o, t)[1] * vv], axis=1)  # [nb, 6]
    omega, c = vel[:, :3], vel[:, 3:]
    db = _dof_bodies(model)
    wdot = jnp.cross(omega[db], w)
    odot = jnp.cross(omega[db], o) + c[db]
    acc = mask @ jnp.concatenate([wdot * vv, -(jnp.cross(wdot, o) + jnp.cross(w, odot)) * vv],
                                 axis=1)
    return BodyMotion(omega=omega, c=c, alpha=acc[:, :3], gamma=acc[:, 3:])


def _com_jacobians(model: RobotModel, q):
    xpos, xrot = forward_kinematics(model, q)
    com, irot = body_com(model, xpos, xrot)
    jp, jr = point_jacobians(model, xpos, xrot, np.arange(len(model.body_names)), com)
    return jp, jr, irot


def com_jacobians(model: RobotModel, kin: tuple[jax.Array, jax.Array],
                  ) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    """Per body, the Jacobians of its centre of mass.

    Args:
        model: the robot model.
        kin: ``(xpos, xrot)`` of ``forward_kinematics``.

    Returns:
        ``(J_p, J_r, irot, com)``: linear and angular Jacobians of each body's centre of
            mass [nb, 3, nv], its principal-axis rotation [nb, 3, 3] and its centre of
            mass [nb, 3], world frame.
    """
    xpos, xrot = kin
    com, irot = body_com(model, xpos, xrot)
    jp, jr = point_jacobians(model, xpos, xrot, np.arange(len(model.body_names)), com)
    return jp, jr, irot, com


class Dynamics(NamedTuple):
    """The equations of motion's terms and the centre of mass's at one state.

    Attributes:
        M: (nv, nv) mass matrix M(q), armature on the diagonal.
        h: (nv,) h(q, v) = C(q, v) v + G(q).
        com: (3,) whole-body centre of mass p_CoM, world frame.
        J_com: (3, nv) its Jacobian J_CoM.
        Jdot_v_com: (3,) its drift J_CoM_dot v.
    """

    M: jax.Array
    h: jax.Array
    com: jax.Array
    J_com: jax.Array
    Jdot_v_com: jax.Array


def _subtrees(model: RobotModel) -> np.ndarray:
    """Static [nb, nb]: 1 where body d is in the subtree of body b (b itself included)."""
    nb = len(model.body_names)
    out = np.zeros((nb, nb))
    for d in range(nb):
        c = d
        while c >= 0:
            out[c, d] = 1.0
            c = model.body_parent[c]
    return out


def _dof_ancestry(model: RobotModel) -> np.ndarray:
    """Static [nv, nv] bool: [i, j] where dof i moves the body of dof j (dof j's body is in
    the subtree of dof i's, the same body for dofs of one joint): M[i, j] is not zero by
    structure only there and at [j, i]."""
    own = _dof_bodies(model)
    return _subtrees(model)[np.ix_(own, own)] > 0


def _spatial_axes(w, o, t):
    """Per dof, the world-frame motion axis about the world origin: angular part w_k and
    the velocity of the point at the origin, t_k - w_k x o_k (``_dof_motion``)."""
    return w, t - jnp.cross(w, o)


_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def _composite(model: RobotModel, kin, motion: BodyMotion | None):
    """Composite rigid bodies about the world origin, one per dof (its body's subtree).

    Each body's spatial inertia about the origin is (m, m c, I_o) with I_o = I_c +
    m (|c|^2 1 - c c^T); its Newton-Euler force (when ``motion`` is given) is f = m (a -
    g) on its CoM acceleration bias a (q_ddot = 0) and n = c x f + I_c alpha + omega x
    I_c omega about the origin. A composite is the sum of these over the body's subtree:
    one product with the static subtree matrix, no pass level by level. Returns (per
    dof: m, m c [3], I_o [6: xx yy zz xy xz yz], and where ``motion`` is given n [3],
    f [3]; the bodies' CoMs [nb, 3]; their CoM bias accelerations [nb, 3] or None)."""
    xpos, xrot = kin
    com, irot = body_com(model, xpos, xrot)
    iworld = jnp.einsum("bij,bj,bkj->bik", irot, model.body_inertia, irot)
    m = model.body_mass
    mc = m[:, None] * com
    io = iworld + (m * jnp.sum(com * com, axis=1))[:, None, None] * jnp.eye(3, dtype=com.dtype) \
        - mc[:, :, None] * com[:, None, :]
    cols = [m[:, None], mc, jnp.stack([io[:, i, j] for i, j in _SYM], axis=1)]
    acc = None
    if motion is not None:
        w = motion.omega
        acc = motion.point_bias(None, com)
        force = m[:, None] * (acc - model.gravity[None])
        torque = (_matvec3(iworld, motion.alpha) + jnp.cross(w, _matvec3(iworld, w))
                  + jnp.cross(com, force))
        cols += [torque, force]
    sub = _subtrees(model)[_dof_bodies(model)]                  # [nv, nb], static
    return jnp.asarray(sub, com.dtype) @ jnp.concatenate(cols, axis=1), com, acc


def _joint_space(model: RobotModel, kin, comp):
    """M (armature on the diagonal) and the CoM Jacobian from the per-dof composites:
    with S_k = [w_k; v0_k] (``_spatial_axes``) and F_k = I^c_k S_k = [I_o w + (m c) x v0;
    m v0 + w x (m c)], M[i, j] = S_i . F_j where dof i moves dof j's body (the composite
    rigid-body algorithm's entries, Featherstone 2008, ch. 6), zero elsewhere by
    structure; column k of m_tot J_CoM is F_k's linear part. Also returns the axes."""
    xpos, xrot = kin
    w, v0 = _spatial_axes(*_dof_motion(model, xpos, xrot))
    m, h = comp[:, 0:1], comp[:, 1:4]
    ixx, iyy, izz, ixy, ixz, iyz = (comp[:, 4 + i] for i in range(6))
    iw = jnp.stack([ixx * w[:, 0] + ixy * w[:, 1] + ixz * w[:, 2],
                    ixy * w[:, 0] + iyy * w[:, 1] + iyz * w[:, 2],
                    ixz * w[:, 0] + iyz * w[:, 1] + izz * w[:, 2]], axis=1)
    f_lin = m * v0 + jnp.cross(w, h)
    force = jnp.concatenate([iw + jnp.cross(h, v0), f_lin], axis=1)     # F_k [nv, 6]
    p = jnp.concatenate([w, v0], axis=1) @ force.T                      # [i, j] = S_i . F_j
    # the upper triangle's structural nonzeros (dofs of one joint give both [i, j] and
    # [j, i]: the upper one is taken, so that M is exactly symmetric)
    anc = _dof_ancestry(model) & np.triu(np.ones((model.nv, model.nv), bool))
    mass = jnp.where(anc, p, jnp.where(anc.T, p.T, 0.0)) + jnp.diag(model.armature)
    return mass, f_lin, (w, v0)


def mass_matrix(model: RobotModel, q: jax.Array) -> jax.Array:
    """The mass matrix by composite rigid bodies (``_joint_space``).

    Args:
        model: the robot model.
        q: (nq,) configuration.

    Returns:
        (nv, nv) M(q), armature (reflected rotor inertia) on the diagonal.
    """
    kin = forward_kinematics(model, q)
    comp, _, _ = _composite(model, kin, None)
    return _joint_space(model, kin, comp)[0]


def dynamics(model: RobotModel, kin: tuple[jax.Array, jax.Array],
             motion: BodyMotion) -> Dynamics:
    """M, h and the CoM terms at one state, from its forward kinematics ``kin`` and body
    motion (``body_motion``), by composite rigid bodies about the world origin
    (``_composite``): M's entries are S_i . I^c S_j (``_joint_space``), and h (the paper's
    C(q, v) v + G(q) of eq. 1) is h_k = S_k . F^c_k, the spatial Newton-Euler forces of the
    subtree that dof k carries (the recursive Newton-Euler algorithm's backward pass,
    as one product). Equal to the virtual-work sum over the bodies' CoM Jacobians,
    sum_b J_b^T (m_b (a_b - g), I_b alpha_b + omega_b x I_b omega_b).

    Args:
        model: the robot model.
        kin: ``(xpos, xrot)`` of ``forward_kinematics`` at q.
        motion: ``body_motion`` at (q, v).

    Returns:
        M, h and the CoM terms.
    """
    comp, com, acc = _composite(model, kin, motion)
    mass, f_lin, (w, v0) = _joint_space(model, kin, comp)
    h = jnp.sum(w * comp[:, 10:13] + v0 * comp[:, 13:16], axis=1)
    mtot = jnp.sum(model.body_mass)
    return Dynamics(M=mass, h=h, com=model.body_mass @ com / mtot, J_com=f_lin.T / mtot,
                    Jdot_v_com=model.body_mass @ acc / mtot)


def bias_forces(model: RobotModel, q: jax.Array, v: jax.Array) -> jax.Array:
    """Coriolis, centrifugal and gravity forces.

    Args:
        model: the robot model.
        q: (nq,) configuration.
        v: (nv,) generalized velocity.

    Returns:
        (nv,) h(q, v) = C(q, v) v + G(q).
    """
    return dynamics_and_com(model, q, v).h


def dynamics_and_com(model: RobotModel, q: jax.Array, v: jax.Array) -> Dynamics:
    """M(q), h(q, v), p_CoM, J_CoM and J_CoM_dot v (``dynamics``) from q and v.

    Args:
        model: the robot model.
        q: (nq,) configuration.
        v: (nv,) generalized velocity.

    Returns:
        M, h and the CoM terms.
    """
    kin = forward_kinematics(model, q)
    return dynamics(model, kin, body_motion(model, kin, v))


# --------------------------------------------------------------------------------------
# Frames, CoM, torso orientation
# --------------------------------------------------------------------------------------

def frame_pose(model: RobotModel, q: jax.Array, frame: str) -> tuple[jax.Array, jax.Array]:
    """World position and rotation matrix of a named site.

    Args:
        model: the robot model.
        q: (nq,) configuration.
        frame: the site's name (e.g. ``left-sole``).

    Returns:
        ``(p, R)``: (3,) position and (3, 3) rotation matrix, world frame.

    Raises:
        KeyError: no site has that name.
    """
    s = model.site_id(frame)
    b = model.site_body[s]
    xpos, xrot = _kinematics_of(model, q, np.array([b]))  # only the body's own path
    return xpos[0] + xrot[0] @ model.site_pos[s], xrot[0] @ model.site_rot[s]


def frame_jacobian(model: RobotModel, q: jax.Array, frame: str) -> jax.Array:
    """6D Jacobian of a site.

    Args:
        model: the robot model.
        q: (nq,) configuration.
        frame: the site's name.

    Returns:
        (6, nv) rows [linear velocity of its origin; angular velocity], both in the world
            frame.

    Raises:
        KeyError: no site has that name.
    """
    s = model.site_id(frame)
    xpos, xrot = forward_kinematics(model, q)
    b = model.site_body[s]
    p = xpos[b] + xrot[b] @ model.site_pos[s]
    jp, jr = point_jacobians(model, xpos, xrot, np.array([b]), p[None])
    return jnp.concatenate([jp[0], jr[0]], axis=0)


def frame_drift(model: RobotModel, q: jax.Array, v: jax.Array, frame: str) -> jax.Array:
    """J_dot v of a site's 6D Jacobian (``frame_jacobian``), by forward-mode AD.

    Args:
        model: the robot model.
        q: (nq,) configuration.
        v: (nv,) generalized velocity.
        frame: the site's name.

    Returns:
        (6,) [linear acceleration bias; angular], world frame.

    Raises:
        KeyError: no site has that name.
    """
    return spatial.derivative_along(lambda qq: frame_jacobian(model, qq, frame) @ v, q, v)


def com_position(model: RobotModel, q: jax.Array) -> jax.Array:
    """Whole-body centre of mass.

    Args:
        model: the robot model.
        q: (nq,) configuration.

    Returns:
        (3,) p_CoM, world frame.
    """
    xpos, xrot = forward_kinematics(model, q)
    com, _ = body_com(model, xpos, xrot)
    return model.body_mass @ com / jnp.sum(model.body_mass)


def com_jacobian(model: RobotModel, q: jax.Array) -> jax.Array:
    """Jacobian of the whole-body centre of mass.

    Args:
        model: the robot model.
        q: (nq,) configuration.

    Returns:
        (3, nv) J_CoM.
    """
    jp, _, _ = _com_jacobians(model, q)
    return jnp.einsum("b,bin->in", model.body_mass, jp) / jnp.sum(model.body_mass)


def com_drift(model: RobotModel, q: jax.Array, v: jax.Array) -> jax.Array:
    """Drift of the whole-body centre of mass, by forward-mode AD.

    Args:
        model: the robot model.
        q: (nq,) configuration.
        v: (nv,) generalized velocity.

    Returns:
        (3,) J_CoM_dot v.
    """
    return spatial.derivative_along(lambda qq: com_jacobian(model, qq) @ v, q, v)


def torso_euler(model: RobotModel, q: jax.Array) -> jax.Array:
    """Torso (base) orientation as Euler ZYX angles.

    Args:
        model: the robot model.
        q: (nq,) configuration.

    Returns:
        (3,) [roll, pitch, yaw], rad.
    """
    return spatial.euler_zyx(spatial.quat_to_mat(q[3:7]))


def torso_euler_jacobian(model: RobotModel, q: jax.Array) -> jax.Array:
    """Jacobian of ``torso_euler``, by forward-mode AD.

    Args:
        model: the robot model.
        q: (nq,) configuration.

    Returns:
        (3, nv) J_theta.
    """
    return spatial.tangent_jacobian(lambda qq: torso_euler(model, qq), q, model.nv)


def torso_euler_drift(model: RobotModel, q: jax.Array, v: jax.Array) -> jax.Array:
    """Drift of the torso Euler angles: their second derivative along v (forward-mode AD).

    Args:
        model: the robot model.
        q: (nq,) configuration.
        v: (nv,) generalized velocity.

    Returns:
        (3,) J_theta_dot v.
    """
    return spatial.second_derivative_along(lambda qq: torso_euler(model, qq), q, v)


def torso_euler_terms(model: RobotModel, q: jax.Array,
                      v: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(theta, J_theta, J_theta_dot v) of the torso Euler ZYX angles in closed form.

    With the base's body-frame angular velocity omega = v[3:6] (MuJoCo's free joint) and
    R = Rz(yaw) Ry(pitch) Rx(roll), omega = [r_dot - s_p y_dot, c_r p_dot + s_r c_p y_dot,
    -s_r p_dot + c_r c_p y_dot]; inverted, theta_dot = E(r, p) omega with

        E = [[1, s_r t_p, c_r t_p], [0, c_r, -s_r], [0, s_r / c_p, c_r / c_p]],

    so J_theta is E in the base's rotational columns. Its drift (omega held fixed) is
    dE/dr omega r_dot + dE/dp omega p_dot with a = s_r w_y + c_r w_z, b = c_r w_y - s_r w_z:
    dE/dr omega = [t_p b, -a, b / c_p], dE/dp omega = [a / c_p^2, 0, a s_p / c_p^2],
    r_dot = w_x + t_p a, p_dot = b. Equal to ``torso_euler_jacobian`` and
    ``torso_euler_drift`` (forward-mode AD) away from pitch = +-pi/2, where both are
    singular.

    Args:
        model: the robot model.
        q: (nq,) configuration.
        v: (nv,) generalized velocity.

    Returns:
        ``(theta, J_theta, J_theta_dot v)``: (3,) [roll, pitch, yaw], (3, nv), (3,).
    """
    theta = torso_euler(model, q)
    k0 = model.body_dadr[0]
    e, drift = _euler_rate_map(theta, v[k0 + 3:k0 + 6])
    jac = jnp.pad(e, ((0, 0), (k0 + 3, model.nv - k0 - 6)))
    return theta, jac, drift


def _euler_rate_map(theta, w):
    """E(roll, pitch) with theta_dot = E w for the body-frame angular velocity w, and
    E_dot w with w held fixed (``torso_euler_terms``)."""
    sr, cr = jnp.sin(theta[0]), jnp.cos(theta[0])
    sp, cp = jnp.sin(theta[1]), jnp.cos(theta[1])
    tp, icp = sp / cp, 1.0 / cp
    zero, one = jnp.zeros_like(sr), jnp.ones_like(sr)
    e = jnp.stack([jnp.stack([one, sr * tp, cr * tp]), jnp.stack([zero, cr, -sr]),
                   jnp.stack([zero, sr * icp, cr * icp])])
    a = sr * w[1] + cr * w[2]
    b = cr * w[1] - sr * w[2]
    r_dot = w[0] + tp * a
    drift = (r_dot * jnp.stack([tp * b, -a, b * icp])
             + b * jnp.stack([a * icp * icp, zero, a * sp * icp * icp]))
    return e, drift


def _site_motion_terms(model: RobotModel, kin, frame: str):
    """Of a named site, from one kinematics pass: its body (static), world position p,
    world rotation R, and the linear and angular Jacobians of p (3 x nv each)."""
    s = model.site_id(frame)
    b = model.site_body[s]
    xpos, xrot = kin
    p = xpos[b] + xrot[b] @ model.site_pos[s]
    jp, jw = point_jacobians(model, xpos, xrot, np.array([b]), p[None])
    return b, p, xrot[b] @ model.site_rot[s], jp[0], jw[0]


def frame_orientation_terms(model: RobotModel, kin: tuple[jax.Array, jax.Array],
                            motion: BodyMotion,
                            frame: str) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(theta, J_theta, J_theta_dot v) of a site's Euler ZYX angles [roll, pitch, yaw] in
    closed form. The site's body-frame angular velocity is w = R^T omega (omega, alpha:
    its body's world angular velocity and bias acceleration, ``body_motion``), and along
    q_ddot = 0, w_dot = R^T alpha (R^T omega x omega vanishes); with theta_dot = E w as for
    the torso (``torso_euler_terms``): J_theta = E R^T J_omega, J_theta_dot v = E_dot w +
    E R^T alpha. Singular at pitch = +-pi/2, as any Euler parametrisation.

    Args:
        model: the robot model.
        kin: ``(xpos, xrot)`` of ``forward_kinematics`` at q.
        motion: ``body_motion`` at (q, v).
        frame: the site's name.

    Returns:
        ``(theta, J_theta, J_theta_dot v)``: (3,) [roll, pitch, yaw], (3, nv), (3,).

    Raises:
        KeyError: no site has that name.
    """
    b, _, r, _, jw = _site_motion_terms(model, kin, frame)
    theta = spatial.euler_zyx(r)
    e, drift = _euler_rate_map(theta, r.T @ motion.omega[b])
    return theta, e @ (r.T @ jw), drift + e @ (r.T @ motion.alpha[b])


def site_point_terms(model: RobotModel, kin: tuple[jax.Array, jax.Array],
                     motion: BodyMotion,
                     frame: str) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(p, J_p, J_p_dot v) of a site's world position in closed form.

    Args:
        model: the robot model.
        kin: ``(xpos, xrot)`` of ``forward_kinematics`` at q.
        motion: ``body_motion`` at (q, v).
        frame: the site's name.

    Returns:
        ``(p, J_p, J_p_dot v)``: (3,), (3, nv), (3,), world frame.

    Raises:
        KeyError: no site has that name.
    """
    b, p, _, jp, _ = _site_motion_terms(model, kin, frame)
    return p, jp, motion.point_bias(np.array([b]), p[None])[0]


def position_in_terms(model: RobotModel, kin: tuple[jax.Array, jax.Array],
                      motion: BodyMotion, frame: str,
                      reference: str) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(y, J_y, J_y_dot v) of y = R_r^T (p_f - p_r), ``frame``'s position in the frame
    ``reference`` (``frame_position_in``), in closed form. With d = p_f - p_r and the
    reference body's angular velocity w and bias acceleration w_dot (world):

        y_dot = R_r^T (d_dot - w x d),          J_y = R_r^T (J_f - J_r + [d]x J_w),
        J_y_dot v = R_r^T (d_ddot - w_dot x d - 2 w x d_dot + w x (w x d)),

    d_ddot the two points' bias accelerations (q_ddot = 0), as the A-ECBF row (eq. 28)
    needs them: no automatic differentiation of the kinematics.

    Args:
        model: the robot model.
        kin: ``(xpos, xrot)`` of ``forward_kinematics`` at q.
        motion: ``body_motion`` at (q, v).
        frame: the site whose position is taken.
        reference: the site in whose frame it is expressed.

    Returns:
        ``(y, J_y, J_y_dot v)``: (3,), (3, nv), (3,), in ``reference``'s frame.

    Raises:
        KeyError: no site has one of the names.
    """
    f, p_f, _, j_f, _ = _site_motion_terms(model, kin, frame)
    b, p_r, rot, j_r, jw = _site_motion_terms(model, kin, reference)
    v_f = motion.point_velocity(np.array([f]), p_f[None])
    v_r = motion.point_velocity(np.array([b]), p_r[None])
    a_f = motion.point_bias(np.array([f]), p_f[None], v_f)[0]
    a_r = motion.point_bias(np.array([b]), p_r[None], v_r)[0]
    w, w_dot = motion.omega[b], motion.alpha[b]
    d = p_f - p_r
    d_dot = v_f[0] - v_r[0]
    jy = rot.T @ (j_f - j_r + spatial.skew(d) @ jw)
    bias = (a_f - a_r - jnp.cross(w_dot, d) - 2.0 * jnp.cross(w, d_dot)
            + jnp.cross(w, jnp.cross(w, d)))
    return rot.T @ d, jy, rot.T @ bias


def frame_position_in(model: RobotModel, q: jax.Array, frame: str,
                      reference: str) -> jax.Array:
    """Position of a site expressed in another site's frame (e.g. a fist in the torso
    base frame, as the paper's arm barrier uses).

    Args:
        model: the robot model.
        q: (nq,) configuration.
        frame: the site whose position is taken.
        reference: the site in whose frame it is expressed.

    Returns:
        (3,) R_r^T (p_f - p_r).

    Raises:
        KeyError: no site has one of the names.
    """
    p, _ = frame_pose(model, q, frame)
    p0, r0 = frame_pose(model, q, reference)
    return r0.T @ (p - p0)
