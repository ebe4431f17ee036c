"""Closed-loop MJX rollouts: the controller and the MJX physics of ``models/scene.xml``
stepped together, scanned over time, vmapped over a batch of ControllerParams, pushes and
initial velocity perturbations. Every scenario of the deployment loop runs here: squat,
bow, arms, and walking ("walk", "push") with its gait state carried per rollout.

One control step of one rollout (the deployment loop's step, in JAX):

    simulator state -> controller (q, v)                  (statemap indices)
    robot_terms, build_qp                                 (the same functions as the MuJoCo loop)
    jax_qp.solve                                          (reduced QP in u, interior point,
                                                           polish, fallback policy)
    u from X; the last good u held where even the relaxed QP fails
    ctrl = clip(u[act_idx] / gear), push force on the base body, n_sub mjx.step
    metrics updated on the device (names of metrics.json)

Walking adds, as in the deployment loop (``sim.mujoco_loop``): the domain from the gait
state (``walking.gait_domain``), the swing leg's rates with rigid springs
(``walking.rigid_spring_velocity``) fed to the controller, and after the physics the gait
advanced by ``walking.gait_step`` from each sole's normal force on the floor (MJX's
pyramid constraint forces, summed as ``mj_contactForce`` does) and the measured soles.

A rollout that falls (base below ``FALL_HEIGHT`` or a non-finite state) is frozen at its
last state and flagged; its metrics stop accumulating. A failed QP is counted and holds the
last torque. Neither touches the other rollouts of the batch.

The batch is sharded over the process's devices (``jax.local_devices()``, leading axis),
padded to a multiple of the device count. On a CPU with one device it runs in chunks of
``CPU_CHUNK`` rollouts, one after the other inside the compiled call (``run_batch``'s
``chunk``).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax import contacts, controller, metrics, walking
from safewbc_jax.chunking import check_chunk, chunked, resolve_chunk
from safewbc_jax.mjx_import import import_mjx
from safewbc_jax.modelinfo import control_substeps, foot_contact_ids, loop_site_pairs
from safewbc_jax.params import ControllerParams
from safewbc_jax.scenarios import SCENARIOS, WALKING, get_scenario, start_state
from safewbc_jax.control_step import FALL_HEIGHT, check_start_poles, start_eta_fn
from safewbc_jax.push import Push, force_at
from safewbc_jax.sim.mujoco_loop import load_at_stand
from safewbc_jax.solvers import jax_qp

BATCHED_SCENARIOS = tuple(SCENARIOS) + WALKING   # squat, bow, arms, walk, push


@dataclasses.dataclass(frozen=True)
class BatchConfig:
    """What every rollout of a batch shares (static: one compile per config and batch
    size). ``decimate`` k > 0 keeps every k-th control step's trajectory."""

    scenario: str = "squat"
    barrier: bool = True
    duration: float | None = None     # s of motion (scenario default when None)
    settle: float | None = None       # s of standing before it (scenario default)
    control_dt: float = 1e-3
    decimate: int = 0
    speed: float = 0.2                # walking: commanded mean forward speed (m/s)


class BatchError(ValueError):
    """Bad input to a batch (shapes, scenario, config), raised before anything compiles."""


# ----------------------------------------------------------------------------- the plant

@dataclasses.dataclass(frozen=True, eq=False)
class Plant:
    """Host-side constants of one config: models, index maps, the start state."""

    cfg: BatchConfig
    scenario: object
    model: object            # RobotModel (controller)
    mjx_model: object
    data0: object            # mjx.Data at the stand keyframe (dtypes as mjx.step returns)
    qpos_idx: np.ndarray
    qvel_idx: np.ndarray
    act_idx: np.ndarray
    gear: np.ndarray
    ctrl_lo: np.ndarray
    ctrl_hi: np.ndarray
    base_id: int
    sole_sites: np.ndarray
    tip_sites: np.ndarray
    anchor_sites: np.ndarray
    sole0_xy: np.ndarray
    start: dict
    q0: np.ndarray
    v0: np.ndarray
    n_sub: int
    sim_dt: float
    nv_sim: int
    walking: bool
    weight: float            # N
    floor_geom: int
    sole_geoms: np.ndarray   # (2,) left, right
    leg_geoms: np.ndarray    # (2, k) collision geoms of the left and the right leg
    contact_rows: np.ndarray  # (ncon, 4) efc rows of each MJX contact's pyramid, -1 padded

    def schedule(self, cfg: BatchConfig) -> tuple[int, float]:
        """(control steps, settle seconds) of a config (run-time values: configs that
        differ only in duration and settle share one compiled function)."""
        sc = self.scenario
        settle = sc.settle if cfg.settle is None else float(cfg.settle)
        duration = sc.duration if cfg.duration is None else float(cfg.duration)
        if settle < sc.blend:
            raise BatchError(f"BatchConfig.settle = {settle}: must cover the reference "
                             f"blend ({sc.blend} s)")
        return int(round((settle + duration) / cfg.control_dt)), settle


