"""``safewbc tune`` without a closed loop: the [tune] table's checks, the two searches,
the ranking, and the whole tuner (generations, resume, validation, params file, report)
with an analytic stand-in for the rollouts (``executor=``; barriers off, so no Theorem-1
compile). The real rollouts on both engines are in test_tune_rollouts.py."""

import json
from pathlib import Path

import numpy as np
import pytest

from safewbc_jax.sweeps import inputs
from safewbc_jax.sweeps import tuning
from safewbc_jax.sweeps.search import Cmaes, GridRefine
from safewbc_jax.sweeps.spec import SpecError, load_spec

ROOT = Path(__file__).resolve().parents[1]
LEAN = f"{ROOT / 'examples' / 'bow_torso_lean.py'}:TORSO_LEAN"
# with a user's safe set (monitored: barriers off), which the params file's run command
# must carry
SPEC = f"""
[sweep]
scenario = "arms"
barrier = false
repeats = 2
batch = 8
safe_sets = ["{LEAN}"]
[grid]
"push.magnitude" = [0.0, 10.0]
[perturb]
joints = 0.05
[tune]
population = 6
budget = 240
validate = 16
objective = {{ "tracking_rms.arms" = 1.0, "torque_ratio_max" = 0.5 }}
[tune.params]
"gain_scale.arms" = {{ bounds = [0.1, 10.0] }}
"weight_scale.com" = {{ bounds = [0.1, 10.0], scale = "log" }}
"""


