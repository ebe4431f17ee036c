"""A task: one output y^a(q) tracked with its own gains, weight and reference.

Paper, "Task Space Inverse dynamics": the error y = y^a(q) - y^d(tau) (eq. 10) is driven by
the desired output acceleration y* = -K_p y - K_d y_dot + y^d_ddot (eq. 15) through the
cost ||J_y q_ddot + J_y_dot v - y*||^2_W of the QP (the unnumbered display after eq. 15).
A ``Task`` carries all of it for one output: the output object (``outputs.Output``), K_p,
K_d and W (defaults that ``ControllerParams`` starts from), and the reference. A scenario is
a list of tasks; adding one to a scenario is the only edit a new task needs.

The reference is one of:

* ``reference(tau, start) -> y^d(tau)``: a smooth function of the motion time; its
  derivatives are taken by AD and, before the motion (tau < 0), it is blended from the
  measured start value (``Scenario.desired_at``);
* ``planned(model, tau, start, q, v, domain) -> (y^d, y^d_dot, y^d_ddot)``: a reference
  planned from the measured state at each control step (the ALIP swing foot).

``start`` is the run's ``scenario.Start``, measured at the start pose: ``start.origin``,
``start.arm0``, ``start.y0[output name]``.

``mask(domain) -> (dim,)`` (0/1) switches components off by domain (walking: the swing
foot is tracked only in single support); None tracks every component always.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from safewbc_jax.control.outputs import Output


@dataclasses.dataclass(frozen=True)
class Task:
    """One output tracked with its gains, weight and reference (the module docstring
    describes the two kinds of reference).

    Args:
        output: the output y^a(q) (an ``outputs.Output``); its name is the task's.
        kp: default K_p, a scalar or one value per component.
        kd: default K_d, a scalar or one value per component.
        weight: default cost weight W, a scalar or one value per component.
        reference: ``reference(tau, start) -> y^d(tau)``, a smooth function of the motion
            time; exactly one of it and ``planned``.
        planned: ``planned(model, tau, start, q, v, domain) -> (y^d, y^d_dot,
            y^d_ddot)``, planned from the measured state at each control step.
        mask: ``mask(domain) -> (dim,)`` 0/1 per component; None tracks every component
            always.

    Raises:
        ValueError: both or neither of ``reference`` and ``planned`` are given.
    """

    output: Output
    kp: float | tuple = 100.0
    kd: float | tuple = 20.0
    weight: float | tuple = 1.0
    reference: Callable | None = None
    planned: Callable | None = None
    mask: Callable | None = None

    def __post_init__(self):
        if (self.reference is None) == (self.planned is None):
            raise ValueError(f"task {self.output.name!r}: give exactly one of reference "
                             "(tau, start) -> y^d or planned (model, tau, start, q, v, domain)")

    @property
    def name(self) -> str:
        """The output's name."""
        return self.output.name

    @property
    def dim(self) -> int:
        """The output's dimension."""
        return self.output.dim

    def params_entry(self) -> tuple[int, float | tuple, float | tuple, float | tuple]:
        """The task's entry of ``params.make_params``' ``outputs``.

        Returns:
            ``(dim, K_p, K_d, W)``.
        """
        return self.dim, self.kp, self.kd, self.weight
