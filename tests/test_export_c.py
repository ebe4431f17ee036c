"""The deployed step as C (issue 52): ``safewbc export-c`` writes a folder that ``make``
builds with warnings as errors and runs with no Python, printing the motor command Python
computes for the same step; a user's scenario and safe set go through the emitter as the
paper's do; an unsupported primitive in a user's safe set is refused naming it and where
it is; and the closed loop with the C engine gives XLA's metrics.

Tolerances: the C and XLA evaluate the same float64 operations and differ in the order of
sums and in libm's last bit (``tests/test_deploy_same_qp.py`` measures 6e-14 relative on
one step); 1e-12 relative holds one step. The example's motor command comes out of the
interior-point solver's iterations, which carry those differences: 1e-9 N m relative to
the largest torque. A closed loop of 2,000 steps in MuJoCo amplifies a 1e-13 difference
through the robot's dynamics; its metrics agree to 1e-6 relative, or 1e-9 absolute for
those at rounding level (the QP's equality residual, ~1e-11); the lockstep tests hold the
vmapped step to the same bound.
"""

import re
import subprocess
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import safewbc_jax
from safewbc_jax.control.safesets import SafeSet
from safewbc_jax.deploy.codegen import emit

safewbc_jax.enable_x64()
ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module", autouse=True)
def c_cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("SAFEWBC_C_CACHE", str(tmp_path_factory.mktemp("c_cache")))
    yield
    mp.undo()


