"""The progress display (safewbc_jax/ui/progress.py) of ``safewbc run``, ``sweep`` and
``tune-poles``: phases, rate and ETA, a bounded number of lines off a terminal, nothing
with quiet; and run_sweep's bar with a fake executor. No JAX compile, no closed loop."""

import io
import re

import numpy as np
import pytest

from safewbc_jax.ui.progress import Progress


class FakeClock:
    def __init__(self):
        self.t = 1000.0

    def __call__(self):
        return self.t


class FakeTTY(io.StringIO):
    def isatty(self):
        return True


def fake_run(p: Progress, clock: FakeClock, n=100_000, settle_steps=50_000, compile_s=60.0,
             dt=1e-3):
    """Drive p as mujoco_loop.run drives its progress callback: (0, n, "compiling") before
    the first step, then (k + 1, n, phase) after every step; the first step compiles."""
    p.update_to(0, "compiling", n)
    for k in range(n):
        clock.t += compile_s if k == 0 else dt
        p.update_to(k + 1, "standing" if k < settle_steps else "motion", n)


def test_log_mode_shows_the_phases_in_a_bounded_number_of_lines():
    clock, out = FakeClock(), io.StringIO()
    p = Progress("[safewbc] squat", unit="steps", phase="compiling", stream=out, clock=clock)
    fake_run(p, clock)                      # 60 s compile + 100 s of steps at 1 kHz
    p.close("done")
    text = out.getvalue()
    lines = text.splitlines()
    assert "\r" not in text                 # no in-place redraws in a log
    assert len(lines) == p.lines
    # start, 2 phase changes, close, and one per 30 s of the 160 s at most
    assert 4 <= len(lines) <= 4 + 160 // 30
    phases = [re.search(r"\((\w[\w ]*)\)$", ln).group(1) for ln in lines]
    assert phases[0] == "compiling" and phases[-1] == "done"
    firsts = [phases.index(ph) for ph in ("compiling", "standing", "motion", "done")]
    assert firsts == sorted(firsts)
    assert lines[0].startswith("[safewbc] squat 0/100000 steps  0%")
    assert lines[-1].startswith("[safewbc] squat 100000/100000 steps  100%")
    # the rate leaves the minute of compilation out: 1000 steps/s, not 100000 / 160 s
    assert "1000 steps/s" in lines[-1]
    mid = next(ln for ln in lines if "(motion)" in ln)
    n_mid = int(re.search(r" (\d+)/100000 steps", mid).group(1))
    eta = re.search(r"ETA (\d\d):(\d\d)", mid)
    assert abs(int(eta.group(1)) * 60 + int(eta.group(2)) - (100_000 - n_mid) / 1000) <= 1


def test_log_mode_rate_unknown_right_after_compiling():
    clock, out = FakeClock(), io.StringIO()
    p = Progress("[safewbc] arms", unit="steps", phase="compiling", stream=out, clock=clock)
    p.update_to(0, "compiling", 2000)
    clock.t += 60.0
    p.update_to(1, "standing")              # the compiled first step: no rate from it
    line = out.getvalue().splitlines()[-1]
    assert "? steps/s" in line and "ETA ?" in line and "elapsed 01:00" in line
    p.close()


def test_tty_mode_is_a_live_tqdm_bar_with_rate_eta_and_phase():
    clock, out = FakeClock(), FakeTTY()
    p = Progress("[safewbc] squat", unit="steps", phase="compiling", stream=out, clock=clock)
    fake_run(p, clock, n=3000, settle_steps=1000)
    p.write("[safewbc] a message")
    p.close("done")
    text = out.getvalue()
    frames = [f for f in text.replace("\n", "\r").split("\r") if f.strip()]
    assert len(frames) > 10                 # redrawn in place (every 0.1 s of the clock)
    assert all(ph in text for ph in (", compiling]", ", standing]", ", motion]", ", done]"))
    assert "[safewbc] a message\n" in text
    assert re.search(r"\[safewbc\] squat: 100%\|#+\| 3000/3000 \[01:02<00:00, 1000 steps/s, "
                     r"done\]", frames[-1])
    bar = next(f for f in frames if ", motion]" in f)
    assert re.search(r"\d+/3000 \[\d\d:\d\d<\d\d:\d\d, 1000 steps/s", bar)   # ETA and rate


