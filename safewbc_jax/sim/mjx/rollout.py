"""Closed-loop MJX rollouts: the controller and the MJX physics of ``models/scene.xml``
stepped together, scanned over time, vmapped over a batch of ControllerParams, pushes and
initial velocity perturbations. Every scenario of the deployment loop runs here: squat,
bow, arms, and walking ("walk", "push") with its gait state carried per rollout.

One control step of one rollout is ``control_step.step_jax`` (measurement check, gait,
rigid swing-leg rates, QP, the JAX QP solver ``jax_qp.solve`` with its fallback policy,
held torque, motor torques, metrics), between what stays per simulator:

    MJX Data -> Measurement (q, v through the state map; walking: each sole's normal force
                on the floor, MJX's pyramid constraint forces summed as ``mj_contactForce``
                does)
    control_step.step_jax
    motor torques into ctrl, the push on the base body (``push.force_at``), n_sub mjx.step
    MJX Data -> the next Measurement: plant metrics (``metrics.plant_accumulate``), the
                fall test (``control_step.fallen``)

A rollout that falls (base below ``FALL_HEIGHT`` or a non-finite state) is frozen at its
last state and flagged; its metrics stop accumulating. A failed QP is counted and holds the
last torque; a measurement the controller refuses (a diverging simulation) is counted in
``bad_measurements`` and holds it too. Neither touches the other rollouts of the batch.

The batch is split over the process's devices (``jax.local_devices()``, leading axis),
padded to a multiple of the device count, each device running its share with its own loops
(``_compiled``: a ``shard_map``). On a CPU with one device it runs in chunks of
``CPU_CHUNK`` rollouts, one after the other inside the compiled call (``run_batch``'s
``chunk``); the chunks and the sub-batched factorisations are chosen by the platform the
program is lowered for (``chunking.ByPlatform``, ``solvers/lapack_batched.py``), so that
``export(cfg, batch, ("cuda",))`` on a CPU machine shows the GPU's one-vmap program.

``BatchConfig.precision`` "mixed" runs MJX physics and the QP's interior point in float32
and the rest in float64 (``safewbc_jax/control/precision.py``); the controller side, the carry's
controller state and the metrics stay float64 in either mode.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.control import step as control_step, metrics
from safewbc_jax.control import precision as precision_mod
from safewbc_jax.sim.mjx.plant import (BATCHED_SCENARIOS, BatchConfig, BatchError, Plant,
                                     default_params, plant)
from safewbc_jax.base.chunking import ByPlatform, check_chunk, chunked, resolve_chunk
from safewbc_jax.control.step import Measurement
from safewbc_jax.sim.mjx.imports import import_mjx
from safewbc_jax.model.modelinfo import loop_residual
from safewbc_jax.control.params import ControllerParams
from safewbc_jax.control.push import Push, force_at
from safewbc_jax.solvers import jax_qp


def _leaf_name(path) -> str:
    return "".join(str(k) for k in path).lstrip(".")


def _check_inputs(pl: Plant, params, push: Push, perturb_v) -> int:
    ref = pl.scenario.default_params()
    ref_leaves, ref_tree = jax.tree_util.tree_flatten_with_path(ref)
    try:
        leaves = ref_tree.flatten_up_to(params)  # type: ignore[attr-defined]
    except (ValueError, TypeError) as e:
        raise BatchError(f"params do not have the structure of the {pl.scenario.name!r} "
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
def _start_check(pl: Plant) -> control_step.StartCheck:
    """Theorem 1 at the stand pose of ``pl`` (``control_step.StartCheck``, jitted)."""
    return control_step.StartCheck(pl.model, pl.scenario, pl.q0)


def _start_velocities(pl: Plant, perturb_v) -> np.ndarray:
    """The controller's start velocities (N, nv) of simulator perturbations (N, nv_sim)."""
    return np.asarray(perturb_v)[:, pl.qvel_idx] + pl.v0


