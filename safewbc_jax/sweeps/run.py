"""``safewbc sweep``: a spec's rollouts in chunks of batched closed-loop rollouts.

Rollout k of a sweep is setting k // repeats (row-major over the grid axes) with
perturbation draw k % repeats; its initial velocity perturbation comes from a generator
seeded by (seed, k). Chunk c holds rollouts [c B, (c + 1) B). On the mjx engine a short
last chunk is padded to B with copies of its last rollout (one compiled shape for the whole
sweep) and the padding is dropped before writing; the mujoco engine's executor says it
needs no padding (``pads = False``) and runs the short chunk as it is. Finished chunks are
Parquet files (see :mod:`.table`); a rerun skips them.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from safewbc_jax.ui.progress import Progress
from safewbc_jax.control.push import Push
from safewbc_jax.sweeps import inputs, sizing
from safewbc_jax.sweeps import table as table_mod
from safewbc_jax.sweeps.spec import SweepSpec

# (scenario, barrier, duration, settle, control_dt, batch) of the real rollouts this process
# has compiled (run_batch keeps its jitted rollout): a sweep's first chunk of one of these
# shows the phase "rolling out", not "compiling" (tune-poles' later rounds)
_COMPILED: set = set()


@dataclasses.dataclass
class SweepResult:
    out: Path
    n_rollouts: int
    chunks_total: int
    chunks_run: int
    chunks_skipped: int
    wall_s: float
    rollouts_per_s: float
    failed: dict = dataclasses.field(default_factory=dict)   # chunk -> why it has no result


def real_executor():
    """The mjx engine's executor: ``safewbc_jax.sim.mjx.rollout.run_batch``."""
    try:
        from safewbc_jax.sim.mjx.rollout import BatchConfig, run_batch
    except ImportError as e:
        raise RuntimeError(f"the batched rollout path is not available ({e}); sweeps need "
                           "safewbc_jax.sim.mjx.rollout.run_batch") from None

    def execute(spec: SweepSpec, params, push: Push, perturb_v: np.ndarray) -> dict:
        cfg = BatchConfig.of(spec.run, precision=spec.precision)
        metrics, _ = run_batch(cfg, params, push, perturb_v)
        return metrics

    return execute


def sim_model():
    import mujoco

    from safewbc_jax.base import paths

    return mujoco.MjModel.from_xml_path(str(paths.scene_xml()))


def chunk_inputs(spec: SweepSpec, base, settings: np.ndarray, rollouts: np.ndarray,
                 seed: int, std: np.ndarray):
    """Inputs of the rollouts ``rollouts`` (global indices): (params batch, ``Push`` batch,
    perturbation (len, nv), per-rollout columns to write)."""
    setting = rollouts // spec.repeats
    vals = settings[setting]
    params = inputs.params_batch(base, spec.axes, vals)
    push, push_cols = inputs.pushes(spec, vals)
    dv = inputs.perturbations(seed, rollouts, std, spec.noise_period)
    cols = {"rollout": rollouts.astype(np.int64), "setting": setting.astype(np.int64),
            "repeat": (rollouts % spec.repeats).astype(np.int64)}
    for j, a in enumerate(spec.axes):
        cols[a.name] = vals[:, j].astype(float)
    for b in spec.barriers:
        for i in range(spec.pole_counts[b]):
            cols[f"poles.{b}.p{i + 1}"] = params.poles[b][:, i].copy()
    for k in ("magnitude", "direction", "at", "duration", "fx", "fy", "fz"):
        cols[f"push.{k}"] = push_cols[k]
    cols["perturb.norm"] = np.linalg.norm(dv, axis=1)
    return params, push, dv, cols


def _pad(x, b):
    """Pad the leading axis of x to b rows with copies of its last row."""
    x = np.asarray(x)
    n = x.shape[0]
    if n == b:
        return x
    return np.concatenate([x, np.repeat(x[-1:], b - n, axis=0)], axis=0)


