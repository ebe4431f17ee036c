"""``runspec.RunSpec``: the one run configuration that ``safewbc run``'s loop
(``RunConfig``), ``run_batch`` (``BatchConfig``), the sweep spec and the mujoco engine's
workers hold, and the controller every loop builds from it."""

import dataclasses

import numpy as np
import pytest

from safewbc_jax.control import metrics
from safewbc_jax.sim.mjx.rollout import BatchConfig
from safewbc_jax.sim.runspec import RunSpec
from safewbc_jax.sim.mujoco_loop import RunConfig
from safewbc_jax.sweeps.spec import parse_spec

RUN_FIELDS = [f.name for f in dataclasses.fields(RunSpec)]


def test_every_loop_config_is_a_run_spec_with_its_own_options():
    run = RunSpec("walk", barrier=False, duration=2.5, settle=1.2, control_dt=2e-3, speed=0.3)
    batch = BatchConfig.of(run, decimate=10, precision="mixed")
    loop = RunConfig.of(run, record_qps_every=5)
    for cfg in (batch, loop):
        assert isinstance(cfg, RunSpec)
        assert [f.name for f in dataclasses.fields(cfg)][:len(RUN_FIELDS)] == RUN_FIELDS
        assert cfg.run_spec() == run
    assert (batch.decimate, batch.precision, loop.record_qps_every) == (10, "mixed", 5)
    # one field list: a loop's config adds options, it does not name the run's fields again
    own = {c: [f.name for f in dataclasses.fields(c)][len(RUN_FIELDS):]
           for c in (BatchConfig, RunConfig)}
    assert own == {BatchConfig: ["decimate", "precision"],
                   RunConfig: ["record_qps_every", "push", "count_kernels", "engine", "native"]}
    with pytest.raises(TypeError):
        BatchConfig.of(run, decimate=1, duration=3.0)     # a run field is the run's


def test_a_sweep_spec_hands_its_run_to_both_engines(tmp_path):
    spec = parse_spec({"sweep": {"scenario": "arms", "duration": 0.4, "settle": 1.5,
                                 "barrier": False, "control_dt": 0.002},
                       "grid": {"threshold.left_fist": [0.0, 0.1]}})
    assert spec.run == RunSpec("arms", False, 0.4, 1.5, 0.002)
    assert BatchConfig.of(spec.run, precision=spec.precision).run_spec() == spec.run


def test_schedule_and_controller_fill_in_the_scenarios_defaults():
    sc = RunSpec("squat").get_scenario()
    n, settle, duration = RunSpec("squat", control_dt=2e-3).schedule()
    assert (settle, duration) == (sc.settle, sc.duration)
    assert n == round((sc.settle + sc.duration) / 2e-3)
    with pytest.raises(ValueError, match="BatchConfig.settle = 0.2: must cover"):
        BatchConfig("arms", settle=0.2).schedule("BatchConfig.")
    # walking's forward speed window is the same in every loop: the controller's t_half is
    # that of the run's schedule, the scenario's duration filled in (the mujoco engine's
    # workers once built theirs with duration None: no window, where the mjx engine had one)
    walk = RunSpec("walk", barrier=False)
    ctl = walk.controller()
    n, settle, _ = walk.schedule()
    t_half = float(ctl.run_values.t_half)
    assert t_half == metrics.half_time(n, settle, 1e-3) and t_half != metrics.NO_HALF
    assert ctl.scenario.barriers == () and ctl.scenario.settle == settle
    assert [b.name for b in ctl.scenario.monitors] == [b.name for b in
                                                      RunSpec("walk").get_scenario().barriers]
    np.testing.assert_array_equal(ctl.params.kp["com"],
                                  walk.get_scenario().default_params().kp["com"])
