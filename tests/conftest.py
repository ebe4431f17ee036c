import os
import tempfile
import time
from pathlib import Path

# before JAX starts its CPU backend: the XLA:CPU flags the package sets on import
# (safewbc_jax.CPU_XLA_FLAGS), as in the command and every process the tests start
import safewbc_jax

import jax
import numpy as np
import pytest

pytest_plugins = ["pytester"]

jax.config.update("jax_enable_x64", True)

# JAX's persistent compilation cache for the whole session and its subprocesses (the
# closed-loop rollout functions take minutes to compile on a 2-core CPU; tests that run
# the same one share it). Keyed by the compiled program, so a stale entry never matches.
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR",
                      os.path.join(tempfile.gettempdir(), "safewbc-jax-test-xla-cache"))
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 5.0)
# The subprocesses keep every program, the small eager ones too, as the command does
# (safewbc_jax.use_compile_cache): each process that starts a controller loads a few
# hundred of them instead of compiling them again (~7 s a process on a 2-core CPU).
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

# Two tiers: `pytest -m "not slow"` is the fast one (minutes), the full suite adds the
# tests marked slow (those that compile an MJX loop, run a closed loop or start a
# subprocess run). An unmarked test whose setup and call together take longer than this
# fails and names itself, so the fast tier stays fast. A module-scoped fixture is set up
# once for the unmarked tests of its module that use it, and each of them is charged its
# share (its setup time / their number) in place of the whole, whichever test happened to
# run first: its cost is theirs together (a jitted solver compiled once for five tests).
# A session-scoped fixture stays charged whole to the test that sets it up: mark that test
# slow where it is costly. With several xdist workers sharing the cores, a test's wall
# time also counts the time it waited for the others' CPU; there it is measured by the
# CPU time it used (its process's threads and its finished subprocesses) where that is
# less than its wall time.
try:
    FAST_LIMIT_S = float(os.environ.get("SAFEWBC_FAST_LIMIT_S", "20"))
except ValueError:
    raise pytest.UsageError("SAFEWBC_FAST_LIMIT_S must be a number of seconds, got "
                            f"{os.environ['SAFEWBC_FAST_LIMIT_S']!r}") from None

# The fast tier (`-m "not slow"`, exactly) compiles with LLVM's optimisation off: its tests
# are compile-bound (measured on a 2-core CPU: XLA backend compiles 179 of its 265 CPU s),
# their programs run for milliseconds, and the level changes how fast the machine code is,
# not what it computes (rounding of the order of 1e-16 where instructions are reordered).
# The full suite, which CI and the README run, compiles every test, these included, at
# XLA's default, as a user's program is. benchmarks/README.md, "The test suite", has the
# figures. A level named in XLA_FLAGS by the user is kept.
FAST_TIER_XLA_FLAGS = ("--xla_backend_optimization_level=0",)


def _fast_tier(config) -> bool:
    return " ".join((config.getoption("markexpr") or "").split()) == "not slow"


def pytest_configure(config):
    if not _fast_tier(config):
        return
    from jax._src import xla_bridge

    if xla_bridge.backends_are_initialized():
        raise pytest.UsageError("the fast tier's XLA flags must be set before JAX starts "
                                "its CPU backend, and something started it earlier")
    safewbc_jax.add_xla_flags(FAST_TIER_XLA_FLAGS)


def pytest_report_header(config):
    if _fast_tier(config):
        return f"fast tier: XLA_FLAGS={os.environ.get('XLA_FLAGS', '')}"


_SETUP_S = pytest.StashKey[float]()
_CPU0 = pytest.StashKey[float]()
_WALL0 = pytest.StashKey[float]()
_SHARED = pytest.StashKey[list]()      # (wall s, CPU s, users) of module fixtures set up
_SETTING_UP: list = [None]             # the test whose setup is running


def _cpu_s() -> float:
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def _shared_cores() -> bool:
    return int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_setup(item):
    item.stash[_CPU0] = _cpu_s()
    item.stash[_WALL0] = time.time()
    item.stash[_SHARED] = []
    _SETTING_UP[0] = item
    try:
        yield
    finally:
        _SETTING_UP[0] = None


def _fast_users(item, name: str) -> int:
    """The unmarked tests of ``item``'s module that use fixture ``name``."""
    return sum(1 for it in item.session.items
               if it.path == item.path and not it.get_closest_marker("slow")
               and name in getattr(it, "fixturenames", ()))


