"""ALIP template model, one-step-ahead foot-placement planner and swing-foot reference.

The walking task of the paper (section "Task: Walking with the A-LIP template model") plans
the swing foot with the Angular-Momentum-based Linear Inverted Pendulum (ALIP) of Gong &
Grizzle [1] and the one-step-ahead foot-placement rule used by Gibson et al. [2]. All
functions here are pure JAX (jit- and vmap-able, no Python branching on traced values).

Frames and sign conventions
---------------------------
Everything is expressed in a *heading frame*: a world-aligned frame rotated by the walking
yaw about the vertical (yaw = 0 gives the world frame), x forward, y to the left, z up.
Horizontal vectors carry the two axes as a trailing dimension ``[..., 2] = [x, y]``.

ALIP state, per horizontal axis, about the stance contact point c:

* ``p = (p_x, p_y)``: horizontal CoM position relative to c, ``p = (p_com - c)_xy``.
* ``L = (L_x^alip, L_y^alip)``: the horizontal angular momentum about c that drives p,

      L^alip = (L_c x e_z)_xy = ( L_c,y , -L_c,x ),

  where ``L_c`` is the whole-body angular momentum about c in the heading frame. With the
  CoM a height H above c and no vertical velocity, ``L_c,y ~= m H v_x`` and
  ``L_c,x ~= -m H v_y``, so in both axes ``L^alip ~= m H p_dot``: positive L moves the
  CoM towards +x (sagittal) or +y (lateral, to the left).

ALIP dynamics [1]: with a passive stance ankle (zero ankle torque) the only
moment about c is gravity's, ``L_c_dot = (p_com - c) x (m g_vec)``, which gives exactly
``L^alip_dot = m g p``; the kinematic relation ``p_dot = L^alip / (m H)`` holds when the
centroidal angular momentum and the vertical CoM velocity are neglected. Per axis

    d/dt [p, L] = A [p, L],   A = [[0, 1/(m H)], [m g, 0]],

and since ``A^2 = (g/H) I = l^2 I`` with ``l = sqrt(g/H)``, the transition over a time t is

    exp(A t) = cosh(l t) I + sinh(l t)/l A
             = [[cosh(l t),           sinh(l t)/(m H l)],
                [m H l sinh(l t),     cosh(l t)        ]].

Foot placement
--------------
A step lasts T (the paper's period, 0.35 s by default); tau in [0, T] is the time since the
step began. At impact the new stance foot is at ``c' = c + u`` (``u``, the *step vector*,
is the next stance foot relative to the current stance foot, horizontal, heading frame).
Following [1, 2], the angular momentum about the new contact point equals the one about the
old contact point just before impact (impact impulses act at c'; moving the reference point
horizontally changes only the vertical component of L when v_z = 0), so

    p^+ = p(T^-) - u,      L^+ = L(T^-).

One-step-ahead rule (Gibson et al. [2], after [1]): from the current state at tau predict
the end of this step with the closed-form solution,

    p_end = cosh(l (T - tau)) p + sinh(l (T - tau))/(m H l) L,
    L_end = m H l sinh(l (T - tau)) p + cosh(l (T - tau)) L,

then choose p^+ so that the *next* step ends with the desired momentum L_des:

    L_des = m H l sinh(l T) p^+ + cosh(l T) L_end
    =>  p^+ = (L_des - cosh(l T) L_end) / (m H l sinh(l T)),
        u   = p_end - p^+   (u - p_end = -p^+ is the next foot relative to the CoM at impact).

Desired end-of-step momenta (for the end of the *next* step):

* sagittal: ``L_des,x = m H v_des`` (the CoM velocity at each step transition equals
  v_des, as in [1]); with ``average_velocity=True`` it is scaled by ``(l T / 2) / tanh(l T / 2)``
  so that the *mean* CoM velocity over a step equals v_des (on the periodic gait the mean
  velocity is ``2 tanh(l T / 2) / (l T)`` times L_end/(m H), about 0.90 for T = 0.35,
  H = 0.9).
* lateral, for a commanded step width w (foot-to-foot lateral distance) and zero mean
  lateral velocity. The period-two orbit is symmetric in time within each step,
  ``p_y(t) = a cosh(l (t - T/2))``, ``L(t) = m H l a sinh(l (t - T/2))``. Consecutive stance
  feet are ``|2 a cosh(l T / 2)| = w`` apart, so ``|a| = w / (2 cosh(l T / 2))`` and the
  end-of-step momentum is ``+-(m H l w / 2) tanh(l T / 2)``. During LEFT stance the CoM is
  to the right of the stance foot (a < 0) and ends moving right: L_end = -that; during
  RIGHT stance it ends moving left: L_end = +that. The planner targets the end of the next
  step, whose stance side is the opposite one:

      stance_side = +1 (LEFT stance now, next is right stance):  L_des,y = +(m H l w/2) tanh(l T/2)
      stance_side = -1 (RIGHT stance now, next is left stance):  L_des,y = -(m H l w/2) tanh(l T/2)

  plus ``m H v_des_y`` (same scaling option) for a commanded lateral velocity. On the
  converged orbit the lateral step is ``u_y = -w`` from a left stance foot and ``+w`` from
  a right one.

In the ALIP model the rule is dead-beat: L at the end of the next step equals L_des
exactly, whatever the state at the planning instant.

References
----------
[1] Y. Gong and J. W. Grizzle, "Zero Dynamics, Pendulum Models, and Angular Momentum in
    Feedback Control of Bipedal Locomotion", ASME J. Dyn. Sys., Meas., Control, 2022.
[2] G. Gibson, O. Dosunmu-Ogunbi, Y. Gong, J. Grizzle, "Terrain-Adaptive, ALIP-Based
    Bipedal Locomotion Controller via Model Predictive Control and Virtual Constraints",
    IROS 2022.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

LEFT = 1.0   # stance_side value while the left foot is the stance foot
RIGHT = -1.0  # stance_side value while the right foot is the stance foot

DEFAULT_T = 0.35      # step period of the paper (s)
DEFAULT_H = 0.9       # CoM height of the paper (m)
DEFAULT_G = 9.81
SWING_HEIGHT = 0.08   # apex of the swing-foot height profile (m)
SWING_RATE = 5.0      # rate of the paper's smoothing factor s = 1 - exp(-rate tau / T) (eq. 37)
LAND_SPEED = 0.2      # m/s: descent of the "land" swing profile at tau = T and after
LAND_DEPTH = 0.05     # m: the "land" profile stops descending this far below the ground


# --------------------------------------------------------------------------------------
# ALIP dynamics
# --------------------------------------------------------------------------------------

def alip_system_matrix(H, m, g=DEFAULT_G):
    """Per-axis ALIP system matrix A = [[0, 1/(m H)], [m g, 0]] of d/dt [p, L] = A [p, L]."""
    H, m, g = jnp.broadcast_arrays(*(jnp.asarray(a, jnp.float64) for a in (H, m, g)))
    zero = jnp.zeros_like(H)
    return jnp.stack([jnp.stack([zero, 1.0 / (m * H)], -1),
                      jnp.stack([m * g, zero], -1)], -2)


def alip_matrix(H, g, m, t):
    """Transition matrix exp(A t) of one ALIP axis over time t (cosh/sinh closed form):

        [[cosh(l t), sinh(l t)/(m H l)], [m H l sinh(l t), cosh(l t)]],  l = sqrt(g/H).

    Arguments broadcast; the result is [..., 2, 2]."""
    H, g, m, t = jnp.broadcast_arrays(*(jnp.asarray(a, jnp.float64) for a in (H, g, m, t)))
    lam = jnp.sqrt(g / H)
    c, s = jnp.cosh(lam * t), jnp.sinh(lam * t)
    mhl = m * H * lam
    return jnp.stack([jnp.stack([c, s / mhl], -1), jnp.stack([mhl * s, c], -1)], -2)


def alip_propagate(state, t, H, m, g=DEFAULT_G):
    """ALIP state after time t: ``state`` is [..., 2] = [p, L] of one axis (for both axes
    pass a [2, 2] array with rows [p_x, L_x^alip] and [p_y, L_y^alip])."""
    a = alip_matrix(H, g, m, t)
    return jnp.einsum("...ij,...j->...i", a, jnp.asarray(state))


def _propagate_pl(p, L, t, H, m, g):
    """Both axes: p, L [..., 2] after time t (t, H, m, g broadcast against [...])."""
    lam = jnp.sqrt(g / H)
    c = jnp.cosh(lam * t)[..., None]
    s = jnp.sinh(lam * t)[..., None]
    mhl = (m * H * lam)[..., None]
    return c * p + s / mhl * L, mhl * s * p + c * L


# --------------------------------------------------------------------------------------
# Angular momentum about a point, ALIP state from the robot
# --------------------------------------------------------------------------------------

def angular_momentum_about_point(L_com, mass, p_com, v_com, point):
    """Angular momentum about a fixed point from the centroidal one:
    ``L_point = L_com + m (p_com - point) x v_com`` (3-vectors, broadcast)."""
    return L_com + jnp.asarray(mass)[..., None] * jnp.cross(p_com - point, v_com)


def angular_momentum_from_bodies(masses, coms, com_vels, inertias_world, omegas, point):
    """Angular momentum about ``point`` of a set of rigid bodies:
    ``sum_b I_b w_b + m_b (c_b - point) x v_b`` with per-body mass [nb], CoM [nb, 3], CoM
    velocity [nb, 3], world inertia about the CoM [nb, 3, 3], angular velocity [nb, 3]."""
    spin = jnp.einsum("bij,bj->i", inertias_world, omegas)
    orbit = jnp.einsum("b,bi->i", masses, jnp.cross(coms - point, com_vels))
    return spin + orbit


class Momentum(NamedTuple):
    """Whole-body momentum terms (world frame)."""
    mass: jax.Array       # total mass
    com: jax.Array        # CoM position [3]
    com_vel: jax.Array    # CoM velocity [3]
    L_com: jax.Array      # centroidal angular momentum (about the CoM) [3]
    L_point: jax.Array    # angular momentum about ``point`` [3]


def robot_momentum(model, q, v, point):
    """Whole-body CoM, CoM velocity, centroidal angular momentum and angular momentum about
    ``point`` (world) of a :class:`safewbc_jax.model.robot.RobotModel` at (q, v), from the bodies'
    velocities in closed form (``robot.body_motion``: a CoM c of a body moves with
    omega x c + c_dot_0; rotor armature carries no momentum here, as in MuJoCo's
    ``subtree_angmom``)."""
    from safewbc_jax.model import robot

    kin = robot.forward_kinematics(model, q)
    com, irot = robot.body_com(model, *kin)
    motion = robot.body_motion(model, kin, v)
    omega = motion.omega
    vel = motion.point_velocity(None, com)
    iworld = jnp.einsum("bij,bj,bkj->bik", irot, model.body_inertia, irot)
    masses = model.body_mass
    mtot = jnp.sum(masses)
    p_com = masses @ com / mtot
    v_com = masses @ vel / mtot
    L_com = angular_momentum_from_bodies(masses, com, vel, iworld, omega, p_com)
    L_point = angular_momentum_about_point(L_com, mtot, p_com, v_com, point)
    return Momentum(mtot, p_com, v_com, L_com, L_point)


def rotate_yaw(vec_xy, yaw):
    """Rotate horizontal vectors [..., 2] by +yaw about z (heading frame -> world)."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    x, y = vec_xy[..., 0], vec_xy[..., 1]
    return jnp.stack([c * x - s * y, s * x + c * y], -1)