def start_etas(pl: Plant, name: str, perturb_v: np.ndarray,
               thresholds: np.ndarray) -> np.ndarray:
    """eta(x_0) of a barrier at N start states: the stand pose with simulator velocity
    perturbations.

    Args:
        pl: the plant (``plant``).
        name: the barrier's name.
        perturb_v: (N, nv_sim) velocity perturbations of the simulator state.
        thresholds: (N,) the barrier's threshold at each.

    Returns:
        (N, r) eta(x_0), r the barrier's relative degree.
    """
    return _start_check(pl).etas(name, _start_velocities(pl, perturb_v), thresholds)


def check_batch_poles(pl: Plant, params: ControllerParams, perturb_v: np.ndarray) -> None:
    """Theorem 1 for every rollout at its own start state (velocity perturbation and
    threshold included), before anything long compiles.

    Args:
        pl: the plant (``plant``).
        params: the batch's params, a leading batch axis B on every leaf.
        perturb_v: (B, nv_sim) velocity perturbations of the simulator state.

    Raises:
        PoleError: a rollout's poles do not keep its barrier's h >= 0 from its start
            state; the message names the rollout.
    """
    _start_check(pl).check(params, _start_velocities(pl, perturb_v), batched=True)


class Run(NamedTuple):
    """Run-time (traced) values shared by the batch: the control step's (settle, speed,
    where the forward speed's window begins) and the number of control steps."""

    values: control_step.RunValues
    n_steps: jax.Array


class Carry(NamedTuple):
    """One rollout between control steps: the simulator, the controller, the plant
    metrics, whether it is still standing (and the step it fell at), the measurement and
    the legs' contact sensed after the last physics step."""

    dx: Any
    ctl: control_step.ControllerState
    tally: control_step.Tally
    plant: metrics.PlantAcc
    alive: jax.Array
    fell_step: jax.Array
    meas: Measurement
    legs: jax.Array


def _sense(pl: Plant, dx, t):
    """MJX Data -> (Measurement, whether a leg touches the other leg)."""
    ft = jnp.float64                  # the controller's dtype, whatever the physics'
    q, v = dx.qpos[pl.qpos_idx].astype(ft), dx.qvel[pl.qvel_idx].astype(ft)
    soles: Any                        # traced: a jax array where Measurement says numpy
    if pl.walking:
        soles, legs = sole_forces_and_leg_contact(pl, dx)
        soles = soles.astype(ft)
    else:
        soles, legs = jnp.zeros(2, ft), jnp.asarray(False)
    return Measurement(q, v, jnp.asarray(t, ft), soles), legs


def _physics(pl: Plant, dx, motor, push: Push, tau):
    mjx = import_mjx()
    # each simulator actuator's motor torque (a gather: the motors are the actuators, in
    # another order)
    dt = dx.ctrl.dtype
    ctrl = jnp.clip(motor[pl.motor_of_ctrl], pl.ctrl_lo, pl.ctrl_hi).astype(dt)
    xfrc = jnp.zeros_like(dx.xfrc_applied).at[pl.base_id, :3].set(
        force_at(push, tau, jnp).astype(dt))
    dx = dx.replace(ctrl=ctrl, xfrc_applied=xfrc)
    step = precision_mod.physics(mjx.step, dt)
    for _ in range(pl.n_sub):
        dx = step(pl.mjx_model, dx)
    return dx


def _pair(g, a, b):
    """(ncon,) True where a contact's geom pair is one of ``a`` with one of ``b``."""
    def member(x, ids):
        return jnp.any(x[:, None] == jnp.atleast_1d(ids)[None], axis=1)

    return ((member(g[:, 0], a) & member(g[:, 1], b))
            | (member(g[:, 0], b) & member(g[:, 1], a)))


