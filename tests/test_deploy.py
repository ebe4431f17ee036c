"""The deployment API (safewbc_jax.deploy.controller): the motor map against the simulator's, start /
step / reset and the counters, refused measurements, and the README example as written.

One compiled squat controller (module fixture) serves most tests; a walking one checks that
a refused measurement does not advance the gait."""

import re
from pathlib import Path

import numpy as np
import pytest

from safewbc_jax.control import barriers
from safewbc_jax.control.step import Measurement, state_ok
from safewbc_jax.deploy import checks as deploy
from safewbc_jax.deploy.controller import Controller
from safewbc_jax.deploy.motors import MotorMap
from safewbc_jax.model import statemap
from safewbc_jax.solvers.problem import FIELDS
from safewbc_jax.solvers.result import failed
from safewbc_jax.solvers.status import SolveStatus

README = Path(__file__).resolve().parent.parent / "README.md"


@pytest.fixture(scope="module")
def squat(stand):
    ctl = Controller("squat")
    ctl.start(*stand)
    return ctl


def _within_limits(ctl, cmd):
    assert np.all(np.isfinite(cmd.u)) and np.all(np.isfinite(cmd.motor))
    assert np.all(np.abs(cmd.motor) <= ctl.motors.motor_limit)
    assert np.all(np.abs(cmd.u) <= np.asarray(ctl.model.torque_limit) * (1 + 1e-9))


# -- no compile --------------------------------------------------------------------------

def test_motor_map_matches_the_simulators_state_map(sim_mj, ctrl_mj):
    """Built from the controller model and the published figures, the motor map gives the
    simulator's commands: to 1e-12 within the limits (the same division). Beyond them it
    clips to the published motor limits; the simulator's ctrlrange is the same figure
    printed to 10 digits (13.557993625 -> 13.55799362), hence 1e-9 relative there."""
    from safewbc_jax.model import modelgen

    mm = MotorMap.build(ctrl_mj)
    acts = modelgen.load_params()["actuators"]
    assert mm.names == tuple(a["name"] for a in acts)
    assert sorted(mm.u_index.tolist()) == list(range(ctrl_mj.nu))
    np.testing.assert_allclose(mm.gear * mm.motor_limit, mm.joint_limit, rtol=1e-12)
    sm = statemap.build_state_map(sim_mj, ctrl_mj)
    sim_order = [sim_mj.actuator(n).id for n in mm.names]
    lo, hi = sim_mj.actuator_ctrlrange[:, 0], sim_mj.actuator_ctrlrange[:, 1]
    rng = np.random.default_rng(0)
    u_lim = mm.joint_limit[np.argsort(mm.u_index)]    # controller actuator order
    u = rng.uniform(-0.999, 0.999, (500, ctrl_mj.nu)) * u_lim
    np.testing.assert_allclose(mm.to_motor(u), sm.to_ctrl(u)[:, sim_order], rtol=0, atol=1e-12)
    u = rng.uniform(-2, 2, (500, ctrl_mj.nu)) * u_lim   # about half of them clipped
    got, want = mm.to_motor(u), np.clip(sm.to_ctrl(u), lo, hi)[:, sim_order]
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=0)
    clipped = np.abs(u[:, mm.u_index]) > mm.joint_limit
    assert 0.3 < clipped.mean() < 0.7
    np.testing.assert_array_equal(np.abs(got[clipped]), np.broadcast_to(mm.motor_limit,
                                                                         got.shape)[clipped])


def test_motor_map_refuses_figures_that_disagree_with_the_model(ctrl_mj):
    from safewbc_jax.model import modelgen

    figs = modelgen.load_params()
    figs["actuators"][3] = {**figs["actuators"][3], "gear": 17.0}
    with pytest.raises(ValueError, match="left-knee.*gear"):
        MotorMap.build(ctrl_mj, figs)