def world_to_heading(vec_xy, yaw):
    """Rotate horizontal world vectors [..., 2] into the heading frame of the given yaw."""
    return rotate_yaw(vec_xy, -yaw)


def alip_momentum(L_xyz):
    """ALIP momenta (L^alip_x, L^alip_y) = (L_y, -L_x) from an angular momentum 3-vector."""
    return jnp.stack([L_xyz[..., 1], -L_xyz[..., 0]], -1)


class AlipState(NamedTuple):
    p: jax.Array   # horizontal CoM relative to the contact point, heading frame [2]
    L: jax.Array   # ALIP momenta (L_y, -L_x) about the contact point, heading frame [2]
    z: jax.Array   # CoM height above the contact point


def alip_state(p_com, L_point, contact, yaw=0.0):
    """ALIP state from the CoM position, the angular momentum about the contact point and
    the contact point (world 3-vectors), expressed in the heading frame of ``yaw``."""
    d = p_com - contact
    p = world_to_heading(d[..., :2], yaw)
    L = world_to_heading(alip_momentum(L_point), yaw)  # (L_y, -L_x) commutes with yaw
    return AlipState(p, L, d[..., 2])


def alip_state_from_robot(model, q, v, contact, yaw=0.0):
    """ALIP state of the robot about the stance contact point ``contact`` (world [3], e.g.
    the stance sole site), heading frame of ``yaw``."""
    mom = robot_momentum(model, q, v, contact)
    return alip_state(mom.com, mom.L_point, contact, yaw)


