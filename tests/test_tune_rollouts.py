"""``safewbc tune`` end to end with real rollouts on both engines: a run killed after its
first generation resumes to the result of an uninterrupted run, and the mujoco engine
tunes the same spec.

The spec is test_sweeps_rollouts.py's tiny configuration (arms, 0.05 s of motion after a
1 s settle), so the compiled programs are shared through the persistent compilation
cache (the mjx engine's, at batch 2, is test_mjx_closed_loop.py's arms program): two
generations of two candidates x two perturbed draws, then two held-out rollouts. The kill
and the resume run on the mjx engine, whose rollouts cost a fraction of the mujoco
engine's; that a mujoco-engine table does not depend on the worker count nor on a kill is
test_sweeps_rollouts.py's (the tuner reads only those tables). The params file's
``--safe-set`` arguments are test_tune.py's.
"""

import importlib.util
import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from test_sweeps_rollouts import SPEC, sweep_env

TUNE = SPEC.replace('[grid]\n"poles.left_fist.p1" = [5.0, 20.0]\n', "") + """
[tune]
population = 2
budget = 8
validate = 2
objective = ["torque_ratio_max"]   # tracking RMS counts from 0.5 s of motion on

[tune.params]
"poles.left_fist.p1" = { bounds = [5.0, 20.0] }
"gain_scale.arms" = { bounds = [0.5, 2.0] }
"""


def tune_cmd(spec, out, *extra):
    return [sys.executable, "-m", "safewbc_jax.app.cli", "tune", str(spec), "--out", str(out),
            "--batch", "2", *extra]


