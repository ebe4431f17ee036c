"""ALIP walking: the single-support domain of the paper's walking task, its outputs and
references, and the gait state that switches domains.

Paper, "Task: Walking with the A-LIP template model": in single support the outputs are
z_CoM = H, the torso held vertical, the swing foot's position following
p^d_swing(tau) towards the ALIP foot placement (u_x, u_y), and the swing foot kept flat
(eq. 38); here the arms are held too. Before walking the robot stands (double support,
the CoM blended to the walking height). The planner is ``alip.plan_foot_placement``,
re-planned at every control step from the measured state.

The gait state ("domain") is data, not structure: stance side (+1 left, -1 right, 0 both
feet), contact flags, time in the step, where the feet were when the step began, the
heading and the commands. One compiled controller serves every domain, which the batched
path needs.

The stance ankle is passive, as the ALIP requires (L_dot = m g p only holds with no ankle
torque): in the QP the stance leg's two ankle motors (toe-A, toe-B, which drive the ankle
pitch and roll through the rods) get the bounds 0 <= u <= 0 (``passive_actuators``).

What differs from the paper's printed task, and why (measured in MuJoCo on this model):

* Swing-foot profile. Horizontally the paper (eq. 37) blends with s = 1 - exp(-5 tau / T), whose
  slope at lift-off is 5/T: a 0.3 m step starts the foot at ~4 m/s, and the lift-off
  feed-forward saturated the hips at every switch. The default here is the minimum-jerk
  blend (``alip.swing_foot_reference(horizontal="minjerk")``: at rest at lift-off, on the
  planned point at T); ``SWING_HORIZONTAL = "paper"`` restores the exponential.
  Vertically the printed 0.08 sin(2 pi tau / T) is below the floor for the second half
  of the step; ``vertical="land"`` rises to ~0.08 m and comes down at 0.2 m/s at T, then
  keeps descending until the contact check ends the step.
* Swing-leg springs. The controller holds the shin and heel springs rigid (the paper's
  n_kc); the simulator's are undamped. The loop feeds the controller the swing leg's
  rates with rigid springs (``rigid_spring_velocity``): with the measured spring rates the
  swing leg rang at ~30 Hz with bang-bang hip and knee torques.
* Touchdown. From T/2 a firm contact (``EARLY_TOUCHDOWN`` x weight) ends the step early;
  from T any contact does; at 2 T the switch is forced and counted.
* Planner target. The planner aims at the commanded *mean* velocity
  (``average_velocity=True``), and its lateral step may cross towards the stance foot
  (``STEP_Y`` down to -0.2 m): keeping the feet apart is the swing-foot barrier's job, as
  in the paper's collision-avoidance task.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.control import alip, outputs, references
from safewbc_jax.model import chains, robot
from safewbc_jax.control.safesets import SafeSet
from safewbc_jax.control.gait import Support
from safewbc_jax.control.scenario import Scenario
from safewbc_jax.control.tasks import Task
from safewbc_jax.solvers import lapack_batched as lb
from safewbc_jax.model import digit

H_WALK = 0.9            # CoM height (m), paper
STEP_T = 0.35           # step period (s), paper
STEP_WIDTH = 0.22       # commanded lateral foot-to-foot distance (m): the stand pose's
SWING_MARGIN = 0.07     # collision barrier h = y_sw - 0.07 (paper, eq. 39)
SWING_POLES = (20.0, 20.0)
# Gait start: before the first (left-stance) step the CoM is moved over the inside edge of
# the left foot, this far (m) to the right of the sole centre, so that the passive-ankle
# pendulum starts near its orbit instead of falling from the middle of the feet.
START_SHIFT = 0.04
# Reach of the swing leg: the planned step vector is clipped to these bounds (m; lateral
# distances are from the stance foot towards the swing side; below 0.07 the step enters
# the swing-foot barrier's unsafe set, below 0 it crosses the stance foot).
STEP_X = (-0.30, 0.40)
STEP_Y = (-0.20, 0.45)
LEFT, RIGHT, BOTH = 1.0, -1.0, 0.0
SWING_HORIZONTAL = "minjerk"
EARLY_TOUCHDOWN = 0.2   # x weight: swing-sole force that ends a step between T/2 and T
TOUCH_FORCE = 5.0       # N: swing-sole force that ends a step from T on


def reachable_speeds(T: float = STEP_T) -> tuple[float, float]:
    """(least, greatest) mean forward speed (m/s) the ALIP planner can command at step
    period T. On the planner's periodic orbit (``alip.plan_foot_placement`` with
    average_velocity) the CoM advances one step length per step, so the step is
    u_x = v_des T; ``plan_step`` clips u_x to STEP_X, so a v_des beyond STEP_X / T is never
    reached, whatever the controller does."""
    return STEP_X[0] / T, STEP_X[1] / T


def check_speed(speed, option: str = "speed") -> float:
    """``speed`` as a float, or ValueError naming ``option`` and the planner's reach
    (``reachable_speeds``) when it is not a finite speed the planner can command."""
    lo, hi = reachable_speeds()
    s = float(speed)
    if not lo <= s <= hi:    # NaN fails too
        raise ValueError(
            f"{option} {s:g}: the ALIP planner at T = {STEP_T:g} s reaches mean forward "
            f"speeds in [{lo:.3f}, {hi:.3f}] m/s (steps of {STEP_X[0]:g} to {STEP_X[1]:g} m "
            "per period); the walks in the README were run at 0.2 m/s")
    return s


def _swing_select(domain, left_val, right_val):
    """The swing foot's value: in left stance the right foot swings."""
    stance = domain.stance
    return jnp.where(stance > 0, right_val, left_val)