def spec_from(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return load_spec(p)


class Analytic:
    """Stand-in rollouts: the arms' tracking RMS is a bowl in (log gain scale of the arms,
    log weight scale of the CoM) with its bottom at (2, 0.5), plus a small term from the
    perturbation; a rollout falls when the arms' gain scale exceeds 3 + push/100.
    Counts its calls (one per chunk)."""

    def __init__(self, spec, fail_at_call=None):
        self.base = inputs.base_params(spec)
        self.calls = 0
        self.fail_at_call = fail_at_call

    def __call__(self, spec, params, push, dv):
        self.calls += 1
        if self.fail_at_call is not None and self.calls == self.fail_at_call:
            raise KeyboardInterrupt("killed")
        g = np.asarray(params.kp["arms"])[:, 0] / np.asarray(self.base.kp["arms"])[0]
        w = np.asarray(params.weight["com"])[:, 0] / np.asarray(self.base.weight["com"])[0]
        n = len(g)
        return {"tracking_rms.arms": (np.log(g / 2.0)) ** 2 + np.log(w / 0.5) ** 2
                + 0.01 * np.linalg.norm(dv, axis=1),
                "torque_ratio_max": 0.1 * g, "fell": g > 3.0 + push.force[:, 0] / 100.0,
                "tracking_rms.com": np.zeros(n)}


BAD = [
    ("[tune]\nmethod = \"bayes\"", "tune.method = \"bayes\": expected one of cmaes, grid"),
    ("[tune.params]\n\"poles.nope.p1\" = [1.0, 2.0]", "no barrier 'nope'"),
    ("[tune.params]\n\"poles.left_fist.p1\" = [5.0, 2.0]", "low must be below high"),
    ("[tune.params]\n\"poles.left_fist.p1\" = { bounds = [1.0, 2.0], scael = \"log\" }",
     "unknown key tune.params.\"poles.left_fist.p1\".scael"),
    ("[tune.params]\n\"gain_scale.arms\" = { bounds = [0.5, 2.0], scale = \"cubic\" }",
     "scale = \"cubic\": expected \"log\" or \"linear\""),
    ("[tune.params]\n\"kp.arms\" = { bounds = [-1.0, 2.0], scale = \"log\" }",
     "must be > 0"),
    ("[tune.params]\n\"push.magnitude\" = [0.0, 50.0]", "pushes are the distribution"),
    ("[tune.params]\n\"threshold.left_fist\" = [0.01, 0.1]", "a threshold defines the safe set"),
    ("[tune.params]\n\"gain_scale.arms\" = { bounds = [0.5, 2.0], start = 3.0 }",
     "start = 3.0: outside the bounds"),
    ("[tune]\nobjective = { \"zmp_margin_min\" = 1.0 }", "give it a negative weight"),
    ("[tune]\nobjective = { \"tracking_rms.arms\" = \"x\" }", "expected a number"),
    ("[tune]\npopulation = 1", "CMA-ES needs at least 2"),
    ("[tune]\nsigma = 2.0", "tune.sigma = 2.0"),
    ("[tune]\nbudget = 0", "tune.budget = 0: must be > 0"),
]


@pytest.mark.parametrize("text,msg", BAD)
def test_bad_tune_tables_name_the_key(tmp_path, text, msg):
    with pytest.raises(SpecError) as e:
        spec_from(tmp_path, "[sweep]\nscenario = \"arms\"\n" + text)
    assert msg in str(e.value)
    assert "s.toml" in str(e.value)


def test_tune_config_defaults_and_budget(tmp_path):
    s = spec_from(tmp_path, SPEC)
    cfg = tuning.config(s)
    assert cfg.method == "cmaes" and cfg.budget == 240 and cfg.validate == 16
    assert [p.name for p in cfg.params] == ["gain_scale.arms", "weight_scale.com"]
    assert cfg.weights == {"tracking_rms.arms": 1.0, "torque_ratio_max": 0.5}
    # a budget below one generation (6 candidates x 4 draws) is refused before any rollout
    with pytest.raises(SpecError, match="a budget of 23 rollouts is less than one generation"):
        tuning.config(s, budget=23)
    # a [grid] axis that is neither a push nor a tuned pole
    with pytest.raises(SpecError, match=r"grid axes \['mu'\]"):
        tuning.config(spec_from(tmp_path, SPEC.replace("[grid]\n", "[grid]\nmu = [0.5, 0.9]\n"),
                                "m.toml"))
    # a single fixed value is a setting, not a distribution; a grid over a tuned parameter
    # is the sweep's and is left out; a single value on a tuned output's gains is refused
    ok = spec_from(tmp_path, SPEC.replace("[grid]\n", "[grid]\nmu = [0.6]\n"
                                          "\"gain_scale.arms\" = [1.0, 2.0]\n"), "f.toml")
    axes, rows = tuning.distribution(ok, tuning.config(ok).params)
    assert [a.name for a in axes] == ["mu", "push.magnitude"]
    np.testing.assert_array_equal(rows, [[0.6, 0.0], [0.6, 10.0]])
    with pytest.raises(SpecError, match=r"grid axes \['kp.arms'\]"):
        tuning.config(spec_from(tmp_path, SPEC.replace("[grid]\n",
                                                       "[grid]\n\"kp.arms\" = [50.0]\n"),
                                "k.toml"))
    # without tune.params and without an enforced barrier there is nothing to tune
    no = SPEC.split("[tune.params]")[0]
    with pytest.raises(SpecError, match="nothing to tune"):
        tuning.config(spec_from(tmp_path, no, "n.toml"))
    # the list form of the objective: weight 1 each
    lst = spec_from(tmp_path, "[sweep]\nscenario = \"arms\"\n[tune]\nobjective = "
                    "[\"tracking_rms.arms\", \"foot_slip_max\"]\n", "l.toml")
    assert lst.tune.weights == {"tracking_rms.arms": 1.0, "foot_slip_max": 1.0}
    assert lst.tune.objective == ("tracking_rms.arms", "foot_slip_max")


def test_param_scales_map_the_unit_box():
    from safewbc_jax.sweeps.spec import Axis, TuneParam

    ax = Axis("gain_scale.arms", "scale", "arms", (0.5, 8.0))
    log = TuneParam(ax, 0.5, 8.0, "log")
    np.testing.assert_allclose(log.to_value([0.0, 0.5, 1.0]), [0.5, 2.0, 8.0], rtol=1e-12)
    lin = TuneParam(ax, 0.5, 8.0, "linear")
    np.testing.assert_allclose(lin.to_value([0.0, 0.5, 1.0]), [0.5, 4.25, 8.0], rtol=1e-12)
    u = np.linspace(0, 1, 7)
    for p in (log, lin):
        np.testing.assert_allclose(p.to_unit(p.to_value(u)), u, atol=1e-12)


def test_cmaes_is_deterministic_and_finds_a_bowl_in_the_box():
    """Two searches with one seed ask the same candidates; on a bowl whose bottom (0.3, 0.7)
    lies inside the box, 40 generations bring the best within 1e-3 of it."""
    def run(seed, gens=40):
        s = Cmaes([0.5, 0.5], 0.3, 6, seed)
        best = (np.inf, None)
        asks = []
        for _ in range(gens):
            x = s.ask()
            asks.append(x)
            assert np.all((x >= 0) & (x <= 1))
            f = np.sum((x - [0.3, 0.7]) ** 2, axis=1)
            s.tell(x, f)
            j = int(np.argmin(f))
            best = min(best, (f[j], tuple(x[j])))
            if s.done():
                break
        return asks, best

    a1, b1 = run(3)
    a2, b2 = run(3)
    assert all(np.array_equal(x, y) for x, y in zip(a1, a2)) and len(a1) == len(a2)
    assert not np.array_equal(run(4, 1)[0][0], a1[0])
    np.testing.assert_allclose(b1[1], [0.3, 0.7], atol=1e-3)


def test_grid_refine_lays_and_shrinks_its_box():
    """points^d candidates evenly over the box, then a box shrink times as wide around
    the best so far, clipped to the unit box."""
    g = GridRefine(2, 3, 2, 0.5)
    x = g.ask()
    assert x.shape == (9, 2)
    np.testing.assert_allclose(np.unique(x[:, 0]), [0.0, 0.5, 1.0])
    f = np.sum((x - [1.0, 0.5]) ** 2, axis=1)     # best: (1, 0.5)
    g.tell(x, f)
    np.testing.assert_allclose(g.lo, [0.75, 0.25])
    np.testing.assert_allclose(g.hi, [1.0, 0.75])
    assert not g.done()
    g.tell(g.ask(), np.ones(9))                    # no better candidate: same centre
    np.testing.assert_allclose(g.lo, [0.9375, 0.375])   # the clipped box is the one shrunk
    assert g.done()


def test_rank_value_orders_safe_first_then_fewest_unsafe_then_shallowest():
    C = tuning.Candidate
    safe_bad = C({}, n=4, objective=10.0)
    safe_good = C({}, n=4, objective=0.1)
    one_unsafe = C({}, n=4, unsafe=1, hmin={"b": -0.002}, objective=0.01)
    one_deeper = C({}, n=4, unsafe=1, hmin={"b": -0.2}, objective=0.01)
    two_unsafe = C({}, n=4, unsafe=2, hmin={"b": -0.0011}, objective=0.01)
    refused = C({}, refused="Theorem 1")
    order = [safe_good, safe_bad, one_unsafe, one_deeper, two_unsafe, refused]
    vals = [tuning.rank_value(c, 0.001) for c in order]
    assert vals == sorted(vals) and len(set(vals)) == len(vals)
    assert vals[:2] == [0.1, 10.0]
    # a safe candidate whose objective is NaN (a metric lost) is not safe
    assert not C({}, n=4, objective=float("nan")).safe


def test_evaluate_counts_violations_falls_and_lost_rollouts(tmp_path):
    """A candidate's outcome from a generation's table: a rollout is unsafe when any
    enforced barrier is below -violation_tol, when it falls, or when it is lost (an error
    or a NaN barrier minimum); the objective is the weighted mean, NaN when a rollout has
    none."""
    spec = spec_from(tmp_path, "[sweep]\nscenario = \"arms\"\nviolation_tol = 0.001\n")
    assert spec.barriers == ("left_fist",)
    nan = float("nan")
    cols = {"rollout": np.arange(8), "setting": np.arange(8) // 2,       # 2 settings each
            "barrier_min.left_fist": np.array([0.01, -0.0009, -0.0011, 0.02,   # c0: 1 violation
                                               0.01, nan, 0.03, 0.04]),        # c1: 1 lost
            "fell": np.array([0, 0, 0, 0, 0, 0, 0, 1], bool),                 # c1: 1 fall
            "error": np.array(["", "", "", "", "", "", "", ""], object),
            "tracking_rms.arms": np.array([1.0, 2, 3, 4, 5, 6, 7, 8]),
            "torque_ratio_max": np.full(8, 0.5)}
    cands = [tuning.Candidate({}), tuning.Candidate({})]
    tuning.evaluate(spec, {"tracking_rms.arms": 1.0, "torque_ratio_max": 2.0}, cols, 2, cands)
    c0, c1 = cands
    assert (c0.n, c0.unsafe, c0.violations, c0.falls, c0.lost) == (4, 1, 1, 0, 0)
    assert (c1.n, c1.unsafe, c1.violations, c1.falls, c1.lost) == (4, 2, 0, 1, 1)
    assert c0.hmin == {"left_fist": -0.0011} and c1.hmin == {"left_fist": 0.01}
    assert c0.objective == pytest.approx(2.5 + 1.0) and c1.objective == pytest.approx(6.5 + 1.0)
    assert not c0.safe and not c1.safe
    cols["error"][0] = "worker died"
    cols["tracking_rms.arms"][0] = nan
    tuning.evaluate(spec, {"tracking_rms.arms": 1.0}, cols, 2, cands)
    assert cands[0].lost == 1 and cands[0].unsafe == 2 and np.isnan(cands[0].objective)


def _run(spec, out, executor, **kw):
    return tuning.tune(spec, out, executor=executor, quiet=True, **kw)


def test_tuner_end_to_end_resume_and_report(tmp_path):
    """The whole tuner on the analytic stand-in: it finds the safe bottom of the bowl,
    validates it on held-out draws, writes a params file `safewbc run` reads; a run
    interrupted in generation 4 resumes without rerunning generations 1-3 and ends with
    the same result as an uninterrupted run; so does a run with another chunk size."""
    from safewbc_jax.control.params import load_overrides
    from safewbc_jax.sweeps.report import make_report

    spec = spec_from(tmp_path, SPEC)
    ex = Analytic(spec)
    r = _run(spec, tmp_path / "a" / "t.toml", ex)
    assert r.method == "cmaes" and r.used == 240 and r.stop.startswith("budget")
    assert len(r.generations) == 10           # 240 / (6 x 4)
    # the baseline's 4 rollouts (one chunk), 10 generations of 24 in chunks of 8, 16 held out
    assert ex.calls == 1 + 10 * 3 + 2
    # the baseline: both scales at 1, on the search's draws (not counted in the budget):
    # ln(1/2)^2 + ln(1/0.5)^2 + 0.05, plus at most 0.01 |dv| (|dv| ~ 0.05 sqrt(30) = 0.27)
    z = r.baseline
    assert z.params == {"gain_scale.arms": 1.0, "weight_scale.com": 1.0} and z.unsafe == 0
    assert z.objective == pytest.approx(2 * np.log(2) ** 2 + 0.05, abs=0.01)
    b = r.best
    assert b.safe and b.n == 4
    # the constrained optimum is the bowl's bottom (2, 0.5) shifted by 0.05 g (torque term):
    # d/dg [ln(g/2)^2 + 0.05 g] = 0 at g = 1.91
    assert b.params["gain_scale.arms"] == pytest.approx(1.91, abs=0.15)
    assert b.params["weight_scale.com"] == pytest.approx(0.5, rel=0.15)
    v = r.validation
    assert v["n"] == 16 and v["unsafe"] == 0 and v["seed"] == 1
    assert v["ci"][0] == 0.0 and v["ci"][1] == pytest.approx(0.1936, abs=1e-4)   # Wilson 0/16
    assert v["objective"] == pytest.approx(b.objective, abs=0.01)
    # every unsafe rollout of the search is one with the arms' gain scale above 3 + push/100
    t = json.loads((tmp_path / "a" / "t_tune" / "tuning.json").read_text())
    for gen in t["generations"]:
        for c in gen["candidates"]:
            g = c["params"]["gain_scale.arms"]
            assert c["unsafe"] == (2 * (g > 3.0) + 2 * (g > 3.1))
    # the params file: the tuned scales applied to the defaults, with the validation header
    text = (tmp_path / "a" / "t.toml").read_text()
    assert "# validation on 16 held-out rollouts (seed 1): 0 unsafe" in text
    assert f"0 of 4 unsafe, mean objective {z.objective:.6g}" in text
    assert f"--safe-set {LEAN}" in text and "--params" in text
    ov = load_overrides(tmp_path / "a" / "t.toml")
    base = inputs.base_params(spec)
    np.testing.assert_allclose(np.asarray(ov["kp"]["arms"]),
                               np.asarray(base.kp["arms"]) * b.params["gain_scale.arms"])
    np.testing.assert_allclose(np.asarray(ov["kd"]["arms"]),
                               np.asarray(base.kd["arms"]) * np.sqrt(b.params["gain_scale.arms"]))

    # interrupted in generation 4 (its first chunk), then rerun
    ex2 = Analytic(spec, fail_at_call=1 + 3 * 3 + 1)
    with pytest.raises(KeyboardInterrupt):
        _run(spec, tmp_path / "b" / "t.toml", ex2)
    done = json.loads((tmp_path / "b" / "t_tune" / "tuning.json").read_text())
    assert [g["generation"] for g in done["generations"]] == [1, 2, 3]
    ex3 = Analytic(spec)
    r2 = _run(spec, tmp_path / "b" / "t.toml", ex3)
    assert ex3.calls == 7 * 3 + 2       # generations 4-10 and the validation only (no baseline)
    assert r2.best == r.best and r2.validation == r.validation
    # another chunk size: the same candidates, outcomes and result
    r3 = _run(spec, tmp_path / "c" / "t.toml", Analytic(spec), batch=5)
    assert r3.best == r.best and r3.validation == r.validation
    # a folder of another run (another seed) is refused, naming it
    with pytest.raises(SpecError, match="holds a tuning run of another spec, method or seed"):
        _run(spec, tmp_path / "b" / "t.toml", Analytic(spec), seed=5)

    # the report of the tuning folder
    rep = make_report(tmp_path / "a" / "t_tune")
    assert rep["figures"] == ["tuning_progress.png", "tuning_params.png"]
    s = (tmp_path / "a" / "t_tune" / "summary.md").read_text()
    assert "| 10 | 6 |" in s and "Validation on 16 held-out rollouts (seed 1)" in s
    assert f"search's draws: 0/4 unsafe, mean objective {z.objective:.6g}" in s
    assert f"- gain_scale.arms = {b.params['gain_scale.arms']:.6g}" in s


def test_grid_method_spends_its_rounds(tmp_path):
    """method = "grid": points^d candidates a round for `rounds` rounds (the tune-poles
    search), then the validation; the budget of the default config is exactly that."""
    spec = spec_from(tmp_path, SPEC.replace("population = 6\nbudget = 240\n",
                                            "points = 3\nrounds = 2\n"))
    cfg = tuning.config(spec, method="grid")
    assert cfg.budget == 2 * 9 * 4
    r = tuning.tune(spec, tmp_path / "g.toml", cfg=cfg, executor=Analytic(spec), quiet=True)
    assert len(r.generations) == 2 and r.used == 72 and r.stop == "rounds done"
    first = sorted({round(c["params"]["gain_scale.arms"], 9)
                    for c in r.generations[0]["candidates"]})
    np.testing.assert_allclose(first, [0.1, 1.0, 10.0])    # log-spaced over [0.1, 10]
    assert r.best.safe and r.best.params["gain_scale.arms"] == pytest.approx(1.0)