def _fmt_s(s: float) -> str:
    if not np.isfinite(s):
        return "?"
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def preflight(spec: SweepSpec, seed: int | None = None, *, check_poles: bool = True):
    """Every check of a parsed spec before the closed loop compiles:
    the fixed params, the perturbation scales against the simulation model, the grid, and
    (``check_poles``) Theorem 1 for every rollout at its own perturbed start state
    (``admissible.check_sweep``; seconds, one small jit). Returns (base params, velocity
    std, settings array) for the run. ``seed`` None: the spec's."""
    seed = spec.seed if seed is None else int(seed)
    base = inputs.base_params(spec)
    std = inputs.velocity_std(spec, sim_model())
    settings = spec.settings_array()
    if check_poles:
        from safewbc_jax.sweeps.admissible import check_sweep

        check_sweep(spec, base, settings, seed, std)
    return base, std, settings


@dataclasses.dataclass
class SweepPlan:
    """What is settled before a sweep's first chunk: the options resolved and checked,
    the chunk plan written to the folder's manifest, the inputs' common parts, and the
    chunks this call runs."""

    spec: SweepSpec
    out: Path
    seed: int
    batch: int
    engine: str              # "mjx" or "mujoco"
    workers: int | None      # the local pool's (None: mjx, or Ray)
    width: int               # the mujoco engine's lockstep width
    chunks: list             # [(start, stop)) of every chunk of the plan
    manifest: table_mod.Manifest
    base: Any                # preflight's: the fixed params, velocity std, settings
    std: np.ndarray
    settings: np.ndarray
    done: set                # chunks already in the table
    todo: list               # chunks this call runs


def _resolve(spec: SweepSpec, out: Path, batch, seed, engine: str, workers, ray, hosts: int,
             host_index: int, quiet) -> tuple[int, int, str, int | None]:
    """(seed, batch, engine, workers) from the options, each checked, naming the option."""
    from safewbc_jax.sweeps import pool as pool_mod

    if not (hosts >= 1 and 0 <= host_index < hosts):
        raise ValueError(f"host index {host_index} of {hosts} hosts: expected 0 <= index < hosts")
    if ray is not None:
        from safewbc_jax.sweeps import cluster

        cluster.check_options(ray, hosts, workers)
        cluster.connect(ray, quiet)
        engine = cluster.resolve_engine(engine)
    seed = spec.seed if seed is None else int(seed)
    if batch == "auto":
        batch = (cluster.auto_batch(spec, out, engine) if ray is not None else
                 sizing.auto_batch(spec, out, pool_mod.resolve_engine(engine), quiet))
    batch = spec.batch if batch is None else int(batch)
    if batch < 1:
        raise ValueError(f"--batch must be >= 1, got {batch}")
    if seed < 0:
        raise ValueError(f"--seed must be >= 0, got {seed}")
    asked = engine
    engine = pool_mod.resolve_engine(engine)
    if engine == "mujoco" and ray is None:
        workers = pool_mod.check_workers(workers)
        if spec.precision != "float64":
            raise ValueError(f"sweep.precision = {spec.precision!r} is the mjx engine's "
                             f"(--engine mjx); the mujoco engine runs float64")
    elif workers is not None:
        raise ValueError(f"--workers {workers}: only the mujoco engine has workers, and "
                         f"--engine {asked} runs mjx here (--engine mujoco)")
    return seed, batch, engine, workers


def _manifest(spec: SweepSpec, seed: int, batch: int, n_chunks: int, engine: str,
              width: int, lanes: str | None) -> table_mod.Manifest:
    """The folder's plan (``sweep.json``): what a resumed or second host's run must share."""
    return table_mod.Manifest(
        fingerprint=spec.fingerprint(), seed=seed, batch=batch, n_rollouts=spec.n_rollouts,
        n_chunks=n_chunks, scenario=spec.scenario, spec_path=spec.path,
        axes=tuple(a.name for a in spec.axes), barriers=tuple(spec.barriers),
        monitors=tuple(spec.monitors), outputs=tuple(spec.outputs), target=spec.target,
        violation_tol=spec.violation_tol, repeats=spec.repeats,
        objective=tuple(spec.tune.objective), objective_weights=dict(spec.tune.weights),
        safe_sets=tuple(spec.safe_sets), engine=engine,
        # rollouts side by side per worker: rounding depends on it
        lockstep=width if engine == "mujoco" else None,
        lanes=lanes if engine == "mujoco" else None)   # C or XLA lanes: rounding too