def passive_dofs(model):
    """Velocity indices of the unactuated hinges (per leg: shin and heel springs, tarsus,
    toe pitch and roll), the dofs that the closed chains (eq. 2) determine."""
    b = np.asarray(model.B)
    return np.array([k for k in range(6, model.nv) if not np.any(b[k] != 0.0)])


def _leg_passive_dofs(model, side):
    names = [model.joint_names[model.body_dadr.index(k)] for k in passive_dofs(model)]
    return np.array([k for k, n in zip(passive_dofs(model), names) if n.startswith(side)])


def rigid_spring_velocity(model, q, v, stance):
    """v_r: the measured velocity with the swing leg's springs held rigid, as the
    controller models them (the paper's n_kc holds q_shin and q_heel-spring fixed).
    ``stance``: +1 left stance (the right leg is rigidified), -1 right stance, 0 double
    support (v unchanged).

    In the simulator the springs are stiff but undamped. Fed back through the swing
    outputs, the QP's drift and Coriolis terms, their ~30 Hz ringing makes the swing-leg
    loop non-collocated: the leg then oscillates with bang-bang hip and knee torques
    (swing-foot height jumping by +-4 cm every 30 ms, torques in phase with the knee
    velocity). v_r keeps every rate but the swing leg's passive ones (springs, tarsus,
    toe pitch and roll), which are recomputed from that leg's rows of
    J_chain(q) v_r = 0 with the spring rates at zero: the controller then damps
    motor-side motion of the swing leg only. A loaded leg keeps its measured rates: there
    the rigid rates would make the controller believe its sole slides (the feet then do
    creep, by ~10 cm in 1.5 s of standing). Positions are never changed."""
    jc = chains.chain_jacobian(model, q)
    rows = {"left": np.arange(0, jc.shape[0] // 2), "right": np.arange(jc.shape[0] // 2,
                                                                         jc.shape[0])}
    out = {}
    for side in ("left", "right"):
        pas = _leg_passive_dofs(model, side)
        rest = np.setdiff1d(np.arange(model.nv), pas)
        j = jc[rows[side]]
        vp = -lb.solve(j[:, pas], j[:, rest] @ v[rest])   # see solvers/lapack_batched.py
        out[side] = v.at[pas].set(vp)
    return jnp.where(stance > 0, out["right"], jnp.where(stance < 0, out["left"], v))


