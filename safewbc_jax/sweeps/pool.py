"""The ``mujoco`` engine of ``safewbc sweep``: a pool of worker processes, one per core,
each running whole rollouts with the deployment controller (``deploy.Controller``, PIQP)
around C MuJoCo, several side by side (``sim.lockstep``: each rollout its own
Controller lane and MjData; the controller's generated C step lane by lane where a C
compiler exists, else its jitted step vmapped over the lanes: ``lanes_engine``).

Each worker is pinned to one CPU, compiles the scenario's controller once
(``Controller.start`` and ``Lockstep.warm_up``; JAX's persistent compilation cache, when
the parent has one, is shared) and then takes groups of up to ``lockstep`` rollouts (a
chunk is split into groups by its size alone; ``lockstep_width``: 16, or the sweep's batch
where that is smaller, so that no lane is computed that no rollout can fill): per
rollout, reset its simulator to the stand keyframe plus its velocity perturbation,
``Controller.restart`` with its params (Theorem 1 at its own start), roll the group out,
and send back each rollout's metric columns (``metrics.table_columns``: the columns the
``mjx`` engine writes). A rollout's result depends only on its inputs and its group's
width, not on the worker that ran it nor on the order.

Failures never stall a chunk: a rollout that raises comes back with the reason; a worker
that dies or sends nothing for ``rollout_timeout`` seconds per rollout of its group is
killed and replaced, and its group is run again (``retries`` times) and then recorded as
failed with the reason in the ``error`` column (metrics NaN, counts -1). Workers end with
the parent, also when it is killed (``PR_SET_PDEATHSIG``, and a check of the parent's pid
once a second). Linux ties ``PR_SET_PDEATHSIG`` to the thread that started the worker:
use a pool from one thread that outlives it.
"""

from __future__ import annotations

import operator
import os
import signal
import time
import traceback
from typing import Any, NamedTuple

import numpy as np

ENGINES = ("auto", "mjx", "mujoco")
LOCKSTEP = 16                 # rollouts a worker runs side by side (sim.lockstep)
START_TIMEOUT_S = 1800.0      # a worker's import, compile and warm-up


class Job(NamedTuple):
    """What a worker process needs to roll out a sweep's
    chunks: the sweep's ``run`` (``SweepSpec.run``, a ``runspec.RunSpec``), the lockstep
    width, JAX's compilation cache folder (None: none), the engine, the mjx engine's
    precision (``BatchConfig.precision``) and the mujoco engine's lanes' step
    (``lanes_engine``: "c" or "xla", the same for every worker of a sweep: the two round
    differently). Pickled to each worker."""

    run: Any
    lockstep: int
    cache_dir: str | None = None
    engine: str = "mujoco"
    precision: str = "float64"
    lanes: str = "xla"


def lanes_engine() -> str:
    """The step the mujoco engine's lanes run on this machine: "c" (the generated C, one
    lane after another: ``sim.lockstep.CLanes``) where a C compiler exists and builds a
    shared library (``build.works``), else "xla" (the jitted step vmapped over the
    lanes)."""
    from safewbc_jax.deploy.codegen.build import works

    return "c" if works() else "xla"


def lockstep_width(batch) -> int:
    """The lockstep width of a pool whose chunks hold at most ``batch`` rollouts: ``LOCKSTEP``,
    or ``batch`` where that is smaller (None, or "auto" before it is resolved:
    ``LOCKSTEP``). Every lane of XLA's vmapped step is computed, filled or not, so narrow
    chunks run faster at their own width (benchmarks/README.md, "Figures behind design
    choices"); C lanes cost nothing unfilled."""
    if isinstance(batch, (int, np.integer)) and batch >= 1:
        return min(LOCKSTEP, int(batch))
    return LOCKSTEP


def available_cpus() -> list[int]:
    """The CPUs this process may run on, in order."""
    return sorted(os.sched_getaffinity(0))


def check_workers(workers: int | None) -> int:
    """The worker count to use (None: one per available CPU); raises ValueError naming
    the count when it is below 1 or above the CPUs this process may run on."""
    cpus = available_cpus()
    if workers is None:
        return len(cpus)
    if int(workers) != workers or workers < 1:
        raise ValueError(f"--workers {workers}: must be an integer >= 1")
    if workers > len(cpus):
        raise ValueError(f"--workers {workers}: this process may run on {len(cpus)} CPU(s) "
                         f"({cpus}); one worker is pinned to each")
    return int(workers)