def test_check_state_names_the_reason(stand, ctrl_mj):
    q, v = stand
    sizes = (ctrl_mj.nq, ctrl_mj.nv)                   # the controller model's
    assert deploy.check_state(q, v, *sizes) == "ok"
    assert "shape" in deploy.check_state(q[:36], v, *sizes)
    qn = q.copy()
    qn[3:7] *= 1 + 2 * deploy.QUAT_TOL
    assert "quaternion" in deploy.check_state(qn, v, *sizes)
    qn[3:7] = q[3:7] * (1 + 0.5 * deploy.QUAT_TOL)     # inside the tolerance
    assert deploy.check_state(qn, v, *sizes) == "ok"
    vb = v.copy()
    vb[0] = 1.1 * deploy.MAX_SPEED
    assert "base speed" in deploy.check_state(q, vb, *sizes)
    vb = v.copy()
    vb[20] = -0.99 * deploy.MAX_RATE
    assert deploy.check_state(q, vb, *sizes) == "ok"


def test_check_state_refuses_exactly_what_the_step_refuses(stand):
    """The host's reason and the jitted step's test are one definition (``state_tests``):
    "ok" exactly where ``state_ok`` holds, also within a few ulps of each bound, where a
    test written twice (``norm(v) > MAX_SPEED`` against ``sum(v**2) <= MAX_SPEED**2``)
    disagrees on about one state in ten (measured: 16,894 of 200,000 speeds)."""
    q0, v0 = stand
    rng = np.random.default_rng(3)
    ulp = np.finfo(float).eps
    seen = set()
    for i in range(2000):
        q, v = q0.copy(), v0.copy()
        kind, k = i % 4, int(rng.integers(-4, 5))
        if kind == 0:                                # the quaternion's norm at 1 + QUAT_TOL
            d = rng.normal(size=4)
            q[3:7] = d / np.linalg.norm(d) * (1 + deploy.QUAT_TOL * (1 + k * 1000 * ulp))
        elif kind == 1:                              # the base speed at MAX_SPEED
            d = rng.normal(size=3)
            v[:3] = d / np.linalg.norm(d) * deploy.MAX_SPEED * (1 + k * ulp)
        elif kind == 2:                              # one rate at MAX_RATE
            v[3 + rng.integers(v.size - 3)] = deploy.MAX_RATE * (1 + k * ulp)
        else:                                        # a NaN or inf somewhere
            (q if rng.random() < 0.5 else v)[rng.integers(30)] = rng.choice([np.nan, np.inf])
        ok = bool(state_ok(q, v))
        reason = deploy.check_state(q, v, q.size, v.size)
        assert (reason == "ok") is ok, (i, reason)
        seen.add((kind, ok))
    assert seen >= {(0, True), (0, False), (1, True), (1, False), (2, True), (2, False), (3, False)}


def test_controller_refuses_bad_options_and_start_states(stand):
    with pytest.raises(ValueError, match="settle"):
        Controller("squat", settle=0.5)
    with pytest.raises(ValueError, match="speed"):
        Controller("walk", speed=2.0)
    with pytest.raises(ValueError, match="solver"):
        Controller("squat", solver="osqp")
    with pytest.raises(ValueError, match=r"solve\(qp, checks=None\)"):
        Controller("squat", solver=object())       # no solve(): not a solvers.host solver
    ctl = Controller("squat")
    with pytest.raises(RuntimeError, match="start"):
        ctl.step(Measurement(*stand, 0.0))
    q = stand[0].copy()
    q[5] = np.nan
    with pytest.raises(ValueError, match="start state refused: q not finite"):
        ctl.start(q, stand[1])


def test_start_checks_theorem_1_before_compiling(stand):
    """The paper's arm threshold 0.195 m makes the start unsafe in this model's base frame
    (README): start refuses it naming h(x0), before anything compiles."""
    ctl = Controller("arms")
    ctl.params = ctl.params.replace(threshold={**ctl.params.threshold, "left_fist": 0.195})
    with pytest.raises(barriers.PoleError, match="left_fist"):
        ctl.start(*stand)
    assert ctl.compile_s is None


# -- the compiled squat controller ---------------------------------------------------------

