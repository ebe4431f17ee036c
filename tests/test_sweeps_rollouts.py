"""``safewbc sweep`` end to end with the real batched closed loop (safewbc_jax.sim.mjx.rollout):
kill-safety, resume, determinism and the same table on two CPU devices.

Every rollout here runs in a subprocess (a sweep to kill, a process with two host
devices), all with one configuration (arms, 0.05 s of motion after the 1 s settle that
the reference blend needs, batch size BATCH), and share JAX's persistent compilation cache
so that the closed-loop step is compiled once per device count. The one- and two-device
sweeps run side by side (their compilations are single-threaded).

The one-device program (arms, float64, batch 2, no trajectories) is also the notebook's,
the mjx tuning test's and the MJX arms test's (test_mjx_closed_loop.py), each of which
loads it from the cache: the spec adds no safe set of its own for that reason (a user's
safe set in an mjx sweep is test_user_scenario.py's).
"""

import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from safewbc_jax.sweeps import pool
from safewbc_jax.sweeps import table as table_mod

ROOT = Path(__file__).resolve().parents[1]
BATCH = 2
SPEC = """
[sweep]
scenario = "arms"
duration = 0.05
settle = 1.0
repeats = 2
seed = 7
violation_tol = 0.001

[grid]
"poles.left_fist.p1" = [5.0, 20.0]

[perturb]
base_linear = 0.02
joints = 0.05
"""


def cache_dir() -> str:
    """JAX's persistent compilation cache of these tests (and of the notebook test)."""
    return os.environ.get("JAX_COMPILATION_CACHE_DIR") or os.path.join(
        tempfile.gettempdir(), "safewbc-jax-test-xla-cache")