# --------------------------------------------------------------------------------------
# Foot-placement planner
# --------------------------------------------------------------------------------------

def _velocity_gain(T, H, g, average_velocity):
    """Factor from a commanded velocity to L_end/(m H) on the periodic gait."""
    if not average_velocity:
        return jnp.ones_like(T)
    half = 0.5 * jnp.sqrt(g / H) * T
    return half / jnp.tanh(half)


def desired_end_momentum(v_des, step_width, stance_side, T, H, m, g=DEFAULT_G, v_des_y=0.0,
                         average_velocity=False):
    """ALIP momenta [2] wanted at the end of the NEXT step (see the module docstring):
    ``[m H v_des k, stance_side (m H l w / 2) tanh(l T / 2) + m H v_des_y k]`` with
    k = 1, or ``(l T/2)/tanh(l T/2)`` when ``average_velocity`` (a static bool)."""
    T, H, m, g = (jnp.asarray(a, jnp.float64) for a in (T, H, m, g))
    lam = jnp.sqrt(g / H)
    k = _velocity_gain(T, H, g, average_velocity)
    lat = stance_side * 0.5 * m * H * lam * step_width * jnp.tanh(0.5 * lam * T)
    return jnp.stack(jnp.broadcast_arrays(m * H * v_des * k, lat + m * H * v_des_y * k), -1)