@pytest.mark.slow
def test_start_step_reset_and_counters(squat, stand):
    ctl = squat
    ctl.reset()
    assert ctl.compile_s > 0
    assert (ctl.steps, ctl.qp_failed, ctl.fallbacks, ctl.bad_measurements) == (0, 0, 0, 0)
    cmds = [ctl.step(Measurement(*stand, t=10.0 + k * ctl.control_dt)) for k in range(5)]
    for c in cmds:
        _within_limits(ctl, c)
        assert (c.solve_status, c.fallback, c.measurement) == (SolveStatus.SOLVED, "none", "ok")
        assert c.latency_us > 0
        np.testing.assert_array_equal(c.motor, ctl.motors.to_motor(c.u))
    assert np.any(cmds[0].u != 0)
    assert ctl.record.tau == pytest.approx(4 * ctl.control_dt - ctl.scenario.settle)
    assert (ctl.steps, ctl.qp_failed, ctl.fallbacks, ctl.bad_measurements) == (5, 0, 0, 0)
    ctl.reset()
    assert (ctl.steps, ctl.qp_failed, ctl.fallbacks, ctl.bad_measurements) == (0, 0, 0, 0)
    # back to the state after start: the clock restarts, PIQP is set up afresh
    again = [ctl.step(Measurement(*stand, t=10.0 + k * ctl.control_dt)) for k in range(2)]
    for a, b in zip(again, cmds):
        np.testing.assert_array_equal(a.u, b.u)


def _bad(stand, case):
    q, v = stand[0].copy(), stand[1].copy()
    f = np.array([230.0, 240.0])
    if case == "nan_q":
        q[12] = np.nan
    elif case == "inf_v":
        v[7] = np.inf
    elif case == "quaternion":
        q[3:7] *= 1.01
    elif case == "huge_velocity":
        v[14] = 3000.0
    elif case == "nan_sole_force":
        f[1] = np.nan
    return q, v, f


REASONS = {"nan_q": "q not finite", "inf_v": "v not finite", "quaternion": "not unit",
           "huge_velocity": "rad/s", "nan_sole_force": "sole_force"}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(REASONS))
def test_bad_measurement_holds_the_last_good_torque(squat, stand, case):
    """Before any good step the command is zero; after one, the last good torque; either
    way finite and within the motor limits, "held", the reason named, counted; the
    clock does not advance (a good measurement at the same t is then accepted)."""
    ctl = squat
    ctl.reset()
    q, v, f = _bad(stand, case)
    c0 = ctl.step(Measurement(q, v, 0.0, f))
    _within_limits(ctl, c0)
    assert np.all(c0.u == 0) and np.all(c0.motor == 0)
    assert (c0.fallback, c0.solve_status) == ("held", None)
    assert REASONS[case] in c0.measurement, c0.measurement
    rec = ctl.record     # the step refused it itself (sole forces aside, all enter the step)
    assert rec is not None and not rec.step.ok and rec.x is None and ctl.bad_measurements == 1
    np.testing.assert_array_equal(rec.step.u, c0.u)
    assert int(ctl.tally.acc.bad) == 1
    good = ctl.step(Measurement(*stand, 0.0, np.array([230.0, 240.0])))
    assert good.measurement == "ok" and np.any(good.u != 0)
    c1 = ctl.step(Measurement(q, v, ctl.control_dt, f))
    _within_limits(ctl, c1)
    np.testing.assert_array_equal(c1.u, good.u)
    np.testing.assert_array_equal(c1.motor, good.motor)
    assert c1.fallback == "held" and REASONS[case] in c1.measurement
    assert (ctl.bad_measurements, ctl.steps, ctl.qp_failed) == (2, 3, 0)
    nxt = ctl.step(Measurement(*stand, ctl.control_dt))
    assert nxt.measurement == "ok"
    assert ctl.record.tau == pytest.approx(ctl.control_dt - ctl.scenario.settle)