def _check_config(cfg: BatchConfig) -> None:
    if cfg.scenario not in BATCHED_SCENARIOS:
        known = ", ".join(BATCHED_SCENARIOS)
        raise BatchError(f"scenario {cfg.scenario!r} is not available in the batched path "
                         f"(available: {known})")
    if not np.isfinite(cfg.speed):
        raise BatchError(f"BatchConfig.speed = {cfg.speed!r}: must be a finite number")
    for name in ("duration", "settle"):
        val = getattr(cfg, name)
        if val is not None and not (np.isfinite(val) and val >= 0):
            raise BatchError(f"BatchConfig.{name} = {val!r}: must be a finite number >= 0")
    if cfg.duration is not None and cfg.duration <= 0:
        raise BatchError(f"BatchConfig.duration = {cfg.duration!r}: must be positive")
    if not (cfg.control_dt > 0):
        raise BatchError(f"BatchConfig.control_dt = {cfg.control_dt!r}: must be positive")
    if int(cfg.decimate) != cfg.decimate or cfg.decimate < 0:
        raise BatchError(f"BatchConfig.decimate = {cfg.decimate!r}: must be an integer >= 0")


def _contact_rows(mjx, ms) -> np.ndarray:
    """The efc rows of each of MJX's (fixed) contact slots: 2 (condim - 1) pyramid edges
    (1 for a frictionless contact), -1 padded to 4."""
    if ms.opt.cone != 0:
        raise BatchError("the batched path reads contact forces of pyramidal cones only")
    con = mjx.make_data(ms)._impl.contact
    addr, dim = np.asarray(con.efc_address), np.asarray(con.dim)
    n = np.where(dim == 1, 1, 2 * (dim - 1))
    width = max(int(n.max()) if n.size else 1, 1)
    rows = np.full((addr.size, width), -1)
    for i, (a, k) in enumerate(zip(addr, n)):
        if a >= 0:
            rows[i, :k] = a + np.arange(k)
    return rows


def plant(cfg: BatchConfig) -> Plant:
    """The host-side constants of a config (validated first)."""
    _check_config(cfg)
    pl = _plant(cfg.scenario, cfg.barrier, float(cfg.control_dt))
    pl.schedule(cfg)
    return pl


@functools.lru_cache(maxsize=8)
def _plant(scenario: str, barrier: bool, control_dt: float) -> Plant:
    cfg = BatchConfig(scenario=scenario, barrier=barrier, control_dt=control_dt)
    mjx = import_mjx()
    ms, mc, model, sm, d = load_at_stand()
    sc = get_scenario(cfg.scenario, cfg.barrier)
    n_sub = control_substeps(ms, cfg.control_dt)
    if n_sub is None:
        raise BatchError(f"BatchConfig.control_dt = {cfg.control_dt}: must be a positive "
                         f"multiple of the simulation step {ms.opt.timestep}")

    q0, v0 = (np.asarray(a) for a in sm.to_controller(d.qpos, d.qvel))
    start = start_state(model, jnp.asarray(q0))
    start["y0"] = controller.output_start_values(model, sc, jnp.asarray(q0))
    is_walking = cfg.scenario in WALKING
    if is_walking:   # as the deployment loop; "settle" is set per run (run-time value)
        start.update(walking.walking_start(model, jnp.asarray(q0), start, sc.blend))

    mx = mjx.put_model(ms)
    dx = mjx.put_data(ms, d)
    # put_data and step disagree on some integer dtypes under x64: make the initial data
    # look like what step returns, so it can be a scan carry.
    shape = jax.eval_shape(mjx.step, mx, dx)
    dx = jax.tree_util.tree_map(lambda a, s: jnp.asarray(a, s.dtype), dx, shape)

    tips, anchors = loop_site_pairs(ms)
    ids = foot_contact_ids(ms)
    soles = ids["sole_sites"]
    return Plant(
        cfg=cfg, scenario=sc, model=model, mjx_model=mx, data0=dx,
        qpos_idx=np.asarray(sm.qpos_idx), qvel_idx=np.asarray(sm.qvel_idx),
        act_idx=np.asarray(sm.act_idx), gear=np.asarray(sm.gear, float),
        ctrl_lo=ms.actuator_ctrlrange[:, 0].copy(), ctrl_hi=ms.actuator_ctrlrange[:, 1].copy(),
        base_id=ms.body("base").id, sole_sites=soles, tip_sites=tips, anchor_sites=anchors,
        sole0_xy=d.site_xpos[soles, :2].copy(),
        start=start, q0=q0, v0=v0, n_sub=n_sub, sim_dt=float(ms.opt.timestep), nv_sim=ms.nv,
        walking=is_walking, weight=float(-model.gravity[2] * model.total_mass),
        floor_geom=ids["floor"], sole_geoms=ids["sole_geoms"], leg_geoms=ids["legs"],
        contact_rows=_contact_rows(mjx, ms))