def sweep_env(devices: int = 1) -> dict:
    env = {**os.environ, "JAX_COMPILATION_CACHE_DIR": cache_dir(),
           "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    flags = [f for f in env.get("XLA_FLAGS", "").split() if "device_count" not in f]
    if devices > 1:
        flags.append(f"--xla_force_host_platform_device_count={devices}")
    env["XLA_FLAGS"] = " ".join(flags)
    return env


def sweep_cmd(spec: Path, out: Path) -> list:
    # the mjx engine unless a test appends another --engine (the last one counts): "auto"
    # picks mujoco on a CPU
    return [sys.executable, "-m", "safewbc_jax.app.cli", "sweep", str(spec), "--out", str(out),
            "--batch", str(BATCH), "--engine", "mjx"]


DEVICES = 4   # the multi-device sweep's CPU devices (--xla_force_host_platform_device_count)

# the closed loop that run_batch compiles for the multi-device sweep, its optimised HLO
# written to argv[1] (a load from the persistent cache once the sweep compiled it)
HLO_SCRIPT = """
import sys
import safewbc_jax
safewbc_jax.enable_x64()
safewbc_jax.use_compile_cache(sys.argv[2])
from safewbc_jax.sim.mjx.rollout import BatchConfig, compiled_text
from safewbc_jax.sweeps.spec import load_spec
spec = load_spec(sys.argv[3])
open(sys.argv[1], "w").write(compiled_text(BatchConfig.of(spec.run), int(sys.argv[4])))
"""


@pytest.fixture(scope="module")
def sweeps(tmp_path_factory):
    """Run the spec three ways: (A) one device, killed with SIGKILL once its first chunk
    is on disk, then rerun to completion; (B) ``DEVICES`` devices, in one go, side by side
    with A, then the optimised HLO of B's closed loop."""
    tmp = tmp_path_factory.mktemp("sweeps")
    spec = tmp / "tiny.toml"
    spec.write_text(SPEC)
    a, b = tmp / "one_device", tmp / "devices"
    log_b = open(tmp / "b.log", "w")
    proc_b = subprocess.Popen(sweep_cmd(spec, b), env=sweep_env(DEVICES), stdout=log_b,
                              stderr=subprocess.STDOUT, cwd=tmp)
    log_a = open(tmp / "a1.log", "w")
    proc_a = subprocess.Popen(sweep_cmd(spec, a), env=sweep_env(1), stdout=log_a,
                              stderr=subprocess.STDOUT, cwd=tmp)
    first = table_mod.chunk_path(a, 0)
    t0 = time.time()
    while not first.exists():
        assert proc_a.poll() is None, (tmp / "a1.log").read_text()[-3000:]
        assert time.time() - t0 < 1200, "the first chunk took more than 20 minutes"
        time.sleep(0.2)
    # the progress line follows the chunk's file by milliseconds: kill after it (a kill in
    # between lost the line once, fresh45), still within chunk 2's rollout (seconds)
    t1 = time.time()
    while "[sweep] 2/4 rollouts" not in (tmp / "a1.log").read_text() and time.time() - t1 < 10:
        time.sleep(0.02)
    proc_a.send_signal(signal.SIGKILL)   # now in chunk 2 of 2 (compiled, rolling out)
    proc_a.wait()
    log_a.close()
    killed = {"finished": table_mod.finished_chunks(a), "cols": table_mod.read_columns(a),
              "chunk0": first.read_bytes(), "rc": proc_a.returncode}
    r = subprocess.run(sweep_cmd(spec, a), env=sweep_env(1), capture_output=True, text=True,
                       cwd=tmp, timeout=1200)
    assert proc_b.wait(timeout=1800) == 0, (tmp / "b.log").read_text()[-3000:]
    log_b.close()
    hlo = tmp / "devices.hlo.txt"
    h = subprocess.run([sys.executable, "-c", HLO_SCRIPT, str(hlo), cache_dir(), str(spec),
                        str(BATCH)], env=sweep_env(DEVICES), capture_output=True, text=True,
                       cwd=tmp, timeout=900)
    assert h.returncode == 0, h.stderr[-3000:]
    return {"a": a, "b": b, "killed": killed, "resume": r, "hlo": hlo.read_text(),
            "b_log": (tmp / "b.log").read_text(), "a_log": (tmp / "a1.log").read_text()}


@pytest.mark.slow
@pytest.mark.timeout(2400)   # the module's sweeps run in this test's setup
def test_killed_sweep_keeps_a_readable_table_and_resumes(sweeps):
    k = sweeps["killed"]
    assert k["rc"] == -signal.SIGKILL
    # the kill lost only the chunk in flight: chunk 0 is whole and readable
    assert k["finished"] == {0}
    assert k["cols"]["rollout"].tolist() == list(range(BATCH))
    assert "[sweep] 2/4 rollouts" in sweeps["a_log"]
    assert "rollouts/s" in sweeps["a_log"] and "ETA" in sweeps["a_log"]
    # the rerun skipped chunk 0 (not rewritten) and ran chunk 1 only
    r = sweeps["resume"]
    assert r.returncode == 0, r.stderr[-3000:]
    assert "1/2 chunks already done, 1 to run" in r.stderr
    assert "2/2 chunks done (1 run now" in r.stdout
    a = sweeps["a"]
    assert table_mod.chunk_path(a, 0).read_bytes() == k["chunk0"]
    cols = table_mod.read_columns(a)
    assert cols["rollout"].tolist() == [0, 1, 2, 3]
    np.testing.assert_array_equal(cols["poles.left_fist.p1"], [5.0, 5.0, 20.0, 20.0])
    np.testing.assert_array_equal(cols["repeat"], [0, 1, 0, 1])
    # real closed-loop numbers: 1.05 s standing, nobody falls, every QP solved, the fist
    # (5 cm inside its safe set at rest) stays within a centimetre of it
    assert not cols["fell"].any()
    assert np.all(cols["qp_failed"] == 0)
    assert np.all(cols["qp_solved"] + cols["fallbacks"] == 1050)
    hmin = cols["barrier_min.left_fist"]
    assert np.all((hmin > 0.035) & (hmin < 0.0505))
    assert np.all(cols["foot_slip_max"] < 0.005)
    assert np.all(cols["perturb.norm"] > 0.01)
    # the perturbations differ between rollouts, and so do the outcomes
    assert len(np.unique(cols["barrier_min.left_fist"])) == 4


@pytest.mark.slow
def test_same_seed_same_table_on_one_and_several_devices(sweeps):
    """The sweep on four CPU devices (the batch split over them, in one go) gives the
    table of the one-device sweep that was killed and resumed."""
    assert f"on {DEVICES} devices" in sweeps["b_log"], sweeps["b_log"][-2000:]
    assert "on 1 device" in sweeps["a_log"]
    ta = table_mod.read_table(sweeps["a"]).drop_columns(["chunk"])
    tb = table_mod.read_table(sweeps["b"]).drop_columns(["chunk"])
    assert ta.column_names == tb.column_names
    for name in ta.column_names:
        x = ta.column(name).to_numpy(zero_copy_only=False)
        y = tb.column(name).to_numpy(zero_copy_only=False)
        if name == "eq_residual_max":
            # the equality residual is round-off itself (~3e-11, measured 2.3e-11 against
            # 2.9e-11 on one and two devices): both below the solver's 1e-8 acceptance
            assert np.all(x < 1e-8) and np.all(y < 1e-8), (x, y)
        elif x.dtype.kind == "f":
            # same inputs, same programme up to the partitioning: agreement to rounding
            np.testing.assert_allclose(x, y, rtol=1e-9, atol=1e-12, err_msg=name)
        else:
            np.testing.assert_array_equal(x, y, err_msg=name)


@pytest.mark.slow
def test_no_collective_inside_a_loop_on_several_devices(sweeps):
    """The closed loop that the multi-device sweep ran, as XLA compiled it for four CPU
    devices: each device runs its own loops (a shard_map over the batch), so no
    all-reduce, all-gather, collective-permute or all-to-all sits in a while loop's
    condition or body (none at all). Partitioning the one-device program by its input
    sharding instead put 20 of them in the loops (6 all-reduce, 5 all-gather, 3
    collective-permute, 6 all-to-all, measured), the interior point's and MJX's trip
    counts kept in step across the devices."""
    from hlo_loops import COLLECTIVES, collectives_in_loops

    text = sweeps["hlo"]
    loops, in_loops, found = collectives_in_loops(text)
    assert loops >= 20 and in_loops > 100, (loops, in_loops)   # the real closed loop
    assert found == {}, found
    assert not any(re.search(r"\s" + op + r"(?:-start)?\(", text) for op in COLLECTIVES)
    # one rollout per device: the batch of 2 padded to 4 and split
    assert "entry_computation_layout={(f64[1," in text


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_notebook_runs_in_small_configuration(tmp_path):
    """notebooks/tune_barrier_poles.ipynb end to end (sweep, report, `tune`, deployment run)
    in its small configuration, in a fresh kernel."""
    import json

    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(ROOT / "notebooks" / "tune_barrier_poles.ipynb", as_version=4)
    env = sweep_env(1)
    env.update(SAFEWBC_NOTEBOOK_SMALL="1", SAFEWBC_NOTEBOOK_OUT=str(tmp_path),
               SAFEWBC_ROOT=str(ROOT), MPLBACKEND="Agg")
    old = dict(os.environ)
    os.environ.update(env)       # the kernel inherits this process's environment
    try:
        NotebookClient(nb, timeout=1500, kernel_name="python3",
                       resources={"metadata": {"path": str(tmp_path)}}).execute()
    finally:
        os.environ.clear()
        os.environ.update(old)
    text = "\n".join(o.get("text", "") for c in nb.cells if c.cell_type == "code"
                     for o in c.get("outputs", []) if o.get("output_type") == "stream")
    images = sum("image/png" in o.get("data", {}) for c in nb.cells if c.cell_type == "code"
                 for o in c.get("outputs", []))
    assert "small configuration" in text
    # the sweep's table, the report, the tuned params and the deployment run
    cols = table_mod.read_columns(tmp_path / "sweep")
    assert len(cols["rollout"]) == 2 and not cols["fell"].any()
    assert (tmp_path / "sweep" / "summary.md").is_file() and images >= 4
    tuning = json.loads((tmp_path / "tune" / "tuning.json").read_text())
    best = tuning["best"]["params"]
    assert len(tuning["generations"]) == 2 and tuning["used"] == 4
    assert 2.0 <= best["poles.left_fist.p1"] <= 40.0 and 0.5 <= best["gain_scale.arms"] <= 2.0
    assert tuning["validation"]["n"] == 2
    from safewbc_jax.control.params import load_overrides

    tuned = load_overrides(tmp_path / "tuned_poles.toml")
    assert tuned["poles"]["left_fist"][0] == pytest.approx(best["poles.left_fist.p1"])
    m = json.loads((tmp_path / "deploy" / "metrics.json").read_text())
    assert m["poles"]["left_fist"][0] == pytest.approx(best["poles.left_fist.p1"])
    assert not m["fell"] and m["qp_failed"] == 0
    assert m["barrier_min"]["left_fist"] > 0.0


# --- the mujoco engine (sweeps.pool): the same spec through a pool of deployment loops

def _children(pid: int) -> set:
    """Pids of the live processes whose parent is ``pid`` (from /proc)."""
    kids = set()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                kids.add(int(d.name))
    return kids


def _alive(pid: int) -> bool:
    try:
        stat = (Path("/proc") / str(pid) / "stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.fixture(scope="module")
def mujoco_sweeps(tmp_path_factory):
    """The spec with ``--engine mujoco``: (C) two workers, the parent killed with SIGKILL
    once the first chunk is on disk, then rerun to completion on one worker; (D) one
    worker, in one go."""
    tmp = tmp_path_factory.mktemp("mujoco_sweeps")
    spec = tmp / "tiny.toml"
    spec.write_text(SPEC)
    c, d = tmp / "two_workers", tmp / "one_worker"
    cmd = lambda out, w: sweep_cmd(spec, out) + ["--engine", "mujoco", "--workers", str(w)]  # noqa: E731
    log = open(tmp / "c1.log", "w")
    proc = subprocess.Popen(cmd(c, 2), env=sweep_env(1), stdout=log, stderr=subprocess.STDOUT,
                            cwd=tmp)
    first = table_mod.chunk_path(c, 0)
    t0 = time.time()
    while not first.exists():
        assert proc.poll() is None, (tmp / "c1.log").read_text()[-3000:]
        assert time.time() - t0 < 900, "the first chunk took more than 15 minutes"
        time.sleep(0.1)
    workers = _children(proc.pid)
    proc.send_signal(signal.SIGKILL)      # its workers are in chunk 2 of 2
    proc.wait()
    log.close()
    t0 = time.time()
    while any(_alive(p) for p in workers) and time.time() - t0 < 15:
        time.sleep(0.1)
    left = [p for p in workers if _alive(p)]
    killed = {"finished": table_mod.finished_chunks(c), "workers": workers, "left": left}
    # the rerun on one worker: its one chunk is one lockstep group, which one worker runs
    # (a second would start, compile and idle)
    resume = subprocess.run(cmd(c, 1), env=sweep_env(1), capture_output=True, text=True,
                            cwd=tmp, timeout=900)
    one = subprocess.run(cmd(d, 1), env=sweep_env(1), capture_output=True, text=True, cwd=tmp,
                         timeout=900)
    other = subprocess.run(sweep_cmd(spec, d) + ["--engine", "mjx"], env=sweep_env(1),
                           capture_output=True, text=True, cwd=tmp, timeout=300)
    return {"c": c, "d": d, "killed": killed, "resume": resume, "one": one, "other": other,
            "c_log": (tmp / "c1.log").read_text()}


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_mujoco_engine_killed_resumed_and_any_worker_count_give_one_table(mujoco_sweeps):
    s = mujoco_sweeps
    k = s["killed"]
    assert "on 2 MuJoCo workers" in s["c_log"], s["c_log"][-2000:]
    assert k["finished"] == {0}
    # the workers (two, pinned) ended with their killed parent, within 15 s
    assert len(k["workers"]) >= 2 and not k["left"], k
    assert s["resume"].returncode == 0, s["resume"].stderr[-3000:]
    assert "1/2 chunks already done, 1 to run" in s["resume"].stderr
    assert "on 1 MuJoCo worker" in s["resume"].stderr
    assert s["one"].returncode == 0, s["one"].stderr[-3000:]
    assert "on 1 MuJoCo worker" in s["one"].stderr
    tc = table_mod.read_table(s["c"]).drop_columns(["chunk"])
    td = table_mod.read_table(s["d"]).drop_columns(["chunk"])
    assert tc.column_names == td.column_names
    # one rollout's result depends on its inputs only (the controller restarts, PIQP set up
    # afresh), so the same machine gives the same floats whichever worker ran it, after a
    # kill or not: compared exactly
    for name in tc.column_names:
        np.testing.assert_array_equal(tc.column(name).to_numpy(zero_copy_only=False),
                                      td.column(name).to_numpy(zero_copy_only=False),
                                      err_msg=name)
    for out in (s["c"], s["d"]):
        manifest = __import__("json").loads((out / table_mod.MANIFEST).read_text())
        # the workers ran BATCH lanes side by side, not 16: no lane a chunk cannot fill;
        # their step was the generated C where this machine has a compiler (CI has)
        assert manifest["engine"] == "mujoco" and manifest["lockstep"] == BATCH
        assert manifest["lanes"] == pool.lanes_engine()
    # resuming the mujoco table with the other engine is refused, naming the engine
    assert s["other"].returncode == 2
    assert "engine = 'mujoco'" in s["other"].stderr and "--engine" in s["other"].stderr


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_engines_agree_rollout_by_rollout(sweeps, mujoco_sweeps):
    """The mujoco engine (C MuJoCo + PIQP) against the mjx engine (MJX + the JAX QP
    solver) on the same spec: the same columns; barrier minima within 1 mm (the tolerance
    of tests/test_mjx_closed_loop.py; measured within 0.03 mm here), the same falls,
    violations and failed QPs."""
    tm = table_mod.read_columns(mujoco_sweeps["c"])
    tx = table_mod.read_columns(sweeps["a"])
    assert sorted(tm) == sorted(tx)
    assert tm["rollout"].tolist() == tx["rollout"].tolist() == [0, 1, 2, 3]
    assert (tm["error"] == "").all() and (tx["error"] == "").all()
    for name in ("barrier_min.left_fist", "barrier_min.right_fist"):
        np.testing.assert_allclose(tm[name], tx[name], atol=1e-3, rtol=0, err_msg=name)
        np.testing.assert_array_equal(tm[name] < -1e-3, tx[name] < -1e-3)
    for name in ("fell", "qp_failed", "control_steps", "perturb.norm", "poles.left_fist.p1"):
        np.testing.assert_array_equal(tm[name], tx[name], err_msg=name)


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_pool_worker_crash_and_hang_are_recorded_not_stalled(tmp_path):
    """A worker killed mid-rollout is replaced and its rollout run again (the same result as
    the uninterrupted run); with no retries left a killed or a hung (SIGSTOP) worker fails
    only its rollout, with the reason in ``error``, and the chunk completes."""
    import threading

    import safewbc_jax
    from safewbc_jax.sweeps import run as run_mod
    from safewbc_jax.sweeps.pool import PoolExecutor
    from safewbc_jax.sweeps.spec import load_spec

    safewbc_jax.enable_x64()
    spec_path = tmp_path / "tiny.toml"
    spec_path.write_text(SPEC)
    spec = load_spec(spec_path)
    base, std, settings = run_mod.preflight(spec, check_poles=False)
    params, push, dv, _ = run_mod.chunk_inputs(spec, base, settings, np.arange(2), spec.seed, std)
    # lockstep=1: a group per rollout, so a crash fails one rollout and spares the other
    pool = PoolExecutor(spec, 1, retries=1, rollout_timeout=10.0, cache_dir=cache_dir(),
                        lockstep=1)

    def chunk_with(signal_no):
        """The chunk, with ``signal_no`` sent to the worker while its first rollout runs
        (from a thread: the pool runs here, in the thread that started its workers)."""
        pool.start()
        slot = pool.slots[0]

        def send():
            t0 = time.time()
            while slot.task is None and time.time() - t0 < 60:
                time.sleep(0.01)
            time.sleep(0.2)
            os.kill(slot.proc.pid, signal_no)

        th = threading.Thread(target=send)
        if signal_no is not None:
            th.start()
        cols = pool(spec, params, push, dv)
        if signal_no is not None:
            th.join(60)
        return cols

    try:
        clean = chunk_with(None)
        assert (clean["error"] == "").all() and not clean["fell"].any()
        retried = chunk_with(signal.SIGKILL)       # replaced, rollout 0 run again
        assert pool.restarts == 1
        for name in clean:
            np.testing.assert_array_equal(retried[name], clean[name], err_msg=name)
        pool.retries = 0
        crashed = chunk_with(signal.SIGKILL)
        assert "SIGKILL" in crashed["error"][0] and crashed["error"][1] == ""
        assert np.isnan(crashed["barrier_min.left_fist"][0]) and crashed["qp_solved"][0] == -1
        assert crashed["barrier_min.left_fist"][1] == clean["barrier_min.left_fist"][1]
        hung = chunk_with(signal.SIGSTOP)
        assert "no result within 10 s" in hung["error"][0] and hung["error"][1] == ""
        assert pool.restarts == 3
    finally:
        pool.close()


# --- on a local Ray cluster (sweeps.cluster): the same spec, the same tables

def _ray_tasks(name: str = "run_chunk") -> list:
    """Pids of the Ray worker processes running a task of the function ``name`` (Ray titles
    such a process ``ray::NAME`` while the task runs)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                argv0 = (d / "cmdline").read_bytes().split(b"\0")[0]
            except OSError:
                continue
            if argv0.startswith(f"ray::{name}".encode()):
                pids.append(int(d.name))
    return pids


@pytest.fixture(scope="module")
def ray_sweeps(tmp_path_factory):
    """The spec on a Ray cluster that ``--ray`` starts on this machine (2 CPUs): (E) the
    mujoco engine, one of its workers SIGKILLed while it runs a chunk; (F) the mjx engine."""
    pytest.importorskip("ray")
    tmp = tmp_path_factory.mktemp("ray_sweeps")
    spec = tmp / "tiny.toml"
    spec.write_text(SPEC)
    e, f = tmp / "ray_mujoco", tmp / "ray_mjx"
    log = open(tmp / "e.log", "w")
    proc = subprocess.Popen(sweep_cmd(spec, e) + ["--engine", "mujoco", "--ray"],
                            env=sweep_env(1), stdout=log, stderr=subprocess.STDOUT, cwd=tmp)
    killed, t0 = None, time.time()
    while proc.poll() is None and killed is None and time.time() - t0 < 600:
        pids = _ray_tasks()
        if pids:
            time.sleep(0.5)                # inside the task: its compile or its rollouts
            if proc.poll() is None and not table_mod.finished_chunks(e):
                os.kill(pids[0], signal.SIGKILL)
                killed = pids[0]
        time.sleep(0.05)
    rc = proc.wait(timeout=900)
    log.close()
    mjx = subprocess.run(sweep_cmd(spec, f) + ["--ray"], env=sweep_env(1),
                         capture_output=True, text=True, cwd=tmp, timeout=900)
    return {"e": e, "f": f, "killed": killed, "rc": rc, "e_log": (tmp / "e.log").read_text(),
            "mjx": mjx}


def _same_table(x, y):
    tx = table_mod.read_table(x).drop_columns(["chunk"])
    ty = table_mod.read_table(y).drop_columns(["chunk"])
    assert tx.column_names == ty.column_names
    # a chunk's result is a function of its inputs: the same floats, whoever ran it
    for name in tx.column_names:
        np.testing.assert_array_equal(tx.column(name).to_numpy(zero_copy_only=False),
                                      ty.column(name).to_numpy(zero_copy_only=False),
                                      err_msg=name)


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_ray_sweeps_give_the_one_process_tables_also_after_a_killed_worker(
        ray_sweeps, sweeps, mujoco_sweeps):
    r = ray_sweeps
    assert r["killed"] is not None, r["e_log"][-3000:]        # a worker died mid-chunk
    assert r["rc"] == 0, r["e_log"][-3000:]
    assert "on a Ray cluster (1 node, 2 CPUs, one chunk per CPU, mujoco engine)" in r["e_log"]
    assert table_mod.finished_chunks(r["e"]) == {0, 1}
    _same_table(r["e"], mujoco_sweeps["d"])          # the pool's table, one worker
    assert r["mjx"].returncode == 0, r["mjx"].stderr[-3000:]
    assert "mjx engine" in r["mjx"].stderr
    _same_table(r["f"], sweeps["a"])                 # the one-process mjx table


@pytest.mark.slow
def test_a_second_host_with_another_batch_is_refused(mujoco_sweeps, capsys):
    """A host started on the same folder with another --batch (here a finished sweep's,
    host 1 of 2) refuses with the reason and leaves the first plan as it was."""
    from safewbc_jax.app.cli import main

    d = mujoco_sweeps["d"]
    before = (d / table_mod.MANIFEST).read_bytes()
    rc = main(["sweep", str(d.parent / "tiny.toml"), "--out", str(d), "--batch", "1",
               "--hosts", "2", "--host-index", "1", "--engine", "mujoco", "--workers", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and "batch = 2, this one has 1 (another --batch)" in err, err
    assert (d / table_mod.MANIFEST).read_bytes() == before