@pytest.fixture(scope="module")
def tunes(tmp_path_factory):
    """(A) the mjx engine, SIGKILLed once generation 1 is written, then rerun; (B) the
    mujoco engine, 2 workers, in one go; (C) the mjx engine, in one go."""
    tmp = tmp_path_factory.mktemp("tune")
    spec = tmp / "tiny_tune.toml"
    spec.write_text(TUNE)
    env = sweep_env(1)
    a = tmp / "a" / "tuned.toml"
    log = open(tmp / "a1.log", "w")
    proc = subprocess.Popen(tune_cmd(spec, a, "--engine", "mjx"), env=env,
                            stdout=log, stderr=subprocess.STDOUT, cwd=tmp)
    state = tmp / "a" / "tuned_tune" / "tuning.json"
    t0 = time.time()
    while not (state.exists() and json.loads(state.read_text())["generations"]):
        assert proc.poll() is None, (tmp / "a1.log").read_text()[-3000:]
        assert time.time() - t0 < 1500, "the first generation took more than 25 minutes"
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    log.close()
    killed = json.loads(state.read_text())
    resume = subprocess.run(tune_cmd(spec, a, "--engine", "mjx"), env=env,
                            capture_output=True, text=True, cwd=tmp, timeout=900)
    b = tmp / "b" / "tuned.toml"
    mujoco = subprocess.run(tune_cmd(spec, b, "--engine", "mujoco", "--workers", "2"), env=env,
                            capture_output=True, text=True, cwd=tmp, timeout=900)
    c = tmp / "c" / "tuned.toml"
    mjx = subprocess.run(tune_cmd(spec, c, "--engine", "mjx"), env=env, capture_output=True,
                         text=True, cwd=tmp, timeout=900)
    d = tmp / "d" / "tuned.toml"
    ray = (subprocess.run(tune_cmd(spec, d, "--engine", "mjx", "--ray"), env=env,
                          capture_output=True, text=True, cwd=tmp, timeout=900)
           if importlib.util.find_spec("ray") else None)
    rd = lambda p: json.loads((p.parent / "tuned_tune" / "tuning.json").read_text())  # noqa: E731
    return {"killed": killed, "resume": resume, "mujoco": mujoco, "mjx": mjx, "tmp": tmp,
            "a": rd(a) if resume.returncode == 0 else None,
            "b": rd(b) if mujoco.returncode == 0 else None,
            "c": rd(c) if mjx.returncode == 0 else None, "paths": (a, b, c), "ray": ray,
            "d": rd(d) if ray is not None and ray.returncode == 0 else None}


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_killed_tuning_resumes_to_the_uninterrupted_result(tunes):
    t = tunes
    assert [g["generation"] for g in t["killed"]["generations"]] == [1]
    assert t["resume"].returncode == 0, t["resume"].stderr[-3000:]
    # the rerun replayed generation 1 from its table (every chunk already done)
    assert "2/2 chunks already done, 0 to run" in t["resume"].stderr
    assert t["mjx"].returncode == 0, t["mjx"].stderr[-3000:]
    a, c = t["a"], t["c"]
    # one rollout's result depends on its inputs only, so the same machine gives the same
    # floats, killed or not: the searches saw the same values and chose the same
    assert a["generations"] == c["generations"]
    assert a["best"] == c["best"] and a["validation"] == c["validation"]
    assert a["used"] == 8 and len(a["generations"]) == 2
    assert a["stop"].startswith("budget")
    # real outcomes: 1.05 s standing, nobody falls, the fist stays inside its safe set
    for g in a["generations"]:
        for cand in g["candidates"]:
            assert cand["n"] == 2 and cand["unsafe"] == 0 and cand["falls"] == 0
            assert 0.035 < cand["hmin"]["left_fist"] < 0.0505
            assert 5.0 <= cand["params"]["poles.left_fist.p1"] <= 20.0
            assert 0.5 <= cand["params"]["gain_scale.arms"] <= 2.0
            assert np.isfinite(cand["objective"]) and cand["objective"] > 0
    v = a["validation"]
    assert v["n"] == 2 and v["unsafe"] == 0 and v["seed"] == 8      # the spec's seed 7, + 1
    # the params file carries the result and its validation, and the run command
    text = t["paths"][0].read_text()
    assert "# validation on 2 held-out rollouts (seed 8): 0 unsafe" in text
    assert "--params" in text
    assert "validation on 2 held-out rollouts" in t["resume"].stdout


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_mujoco_engine_tunes_the_same_spec(tunes):
    """The mujoco engine (a pool of two deployment loops, kept across the generations)
    runs the same search: its first generation asks the same candidates (the search's
    first draw depends on the seed only), with outcomes within the engines' agreement
    (test_sweeps_rollouts: barrier minima within 0.042 mm)."""
    t = tunes
    assert t["mujoco"].returncode == 0, t["mujoco"].stderr[-3000:]
    assert "on 2 MuJoCo workers" in t["mujoco"].stderr
    b, c = t["b"], t["c"]
    g1b, g1c = b["generations"][0]["candidates"], c["generations"][0]["candidates"]
    assert len(g1b) == len(g1c) == 2
    for x, y in zip(g1c, g1b):
        assert x["params"] == y["params"]
        assert x["n"] == y["n"] == 2 and x["unsafe"] == y["unsafe"] == 0
        assert abs(x["hmin"]["left_fist"] - y["hmin"]["left_fist"]) < 1e-4
        assert x["objective"] == pytest.approx(y["objective"], rel=1e-2)
    assert b["used"] == 8 and len(b["generations"]) == 2
    assert b["validation"]["n"] == 2 and b["validation"]["unsafe"] == 0
    assert b["validation"]["seed"] == 8
    # the pool, kept across the generations, ran --batch 2 lanes side by side in each
    work = t["paths"][1].parent / "tuned_tune"
    widths = {json.loads(m.read_text())["lockstep"] for m in work.glob("*/sweep.json")}
    assert widths == {2}, widths


@pytest.mark.slow
@pytest.mark.timeout(3600)
def test_tuning_on_a_local_ray_cluster_is_the_one_process_tuning(tunes):
    """``tune --ray`` (a Ray started on this machine, every generation's chunks its tasks)
    searches, decides and validates exactly as the one-process run of the same engine."""
    if tunes["ray"] is None:
        pytest.skip("Ray is not installed (pip install '.[ray]')")
    assert tunes["ray"].returncode == 0, tunes["ray"].stderr[-3000:]
    assert "on a Ray cluster (1 node, 2 CPUs" in tunes["ray"].stderr
    d, c = tunes["d"], tunes["c"]
    assert d["generations"] == c["generations"] and d["best"] == c["best"]
    assert d["validation"] == c["validation"] and d["used"] == c["used"] == 8
