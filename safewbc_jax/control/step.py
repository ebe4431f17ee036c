"""The control step: a measurement in, the QP, the torque, the record and the metrics out.

    state, prep, qp = prepare(ctx, params, start, run, state, meas)  # measurement -> QP
    sol             = <a QP solver>(qp)                   # jax_qp in JAX, PIQP on the host
    tally, out      = conclude(ctx, run, tally, prep, sol)  # torque, motors, record, metrics

``prepare`` and ``conclude`` are pure JAX functions of typed pytrees; the QP between them is
the seam to the solvers, and their answer (``solvers.result.SolveResult``, the same type
from either solver) comes back to ``conclude``. ``prepare`` carries the ControllerState
(gait, clock, last good measurement), ``conclude`` the Tally (last good torque, metrics):
the next ``prepare`` does not wait for ``conclude``. ``step_jax`` composes the three in one
traced step; ``prepare`` and ``conclude`` can also be jitted apart, with a host solver
(PIQP) between them and ``conclude`` run after the command is out. Everything that decides
about control is here:

* the measurement check (``state_ok``): a refused measurement holds the last good torque,
  does not advance the gait or the clock, and is counted (``bad_measurements``);
* the clock: tau = (t - t_first) - settle, from the first good measurement;
* a domain-driven scenario: its gait (``scenario.gait``, the protocol of ``control.gait``)
  advanced over the control periods since the last good step, from the measurement (q and
  the soles' normal forces); the domain; the rates the gait's controller sees;
* the QP (``controller.robot_terms``, ``controller.build_qp``);
* the torque: the solution's u, or the last good u where the QP failed (``hold_torque``);
  the motor torques in the robot's motor order (``MotorArrays.to_motor``);
* the metrics (``metrics.control_accumulate``) and the fall test (``fallen``).

What stays per simulator is sensing (its data to a ``Measurement``) and pushing.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.control import barriers, terms as controller, metrics
from safewbc_jax.control import gait as gait_mod
from safewbc_jax.control import qp as qp_assembly
from safewbc_jax.model import contacts, robot
from safewbc_jax.control import scenario as scenario_mod
from safewbc_jax.solvers.problem import Blocks
from safewbc_jax.solvers.result import FALLBACK_FAILED, SolveResult
from safewbc_jax.model.digit import FALL_HEIGHT

DEFAULT_CONTROL_DT = 1e-3   # s: the paper's 1 kHz
DEFAULT_SPEED = 0.2         # m/s: walking's commanded mean forward speed
# Measurement bounds. |quat| is 1 to ~1e-15 from any estimator that normalises; 1e-3 is far
# above that and far below an error that changes the controller's rotation noticeably.
QUAT_TOL = 1e-3
# Angular rates (joints and base, rad/s) and base speed (m/s): in the MuJoCo runs the
# fastest joint peaks at ~7 rad/s (knees, walking at 0.2 m/s; undamped springs and
# touchdowns included) and the base at 0.4 m/s; a humanoid's joints and a fall stay well
# within 100 rad/s and 20 m/s, so an estimate beyond them is a fault, not a motion.
MAX_RATE = 100.0
MAX_SPEED = 20.0


@functools.partial(jax.tree_util.register_dataclass, data_fields=["q", "v", "sole_force", "t"],
                   meta_fields=[])
@dataclasses.dataclass(frozen=True)
class Measurement:
    """What the robot's estimator hands over each control step (docs/models.md, Conventions):
    q (37,), v (36,), the soles' normal forces on the floor (2,) in N (left, right; None is
    allowed in double-support scenarios), and the time stamp t in s (any clock that
    advances; the controller's clock starts at the first good measurement)."""

    q: np.ndarray
    v: np.ndarray
    t: Any                  # s: a float, or a JAX scalar in the batched path
    sole_force: np.ndarray | None = None


def state_tests(q, v, xp=np):
    """The tests a robot state (q, v) must pass, each True where it does: (finite, the
    base quaternion of unit length within QUAT_TOL, the base speed within MAX_SPEED, every
    angular rate within MAX_RATE); a NaN fails every comparison. Leading axes of q and v
    are a batch of states; the results have those axes."""
    n2 = xp.sum(q[..., 3:7] ** 2, axis=-1)
    return (xp.isfinite(xp.sum(q, axis=-1)) & xp.isfinite(xp.sum(v, axis=-1)),
            xp.abs(xp.sqrt(n2) - 1.0) <= QUAT_TOL,
            xp.sum(v[..., :3] ** 2, axis=-1) <= MAX_SPEED ** 2,
            xp.max(xp.abs(v[..., 3:]), axis=-1) <= MAX_RATE)


def state_ok(q, v, xp=np):
    """True where (q, v) passes every test of ``state_tests``: can be a state of the
    robot. Leading axes: a batch, as there."""
    finite, unit, speed, rates = state_tests(q, v, xp)
    return finite & unit & speed & rates


def fallen(q, v, xp=np):
    """The fall test, on a measurement: a non-finite state, or the base below FALL_HEIGHT
    (q[2], the floating base's height). Leading axes: a batch, as in ``state_ok``."""
    finite = xp.isfinite(xp.sum(q, axis=-1)) & xp.isfinite(xp.sum(v, axis=-1))
    return ~finite | (q[..., 2] < FALL_HEIGHT)


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["u_index", "gear", "motor_limit"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class MotorArrays:
    """The motor map as arrays (``deploy.MotorMap``): index of each motor's torque in u,
    gear ratio, motor-side torque limit, in the robot's motor order."""

    u_index: np.ndarray
    gear: np.ndarray
    motor_limit: np.ndarray

    def to_motor(self, u, xp=np):
        """Joint torques u (controller actuator order) -> motor torques u / gear, in motor
        order, clipped to the motor limits."""
        m = u[..., self.u_index] / self.gear
        return xp.clip(m, -self.motor_limit, self.motor_limit)


def hold_torque(x, usable, last_u, blocks: Blocks, xp=np):
    """The torque to apply: the solution's u (``blocks``: the QP's block sizes, e.g.
    ``QP.blocks``) where the solve is usable, else the last good u."""
    return xp.where(usable, blocks.split(x)[1], last_u)


@dataclasses.dataclass(frozen=True, eq=False)
class Context:
    """What a control step is compiled for (static: hashed by identity): the controller
    model, the scenario (barriers off: ``Scenario.without_barriers``), the control period,
    the motor map, the robot's weight (N, the gait's early-touchdown test), and the JAX
    solver's settings (``precision.qp_settings``)."""

    model: robot.RobotModel
    scenario: scenario_mod.Scenario
    control_dt: float
    motors: MotorArrays
    qp_settings: Any = None      # jax_qp.Settings of step_jax's solve (None: float64's)
    weight: float = dataclasses.field(init=False)     # N, from the model (__post_init__)

    @property
    def walking(self) -> bool:
        return self.scenario.gait is not None

    @property
    def blocks(self) -> Blocks:
        """The block sizes of the QP's X = [q_ddot, u, lambda], the model's (``qp.assemble``
        reads the same sizes off the model's B)."""
        return Blocks(self.model.nv, self.model.nu)

    def __post_init__(self):
        # evaluated here, eagerly: under a jit trace jnp operations on the model's constants
        # are traced too
        object.__setattr__(self, "weight",
                           float(-self.model.gravity[2] * self.model.total_mass))
        # every safe set's h, traced once (nothing compiles): a user's h of the wrong shape
        # or one that fails is refused here, naming it, before the step compiles
        q0 = np.zeros(self.model.nq)
        q0[3] = 1.0
        for s in self.scenario.safe_sets:
            s.check(self.model, jnp.asarray(q0), jnp.zeros(self.model.nv),
                    self.scenario.theorem_domain(self.model, s, q0))


def schedule(scenario, duration=None, settle=None, control_dt=DEFAULT_CONTROL_DT, what=""):
    """(control steps, settle s, duration s) of a run: the scenario's defaults where None;
    raises ValueError, naming ``what`` + the option, for a settle shorter than the
    reference blend, a duration or a control period that is not a positive number."""
    settle = scenario.settle if settle is None else float(settle)
    duration = scenario.duration if duration is None else float(duration)
    if not (np.isfinite(control_dt) and control_dt > 0):
        raise ValueError(f"{what}control_dt = {control_dt!r}: must be a positive number")
    if not (np.isfinite(duration) and duration > 0):
        raise ValueError(f"{what}duration = {duration!r}: must be a positive number")
    if not (np.isfinite(settle) and settle >= scenario.blend):
        raise ValueError(f"{what}settle = {settle}: must cover the reference blend "
                         f"({scenario.blend} s)")
    return int(round((settle + duration) / control_dt)), settle, duration


class RunValues(NamedTuple):
    """Run-time values of a control step (traced: runs that differ in them share a
    compile): the settle time (s), the walking speed command (m/s), and the time after
    the first measurement (s) at which the second half of the motion begins, where
    ``avg_forward_speed`` is measured from (negative: not measured)."""

    settle: jax.Array
    speed: jax.Array
    t_half: jax.Array


def start_data(model, scenario, q) -> scenario_mod.Start:
    """The references' start data, measured at the start pose q (``scenario.start_state``,
    the outputs' start values; a gait's own, ``gait.start_data``). The settle time is not
    part of it: it is the run's (``RunValues``).

    One jitted call per scenario: op by op, these kinematics cost a fresh process seconds
    (benchmarks/README.md, "Figures behind design choices")."""
    return _start_data(model, scenario, jnp.asarray(q))


@functools.partial(jax.jit, static_argnums=1)
def _start_data(model, scenario, q) -> scenario_mod.Start:
    start = scenario_mod.start_state(model, q)
    start = dataclasses.replace(start, y0=controller.output_start_values(model, scenario, q))
    if scenario.gait is not None:
        start = dataclasses.replace(
            start, gait=scenario.gait.start_data(model, q, start, scenario.blend))
    return start


class ControllerState(NamedTuple):
    """What ``prepare`` carries from one step to the next: the gait's state (its own
    pytree, ``control.gait``; () without a gait); the last accepted state, time and tau;
    the clock's origin (NaN before the first good measurement)."""

    gait: Any
    last_q: jax.Array
    last_v: jax.Array
    t0: jax.Array
    prev_t: jax.Array
    prev_tau: jax.Array


class Tally(NamedTuple):
    """What ``conclude`` carries from one step to the next: the last good torque (held
    where a QP fails or a measurement is refused) and the metric accumulators
    (``metrics.ControlAcc``)."""

    last_u: jax.Array
    acc: metrics.ControlAcc


def init_state(ctx: Context, q, v, xp=jnp, dtype=jnp.float64) -> tuple[ControllerState, Tally]:
    """(ControllerState, Tally) before the first step, at the start state (q, v)."""
    nan = xp.asarray(np.nan, dtype)
    return (ControllerState(gait_mod.initial(ctx.scenario.gait, xp, dtype), xp.asarray(q, dtype),
                            xp.asarray(v, dtype), nan, nan, nan),
            Tally(xp.zeros(ctx.model.nu, dtype), metrics.control_init(ctx.scenario, xp, dtype)))


class Prepared(NamedTuple):
    """``prepare``'s output: whether the measurement was accepted, the state and time the
    QP was built at (v with the rigid swing-leg rates), the domain (walking; None else),
    and the QP's aux (output values and references, barrier values). The QP itself is
    returned beside it (it goes to the solver, not to ``conclude``)."""

    ok: jax.Array
    q: jax.Array
    v: jax.Array
    t_rel: jax.Array
    tau: jax.Array
    gait: Any               # the gait's state (() without a gait)
    domain: Any             # the gait's domain, or None
    aux: controller.QPAux


def prepare(ctx: Context, params, start, run: RunValues, state: ControllerState,
            meas: Measurement):
    """Measurement -> QP (module docstring). Returns (state with the gait advanced,
    Prepared, the QP).
    A refused measurement builds the QP at the last good state (its result is not used)."""
    model, sc = ctx.model, dataclasses.replace(ctx.scenario, settle=run.settle)  # type: ignore[arg-type]
    q_in, v_in = jnp.asarray(meas.q), jnp.asarray(meas.v)
    dtype = q_in.dtype
    force = jnp.zeros(2, dtype) if meas.sole_force is None else jnp.asarray(meas.sole_force, dtype)
    t = jnp.asarray(meas.t, dtype)
    started = jnp.isfinite(state.t0)
    ok = (state_ok(q_in, v_in, jnp) & jnp.all(jnp.isfinite(force)) & jnp.isfinite(t)
          & (~started | (t > state.prev_t)))
    q = jnp.where(ok, q_in, state.last_q)
    v = jnp.where(ok, v_in, state.last_v)
    t0 = jnp.where(started, state.t0, t)
    t = jnp.where(ok, t, state.prev_t)
    tau = (t - t0) - run.settle
    gait, domain = state.gait, None
    if sc.gait is not None:
        dt = ctx.control_dt
        periods = jnp.maximum(1.0, jnp.round((t - state.prev_t) / dt))
        new = sc.gait.advance(gait, state.prev_tau, periods * dt, model, q, force, ctx.weight)
        advance = ok & started
        gait = jax.tree_util.tree_map(lambda a, b: jnp.where(advance, a, b), new, gait)
        domain = sc.gait.domain(gait, run.speed)
        v = sc.gait.controller_velocity(model, q, v, domain)
        start = dataclasses.replace(start, settle=run.settle)
    terms = controller.robot_terms(model, sc, q, v, domain)
    qpm, aux = controller.build_qp(model, sc, params, terms, q, v, tau, start,
                                   jnp.asarray(sc.in_contact, dtype), domain=domain)
    keep = lambda new, old: jnp.where(ok, new, old)  # noqa: E731
    state = ControllerState(gait=gait, last_q=q, last_v=keep(v_in, state.last_v),
                            t0=keep(t0, state.t0), prev_t=t, prev_tau=keep(tau, state.prev_tau))
    return state, Prepared(ok, q, v, t - t0, tau, gait, domain, aux), qpm


class Output(NamedTuple):
    """``conclude``'s output: joint torques u (controller actuator order), motor torques
    (the robot's motor order), and this step's record (``StepRecord``)."""

    u: jax.Array
    motor: jax.Array
    record: "StepRecord"


class StepRecord(NamedTuple):
    """One step, for logs and trajectories: the measurement accepted; tau; the solver's
    status, fallback and iterations; u; lambda (NaN where the QP failed); the ZMP margin
    over the domain's support polygon (NaN where the QP failed); the stance side (0: both
    feet) and the stance sole's position when its step began (``gait.Support``); the
    gait's own fields ({} without a gait); each output's value and reference (a component
    not tracked in this domain: reference NaN); each barrier's value h."""

    ok: jax.Array
    tau: jax.Array
    status: jax.Array
    fallback: jax.Array
    iterations: jax.Array
    eq_residual: jax.Array
    u: jax.Array
    lam: jax.Array
    zmp_margin: jax.Array
    stance: jax.Array
    stance0: jax.Array
    gait: dict
    y: dict
    yd: dict
    h: dict


def conclude(ctx: Context, run: RunValues, tally: Tally, prep: Prepared, sol: SolveResult):
    """The solver's answer (a ``SolveResult`` over the full X, from either solver) ->
    (new Tally, Output): the torque held where the QP failed or the measurement was
    refused, the motor torques, the record, the metrics accumulated. Depends on
    ``prepare``'s output only (the gait of the record is the domain's)."""
    model, sc = ctx.model, ctx.scenario
    x = jnp.asarray(sol.x)
    usable = prep.ok & (sol.fallback != FALLBACK_FAILED) & jnp.all(jnp.isfinite(x))
    u = hold_torque(x, usable, tally.last_u, ctx.blocks, jnp)
    # lambda: the chain rows' forces first, then the contacts' (controller.build_qp)
    lam = jnp.where(usable, ctx.blocks.split(x)[2][controller.n_chain_rows(model):], jnp.nan)
    domain = prep.domain
    in_contact = domain.in_contact if domain is not None else jnp.asarray(sc.in_contact)
    margin = contacts.zmp_margin(model, prep.q, jnp.where(usable, lam, 0.0),
                                 jnp.asarray(in_contact, prep.q.dtype))
    margin = jnp.where(usable, margin, jnp.nan)
    mask = sc.masks(domain)
    y = {n: ya for n, (ya, _) in prep.aux.outputs.items()}
    yd = {n: jnp.where(mask[n] > 0, yd_, jnp.nan) if n in mask else yd_
          for n, (_, yd_) in prep.aux.outputs.items()}
    support = gait_mod.support(sc.gait, prep.gait, jnp, prep.q.dtype)
    rec = StepRecord(ok=prep.ok, tau=prep.tau, status=jnp.asarray(sol.status, jnp.int32),
                     fallback=jnp.asarray(sol.fallback, jnp.int32),
                     iterations=jnp.asarray(sol.iterations, jnp.int32),
                     eq_residual=jnp.where(usable, sol.eq_residual, jnp.nan), u=u, lam=lam,
                     zmp_margin=margin, stance=support.stance, stance0=support.stance0,
                     gait={} if sc.gait is None else sc.gait.record(prep.gait), y=y, yd=yd,
                     h=dict(prep.aux.barrier_h))
    acc = metrics.control_accumulate(tally.acc, rec, prep.t_rel, run.t_half,
                                     jnp.asarray(model.torque_limit), xp=jnp)
    return Tally(u, acc), Output(u, ctx.motors.to_motor(u, jnp), rec)


def step_jax(ctx: Context, params, start, run: RunValues, state: ControllerState,
             tally: Tally, meas: Measurement):
    """prepare -> the JAX QP solver (``jax_qp.solve``, fallback policy included; the block
    sizes from the QP) -> conclude: the whole step in JAX (the batched path). The
    controller's P has no cross blocks (``qp.assemble``: Gamma diagonal, the tasks on
    q_ddot; its u and lambda blocks are the diagonal Gamma), so only its diagonal blocks
    enter the elimination, the lambda block as its diagonal."""
    from safewbc_jax.solvers import jax_qp

    state, prep, qpm = prepare(ctx, params, start, run, state, meas)
    res = jax_qp.solve(qpm, p_blockdiag=qp_assembly.P_STRUCTURE, settings=ctx.qp_settings)
    tally, out = conclude(ctx, run, tally, prep, res)
    return state, tally, out


# ----------------------------------------------------------------------------- Theorem 1

def start_eta_fn(model, scenario, barrier, q):
    """(v, threshold) -> eta(x_0) (r,) of ``barrier`` (a SafeSet of ``scenario``) at the
    start state (q, v): the values Theorem 1 (eq. 25) is checked on, in the domain
    ``Scenario.theorem_domain`` gives (a barrier active only in some domains, like the
    swing-foot barrier, where it first becomes active). Pure JAX in (v, threshold), so it
    vmaps over start velocities."""
    domain = scenario.theorem_domain(model, barrier, q)

    def eta(v, threshold):
        return barriers.barrier_lie_derivatives(barrier.h_fn(model, threshold, domain), q, v,
                                                barrier.relative_degree)[0]

    return eta


class StartCheck:
    """Theorem 1 (eq. 25) at start states (q, v_i) of ``scenario``, all at one
    configuration q. Each barrier's eta(x_0) (``start_eta_fn``) is vmapped over the start
    velocities and thresholds (``etas``), or taken at one start state (``eta``), and
    jitted once per barrier where ``jit`` (False: eager, for a single check that would not
    repay a compile)."""

    def __init__(self, model, scenario, q, jit: bool = True):
        self.model, self.scenario, self.q = model, scenario, jnp.asarray(q)
        self._jit = bool(jit)
        self._eta: dict = {}

    def _fn(self, name: str, batched: bool):
        fn = self._eta.get((name, batched))
        if fn is None:
            b = next(b for b in self.scenario.barriers if b.name == name)
            fn = start_eta_fn(self.model, self.scenario, b, self.q)
            fn = jax.vmap(fn) if batched else fn
            fn = self._eta[(name, batched)] = jax.jit(fn) if self._jit else fn
        return fn

    def etas(self, name: str, v, thresholds) -> np.ndarray:
        """(N, r) eta(x_0) of barrier ``name`` at velocities v (N, nv) with thresholds (N,)."""
        return np.asarray(self._fn(name, True)(jnp.asarray(v), jnp.asarray(thresholds)))

    def eta(self, name: str, v, threshold) -> np.ndarray:
        """(r,) eta(x_0) of barrier ``name`` at one velocity v (nv,) and threshold: not
        vmapped (a vmap's trace of the barrier chain takes half as long again, which a
        deployed controller's start pays)."""
        return np.asarray(self._fn(name, False)(jnp.asarray(v), jnp.asarray(threshold)))

    def check(self, params, v, batched: bool = True) -> None:
        """Raise barriers.PoleError unless every barrier's poles are admissible at each
        start state. ``batched``: params with a leading axis N, v (N, nv), the error names
        the rollout; else one robot's params and v (nv,)."""
        for b in self.scenario.barriers:
            if batched:
                etas = self.etas(b.name, v, params.threshold[b.name])
                poles = params.poles[b.name]
            else:
                etas = self.eta(b.name, v, params.threshold[b.name])[None]
                poles = np.asarray(params.poles[b.name])[None]
            check_start_poles(b.name, etas, poles, batched)


def check_start_poles(name: str, etas, poles, batched: bool) -> None:
    """Theorem 1 (``barriers.check_poles``) for barrier ``name`` at each start state:
    etas and poles (N, r). Raises barriers.PoleError naming the barrier, the pole, its
    bound and, where ``batched``, the rollout."""
    etas, poles = np.asarray(etas), np.asarray(poles)
    for i in range(etas.shape[0]):
        try:
            barriers.check_poles(name, etas[i], poles[i])
        except barriers.PoleError as e:
            if not batched:
                raise
            raise barriers.PoleError(f"rollout {i}: {e}") from None