@pytest.hookimpl(hookwrapper=True)
def pytest_fixture_setup(fixturedef, request):
    """Times a module-scoped fixture's own setup (its dependencies are set up before this
    hook runs) for the guard's share, on the test whose setup ran it."""
    cpu0, wall0 = _cpu_s(), time.time()
    yield
    item = _SETTING_UP[0]
    if fixturedef.scope == "module" and item is not None:
        users = max(1, _fast_users(item, fixturedef.argname))
        item.stash[_SHARED].append((time.time() - wall0, _cpu_s() - cpu0, users))


# SAFEWBC_TEST_CPU_LOG=FILE: one tab-separated line a test (worker, test, start and end
# time, CPU seconds of its process and finished subprocesses from setup to teardown), for
# seeing where a run's time goes: benchmarks/README.md, "The test suite".
_CPU_LOG = os.environ.get("SAFEWBC_TEST_CPU_LOG")


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item, nextitem):
    if _CPU_LOG and _CPU0 in item.stash:
        with open(_CPU_LOG, "a") as f:
            f.write(f"{os.environ.get('PYTEST_XDIST_WORKER', 'main')}\t{item.nodeid}\t"
                    f"{item.stash[_WALL0]:.1f}\t{time.time():.1f}\t"
                    f"{_cpu_s() - item.stash[_CPU0]:.1f}\n")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    if rep.when == "setup":
        item.stash[_SETUP_S] = call.duration
        return
    if rep.when != "call" or not rep.passed or item.get_closest_marker("slow"):
        return
    shared = item.stash.get(_SHARED, [])
    # each module fixture set up here: its share in place of the whole
    rebate_wall = sum(w * (1 - 1 / n) for w, _, n in shared)
    rebate_cpu = sum(c * (1 - 1 / n) for _, c, n in shared)
    took = item.stash.get(_SETUP_S, 0.0) + call.duration - rebate_wall
    what = "setup and call"
    if _shared_cores() and _CPU0 in item.stash:
        cpu = _cpu_s() - item.stash[_CPU0] - rebate_cpu
        if cpu < took:
            took, what = cpu, "CPU time of setup and call, the cores shared with other workers"
    if shared:
        what += ", with its share of the module fixtures it set up"
    if took > FAST_LIMIT_S:
        rep.outcome = "failed"
        rep.longrepr = (f"{item.nodeid} took {took:.1f} s ({what}) without the "
                        f"'slow' marker: mark it @pytest.mark.slow, or make it faster "
                        f"(the fast tier's limit is {FAST_LIMIT_S:g} s a test)")


# Parallel runs (pytest-xdist, ``-n auto --dist loadfile`` in pyproject.toml): most of the
# suite's time is XLA compiling closed loops, one core each, so two test files at a time
# use a 2-core machine that one leaves half idle. Each file runs whole on one worker (its
# module fixtures are computed once); files that share session fixtures or compiled
# programs (through the persistent cache, which helps only when the second runs after the
# first) run as one unit (GROUPS, by ``pytest_xdist_make_scheduler``: xdist's own
# ``xdist_group`` marks do not group on pytest 9.2, pytest-xdist issue 1386). The long
# units start first, so that none starts last (the order only schedules). From the full
# suite's --durations on a 2-core CPU.
GROUPS = {"test_sweeps_rollouts.py": "sweep_engines", "test_tune_rollouts.py": "sweep_engines",
          "test_mjx_closed_loop.py": "deployment_runs", "test_closed_loop.py": "deployment_runs",
          "test_walking.py": "deployment_runs", "test_precision.py": "deployment_runs"}
LONG_FIRST = ("deployment_runs", "sweep_engines", "test_user_scenario.py", "test_examples.py",
              "test_cuda_lowering.py", "test_mjx_batch.py")
MAX_WORKERS = 4     # each worker may hold a closed-loop compile of a few GB


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config):
    """``-n auto``: PYTEST_XDIST_AUTO_NUM_WORKERS if set, else one worker per core, at
    most MAX_WORKERS."""
    env = os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS")
    if env:
        return int(env)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(cores or 1, MAX_WORKERS))


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile``, with the files of a GROUPS entry one unit."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class FileGroups(LoadScopeScheduling):
        def _split_scope(self, nodeid):
            path = nodeid.split("::", 1)[0]
            return GROUPS.get(Path(path).name, path)

    return FileGroups(config, log)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONG_FIRST)}
    items.sort(key=lambda it: rank.get(GROUPS.get(it.path.name, it.path.name),
                                       len(LONG_FIRST)))   # stable