def test_export_c_builds_with_make_and_prints_pythons_command(tmp_path, capsys):
    from safewbc_jax.app.cli import main

    out = tmp_path / "squat_c"
    assert main(["export-c", "squat", "--out", str(out)]) == 0
    assert f"make -C {out}" in capsys.readouterr().out
    src = (out / "safewbc_step.c").read_text()
    assert sorted(set(re.findall(r"#include [<\"](.+?)[>\"]", src))) == \
        ["math.h", "safewbc_step.h", "stdint.h", "string.h"]
    assert "malloc" not in src and "free(" not in src
    # a robot computer: no Python on the PATH, only the compiler and make
    env = {"PATH": "/usr/bin:/bin", "HOME": str(tmp_path)}
    r = subprocess.run(["make", "-C", str(out), "CFLAGS=-O3 -std=c99 -Wall -Wextra -Werror"],
                       capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stdout + r.stderr
    printed = np.array([float(x) for x in re.findall(r"motor\[\d+\] = (\S+)", r.stdout)])
    from safewbc_jax.deploy.codegen.export import export_c

    again = export_c("squat", tmp_path / "again")
    want = again.motor                                        # Python's (XLA) motor command
    assert printed.shape == want.shape == (20,)
    np.testing.assert_allclose(printed, want, rtol=0, atol=1e-9 * np.abs(want).max())
    assert np.abs(want).max() > 1.0                           # a real command, not zeros
    # the reduced QP read from prepare's qp vector where the header says it is: its P's
    # diagonal (C's against XLA's: the same sums up to their order, 1e-12 relative)
    header = (out / "safewbc_step.h").read_text()
    assert re.search(r"#define SWBC_QP_RED_P \d+", header), header
    p_diag = np.array([float(x) for x in re.findall(r"reduced P\[\d+\]\[\d+\] = (\S+)",
                                                    r.stdout)])
    assert p_diag.shape == (20,) and (again.reduced_p_diagonal > 0).all()
    np.testing.assert_allclose(p_diag, again.reduced_p_diagonal, rtol=1e-12)


def _prepare_agrees(ctl_c, ctl_x, stand, n=10):
    rng = np.random.default_rng(3)
    q0, v0 = stand
    cs, xs = ctl_c.compiled, ctl_x.compiled
    fixed = cs.pack_fixed(ctl_c.params, ctl_c.start_data, ctl_c.run_values)
    state, _ = cs.initial(q0, v0)
    for k in range(n):
        q = q0.copy()
        q[7:] += rng.uniform(-0.05, 0.05, q.size - 7)
        meas = cs.flat_measurement(safewbc_jax.Measurement(q, v0 + rng.uniform(-0.2, 0.2,
                                                                                  v0.size),
                                                             1.0 + 1e-3 * k, np.zeros(2)))
        for a, b in zip(cs.prepare(fixed, state, meas), xs.prepare(fixed, state, meas)):
            b = np.asarray(b)
            np.testing.assert_array_equal(np.isfinite(a), np.isfinite(b))
            fin = np.isfinite(b)
            np.testing.assert_allclose(a[fin], b[fin], rtol=0,
                                       atol=1e-12 * max(1.0, np.abs(b[fin]).max()))


def test_a_users_scenario_and_safe_set_in_c(stand):
    from safewbc_jax.deploy.controller import Controller

    sc = safewbc_jax.get_scenario(f"{ROOT / 'examples' / 'side_sway.py'}:SIDE_SWAY", True,
                                  (f"{ROOT / 'examples' / 'bow_torso_lean.py'}:TORSO_LEAN",))
    assert [b.name for b in sc.barriers] == ["com_side", "torso_lean"]
    ctl_c, ctl_x = Controller(sc, engine="c"), Controller(sc, engine="xla")
    for ctl in (ctl_c, ctl_x):
        ctl.start(*stand, warm_up=False)
    assert (ctl_c.engine, ctl_x.engine) == ("c", "xla")
    _prepare_agrees(ctl_c, ctl_x, stand)
    _no_fused_multiply_add(ctl_c.compiled.c_source)


def _no_fused_multiply_add(source: str) -> None:
    """The library the C engine built from ``source`` (``build.build``: the CPU's x86-64
    level) has no fused multiply-add instruction. Where FMA is enabled, gcc 12 forms a few
    in vectorised loops of the generated step despite ``-ffp-contract=off``, and they
    change last bits against the baseline build (``build.py``): the level is built with
    ``-mno-fma``. Checked with objdump where a level is used (``build.isa_flags``: x86-64
    only); the baseline build has no FMA instructions to form."""
    import shutil

    from safewbc_jax.deploy.codegen import build

    objdump = shutil.which("objdump")
    if objdump is None or not build.isa_flags():
        return
    path, built = build.build(source)
    assert not built                  # the controller's start built this very library
    text = subprocess.run([objdump, "-d", str(path)], capture_output=True, text=True,
                          check=True).stdout
    fused = re.findall(r"\tv?fn?m(?:add|sub)\w*", text)
    assert not fused, f"{len(fused)} fused multiply-adds in {path.name}: {fused[:4]}"


def test_an_unsupported_primitive_in_a_users_safe_set_is_refused(stand):
    from safewbc_jax.deploy.controller import Controller

    def spectral(model, q, threshold, domain=None):       # an FFT: no C rule
        return threshold - jnp.fft.fft(q[:8]).real[1]

    sc = safewbc_jax.get_scenario("squat", True, (SafeSet("spectral", spectral,
                                                          relative_degree=2,
                                                          poles=(10.0, 10.0),
                                                          threshold=5.0),))
    with pytest.raises(emit.UnsupportedPrimitive, match=r"'fft'.*test_export_c\.py"):
        Controller(sc, engine="c").start(*stand, warm_up=False)


def test_closed_loop_with_the_c_engine_gives_xlas_metrics():
    from safewbc_jax.sim.mujoco_loop import RunConfig, run

    got = {}
    for engine in ("c", "xla"):
        cfg = RunConfig("squat", duration=1.0, settle=1.0, engine=engine)
        _, info = run(cfg)
        assert info["engine"] == engine
        got[engine] = info["metrics"]
    assert got["c"].keys() == got["xla"].keys()
    for k, a in got["c"].items():
        a, b = np.asarray(a, float), np.asarray(got["xla"][k], float)
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9, err_msg=k)
    assert int(got["c"]["qp_solved"]) == 2000 and not bool(got["c"]["fell"])

