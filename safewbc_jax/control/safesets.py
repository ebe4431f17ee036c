"""A safe set C = {x : h(x) >= 0} as one object, and user safe sets loaded from a file.

Paper, "Exponential control barrier functions": a barrier h of relative degree r_b (eq. 18)
is enforced through the A-ECBF row L_F^r h + L_G L_F^(r-1) h q_ddot >= -K_alpha eta
(eqs. 26, 28; ``barriers.aecbf_row``), K_alpha placing the roots of the closed-loop chain at
-p_1, ..., -p_r; Theorem 1 says which poles keep h >= 0 from a given start state.

A ``SafeSet`` carries everything a scenario needs of one barrier:

* ``h``: ``h(model, q, threshold, domain)`` (relative degree 2, a function of the
  configuration) or ``h(model, q, v, threshold, domain)`` (relative degree 1, of the
  state); ``threshold`` is a parameter (``ControllerParams.threshold[name]``) so that it
  can be swept, ``domain`` is the gait's ``walking.Domain`` in walking scenarios (None else);
* its default ``poles`` (p_1..p_r > 0) and ``threshold``;
* ``active(domain) -> 0/1``: where the row is enforced (None: always);
* ``check_domain(model, q) -> domain``: where Theorem 1 is checked for a barrier that is
  not active at the start state (the swing-foot barrier: at the start of the first step);
  None: at the start state itself;
* ``enforce``: False evaluates h for the metrics and plots only (a monitor);
* ``unit``: the unit of h, for the summaries ("m", "rad", "m/s", ...);
* ``terms`` (optional, relative degree 2): ``terms(model, kin, motion, threshold, domain)
  -> (h, J_h, J_h_dot v)`` in closed form from the step's kinematics (``kin``: forward
  kinematics; ``motion``: ``robot.BodyMotion``), used for the QP row instead of automatic
  differentiation of h, which on the CPU costs hundreds of kernels per barrier. It must
  be h's own derivatives: the built-in ones are tested against the AD of h.

A user adds one from their own file: ``load("path/to/file.py:NAME")`` imports the file and
returns its ``NAME`` (a SafeSet, or a function of no arguments that returns one).
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from safewbc_jax.base import userfile

if TYPE_CHECKING:
    import jax

    from safewbc_jax.model.robot import RobotModel

_NAME_RE = userfile.NAME_RE


class SafeSetError(ValueError):
    """A safe set (or a reference FILE.py:NAME to one) that cannot be used; the message
    names the safe set or the file and what is wrong."""


@dataclasses.dataclass(frozen=True)
class SafeSet:
    """One barrier h and what a scenario needs of it (the module docstring says more).

    Args:
        name: an identifier, the barrier's key in ``ControllerParams``' poles and
            threshold tables.
        h: ``h(model, q, threshold, domain)`` (relative degree 2) or ``h(model, q, v,
            threshold, domain)`` (relative degree 1), returning one number: the set is
            h >= 0.
        relative_degree: 1 or 2.
        poles: the default poles p_1..p_r > 0, one per derivative (r =
            ``relative_degree``).
        threshold: the default threshold passed to ``h``.
        active: ``active(domain) -> 0/1``, where the row is enforced; None: always.
        check_domain: ``check_domain(model, q) -> domain``, where Theorem 1 is checked for
            a barrier not active at the start state; None: at the start state.
        enforce: False: h is evaluated for the metrics and plots only (a monitor).
        unit: the unit of h, for the summaries ("m", "rad", "m/s", ...).
        terms: relative degree 2 only: ``terms(model, kin, motion, threshold, domain) ->
            (h, J_h, J_h_dot v)`` in closed form, used for the QP row instead of the AD
            of h; None: the AD.

    Raises:
        SafeSetError: a name that is not an identifier, an ``h`` or ``terms`` that is not
            a function or has the wrong signature, a relative degree other than 1 or 2,
            poles that are not ``relative_degree`` finite numbers > 0, a threshold that is
            not a finite number.
    """

    name: str
    h: Callable
    relative_degree: int = 2
    poles: tuple = (10.0, 10.0)
    threshold: float = 0.0
    active: Callable | None = None
    check_domain: Callable | None = None
    enforce: bool = True
    unit: str = "m"
    terms: Callable | None = None

    def __post_init__(self):
        where = f"safe set {self.name!r}"
        if not isinstance(self.name, str) or not _NAME_RE.match(self.name):
            raise SafeSetError(f"{where}: the name must be an identifier (letters, digits, _): "
                               "it is a key of [poles] and [threshold] in params files")
        if not callable(self.h):
            raise SafeSetError(f"{where}: h must be a function")
        if self.relative_degree not in (1, 2):
            raise SafeSetError(f"{where}: relative_degree must be 1 (h(model, q, v, threshold, "
                               f"domain)) or 2 (h(model, q, threshold, domain)), got "
                               f"{self.relative_degree!r}")
        want = ("h(model, q, threshold, domain)" if self.relative_degree == 2 else
                "h(model, q, v, threshold, domain)")
        try:
            inspect.signature(self.h).bind(*range(4 if self.relative_degree == 2 else 5))
        except TypeError:
            raise SafeSetError(f"{where}: relative degree {self.relative_degree} needs {want}; "
                               f"h has the signature {inspect.signature(self.h)}") from None
        except ValueError:   # a builtin without a signature: checked when evaluated
            pass
        poles = tuple(float(p) if isinstance(p, (int, float, np.floating, np.integer))
                      and not isinstance(p, (bool, np.bool_)) else p
                      for p in np.atleast_1d(np.asarray(self.poles, dtype=object)).tolist())
        if len(poles) != self.relative_degree:
            raise SafeSetError(f"{where}: {len(poles)} poles for relative degree "
                               f"{self.relative_degree} (one pole per derivative)")
        if not all(isinstance(p, (int, float)) and not isinstance(p, bool) and math.isfinite(p)
                   and p > 0 for p in poles):
            raise SafeSetError(f"{where}: poles {poles!r} must be finite numbers > 0 "
                               "(Theorem 1)")
        if not (isinstance(self.threshold, (int, float)) and math.isfinite(self.threshold)):
            raise SafeSetError(f"{where}: threshold {self.threshold!r} must be a finite number")
        if self.terms is not None and (self.relative_degree != 2 or not callable(self.terms)):
            raise SafeSetError(f"{where}: terms (closed-form h, J_h, J_h_dot v) must be a "
                               "function, and only for relative degree 2")
        object.__setattr__(self, "poles", tuple(float(p) for p in poles))
        object.__setattr__(self, "threshold", float(self.threshold))

    def h_fn(self, model: RobotModel, threshold: Any,
             domain: Any = None) -> Callable[..., jax.Array]:
        """The barrier as a function of the state alone (as ``barriers`` takes it).

        Args:
            model: the robot model.
            threshold: the threshold passed to ``h``.
            domain: the gait's domain in walking, else None.

        Returns:
            ``h_fn(q)`` (relative degree 2) or ``h_fn(q, v)`` (relative degree 1).
        """
        if self.relative_degree == 2:
            return lambda q: self.h(model, q, threshold, domain)
        return lambda q, v: self.h(model, q, v, threshold, domain)

    def value(self, model: RobotModel, q: jax.Array, v: jax.Array, threshold: Any,
              domain: Any = None) -> jax.Array:
        """h at (q, v).

        Args:
            model: the robot model.
            q: (nq,) configuration.
            v: (nv,) generalized velocity (not used at relative degree 2).
            threshold: the threshold passed to ``h``.
            domain: the gait's domain in walking, else None.

        Returns:
            h, a scalar.
        """
        hf = self.h_fn(model, threshold, domain)
        return hf(q) if self.relative_degree == 2 else hf(q, v)

    def check(self, model: RobotModel, q: jax.Array, v: jax.Array,
              domain: Any = None) -> None:
        """Check that h evaluates to one number at (q, v), at the default threshold, by
        ``jax.eval_shape`` (nothing runs or compiles).

        Args:
            model: the robot model.
            q: (nq,) configuration.
            v: (nv,) generalized velocity.
            domain: the gait's domain in walking, else None.

        Raises:
            SafeSetError: evaluating h fails, or h does not return shape (); the message
                names the safe set.
        """
        import jax

        try:
            out = jax.eval_shape(lambda q, v: self.value(model, q, v, self.threshold, domain),
                                 q, v)
        except Exception as e:  # noqa: BLE001 - the user's h: say which one failed, and how
            raise SafeSetError(f"safe set {self.name!r}: evaluating h failed: "
                               f"{type(e).__name__}: {e}") from e
        if getattr(out, "shape", None) != ():
            raise SafeSetError(f"safe set {self.name!r}: h must return one number (shape ()), "
                               f"it returns shape {getattr(out, 'shape', type(out).__name__)}")

    def is_active(self, domain: Any) -> Any:
        """Whether the row is enforced in a domain.

        Args:
            domain: the gait's domain in walking, else None.

        Returns:
            1.0 where ``active`` is None, else ``active(domain)`` (0 or 1).
        """
        return 1.0 if self.active is None else self.active(domain)

    def monitored(self) -> SafeSet:
        """This safe set evaluated only (no QP row).

        Returns:
            A copy with ``enforce`` False.
        """
        return dataclasses.replace(self, enforce=False)


def load(ref: str) -> SafeSet:
    """A user's safe set from a Python file (``userfile.load``).

    Args:
        ref: "FILE.py:NAME": the file, imported, and the name in it of a SafeSet or of a
            function of no arguments that returns one.

    Returns:
        The SafeSet.

    Raises:
        SafeSetError: a malformed ``ref``, a missing file or name, a file whose import
            fails, or a name that is not a SafeSet; the message names the file and what
            is wrong.
    """
    return userfile.load(ref, SafeSet, "safe set", SafeSetError)
