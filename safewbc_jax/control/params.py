"""``ControllerParams``: every gain a user may sweep, as one pytree.

Per output: K_p, K_d (y* = -K_p y - K_d y_dot + y^d_ddot, paper eq. 15) and the cost
weight W; the diagonal of Gamma (regulariser X^T Gamma X) per block of X = [q_ddot, u,
lambda]; contact parameters mu (friction), gamma (torsion), f_min (least normal force),
the ZMP margin; per barrier its poles p_1..p_r (K_alpha from Theorem 1) and threshold.

Overrides come from TOML (``load_overrides``), validated before anything compiles.
"""

from __future__ import annotations

import dataclasses
import math
from functools import partial
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

SCALARS = ("gamma_qdd", "gamma_u", "gamma_lambda", "mu", "gamma_torsion", "f_min", "zmp_margin",
           "kd_constraint", "gamma_tangential")


@partial(jax.tree_util.register_dataclass,
         data_fields=["kp", "kd", "weight", "poles", "threshold", *SCALARS], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class ControllerParams:
    """Every gain of a scenario's controller, float64 JAX arrays (a leading batch axis on
    every leaf in the batched path); build one with ``make_params`` or a scenario's
    ``default_params``.

    Args:
        kp: output name -> (dim,) K_p.
        kd: output name -> (dim,) K_d.
        weight: output name -> (dim,) cost weight W.
        poles: barrier name -> (r,) poles p_1..p_r > 0.
        threshold: barrier name -> () threshold of its safe set.
        gamma_qdd: Gamma's diagonal on the q_ddot block.
        gamma_u: Gamma's diagonal on the torques u.
        gamma_lambda: Gamma's diagonal on the contact forces lambda.
        mu: friction coefficient of the friction pyramid.
        gamma_torsion: the torsional limit's coefficient, |m_z| <= gamma f_z (eq. 7).
        f_min: least normal force of a contact, N.
        zmp_margin: how far inside the soles the centre of pressure and the ZMP are
            held, m.
        kd_constraint: kd of the holonomic rows J q_ddot = -J_dot v - kd J v (0: eqs.
            2-3 as written).
        gamma_tangential: added to Gamma's diagonal on the tangential contact forces and
            torsion moments (f_x, f_y, m_z).
    """

    kp: dict            # output name -> (dim,)
    kd: dict            # output name -> (dim,)
    weight: dict        # output name -> (dim,)
    poles: dict         # barrier name -> (r,), p_i > 0
    threshold: dict     # barrier name -> ()
    gamma_qdd: jax.Array
    gamma_u: jax.Array
    gamma_lambda: jax.Array
    mu: jax.Array
    gamma_torsion: jax.Array
    f_min: jax.Array
    zmp_margin: jax.Array
    kd_constraint: jax.Array
    gamma_tangential: jax.Array

    def replace(self, **kw: Any) -> ControllerParams:
        """A copy with some fields replaced.

        Args:
            **kw: field name -> new value (a number, an array, or for the tables a dict
                of them), made float64 arrays (``as_float64``).

        Returns:
            The new ControllerParams.

        Raises:
            TypeError: a name that is not a field.
        """
        return dataclasses.replace(self, **as_float64(kw))


def as_float64(tree: Any) -> Any:
    """Every leaf of a pytree as a float64 JAX array that is not weakly typed.

    A Python float through ``jnp.asarray`` is weakly typed, and a weak leaf makes another
    program for every jitted function that takes the params as a pytree: a controller
    started with such params compiles its start-up QP again where the same params as
    float64 load it from the cache.

    Args:
        tree: a pytree of numbers or arrays.

    Returns:
        The same pytree of float64 JAX arrays.
    """
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), tree)


def make_params(outputs: dict[str, tuple], barriers: dict[str, tuple],
                **scalars: float) -> ControllerParams:
    """Build the params of a controller's outputs and barriers, float64.

    Args:
        outputs: output name -> (dim, kp, kd, weight), each gain a scalar or dim values
            (``Task.params_entry``).
        barriers: barrier name -> (poles, threshold).
        **scalars: values of the scalar fields (``SCALARS``: gamma_qdd, mu, f_min, ...)
            over the defaults.

    Returns:
        The ControllerParams.

    Raises:
        RuntimeError: JAX's 64-bit floats are off (``safewbc_jax.enable_x64``).
        ValueError: a name in ``scalars`` that is not a scalar field.
    """
    from safewbc_jax.base.runtime import require_x64

    require_x64("ControllerParams (params.make_params)")
    f = lambda x: jnp.asarray(x, jnp.float64)  # noqa: E731
    kp, kd, w = {}, {}, {}
    for name, (dim, p, d, wt) in outputs.items():
        kp[name] = f(np.broadcast_to(p, (dim,)))
        kd[name] = f(np.broadcast_to(d, (dim,)))
        w[name] = f(np.broadcast_to(wt, (dim,)))
    poles = {n: f(np.atleast_1d(p)) for n, (p, _) in barriers.items()}
    thr = {n: f(t) for n, (_, t) in barriers.items()}
    defaults = dict(gamma_qdd=1e-4, gamma_u=1e-6, gamma_lambda=1e-7, mu=0.6, gamma_torsion=0.02,
                    f_min=10.0, zmp_margin=0.01, kd_constraint=0.0,
                    gamma_tangential=1e-4)
    unknown = set(scalars) - set(defaults)
    if unknown:
        raise ValueError(f"unknown controller parameters: {sorted(unknown)}")
    defaults.update(scalars)
    return ControllerParams(kp=kp, kd=kd, weight=w, poles=poles, threshold=thr,
                            **{k: f(v) for k, v in defaults.items()})


