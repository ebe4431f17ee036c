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

    def replace(self, **kw) -> "ControllerParams":
        """A copy with the fields in ``kw`` replaced, their values as float64 arrays
        (``as_float64``)."""
        return dataclasses.replace(self, **as_float64(kw))


def as_float64(tree):
    """Every leaf of ``tree`` as a float64 JAX array that is not weakly typed. A Python
    float through ``jnp.asarray`` is weakly typed, and a weak leaf makes another program
    for every jitted function that takes the params as a pytree: a controller started with
    such params compiled its start-up QP again where the same params as float64 load it
    from the cache (benchmarks/README.md, "Figures behind design choices")."""
    return jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), tree)


def make_params(outputs: dict, barriers: dict, **scalars) -> ControllerParams:
    """outputs: name -> (dim, kp, kd, weight) with scalar or per-dim gains; barriers:
    name -> (poles, threshold). Float64: needs ``safewbc_jax.enable_x64()``."""
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


def apply_overrides(params: ControllerParams, overrides: dict,
                    src: str = "params") -> ControllerParams:
    """Apply a nested dict of overrides (as read from TOML):

        [kp] com = 120            [kd] torso = [20, 20, 10]      [weight] arms = 5
        [poles] left_fist = [8, 12]          [threshold] left_fist = 0.05
        mu = 0.5   gamma_qdd = 1e-4   ...

    Every key and value is checked; errors name the source, key and value."""
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


def load_overrides(path: str | Path) -> dict:
    """Read a params TOML file."""
    import tomllib

    p = Path(path)
    if not p.is_file():
        raise ParamsError(f"params file {p} does not exist")
    try:
        return tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise ParamsError(f"{p}: not valid TOML: {e}") from None


def to_toml(params: ControllerParams) -> str:
    """Write every parameter as TOML that ``load_overrides`` reads back."""
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
