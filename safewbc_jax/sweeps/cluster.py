"""Ray as the engine of a sweep or a tuning run on more than one machine or device
(``safewbc sweep SPEC --out DIR --ray [ADDRESS]``, the same for ``tune``).

Each pending chunk is one Ray task with the resources its engine needs: one GPU for the
mjx engine on a cluster with GPUs (Ray gives the task's process that GPU alone, so each
GPU runs its own batch and its own loops), one CPU otherwise; one CPU for the mujoco
engine, whose task runs the chunk's lockstep groups in its process (``pool.Lanes``, JAX
on the CPU). A Ray worker process keeps what it compiled for the next chunk of the same
run. The driver receives each chunk's columns and writes the chunk's Parquet file as a
one-process sweep does (``run_sweep``): the workers need no shared filesystem. A task
whose worker dies is run again (``RETRIES`` times) on another; a chunk still without a
result is reported with the reason, its file not written, and a rerun of the same
command runs it (the finished chunks are skipped, as always).

A chunk's result is a function of its inputs, the batch and, on the mujoco engine, the
lockstep width: the table is the one-process table, whichever worker ran each chunk.
"""

from __future__ import annotations

import socket
from pathlib import Path
import warnings

from safewbc_jax.sweeps.pool import Job, lanes_engine

RETRIES = 2            # runs of a chunk's task after its worker died
CONNECT_TIMEOUT_S = 5.0
LOCAL = "local"        # --ray with no address: a Ray instance on this machine
INSTALL = "pip install 'safewbc-jax[ray]'"


class ClusterError(ValueError):
    """The Ray cluster asked for cannot be used (no Ray, an address that does not answer)."""


def _ray():
    try:
        import ray
    except ImportError:
        raise ClusterError(f"--ray needs Ray, which is not installed here: {INSTALL} "
                           "(or pip install '.[ray]' in a clone)") from None
    return ray


def check_options(ray: str | None, hosts: int = 1, workers: int | None = None) -> None:
    """Refuse the options ``--ray`` replaces, naming them: Ray schedules every chunk itself
    (no ``--hosts``/``--distributed``) on every CPU of the cluster (no ``--workers``)."""
    if ray is None:
        return
    if hosts > 1:
        raise ValueError(f"--ray with {hosts} hosts: Ray schedules every chunk itself; "
                         "--hosts and --distributed are for job arrays without Ray")
    if workers is not None:
        raise ValueError(f"--workers {workers} with --ray: Ray runs one chunk per CPU of the "
                         "cluster; --workers is the local pool's")


def check_address(address: str) -> None:
    """Raise ClusterError naming ``address`` unless it is "auto", or HOST:PORT (or
    ray://HOST:PORT) with HOST resolvable and PORT accepting a TCP connection within
    ``CONNECT_TIMEOUT_S``: a wrong address fails in seconds, not at Ray's own timeout."""
    if address == "auto":
        return
    rest = address[len("ray://"):] if address.startswith("ray://") else address
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ClusterError(f"--ray {address!r}: expected HOST:PORT (the head node's address "
                           "that `ray start --head` printed), ray://HOST:PORT or auto")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), CONNECT_TIMEOUT_S) as c:
            # Ray's head answers gRPC (HTTP/2): its first frame is SETTINGS (type 4). A port
            # that is something else would keep ray.init waiting for minutes
            c.settimeout(CONNECT_TIMEOUT_S)
            c.sendall(_H2_PREFACE)
            head = c.recv(9)
    except OSError as e:
        raise ClusterError(f"--ray {address}: cannot connect to {host} port {port} "
                           f"({e.strerror or e}); is `ray start --head` running there?"
                           ) from None
    if len(head) < 9 or head[3] != 4:
        raise ClusterError(f"--ray {address}: {host} port {port} answers, but not as a Ray "
                           "head node (no gRPC there); give the address that `ray start "
                           "--head` printed")


# an HTTP/2 client's connection preface and an empty SETTINGS frame
_H2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])


def connect(address: str | None = LOCAL, quiet: bool = False) -> None:
    """Join the Ray cluster at ``address`` (``LOCAL`` or None: start one on this machine,
    with its CPUs and GPUs), unless this process already has. Raises ClusterError."""
    ray = _ray()
    if ray.is_initialized():
        return
    local = address in (None, LOCAL)
    if address is not None and not local:
        check_address(address)
    kw = dict(include_dashboard=False, log_to_driver=not quiet, configure_logging=quiet)
    try:
        with warnings.catch_warnings():
            # JAX warns of any fork in a process where it runs; Ray's processes start by
            # fork and exec, which shares no JAX state
            warnings.filterwarnings("ignore", r"os\.fork\(\) was called", RuntimeWarning)
            ray.init(**kw) if local else ray.init(address=address, **kw)
    except ConnectionError as e:
        raise ClusterError(f"--ray {address}: {e}") from None


def gpus() -> float:
    """GPUs in the connected cluster."""
    return float(_ray().cluster_resources().get("GPU", 0.0))


def resolve_engine(engine: str) -> str:
    """``--engine auto`` on a cluster: mjx where the cluster has GPUs, else the CPU engine
    ``pool.AUTO_CPU_ENGINE``; "mjx" and "mujoco" as given."""
    from safewbc_jax.sweeps import pool

    if engine != "auto":
        return pool.resolve_engine(engine)
    return "mjx" if gpus() > 0 else pool.AUTO_CPU_ENGINE


