"""``RunSpec``: what a run of a scenario is, whichever loop runs it.

A run is a scenario (a name, a user's ``"FILE.py:NAME"`` or a ``Scenario`` object) with
the user's safe sets added (``safesets.load`` references), its barriers enforced or only
monitored (``barrier``: ``Scenario.without_barriers``), the seconds of standing before the
motion (``settle``) and of motion (``duration``; the scenario's defaults where None), the
control period and walking's speed command. Each loop adds its own options to it by
subclassing it:

- ``sim.mujoco_loop.RunConfig``: the MuJoCo loop (a push, QP recording);
- ``batch.rollout.BatchConfig``: the batched MJX rollouts (trajectories, precision).

What varies from rollout to rollout is not in it: the ``ControllerParams``, the push
(``push.Push``) and the start perturbation go with each rollout.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from safewbc_jax import scenarios
from safewbc_jax.control import step as control_step


@dataclasses.dataclass(frozen=True)
class RunSpec:
    scenario: Any = "squat"        # a name, "FILE.py:NAME", or a Scenario object
    barrier: bool = True              # False: every safe set monitored only
    duration: float | None = None     # s of motion (the scenario's default when None)
    settle: float | None = None       # s of standing before it (the scenario's default)
    control_dt: float = control_step.DEFAULT_CONTROL_DT     # s
    speed: float = control_step.DEFAULT_SPEED  # walking: commanded mean forward speed (m/s)
    safe_sets: tuple = ()             # the user's safe sets: "FILE.py:NAME" references

    @classmethod
    def of(cls, run: "RunSpec", **options):
        """A ``cls`` (a loop's config) of the run ``run`` with the loop's ``options``."""
        return cls(**{f.name: getattr(run, f.name) for f in dataclasses.fields(RunSpec)},
                   **options)

    def run_spec(self) -> "RunSpec":
        """The run of this config, without the loop's options."""
        return RunSpec.of(self)

    def get_scenario(self):
        """The Scenario this run controls (``scenarios.get_scenario``)."""
        return scenarios.get_scenario(self.scenario, self.barrier, tuple(self.safe_sets))

    def schedule(self, what: str = "") -> tuple[int, float, float]:
        """(control steps, settle s, duration s), the defaults filled in
        (``control_step.schedule``; ValueError, naming ``what`` + the field, where one is
        out of range)."""
        return self._schedule(self.get_scenario(), what)

    def _schedule(self, scenario, what: str = "") -> tuple[int, float, float]:
        return control_step.schedule(scenario, self.duration, self.settle, self.control_dt, what)

    def controller(self, params=None, **options):
        """The deployable controller of this run (``deploy.Controller``; ``params`` None:
        the scenario's defaults; ``options``: its ``solver`` and ``keep_metrics``), with
        the settle and duration filled in, so that every loop measures walking's
        ``avg_forward_speed`` over the same window."""
        from safewbc_jax.deploy.controller import Controller

        sc = self.get_scenario()          # once: a user's files are loaded each time
        _, settle, duration = self._schedule(sc)
        return Controller(sc, params, self.control_dt, barrier=self.barrier, speed=self.speed,
                          settle=settle, duration=duration, **options)