# ----------------------------------------------------------------------------- validation

def default_params(scenario: str, batch: int) -> ControllerParams:
    """The scenario's default ControllerParams with a leading batch axis on every leaf."""
    p = get_scenario(scenario).default_params()
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (batch,) + a.shape), p)


def _leaf_name(path) -> str:
    return "".join(str(k) for k in path).lstrip(".")


def _check_inputs(pl: Plant, params, push: Push, perturb_v) -> int:
    ref = pl.scenario.default_params()
    ref_leaves, ref_tree = jax.tree_util.tree_flatten_with_path(ref)
    try:
        leaves = ref_tree.flatten_up_to(params)
    except (ValueError, TypeError) as e:
        raise BatchError(f"params do not have the structure of the {pl.cfg.scenario!r} "
                         f"scenario's ControllerParams: {e}") from None
    batch = None
    for (path, r), a in zip(ref_leaves, leaves):
        a = np.shape(a)
        if len(a) != len(r.shape) + 1 or tuple(a[1:]) != tuple(r.shape):
            raise BatchError(f"params.{_leaf_name(path)} has shape {a}; expected "
                             f"(batch,) + {tuple(r.shape)}")
        if batch is None:
            batch = a[0]
        elif a[0] != batch:
            raise BatchError(f"params.{_leaf_name(path)} has batch size {a[0]}, others {batch}")
    if not batch:
        raise BatchError("the batch is empty")
    for name, arr, shape in (("push.force", push.force, (batch, 3)), ("push.at", push.at, (batch,)),
                             ("push.duration", push.duration, (batch,)),
                             ("perturb_v", perturb_v, (batch, pl.nv_sim))):
        if np.shape(arr) != shape:
            raise BatchError(f"{name} has shape {np.shape(arr)}; expected {shape}")
        if not np.all(np.isfinite(np.asarray(arr))):
            raise BatchError(f"{name} has non-finite entries")
    if np.any(np.asarray(push.duration) < 0):
        raise BatchError("push.duration must be >= 0")
    return int(batch)


@functools.lru_cache(maxsize=16)
def _start_eta(pl: Plant, name: str):
    """jit(vmap): (v0, threshold) -> eta(x0) of barrier ``name`` at the stand pose
    (``control_step.start_eta_fn``)."""
    b = next(b for b in pl.scenario.barriers if b.name == name)
    return jax.jit(jax.vmap(start_eta_fn(pl.model, b, jnp.asarray(pl.q0))))


def start_etas(pl: Plant, name: str, perturb_v, thresholds) -> np.ndarray:
    """(N, r) eta(x_0) of barrier ``name`` at N start states: the stand pose with the
    simulator velocity perturbations ``perturb_v`` (N, nv_sim) and thresholds (N,)."""
    v0 = np.asarray(perturb_v)[:, pl.qvel_idx] + pl.v0
    return np.asarray(_start_eta(pl, name)(jnp.asarray(v0), jnp.asarray(thresholds)))


def check_batch_poles(pl: Plant, params, perturb_v) -> None:
    """Theorem 1 for every rollout at its own start state (velocity perturbation and
    threshold included), before anything long compiles: PoleError names the rollout."""
    for b in pl.scenario.barriers:
        check_start_poles(b.name, start_etas(pl, b.name, perturb_v, params.threshold[b.name]),
                          params.poles[b.name], batched=True)


