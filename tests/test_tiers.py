"""The fast tier's guard (conftest): an unmarked test slower than the limit fails and names
itself; a test marked slow, or a fast one, passes. Run in a child pytest with the
project's conftest and a limit of 0.5 s."""

import re
from pathlib import Path

CONFTEST = Path(__file__).with_name("conftest.py")


def test_unmarked_slow_test_fails_and_names_itself(pytester, monkeypatch):
    monkeypatch.setenv("SAFEWBC_FAST_LIMIT_S", "0.5")
    monkeypatch.delenv("PYTEST_XDIST_WORKER_COUNT", raising=False)   # one process: wall time
    pytester.makeconftest(CONFTEST.read_text())
    pytester.makeini("[pytest]\nmarkers =\n    slow: slow\n")
    pytester.makepyfile(test_guarded="""
import time
import pytest

@pytest.fixture(scope="module")
def costly():
    time.sleep(0.4)

def test_quick():
    pass

def test_sleeps_unmarked():
    time.sleep(0.8)

def test_setup_and_call_add_up(costly):
    time.sleep(0.3)

@pytest.mark.slow
def test_sleeps_marked():
    time.sleep(0.8)

@pytest.fixture(scope="module")
def shared():
    time.sleep(0.9)

# three unmarked users of a 0.9 s module fixture: charged 0.3 s each, whichever sets it up
def test_shares_a_fixture_1(shared):
    pass

def test_shares_a_fixture_2(shared):
    pass

def test_shares_a_fixture_3(shared):
    pass
""")
    res = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    res.assert_outcomes(passed=5, failed=2)
    out = res.stdout.str()
    for name in ("test_sleeps_unmarked", "test_setup_and_call_add_up"):
        assert f"test_guarded.py::{name} took" in out, out
    assert "without the 'slow' marker" in out


def test_with_shared_cores_the_guard_counts_cpu_time(pytester, monkeypatch):
    """As an xdist worker beside others (PYTEST_XDIST_WORKER_COUNT > 1), a test is held to
    the CPU time it used where that is less than its wall time: waiting (here sleeping,
    there for the other workers' CPU) does not count, computing does."""
    monkeypatch.setenv("SAFEWBC_FAST_LIMIT_S", "0.5")
    monkeypatch.setenv("PYTEST_XDIST_WORKER_COUNT", "2")
    pytester.makeconftest(CONFTEST.read_text())
    pytester.makeini("[pytest]\nmarkers =\n    slow: slow\n")
    pytester.makepyfile(test_shared="""
import time

def test_waits():
    time.sleep(0.8)

def _busy(s):
    t0 = time.process_time()
    while time.process_time() - t0 < s:
        pass

def test_computes():
    _busy(0.8)
    time.sleep(0.3)     # its wall time above its CPU time, on a busy machine or an idle one

import pytest

@pytest.fixture(scope="module")
def compiled():
    _busy(0.9)

# 0.9 CPU s set up once for three unmarked tests: 0.3 s each
def test_shares_1(compiled):
    pass

def test_shares_2(compiled):
    pass

def test_shares_3(compiled):
    pass
""")
    res = pytester.runpytest_subprocess("-p", "no:cacheprovider", "-p", "no:xdist")
    out = res.stdout.str()
    # the output names which test the guard held, and with how much time: its CPU time
    # (0.8 s and the hooks'), not its wall time (1.1 s or more). Without the sleep the two
    # were equal to the clock's tick on an idle machine, and either was reported
    assert res.parseoutcomes().get("passed") == 4 and res.parseoutcomes().get("failed") == 1, out
    held = re.search(r"test_shared.py::test_computes took ([0-9.]+) s \(CPU time", out)
    assert held and 0.75 <= float(held.group(1)) <= 1.0, out


def test_the_fast_tier_compiles_with_llvm_optimisation_off(pytester, monkeypatch):
    """``-m "not slow"`` (and only that selection) adds FAST_TIER_XLA_FLAGS to XLA_FLAGS
    before JAX starts, and says so in the header; a level the user names is kept."""
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    pytester.makeconftest(CONFTEST.read_text())
    pytester.makeini("[pytest]\nmarkers =\n    slow: slow\n")
    pytester.makepyfile(test_flags="""
import os
import jax.numpy as jnp

def test_flags():
    jnp.zeros(1)                       # the backend starts with the flags of this moment
    print("FLAGS=" + os.environ.get("XLA_FLAGS", ""))
""")

    def flags(*args):
        res = pytester.runpytest_subprocess("-p", "no:cacheprovider", "-s", *args)
        res.assert_outcomes(passed=1)
        line = [x for x in res.stdout.lines if "FLAGS=" in x][0]
        return line.split("FLAGS=", 1)[1].split(), res.stdout.str()

    fast, out = flags("-m", "not slow")
    assert "--xla_backend_optimization_level=0" in fast, fast
    assert "fast tier: XLA_FLAGS=" in out
    full, out = flags()
    assert not any("optimization_level" in f for f in full) and "fast tier" not in out
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=2")
    kept, _ = flags("-m", "not   slow")
    assert [f for f in kept if "optimization_level" in f] == ["--xla_backend_optimization_level=2"]
