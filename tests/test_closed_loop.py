"""Closed-loop deployment runs in MuJoCo with the PIQP controller (short versions of the
paper's scenarios)."""

import json

import numpy as np
import pytest

from safewbc_jax.app.runner import run_scenario


@pytest.mark.slow
def test_short_squat(short_squat_deployment):
    m, out = short_squat_deployment          # conftest: 2 s of squat after a 1 s settle
    assert json.loads((out / "metrics.json").read_text()) == json.loads(json.dumps(m))
    assert not m["fell"]
    assert m["qp_failed"] == 0 and m["qp_solved"] + m["fallbacks"] == m["control_steps"]
    assert m["tracking_rms"]["com"] <= 0.01          # m, after the first 0.5 s of motion
    assert m["foot_slip_max"] <= 0.005               # m
    assert m["zmp_margin_min"] > 0.0
    assert m["torque_ratio_max"] <= 1.0
    assert m["eq_residual_max"] <= 1e-8              # the dynamics hold in every solution
    assert m["loop_residual_max"] < 0.002            # the simulator's rods stay closed
    for f in ("tracking_com.png", "tracking_torso.png", "tracking_arms.png", "log.npz"):
        assert (out / f).is_file()
    log = np.load(out / "log.npz")
    assert np.all(np.isfinite(log["u"]))


@pytest.mark.slow
@pytest.mark.parametrize("barrier", [True, False])
def test_arms_barrier_keeps_left_fist_safe(tmp_path, barrier, request):
    """The paper's arm task: both fists follow the same reference into the unsafe set;
    with the A-ECBF the left fist stays out of it (h >= -1 mm), the unguarded right one
    enters it; without the barrier both do. The run without it stops at tau = 6.2 s: the
    fists pass h = -1 cm at tau = 5.8 s and reach -4.1 cm by 6.2 s (measured), against
    -9.6 cm at their deepest (tau = 7.8 s), where the run with it goes on to."""
    if barrier:
        m = request.getfixturevalue("arms_deployment")[0]
    else:
        m = run_scenario("arms", duration=6.2, settle=1.0, out=tmp_path, barrier=False,
                         quiet=True)
    assert not m["fell"] and m["qp_failed"] == 0
    assert m["barrier_min"]["right_fist"] < -0.01
    if barrier:
        assert m["barrier_min"]["left_fist"] >= -0.001
    else:
        assert m["barrier_min"]["left_fist"] < -0.01


@pytest.mark.slow
def test_accumulated_metrics_match_the_logged_time_series(arms_deployment):
    """The metrics accumulated inside the control step and the plant loop
    (``metrics.control_accumulate`` / ``plant_accumulate``) against a direct evaluation
    of the run's logged time series: barrier minima, the ZMP margin over the motion,
    tracking RMS from TRACKING_SKIP_S on, the torque ratio, the QP counts, the loop
    residual. The same numbers summed in a different order: 1e-9 relative."""
    from safewbc_jax.control.metrics import TRACKING_SKIP_S

    m, out = arms_deployment
    log = np.load(out / "log.npz")
    tau = log["tau"]
    assert m["control_steps"] == tau.size and m["bad_measurements"] == 0
    for name, h in m["barrier_min"].items():
        assert h == pytest.approx(float(np.min(log[f"h_{name}"])), rel=1e-12)
    motion = tau >= 0
    assert m["zmp_margin_min"] == pytest.approx(float(np.nanmin(log["zmp_margin"][motion])),
                                                rel=1e-12)
    track = tau >= TRACKING_SKIP_S
    for name, val in m["tracking_rms"].items():
        err = log[f"y_{name}"][track] - log[f"yd_{name}"][track]
        assert val == pytest.approx(float(np.sqrt(np.mean(np.sum(err ** 2, axis=1)))), rel=1e-9)
        for i in range(err.shape[1]):
            assert m["tracking_rms_components"][f"{name}[{i}]"] == pytest.approx(
                float(np.sqrt(np.mean(err[:, i] ** 2))), rel=1e-9, abs=1e-15)
    from safewbc_jax.model import robot
    import mujoco
    from safewbc_jax.base import paths

    lim = np.asarray(robot.from_mujoco(mujoco.MjModel.from_xml_path(
        str(paths.controller_xml()))).torque_limit)
    assert m["torque_ratio_max"] == pytest.approx(float(np.max(np.abs(log["u"]) / lim)),
                                                  rel=1e-12)
    assert m["qp_solved"] == int(np.sum(log["fallback"] == "none"))
    assert m["qp_failed"] == int(np.sum(log["fallback"] == "failed"))
    assert m["loop_residual_max"] == pytest.approx(float(np.max(log["loop_residual"])),
                                                   rel=1e-12)
