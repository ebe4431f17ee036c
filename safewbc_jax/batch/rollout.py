"""Closed-loop MJX rollouts: the controller and the MJX physics of ``models/scene.xml``
stepped together, scanned over time, vmapped over a batch of ControllerParams, pushes and
initial velocity perturbations.

One control step of one rollout (the deployment loop's step, in JAX):

    simulator state -> controller (q, v)                  (statemap indices)
    robot_terms, build_qp                                 (the same functions as the MuJoCo loop)
    jax_qp.solve                                          (reduced QP in u, interior point,
                                                           polish, fallback policy)
    u from X; the last good u held where even the relaxed QP fails
    ctrl = clip(u[act_idx] / gear), push force on the base body, n_sub mjx.step
    metrics updated on the device (names of metrics.json)

A rollout that falls (base below ``FALL_HEIGHT`` or a non-finite state) is frozen at its
last state and flagged; its metrics stop accumulating. A failed QP is counted and holds the
last torque. Neither touches the other rollouts of the batch.

The batch is sharded over the process's devices (``jax.local_devices()``, leading axis),
padded to a multiple of the device count.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax import barriers, contacts, controller, metrics
from safewbc_jax.mjx_import import import_mjx
from safewbc_jax.modelinfo import loop_site_pairs
from safewbc_jax.params import ControllerParams
from safewbc_jax.scenarios import SCENARIOS, get_scenario, start_state
from safewbc_jax.sim.mujoco_loop import FALL_HEIGHT, load_at_stand
from safewbc_jax.solvers import jax_qp

BATCHED_SCENARIOS = tuple(SCENARIOS)   # squat, bow, arms (walking's gait is host-side)


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


class Push(NamedTuple):
    """A force on the base body (world frame), per rollout: force (B, 3) N, from ``at``
    (B,) s after the motion starts, for ``duration`` (B,) s."""

    force: np.ndarray
    at: np.ndarray
    duration: np.ndarray

    @staticmethod
    def none(batch: int) -> "Push":
        return Push(np.zeros((batch, 3)), np.zeros(batch), np.zeros(batch))


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
                         f"(available: {known}; walking runs in the MuJoCo loop only)")
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
    n_sub = int(round(cfg.control_dt / ms.opt.timestep))
    if n_sub < 1 or abs(n_sub * ms.opt.timestep - cfg.control_dt) > 1e-12:
        raise BatchError(f"BatchConfig.control_dt = {cfg.control_dt}: must be a positive "
                         f"multiple of the simulation step {ms.opt.timestep}")

    q0, v0 = (np.asarray(a) for a in sm.to_controller(d.qpos, d.qvel))
    start = start_state(model, jnp.asarray(q0))
    start["y0"] = controller.output_start_values(model, sc, jnp.asarray(q0))

    mx = mjx.put_model(ms)
    dx = mjx.put_data(ms, d)
    # put_data and step disagree on some integer dtypes under x64: make the initial data
    # look like what step returns, so it can be a scan carry.
    shape = jax.eval_shape(mjx.step, mx, dx)
    dx = jax.tree_util.tree_map(lambda a, s: jnp.asarray(a, s.dtype), dx, shape)

    tips, anchors = loop_site_pairs(ms)
    soles = np.array([ms.site(f"{s}-sole").id for s in ("left", "right")])
    return Plant(
        cfg=cfg, scenario=sc, model=model, mjx_model=mx, data0=dx,
        qpos_idx=np.asarray(sm.qpos_idx), qvel_idx=np.asarray(sm.qvel_idx),
        act_idx=np.asarray(sm.act_idx), gear=np.asarray(sm.gear, float),
        ctrl_lo=ms.actuator_ctrlrange[:, 0].copy(), ctrl_hi=ms.actuator_ctrlrange[:, 1].copy(),
        base_id=ms.body("base").id, sole_sites=soles, tip_sites=tips, anchor_sites=anchors,
        sole0_xy=d.site_xpos[soles, :2].copy(),
        start=start, q0=q0, v0=v0, n_sub=n_sub, sim_dt=float(ms.opt.timestep), nv_sim=ms.nv)


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
    """jit(vmap): (v0, threshold) -> eta(x0) of barrier ``name`` at the stand pose."""
    b = next(b for b in pl.scenario.barriers if b.name == name)
    q0 = jnp.asarray(pl.q0)

    def eta(v, thr):
        return barriers.barrier_lie_derivatives(b.h_fn(pl.model, thr), q0, v,
                                                b.relative_degree)[0]

    return jax.jit(jax.vmap(eta))


def start_etas(pl: Plant, name: str, perturb_v, thresholds) -> np.ndarray:
    """(N, r) eta(x_0) of barrier ``name`` at N start states: the stand pose with the
    simulator velocity perturbations ``perturb_v`` (N, nv_sim) and thresholds (N,)."""
    v0 = np.asarray(perturb_v)[:, pl.qvel_idx] + pl.v0
    return np.asarray(_start_eta(pl, name)(jnp.asarray(v0), jnp.asarray(thresholds)))


def check_batch_poles(pl: Plant, params, perturb_v) -> None:
    """Theorem 1 for every rollout at its own start state (velocity perturbation and
    threshold included), before anything long compiles: PoleError names the rollout."""
    sc = pl.scenario
    if not sc.barriers:
        return
    for b in sc.barriers:
        etas = start_etas(pl, b.name, perturb_v, params.threshold[b.name])
        poles = np.asarray(params.poles[b.name])
        for i in range(etas.shape[0]):
            try:
                barriers.check_poles(b.name, etas[i], poles[i])
            except barriers.PoleError as e:
                raise barriers.PoleError(f"rollout {i}: {e}") from None


# ----------------------------------------------------------------------------- the loop

class Acc(NamedTuple):
    """Per-rollout running metrics."""

    alive: jax.Array
    fell_step: jax.Array
    n_none: jax.Array
    n_relaxed: jax.Array
    n_failed: jax.Array
    track_sq: dict
    track_n: jax.Array
    h_min: dict
    zmp_min: jax.Array
    slip_max: jax.Array
    torque_max: jax.Array
    loop_max: jax.Array


def _acc0(pl: Plant, dtype) -> Acc:
    sc = pl.scenario
    z = jnp.zeros((), dtype)
    inf = jnp.asarray(jnp.inf, dtype)
    return Acc(alive=jnp.asarray(True), fell_step=jnp.asarray(-1, jnp.int32),
               n_none=jnp.zeros((), jnp.int32), n_relaxed=jnp.zeros((), jnp.int32),
               n_failed=jnp.zeros((), jnp.int32), track_sq={o.name: z for o in sc.outputs},
               track_n=jnp.zeros((), jnp.int32),
               h_min={b.name: inf for b in sc.barriers + sc.monitors},
               zmp_min=inf, slip_max=z, torque_max=z, loop_max=z)


class Run(NamedTuple):
    """Run-time (traced) values shared by the batch: the scenario with its settle time,
    the number of control steps."""

    scenario: object
    n_steps: jax.Array


def _control(pl: Plant, sc, params, q, v, tau, last_u):
    """One controller step: (u to apply, lambda, solver Result, aux of build_qp)."""
    model = pl.model
    nv, nu = model.nv, model.nu
    terms = controller.robot_terms(model, sc, q, v)
    qpm, aux = controller.build_qp(model, sc, params, terms, q, v, tau, pl.start,
                                   jnp.asarray(sc.in_contact, q.dtype),
                                   barrier_on=pl.cfg.barrier)
    res = jax_qp.solve(qpm, nv=nv, nu=nu, p_blockdiag=True)
    ok = res.fallback != jax_qp.FALLBACK_FAILED
    u = jnp.where(ok, res.x[nv:nv + nu], last_u)
    lam = res.x[nv + nu + controller.n_chain_rows(model):]
    return u, lam, res, aux


def _physics(pl: Plant, dx, u, push: Push, tau):
    mjx = import_mjx()
    ctrl = jnp.clip(u[pl.act_idx] / pl.gear, pl.ctrl_lo, pl.ctrl_hi)
    on = (tau >= push.at) & (tau < push.at + push.duration)
    xfrc = jnp.zeros_like(dx.xfrc_applied).at[pl.base_id, :3].set(
        jnp.where(on, push.force, 0.0))
    dx = dx.replace(ctrl=ctrl, xfrc_applied=xfrc)
    for _ in range(pl.n_sub):
        dx = mjx.step(pl.mjx_model, dx)
    return dx


def _update(pl: Plant, acc: Acc, live, tau, q, u, lam, res, aux, dx_new) -> Acc:
    """Metrics of this step (counted where ``live``: alive and inside the run)."""
    model, sc = pl.model, pl.scenario
    fb = res.fallback
    count = lambda c: jnp.where(live & c, 1, 0).astype(jnp.int32)  # noqa: E731
    track = live & (tau >= metrics.TRACKING_SKIP_S)
    track_sq = {}
    for o in sc.outputs:
        ya, yd = aux["outputs"][o.name]
        track_sq[o.name] = acc.track_sq[o.name] + jnp.where(track, jnp.sum((ya - yd) ** 2), 0.0)
    h_min = {n: jnp.where(live, jnp.minimum(acc.h_min[n], aux["barrier_h"][n]), acc.h_min[n])
             for n in acc.h_min}
    margin = contacts.zmp_margin(model, q, lam, jnp.asarray(sc.in_contact, q.dtype))
    zmp_ok = live & (tau >= 0) & (fb != jax_qp.FALLBACK_FAILED)
    sites = dx_new.site_xpos
    slip = jnp.max(jnp.linalg.norm(sites[pl.sole_sites, :2] - pl.sole0_xy, axis=-1))
    loop = jnp.max(jnp.linalg.norm(sites[pl.tip_sites] - sites[pl.anchor_sites], axis=-1))
    ratio = jnp.max(jnp.abs(u) / model.torque_limit)
    mx = lambda old, new: jnp.where(live, jnp.maximum(old, new), old)  # noqa: E731
    return acc._replace(
        n_none=acc.n_none + count(fb == jax_qp.FALLBACK_NONE),
        n_relaxed=acc.n_relaxed + count(fb == jax_qp.FALLBACK_RELAXED),
        n_failed=acc.n_failed + count(fb == jax_qp.FALLBACK_FAILED),
        track_sq=track_sq, track_n=acc.track_n + jnp.where(track, 1, 0).astype(jnp.int32),
        h_min=h_min, zmp_min=jnp.where(zmp_ok, jnp.minimum(acc.zmp_min, margin), acc.zmp_min),
        slip_max=mx(acc.slip_max, slip), loop_max=mx(acc.loop_max, loop),
        torque_max=mx(acc.torque_max, ratio))


def _fallen(pl: Plant, dx) -> jax.Array:
    finite = jnp.all(jnp.isfinite(dx.qpos)) & jnp.all(jnp.isfinite(dx.qvel))
    return ~finite | (dx.xpos[pl.base_id, 2] < FALL_HEIGHT)


def _step(pl: Plant, run: Run, params, push: Push, carry, k):
    """One control step of one rollout; returns the new carry and this step's record."""
    dx, last_u, acc = carry
    sc = run.scenario
    inside = k < run.n_steps
    tau = k * pl.cfg.control_dt - sc.settle
    q, v = dx.qpos[pl.qpos_idx], dx.qvel[pl.qvel_idx]
    u, lam, res, aux = _control(pl, sc, params, q, v, tau, last_u)
    dx_new = _physics(pl, dx, u, push, tau)
    live = acc.alive & inside
    acc = _update(pl, acc, live, tau, q, u, lam, res, aux, dx_new)
    fell_now = live & _fallen(pl, dx_new)
    keep = live & ~fell_now
    dx = jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), dx_new, dx)
    acc = acc._replace(alive=acc.alive & ~fell_now,
                       fell_step=jnp.where(fell_now, k, acc.fell_step).astype(jnp.int32))
    record = {"tau": tau, "alive": acc.alive, "qpos": dx.qpos, "u": u, "status": res.status,
              "fallback": res.fallback, "qp_iterations": res.iterations,
              **{f"y_{n}": aux["outputs"][n][0] for n in aux["outputs"]},
              **{f"yd_{n}": aux["outputs"][n][1] for n in aux["outputs"]},
              **{f"h_{n}": aux["barrier_h"][n] for n in aux["barrier_h"]}}
    return (dx, jnp.where(keep, u, last_u), acc), record