def sole_forces_and_leg_contact(pl: Plant, dx: Any) -> tuple[jax.Array, jax.Array]:
    """The soles' normal forces and the legs' contact, from MJX's contacts.

    The normal force of a pyramidal contact is the sum of its 2 (condim - 1) edge forces,
    as ``mj_contactForce`` computes it (as the deployment loop's ``ContactSensing``).

    Args:
        pl: the plant (``plant``).
        dx: one rollout's ``mjx.Data`` after a physics step.

    Returns:
        ``(soles, legs)``: (2,) normal force of the left and the right sole on the floor,
            N, and whether a geom of one leg touches one of the other leg.
    """
    con = dx._impl.contact
    rows = np.asarray(pl.contact_rows)
    f = dx._impl.efc_force[np.maximum(rows, 0)] * (rows >= 0)
    normal = jnp.sum(f, axis=1) * (con.efc_address >= 0)
    g = con.geom
    soles = jnp.stack([jnp.sum(jnp.where(_pair(g, pl.floor_geom, pl.sole_geoms[i]), normal, 0.0))
                       for i in range(2)])
    legs = jnp.any(_pair(g, pl.leg_geoms[0], pl.leg_geoms[1]) & (con.dist < 0))
    return soles, legs


def _step(pl: Plant, run: Run, params, push: Push, carry: Carry, k):
    """One control step of one rollout (sense -> control_step.step_jax -> push and
    physics -> plant metrics and the fall test); returns the new carry and this step's
    record."""
    where = lambda c, a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(c, x, y), a, b)  # noqa: E731
    live = carry.alive & (k < run.n_steps)
    ctl, tally, out = control_step.step_jax(pl.ctx, params, pl.start, run.values, carry.ctl,
                                            carry.tally, carry.meas)
    rec = out.record
    dx_new = _physics(pl, carry.dx, out.motor, push, rec.tau)
    meas, legs = _sense(pl, dx_new, (k + 1) * pl.cfg.control_dt)
    sites = dx_new.site_xpos.astype(jnp.float64)
    loop = loop_residual(sites, (pl.tip_sites, pl.anchor_sites), jnp)
    plant = metrics.plant_accumulate(carry.plant, live, rec, sites[pl.sole_sites], pl.sole0_xy,
                                     loop, legs, xp=jnp)
    fell_now = live & control_step.fallen(meas.q, meas.v, jnp)
    keep = live & ~fell_now
    new = Carry(dx=where(keep, dx_new, carry.dx), ctl=where(live, ctl, carry.ctl),
                tally=where(live, tally, carry.tally), plant=plant,
                alive=carry.alive & ~fell_now,
                fell_step=jnp.where(fell_now, k, carry.fell_step).astype(jnp.int32),
                meas=where(keep, meas, carry.meas), legs=jnp.where(keep, legs, carry.legs))
    record = {"tau": rec.tau, "alive": new.alive, "qpos": new.dx.qpos, "u": out.u,
              "status": rec.status, "fallback": rec.fallback, "qp_iterations": rec.iterations,
              "stance": rec.stance, "bad_measurement": ~rec.ok,
              **{f"y_{n}": y for n, y in rec.y.items()},
              **{f"yd_{n}": yd for n, yd in rec.yd.items()},
              **{f"h_{n}": h for n, h in rec.h.items()}}
    return new, record


def _start(pl: Plant, perturb_v) -> Carry:
    """One rollout's Carry at the stand keyframe, its velocity perturbed by ``perturb_v``."""
    dtype = jnp.float64               # the controller's; the physics' is pl.data0's
    qvel0 = pl.data0.qvel
    dx = pl.data0.replace(qvel=(qvel0 + perturb_v).astype(qvel0.dtype))
    meas, legs = _sense(pl, dx, 0.0)
    return Carry(dx, *control_step.init_state(pl.ctx, meas.q, meas.v, jnp, dtype),
                 metrics.plant_init(jnp, dtype), jnp.asarray(True), jnp.asarray(-1, jnp.int32),
                 meas, legs)


