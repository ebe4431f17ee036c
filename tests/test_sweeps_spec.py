"""Sweep specs (validation before anything compiles), Wilson intervals, the chunked
Parquet table and the report figures: everything of the sweep layer that needs no
rollout. The rollouts themselves are in test_sweeps_rollouts.py."""

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from safewbc_jax.sweeps import inputs
from safewbc_jax.sweeps import table as table_mod
from safewbc_jax.sweeps.spec import SpecError, load_spec
from safewbc_jax.sweeps.stats import wilson_interval

ROOT = Path(__file__).resolve().parents[1]

GOOD = """
[sweep]
scenario = "arms"
duration = 0.5
repeats = 2
[grid]
"poles.left_fist.p1" = [2.0, 8.0]
"poles.left_fist.p2" = { logspace = [1.0, 100.0, 3] }
"push.magnitude" = [0.0, 50.0]
[perturb]
base_linear = 0.01
"""


def spec_from(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return load_spec(p)


def manifest(**kw) -> table_mod.Manifest:
    """A sweep folder's manifest: made-up values, ``kw`` replacing them."""
    base = dict(fingerprint="abc", seed=1, batch=4, n_rollouts=10, n_chunks=3, scenario="arms",
                spec_path="s.toml", axes=(), barriers=("left_fist",), monitors=("right_fist",),
                outputs=("com", "arms"), target="left_fist", violation_tol=0.0, repeats=1,
                objective=("tracking_rms.arms",))
    return table_mod.Manifest(**{**base, **kw})


def test_shipped_specs_are_valid():
    targets = {"kalpha_poles": "left_fist", "gains": "left_fist", "push_forces": "swing_foot",
               "kalpha_poles_walk": "swing_foot"}
    for name, target in targets.items():
        s = load_spec(ROOT / "sweeps" / f"{name}.toml")
        assert s.n_rollouts >= 50
        assert s.target == target
    s = load_spec(ROOT / "sweeps" / "push_forces.toml")   # walking with pushes
    assert s.scenario == "push" and s.n_settings == 80
    assert [a.name for a in s.axes] == ["push.magnitude", "push.direction", "push.at"]
    s = load_spec(ROOT / "sweeps" / "kalpha_poles.toml")
    assert [a.name for a in s.axes] == ["poles.left_fist.p1", "poles.left_fist.p2"]
    assert s.axes[0].values[0] == pytest.approx(2.0)
    assert s.axes[0].values[-1] == pytest.approx(128.0)
    assert s.n_settings == 49


def test_kalpha_poles_spec_reaches_the_barrier(stand, ctrl_mj):
    """A pole sweep measures nothing unless its barrier acts. Along the arm reference of
    ``sweeps/kalpha_poles.toml`` (the scenario's own arm task reference, paper eqs. 35-36,
    from its start data at the stand pose; the other joints held), the left fist's h(q)
    (eq. 33, the barrier's own function) must go below zero within the spec's duration. It
    stays above +40 mm for the first 4 s (the fist goes down first): the spec's old 4 s
    duration swept a barrier that never acted. Pure kinematics on a 1 ms grid; the bounds
    are tens of mm from the computed values (h(0) = +50 mm, zero crossed at 5.6 s, -101 mm
    at 7.5 s)."""
    import jax
    import jax.numpy as jnp

    from safewbc_jax import scenarios
    from safewbc_jax.control import step as control_step
    from safewbc_jax.model import robot

    spec = load_spec(ROOT / "sweeps" / "kalpha_poles.toml")
    model = robot.from_mujoco(ctrl_mj)
    sc = scenarios.get_scenario(spec.scenario)
    fist = next(b for b in sc.barriers if b.name == spec.target)
    arms = next(t for t in sc.tasks if t.name == "arms")
    q0 = jnp.asarray(stand[0])
    start = control_step.start_data(model, sc, q0)
    idx = np.array([model.joint_qadr(j) for j in arms.output.joints])

    def h(tau):
        q = q0.at[idx].set(arms.reference(tau, start))
        return fist.h(model, q, fist.threshold)

    tau = np.arange(0.0, spec.duration + 1e-9, 1e-3)
    hs = np.asarray(jax.jit(jax.vmap(h))(jnp.asarray(tau)))
    assert hs[0] == pytest.approx(0.05, abs=0.01)
    assert hs[tau <= 4.0].min() > 0.04
    assert hs.min() < -0.02, f"the reference keeps h >= {hs.min():.4f} m: the barrier never acts"
    assert 4.0 < tau[np.argmax(hs < 0)] < spec.duration


@pytest.mark.parametrize("path", sorted((ROOT / "sweeps").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_specs_pass_the_sweep_preflight(path):
    """Every shipped spec passes every check ``safewbc sweep`` makes before it compiles,
    Theorem 1 at each rollout's perturbed start state included, with its own seed."""
    from safewbc_jax.sweeps.run import preflight

    spec = load_spec(path)
    base, std, settings = preflight(spec)
    assert settings.shape[0] == spec.n_settings and std.shape[-1] > 0


def test_grid_plan_is_row_major(tmp_path):
    s = spec_from(tmp_path, GOOD)
    assert s.n_settings == 2 * 3 * 2 and s.n_rollouts == 24
    arr = s.settings_array()
    assert arr.shape == (12, 3)
    # the last axis varies fastest, as setting() says
    assert s.setting(0) == {"poles.left_fist.p1": 2.0, "poles.left_fist.p2": 1.0,
                            "push.magnitude": 0.0}
    assert s.setting(1)["push.magnitude"] == 50.0
    assert s.setting(2)["poles.left_fist.p2"] == pytest.approx(10.0)
    assert s.setting(11) == {"poles.left_fist.p1": 8.0, "poles.left_fist.p2": pytest.approx(100.0),
                             "push.magnitude": 50.0}
    for i in range(12):
        assert list(s.setting(i).values()) == pytest.approx(list(arr[i]))


@pytest.mark.parametrize("text, needle", [
    # unknown keys, at every level
    ('[sweep]\nscenario = "arms"\n[grids]\nx = 1', "unknown key 'grids'"),
    ('[sweep]\nscenario = "arms"\nrepeat = 2', "unknown key sweep.repeat = 2"),
    ('[sweep]\nscenario = "arms"\n[push]\nforce = 3.0', "unknown key push.force = 3.0"),
    ('[sweep]\nscenario = "arms"\n[perturb]\nbase = 0.1', "unknown key perturb.base = 0.1"),
    ('[sweep]\nscenario = "arms"\n[tune]\nsteps = 3', "unknown key tune.steps = 3"),
    ('[sweep]\nscenario = "arms"\n[params]\nfriction = 0.5', "unknown key 'friction'"),
    ('[sweep]\nscenario = "arms"\n[grid]\n"foo.bar" = [1.0]', 'grid."foo.bar": unknown axis'),
    # wrong types
    ('[sweep]\nscenario = "arms"\nrepeats = "four"', 'sweep.repeats = "four": expected an integer'),
    ('[sweep]\nscenario = "arms"\nrepeats = 2.5', "sweep.repeats = 2.5: expected an integer"),
    ('[sweep]\nscenario = "arms"\nbarrier = 1', "sweep.barrier = 1: expected true or false"),
    ('[sweep]\nscenario = "arms"\n[grid]\nmu = 0.5', "grid.mu = 0.5: expected a list of numbers"),
    ('[sweep]\nscenario = "arms"\n[grid]\nmu = [0.5, "x"]', 'grid.mu[1] = "x": expected a number'),
    ('[sweep]\nscenario = "arms"\n[grid]\nmu = {range = [1, 2]}', "grid.mu = {'range'"),
    ('[sweep]\nscenario = "arms"\n[perturb]\njoints = "lots"',
     'perturb.joints = "lots": expected a number'),
    # empty grids
    ('[sweep]\nscenario = "arms"\n[grid]\nmu = []', "grid.mu = []: empty grid"),
    ('[sweep]\nscenario = "arms"\n[grid]\nmu = {linspace = [0.3, 0.9, 0]}', "gives an empty grid"),
    # non-positive poles
    ('[sweep]\nscenario = "arms"\n[grid]\n"poles.left_fist.p1" = [1.0, 0.0]',
     'grid."poles.left_fist.p1" = [1.0, 0.0]: pole 0.0 is not > 0'),
    ('[sweep]\nscenario = "arms"\n[grid]\n"poles.left_fist" = [-2.0]', "pole -2.0 is not > 0"),
    ('[sweep]\nscenario = "arms"\n[params.poles]\nleft_fist = [0.0, 5.0]', "poles must be > 0"),
    ('[sweep]\nscenario = "arms"\n[grid]\n"poles.left_fist.p3" = [1.0]',
     "'p3' is not a pole of 'left_fist'"),
    # unknown scenario, barrier, output
    ('[sweep]\nscenario = "dance"', 'sweep.scenario = "dance": no such scenario'),
    ('[sweep]\nscenario = "walk"\n[grid]\n"poles.left_fist.p1" = [1.0]', "no barrier 'left_fist'"),
    ('[sweep]\nbarrier = true', "sweep.scenario is missing"),
    ('[sweep]\nscenario = "arms"\n[grid]\n"poles.right_foot.p1" = [1.0]',
     "no barrier 'right_foot'"),
    ('[sweep]\nscenario = "squat"\ntarget = "left_fist"', 'sweep.target = "left_fist": no barrier'),
    ('[sweep]\nscenario = "arms"\n[grid]\n"kp.legs" = [10.0]', "kp.OUTPUT with OUTPUT one of"),
    ('[sweep]\nscenario = "arms"\n[tune]\nobjective = ["tracking_rms.legs"]',
     "'tracking_rms.legs' is not a metric to minimize"),
    # other bad values
    ('[sweep]\nscenario = "arms"\nduration = -1.0', "sweep.duration = -1.0: must be > 0"),
    ('[sweep]\nscenario = "arms"\n[grid]\n"push.magnitude" = [-5.0]', "magnitudes must be >= 0"),
    ('[sweep]\nscenario = "arms"\n[grid]\n"push.at" = [1.0]\n[push]\nat = 2.0', "also swept"),
    ('[sweep]\nscenario = "arms"\n[grid]\n"poles.left_fist" = [1.0]\n"poles.left_fist.p1" = [2.0]',
     'grid."poles.left_fist" and grid."poles.left_fist.p1" both set the poles of '
     "'left_fist'; sweep one or the other"),
    ('[sweep]\nscenario = "arms"\n[grid]\nmu = [0.5, 0.5]', "repeated values"),
    ('[sweep]\nscenario = "arms"\n[tune]\nshrink = 1.5',
     "tune.shrink = 1.5: must be between 0 and 1"),
    ('[sweep\nscenario = "arms"', "not valid TOML"),
])
def test_each_bad_spec_gets_one_clear_error(tmp_path, text, needle):
    with pytest.raises(SpecError) as e:
        spec_from(tmp_path, text, "bad.toml")
    msg = str(e.value)
    assert needle in msg, msg
    assert str(tmp_path / "bad.toml") in msg          # names the file
    assert "\n" not in msg.strip()                    # one line


def test_missing_spec_file(tmp_path):
    with pytest.raises(SpecError, match="does not exist"):
        load_spec(tmp_path / "nope.toml")


def test_cli_rejects_bad_spec_before_compiling(tmp_path):
    """The CLI stops on a bad spec within seconds (no compile), exit status 2, one line."""
    bad = tmp_path / "bad.toml"
    bad.write_text('[sweep]\nscenario = "arms"\n[grid]\n"poles.left_fist.p2" = [4.0, -1.0]\n')
    r = subprocess.run([sys.executable, "-m", "safewbc_jax.app.cli", "sweep", str(bad), "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert 'grid."poles.left_fist.p2" = [4.0, -1.0]: pole -1.0 is not > 0' in r.stderr
    assert not (tmp_path / "o").exists()


def test_params_batch_applies_every_axis_kind(tmp_path):
    s = spec_from(tmp_path, """
[sweep]
scenario = "arms"
[params]
mu = 0.7
[grid]
"poles.left_fist" = [3.0, 5.0]
"poles.right_fist.p2" = [7.0]
"threshold.left_fist" = [0.04]
"kp.torso" = [50.0]
"gain_scale.arms" = [4.0]
"weight_scale.com" = [0.5]
f_min = [20.0]
""")
    base = inputs.base_params(s)
    vals = s.settings_array()
    p = inputs.params_batch(base, s.axes, vals)
    assert np.asarray(p.poles["left_fist"]).tolist() == [[3.0, 3.0], [5.0, 5.0]]
    assert np.asarray(p.poles["right_fist"])[:, 1].tolist() == [7.0, 7.0]
    assert np.asarray(p.threshold["left_fist"]).tolist() == [0.04, 0.04]
    assert np.all(np.asarray(p.kp["torso"]) == 50.0)
    d_kp, d_kd = np.asarray(base.kp["arms"]), np.asarray(base.kd["arms"])
    np.testing.assert_allclose(p.kp["arms"][0], 4.0 * d_kp)
    np.testing.assert_allclose(p.kd["arms"][0], 2.0 * d_kd)      # sqrt(4): same damping ratio
    np.testing.assert_allclose(p.weight["com"][1], 0.5 * np.asarray(base.weight["com"]))
    assert np.asarray(p.mu).tolist() == [0.7, 0.7] and np.asarray(p.f_min).tolist() == [20.0, 20.0]
    # the base is untouched and every leaf has the batch axis
    import jax
    assert all(np.shape(x)[0] == 2 for x in jax.tree_util.tree_leaves(p))
    assert float(base.mu) == 0.7 and np.asarray(base.poles["left_fist"]).tolist() == [10.0, 10.0]


def test_push_and_perturbations(tmp_path):
    s = spec_from(tmp_path, GOOD + '\n[push]\ndirection = 90.0\n')
    vals = s.settings_array()
    push, cols = inputs.pushes(s, vals)
    np.testing.assert_allclose(cols["fx"], 0.0, atol=1e-12)
    np.testing.assert_allclose(cols["fy"], vals[:, 2])
    np.testing.assert_array_equal(push.force, np.stack([cols["fx"], cols["fy"], cols["fz"]], 1))
    assert push.at.shape == push.duration.shape == (len(vals),)
    import mujoco

    from safewbc_jax.base import paths
    m = mujoco.MjModel.from_xml_path(str(paths.scene_xml()))
    std = inputs.velocity_std(s, m)
    assert std.shape == (m.nv,) and np.all(std[:3] == 0.01) and np.all(std[3:] == 0.0)
    # rollout k's draw depends on (seed, k) only, not on the chunk it is in
    a = inputs.perturbations(3, np.arange(10), std)
    b = np.concatenate([inputs.perturbations(3, np.arange(0, 4), std),
                        inputs.perturbations(3, np.arange(4, 10), std)])
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, inputs.perturbations(4, np.arange(10), std))
    assert np.all(a[:, 3:] == 0.0) and 0.002 < np.std(a[:, :3]) < 0.03


def test_wilson_interval_textbook_values():
    """Newcombe (1998), Stat. Med. 17:857, table I, method 3 (Wilson score, no continuity
    correction), to the 4 decimals printed there."""
    for (k, n), (lo, hi) in {(81, 263): (0.2553, 0.3662), (15, 148): (0.0624, 0.1605),
                             (0, 20): (0.0, 0.1611), (1, 29): (0.0061, 0.1718),
                             (29, 29): (0.8830, 1.0)}.items():
        got = wilson_interval(k, n)
        assert got == pytest.approx((lo, hi), abs=5e-5), (k, n, got)
    lo, hi = wilson_interval(np.array([0, 5]), np.array([10, 10]))
    assert lo[0] == 0.0 and hi[1] == pytest.approx(0.7634, abs=5e-5)   # 5/10: 0.2366-0.7634
    assert lo[1] == pytest.approx(0.2366, abs=5e-5)


def test_chunk_plan_and_atomic_parquet(tmp_path):
    assert table_mod.plan_chunks(10, 4) == [(0, 4), (4, 8), (8, 10)]
    assert table_mod.plan_chunks(8, 4) == [(0, 4), (4, 8)]
    out = tmp_path / "sw"
    man = manifest()
    table_mod.open_manifest(out, man, "x = 1\n")
    table_mod.write_chunk(out, 1, {"rollout": np.arange(4, 8), "h": np.linspace(0, 1, 4)})
    table_mod.write_chunk(out, 0, {"rollout": np.arange(0, 4), "h": np.zeros(4)})
    # a temporary file of a chunk in flight is invisible to readers and removed on resume
    (out / "chunks" / ".chunk-000002.parquet.tmp-123").write_bytes(b"PAR1 half written")
    assert table_mod.finished_chunks(out) == {0, 1}
    cols = table_mod.read_columns(out)
    assert cols["rollout"].tolist() == list(range(8))
    np.testing.assert_allclose(cols["h"][4:], np.linspace(0, 1, 4))
    assert table_mod.remove_partial(out) == [".chunk-000002.parquet.tmp-123"]
    # resuming with another seed / batch / spec is refused, naming what differs
    for key, val in (("seed", 2), ("batch", 8), ("fingerprint", "other")):
        with pytest.raises(table_mod.TableError, match=f"{key} = "):
            table_mod.open_manifest(out, dataclasses.replace(man, **{key: val}))
    assert table_mod.open_manifest(out, man).seed == 1
    with pytest.raises(table_mod.TableError, match="not a sweep directory"):
        table_mod.read_manifest(tmp_path)


def test_a_second_plan_never_replaces_the_first(tmp_path):
    """Hosts sharing one folder (``--hosts``) share its first plan: a manifest with another
    batch is refused even before any chunk has finished, the file is left as the first
    host wrote it, and a host with the same plan gets it back."""
    out = tmp_path / "shared"
    man = manifest(engine="mjx")
    assert table_mod.open_manifest(out, man, "x = 1\n") == man
    first = (out / table_mod.MANIFEST).read_bytes()
    with pytest.raises(table_mod.TableError, match=r"batch = 4, this one has 8 \(another "
                       r"--batch\).*no chunk of it has finished"):
        table_mod.open_manifest(out, dataclasses.replace(man, batch=8))
    assert (out / table_mod.MANIFEST).read_bytes() == first
    assert table_mod.open_manifest(out, man) == man
    assert not [f.name for f in out.iterdir() if ".tmp-" in f.name]   # no temp file left


def test_manifest_round_trips_and_refuses_a_bad_key(tmp_path):
    """The manifest's JSON round-trips (the same record, the same text, the keys in the
    file's order); a file with a key missing or unknown is refused naming the key and the
    file; a folder begun before objective_weights, safe_sets, engine, lockstep and lanes
    reads with their defaults (lockstep 1 and lanes "xla" on the mujoco engine); resuming
    with the other lanes' step is refused, naming it."""
    from safewbc_jax.sweeps.run import _manifest

    man = manifest(objective_weights={"tracking_rms.arms": 2.0}, safe_sets=("/x/y.py:S",),
                   engine="mujoco", lockstep=8, lanes="c")
    text = man.to_json()
    assert table_mod.Manifest.from_json(text) == man
    assert table_mod.Manifest.from_json(json.loads(text)) == man
    assert table_mod.Manifest.from_json(text).to_json() == text
    assert list(json.loads(text)) == [
        "format", "fingerprint", "seed", "batch", "n_rollouts", "n_chunks", "scenario",
        "spec_path", "axes", "barriers", "monitors", "outputs", "target", "violation_tol",
        "repeats", "objective", "objective_weights", "safe_sets", "engine", "lockstep",
        "lanes"]
    assert not {"lockstep", "lanes"} & set(json.loads(manifest().to_json()))  # mjx's
    # a spec's manifest, written and read back by the folder
    spec = load_spec(ROOT / "sweeps" / "kalpha_poles.toml")
    assert spec.fingerprint() == "54a9cd7467753d3c"     # folders begun before stay valid
    mine = _manifest(spec, 3, 16, 7, "mujoco", 8, "c")
    out = tmp_path / "sw"
    assert table_mod.open_manifest(out, mine) == mine == table_mod.read_manifest(out)
    assert (out / table_mod.MANIFEST).read_text() == mine.to_json()
    with pytest.raises(table_mod.TableError, match=r"lanes = 'c', this one has 'xla' "
                                                   r"\(another step of the mujoco engine"):
        table_mod.open_manifest(out, dataclasses.replace(mine, lanes="xla"))
    # the lanes a sweep into a folder runs: this machine's, but XLA's where the folder's
    # table was begun with XLA lanes (XLA runs anywhere; the table keeps one rounding)
    from safewbc_jax.sweeps.pool import lanes_engine
    from safewbc_jax.sweeps.run import _lanes
    assert _lanes(tmp_path / "none") == _lanes(out) == lanes_engine()
    xla = tmp_path / "xla"
    table_mod.open_manifest(xla, dataclasses.replace(mine, lanes="xla"))
    assert _lanes(xla) == "xla"
    # a missing or an unknown key, named with the file
    path = out / table_mod.MANIFEST
    for key in ("seed", "fingerprint"):
        d = json.loads(text)
        del d[key]
        path.write_text(json.dumps(d))
        with pytest.raises(table_mod.TableError, match=f"{path}: the manifest has no key "
                                                       f"'{key}'"):
            table_mod.read_manifest(out)
        with pytest.raises(table_mod.TableError, match=f"no key '{key}'"):
            table_mod.open_manifest(out, mine)
    path.write_text(json.dumps({**json.loads(text), "sed": 1}))
    with pytest.raises(table_mod.TableError, match=f"{path}: unknown manifest key 'sed'"):
        table_mod.read_manifest(out)
    with pytest.raises(table_mod.TableError, match="'axes' = 'x': expected a list"):
        table_mod.Manifest.from_json({**json.loads(text), "axes": "x"}, "m.json")
    # a folder from before the later keys
    old = {k: v for k, v in json.loads(text).items()
           if k not in ("objective_weights", "safe_sets", "engine", "lockstep", "lanes")}
    got = table_mod.Manifest.from_json(old)
    assert (got.engine, got.safe_sets, got.objective_weights, got.lockstep) == ("mjx", (), {},
                                                                                None)
    got = table_mod.Manifest.from_json({**old, "engine": "mujoco"})
    assert (got.lockstep, got.lanes) == (1, "xla")


def test_spec_tables_are_typed_and_the_pool_job_pickles(tmp_path):
    """[push], [perturb] and [tune] are typed records with the spec's values and the
    defaults; the pool's job (``pool.Job``) pickles, as multiprocessing's spawn and Ray
    send it."""
    import pickle

    from safewbc_jax.sweeps.pool import Job
    from safewbc_jax.sweeps.spec import (PUSH_DEFAULTS, PerturbTable, PushTable,
                                         TuneTable)

    s = spec_from(tmp_path, GOOD + "[push]\ndirection = 90.0\n[tune]\npopulation = 6\n")
    assert s.push == PushTable(**{**PUSH_DEFAULTS, "direction": 90.0})
    assert s.perturb == PerturbTable(base_linear=0.01)
    assert isinstance(s.tune, TuneTable) and s.tune.population == 6 and s.tune.budget is None
    assert s.tune.barrier == "left_fist" and s.tune.params == ()
    assert s.tune.weights == {"tracking_rms.com": 1.0, "tracking_rms.torso": 1.0,
                              "tracking_rms.arms": 1.0}
    job = Job(s.run, 4, str(tmp_path), "mjx", "mixed")
    assert pickle.loads(pickle.dumps(job)) == job


def _fake_table(tmp_path):
    """A table with the columns run_sweep writes, filled from a made-up closed form (a
    report test only; every rollout test runs the real batched path)."""
    rng = np.random.default_rng(0)
    p1, p2 = np.meshgrid([1.0, 4.0, 16.0], [2.0, 8.0], indexing="ij")
    p1, p2 = np.repeat(p1.ravel(), 10), np.repeat(p2.ravel(), 10)
    n = p1.size
    mag = np.tile(np.repeat([0.0, 100.0], 5), 6)
    d = np.tile([0.0, 90.0, 180.0, 270.0, 0.0], 12)
    hmin = 0.02 / np.sqrt(p1 * p2) - 0.003 * mag / 100 + rng.normal(0, 0.001, n)
    cols = {"rollout": np.arange(n), "setting": np.arange(n) // 5, "repeat": np.arange(n) % 5,
            "poles.left_fist.p1": p1, "poles.left_fist.p2": p2, "push.magnitude": mag,
            "push.direction": d, "push.at": np.ones(n), "push.duration": np.full(n, 0.15),
            "fell": mag * p1 > 1500, "qp_failed": np.zeros(n, int), "fallbacks": np.zeros(n, int),
            "barrier_min.left_fist": hmin, "tracking_rms.arms": 0.05 + 0.01 / p1,
            "tracking_rms.com": np.full(n, 0.002)}
    out = tmp_path / "rep"
    man = manifest(fingerprint="f", seed=0, batch=20, n_rollouts=n, n_chunks=3,
                   axes=("poles.left_fist.p1", "poles.left_fist.p2", "push.magnitude",
                         "push.direction"))
    table_mod.open_manifest(out, man)
    for k, (a, b) in enumerate(table_mod.plan_chunks(n, 20)):
        table_mod.write_chunk(out, k, {c: v[a:b] for c, v in cols.items()})
    return out, cols


def test_report_from_a_table(tmp_path):
    from safewbc_jax.sweeps.report import make_report

    out, cols = _fake_table(tmp_path)
    r = make_report(out)
    assert set(r["figures"]) == {"poles_heatmap.png", "push_violation.png",
                                 "tracking_vs_margin.png"}
    for f in r["figures"]:
        assert (out / f).stat().st_size > 10_000
    text = (out / "summary.md").read_text()
    # the overall violation count and its Wilson interval, as computed here
    k = int(np.sum(cols["barrier_min.left_fist"] < 0))
    lo, hi = wilson_interval(k, 60)
    assert f"barrier violations: {k}/60 = {k / 60:.3f} [{lo:.3f}, {hi:.3f}]" in text
    assert f"falls: {int(np.sum(cols['fell']))}/60" in text
    # best setting: the smallest poles (largest margin, no fall); worst: the largest
    best = text.split("## Best")[1].split("\n| ")[2]
    worst = text.split("## Worst")[1].split("\n| ")[2]
    assert best.startswith("4 | 2 |"), best      # safe, least tracking
    assert worst.startswith("16 | 8 |"), worst
    assert "## By push condition" in text


def test_report_objective_uses_the_spec_weights(tmp_path):
    """A manifest's objective_weights (tune.objective as a table) weight the report's
    objective as the tuner does; a manifest without them sums its objective list."""
    from safewbc_jax.sweeps.report import outcome

    _, cols = _fake_table(tmp_path)
    man = manifest(objective=("tracking_rms.arms", "tracking_rms.com"))
    np.testing.assert_allclose(outcome(man, cols)["objective"],
                               cols["tracking_rms.arms"] + cols["tracking_rms.com"], rtol=1e-12)
    man = dataclasses.replace(man, objective_weights={"tracking_rms.arms": 2.0,
                                                      "tracking_rms.com": -0.5})
    np.testing.assert_allclose(outcome(man, cols)["objective"],
                               2.0 * cols["tracking_rms.arms"] - 0.5 * cols["tracking_rms.com"],
                               rtol=1e-12)


def test_cli_sweep_help_lists_options():
    r = subprocess.run([sys.executable, "-m", "safewbc_jax.app.cli", "sweep", "--help"],
                       capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0
    for opt in ("--out", "--batch", "--seed"):
        assert opt in r.stdout


def test_theorem1_bounds_used_by_tuning():
    """The first pole's bound -h_dot / h over the start states, and the admissibility mask
    (barriers.check_poles at every start state) on both sides of it."""
    from safewbc_jax.sweeps.admissible import admissible_mask, first_pole_bound

    etas = np.array([[0.05, 0.02], [0.05, -0.1], [0.04, 0.0]])   # h, h_dot
    assert first_pole_bound(etas) == pytest.approx(2.0)
    cand = np.array([[1.9, 5.0], [2.1, 5.0], [2.1, 0.1], [50.0, 50.0]])
    assert admissible_mask("left_fist", cand, etas).tolist() == [False, True, True, True]
    assert first_pole_bound(np.array([[0.05, 0.0]])) == 0.0      # at rest: any poles


def test_tune_poles_preset_box_and_distribution(tmp_path):
    """tune-poles' parameters: the barrier's poles over [pole_min, pole_max], narrowed by
    the spec's pole axes; the distribution is the push axes, and any other axis is refused."""
    from safewbc_jax.sweeps.tuning import distribution, poles_preset

    s = spec_from(tmp_path, GOOD + "\n[tune]\npole_min = 1.5\npole_max = 50.0\n")
    ps = poles_preset(s)
    assert [p.name for p in ps] == ["poles.left_fist.p1", "poles.left_fist.p2"]
    np.testing.assert_allclose([p.lo for p in ps], [2.0, 1.5])   # p1 from the grid, p2 from tune
    np.testing.assert_allclose([p.hi for p in ps], [8.0, 50.0])
    assert {p.scale for p in ps} == {"log"}
    axes, rows = distribution(s, ps)
    assert [a.name for a in axes] == ["push.magnitude"] and rows[:, 0].tolist() == [0.0, 50.0]
    eq = poles_preset(spec_from(tmp_path, GOOD + "\n[tune]\nequal_poles = true\n", "e.toml"))
    assert [(p.name, p.lo, p.hi) for p in eq] == [("poles.left_fist", 2.0, 8.0)]
    bad = spec_from(tmp_path, GOOD.replace('"push.magnitude" = [0.0, 50.0]', "mu = [0.5, 0.9]"),
                    "g.toml")
    with pytest.raises(SpecError, match=r"grid axes \['mu'\] are neither"):
        distribution(bad, poles_preset(bad))


def test_precision_key(tmp_path):
    """sweep.precision: validated by name; "float64" keeps the fingerprint of a spec
    without the key (sweeps begun before it resume), "mixed" is another sweep; the
    mujoco engine refuses "mixed" before anything runs."""
    from safewbc_jax.sweeps.run import run_sweep

    base = spec_from(tmp_path, GOOD, "a.toml")
    with_key = lambda v: GOOD.replace("[sweep]\n", f"[sweep]\nprecision = \"{v}\"\n")  # noqa: E731
    same = spec_from(tmp_path, with_key("float64"), "b.toml")
    mixed = spec_from(tmp_path, with_key("mixed"), "c.toml")
    assert base.precision == "float64" and mixed.precision == "mixed"
    assert base.fingerprint() == same.fingerprint() != mixed.fingerprint()
    with pytest.raises(SpecError, match="sweep.precision = 'half'"):
        spec_from(tmp_path, GOOD.replace("[sweep]\n", "[sweep]\nprecision = \"half\"\n"), "d.toml")
    with pytest.raises(ValueError, match="mjx engine"):
        run_sweep(mixed, tmp_path / "out", engine="mujoco", quiet=True)
    assert not (tmp_path / "out").exists()


def test_auto_batch_on_the_cpu_and_on_resume(tmp_path):
    """--batch auto: the spec's batch on a CPU (and with the mujoco engine); a sweep
    directory already begun keeps its manifest's batch. (On an accelerator it comes from
    rollout.memory_model; benchmarks/accelerator.py exercises that model on the CPU.)"""
    from safewbc_jax.app.cli import _batch_arg
    from safewbc_jax.sweeps.sizing import auto_batch
    from safewbc_jax.sweeps.table import MANIFEST

    spec = spec_from(tmp_path, GOOD)
    assert auto_batch(spec, tmp_path / "new", "mjx", quiet=True) == spec.batch
    assert auto_batch(spec, tmp_path / "new", "mujoco", quiet=True) == spec.batch
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / MANIFEST).write_text(manifest(batch=7).to_json())
    assert auto_batch(spec, tmp_path / "old", "mjx", quiet=True) == 7
    assert _batch_arg("auto") == "auto" and _batch_arg("12") == 12
    with pytest.raises(Exception, match="expected an integer >= 1"):
        _batch_arg("0")


def test_lockstep_width_is_16_or_a_smaller_batch():
    """The mujoco engine's lanes side by side (sweeps.pool): 16, or the batch where it is
    smaller, a chunk's groups never wider than the chunk; unresolved ("auto", None): 16."""
    from safewbc_jax.sweeps.pool import LOCKSTEP, lockstep_width

    assert LOCKSTEP == 16
    assert [lockstep_width(b) for b in (1, 2, 15, 16, 17, 256)] == [1, 2, 15, 16, 16, 16]
    assert lockstep_width(None) == lockstep_width("auto") == 16
    assert lockstep_width(np.int64(3)) == 3


def test_the_push_scenario_pushes_by_default_everywhere(tmp_path):
    """A scenario's push (``Scenario.push``) is the default of every path: the push
    scenario's sweep without a [push] table pushes 30 N to the right at 2.55 s for 0.15 s
    (the paper's push, the one ``safewbc run push`` applies); keys the spec gives override
    it one by one; a scenario without a push gets none."""
    import numpy as np

    from safewbc_jax import scenarios
    from safewbc_jax.app import runner
    from safewbc_jax.sweeps import inputs

    text = '[sweep]\nscenario = "push"\nduration = 4.0\n[grid]\n"poles.swing_foot.p1" = [20.0]\n'
    s = spec_from(tmp_path, text)
    assert (s.push.magnitude, s.push.direction, s.push.at, s.push.duration) == \
        (30.0, 270.0, 2.55, 0.15)
    push, _ = inputs.pushes(s, s.settings_array())
    np.testing.assert_allclose(push.force, [[0.0, -30.0, 0.0]], atol=1e-12)  # cos(270 deg)
    run = runner.check_run_options("push", scenarios.get_scenario("push"))
    assert run.push == (0.0, -30.0, 0.0) and (run.push_at, run.push_for) == (2.55, 0.15)
    s = spec_from(tmp_path, text + "[push]\nmagnitude = 10.0\n", "t.toml")
    assert (s.push.magnitude, s.push.direction) == (10.0, 270.0)
    assert spec_from(tmp_path, GOOD, "u.toml").push.magnitude == 0.0     # arms: no push