@dataclasses.dataclass(frozen=True)
class SwingFootPosition(outputs.Output):
    """p_swing(q): world position of the swinging sole (the foot opposite the stance)."""

    name: str = "swing_pos"
    dim = 3
    labels = ("swing_x", "swing_y", "swing_z")

    def value(self, model, q, domain=None):
        pl = robot.frame_pose(model, q, digit.LEFT_SOLE)[0]
        pr = robot.frame_pose(model, q, digit.RIGHT_SOLE)[0]
        return pl if domain is None else _swing_select(domain, pl, pr)

    def evaluate(self, model, q, v, terms=None):
        left = outputs.FramePosition(frame=digit.LEFT_SOLE).evaluate(model, q, v, terms)
        right = outputs.FramePosition(frame=digit.RIGHT_SOLE).evaluate(model, q, v, terms)
        domain = terms.domain
        return tuple(_swing_select(domain, a, b) for a, b in zip(left, right))


@dataclasses.dataclass(frozen=True)
class SwingFootOrientation(outputs.Output):
    """theta_swing(q): Euler ZYX angles [roll, pitch, yaw] of the swinging sole."""

    name: str = "swing_rot"
    dim = 3
    labels = ("swing_roll", "swing_pitch", "swing_yaw")

    def value(self, model, q, domain=None):
        left = outputs.FrameOrientation(frame=digit.LEFT_SOLE).value(model, q)
        right = outputs.FrameOrientation(frame=digit.RIGHT_SOLE).value(model, q)
        return left if domain is None else _swing_select(domain, left, right)

    def evaluate(self, model, q, v, terms=None):
        left = outputs.FrameOrientation(frame=digit.LEFT_SOLE).evaluate(model, q, v, terms)
        right = outputs.FrameOrientation(frame=digit.RIGHT_SOLE).evaluate(model, q, v, terms)
        domain = terms.domain
        return tuple(_swing_select(domain, a, b) for a, b in zip(left, right))


def _heading_lateral(model, q, domain):
    """Lateral distance of the swing sole from the stance sole in the heading frame,
    signed positive when the feet are apart (either stance side)."""
    pl = robot.frame_pose(model, q, digit.LEFT_SOLE)[0]
    pr = robot.frame_pose(model, q, digit.RIGHT_SOLE)[0]
    d = alip.world_to_heading((pl - pr)[:2], domain.heading)  # left foot from right
    return d[1]  # > 0 when the left foot is to the left of the right one


def swing_clearance_h(model, q, threshold, domain):
    """Paper, "Task: Collision avoidance", eq. 39: h_ALIP(q) = y_sw(q) - 0.07 >= 0, y_sw the
    lateral position of the swing foot relative to the stance foot, signed so that it is
    positive when the feet are apart whichever foot swings."""
    return _heading_lateral(model, q, domain) - threshold


def swing_clearance_terms(model, kin, motion, threshold, domain):
    """(h, J_h, J_h_dot v) of ``swing_clearance_h`` in closed form: h is linear in the two
    soles' world positions (the heading is the domain's, fixed within a step), so its
    Jacobian and drift are that combination of the soles' (``robot.site_point_terms``)."""
    pl, jl, al = robot.site_point_terms(model, kin, motion, digit.LEFT_SOLE)
    pr, jr, ar = robot.site_point_terms(model, kin, motion, digit.RIGHT_SOLE)
    eye = jnp.eye(2, dtype=pl.dtype)
    c = alip.world_to_heading(eye, domain.heading)[:, 1]     # d_y = c . (p_l - p_r)_xy
    return c @ (pl - pr)[:2] - threshold, c @ (jl - jr)[:2], c @ (al - ar)[:2]


def _single_support(domain):
    return jnp.abs(domain.stance)