def _rollout(pl: Plant, decimate: int, n_records: int, params, push: Push, perturb_v,
             n_steps, settle):
    """One rollout from the stand keyframe: (final Acc, decimated records or None).

    Without records the time loop is a ``fori_loop`` over the run-time ``n_steps``; with
    records (every ``decimate``-th step, ``n_records`` of them: static) a scan."""
    run = Run(dataclasses.replace(pl.scenario, settle=settle), n_steps)
    dx = pl.data0.replace(qvel=pl.data0.qvel + perturb_v)
    carry = (dx, jnp.zeros(pl.model.nu, dx.qvel.dtype), _acc0(pl, dx.qvel.dtype))
    step = functools.partial(_step, pl, run, params, push)
    if not decimate:
        _, _, acc = jax.lax.fori_loop(0, n_steps, lambda k, c: step(c, k)[0], carry)
        return acc, None

    def outer(c, k0):
        c, rec = step(c, k0)
        c = jax.lax.fori_loop(k0 + 1, k0 + decimate, lambda k, cc: step(cc, k)[0], c)
        return c, rec

    (_, _, acc), recs = jax.lax.scan(outer, carry, decimate * jnp.arange(n_records))
    return acc, recs


@functools.lru_cache(maxsize=16)
def _compiled(pl: Plant, decimate: int, n_records: int):
    fn = functools.partial(_rollout, pl, decimate, n_records)
    return jax.jit(jax.vmap(fn, in_axes=(0, 0, 0, None, None)))


