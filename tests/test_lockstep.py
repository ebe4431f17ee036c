"""``sim.lockstep``: rollouts side by side through the vmapped deployed step, held to the
single-robot deployment loop (``sim.mujoco_loop.rollout``) they stand in for in the
``mujoco`` sweep engine."""

from __future__ import annotations

import numpy as np
import pytest

import safewbc_jax
from safewbc_jax.sim.lockstep import RolloutTask

safewbc_jax.enable_x64()

N_STEPS = 1150         # 1 s standing (the reference blend), 0.15 s of the arms motion, pushed


_LOOPS: dict = {}


def _loop(engine):
    """(leader Controller, SimRobot, Lockstep of width 3) on ``engine``, made once."""
    from safewbc_jax.deploy.codegen.build import works

    if engine == "c" and not works():
        pytest.skip("no working C compiler here: the C lanes cannot be built")
    if engine not in _LOOPS:
        from safewbc_jax import scenarios
        from safewbc_jax.deploy.controller import Controller
        from safewbc_jax.sim.lockstep import Lockstep
        from safewbc_jax.sim.mujoco_loop import SimRobot

        sc = scenarios.get_scenario("arms", True)
        ctl = Controller(sc, sc.default_params(), 1e-3, barrier=True, settle=1.0,
                         duration=0.15, engine=engine)
        sim = SimRobot(ctl.motors.names, 1e-3)
        sim.reset()
        ctl.start(*sim.sm.to_controller(sim.d.qpos, sim.d.qvel))
        lock = Lockstep(ctl, sim, 3)
        lock.warm_up()
        _LOOPS[engine] = ctl, sim, lock
    return _LOOPS[engine]


@pytest.fixture(scope="module", params=["c", "xla"])
def loop(request):
    """Both engines' lanes: the generated C lane by lane (``CLanes``), XLA vmapped
    (``Lanes``)."""
    return _loop(request.param)


@pytest.fixture(scope="module")
def c_loop():
    return _loop("c")


def _task(ctl, sim, seed, p1, push_y):
    import dataclasses

    from safewbc_jax.control.push import Push

    poles = {**ctl.params.poles, "left_fist": np.array([p1, 10.0])}
    params = dataclasses.replace(ctl.params, poles=poles)
    dv = 0.05 * np.random.default_rng(seed).standard_normal(sim.ms.nv)
    return RolloutTask(params, Push.single(np.array([0.0, push_y, 0.0]), 0.05, 0.05), dv)


def _single(ctl, sim, task):
    from safewbc_jax.control import metrics
    from safewbc_jax.sim.mujoco_loop import rollout

    sim.reset(task[2])
    ctl.restart(*sim.sm.to_controller(sim.d.qpos, sim.d.qvel), task[0])
    fell, fell_step, plant = rollout(sim, ctl, N_STEPS, task[1])
    return fell, fell_step, metrics.finalize(ctl.scenario, ctl.tally.acc, plant, fell, ctl.state.gait)


@pytest.mark.slow
def test_lockstep_lanes_are_the_deployment_loop(loop):
    """Each lane against the deployment loop run alone on the same rollout: the same
    falls and counts exactly; every metric the same floats on the C engine (a lane runs
    the same generated functions on the same inputs as one robot), within 1e-6 on XLA
    (the vmapped kernels round differently from the single-robot ones, ~1e-16 relative,
    and the closed loop carries that; measured <= 5e-7 over 400-1000 steps, barrier
    minima <= 1e-9 m). A lane whose start state is refused (a NaN in its velocity
    perturbation) fails alone with the reason, the others run."""
    ctl, sim, lock = loop
    atol = 0.0 if ctl.compiled.engine == "c" else 1e-6
    bad = _task(ctl, sim, 2, 8.0, 0.0)
    bad[2][5] = np.nan
    tasks = [_task(ctl, sim, 1, 8.0, 40.0), bad, _task(ctl, sim, 3, 30.0, -60.0)]
    got = lock.run(tasks, N_STEPS)
    assert got[1].columns is None and "start state refused" in got[1].error, got[1]
    assert "not finite" in got[1].error
    for k in (0, 2):
        fell, fell_step, ref = _single(ctl, sim, tasks[k])
        cols, lfell, lstep, error = got[k]
        assert cols is not None and not error and (lfell, lstep) == (fell, fell_step)
        assert sorted(cols) == sorted(ref)
        for name in ref:
            a, b = np.asarray(ref[name]), np.asarray(cols[name])
            if a.dtype.kind in "biu":
                assert a == b, name
            else:
                np.testing.assert_allclose(b, a, rtol=0, atol=atol, err_msg=name)
        assert int(cols["control_steps"]) == N_STEPS and int(cols["qp_failed"]) == 0