def _rollouts(pl: Plant, decimate: int, n_records: int, params, push: Push, perturb_v,
              n_steps, settle, speed, t_half):
    """The rollouts of a batch (``params``, ``push`` and ``perturb_v`` with a leading batch
    axis) from the stand keyframe: (final Carry, decimated records or None), each leaf
    with the batch axis first.

    The time loop runs over the batch's control step: ``vmap`` of ``_step`` inside the
    loop, not of the loop. The results are the same, bitwise (every carry leaf is
    per-rollout after one step; the loop's bounds are shared), but ``vmap`` of a loop
    batches its body through the loop's batching rule, which first finds which carry
    leaves are per-rollout, a batching of the body a round, and then batches it again;
    the ``vmap``ped step is batched once, as it is traced: a shorter trace and a cheaper
    first call (benchmarks/README.md, "Tracing the closed loop").

    Without records the time loop is a ``fori_loop`` over the run-time ``n_steps``; with
    records (every ``decimate``-th step, ``n_records`` of them: static) a scan."""
    dtype = jnp.float64
    run = Run(control_step.RunValues(jnp.asarray(settle, dtype), jnp.asarray(speed, dtype),
                                     jnp.asarray(t_half, dtype)), n_steps)
    carry = jax.vmap(functools.partial(_start, pl))(perturb_v)
    batched = jax.vmap(functools.partial(_step, pl, run), in_axes=(0, 0, 0, None))

    def step(c, k):
        return batched(params, push, c, k)

    if not decimate:
        return jax.lax.fori_loop(0, n_steps, lambda k, c: step(c, k)[0], carry), None

    def outer(c, k0):
        # the group's ``decimate`` steps in one scan, whose first record is kept: the
        # program holds the control step once (a record step traced apart from the
        # others' loop held it twice, and compiled about twice as long)
        c, recs = jax.lax.scan(step, c, k0 + jnp.arange(decimate))
        return c, jax.tree_util.tree_map(lambda r: r[0], recs)

    final, recs = jax.lax.scan(outer, carry, decimate * jnp.arange(n_records))
    return final, jax.tree_util.tree_map(lambda r: jnp.swapaxes(r, 0, 1), recs)


@functools.lru_cache(maxsize=16)
def _compiled(pl: Plant, decimate: int, n_records: int, chunk: int | None,
              n_devices: int = 1):
    """jit of the batch's rollouts over (params, push, perturb_v), the batch run ``chunk``
    rollouts at a time (``chunking.chunked``; None: the whole batch at once).

    On ``n_devices`` > 1 (this process's first ``n_devices`` local devices) the function
    is a ``shard_map`` over the batch axis: each device runs the rollouts of its share with
    its own loops (the time loop, the interior point's, MJX's solver's), whose trip counts
    are its own, and no collective anywhere. Partitioning the one-device program by its
    input sharding instead gives every loop one trip count for all devices, kept in step
    by a collective per iteration."""
    one = functools.partial(_rollouts, pl, decimate, n_records)
    run = chunked(lambda batched, *shared: one(*batched, *shared), chunk)

    def rollouts(params, push, perturb_v, *shared):
        return run((params, push, perturb_v), *shared)

    if n_devices > 1:
        from jax.sharding import Mesh, PartitionSpec

        mesh = Mesh(np.array(jax.local_devices()[:n_devices]), ("batch",))
        rows, same = PartitionSpec("batch"), PartitionSpec()
        rollouts = jax.shard_map(rollouts, mesh=mesh, in_specs=(rows,) * 3 + (same,) * 4,
                                 out_specs=rows, check_vma=False)
    return jax.jit(rollouts)


CPU_CHUNK = 64
"""Default ``chunk`` of ``run_batch`` on the CPU backend (rollouts per chunk)."""


def default_chunk(backend: str | None = None, n_devices: int | None = None) -> int | None:
    """``run_batch``'s default ``chunk`` on a platform.

    Args:
        backend: JAX's backend name ("cpu", "gpu", ...); None: this process's default.
        n_devices: the number of local devices; None: this process's.

    Returns:
        ``CPU_CHUNK`` on the CPU backend with one local device; None (one vmap over each
        device's share) on an accelerator, whose parallelism wants the widest batch, and
        wherever the batch is sharded over several devices.
    """
    backend = jax.default_backend() if backend is None else backend
    n_devices = len(jax.local_devices()) if n_devices is None else n_devices
    return CPU_CHUNK if backend == "cpu" and n_devices == 1 else None


