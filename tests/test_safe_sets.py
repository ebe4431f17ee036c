"""User tasks and safe sets: one object each. Loading a safe set from the user's own file
(``safesets.load``, ``safewbc run --safe-set``, ``sweep.safe_sets``), its errors before
anything compiles, its parameters, Theorem 1 at the start for it, and a new task added as
one object changing the QP's cost by exactly its own term."""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safewbc_jax import scenarios
from safewbc_jax.control import barriers, step as control_step, outputs, safesets
from safewbc_jax.deploy import checks as deploy
from safewbc_jax.control.params import apply_overrides
from safewbc_jax.control.safesets import SafeSet, SafeSetError
from safewbc_jax.control.scenario import Scenario
from safewbc_jax.control.tasks import Task

ROOT = Path(__file__).resolve().parents[1]
LEAN = f"{ROOT / 'examples' / 'bow_torso_lean.py'}:TORSO_LEAN"
SPEED = f"{ROOT / 'examples' / 'squat_com_velocity.py'}:COM_SPEED"


def test_load_from_a_file_and_its_errors(tmp_path):
    s = safesets.load(LEAN)
    assert isinstance(s, SafeSet) and s.name == "torso_lean" and s.relative_degree == 2
    assert s.threshold == 0.9 and s.poles == (10.0, 10.0)
    assert safesets.load(SPEED).relative_degree == 1
    with pytest.raises(SafeSetError, match="expected FILE.py:NAME"):
        safesets.load("examples/bow_torso_lean.py")
    with pytest.raises(SafeSetError, match="does not exist"):
        safesets.load(str(tmp_path / "none.py") + ":X")
    with pytest.raises(SafeSetError, match="has no 'NOPE'; SafeSets there: TORSO_LEAN"):
        safesets.load(LEAN.replace("TORSO_LEAN", "NOPE"))
    f = tmp_path / "mine.py"
    f.write_text("from safewbc_jax.control.safesets import SafeSet\nX = 3\n"
                 "def make():\n    return SafeSet('mine', lambda m, q, c, d: c - q[0])\n")
    with pytest.raises(SafeSetError, match="X is a int, not a safewbc_jax.control.safesets.SafeSet"):
        safesets.load(f"{f}:X")
    assert safesets.load(f"{f}:make").name == "mine"     # a factory works too
    bad = tmp_path / "broken.py"
    bad.write_text("raise RuntimeError('boom')\n")
    with pytest.raises(SafeSetError, match="importing .*broken.py failed: RuntimeError: boom"):
        safesets.load(f"{bad}:X")


def test_a_safe_set_is_one_object_in_the_scenario_and_its_params():
    sc = scenarios.get_scenario("bow", True, (LEAN,))
    assert [b.name for b in sc.barriers] == ["torso_lean"]
    p = sc.default_params()
    np.testing.assert_array_equal(p.poles["torso_lean"], [10.0, 10.0])
    assert float(p.threshold["torso_lean"]) == 0.9
    p2 = apply_overrides(p, {"poles": {"torso_lean": [8.0, 9.0]},
                             "threshold": {"torso_lean": 0.8}})
    np.testing.assert_array_equal(p2.poles["torso_lean"], [8.0, 9.0])
    # the built-in scenario is unchanged, and returned as the same object
    assert scenarios.get_scenario("bow") is scenarios.get_scenario("bow")
    assert scenarios.get_scenario("bow").safe_sets == ()
    with pytest.raises(SafeSetError, match="already has a safe set of that name"):
        scenarios.get_scenario("arms", True, (SafeSet("left_fist", lambda m, q, c, d: c),))
    # walking without the barrier: the user's safe set is monitored like the built-in one
    w = scenarios.get_scenario("walk", False, (LEAN,))
    assert w.barriers == () and [m.name for m in w.monitors] == ["swing_foot", "torso_lean"]