def swing_barrier():
    """The collision-avoidance safe set (``swing_clearance_h``), active in single support
    and checked (Theorem 1) where the first step begins."""
    return SafeSet("swing_foot", swing_clearance_h, 2, SWING_POLES, SWING_MARGIN,
                   active=_single_support, check_domain=first_step_domain,
                   terms=swing_clearance_terms)


def passive_actuators(model, domain):
    """1 for the stance leg's ankle motors (toe-A, toe-B): the passive stance ankle."""
    left = np.array([n in digit.toe_motors("left") for n in model.actuator_names], float)
    right = np.array([n in digit.toe_motors("right") for n in model.actuator_names], float)
    stance = domain.stance
    return jnp.where(stance > 0, left, 0.0) + jnp.where(stance < 0, right, 0.0)


def plan_step(model, q, v, domain):
    """(ALIP state about the stance sole, the planner's FootPlacement, the step vector u
    [2] clipped to the leg's reach), heading frame, from the measured state."""
    heading = domain.heading
    stance = domain.stance
    pl = robot.frame_pose(model, q, digit.LEFT_SOLE)[0]
    pr = robot.frame_pose(model, q, digit.RIGHT_SOLE)[0]
    contact = jnp.where(stance > 0, pl, pr)
    state = alip.alip_state_from_robot(model, q, v, contact, heading)
    mass = jnp.sum(model.body_mass)
    side = jnp.where(stance == 0, 1.0, stance)  # +1: the swing foot goes to the right (-y)
    plan = alip.plan_foot_placement(state.p, state.L, domain.tau_step, STEP_T, H_WALK, mass,
                                    -model.gravity[2], domain.v_des, domain.step_width,
                                    side, average_velocity=True)
    u = jnp.stack([jnp.clip(plan.u[0], *STEP_X),
                   -side * jnp.clip(-side * plan.u[1], *STEP_Y)])
    return state, plan, u


def diagnostics(model, q, v, domain):
    """Per-step walking quantities for the logs (flat array): ALIP p [2], L [2], z, the
    planned step u [2] (clipped), the predicted end-of-step p_end [2] and L_end [2]."""
    state, plan, u = plan_step(model, q, v, domain)
    mom = alip.robot_momentum(model, q, v, jnp.zeros(3))
    lcom = alip.world_to_heading(alip.alip_momentum(mom.L_com), domain.heading)
    vcom = alip.world_to_heading(mom.com_vel[:2], domain.heading)
    return jnp.concatenate([state.p, state.L, state.z[None], u, plan.p_end, plan.L_end, lcom,
                            vcom, mom.com_vel[2:3]])


DIAG_NAMES = ("p_x", "p_y", "L_x", "L_y", "z", "u_x", "u_y", "p_end_x", "p_end_y", "L_end_x",
              "L_end_y", "Lcom_x", "Lcom_y", "v_x", "v_y", "v_z")


# The walking tasks' references, planned at each control step (``tasks.Task.planned``):
# standing (tau < 0) blends the CoM to [stance origin, H]; walking plans the foot placement
# from the measured ALIP state and sends the swing foot there (``alip.swing_foot_reference``,
# see the module docstring).

def _com_reference(model, tau, start, q, v, domain):
    """Standing: the CoM over the inside of the first stance foot at the walking height."""
    def com_ref(s):
        target = jnp.concatenate([start.origin[:2] + jnp.array([0.0, start.gait.half_width
                                                                - START_SHIFT]),
                                  jnp.array([H_WALK])])
        y0 = start.y0["com"]
        return y0 + (target - y0) * references.smoothstep5((s + start.settle) / start.gait.blend)

    return references.with_derivatives(com_ref, jnp.minimum(tau, 0.0))


def _heading_reference(model, tau, start, q, v, domain):
    """Level, facing the heading (the torso; the swing sole kept flat)."""
    zero3 = jnp.zeros(3)
    return jnp.array([0.0, 0.0, 1.0]) * domain.heading, zero3, zero3