# ----------------------------------------------------------------------------- the loop

class Acc(NamedTuple):
    """Per-rollout running metrics."""

    alive: jax.Array
    fell_step: jax.Array
    n_none: jax.Array
    n_relaxed: jax.Array
    n_failed: jax.Array
    track_sq: dict
    track_n: dict
    h_min: dict
    zmp_min: jax.Array
    slip_max: jax.Array
    torque_max: jax.Array
    loop_max: jax.Array
    # walking (left at their start values in the other scenarios)
    legs_prev: jax.Array
    leg_collisions: jax.Array
    leg_contact_steps: jax.Array
    clearance_min: jax.Array
    com_x_half: jax.Array
    com_x_end: jax.Array


def _acc0(pl: Plant, dtype) -> Acc:
    sc = pl.scenario
    z = jnp.zeros((), dtype)
    inf = jnp.asarray(jnp.inf, dtype)
    i0 = jnp.zeros((), jnp.int32)
    return Acc(alive=jnp.asarray(True), fell_step=jnp.asarray(-1, jnp.int32),
               n_none=i0, n_relaxed=i0, n_failed=i0, track_sq={o.name: z for o in sc.outputs},
               track_n={o.name: i0 for o in sc.outputs},
               h_min={b.name: inf for b in sc.barriers + sc.monitors},
               zmp_min=inf, slip_max=z, torque_max=z, loop_max=z,
               legs_prev=jnp.asarray(False), leg_collisions=i0, leg_contact_steps=i0,
               clearance_min=inf, com_x_half=jnp.asarray(jnp.nan, dtype),
               com_x_end=jnp.asarray(jnp.nan, dtype))


class Run(NamedTuple):
    """Run-time (traced) values shared by the batch: the scenario with its settle time,
    the number of control steps; walking: the commanded speed, and the control step at
    which the second half of the walk begins (``avg_forward_speed``, as in
    ``metrics.summarize``)."""

    scenario: object
    n_steps: jax.Array
    speed: jax.Array
    k_half: jax.Array


def _control(pl: Plant, sc, params, q, v, tau, last_u, start, domain):
    """One controller step: (u to apply, lambda, solver Result, aux of build_qp)."""
    model = pl.model
    nv, nu = model.nv, model.nu
    terms = controller.robot_terms(model, sc, q, v, domain)
    qpm, aux = controller.build_qp(model, sc, params, terms, q, v, tau, start,
                                   jnp.asarray(sc.in_contact, q.dtype),
                                   barrier_on=pl.cfg.barrier, domain=domain)
    res = jax_qp.solve(qpm, nv=nv, nu=nu, p_blockdiag=True)
    ok = res.fallback != jax_qp.FALLBACK_FAILED
    u = jnp.where(ok, res.x[nv:nv + nu], last_u)
    lam = res.x[nv + nu + controller.n_chain_rows(model):]
    return u, lam, res, aux


def _physics(pl: Plant, dx, u, push: Push, tau):
    mjx = import_mjx()
    ctrl = jnp.clip(u[pl.act_idx] / pl.gear, pl.ctrl_lo, pl.ctrl_hi)
    xfrc = jnp.zeros_like(dx.xfrc_applied).at[pl.base_id, :3].set(force_at(push, tau, jnp))
    dx = dx.replace(ctrl=ctrl, xfrc_applied=xfrc)
    for _ in range(pl.n_sub):
        dx = mjx.step(pl.mjx_model, dx)
    return dx