def test_quiet_writes_nothing():
    out = FakeTTY()
    clock = FakeClock()
    for stream in (out, io.StringIO()):
        p = Progress("[safewbc] squat", unit="steps", phase="compiling", quiet=True,
                     stream=stream, clock=clock)
        fake_run(p, clock, n=2000, settle_steps=1000)
        p.write("message")
        p.close("done")
        assert stream.getvalue() == ""


def test_update_is_cheap():
    """The loop calls the callback once per control step (outside the timed QP step)."""
    import time

    for stream in (FakeTTY(), io.StringIO()):
        p = Progress("[x]", unit="steps", phase="compiling", stream=stream)
        n = 50_000
        p.update_to(0, "compiling", n)
        t0 = time.perf_counter()
        for k in range(n):
            p.update_to(k + 1, "standing" if k < n // 2 else "motion", n)
        per_call = (time.perf_counter() - t0) / n
        p.close()
        assert per_call < 20e-6, per_call    # measured about 1 us


# ---- run_sweep ---------------------------------------------------------------------------

SPEC = """
[sweep]
scenario = "arms"
duration = 0.5
repeats = 3
batch = 4
[grid]
"poles.left_fist.p1" = [2.0, 8.0]
"""


@pytest.fixture
def spec(tmp_path):
    from safewbc_jax.sweeps.spec import load_spec

    p = tmp_path / "s.toml"
    p.write_text(SPEC)
    return load_spec(p)


class FakeExecutor:
    def __init__(self, clock=None, chunk_s=(90.0, 2.0)):
        self.calls = 0
        self.clock, self.chunk_s = clock, chunk_s

    def __call__(self, spec, params, push, perturb_v):
        b = perturb_v.shape[0]
        if self.clock is not None:
            self.clock.t += self.chunk_s[min(self.calls, len(self.chunk_s) - 1)]
        self.calls += 1
        return {"fell": np.zeros(b, bool), "h_min.left_fist": np.full(b, 0.01)}


def test_a_callers_mujoco_executor_runs_the_tables_lanes(spec, tmp_path):
    """A mujoco executor made by the caller without a lanes' step (``lanes`` None, as
    ``PoolExecutor``'s default) runs the folder's: a new folder gets this machine's
    (``pool.lanes_engine``), a table begun with XLA lanes stays on them."""
    import dataclasses

    from safewbc_jax.sweeps import pool, table
    from safewbc_jax.sweeps.run import run_sweep

    ex = FakeExecutor()
    ex.lanes = None
    run_sweep(spec, tmp_path / "new", executor=ex, check_poles=False, engine="mujoco",
              quiet=True)
    assert ex.lanes == pool.lanes_engine() == table.read_manifest(tmp_path / "new").lanes
    old = tmp_path / "old"
    man = table.read_manifest(tmp_path / "new")
    table.open_manifest(old, dataclasses.replace(man, lanes="xla"))
    ex = FakeExecutor()
    ex.lanes = None
    run_sweep(spec, old, executor=ex, check_poles=False, engine="mujoco", quiet=True)
    assert ex.lanes == "xla" and ex.calls == 2


def test_run_sweep_bar_reports_the_rollouts(spec, tmp_path, monkeypatch):
    from safewbc_jax.ui import progress as progress_mod
    from safewbc_jax.sweeps.run import run_sweep

    clock = FakeClock()
    real = progress_mod.Progress
    monkeypatch.setattr("safewbc_jax.sweeps.run.Progress",
                        lambda *a, **kw: real(*a, clock=clock, **kw))
    out = io.StringIO()
    ex = FakeExecutor(clock)
    r = run_sweep(spec, tmp_path / "sw", executor=ex, check_poles=False, stream=out)
    assert ex.calls == 2 and r.chunks_run == 2 and r.n_rollouts == 6
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    bar = [ln for ln in lines if ln.startswith("[sweep] ") and " rollouts  " in ln]
    assert bar[0].startswith("[sweep] 0/6 rollouts  0%") and bar[0].endswith("(compiling)")
    assert bar[1].startswith("[sweep] 4/6 rollouts  67%") and bar[1].endswith("(rolling out)")
    assert bar[-1].startswith("[sweep] 6/6 rollouts  100%")
    # the rate of the chunks after the compiling one: 2 rollouts in 2 s
    assert "1.00 rollouts/s" in bar[-1] and "ETA 00:00" in bar[-1]
    assert len(lines) <= 6                   # header + a few bar lines, not one per update
    assert any("[sweep] arms: 6 rollouts" in ln for ln in lines)   # the header message


def test_run_sweep_resumed_bar_starts_at_the_done_rollouts(spec, tmp_path):
    from safewbc_jax.sweeps.run import run_sweep

    d = tmp_path / "sw"
    run_sweep(spec, d, executor=FakeExecutor(), check_poles=False, max_chunks=1,
              quiet=True)
    out = io.StringIO()
    run_sweep(spec, d, executor=FakeExecutor(), check_poles=False, stream=out,
              desc="[tune] round 2/3:")
    text = out.getvalue()
    assert "1/2 chunks already done, 1 to run" in text
    assert "[tune] round 2/3: 4/6 rollouts  67%" in text
    assert "[tune] round 2/3: 6/6 rollouts  100%" in text


def test_run_sweep_quiet_and_progress_callable(spec, tmp_path):
    from safewbc_jax.sweeps.run import run_sweep

    out = io.StringIO()
    run_sweep(spec, tmp_path / "q", executor=FakeExecutor(), check_poles=False, stream=out,
              quiet=True)
    assert out.getvalue() == ""
    # a progress callable (the notebook's progress=print) gets the messages and one line
    # per chunk, and no bar is drawn
    msgs, out = [], io.StringIO()
    run_sweep(spec, tmp_path / "p", executor=FakeExecutor(), check_poles=False, stream=out,
              progress=msgs.append)
    assert out.getvalue() == ""
    per_chunk = [m for m in msgs if "rollouts/s" in m]
    assert len(per_chunk) == 2
    assert per_chunk[0].startswith("[sweep] 4/6 rollouts") and "ETA" in per_chunk[0]
    assert per_chunk[1].startswith("[sweep] 6/6 rollouts")


@pytest.mark.parametrize("argv", [["run", "squat"], ["sweep", "s.toml", "--out", "d"],
                                  ["tune-poles", "s.toml", "--out", "p.toml"]])
def test_cli_quiet_flag(argv):
    from safewbc_jax.app.cli import build_parser

    ap = build_parser()
    assert ap.parse_args(argv).quiet is False
    assert ap.parse_args(argv + ["--quiet"]).quiet is True


@pytest.mark.skipif(not hasattr(__import__("os"), "openpty"), reason="needs a pty (POSIX)")
def test_real_terminal_of_unknown_size_gets_a_bar(tmp_path):
    """On a pty with no window size (as some CI runners and `docker exec -t` give) tqdm
    reads -1 columns and rows and would draw nothing; the bar is drawn 10 columns wide."""
    import os
    import subprocess
    import sys

    script = tmp_path / "demo.py"
    script.write_text(
        "from safewbc_jax.ui.progress import Progress\n"
        "p = Progress('[safewbc] squat', unit='steps', phase='compiling')\n"
        "p.update_to(0, 'compiling', 300)\n"
        "for k in range(300):\n"
        "    p.update_to(k + 1, 'standing' if k < 100 else 'motion', 300)\n"
        "p.close('done')\n")
    main, child = os.openpty()   # a new pty: no window size set
    proc = subprocess.Popen([sys.executable, str(script)], stdin=child, stdout=child,
                            stderr=child, close_fds=True)
    os.close(child)
    out = b""
    while True:
        try:
            chunk = os.read(main, 4096)
        except OSError:          # EIO once the child has exited and closed the pty
            break
        if not chunk:
            break
        out += chunk
    os.close(main)
    text = out.decode(errors="replace")
    assert proc.wait(timeout=120) == 0, text[-2000:]
    assert "\r[safewbc] squat:   0%|" in text and ", compiling]" in text
    assert re.search(r"\[safewbc\] squat: 100%\|\S{10}\| 300/300 \[.*steps/s, done\]", text)


def test_a_run_that_fails_before_its_first_step_shows_no_bar():
    """run_scenario makes the bar before the loop knows its length; an error before the
    first step (a pole check, say) must not leave an empty bar above the error."""
    for stream in (io.StringIO(), FakeTTY()):
        p = Progress("[safewbc] arms", unit="steps", phase="compiling", stream=stream)
        p.close()
        assert "steps" not in stream.getvalue()