def _arms_reference(model, tau, start, q, v, domain):
    return start.arm0, jnp.zeros(8), jnp.zeros(8)


def _swing_reference(model, tau, start, q, v, domain):
    """The swing sole towards the ALIP foot placement planned from (q, v)."""
    heading = domain.heading
    _, _, u = plan_step(model, q, v, domain)
    p_sw0 = alip.world_to_heading((domain.swing0 - domain.stance0)[:2], heading)
    sw = alip.swing_foot_reference(domain.tau_step, STEP_T, p_sw0, u, z0=0.0,
                                   vertical="land", horizontal=SWING_HORIZONTAL)
    base = domain.stance0
    rot = lambda xy: alip.rotate_yaw(xy, heading)  # noqa: E731
    pos = jnp.concatenate([base[:2] + rot(sw.pos[:2]), base[2:3] + sw.pos[2:3]])
    vel = jnp.concatenate([rot(sw.vel[:2]), sw.vel[2:3]])
    acc = jnp.concatenate([rot(sw.acc[:2]), sw.acc[2:3]])
    return pos, vel, acc


def _com_mask(domain):
    """CoM x, y tracked only standing (walking leaves them to the ALIP)."""
    ss = _single_support(domain)
    return jnp.stack([1.0 - ss, 1.0 - ss, jnp.ones_like(ss)])


def _swing_mask(domain):
    return _single_support(domain) * jnp.ones(3)


def walk_tasks():
    return (Task(outputs.CoMPosition(), 100.0, 20.0, 100.0, planned=_com_reference,
                 mask=_com_mask),
            Task(outputs.TorsoOrientation(), 100.0, 20.0, 20.0, planned=_heading_reference),
            Task(outputs.JointPositions(name="arms", joints=outputs.ARM_JOINTS), 900.0, 60.0,
                 1.0, planned=_arms_reference),
            Task(SwingFootPosition(), 900.0, 60.0, 100.0, planned=_swing_reference,
                 mask=_swing_mask),
            Task(SwingFootOrientation(), 400.0, 40.0, 10.0, planned=_heading_reference,
                 mask=_swing_mask))


def make_scenario(name, duration, push=None):
    """A walking scenario of ``duration`` s, with ``push`` (a ``Push``, or None)."""
    return Scenario(name, walk_tasks(), (swing_barrier(),), duration=duration, settle=1.5,
                    blend=1.0, gait=AlipGait(), push=push)


# --------------------------------------------------------------------------------------
# The gait state machine
# --------------------------------------------------------------------------------------

class GaitState(NamedTuple):
    """The gait's state as data (numpy on the host, jax arrays in the batched path):
    stance side (LEFT, RIGHT, BOTH), time in the current step, both soles' positions when
    it began, steps taken and touchdowns missed (forced switches)."""

    stance: Any
    tau_step: Any
    stance0: Any
    swing0: Any
    steps: Any
    missed: Any

    @staticmethod
    def standing(xp=np, dtype=np.float64):
        """Before walking: both feet on the floor, no step taken."""
        z3 = xp.zeros(3, dtype)
        return GaitState(xp.asarray(BOTH, dtype), xp.zeros((), dtype), z3, z3,
                         xp.zeros((), np.int32), xp.zeros((), np.int32))


