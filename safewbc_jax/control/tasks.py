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
        return self.output.name

    @property
    def dim(self) -> int:
        return self.output.dim

    def params_entry(self):
        """(dim, K_p, K_d, W) as ``params.make_params`` takes them."""
        return self.dim, self.kp, self.kd, self.weight