@pytest.mark.slow
def test_lockstep_lane_does_not_depend_on_its_neighbours(loop):
    """The same rollout beside other rollouts (or none) gives the same floats: what lets
    the ``mujoco`` engine's table be the same for any worker count."""
    ctl, sim, lock = loop
    a = _task(ctl, sim, 4, 12.0, 30.0)
    one = lock.run([a, _task(ctl, sim, 5, 4.0, -50.0), _task(ctl, sim, 6, 50.0, 0.0)], 200)
    two = lock.run([a], 200)
    assert one[0].columns is not None and two[0].columns is not None
    for name, v in one[0].columns.items():
        np.testing.assert_array_equal(two[0].columns[name], v, err_msg=name)


@pytest.mark.slow
def test_finish_of_lanes_is_finish_lane_by_lane(c_loop):
    """``CompiledStep.finish`` (the lockstep's host side: PIQP per lane, the acceptance,
    expansion, held torque and motor map for all lanes at once) against the same with one
    lane at a time (what one robot's ``step`` runs), on the same rows of the vmapped
    prepare, with fresh solvers on both sides, after a first good step that gives each lane
    a torque to hold: a lane solved as posed, one whose QP needs the relaxed QP (a soft row
    no torque can meet), one that fails (a hard row no torque can meet: the first step's
    torque held) and one whose measurement was refused. Commands, counters, statuses and
    the torque each lane holds next exactly; the solve records within 1e-12 relative /
    1e-9 absolute (X = x0 + N u is one batched product against one per lane: BLAS may
    round differently; the torques are N's identity block and come out exactly)."""
    ctl, sim, _ = c_loop
    cs = ctl.compiled
    sim.reset()
    ctl.restart(*sim.sm.to_controller(sim.d.qpos, sim.d.qvel))
    meas = sim.sense(0.0)[0]
    rows = lambda a: np.stack([np.asarray(a)] * 3)  # noqa: E731
    fixed, state, _ = ctl.lane_start(*ctl.start_state)
    _, prep, packed = cs.prepare(fixed, state, cs.flat_measurement(meas))
    prep, packed = rows(prep), rows(packed)                 # three lanes' rows, writable
    first = [0, 0, 0, 0]
    first_prep, first_packed = prep[first], packed[first]  # the good rows, before the edit
    _, red, _, checks = cs.unpack_qp(packed)               # views into packed
    soft, hard = np.flatnonzero(red.soft[0] > 0), np.flatnonzero(red.soft[0] == 0)
    for lane, row in ((1, soft[0]), (2, hard[0])):          # 0 u <= -1000
        red.G[lane, row] = checks.rows[lane, row] = 0.0
        red.h[lane, row] = checks.rhs[lane, row] = -1e3
    pick = [0, 1, 2, 0]
    prep, packed = prep[pick], packed[pick]
    reasons = ["ok", "ok", "ok", "t = 0.0 does not advance (last step at 0.0)"]
    batch, single = [ctl.lane.sibling() for _ in pick], [ctl.lane.sibling() for _ in pick]
    held, _ = cs.finish(batch, first_prep, first_packed, ["ok"] * 4, [-1e-3] * 4, 0.0)
    for i, lane in enumerate(single):
        cs.finish([lane], first_prep[i:i + 1], first_packed[i:i + 1], ["ok"], [-1e-3], 0.0)
    cmds, sols = cs.finish(batch, prep, packed, reasons, [0.0] * 4, 0.0)
    assert [c.fallback for c in cmds] == ["none", "relaxed", "failed", "held"]
    for i, lane in enumerate(single):
        want, want_sol = cs.finish([lane], prep[i:i + 1], packed[i:i + 1], [reasons[i]],
                                   [0.0], 0.0)
        want, got = want[0], cmds[i]
        assert (got.solve_status, got.fallback, got.measurement) == \
            (want.solve_status, want.fallback, want.measurement)
        np.testing.assert_array_equal(got.u, want.u)
        np.testing.assert_array_equal(got.motor, want.motor)
        np.testing.assert_allclose(sols[i], want_sol[0], rtol=1e-12, atol=1e-9)
        b = batch[i]
        assert (b.steps, b.qp_failed, b.fallbacks) == (lane.steps, lane.qp_failed, lane.fallbacks)
    np.testing.assert_array_equal(cmds[2].u, held[2].u)        # the first step's torque
    np.testing.assert_array_equal(cmds[3].u, held[3].u)
    assert np.abs(held[2].u).max() > 1.0                       # a real torque, not zeros
    # the torque each lane holds next (a refused measurement), batch against one by one
    refused = ["refused"] * 4
    nxt, _ = cs.finish(batch, prep, packed, refused, [1e-3] * 4, 0.0)
    for i, lane in enumerate(single):
        one, _ = cs.finish([lane], prep[i:i + 1], packed[i:i + 1], refused[:1], [1e-3], 0.0)
        np.testing.assert_array_equal(nxt[i].u, one[0].u)

    # one robot's step on the C engine (``CompiledStep.solve_one``: PIQP, then the
    # generated acceptance in one call, and the numpy path where it does not accept),
    # with the same solver history: the same commands, counters and solve records (the
    # acceptance's sums in C against numpy's: the tolerance above)
    assert cs.fast(ctl.lane)
    fast = [ctl.lane.sibling() for _ in pick]

    def solve_one(lane, rows_, i, t):
        lane.views, lane.fast = cs.unpack_qp(rows_[i:i + 1]), None
        return cs.solve_one(lane, rows_[i], t, 0.0, 0.0)

    for i, lane in enumerate(fast):
        solve_one(lane, first_packed, i, -1e-3)
    for i in range(3):                          # solved as posed, relaxed, failed
        got, got_sol, x = solve_one(fast[i], packed, i, 0.0)
        want = cmds[i]
        assert (got.solve_status, got.fallback, got.measurement) == \
            (want.solve_status, want.fallback, want.measurement)
        np.testing.assert_allclose(got.u, want.u, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(got.motor, want.motor, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(got_sol, sols[i], rtol=1e-12, atol=1e-9)
        assert (x is None) == (want.fallback == "failed")
        b, lane = batch[i], fast[i]
        assert (b.qp_failed, b.fallbacks) == (lane.qp_failed, lane.fallbacks)
        np.testing.assert_array_equal(lane.last_u, b.last_u)

    # a user's solver of the solvers.host protocol with ``solve`` alone (no solve_lanes,
    # lane or reset): one ``solve`` per lane (``solvers.host.solve_lanes``), with PIQP's
    # outcome
    from safewbc_jax.deploy.compiled import LaneState
    from safewbc_jax.solvers import host
    from safewbc_jax.solvers.piqp_path import REDUCED_QP_SETTINGS, PiqpSolver

    class OnlySolve:
        def __init__(self):
            self.inner, self.calls = PiqpSolver(nominal_settings=REDUCED_QP_SETTINGS), 0

        def solve(self, qp, checks=None):
            self.calls += 1
            return self.inner.solve(qp, checks=checks)

    assert isinstance(OnlySolve(), host.HostSolver) and not host.solves_lanes(OnlySolve())
    own = [LaneState(OnlySolve(), ctl.model.nu) for _ in pick]
    cs.finish(own, first_prep, first_packed, ["ok"] * 4, [-1e-3] * 4, 0.0)
    cmds2, _ = cs.finish(own, prep, packed, reasons, [0.0] * 4, 0.0)
    assert [lane.solver.calls for lane in own] == [2, 2, 2, 1]
    for got, want in zip(cmds2, cmds):
        assert (got.solve_status, got.fallback, got.measurement) == \
            (want.solve_status, want.fallback, want.measurement)
        np.testing.assert_array_equal(got.u, want.u)