def _update(pl: Plant, acc: Acc, live, tau, q, u, lam, res, aux, dx_new, domain) -> Acc:
    """Metrics of this step (counted where ``live``: alive and inside the run). Walking:
    output components not tracked in this domain are left out of the tracking RMS, and
    in single support the slip is the stance sole's, from where its step began (as
    ``metrics.summarize`` and the MuJoCo loop)."""
    model, sc = pl.model, pl.scenario
    fb = res.fallback
    count = lambda c: jnp.where(live & c, 1, 0).astype(jnp.int32)  # noqa: E731
    track = live & (tau >= metrics.TRACKING_SKIP_S)
    mask = sc.weight_mask(domain) if domain is not None else {}
    track_sq, track_n = {}, {}
    for o in sc.outputs:
        ya, yd = aux["outputs"][o.name]
        m = mask.get(o.name, jnp.ones(o.dim))
        row = track & jnp.any(m > 0)
        track_sq[o.name] = acc.track_sq[o.name] + jnp.where(
            row, jnp.sum(jnp.where(m > 0, ya - yd, 0.0) ** 2), 0.0)
        track_n[o.name] = acc.track_n[o.name] + jnp.where(row, 1, 0).astype(jnp.int32)
    h_min = {n: jnp.where(live, jnp.minimum(acc.h_min[n], aux["barrier_h"][n]), acc.h_min[n])
             for n in acc.h_min}
    # the support polygon of the domain the QP ran in (single support: the stance sole)
    in_contact = domain["in_contact"] if domain is not None else sc.in_contact
    margin = contacts.zmp_margin(model, q, lam, jnp.asarray(in_contact, q.dtype))
    zmp_ok = live & (tau >= 0) & (fb != jax_qp.FALLBACK_FAILED)
    sites = dx_new.site_xpos
    slip = jnp.max(jnp.linalg.norm(sites[pl.sole_sites, :2] - pl.sole0_xy, axis=-1))
    if domain is not None:
        stance = domain["stance"]
        st = jnp.where(stance > 0, sites[pl.sole_sites[0], :2], sites[pl.sole_sites[1], :2])
        slip = jnp.where(stance != 0, jnp.linalg.norm(st - domain["stance0"][:2]), slip)
    loop = jnp.max(jnp.linalg.norm(sites[pl.tip_sites] - sites[pl.anchor_sites], axis=-1))
    ratio = jnp.max(jnp.abs(u) / model.torque_limit)
    mx = lambda old, new: jnp.where(live, jnp.maximum(old, new), old)  # noqa: E731
    return acc._replace(
        n_none=acc.n_none + count(fb == jax_qp.FALLBACK_NONE),
        n_relaxed=acc.n_relaxed + count(fb == jax_qp.FALLBACK_RELAXED),
        n_failed=acc.n_failed + count(fb == jax_qp.FALLBACK_FAILED),
        track_sq=track_sq, track_n=track_n,
        h_min=h_min, zmp_min=jnp.where(zmp_ok, jnp.minimum(acc.zmp_min, margin), acc.zmp_min),
        slip_max=mx(acc.slip_max, slip), loop_max=mx(acc.loop_max, loop),
        torque_max=mx(acc.torque_max, ratio))


def _fallen(pl: Plant, dx) -> jax.Array:
    finite = jnp.all(jnp.isfinite(dx.qpos)) & jnp.all(jnp.isfinite(dx.qvel))
    return ~finite | (dx.xpos[pl.base_id, 2] < FALL_HEIGHT)


def _pair(g, a, b):
    """(ncon,) True where a contact's geom pair is one of ``a`` with one of ``b``."""
    def member(x, ids):
        return jnp.any(x[:, None] == jnp.atleast_1d(ids)[None], axis=1)

    return ((member(g[:, 0], a) & member(g[:, 1], b))
            | (member(g[:, 0], b) & member(g[:, 1], a)))


def sole_forces_and_leg_contact(pl: Plant, dx):
    """((2,) normal force of the left and the right sole on the floor (N), whether a
    geom of one leg touches one of the other leg), from MJX's contacts: the normal force
    of a pyramidal contact is the sum of its 2 (condim - 1) edge forces, as
    ``mj_contactForce`` computes it (the deployment loop's ``_floor_and_leg_contacts``)."""
    con = dx._impl.contact
    rows = np.asarray(pl.contact_rows)
    f = dx._impl.efc_force[np.maximum(rows, 0)] * (rows >= 0)
    normal = jnp.sum(f, axis=1) * (con.efc_address >= 0)
    g = con.geom
    soles = jnp.stack([jnp.sum(jnp.where(_pair(g, pl.floor_geom, pl.sole_geoms[i]), normal, 0.0))
                       for i in range(2)])
    legs = jnp.any(_pair(g, pl.leg_geoms[0], pl.leg_geoms[1]) & (con.dist < 0))
    return soles, legs


