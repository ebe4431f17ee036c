"""Every numeric option of the CLI is checked before anything compiles, and refused with
a message that names the option and its allowed range (issue: bad values that ran)."""

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from safewbc_jax.app import cli

SPEC = str(Path(__file__).resolve().parents[1] / "sweeps" / "kalpha_poles.toml")


def _run(argv, capsys):
    """(exit code, stderr) of ``safewbc ARGV`` in this process; argparse errors exit 2."""
    t0 = time.perf_counter()
    try:
        rc = cli.main(argv)
    except SystemExit as e:
        rc = e.code
    err = capsys.readouterr().err
    # refused before any controller or closed loop compiles (those take tens of seconds)
    assert time.perf_counter() - t0 < 20, argv
    return rc, err


RUN_REFUSED = [
    (["push", "--at", "-1"], "--at -1"),
    (["push", "--at", "7.9"], "within the 8 s of motion"),
    (["push", "--for", "0"], "--for 0"),
    (["push", "--force", "0,-2000,0"], "|F| <= 1000"),
    (["push", "--force", "1,2"], "three numbers"),
    (["push", "--force", "1,x,2"], "expected FX,FY,FZ"),
    (["push", "--force", "nan,0,0"], "finite"),
    (["walk", "--speed", "nan"], "expected a finite number"),
    (["walk", "--speed", "inf"], "expected a finite number"),
    (["walk", "--speed", "2"], "[-0.857, 1.143] m/s"),
    (["walk", "--speed", "-1"], "[-0.857, 1.143] m/s"),
    (["squat", "--speed", "0.3"], "--speed applies to the walking scenarios"),
    (["squat", "--at", "1"], "--at and --for time a push"),
    (["squat", "--duration", "0"], "(0, 600]"),
    (["squat", "--duration", "1e6"], "(0, 600]"),
    (["squat", "--duration", "-inf"], "expected a finite number"),
    (["squat", "--settle", "0.5"], "[1, 60] s"),
    (["squat", "--settle", "nan"], "expected a finite number"),
    (["squat", "--cpu", "-5"], "--cpu -5"),
]


@pytest.mark.parametrize("argv,msg", RUN_REFUSED, ids=lambda a: " ".join(a) if isinstance(a, list) else "")
def test_run_options_refused(argv, msg, capsys, tmp_path):
    out = tmp_path / "o"
    rc, err = _run(["run", *argv, "--out", str(out)] + ([] if "--cpu" in argv else ["--cpu", "-1"]),
                   capsys)
    assert rc == 2 and msg in err, err
    assert not out.exists()     # nothing written


@pytest.mark.parametrize("argv,msg", [
    (["sweep", "S", "--out", "o", "--batch", "0"], "expected an integer >= 1"),
    (["sweep", "S", "--out", "o", "--seed", "-1"], "expected an integer >= 0"),
    (["sweep", "S", "--out", "o", "--max-chunks", "0"], "expected an integer >= 1"),
    (["sweep", "S", "--out", "o", "--hosts", "0"], "expected an integer >= 1"),
    (["sweep", "S", "--out", "o", "--hosts", "2", "--host-index", "2"], "must be below --hosts 2"),
    (["sweep", "S", "--out", "o", "--batch", "1.5"], "is not an integer"),
    (["tune-poles", "S", "--out", "o.toml", "--batch", "-3"], "expected an integer >= 1"),
    (["tune-poles", "S", "--out", "o.toml", "--seed", "x"], "is not an integer"),
    (["sweep", SPEC, "--out", "o", "--engine", "gpu"], "invalid choice: 'gpu'"),
    (["sweep", SPEC, "--out", "o", "--engine", "mujoco", "--workers", "999"],
     "--workers 999: this process may run on"),
    (["sweep", SPEC, "--out", "o", "--workers", "0"], "expected an integer >= 1"),
    (["sweep", SPEC, "--out", "o", "--engine", "mjx", "--workers", "1"],
     "only the mujoco engine has workers"),
    (["tune-poles", SPEC, "--out", "o.toml", "--workers", "999"], "this process may run on"),
    (["tune", SPEC, "--out", "o.toml", "--method", "random"], "invalid choice: 'random'"),
    (["tune", SPEC, "--out", "o.toml", "--budget", "0"], "expected an integer >= 1"),
    (["tune", SPEC, "--out", "o.toml", "--validate", "-1"], "expected an integer >= 0"),
    (["tune", SPEC, "--out", "o.toml", "--budget", "5"],
     "a budget of 5 rollouts is less than one generation"),
    (["tune", SPEC, "--out", "o.params", "--budget", "500"], "expected a .toml file"),
    (["tune", SPEC, "--out", "o.toml", "--engine", "mjx", "--workers", "1"],
     "only the mujoco engine has workers"),
])
def test_sweep_and_tune_options_refused(argv, msg, capsys):
    rc, err = _run(argv, capsys)
    assert rc == 2 and msg in err, err


def test_negative_push_components_as_typed(capsys, tmp_path):
    """'--force -20,-25,0' is a value, not an option (argparse alone refuses it)."""
    argv = ["run", "push", "--force", "-20,-25,0", "--at", "1.0"]
    args = cli.build_parser().parse_args(cli._join_dash_values(argv))
    assert args.force == "-20,-25,0" and args.at == 1.0
    assert cli.build_parser().parse_args(cli._join_dash_values(
        ["run", "push", "--force", "-.5,0,0"])).force == "-.5,0,0"
    # the whole command gets as far as the run options' own checks
    rc, err = _run(argv[:4] + ["--at", "-1", "--cpu", "-1", "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and "--at -1" in err and "expected one argument" not in err, err
    run_help = cli.build_parser()._subparsers._group_actions[0].choices["run"].format_help()
    assert "--force -20,-25,0" in " ".join(run_help.split())


def test_check_run_options_defaults():
    """The defaults the run fills in, for a walking and a double-support scenario."""
    from safewbc_jax import scenarios
    from safewbc_jax.app import runner

    o = runner.check_run_options("push", scenarios.get_scenario("push"))
    assert o.push == scenarios.PAPER_PUSH and o.push_at == runner.PUSH_AT
    assert o.push_for == runner.PUSH_FOR and o.speed == 0.2 and o.duration == 8.0
    o = runner.check_run_options("squat", scenarios.get_scenario("squat"), duration=3)
    assert o.push is None and o.duration == 3.0
    o = runner.check_run_options("walk", scenarios.get_scenario("walk"), speed=1.1)
    assert o.speed == 1.1


def test_compile_cache_keeps_the_small_programs_too(tmp_path):
    """The command's compilation cache (``safewbc_jax.use_compile_cache``, which the CLI and
    the pool's workers call) keeps a program that compiles in milliseconds, so that the next
    process loads it: a controller's start compiles a few hundred of them."""
    code = ("import sys, jax.numpy as jnp, safewbc_jax\n"
            "safewbc_jax.use_compile_cache(sys.argv[1])\n"
            "print(float(jnp.sin(jnp.arange(3.0)).sum()))\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_PERSISTENT_CACHE")}
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path)], env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert float(out.stdout) == pytest.approx(np.sin(1.0) + np.sin(2.0), abs=1e-6)
    assert [p.name for p in tmp_path.glob("jit_sin-*")], sorted(p.name for p in tmp_path.iterdir())