class ParamsError(ValueError):
    """A params override (TOML) names something that does not exist or has a bad value."""


def _vector(src: str, table: str, name: str, value, dim: int) -> np.ndarray:
    """``value`` of key ``name`` in TOML table ``[table]`` as a (dim,) float vector; a
    number, or a list of ``dim`` numbers (no strings, booleans or nested tables)."""
    where = f"{src}: [{table}] {name} = {value!r}"
    items = value if isinstance(value, list) else [value]
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in items):
        raise ParamsError(f"{where}: expected a number or a list of {dim} numbers")
    arr = np.asarray(value, dtype=float)
    if arr.ndim > 1 or (arr.ndim == 1 and arr.size != dim):
        raise ParamsError(f"{where}: expected a number or a list of {dim} numbers")
    if not np.all(np.isfinite(arr)):
        raise ParamsError(f"{where}: not finite")
    return np.broadcast_to(arr, (dim,)).copy()


def apply_overrides(params: ControllerParams, overrides: dict[str, Any],
                    src: str = "params") -> ControllerParams:
    """Apply a nested dict of overrides, as read from TOML (``load_overrides``):

        [kp] com = 120            [kd] torso = [20, 20, 10]      [weight] arms = 5
        [poles] left_fist = [8, 12]          [threshold] left_fist = 0.05
        mu = 0.5   gamma_qdd = 1e-4   ...

    Args:
        params: the params to start from.
        overrides: table name ("kp", "kd", "weight", "poles", "threshold") -> {name:
            a number or a list of numbers}, or a scalar field's name -> a number.
        src: where the overrides come from (a file's path), for the error messages.

    Returns:
        ``params`` with the overrides applied.

    Raises:
        ParamsError: an unknown key, output or barrier, or a bad value (not a finite
            number or a list of the right length, a gain or pole not > 0, a negative
            weight); the message names the source, key and value.
    """
    kw: dict[str, Any] = {}
    for key, value in overrides.items():
        if key in ("kp", "kd", "weight"):
            if not isinstance(value, dict):
                raise ParamsError(f"{src}: [{key}] must be a table of output = gain")
            table = dict(getattr(params, key))
            for name, v in value.items():
                if name not in table:
                    raise ParamsError(f"{src}: {key}.{name}: no output {name!r}; outputs are "
                                      f"{sorted(table)}")
                vec = _vector(src, key, name, v, table[name].shape[0])
                if key != "weight" and np.any(vec <= 0) or key == "weight" and np.any(vec < 0):
                    raise ParamsError(f"{src}: [{key}] {name} = {v!r}: must be "
                                      + ("positive" if key != "weight" else "non-negative"))
                table[name] = jnp.asarray(vec)
            kw[key] = table
        elif key in ("poles", "threshold"):
            if not isinstance(value, dict):
                raise ParamsError(f"{src}: [{key}] must be a table of barrier = value")
            table = dict(getattr(params, key))
            for name, v in value.items():
                if name not in table:
                    raise ParamsError(f"{src}: {key}.{name}: no barrier {name!r}; barriers are "
                                      f"{sorted(table)}")
                vec = _vector(src, key, name, v, table[name].size).reshape(table[name].shape)
                if key == "poles" and np.any(vec <= 0):
                    raise ParamsError(f"{src}: [poles] {name} = {v!r}: poles must be > 0 "
                                      "(Theorem 1)")
                table[name] = jnp.asarray(vec)
            kw[key] = table
        elif key in SCALARS:
            if (isinstance(value, bool) or not isinstance(value, (int, float))
                    or not math.isfinite(value)):
                raise ParamsError(f"{src}: {key} = {value!r}: expected a finite number")
            if value < 0 or (key in ("mu", "f_min") and value <= 0):
                raise ParamsError(f"{src}: {key} = {value!r}: must be positive")
            kw[key] = float(value)
        else:
            raise ParamsError(f"{src}: unknown key {key!r}; known: kp, kd, weight, poles, "
                              f"threshold, {', '.join(SCALARS)}")
    return params.replace(**kw)


def load_overrides(path: str | Path) -> dict[str, Any]:
    """Read a params TOML file.

    Args:
        path: the file.

    Returns:
        Its tables.

    Raises:
        ParamsError: the file does not exist or is not valid TOML.
    """
    import tomllib

    p = Path(path)
    if not p.is_file():
        raise ParamsError(f"params file {p} does not exist")
    try:
        return tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ParamsError(f"{p}: not valid TOML: {e}") from None


def to_toml(params: ControllerParams) -> str:
    """Every parameter as TOML that ``load_overrides`` reads back.

    Args:
        params: params without a batch axis.

    Returns:
        The TOML text.
    """
    lines = []
    for key in SCALARS:
        lines.append(f"{key} = {float(getattr(params, key))!r}")
    for table in ("kp", "kd", "weight", "poles", "threshold"):
        lines.append(f"\n[{table}]")
        for name, v in getattr(params, table).items():
            arr = np.asarray(v)
            val = (repr(float(arr)) if arr.ndim == 0 else
                   "[" + ", ".join(repr(float(x)) for x in arr) + "]")
            lines.append(f"{name} = {val}")
    return "\n".join(lines) + "\n"