def gait_step(g: GaitState, tau, dt, sole_left, sole_right, swing_force, weight, xp=np):
    """One control step of the gait, as a pure function of arrays (``xp`` numpy or
    jax.numpy).
    Returns (new GaitState, True where a new step began).

    Walking starts at tau = 0 in left stance. A step ends at touchdown of the swing
    foot, ``swing_force`` its sole's normal force (N) on the floor: from T/2 to T a firm
    one (``EARLY_TOUCHDOWN`` x ``weight``: a foot that really lands early, not a scuff at
    lift-off); from T on any force above ``TOUCH_FORCE`` (the swing reference is then below
    the floor, and a foot that rests without pressing must not keep the step going); at
    2 T the switch is forced and counted in ``missed``. The new stance foot's position
    (``stance0``) and the new swing foot's (``swing0``) are the measured soles."""
    tau, swing_force = xp.asarray(tau), xp.asarray(swing_force)
    started = tau >= 0
    first = started & (g.stance == BOTH)
    stepping = started & (g.stance != BOTH)
    ts = g.tau_step + dt
    early = (ts >= 0.5 * STEP_T) & (swing_force > EARLY_TOUCHDOWN * weight)
    late = (ts >= STEP_T) & (swing_force > TOUCH_FORCE)
    forced = ts >= 2 * STEP_T
    switch = stepping & (early | late | forced)
    begin = first | switch
    stance = xp.where(first, LEFT, xp.where(switch, -g.stance, g.stance))
    left = stance > 0
    new = GaitState(
        stance=stance,
        tau_step=xp.where(begin, 0.0, xp.where(stepping, ts, g.tau_step)),
        stance0=xp.where(begin, xp.where(left, sole_left, sole_right), g.stance0),
        swing0=xp.where(begin, xp.where(left, sole_right, sole_left), g.swing0),
        steps=g.steps + xp.where(switch, 1, 0),
        missed=g.missed + xp.where(switch & ~(early | late), 1, 0))
    return new, begin


class Domain(NamedTuple):
    """The walking domain a control step's QP is built in (``controller.build_qp``): the
    gait state's stance side (+1 left, -1 right, 0 double support), its contact flags
    (left, right), the time into the step, the stance and swing soles' positions at the
    step's start, and the commands (heading, mean speed, step width)."""

    stance: Any
    in_contact: Any
    tau_step: Any
    stance0: Any
    swing0: Any
    heading: Any
    v_des: Any
    step_width: Any


def gait_domain(g: GaitState, heading, v_des, step_width, xp=np) -> Domain:
    """The controller's ``Domain`` of a gait state: contact flags from the stance side,
    and the commands."""
    ic = xp.stack([xp.where(g.stance < 0, 0.0, 1.0), xp.where(g.stance > 0, 0.0, 1.0)])
    return Domain(stance=g.stance, in_contact=ic, tau_step=g.tau_step, stance0=g.stance0,
                  swing0=g.swing0, heading=heading, v_des=v_des, step_width=step_width)


class WalkStart(NamedTuple):
    """Walking's own start data (``scenario.Start.gait``): the standing blend's length
    (s) and how far the left sole is from the stance origin, laterally (m; the CoM goes
    over its inside edge)."""

    blend: jax.Array
    half_width: jax.Array


def walking_start(model, q, start, blend) -> WalkStart:
    """What the walking references need in the run's start data beyond
    ``scenario.start_state`` (``WalkStart``)."""
    pl = robot.frame_pose(model, q, digit.LEFT_SOLE)[0]
    return WalkStart(jnp.asarray(blend), pl[1] - start.origin[1])


@jax.jit
def _sole_positions(model, q):
    """(2, 3): the left and right sole at q, in one compiled call (op by op, each jnp
    operation would compile alone)."""
    return jnp.stack([robot.frame_pose(model, q, f)[0]
                      for f in (digit.LEFT_SOLE, digit.RIGHT_SOLE)])


def first_step_domain(model, q, v_des=0.2):
    """The domain at the start of the first (left-stance) step with the robot at ``q``:
    where walking barriers, inactive while standing, meet Theorem 1 first."""
    pl, pr = np.asarray(_sole_positions(model, jnp.asarray(q)))
    g = GaitState(np.float64(LEFT), np.float64(0.0), pl, pr, 0, 0)
    return gait_domain(g, np.float64(0.0), np.float64(v_des), np.float64(STEP_WIDTH))