def test_run_refuses_a_bad_safe_set_before_compiling(capsys):
    from safewbc_jax.app.cli import main

    # --cpu -1: no pinning (else the CLI pins this whole test process to one core)
    assert main(["run", "bow", "--cpu", "-1", "--safe-set", "examples/none.py:X"]) == 2
    assert "examples/none.py does not exist" in capsys.readouterr().err
    assert main(["run", "bow", "--cpu", "-1", "--safe-set", LEAN.replace("TORSO_LEAN", "lean")]) == 2
    assert "has no 'lean'" in capsys.readouterr().err


def test_sweep_spec_takes_safe_sets_from_its_folder(tmp_path):
    from safewbc_jax.sweeps.spec import SpecError, parse_spec

    src = tmp_path / "s.toml"
    (tmp_path / "lean.py").write_text((ROOT / "examples" / "bow_torso_lean.py").read_text())
    src.write_text("")
    data = {"sweep": {"scenario": "bow", "safe_sets": ["lean.py:TORSO_LEAN"],
                      "target": "torso_lean"},
            "grid": {"poles.torso_lean.p1": [2.0, 8.0], "threshold.torso_lean": [0.8, 0.9]}}
    s = parse_spec(data, str(src))
    assert s.safe_sets == (f"{(tmp_path / 'lean.py').resolve()}:TORSO_LEAN",)
    assert s.barriers == ("torso_lean",) and s.pole_counts["torso_lean"] == 2
    fp = s.fingerprint()
    # the fingerprint follows the file's content (a resumed table must come from the same h)
    (tmp_path / "lean.py").write_text((tmp_path / "lean.py").read_text() + "\n# edited\n")
    assert parse_spec(data, str(src)).fingerprint() != fp
    with pytest.raises(SpecError, match="sweep.safe_sets: .*does not exist"):
        parse_spec({"sweep": {"scenario": "bow", "safe_sets": ["no.py:X"]}}, str(src))
    with pytest.raises(SpecError, match="expected a list"):
        parse_spec({"sweep": {"scenario": "bow", "safe_sets": "lean.py:TORSO_LEAN"}}, str(src))
    with pytest.raises(SpecError, match="no barrier 'torso_lean'"):
        parse_spec({"sweep": {"scenario": "bow", "target": "torso_lean"}}, str(src))


@pytest.fixture(scope="module")
def stand(ctrl_mj):
    return jnp.asarray(ctrl_mj.key_qpos[0]), jnp.zeros(ctrl_mj.nv)


@pytest.mark.slow
def test_theorem_1_is_checked_for_user_safe_sets(rm, stand):
    """checks.check_barrier_poles, what Controller.start runs before it compiles."""
    q, _ = stand
    lean = scenarios.get_scenario("bow", True, (LEAN,))
    p = lean.default_params()
    deploy.check_barrier_poles(rm, lean, p, q, jnp.zeros(rm.nv))   # at rest: any poles
    # the torso pitching forward at 1 rad/s, 0.9 rad from its limit: p_1 >= 1 / 0.9
    from safewbc_jax.model import spatial

    h0 = lambda qq: lean.barriers[0].h(rm, qq, 0.0)  # noqa: E731  (= -pitch)
    j = spatial.tangent_jacobian(h0, q, rm.nv)
    v = -j / (j @ j)                                      # h_dot = -1 rad/s
    eta = control_step.start_eta_fn(rm, lean, lean.barriers[0], q)(v, 0.9)
    assert float(eta[1]) == pytest.approx(-1.0, rel=1e-9)
    bound = 1.0 / float(eta[0])
    slow = p.replace(poles={"torso_lean": jnp.array([0.9 * bound, 5.0])})
    with pytest.raises(barriers.PoleError, match="torso_lean.*p_1"):
        deploy.check_barrier_poles(rm, lean, slow, q, v)
    deploy.check_barrier_poles(rm, lean, p.replace(poles={"torso_lean": jnp.array(
        [1.01 * bound, 5.0])}), q, v)
    # relative degree 1: a start faster than v_max is outside the safe set
    sp = scenarios.get_scenario("squat", True, (SPEED,))
    fast = jnp.zeros(rm.nv).at[0].set(0.05)               # the base at 5 cm/s: CoM too
    with pytest.raises(barriers.PoleError, match=r"com_speed.*h\(x0\)"):
        deploy.check_barrier_poles(rm, sp, sp.default_params(), q, fast)
    deploy.check_barrier_poles(rm, sp, sp.default_params(), q, 0.2 * fast)