def _arg_shapes(pl: Plant, batch: int) -> tuple:
    """Shapes and dtypes of the compiled closed loop's arguments at ``batch`` rollouts."""
    def sds(a):
        return jax.ShapeDtypeStruct(np.shape(a), jnp.asarray(a).dtype)

    batched = jax.tree_util.tree_map(sds, (default_params(pl.cfg.scenario, batch,
                                                          pl.cfg.safe_sets),
                                           Push.none(batch), np.zeros((batch, pl.nv_sim))))
    return batched + tuple(jax.tree_util.tree_map(sds, _run_scalars(0, 0.0, 0.0, 0.0)))


def _run_scalars(n_steps, settle, speed, t_half) -> tuple:
    """The compiled closed loop's run-time scalars, typed as ``_arg_shapes`` types them:
    int32 and strong float64. (A Python float through ``jnp.asarray`` is weakly typed,
    and a weak type is another program, with a compile of its own.)"""
    f = jnp.float64
    return (jnp.asarray(n_steps, jnp.int32), jnp.asarray(settle, f), jnp.asarray(speed, f),
            jnp.asarray(t_half, f))


def _checked_batch(batch) -> int:
    if isinstance(batch, bool) or int(batch) != batch or batch < 1:
        raise BatchError(f"batch = {batch!r}: must be a positive integer")
    return int(batch)


def export(cfg: BatchConfig, batch: int, platforms: Sequence[str] = ("cuda",),
           chunk: int | str | None = "auto") -> jax.export.Exported:
    """The batched closed loop of a config (the function ``run_batch`` compiles, without
    trajectories), lowered by ``jax.export``: no device of the platforms is needed and
    nothing compiles.

    Args:
        cfg: the batch's config.
        batch: the number of rollouts.
        platforms: JAX platform names to lower for ("cuda", "cpu", "rocm", ...).
        chunk: as in ``run_batch`` on one device ("auto": the chunk each platform's
            program gets).

    Returns:
        The ``jax.export.Exported``; its ``.mlir_module()`` is the program the platform
        would run (its custom calls, batch shapes, loops).

    Raises:
        BatchError: a bad config or ``batch``.
        ValueError: a bad ``chunk``.
    """
    pl = plant(cfg)
    batch = _checked_batch(batch)
    ch = resolve_chunk(chunk, batch, ByPlatform(CPU_CHUNK))
    return jax.export.export(_compiled(pl, 0, 0, ch), platforms=list(platforms))(
        *_arg_shapes(pl, batch))