def _resources(engine: str) -> dict:
    """A chunk task's resources: one GPU for mjx where the cluster has GPUs, else one CPU;
    the mujoco engine's workers start JAX on the CPU whatever the machine has."""
    if engine == "mjx" and gpus() > 0:
        return {"num_gpus": 1, "num_cpus": 1}
    if engine == "mujoco":
        return {"num_cpus": 1, "runtime_env": {"env_vars": {"JAX_PLATFORMS": "cpu"}}}
    return {"num_cpus": 1}


# --- what runs in a Ray worker process

_LANES: dict = {}       # (run, lockstep, lanes) -> pool.Lanes: made once per worker process


def run_chunk(job: Job, params, push, perturb_v) -> dict:
    """One chunk in this process: the metric columns of its rollouts. ``job``:
    ``pool.Job``, its engine the chunk's."""
    from safewbc_jax.base import runtime

    if job.engine == "mujoco":
        runtime.use_cpu()
        from safewbc_jax.sweeps import pool

        key = (job.run, job.lockstep, job.lanes)
        if key not in _LANES:
            _LANES.clear()
            _LANES[key] = pool.Lanes(job)
        lanes = _LANES[key]
        tasks = pool.chunk_tasks(params, push, perturb_v)
        results: dict = {}
        errors: dict = {}
        for group in pool.lockstep_groups(len(tasks), job.lockstep):
            for i, r in zip(group, lanes.run([tasks[i] for i in group])):
                if r.columns is not None:
                    results[i] = r.columns
                else:
                    errors[i] = r.error
        return pool.columns(lanes.dtypes, len(tasks), results, errors)
    runtime.enable_x64()
    if job.cache_dir:
        runtime.use_compile_cache(job.cache_dir)
    from safewbc_jax.sim.mjx.rollout import BatchConfig, run_batch

    return run_batch(BatchConfig.of(job.run, precision=job.precision), params, push,
                     perturb_v)[0]


def _auto_batch(spec, out: str) -> int:
    from safewbc_jax.sweeps.sizing import auto_batch

    return auto_batch(spec, Path(out), "mjx", quiet=True)


# --- the driver

def auto_batch(spec, out, engine: str) -> int:
    """``--batch auto`` on a cluster: a sweep already begun keeps its batch; the mjx engine
    on a cluster with GPUs sizes it on one of them (``sizing.auto_batch`` in a one-GPU
    task); otherwise the spec's ``sweep.batch``."""
    from safewbc_jax.sweeps.sizing import resumed_batch

    resumed = resumed_batch(out)
    if resumed is not None:
        return resumed
    if engine != "mjx" or gpus() == 0:
        return spec.batch
    ray = _ray()
    task = ray.remote(_auto_batch).options(num_gpus=1, num_cpus=1)
    return int(ray.get(task.remote(spec, str(out))))


class RayExecutor:
    """``run_sweep``'s executor on a Ray cluster: ``map_chunks`` sends every chunk as a
    task and yields (chunk, columns, None) as each finishes, in the order they finish, or
    (chunk, None, reason) for a chunk whose task failed ``RETRIES`` + 1 times or raised."""

    def __init__(self, spec, engine: str, *, lockstep: int, address: str | None = LOCAL,
                 cache_dir: str | None = None, quiet: bool = False, lanes: str | None = None):
        connect(address, quiet)
        if cache_dir is None:
            import jax

            cache_dir = getattr(jax.config, "jax_compilation_cache_dir", None)
        self.engine = engine
        self.pads = engine == "mjx"          # one compiled batch shape; the pool needs none
        self.lockstep = lockstep
        # the mujoco lanes' step, the same for every task (None: the table's, which
        # run_sweep sets, else the driver's): a node without a working C compiler then
        # fails its chunks of C lanes with that reason, rather than rounding otherwise
        self.lanes = lanes
        self.job = Job(spec.run, lockstep, cache_dir, engine, spec.precision)

    def describe(self) -> str:
        r = _ray().cluster_resources()
        what = "GPU" if self.engine == "mjx" and r.get("GPU", 0) else "CPU"
        n = int(r.get(what, 0))
        nodes = len([x for x in _ray().nodes() if x.get("Alive")])
        return (f"on a Ray cluster ({nodes} node{'s' if nodes != 1 else ''}, {n} {what}"
                f"{'s' if n != 1 else ''}, one chunk per {what}, {self.engine} engine)")

    def map_chunks(self, spec, jobs):
        ray = _ray()
        from ray.exceptions import RayError

        task = ray.remote(run_chunk).options(max_retries=RETRIES, **_resources(self.engine))
        job = ray.put(self.job._replace(lanes=self.lanes or lanes_engine()))
        refs = {task.remote(job, params, push, dv): k for k, params, push, dv in jobs}
        while refs:
            done, _ = ray.wait(list(refs), num_returns=1)
            k = refs.pop(done[0])
            try:
                yield k, ray.get(done[0]), None
            except RayError as e:
                msg = str(e).strip().splitlines()
                yield k, None, f"{type(e).__name__}: {msg[-1] if msg else ''}"


def describe_failures(failed: dict, out) -> str:
    """The chunks that have no result, with why, and what to do."""
    lines = [f"  chunk {k}: {why}" for k, why in sorted(failed.items())]
    return (f"{len(failed)} chunk(s) failed and were not written:\n" + "\n".join(lines)
            + f"\nrerun the same command to run them again (the finished chunks in {out} "
            "are kept)")