def test_a_new_task_is_one_object_and_adds_exactly_its_cost(rm, ctrl_mj, stand):
    """A task nobody wrote into the package (the left fist's world position), added to the
    squat as one Task: its gains are in the default params, and the QP's Hessian and
    gradient change by exactly 2 J'WJ and 2 J'W (J_dot v - y*) (eq. 15 and the QP after
    it), everything else equal."""
    q = jnp.asarray(ctrl_mj.key_qpos[0])
    rng = np.random.default_rng(1)
    v = jnp.asarray(0.1 * rng.standard_normal(rm.nv))
    base = scenarios.get_scenario("squat")
    fist = outputs.FramePosition(frame="left-fist", name="fist_pos")
    extra = Task(fist, 50.0, 10.0, 2.0, reference=lambda tau, start: start.y0["fist_pos"]
                 + jnp.array([0.0, 0.0, 0.01]) + 0.0 * tau)
    plus = Scenario("squat_fist", base.tasks + (extra,), duration=base.duration)
    params = plus.default_params()
    assert float(params.kp["fist_pos"][0]) == 50.0 and float(params.weight["fist_pos"][2]) == 2.0
    from safewbc_jax.control import terms as controller
    run = dict(tau=jnp.asarray(0.5), in_contact=jnp.ones(2))

    @jax.jit
    def both(q, v):
        out = []
        for sc in (base, plus):
            start = control_step.start_data(rm, sc, q)
            terms = controller.robot_terms(rm, sc, q, v)
            qp, _ = controller.build_qp(rm, sc, sc.default_params(), terms, q, v, run["tau"],
                                        start, run["in_contact"])
            out.append(qp)
        ya, jy, jdv = fist.evaluate(rm, q, v)
        return out, (ya, jy, jdv), control_step.start_data(rm, plus, q)

    (qa, qb), (ya, jy, jdv), start = both(q, v)
    yd = start.y0["fist_pos"] + jnp.array([0.0, 0.0, 0.01])
    ystar = -50.0 * (ya - yd) - 10.0 * (jy @ v)
    w = 2.0
    dp = np.asarray(qb.P - qa.P)[: rm.nv, : rm.nv]
    np.testing.assert_allclose(dp, 2 * w * np.asarray(jy.T @ jy), rtol=0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(qb.q - qa.q)[: rm.nv],
                               2 * w * np.asarray(jy.T @ (jdv - ystar)), rtol=0, atol=1e-9)
    assert float(jnp.abs(qb.P - qa.P)[rm.nv:].max()) == 0.0
    assert float(jnp.abs(qb.P - qa.P)[:rm.nv, rm.nv:].max()) == 0.0
    for f in ("A", "b", "G", "h", "lb", "ub"):
        np.testing.assert_array_equal(np.asarray(getattr(qa, f)), np.asarray(getattr(qb, f)))


def test_task_and_scenario_validation():
    o = outputs.CoMPosition()
    with pytest.raises(ValueError, match="exactly one of reference"):
        Task(o)
    with pytest.raises(ValueError, match="exactly one of reference"):
        Task(o, reference=lambda t, s: 0, planned=lambda *a: 0)
    t = Task(o, reference=lambda t, s: jnp.zeros(3))
    with pytest.raises(ValueError, match="task names repeated"):
        Scenario("x", (t, t))