def _lanes(out: Path) -> str:
    """The mujoco engine's lanes' step for folder ``out``: this machine's
    (``pool.lanes_engine``), but XLA's where ``out`` holds a table begun with XLA lanes
    (a C compiler missing there, or a folder from before the C lanes): XLA runs anywhere,
    and the table keeps one rounding."""
    from safewbc_jax.sweeps import pool as pool_mod

    try:
        if table_mod.read_manifest(out).lanes == "xla":
            return "xla"
    except table_mod.TableError:      # no folder yet, or one that open_manifest refuses
        pass
    return pool_mod.lanes_engine()


def plan_sweep(spec: SweepSpec, out, *, batch=None, seed=None, executor=None,
               spec_text: str | None = None, max_chunks: int | None = None,
               check_poles: bool = True, hosts: int = 1, host_index: int = 0,
               engine: str = "mjx", workers: int | None = None, ray: str | None = None,
               quiet=False, say=print) -> SweepPlan:
    """Every check and the folder's plan, before any chunk runs (``run_sweep``'s
    arguments): the options, the spec's preflight, the manifest created or matched, the
    partial files of a killed run removed, the chunks already done found."""
    from safewbc_jax.sweeps import pool as pool_mod

    out = Path(out)
    seed, batch, engine, workers = _resolve(spec, out, batch, seed, engine, workers, ray,
                                            hosts, host_index, quiet)
    chunks = table_mod.plan_chunks(spec.n_rollouts, batch)
    width = getattr(executor, "lockstep", None) or pool_mod.lockstep_width(batch)
    lanes = getattr(executor, "lanes", None) or _lanes(out)
    manifest = _manifest(spec, seed, batch, len(chunks), engine, width, lanes)
    base, std, settings = preflight(spec, seed, check_poles=check_poles)
    table_mod.open_manifest(out, manifest, spec_text)
    mine = {k for k in range(len(chunks)) if k % hosts == host_index}
    stale = table_mod.remove_partial(out, mine if hosts > 1 else None)
    if stale:
        say(f"[sweep] removed {len(stale)} partial chunk file(s) of an interrupted run")
    done = table_mod.finished_chunks(out)
    extra = sorted(k for k in done if k >= len(chunks))
    if extra:
        raise table_mod.TableError(f"{out}: chunk files {extra} beyond the plan's {len(chunks)} "
                                   "chunks; the directory was written by another plan")
    todo = [k for k in range(len(chunks)) if k not in done and k in mine]
    if done:
        say(f"[sweep] {out}: {len(done)}/{len(chunks)} chunks already done, "
            f"{len(todo)} to run" + (f" on host {host_index} of {hosts}" if hosts > 1 else ""))
    if max_chunks is not None:
        todo = todo[:max_chunks]
    return SweepPlan(spec, out, seed, batch, engine, workers, width, chunks, manifest, base,
                     std, settings, done, todo)