@pytest.fixture(scope="session")
def ctrl_mj():
    import mujoco

    from safewbc_jax.base import paths

    return mujoco.MjModel.from_xml_path(str(paths.controller_xml()))


@pytest.fixture(scope="session")
def sim_mj():
    import mujoco

    from safewbc_jax.base import paths

    return mujoco.MjModel.from_xml_path(str(paths.scene_xml()))


@pytest.fixture(scope="session")
def rm(ctrl_mj):
    from safewbc_jax.model import robot

    return robot.from_mujoco(ctrl_mj)


def random_state(m, rng, spread=0.4):
    """A random controller state near the stand keyframe: random base pose, joints within
    +-spread rad of stand, random velocities."""
    q = m.key_qpos[0].copy()
    q[:3] = rng.normal(0, 0.5, 3)
    quat = rng.normal(size=4)
    q[3:7] = quat / np.linalg.norm(quat)
    q[7:] += rng.uniform(-spread, spread, m.nq - 7)
    v = rng.normal(0, 1.0, m.nv)
    return q, v


def mj_integrate(m, q, v, dt=1.0):
    """MuJoCo's own mj_integratePos (independent of safewbc_jax.model.spatial.integrate)."""
    import mujoco

    out = np.array(q, dtype=float)
    mujoco.mj_integratePos(m, out, np.asarray(v, float), dt)
    return out


def trajectory_point(m, q0, v0, a, t, substeps=400):
    """(q, v) at time t under q_ddot = a (constant) from (q0, v0), integrated with
    mj_integratePos in small midpoint steps: the reference trajectory of the drift tests."""
    q = np.array(q0, float)
    h = t / substeps
    for i in range(substeps):
        q = mj_integrate(m, q, v0 + a * (i + 0.5) * h, h)
    return q, v0 + a * t


@pytest.fixture(scope="session")
def arms_deployment(tmp_path_factory):
    """One MuJoCo + PIQP run of the arms scenario with its barrier (8 s of motion after a
    1 s settle: the fists pass their highest point at tau = 7.5 s), shared by the
    closed-loop test and the MJX consistency test: (metrics, output directory)."""
    from safewbc_jax.app.runner import run_scenario

    out = tmp_path_factory.mktemp("arms_deployment")
    return run_scenario("arms", duration=8.0, settle=1.0, out=out, quiet=True), out


@pytest.fixture(scope="session")
def short_squat_deployment(tmp_path_factory):
    """One MuJoCo + PIQP run of the squat (2 s of motion after a 1 s settle), shared by the
    closed-loop test and the MJX squat consistency test: (metrics, output directory)."""
    from safewbc_jax.app.runner import run_scenario

    out = tmp_path_factory.mktemp("short_squat_deployment")
    return run_scenario("squat", duration=2.0, settle=1.0, out=out, quiet=True), out


@pytest.fixture(scope="session")
def short_walk_deployment(tmp_path_factory):
    """One MuJoCo + PIQP run of a short walk (2.2 s of walking after a 1.2 s settle: six
    steps), shared by the walking test and the MJX walking consistency test:
    (metrics, output directory)."""
    from safewbc_jax.app.runner import run_scenario

    out = tmp_path_factory.mktemp("short_walk_deployment")
    return run_scenario("walk", duration=2.2, settle=1.2, out=out, quiet=True), out


@pytest.fixture(scope="session")
def stand(sim_mj, ctrl_mj):
    """(q, v) of the controller at the ``stand`` keyframe of the simulation model."""
    import mujoco

    from safewbc_jax.model import statemap

    d = mujoco.MjData(sim_mj)
    mujoco.mj_resetDataKeyframe(sim_mj, d, sim_mj.key("stand").id)
    mujoco.mj_forward(sim_mj, d)
    q, v = statemap.build_state_map(sim_mj, ctrl_mj).to_controller(d.qpos, d.qvel)
    return q.copy(), v.copy()
