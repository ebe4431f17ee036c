"""Closed-loop deployment runs in MuJoCo with the PIQP controller (short versions of the
paper's scenarios)."""

import json

import numpy as np
import pytest

from safewbc_jax.runner import run_scenario


@pytest.mark.slow
def test_short_squat(tmp_path):
    m = run_scenario("squat", duration=1.5, settle=1.0, out=tmp_path, quiet=True)
    assert json.loads((tmp_path / "metrics.json").read_text()) == json.loads(json.dumps(m))
    assert not m["fell"]
    assert m["qp_failed"] == 0 and m["qp_solved"] + m["fallbacks"] == m["control_steps"]
    assert m["tracking_rms"]["com"] <= 0.01          # m, after the first 0.5 s of motion
    assert m["foot_slip_max"] <= 0.005               # m
    assert m["zmp_margin_min"] > 0.0
    assert m["torque_ratio_max"] <= 1.0
    assert m["eq_residual_max"] <= 1e-8              # the dynamics hold in every solution
    assert m["loop_residual_max"] < 0.002            # the simulator's rods stay closed
    for f in ("tracking_com.png", "tracking_torso.png", "tracking_arms.png", "log.npz"):
        assert (tmp_path / f).is_file()
    log = np.load(tmp_path / "log.npz")
    assert np.all(np.isfinite(log["u"]))


@pytest.mark.slow
@pytest.mark.parametrize("barrier", [True, False])
def test_arms_barrier_keeps_left_fist_safe(tmp_path, barrier, request):
    """The paper's arm task: both fists follow the same reference into the unsafe set;
    with the A-ECBF the left fist stays out of it (h >= -1 mm), the unguarded right one
    enters it; without the barrier both do."""
    if barrier:
        m = request.getfixturevalue("arms_deployment")[0]
    else:
        m = run_scenario("arms", duration=7.0, settle=1.0, out=tmp_path, barrier=False,
                         quiet=True)
    assert not m["fell"] and m["qp_failed"] == 0
    assert m["barrier_min"]["right_fist"] < -0.01
    if barrier:
        assert m["barrier_min"]["left_fist"] >= -0.001
    else:
        assert m["barrier_min"]["left_fist"] < -0.01