@pytest.mark.slow
def test_a_refused_step_leaves_the_last_good_qp(squat, stand):
    """``last_qp`` is the full QP the last good step solved, computed again from its state
    and measurement (the step writes only the reduced QP and the equality rows): its
    elimination (numpy's), solved by a PIQP of the controller's settings, gives the step's
    X, and X's equality residual on it is the step's record. A refused step (whose prepare
    runs too) leaves it the good step's, whatever the refused measurement's time or
    state."""
    from safewbc_jax.solvers import reduce

    ctl = squat
    ctl.reset()
    t_late = ctl.scenario.settle + 1.0
    ctl.step(Measurement(*stand, 0.0))               # the clock starts
    ctl.step(Measurement(*stand, t_late))
    good = ctl.last_qp()
    X = ctl.record.solve.x
    red, rmap = reduce.eliminate_equalities_np(good)
    x, status, _ = ctl.lane.sibling().solver.solve_nominal(red)
    assert status == SolveStatus.SOLVED
    # PIQP stops within 1e-8 of the KKT conditions on QPs that differ by rounding (C's
    # and XLA's): the two answers differ by ~1e-5 in the contact forces (~30 N)
    np.testing.assert_allclose(reduce.expand(x, rmap), X, rtol=0, atol=1e-4)
    # the same products on A from C and from XLA: rounding of the ~1e-11 residual alone
    assert abs(np.abs(good.A @ X - good.b).max() - ctl.record.solve.eq_residual) < 1e-12
    q, v, f = _bad(stand, "nan_q")
    for meas in (Measurement(*stand, t_late - 0.5),           # refused for its time
                 Measurement(q, v, t_late + 0.5, f)):         # refused for its state
        cmd = ctl.step(meas)
        assert cmd.fallback == "held", cmd
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(ctl.last_qp(), name), getattr(good, name))


@pytest.mark.slow
def test_time_that_does_not_advance_is_refused(squat, stand):
    ctl = squat
    ctl.reset()
    ctl.step(Measurement(*stand, 1.0))
    c = ctl.step(Measurement(*stand, 1.0))
    assert c.fallback == "held" and "does not advance" in c.measurement
    assert ctl.bad_measurements == 1


@pytest.mark.slow
def test_bad_measurement_does_not_advance_the_gait(stand):
    """Walking: the gait leaves double support at the first good step with tau >= 0 (as
    in the MuJoCo loop, touchdown and timing from the measurement that ends the step);
    a refused measurement (sole forces missing, or NaN) leaves it where it is."""
    from safewbc_jax.control.walking import BOTH, LEFT

    ctl = Controller("walk", settle=1.0)
    ctl.start(*stand)
    f = np.array([235.0, 235.0])
    n = int(round(ctl.scenario.settle / ctl.control_dt))
    for k in range(n + 1):     # through tau = 0: the gait advances at the next good step
        ctl.step(Measurement(*stand, k * ctl.control_dt, f))
    assert ctl.gait.stance == BOTH and ctl.record.tau == pytest.approx(0.0, abs=1e-12)
    for bad in (None, np.array([np.nan, 235.0])):
        c = ctl.step(Measurement(*stand, (n + 1) * ctl.control_dt, bad))
        _within_limits(ctl, c)
        assert c.fallback == "held" and "sole_force" in c.measurement
        assert ctl.gait.stance == BOTH
    assert ctl.bad_measurements == 2
    c = ctl.step(Measurement(*stand, (n + 1) * ctl.control_dt, f))
    assert c.measurement == "ok" and ctl.gait.stance == LEFT and ctl.gait.tau_step == 0.0
    _within_limits(ctl, c)
    ctl.reset()
    assert ctl.gait.stance == BOTH and ctl.steps == 0


# -- the README example ----------------------------------------------------------------------