def _walk_update(pl: Plant, acc: Acc, live, k, tau, run: Run, aux, gait_new, legs, dx_new):
    """Walking metrics of this step (``metrics.summarize``'s walking block)."""
    sites = dx_new.site_xpos
    clearance = sites[pl.sole_sites[0], 1] - sites[pl.sole_sites[1], 1]
    ss = live & (tau >= 0) & (gait_new.stance != 0)
    com_x = aux["outputs"]["com"][0][0]
    return acc._replace(
        leg_collisions=acc.leg_collisions + jnp.where(live & legs & ~acc.legs_prev, 1, 0)
        .astype(jnp.int32),
        leg_contact_steps=acc.leg_contact_steps + jnp.where(live & legs, 1, 0).astype(jnp.int32),
        legs_prev=jnp.where(live, legs, acc.legs_prev),
        clearance_min=jnp.where(ss, jnp.minimum(acc.clearance_min, clearance), acc.clearance_min),
        com_x_half=jnp.where(live & (k == run.k_half), com_x, acc.com_x_half),
        com_x_end=jnp.where(live, com_x, acc.com_x_end))


def _step(pl: Plant, run: Run, params, push: Push, carry, k):
    """One control step of one rollout; returns the new carry and this step's record."""
    dx, last_u, acc, gait = carry
    sc = run.scenario
    dt = pl.cfg.control_dt
    inside = k < run.n_steps
    tau = k * dt - sc.settle
    q, v = dx.qpos[pl.qpos_idx], dx.qvel[pl.qvel_idx]
    domain, start = None, pl.start
    if pl.walking:
        domain = walking.gait_domain(gait, jnp.zeros((), q.dtype), run.speed,
                                     jnp.asarray(walking.STEP_WIDTH, q.dtype), xp=jnp)
        v = walking.rigid_spring_velocity(pl.model, q, v, domain["stance"])
        start = {**pl.start, "settle": sc.settle}
    u, lam, res, aux = _control(pl, sc, params, q, v, tau, last_u, start, domain)
    dx_new = _physics(pl, dx, u, push, tau)
    live = acc.alive & inside
    acc = _update(pl, acc, live, tau, q, u, lam, res, aux, dx_new, domain)
    if pl.walking:
        soles, legs = sole_forces_and_leg_contact(pl, dx_new)
        sites = dx_new.site_xpos
        swing_force = jnp.where(gait.stance > 0, soles[1], soles[0])
        new, _ = walking.gait_step(gait, tau, dt, sites[pl.sole_sites[0]],
                                   sites[pl.sole_sites[1]], swing_force, pl.weight, xp=jnp)
        acc = _walk_update(pl, acc, live, k, tau, run, aux, new, legs, dx_new)
        gait = jax.tree_util.tree_map(lambda a, b: jnp.where(live, a, b), new, gait)
    fell_now = live & _fallen(pl, dx_new)
    keep = live & ~fell_now
    dx = jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), dx_new, dx)
    acc = acc._replace(alive=acc.alive & ~fell_now,
                       fell_step=jnp.where(fell_now, k, acc.fell_step).astype(jnp.int32))
    record = {"tau": tau, "alive": acc.alive, "qpos": dx.qpos, "u": u, "status": res.status,
              "fallback": res.fallback, "qp_iterations": res.iterations,
              "stance": gait.stance,
              **{f"y_{n}": aux["outputs"][n][0] for n in aux["outputs"]},
              **{f"yd_{n}": aux["outputs"][n][1] for n in aux["outputs"]},
              **{f"h_{n}": aux["barrier_h"][n] for n in aux["barrier_h"]}}
    return (dx, jnp.where(keep, u, last_u), acc, gait), record


def _rollout(pl: Plant, decimate: int, n_records: int, params, push: Push, perturb_v,
             n_steps, settle, speed, k_half):
    """One rollout from the stand keyframe: (final Acc, final GaitState, decimated
    records or None).

    Without records the time loop is a ``fori_loop`` over the run-time ``n_steps``; with
    records (every ``decimate``-th step, ``n_records`` of them: static) a scan."""
    run = Run(dataclasses.replace(pl.scenario, settle=settle), n_steps, speed, k_half)
    dx = pl.data0.replace(qvel=pl.data0.qvel + perturb_v)
    dtype = dx.qvel.dtype
    gait = walking.GaitState.standing(jnp, dtype)
    carry = (dx, jnp.zeros(pl.model.nu, dtype), _acc0(pl, dtype), gait)
    step = functools.partial(_step, pl, run, params, push)
    if not decimate:
        _, _, acc, gait = jax.lax.fori_loop(0, n_steps, lambda k, c: step(c, k)[0], carry)
        return acc, gait, None

    def outer(c, k0):
        c, rec = step(c, k0)
        c = jax.lax.fori_loop(k0 + 1, k0 + decimate, lambda k, cc: step(cc, k)[0], c)
        return c, rec

    (_, _, acc, gait), recs = jax.lax.scan(outer, carry, decimate * jnp.arange(n_records))
    return acc, gait, recs