def run_sweep(spec: SweepSpec, out, *, batch: int | None = None, seed: int | None = None,
              executor: Any = None, progress: Callable | None = None,
              spec_text: str | None = None, max_chunks: int | None = None,
              check_poles: bool = True, hosts: int = 1, host_index: int = 0,
              quiet: bool = False, desc: str | None = None, stream=None,
              engine: str = "mjx", workers: int | None = None,
              ray: str | None = None) -> SweepResult:
    """Run (or resume) the sweep into ``out``. ``executor(spec, params, push, perturb_v)``
    (a batch: ControllerParams, ``push.Push`` and perturbations with a leading rollout axis)
    returns the metrics dict of the batch (default: the real ``run_batch``); an executor
    with ``map_chunks(spec, jobs)`` instead takes every (chunk, params, push, perturb_v) of
    ``jobs`` and yields (chunk, metrics, None), or (chunk, None, why it has no result), in
    the order the chunks finish (``cluster.RayExecutor``).
    ``max_chunks`` stops after that many chunks of this call.
    Progress: with ``progress`` None, a tqdm bar of the rollouts (``progress.Progress``,
    titled ``desc``) and the messages go to ``stream`` (default stderr), nothing with
    ``quiet``; a ``progress`` callable instead receives every message and one line per
    chunk, and no bar is drawn.
    With ``hosts`` N > 1 this process runs the chunks k with k mod N = ``host_index`` (the
    same command on N hosts sharing ``out`` runs the whole sweep once).
    ``engine``: "mjx" (the batched MJX closed loop, ``batch.rollout``) or "mujoco" (a pool
    of ``workers`` deployment loops, one per CPU, ``sweeps.pool``; None: one per CPU this
    process may use); "auto" is resolved by ``pool.resolve_engine``. The engine is in the
    manifest: a table is resumed only with the engine that began it.
    ``ray``: run every pending chunk as a task on the Ray cluster at that address
    (``cluster.LOCAL``: one started on this machine; ``sweeps.cluster``); a chunk that has
    no result after its retries is in ``SweepResult.failed``, with the reason, and the
    others are written."""
    from safewbc_jax.sweeps import pool as pool_mod

    say = progress if progress is not None else (lambda msg: None) if quiet else (
        lambda msg: print(msg, file=sys.stderr if stream is None else stream, flush=True))
    plan = plan_sweep(spec, out, batch=batch, seed=seed, executor=executor,
                      spec_text=spec_text, max_chunks=max_chunks, check_poles=check_poles,
                      hosts=hosts, host_index=host_index, engine=engine, workers=workers,
                      ray=ray, quiet=quiet or progress is not None, say=say)
    if not plan.todo:
        return SweepResult(plan.out, spec.n_rollouts, len(plan.chunks), 0, len(plan.done),
                           0.0, float("nan"))
    own = executor is None and plan.engine == "mujoco" and ray is None
    if executor is None and ray is not None:
        from safewbc_jax.sweeps import cluster

        executor = cluster.RayExecutor(spec, plan.engine, lockstep=plan.width, address=ray,
                                       quiet=quiet)
    execute = (executor or (pool_mod.PoolExecutor(spec, plan.workers, lockstep=plan.width)
                            if own else real_executor()))
    if getattr(execute, "lanes", "") is None and plan.manifest.lanes is not None:
        execute.lanes = plan.manifest.lanes   # an executor without its lanes: the table's
    key = (None if executor is not None or plan.engine != "mjx" else
           (spec.scenario, spec.barrier, spec.duration, spec.settle, spec.control_dt,
            plan.batch, spec.safe_sets))
    try:
        return _run_chunks(plan, execute, key, say, progress, quiet, desc, stream)
    finally:
        if own:
            execute.close()