def readme_example() -> str:
    text = README.read_text()
    section = text[text.index("## Deployment API"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


@pytest.mark.slow
def test_readme_example_runs_as_written(capsys):
    ns = {}
    exec(compile(readme_example(), "README.md (Deployment API)", "exec"), ns)
    ctl, cmd, d = ns["ctl"], ns["cmd"], ns["d"]
    assert ctl.steps == 1000 and ctl.qp_failed == 0 and ctl.bad_measurements == 0
    assert cmd.measurement == "ok" and cmd.fallback == "none"
    _within_limits(ctl, cmd)
    assert d.qpos[2] > 0.8      # standing
    assert "failed QPs" in capsys.readouterr().out


def test_motor_map_needs_only_the_installed_package_files(monkeypatch):
    """An installed package (pip install .) has no repository around it: the motor map
    reads the figures shipped in safewbc_jax/models, not modelgen's search for the
    figures to regenerate the models from (which found nothing there and broke
    `safewbc run` after a non-editable install)."""
    from safewbc_jax.base import paths
    from safewbc_jax.model import modelgen

    def nowhere(*a, **k):
        raise FileNotFoundError("digit_v3_parameters.json not found (test)")

    monkeypatch.setattr(modelgen, "find_params_file", nowhere)
    monkeypatch.setattr(modelgen, "load_params", nowhere)
    mm = MotorMap.build()
    assert len(mm.names) == 20 and paths.figures_json().is_file()


def test_installed_package_finds_its_files(tmp_path):
    """Outside the repository (cwd elsewhere: the installed package, as after the README's
    'pip install .'), the deployment pieces find the models and the figures."""
    import subprocess
    import sys

    code = ("import safewbc_jax, json; from safewbc_jax import scenarios; "
            "from safewbc_jax.base import paths; from safewbc_jax.deploy import controller; "
            "mm = controller.MotorMap.build(); scenarios.get_scenario('walk'); "
            "print(json.dumps([safewbc_jax.__file__, str(paths.figures_json()), len(mm.names)]))")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True)
    if "No module named 'safewbc_jax'" in out.stderr:
        pytest.skip("safewbc_jax is not installed in this environment")
    assert out.returncode == 0, out.stderr[-2000:]
    import json

    pkg, figures, n = json.loads(out.stdout.strip().splitlines()[-1])
    assert n == 20 and Path(figures).is_file(), (pkg, figures)


# -- the control step's own refusal (the batched path's; the host check comes first here) --

@pytest.mark.slow
@pytest.mark.parametrize("case", list(REASONS) + ["stale_time"])
def test_control_step_refuses_in_the_graph(squat, stand, case):
    """The jitted control step refuses a bad measurement by itself (the batched path has no
    host check before it): after one good step, a bad measurement fed straight to the
    controller's compiled ``control_step.prepare`` / ``conclude`` gives ok False, the last
    good torque (finite, within the motor limits) even when the solver hands back a finite
    x, one count in ``bad``, and leaves the clock and the last good state where they
    were."""
    ctl = squat
    ctl.reset()
    good = ctl.step(Measurement(*stand, 0.0, np.zeros(2)))
    ctl.flush()
    cs, lay = ctl.compiled, ctl.compiled.layouts
    prepare, conclude = cs.prepare, cs.conclude
    fixed = cs.pack_fixed(ctl.params, ctl.start_data, ctl.run_values)
    state, tally0 = lay.state.pack(ctl.state), lay.tally.pack(ctl.tally)
    st0 = ctl.state
    if case == "stale_time":   # a good state at the time of the last step
        (q, v), f, t = stand, np.zeros(2), 0.0
    else:
        (q, v, f), t = _bad(stand, case), ctl.control_dt
    meas = cs.flat_measurement(Measurement(q, v, t, f))
    st_flat, prep, _ = prepare(fixed, state, meas)
    st1 = lay.state.unpack(np.asarray(st_flat))
    assert float(st1.prev_t) == float(st0.prev_t) == 0.0 and float(st1.t0) == 0.0
    np.testing.assert_array_equal(st1.last_q, st0.last_q)
    np.testing.assert_array_equal(st1.last_v, st0.last_v)
    n = ctl.last_qp().P.shape[0]
    for x in (np.full(n, np.nan), np.ones(n)):   # a failed solve, a finite wrong answer
        # as the solver's SolveResult (status SOLVED, fallback NONE), flat for the jit
        sol = cs.flat_solution(failed(n)._replace(x=x, status=0, fallback=0, iterations=3,
                                                   eq_residual=0.0))
        tally_flat, packed = conclude(fixed, tally0, prep, sol)
        tally = lay.tally.unpack(np.asarray(tally_flat))
        rec = cs.unpack_record(packed)[0]
        assert not bool(rec.ok)
        np.testing.assert_array_equal(rec.u, good.u)
        np.testing.assert_array_equal(tally.last_u, good.u)
        motor = ctl.motors.to_motor(rec.u)
        assert np.all(np.isfinite(motor)) and np.all(np.abs(motor) <= ctl.motors.motor_limit)
        assert int(tally.acc.bad) == 1 and int(tally.acc.steps) == 1