def _die_with_parent(parent_pid: int):
    """Ask Linux to SIGKILL this process when its parent ends (prctl PR_SET_PDEATHSIG); the
    worker loop also checks the parent's pid, where prctl is not available."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent_pid:        # the parent ended before prctl took effect
        os._exit(1)


class Lanes:
    """One process's deployment loops of a sweep's run: the scenario's controller compiled
    once (``Controller.start`` and ``Lockstep.warm_up``), then any number of lockstep
    groups. ``job``: its run, cache_dir, lockstep (the width of ``sim.lockstep.Lockstep``)
    and lanes (the controller's engine: "c" or "xla"). Start JAX on the CPU
    (``safewbc_jax.use_cpu``) first."""

    def __init__(self, job: Job):
        from safewbc_jax.base import runtime

        runtime.enable_x64()
        if job.cache_dir:
            runtime.use_compile_cache(job.cache_dir)
        from safewbc_jax.control import metrics
        from safewbc_jax.sim.lockstep import Lockstep
        from safewbc_jax.sim.mujoco_loop import SimRobot

        run = job.run
        self.dt = run.control_dt
        self.n_steps, _, _ = run.schedule()
        ctl = run.controller(engine=job.lanes)    # the lanes' step: C, or XLA vmapped
        sim = SimRobot(ctl.motors.names, self.dt)
        sim.reset()
        ctl.start(*sim.sm.to_controller(sim.d.qpos, sim.d.qvel), warm_up=False)
        self.lock = Lockstep(ctl, sim, job.lockstep)
        self.lock.warm_up()
        template = metrics.table_columns(
            metrics.finalize(ctl.scenario, ctl.tally.acc, metrics.plant_init(), False,
                             ctl.state.gait), -1, self.dt)
        self.dtypes = {k: np.asarray(v).dtype.str for k, v in template.items()}

    def run(self, tasks: list) -> list:
        """Roll out one lockstep group: an ``Outcome`` per task, with the table's metric
        columns (``metrics.table_columns``); an exception of the group fails each of its
        rollouts, with the reason."""
        from safewbc_jax.control import metrics
        from safewbc_jax.sim.lockstep import Outcome

        try:
            res = self.lock.run(tasks, self.n_steps)
            return [o if o.columns is None else
                    o._replace(columns=metrics.table_columns(o.columns, o.fell_step, self.dt))
                    for o in res]
        except Exception as e:  # noqa: BLE001 - the group's rollouts fail, with the reason
            traceback.print_exc()     # to the sweep's stderr: the why of the failure
            return [Outcome.failed(f"{type(e).__name__}: {e}")] * len(tasks)


def chunk_tasks(params, push, perturb_v) -> list:
    """A chunk's rollouts as lockstep tasks (``RolloutTask``)."""
    import jax

    from safewbc_jax.sim.lockstep import RolloutTask
    from safewbc_jax.control.push import Push

    perturb_v = np.asarray(perturb_v, float)
    leaves = jax.tree_util.tree_map(np.asarray, params)
    return [RolloutTask(jax.tree_util.tree_map(operator.itemgetter(i), leaves),
                        Push.single(push.force[i], float(push.at[i]), float(push.duration[i])),
                        perturb_v[i]) for i in range(perturb_v.shape[0])]


def lockstep_groups(m: int, width: int) -> list:
    """A chunk of ``m`` rollouts cut into lockstep groups of at most ``width``: a function of
    the chunk alone (not of the worker count), so a rollout is always computed in the same
    group, with the same neighbours, whoever runs it."""
    return [g.tolist() for g in np.array_split(np.arange(m), -(-m // width))]


def columns(dtypes: dict, m: int, results: dict, errors: dict) -> dict:
    """Per-rollout results -> columns (m,); a failed rollout's metrics NaN (floats),
    -1 (integers), False (flags), with its reason in ``error``."""
    cols = {}
    for name, dt in dtypes.items():
        dt = np.dtype(dt)
        fill = np.nan if dt.kind == "f" else (False if dt.kind == "b" else -1)
        cols[name] = np.array([np.asarray(results[i][name]).item() if i in results else fill
                               for i in range(m)], dtype=dt)
    cols["error"] = np.array([errors.get(i, "") for i in range(m)], dtype=object)
    return cols


def _worker(conn, job: Job, cpu: int | None, parent_pid: int):
    """A worker process (module docstring): ``Lanes`` of ``job``, then groups from
    ``conn`` until it sends None."""
    _die_with_parent(parent_pid)
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
    try:
        from safewbc_jax.base import runtime

        runtime.use_cpu()          # a CPU engine: never a GPU backend, whatever is installed
        lanes = Lanes(job)
        conn.send(("ready", lanes.n_steps, lanes.dtypes))
    except Exception:  # noqa: BLE001
        conn.send(("init-error", traceback.format_exc()))
        return
    while True:
        if not conn.poll(1.0):
            if os.getppid() != parent_pid:
                os._exit(1)
            continue
        msg = conn.recv()
        if msg is None:
            return
        g, tasks = msg
        conn.send(("done", g, lanes.run(tasks)))


class _Slot:
    """One worker process and what it is doing."""

    def __init__(self, ctx, job: Job, cpu: int | None):
        self.cpu = cpu
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker, args=(child, job, cpu, os.getpid()),
                                daemon=True)
        self.proc.start()
        child.close()
        self.task: int | None = None    # group index in flight
        self.since = time.monotonic()

    def kill(self):
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(5)
        self.conn.close()


def _death_reason(proc) -> str:
    code = proc.exitcode
    if code is None:
        return "worker did not exit"
    if code < 0:
        try:
            return f"worker killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"worker killed by signal {-code}"
    return f"worker exited with code {code}"


class PoolExecutor:
    """``run_sweep``'s executor for the ``mujoco`` engine: ``execute(spec, params, push,
    perturb_v)`` -> metric columns of the chunk's rollouts (numpy, leading axis the
    rollouts, plus ``error``: "" or why the rollout has no result). The workers start at
    the first call and live until ``close``. ``pads`` False: the sweep does not pad its last
    chunk for this engine."""

    pads = False

    def __init__(self, spec, workers: int | None = None, *, retries: int = 1,
                 rollout_timeout: float | None = None, cache_dir: str | None = None,
                 lockstep: int = LOCKSTEP, lanes: str | None = None):
        if int(lockstep) != lockstep or lockstep < 1:
            raise ValueError(f"lockstep {lockstep}: must be an integer >= 1")
        if lanes not in (None, "c", "xla"):
            raise ValueError(f"lanes {lanes!r}: 'c', 'xla' or None (lanes_engine())")
        self.spec = spec
        self.lockstep = int(lockstep)
        self.lanes = lanes      # None: the table's, which run_sweep sets, else lanes_engine()
        self.n_workers = check_workers(workers)
        self.retries = int(retries)
        self.rollout_timeout = rollout_timeout
        self.cache_dir = cache_dir
        self.slots: list[_Slot] = []
        self.dtypes: dict | None = None     # the metric columns, from the first worker
        self.n_steps: int | None = None     # control steps of a rollout, likewise
        self.restarts = 0

    # --- workers
    def _job(self) -> Job:
        if self.cache_dir is None:
            import jax

            self.cache_dir = getattr(jax.config, "jax_compilation_cache_dir", None)
        return Job(self.spec.run, self.lockstep, self.cache_dir,
                   lanes=self.lanes or lanes_engine())

    def _spawn(self, cpu) -> _Slot:
        import multiprocessing as mp

        return _Slot(mp.get_context("spawn"), self._job(), cpu)

    def _await_ready(self, slot: _Slot):
        """Wait for a new worker's compile; raises RuntimeError with its traceback when it
        cannot start (nothing of the sweep can run then)."""
        if not slot.conn.poll(START_TIMEOUT_S):
            slot.kill()
            raise RuntimeError(f"a sweep worker did not start within {START_TIMEOUT_S:.0f} s")
        try:
            msg = slot.conn.recv()
        except EOFError:
            raise RuntimeError(f"a sweep worker ended while starting ({_death_reason(slot.proc)})"
                               ) from None
        if msg[0] != "ready":
            slot.kill()
            raise RuntimeError(f"a sweep worker could not start:\n{msg[1]}")
        self.n_steps, self.dtypes = int(msg[1]), msg[2]

    def start(self):
        if self.slots:
            return
        cpus = available_cpus()[:self.n_workers]
        self.slots = [self._spawn(c) for c in cpus]
        for s in self.slots:
            self._await_ready(s)

    def close(self):
        for s in self.slots:
            try:
                s.conn.send(None)
            except (OSError, BrokenPipeError):
                pass
        for s in self.slots:
            s.proc.join(10)
            s.kill()
        self.slots = []

    def _timeout(self, n_steps: int, rollouts: int) -> float:
        """Seconds a worker may take for a group of ``rollouts`` run in lockstep."""
        if self.rollout_timeout is not None:
            return float(self.rollout_timeout) * rollouts
        return 120.0 + 0.02 * n_steps * rollouts   # 20 ms a robot-step: ~25x the measured

    # --- a chunk
    def __call__(self, spec, params, push, perturb_v) -> dict:
        self.start()
        n_steps, dtypes = self.n_steps, self.dtypes     # set by the first worker
        assert n_steps is not None and dtypes is not None
        tasks = chunk_tasks(params, push, perturb_v)
        m = len(tasks)
        groups = lockstep_groups(m, self.lockstep)
        todo = list(range(len(groups)))[::-1]      # popped from the end: in order
        tries = [0] * len(groups)
        results: dict[int, dict] = {}
        errors: dict[int, str] = {}
        from multiprocessing.connection import wait

        while len(results) + len(errors) < m:
            for s in self.slots:
                if s.task is None and todo:
                    g = todo.pop()
                    s.task, s.since = g, time.monotonic()
                    tries[g] += 1
                    s.conn.send((g, [tasks[i] for i in groups[g]]))
            busy = [s for s in self.slots if s.task is not None]
            ready = wait([s.conn for s in busy] + [s.proc.sentinel for s in busy], timeout=1.0)
            now = time.monotonic()
            for k, s in enumerate(list(self.slots)):
                if s.task is None:
                    continue
                reason = None
                if s.conn in ready:
                    try:
                        msg = s.conn.recv()
                    except (EOFError, OSError):
                        s.proc.join(5)
                        reason = _death_reason(s.proc)
                    else:
                        for i, r in zip(groups[msg[1]], msg[2]):
                            if r.columns is not None:
                                results[i] = r.columns
                            else:                      # the rollout raised: its own reason
                                errors[i] = r.error
                        s.task = None
                        continue
                elif s.proc.sentinel in ready or not s.proc.is_alive():
                    s.proc.join(5)
                    reason = _death_reason(s.proc)
                elif now - s.since > (limit := self._timeout(n_steps, len(groups[s.task]))):
                    reason = f"no result within {limit:.0f} s (worker killed)"
                if reason is None:
                    continue
                g = s.task
                s.kill()
                if tries[g] <= self.retries:
                    todo.append(g)
                else:
                    for i in groups[g]:
                        errors[i] = f"rollout {i} of the chunk: {reason}"
                self.restarts += 1
                new = self._spawn(s.cpu)
                self.slots[k] = new
                self._await_ready(new)
        return columns(dtypes, m, results, errors)


def resolve_engine(engine: str) -> str:
    """``--engine`` -> the engine that runs: "mjx" or "mujoco" as given; "auto": ``mjx`` on
    an accelerator and ``AUTO_CPU_ENGINE`` on a CPU (docs/sweeps.md, "Two engines")."""
    if engine not in ENGINES:
        raise ValueError(f"--engine {engine!r}: one of {', '.join(ENGINES)}")
    if engine != "auto":
        return engine
    import jax

    return "mjx" if jax.default_backend() != "cpu" else AUTO_CPU_ENGINE


# what "auto" runs on a CPU: the engine with the higher robot-steps/s in
# benchmarks/sweep_engines.py on the development machine (benchmarks/README.md:
# mujoco about 2x mjx)
AUTO_CPU_ENGINE = "mujoco"