class FootPlacement(NamedTuple):
    u: jax.Array        # next stance foot relative to the current stance foot [2]
    L_end: jax.Array    # predicted ALIP momenta at the end of the current step [2]
    p_end: jax.Array    # predicted CoM relative to the stance foot at the end of the step [2]
    L_des: jax.Array    # momenta targeted at the end of the next step [2]

    @property
    def u_from_com(self):
        """Next stance foot relative to the CoM at impact (= -p^+)."""
        return self.u - self.p_end


def plan_foot_placement(p_now, L_now, tau, T, H, m, g, v_des, step_width, stance_side,
                        v_des_y=0.0, average_velocity=False):
    """One-step-ahead ALIP foot placement (Gibson et al. 2022, after Gong & Grizzle 2022).

    p_now, L_now: current ALIP state [..., 2] ([x, y], heading frame, ALIP momenta as in
    the module docstring); tau: time since the step began; T: step period; H: CoM height;
    m: mass; g: gravity (positive); v_des: forward velocity command; step_width: lateral
    foot-to-foot distance command; stance_side: +1 (LEFT) or -1 (RIGHT) stance now;
    v_des_y: lateral velocity command; average_velocity (static bool): interpret the
    velocity commands as mean CoM velocities instead of CoM velocities at the step
    transitions.

    Returns :class:`FootPlacement` (u = step vector from the current stance foot, the
    predicted end-of-step state, the target momenta). The remaining time ``T - tau`` is
    clipped at 0 (an overdue step plans from the current state as if impact were now)."""
    dtype = jnp.float64
    p_now, L_now = jnp.asarray(p_now, dtype), jnp.asarray(L_now, dtype)
    tau, T, H, m, g = (jnp.asarray(a, dtype) for a in (tau, T, H, m, g))
    stance_side = jnp.asarray(stance_side, dtype)
    lam = jnp.sqrt(g / H)
    remaining = jnp.maximum(T - tau, 0.0)
    p_end, L_end = _propagate_pl(p_now, L_now, remaining, H, m, g)
    L_des = desired_end_momentum(v_des, step_width, stance_side, T, H, m, g, v_des_y,
                                 average_velocity)
    c, s = jnp.cosh(lam * T)[..., None], jnp.sinh(lam * T)[..., None]
    p_plus = (L_des - c * L_end) / ((m * H * lam)[..., None] * s)
    return FootPlacement(p_end - p_plus, L_end, p_end, L_des)


