"""The pieces of the shared control step that need no compile of the controller: the
measurement test and the fall test (numpy and jax.numpy give the same verdicts), the push
window, the plant metrics in single support, the forward-speed window, and the metric
finalization (empty accumulators are NaN, not +-inf)."""

import jax.numpy as jnp
import numpy as np
import pytest

from safewbc_jax import scenarios
from safewbc_jax.control import metrics
from safewbc_jax.control.step import (FALL_HEIGHT, MAX_RATE, MAX_SPEED, QUAT_TOL, fallen,
                                      state_ok)
from safewbc_jax.control.push import PUSH_AT, PUSH_FOR, Push, force_at


def _state():
    q = np.zeros(37)
    q[2], q[3] = 1.0, 1.0
    return q, np.zeros(36)


def _cases():
    q, v = _state()
    yield "good", q, v, True
    for name, edit, ok in (
            ("nan q", lambda q, v: q.__setitem__(12, np.nan), False),
            ("inf v", lambda q, v: v.__setitem__(7, np.inf), False),
            ("quaternion just inside", lambda q, v: q.__setitem__(3, 1.0 + 0.9 * QUAT_TOL), True),
            ("quaternion outside", lambda q, v: q.__setitem__(3, 1.0 + 1.1 * QUAT_TOL), False),
            ("rate at the bound", lambda q, v: v.__setitem__(20, -MAX_RATE), True),
            ("rate above", lambda q, v: v.__setitem__(20, MAX_RATE * 1.001), False),
            ("base rate above", lambda q, v: v.__setitem__(4, MAX_RATE * 1.001), False),
            ("base speed above", lambda q, v: v.__setitem__(slice(0, 3), MAX_SPEED / 1.7), False),
            ("base speed inside", lambda q, v: v.__setitem__(slice(0, 3), MAX_SPEED / 1.8), True)):
        q, v = _state()
        edit(q, v)
        yield name, q, v, ok


@pytest.mark.parametrize("name,q,v,ok", list(_cases()), ids=[c[0] for c in _cases()])
def test_state_ok_numpy_and_jax_agree(name, q, v, ok):
    assert bool(state_ok(q, v)) is ok
    assert bool(state_ok(jnp.asarray(q), jnp.asarray(v), jnp)) is ok


def test_fall_test():
    q, v = _state()
    assert not fallen(q, v) and not bool(fallen(jnp.asarray(q), jnp.asarray(v), jnp))
    q[2] = FALL_HEIGHT - 1e-6
    assert fallen(q, v) and bool(fallen(jnp.asarray(q), jnp.asarray(v), jnp))
    q, v = _state()
    v[30] = np.nan
    assert fallen(q, v)


def test_push_window_and_one_default():
    p = Push.single([0.0, -30.0, 0.0])
    assert (p.at, p.duration) == (PUSH_AT, PUSH_FOR)
    assert np.all(force_at(p, PUSH_AT - 1e-9) == 0)
    np.testing.assert_array_equal(force_at(p, PUSH_AT), [0.0, -30.0, 0.0])
    assert np.all(force_at(p, PUSH_AT + PUSH_FOR) == 0)       # [at, at + duration)
    from safewbc_jax.app import runner
    from safewbc_jax.sweeps import spec

    assert runner.PUSH_AT == spec.PUSH_DEFAULTS["at"] == PUSH_AT
    assert spec.PUSH_DEFAULTS["duration"] == PUSH_FOR


class _Rec:
    def __init__(self, stance, stance0, tau=0.5):
        self.stance, self.stance0, self.tau = np.float64(stance), np.asarray(stance0), tau


def test_plant_slip_is_the_stance_soles_in_single_support():
    """Double support: the larger of both soles' displacements from the start; single
    support: the stance sole's from where its step began; clearance only in single
    support; a leg contact that lasts three steps is one collision."""
    soles0 = np.array([[0.0, 0.1], [0.0, -0.1]])
    soles = np.array([[0.03, 0.14, 0.0], [0.20, -0.1, 0.05]])   # left moved 5 cm
    acc = metrics.plant_init()
    acc = metrics.plant_accumulate(acc, True, _Rec(0, np.zeros(3)), soles, soles0, 1e-4, False)
    assert acc.slip_max == pytest.approx(0.2)                 # the right sole, 20 cm
    assert acc.clearance_min == np.inf
    acc = metrics.plant_init()
    for legs in (True, True, True, False):
        acc = metrics.plant_accumulate(acc, True, _Rec(1, [0.0, 0.1, 0.0]), soles, soles0,
                                       2e-4, legs)
    assert acc.slip_max == pytest.approx(0.05)                # the left (stance) sole
    assert acc.clearance_min == pytest.approx(0.24)
    assert (acc.leg_collisions, acc.leg_contact_steps) == (1, 3)
    assert acc.loop_max == pytest.approx(2e-4)
    frozen = metrics.plant_accumulate(acc, False, _Rec(1, [9.0, 9.0, 0.0]), soles, soles0,
                                      1.0, True)
    assert frozen == acc


@pytest.mark.parametrize("n_steps,settle,dt", [(3400, 1.2, 1e-3), (1000, 0.5, 1e-3),
                                               (9501, 1.5, 1e-3), (50, 0.1, 5e-3)])
def test_half_time_is_the_first_step_of_the_second_half(n_steps, settle, dt):
    t = np.arange(n_steps) * dt
    tw = t[t - settle >= 0]
    i0 = np.searchsorted(t, tw[0] + 0.5 * (tw[-1] - tw[0]))
    th = metrics.half_time(n_steps, settle, dt)
    assert np.sum(t < th) == i0          # the step at index i0 is the first with t >= th
    assert metrics.half_time(10, 1.0, 1e-3) == metrics.NO_HALF


def test_finalize_of_an_empty_run_is_nan_not_inf():
    sc = scenarios.get_scenario("arms")
    flat = metrics.finalize(sc, metrics.control_init(sc), metrics.plant_init(), False)
    for key in ("zmp_margin_min", "eq_residual_max", "tracking_rms.com",
                "barrier_min.left_fist", "torso_pitch_max_reached"):
        assert np.isnan(flat[key]), key
    assert flat["qp_solved"] == 0 and flat["bad_measurements"] == 0


def test_latency_and_deadline_misses():
    """metrics.latency on made-up step times: percentiles of t_qp + t_solve after the
    first LATENCY_SKIP steps, and the steps over the control period counted."""
    k = metrics.LATENCY_SKIP
    t_qp = np.concatenate([np.full(k, 5e4), np.full(100, 400.0)])      # warm-up left out
    t_solve = np.concatenate([np.zeros(k), np.full(97, 200.0), [700.0, 900.0, 601.0]])
    out = metrics.latency(t_qp, t_solve, 1e-3)
    assert out["step_latency_us"]["p50"] == 600.0 and out["step_latency_us"]["max"] == 1300.0
    assert out["deadline_misses"] == {"period_us": 1000.0, "count": 3, "rate": 0.03}
    assert "deadline_misses" not in metrics.latency(t_qp, t_solve)
