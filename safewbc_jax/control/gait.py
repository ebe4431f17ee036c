"""A gait: what a domain-driven scenario (``Scenario.gait``) gives the control step.

The control step (``control.step``) and the metrics know a gait only through this protocol.
A gait owns its state, an opaque pytree carried in ``ControllerState.gait`` from one step to
the next, and says what of it goes into each step's record and into a run's metric
columns. A scenario without a gait stands in double support. A new gait is
one new object of this protocol, set as its scenario's ``gait``.

``scenarios.walking.AlipGait`` (the paper's ALIP walking) implements it.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol, runtime_checkable


class Support(NamedTuple):
    """Which feet carry the robot: ``stance`` +1 left, -1
    right, 0 both feet; ``stance0`` (3,) where the stance sole stood when the step began
    (zeros in double support)."""

    stance: Any
    stance0: Any


@runtime_checkable
class Gait(Protocol):
    """The protocol of a scenario's gait: its per-step methods and those of the start
    (``start_data``, the start domains). Every method but ``check_speed``,
    ``columns`` and the start domains is pure JAX of its array arguments."""

    def check_speed(self, speed: float, option: str = "speed") -> float:
        """The commanded speed, or ValueError naming ``option``."""
        ...

    def start_data(self, model, q, start, blend: float) -> Any:
        """The gait's own start data (``scenario.Start.gait``) at the start pose q."""
        ...

    def initial(self, xp, dtype) -> Any:
        """The gait's state before the first step (a pytree of ``xp`` arrays)."""
        ...

    def advance(self, state, prev_tau, dt, model, q, sole_force, weight) -> Any:
        """The state after ``dt`` s more, from the measurement (q, the soles' normal
        forces) and the robot's weight (N)."""
        ...

    def domain(self, state, speed) -> Any:
        """The domain the QP is built in (what tasks, masks and safe sets read)."""
        ...

    def controller_velocity(self, model, q, v, domain) -> Any:
        """The rates the controller builds its QP with (e.g. springs held rigid)."""
        ...

    def passive_actuators(self, model, domain) -> Any:
        """(nu,) 1 where a motor gives no torque in this domain, else 0."""
        ...

    def first_domain(self, model, q) -> Any:
        """The domain of the first step from the start pose (Theorem 1's check)."""
        ...

    def start_domain(self, model, q) -> Any:
        """The domain at the start (standing)."""
        ...

    def support(self, state) -> Support:
        """Which feet carry the robot in ``state``."""
        ...

    def record(self, state) -> dict:
        """The gait's fields of a step's record ({name: array})."""
        ...

    def columns(self, state) -> dict:
        """The gait's metric columns at the end of a run ({name: numpy array}; a leading
        batch axis stays)."""
        ...


def initial(gait: Gait | None, xp, dtype) -> Any:
    """The gait's initial state; ``()`` (no state) without a gait."""
    return () if gait is None else gait.initial(xp, dtype)


def support(gait: Gait | None, state, xp, dtype) -> Support:
    """``gait.support(state)``; double support without a gait."""
    if gait is None:
        return Support(xp.zeros((), dtype), xp.zeros(3, dtype))
    return gait.support(state)


def columns(gait: Gait | None, state) -> dict | None:
    """The gait's metric columns of a run that ended in ``state``; None without a gait."""
    return None if gait is None else gait.columns(state)