def impact_map(p_end, L_end, u):
    """ALIP state just after impact at the planned foot: p^+ = p^- - u, L^+ = L^-."""
    return p_end - u, L_end


# --------------------------------------------------------------------------------------
# Swing-foot reference
# --------------------------------------------------------------------------------------

class SwingReference(NamedTuple):
    pos: jax.Array   # [3]
    vel: jax.Array   # [3]
    acc: jax.Array   # [3]


def swing_foot_reference(tau, T, p_sw0, u, height=SWING_HEIGHT, rate=SWING_RATE, z0=0.0,
                         exact_landing=False, vertical="sine", land_speed=LAND_SPEED,
                         land_depth=LAND_DEPTH, horizontal="paper", reach=1.0):
    """Swing-foot position reference and its first two time derivatives (analytic).

    Horizontal (the paper's formula, eq. 37): ``p_xy(tau) = p_sw0 + s(tau) (u - p_sw0)`` with the
    smoothing factor ``s = 1 - exp(-rate tau / T)`` (rate = 5), where ``p_sw0`` [2] is the
    swing foot at the start of the step and ``u`` [2] the planned foot placement, both
    relative to the stance foot in the heading frame. Note ``s(T) = 1 - e^-5 ~= 0.9933``:
    the reference reaches only 99.3 % of the way at T; ``exact_landing=True`` (static)
    divides s by ``1 - exp(-rate)`` so it lands on u at tau = T. ``ds/dtau(0) = rate/T`` is
    not zero: the horizontal velocity reference jumps at lift-off, as in the paper.

    ``horizontal="minjerk"`` (static) replaces s by the minimum-jerk blend
    ``s = 10 sigma^3 - 15 sigma^4 + 6 sigma^5``, sigma = clip(tau / (reach T), 0, 1): zero
    velocity and acceleration at lift-off, on u from ``reach T`` on. The paper's s
    starts the swing foot at ``(rate / T) |u - p_sw0|`` (4 m/s for a 0.3 m step), a
    feed-forward that saturates the hips at every lift-off on this model.

    Vertical, ``vertical="sine"`` (static): ``z(tau) = z0 + height sin(pi tau / T)`` for
    tau in [0, T] and z0 outside. This differs from the printed
    ``0.08 sin(2 pi tau / T)`` of eq. 37, which returns to 0 at T/2 and is negative (foot
    below the ground) over the second half of the step; with ``pi tau / T`` the foot lifts
    off at tau = 0, peaks at ``height`` (0.08 m) at mid-step and touches down at tau = T
    (with vertical velocity ``-height pi / T``, 0.72 m/s for the defaults: a hard landing).

    ``vertical="land"``: with sigma = tau / T and d = v_land T,
    ``z = z0 + height 16 sigma^2 (1 - sigma)^2 + d sigma^2 (1 - sigma)`` on [0, T]:
    lift-off with zero velocity, apex ~``height`` near mid-step, back at z0 at tau = T
    descending at ``v_land`` (``land_speed``, 0.2 m/s by default: a soft landing). After
    T it keeps descending at v_land down to ``z0 - land_depth`` and stays there: a foot
    that has not touched down yet is pushed on until it does, so that the contact check
    ends the step (a reference holding the foot at ground level lets it hover
    millimetres above the floor, and the step never ends)."""
    dtype = jnp.float64
    tau, T = jnp.asarray(tau, dtype), jnp.asarray(T, dtype)
    p_sw0, u = jnp.asarray(p_sw0, dtype), jnp.asarray(u, dtype)
    if horizontal == "paper":
        k = rate / T
        e = jnp.exp(-k * tau)
        norm = (1.0 - np.exp(-rate)) if exact_landing else 1.0
        s, ds, dds = (1.0 - e) / norm, k * e / norm, -k * k * e / norm
    elif horizontal == "minjerk":
        tr = reach * T
        sg = jnp.clip(tau / tr, 0.0, 1.0)
        on = (tau > 0.0) & (tau < tr)
        s = sg**3 * (10.0 - 15.0 * sg + 6.0 * sg**2)
        ds = jnp.where(on, 30.0 * sg**2 * (1.0 - sg) ** 2 / tr, 0.0)
        dds = jnp.where(on, 60.0 * sg * (1.0 - sg) * (1.0 - 2.0 * sg) / tr**2, 0.0)
    else:
        raise ValueError(f"horizontal must be 'paper' or 'minjerk', got {horizontal!r}")
    d = u - p_sw0
    if vertical == "sine":
        w = jnp.pi / T
        inside = (tau >= 0.0) & (tau <= T)
        ph = jnp.clip(tau, 0.0, T) * w
        z = jnp.where(inside, z0 + height * jnp.sin(ph), z0)
        dz = jnp.where(inside, height * w * jnp.cos(ph), 0.0)
        ddz = jnp.where(inside, -height * w * w * jnp.sin(ph), 0.0)
    elif vertical == "land":
        sg = jnp.clip(tau / T, 0.0, 1.0)
        inside = (tau >= 0.0) & (tau <= T)
        dd = land_speed * T
        zi = height * 16.0 * sg**2 * (1.0 - sg) ** 2 + dd * sg**2 * (1.0 - sg)
        dzi = (height * 32.0 * sg * (1.0 - sg) * (1.0 - 2.0 * sg)
               + dd * (2.0 * sg - 3.0 * sg**2)) / T
        ddzi = (height * 32.0 * (1.0 - 6.0 * sg + 6.0 * sg**2) + dd * (2.0 - 6.0 * sg)) / T**2
        z_after = -land_speed * (tau - T)
        below = z_after > -land_depth  # still descending
        z = z0 + jnp.where(inside, zi, jnp.where(tau > T, jnp.maximum(z_after, -land_depth), 0.0))
        dz = jnp.where(inside, dzi, jnp.where((tau > T) & below, -land_speed, 0.0))
        ddz = jnp.where(inside, ddzi, 0.0)
    else:
        raise ValueError(f"vertical must be 'sine' or 'land', got {vertical!r}")
    pos = jnp.concatenate([p_sw0 + s[..., None] * d, z[..., None]], -1)
    vel = jnp.concatenate([ds[..., None] * d, dz[..., None]], -1)
    acc = jnp.concatenate([dds[..., None] * d, ddz[..., None]], -1)
    return SwingReference(pos, vel, acc)