def compiled_text(cfg: BatchConfig, batch: int) -> str:
    """The optimised HLO text of the closed loop that ``run_batch`` compiles (no
    trajectories, the default chunk) on this process's devices.

    A compile, or a load from JAX's persistent compilation cache where ``run_batch``
    already compiled it.

    Args:
        cfg: the batch's config.
        batch: the number of rollouts.

    Returns:
        The program each device runs, with its loops and any collective.

    Raises:
        BatchError: a bad config or ``batch``.
    """
    pl = plant(cfg)
    batch = _checked_batch(batch)
    ndev = len(jax.local_devices())
    padded = -(-batch // ndev) * ndev
    ch = resolve_chunk("auto", padded, ByPlatform(CPU_CHUNK)) if ndev == 1 else None
    shapes = _arg_shapes(pl, padded)
    if ndev > 1:
        sh = _batch_sharding()
        shapes = tuple(jax.tree_util.tree_map(
            lambda s: jax.ShapeDtypeStruct(s.shape, s.dtype, sharding=sh), a)
            for a in shapes[:3]) + shapes[3:]
    return _compiled(pl, 0, 0, ch, ndev).lower(*shapes).compile().as_text()


def memory_bytes(cfg: BatchConfig, batch: int, chunk: int | str | None = None) -> int:
    """Bytes the closed loop of a config takes on the default device, from the compiled
    program's memory analysis (a compile).

    Args:
        cfg: the batch's config.
        batch: the number of rollouts.
        chunk: as in ``run_batch``; None (default): one vmap, the accelerator form.

    Returns:
        Arguments + outputs + temporaries, less what the outputs alias, bytes.

    Raises:
        BatchError: a bad config or ``batch``.
        ValueError: a bad ``chunk``.
    """
    pl = plant(cfg)
    batch = _checked_batch(batch)
    ch = resolve_chunk(chunk, batch, ByPlatform(CPU_CHUNK))
    # kept out of the persistent compilation cache: serialising this AOT executable
    # crashed the process inside XLA (an abort here, a segfault in CI) in full-suite runs,
    # never alone. JAX decides once per process whether the cache is used, so turning the
    # cache off here would do nothing; the minimum compile time for a write is read at
    # each write, so an infinite one skips it. jit reuses this executable in memory for
    # the run that follows.
    was = jax.config.jax_persistent_cache_min_compile_time_secs  # type: ignore[attr-defined]
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float("inf"))
    try:
        m = _compiled(pl, 0, 0, ch).lower(*_arg_shapes(pl, batch)).compile().memory_analysis()
    finally:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", was)
    return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes
               - m.alias_size_in_bytes)