def _run_chunks(plan: SweepPlan, execute, key, say, progress, quiet, desc,
                stream) -> SweepResult:
    """The plan's chunks through ``execute``, each written as its result comes back, with
    the bar or the progress lines (``run_sweep``)."""
    import jax

    spec, chunks, todo, batch, out = plan.spec, plan.chunks, plan.todo, plan.batch, plan.out
    n = spec.n_rollouts
    pads = getattr(execute, "pads", True)
    t0 = t_chunk = time.perf_counter()
    ran = 0
    chunk_times = []
    devs = jax.devices()
    where = (execute.describe() if hasattr(execute, "describe") else
             f"on {len(devs)} device{'s' if len(devs) > 1 else ''} ({devs[0].platform})"
             if plan.engine == "mjx" else
             f"on {plan.workers} MuJoCo worker{'s' if (plan.workers or 0) > 1 else ''}")
    say(f"[sweep] {spec.scenario}: {n} rollouts ({spec.n_settings} settings x {spec.repeats}) "
        f"in {len(chunks)} chunk{'s' if len(chunks) > 1 else ''} of {batch} {where}"
        + ("" if key in _COMPILED else "; the first chunk includes compilation"))
    # the bar: this process's rollouts, after those already in the table
    done_n = sum(chunks[j][1] - chunks[j][0] for j in plan.done)
    bar = Progress(desc or "[sweep]", unit="rollouts", initial=done_n,
                   total=done_n + sum(chunks[j][1] - chunks[j][0] for j in todo),
                   phase="rolling out" if key in _COMPILED else "compiling",
                   quiet=quiet or progress is not None, stream=stream)
    pending: dict = {}          # chunk -> its per-rollout input columns, until written
    failed: dict = {}
    seen: set = set()           # chunks of this call with a result or a failure

    def jobs():
        for k in todo:
            start, stop = chunks[k]
            params, push, dv, pending[k] = chunk_inputs(spec, plan.base, plan.settings,
                                                        np.arange(start, stop), plan.seed,
                                                        plan.std)
            if stop - start < batch and pads:
                params, push, dv = jax.tree_util.tree_map(lambda x: _pad(x, batch),
                                                          (params, push, dv))
            yield k, params, push, dv

    results = (execute.map_chunks(spec, jobs()) if hasattr(execute, "map_chunks") else
               ((k, execute(spec, params, push, dv), None) for k, params, push, dv in jobs()))
    try:
        for k, metrics, why in results:
            seen.add(k)
            start, stop = chunks[k]
            m = stop - start
            cols = pending.pop(k)
            if why is not None:
                failed[k] = why
                say(f"[sweep] chunk {k} has no result: {why}")
                continue
            if key is not None:
                _COMPILED.add(key)
            rows = batch if pads else m
            for name, v in metrics.items():
                v = np.asarray(v)
                if v.shape[:1] != (rows,):
                    raise RuntimeError(f"the executor returned metric {name!r} of shape "
                                       f"{v.shape}, expected ({rows},)")
                cols[name] = v[:m]
            if "error" not in cols:     # the mjx engine: a failure fails the whole chunk
                cols["error"] = np.full(m, "", dtype=object)
            cols["chunk"] = np.full(m, k, np.int64)
            table_mod.write_chunk(out, k, cols, {"chunk": k, "start": start, "stop": stop,
                                                "seed": plan.seed,
                                                "fingerprint": plan.manifest.fingerprint})
            ran += m
            if progress is None:       # the bar (nothing with quiet)
                bar.update(m, "rolling out")
                continue
            # a progress callable: one line per chunk
            now = time.perf_counter()
            chunk_times.append((m, now - t_chunk))
            t_chunk = now
            el = now - t0
            # after the first chunk (which compiles), estimate from the later ones only
            steady = chunk_times[1:] or chunk_times
            rate = sum(x for x, _ in steady) / max(sum(t for _, t in steady), 1e-9)
            left = sum(chunks[j][1] - chunks[j][0] for j in todo if j not in seen)  # this process's
            total_done = sum(chunks[j][1] - chunks[j][0] for j in table_mod.finished_chunks(out))
            say(f"[sweep] {total_done}/{n} rollouts  {rate:.3g} rollouts/s  "
                f"ETA {_fmt_s(left / rate if rate > 0 else float('inf'))}  "
                f"(chunk {k + 1}/{len(chunks)}, {el:.0f} s so far"
                + (", first chunk with compilation" if len(chunk_times) == 1 else "") + ")")
    finally:
        bar.close()
    el = time.perf_counter() - t0
    return SweepResult(out, n, len(chunks), len(todo) - len(failed), len(plan.done), el,
                       ran / el if el > 0 else float("nan"), failed)