@functools.lru_cache(maxsize=16)
def _compiled(pl: Plant, decimate: int, n_records: int, chunk: int | None):
    """jit of the vmapped rollout over (params, push, perturb_v), the batch run ``chunk``
    rollouts at a time (``chunking.chunked``; None: one vmap)."""
    one = jax.vmap(functools.partial(_rollout, pl, decimate, n_records),
                   in_axes=(0, 0, 0, None, None, None, None))
    run = chunked(lambda batched, *shared: one(*batched, *shared), chunk)
    return jax.jit(lambda params, push, perturb_v, *shared:
                   run((params, push, perturb_v), *shared))


CPU_CHUNK = 64
"""Default ``chunk`` of ``run_batch`` on the CPU backend (rollouts per chunk)."""


def default_chunk(backend: str | None = None, n_devices: int | None = None) -> int | None:
    """``run_batch``'s default ``chunk``: ``CPU_CHUNK`` on the CPU backend with one local
    device; None (one vmap over each device's share) on an accelerator, whose parallelism
    wants the widest batch, and wherever the batch is sharded over several devices."""
    backend = jax.default_backend() if backend is None else backend
    n_devices = len(jax.local_devices()) if n_devices is None else n_devices
    return CPU_CHUNK if backend == "cpu" and n_devices == 1 else None


def _finish(pl: Plant, acc: Acc, gait, n_steps: int, k_half: int) -> dict:
    """Acc and GaitState (batched, numpy) -> flat metric columns, names as in
    metrics.json."""
    sc, cfg = pl.scenario, pl.cfg
    out = {"fell": ~acc.alive, "fell_time_s": np.where(acc.alive, np.nan,
                                                      acc.fell_step * cfg.control_dt),
           "qp_solved": acc.n_none, "qp_failed": acc.n_failed, "fallbacks": acc.n_relaxed,
           # +inf: never evaluated (no motion phase reached) -> NaN; -inf (no normal force
           # under the feet, as in the MuJoCo loop's metric) is kept
           "zmp_margin_min": np.where(acc.zmp_min == np.inf, np.nan, acc.zmp_min),
           "foot_slip_max": acc.slip_max, "torque_ratio_max": acc.torque_max,
           "loop_residual_max": acc.loop_max}
    for o in sc.outputs:
        cnt = acc.track_n[o.name]
        out[f"tracking_rms.{o.name}"] = np.where(
            cnt > 0, np.sqrt(acc.track_sq[o.name] / np.maximum(cnt, 1)), np.nan)
    for name, h in acc.h_min.items():
        out[f"barrier_min.{name}"] = np.where(h == np.inf, np.nan, h)
    if pl.walking:
        # the second half of the walk, as metrics.summarize (NaN for a fallen rollout, whose
        # walk ended early, and for walks too short to have two halves)
        dt = cfg.control_dt
        span = (n_steps - 1) * dt - k_half * dt
        ok = acc.alive & (k_half >= 0)
        out["avg_forward_speed"] = np.where(ok, (acc.com_x_end - acc.com_x_half)
                                            / max(span, 1e-9), np.nan)
        out["steps_taken"] = gait.steps
        out["leg_collisions"] = acc.leg_collisions
        out["leg_contact_steps"] = acc.leg_contact_steps
        out["swing_clearance_min"] = np.where(acc.clearance_min == np.inf, np.nan,
                                              acc.clearance_min)
        out["missed_touchdowns"] = gait.missed
    return {k: np.asarray(v) for k, v in out.items()}


def half_walk_step(n_steps: int, settle: float, dt: float) -> int:
    """The control step where the second half of the motion begins (t >= midpoint of the
    motion's first and last step times), -1 if the motion has fewer than 3 steps: the
    window of ``metrics.summarize``'s avg_forward_speed, with the same float operations."""
    t = np.arange(n_steps) * dt
    tw = t[t - settle >= 0]
    if tw.size <= 2:
        return -1
    return int(np.searchsorted(t, tw[0] + 0.5 * (tw[-1] - tw[0])))


def _pad(tree, batch: int, padded: int):
    if padded == batch:
        return tree
    return jax.tree_util.tree_map(
        lambda a: np.concatenate([np.asarray(a), np.repeat(np.asarray(a)[-1:], padded - batch, 0)]),
        tree)