@dataclasses.dataclass
class Gait:
    """A host-side (numpy) ``GaitState`` advanced by ``gait_step``, with the commands: the
    gait stepped by hand. The controller itself carries a
    ``GaitState`` in ``control_step.ControllerState`` and advances it in ``prepare``."""

    v_des: float = 0.2
    step_width: float = STEP_WIDTH
    heading: float = 0.0
    stance: float = BOTH
    tau_step: float = 0.0
    stance0: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    swing0: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    steps: int = 0
    missed_touchdowns: int = 0

    def state(self) -> GaitState:
        return GaitState(np.float64(self.stance), np.float64(self.tau_step),
                         np.asarray(self.stance0, float).copy(),
                         np.asarray(self.swing0, float).copy(), self.steps,
                         self.missed_touchdowns)

    def domain(self):
        return gait_domain(self.state(), np.float64(self.heading), np.float64(self.v_des),
                           np.float64(self.step_width))

    def update(self, tau, dt, sole_pos, swing_force, weight):
        """Advance by one control step (``gait_step``). sole_pos: {"left": (3,),
        "right": (3,)} measured; swing_force: the swinging sole's normal force on the
        floor now (N); weight: the robot's weight (N). Returns True when a new step
        began."""
        g, begin = gait_step(self.state(), tau, dt, np.asarray(sole_pos["left"], float),
                             np.asarray(sole_pos["right"], float), swing_force, weight)
        self.stance, self.tau_step = float(g.stance), float(g.tau_step)
        self.stance0, self.swing0 = np.asarray(g.stance0), np.asarray(g.swing0)
        self.steps, self.missed_touchdowns = int(g.steps), int(g.missed)
        return bool(begin)


@dataclasses.dataclass(frozen=True)
class AlipGait:
    """The walking scenarios' gait (``scenario.Scenario.gait``), of the protocol
    ``control.gait.Gait``: its state is a ``GaitState``, its domain a ``Domain``."""

    step_width: float = STEP_WIDTH

    def start_data(self, model, q, start, blend) -> WalkStart:
        return walking_start(model, q, start, blend)

    def advance(self, gait: GaitState, prev_tau, dt, model, q, sole_force, weight):
        """``gait_step`` from the measurement: the soles by forward kinematics of q, the
        swinging sole's normal force."""
        swing = jnp.where(gait.stance > 0, sole_force[1], sole_force[0])
        sole_l = robot.frame_pose(model, q, digit.LEFT_SOLE)[0]
        sole_r = robot.frame_pose(model, q, digit.RIGHT_SOLE)[0]
        return gait_step(gait, prev_tau, dt, sole_l, sole_r, swing, weight, xp=jnp)[0]

    def domain(self, gait: GaitState, speed):
        dtype = gait.tau_step.dtype
        return gait_domain(gait, jnp.zeros((), dtype), speed, jnp.asarray(self.step_width, dtype),
                           xp=jnp)

    def controller_velocity(self, model, q, v, domain):
        """The rates the controller sees: the swing leg's springs held rigid."""
        return rigid_spring_velocity(model, q, v, domain.stance)

    def passive_actuators(self, model, domain):
        return passive_actuators(model, domain)

    def first_domain(self, model, q):
        return first_step_domain(model, q)

    def start_domain(self, model, q):
        """The domain at the start: standing (both feet), the default commands."""
        return gait_domain(GaitState.standing(), np.float64(0.0), np.float64(0.2),
                           np.float64(self.step_width))

    def check_speed(self, speed, option="speed"):
        return check_speed(speed, option)

    def initial(self, xp, dtype) -> GaitState:
        return GaitState.standing(xp, dtype)

    def support(self, state: GaitState) -> Support:
        return Support(state.stance, state.stance0)

    def record(self, state: GaitState) -> dict:
        return {"missed_touchdowns": state.missed}

    def columns(self, state: GaitState) -> dict:
        return {"steps_taken": np.asarray(state.steps),
                "missed_touchdowns": np.asarray(state.missed)}

    def diagnostics(self, model, q, v, domain):
        """The ALIP quantities of a step for the logs (``diagnostics``, ``DIAG_NAMES``)."""
        return diagnostics(model, q, v, domain)