def _finish(pl: Plant, acc: Acc) -> dict:
    """Acc (batched, numpy) -> flat metric columns, names as in metrics.json."""
    sc, cfg = pl.scenario, pl.cfg
    out = {"fell": ~acc.alive, "fell_time_s": np.where(acc.alive, np.nan,
                                                      acc.fell_step * cfg.control_dt),
           "qp_solved": acc.n_none, "qp_failed": acc.n_failed, "fallbacks": acc.n_relaxed,
           # +inf: never evaluated (no motion phase reached) -> NaN; -inf (no normal force
           # under the feet, as in the MuJoCo loop's metric) is kept
           "zmp_margin_min": np.where(acc.zmp_min == np.inf, np.nan, acc.zmp_min),
           "foot_slip_max": acc.slip_max, "torque_ratio_max": acc.torque_max,
           "loop_residual_max": acc.loop_max}
    n = np.maximum(acc.track_n, 1)
    for o in sc.outputs:
        out[f"tracking_rms.{o.name}"] = np.where(acc.track_n > 0,
                                                 np.sqrt(acc.track_sq[o.name] / n), np.nan)
    for name, h in acc.h_min.items():
        out[f"barrier_min.{name}"] = np.where(h == np.inf, np.nan, h)
    return {k: np.asarray(v) for k, v in out.items()}


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
              perturb_v=None):
    """Run a batch of closed-loop rollouts.

    params: the scenario's ControllerParams with a leading batch axis B on every leaf
    (``default_params(scenario, B)``); push: ``Push`` (None: no push); perturb_v: (B, nv)
    initial velocity perturbation of the simulator state (None: zeros).

    Returns (metrics, trajectories): metrics a dict of numpy arrays of shape (B,), named as
    in ``metrics.json`` with nested names flattened by "." (``tracking_rms.com``,
    ``barrier_min.left_fist``), plus ``fell_time_s``; trajectories None, or with
    ``cfg.decimate`` = k a dict of arrays (B, T, ...) of every k-th control step (tau,
    alive, qpos, u, status, fallback, y_<output>, yd_<output>, h_<barrier>)."""
    pl = plant(cfg)
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
    with jax_qp.blas_threads(1):      # see safewbc_jax/__init__.py
        n_steps, settle = pl.schedule(cfg)
    dec = int(cfg.decimate)
    fn = _compiled(pl, dec, -(-n_steps // dec) if dec else 0)
    acc, recs = fn(*args, jnp.asarray(n_steps, jnp.int32), jnp.asarray(settle))
    acc, recs = jax.tree_util.tree_map(lambda a: np.asarray(a)[:batch], (acc, recs))
    return _finish(pl, acc), recs
