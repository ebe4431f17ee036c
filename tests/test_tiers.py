"""The fast tier's guard (conftest): an unmarked test slower than the limit fails and names
itself; a test marked slow, or a fast one, passes. Run in a child pytest with the
project's conftest and a limit of 0.5 s."""

from pathlib import Path

CONFTEST = Path(__file__).with_name("conftest.py")


def test_unmarked_slow_test_fails_and_names_itself(pytester, monkeypatch):
    monkeypatch.setenv("SAFEWBC_FAST_LIMIT_S", "0.5")
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
""")
    res = pytester.runpytest_subprocess("-p", "no:cacheprovider")
    res.assert_outcomes(passed=2, failed=2)
    out = res.stdout.str()
    for name in ("test_sleeps_unmarked", "test_setup_and_call_add_up"):
        assert f"test_guarded.py::{name} took" in out, out
    assert "without the 'slow' marker" in out