def largest_batch(fixed: float, per_rollout: float, memory: float,
                  headroom: float = 0.9) -> int:
    """The most rollouts whose ``fixed + batch * per_rollout`` bytes fit in a share of a
    device's memory.

    Args:
        fixed: bytes that do not depend on the batch (``memory_model``).
        per_rollout: bytes per rollout (``memory_model``).
        memory: the device's memory, bytes.
        headroom: the share of ``memory`` to fill.

    Returns:
        The batch size; 0 when not even one rollout fits.
    """
    return max(0, int((headroom * memory - fixed) // max(per_rollout, 1.0)))


def memory_model(cfg: BatchConfig,
                 batches: tuple[int, int] = (256, 1024)) -> tuple[float, float]:
    """The closed loop's memory as a linear function of the batch size, in its one-vmap
    (accelerator) form on the default device.

    Args:
        cfg: the batch's config.
        batches: the two batch sizes ``memory_bytes`` is measured at (two compiles).

    Returns:
        ``(fixed bytes, bytes per rollout)``.

    Raises:
        BatchError: a bad config or batch size.
    """
    b0, b1 = (int(b) for b in batches)
    m0, m1 = memory_bytes(cfg, b0), memory_bytes(cfg, b1)
    per = (m1 - m0) / (b1 - b0)
    return m0 - per * b0, per


def _finish(pl: Plant, final: Carry) -> dict:
    """The final Carry (batched, numpy) -> flat metric columns, names as in metrics.json
    (``metrics.table_columns``)."""
    out = metrics.finalize(pl.scenario, final.tally.acc, final.plant, ~final.alive,
                           final.ctl.gait)
    return metrics.table_columns(out, np.where(final.alive, -1, final.fell_step),
                                 pl.cfg.control_dt)


def _pad(tree, batch: int, padded: int):
    if padded == batch:
        return tree
    return jax.tree_util.tree_map(
        lambda a: np.concatenate([np.asarray(a), np.repeat(np.asarray(a)[-1:], padded - batch, 0)]),
        tree)


def _batch_sharding():
    """The leading (batch) axis split over this process's devices."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    return NamedSharding(Mesh(np.array(jax.local_devices()), ("batch",)), PartitionSpec("batch"))


def _shard(tree):
    """Split the leading (batch) axis over this process's devices."""
    if len(jax.local_devices()) == 1:
        return tree
    return jax.device_put(tree, _batch_sharding())


def run_batch(cfg: BatchConfig, params: ControllerParams, push: Push | None = None,
              perturb_v: np.ndarray | None = None, chunk: int | str | None = "auto",
              ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]:
    """Run a batch of closed-loop rollouts.

    Why chunks on a CPU: one vmap over a large batch is slower per robot-step (its working
    set leaves the caches, and its solver loops run until the batch's slowest QP stops);
    small chunks lose too (benchmarks/README.md, "Figures behind design choices",
    ``benchmarks/closed_loop_batch.py --chunks``).

    Args:
        cfg: what every rollout shares (scenario, durations, ...).
        params: the scenario's ControllerParams with a leading batch axis B on every leaf
            (``default_params(scenario, B)``).
        push: a ``Push`` per rollout, (B,)-batched fields; None: the scenario's own push
            (``Scenario.push``) on every rollout, or none.
        perturb_v: (B, nv_sim) initial velocity perturbation of the simulator state;
            None: zeros.
        chunk: run the batch ``chunk`` rollouts at a time, one chunk after the other
            inside the one compiled call (``chunking.chunked``; the results do not depend
            on it); None: one vmap over the whole batch; "auto" (default): with one
            device, ``CPU_CHUNK`` when the program is lowered for a CPU and one vmap when
            it is lowered for an accelerator (``chunking.ByPlatform``, the choice
            ``default_chunk`` reports); on several devices None (each device runs one
            vmap over its share; a chunk given there is not used). A different chunk is
            a different compile.

    Returns:
        ``(metrics, trajectories)``: metrics a dict of numpy arrays of shape (B,), named
            as in ``metrics.json`` with nested names flattened by "."
            (``tracking_rms.com``, ``barrier_min.left_fist``), plus ``fell_time_s``;
            walking adds avg_forward_speed, steps_taken, leg_collisions,
            leg_contact_steps, swing_clearance_min and missed_touchdowns. trajectories
            None, or with ``cfg.decimate`` = k a dict of arrays (B, T, ...) of every k-th
            control step (tau, alive, qpos, u, status, fallback, qp_iterations, stance,
            ``y_<output>``, ``yd_<output>``, ``h_<barrier>``).

    Raises:
        BatchError: a bad config, chunk, or input (params not of the scenario's
            structure, shapes or batch sizes that do not match, non-finite pushes or
            perturbations, a negative push duration, an empty batch), before anything
            compiles.
        PoleError: with ``cfg.barrier``, a rollout whose poles fail Theorem 1 at its
            start state.
    """
    pl = plant(cfg)
    try:
        check_chunk(chunk)
    except ValueError as e:
        raise BatchError(str(e)) from None
    if push is None or perturb_v is None:
        leaves = jax.tree_util.tree_leaves(params)
        b = np.shape(leaves[0])[0] if leaves and np.ndim(leaves[0]) else 0
        if push is None:       # the scenario's own push on every rollout, or none
            own = pl.scenario.push
            push = Push.none(b) if own is None else Push(
                np.tile(np.asarray(own.force, float), (b, 1)), np.full(b, float(own.at)),
                np.full(b, float(own.duration)))
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
    t_half = metrics.half_time(n_steps, settle, cfg.control_dt)
    dec = int(cfg.decimate)
    ch = resolve_chunk(chunk, padded, ByPlatform(CPU_CHUNK)) if ndev == 1 else None
    fn = _compiled(pl, dec, -(-n_steps // dec) if dec else 0, ch, ndev)
    with jax_qp.blas_threads(1):      # see safewbc_jax/__init__.py
        final, recs = fn(*args, *_run_scalars(n_steps, settle, cfg.speed, t_half))
        final = final._replace(dx=None)
        final, recs = jax.tree_util.tree_map(lambda a: np.asarray(a)[:batch], (final, recs))
    return _finish(pl, final), recs


# the batched path's API; the config and the plant are batch.plant's
__all__ = ["BATCHED_SCENARIOS", "BatchConfig", "BatchError", "CPU_CHUNK", "Plant", "Push",
           "check_batch_poles", "compiled_text", "default_chunk", "default_params", "export",
           "largest_batch", "memory_bytes", "memory_model", "plant", "run_batch",
           "sole_forces_and_leg_contact", "start_etas"]