def _shard(tree):
    """Split the leading (batch) axis over this process's devices. With several hosts
    (``jax.distributed``) each process runs its own batches on its own devices."""
    devs = jax.local_devices()
    if len(devs) == 1:
        return tree
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    sh = NamedSharding(Mesh(np.array(devs), ("batch",)), PartitionSpec("batch"))
    return jax.device_put(tree, sh)


def run_batch(cfg: BatchConfig, params: ControllerParams, push: Push | None = None,
              perturb_v=None, chunk: int | str | None = "auto"):
    """Run a batch of closed-loop rollouts.

    params: the scenario's ControllerParams with a leading batch axis B on every leaf
    (``default_params(scenario, B)``); push: ``Push`` (None: no push); perturb_v: (B, nv)
    initial velocity perturbation of the simulator state (None: zeros).

    Returns (metrics, trajectories): metrics a dict of numpy arrays of shape (B,), named as
    in ``metrics.json`` with nested names flattened by "." (``tracking_rms.com``,
    ``barrier_min.left_fist``), plus ``fell_time_s``; trajectories None, or with
    ``cfg.decimate`` = k a dict of arrays (B, T, ...) of every k-th control step (tau,
    alive, qpos, u, status, fallback, qp_iterations, stance, y_<output>, yd_<output>,
    h_<barrier>). Walking adds avg_forward_speed, steps_taken, leg_collisions,
    leg_contact_steps, swing_clearance_min and missed_touchdowns.

    chunk: run the batch ``chunk`` rollouts at a time, one chunk after the other inside
    the one compiled call (``chunking.chunked``; the results do not depend on it); None:
    one vmap over the whole batch; "auto" (default): ``default_chunk()``, ``CPU_CHUNK``
    on a CPU with one device, None on accelerators and on several devices (each device
    then runs one vmap over its share; a chunk given there is not used). A different
    chunk is a different compile.

    Why chunks on a CPU: one vmap over a large batch is slower per robot-step (its working
    set leaves the caches, and its solver loops run until the batch's slowest QP stops).
    Measured with ``benchmarks/closed_loop_batch.py --chunks`` (arms, 1,050 steps per
    rollout, 2-core x86-64 machine, one timed call each), robot-steps/s: batch 1,024:
    1,476 in chunks of 64 against 1,195 as one vmap; batch 256: 1,891 (64) and 1,804
    (one vmap), 1,300 in chunks of 16; batch 64: 1,504 as one vmap, 1,364 / 1,247 / 1,148
    in chunks of 16 / 32 / 8. Small chunks lose (why was not measured: a likely cause is
    too little work per step to keep XLA's thread pool busy); 64 is the default."""
    pl = plant(cfg)
    try:
        check_chunk(chunk)
    except ValueError as e:
        raise BatchError(str(e)) from None
    if push is None or perturb_v is None:
        leaves = jax.tree_util.tree_leaves(params)
        b = np.shape(leaves[0])[0] if leaves and np.ndim(leaves[0]) else 0
        push = Push.none(b) if push is None else push
        perturb_v = np.zeros((b, pl.nv_sim)) if perturb_v is None else perturb_v
    push = Push(*(np.asarray(a, float) for a in push))
    perturb_v = np.asarray(perturb_v, float)
    batch = _check_inputs(pl, params, push, perturb_v)
    if cfg.barrier:
        check_batch_poles(pl, params, perturb_v)
    ndev = len(jax.local_devices())
    padded = -(-batch // ndev) * ndev
    args = _shard(_pad((params, push, perturb_v), batch, padded))
    n_steps, settle = pl.schedule(cfg)
    k_half = half_walk_step(n_steps, settle, cfg.control_dt)
    dec = int(cfg.decimate)
    ch = resolve_chunk(chunk, padded, default_chunk(n_devices=ndev)) if ndev == 1 else None
    fn = _compiled(pl, dec, -(-n_steps // dec) if dec else 0, ch)
    with jax_qp.blas_threads(1):      # see safewbc_jax/__init__.py
        acc, gait, recs = fn(*args, jnp.asarray(n_steps, jnp.int32), jnp.asarray(settle),
                             jnp.asarray(cfg.speed), jnp.asarray(k_half, jnp.int32))
        acc, gait, recs = jax.tree_util.tree_map(lambda a: np.asarray(a)[:batch],
                                                 (acc, gait, recs))
    return _finish(pl, acc, gait, n_steps, k_half), recs
