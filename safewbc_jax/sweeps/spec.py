"""Sweep spec files: parsing, validation and the plan of rollouts.

A spec is a TOML file::

    [sweep]
    scenario = "arms"        # a scenario's name, or "my_scenario.py:NAME": a Scenario of
                             #   your own (the path from the spec's folder)
    barrier = true           # enforce the scenario's A-ECBF rows
    duration = 3.0           # seconds of motion (default: the scenario's)
    settle = 1.5             # seconds standing before the motion (default: the scenario's)
    repeats = 4              # rollouts per setting, each with its own perturbation
    seed = 0                 # default seed (``--seed`` overrides)
    batch = 64               # default rollouts per chunk (``--batch`` overrides)
    violation_tol = 0.0      # a rollout violates barrier b when min h_b < -violation_tol
    target = "left_fist"     # the barrier the report and tune-poles look at
    safe_sets = ["my_barrier.py:NAME"]   # the user's safe sets (paths from the spec's folder);
                                         # their poles and thresholds are axes like any other
    precision = "float64"    # or "mixed" (mjx engine only): safewbc_jax/control/precision.py

    [params]                 # fixed ControllerParams overrides, as in ``--params FILE``
    mu = 0.6

    [grid]                   # swept axes: the rollouts are their cartesian product
    "poles.left_fist.p1" = [2.0, 5.0, 10.0]
    "poles.left_fist.p2" = { logspace = [2.0, 40.0, 4] }

    [push]                   # a push on the torso applied in every rollout (or sweep it:
    magnitude = 0.0          #   "push.magnitude" etc. in [grid])
    direction = 0.0          # degrees in the ground plane, 0 = +x (forward), 90 = +y (left)
    at = 1.0                 # seconds after the motion starts
    duration = 0.15          # seconds

    [perturb]                # Gaussian initial velocity perturbation, one draw per rollout
    base_linear = 0.0        # std of each base linear velocity component (m/s)
    base_angular = 0.0       # std of each base angular velocity component (rad/s)
    joints = 0.0             # std of each hinge joint rate (rad/s)

    [tune]                   # ``safewbc tune`` and ``tune-poles`` only: method, budget,
    objective = ["tracking_rms.arms"]   # validate, population, sigma, the grid's keys
    [tune.params]            # what to tune: controller axes of [grid] (docs/sweeps.md)
    "poles.left_fist.p1" = { bounds = [2.0, 128.0] }               # log scale when > 0

Axis names in ``[grid]``:

* ``poles.B`` (every pole of barrier B equal to the value), ``poles.B.p1`` .. ``poles.B.pr``;
* ``threshold.B``;
* ``kp.O``, ``kd.O``, ``weight.O`` (the same value on every component of output O);
* ``kp_scale.O``, ``kd_scale.O``, ``weight_scale.O`` (factors on the defaults), and
  ``gain_scale.O`` (K_p times s and K_d times sqrt(s): the damping ratio is kept);
* the scalar parameters of :data:`safewbc_jax.control.params.SCALARS` (``mu``, ``f_min``, ...);
* ``push.magnitude``, ``push.direction``, ``push.at``, ``push.duration``.

Axis values are a non-empty list of numbers or one of ``{ values = [...] }``,
``{ linspace = [start, stop, n] }``, ``{ logspace = [start, stop, n] }`` (the endpoints
themselves, not their logarithms).

:func:`load_spec` checks every key, type and value before anything is compiled and raises
:class:`SpecError` naming the file, the key and the value.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from safewbc_jax.base import userfile
from safewbc_jax.control.push import PUSH_AT, PUSH_FOR

SECTIONS = ("sweep", "params", "grid", "push", "perturb", "tune")
SWEEP_KEYS = {"scenario": str, "barrier": bool, "duration": float, "settle": float,
              "control_dt": float, "repeats": int, "seed": int, "batch": int,
              "violation_tol": float, "target": str, "description": str, "safe_sets": list,
              "precision": str}
TUNE_KEYS = {"rounds": int, "points": int, "shrink": float, "pole_min": float,
             "pole_max": float, "objective": list, "barrier": str, "equal_poles": bool,
             "method": str, "params": dict, "population": int, "sigma": float, "budget": int,
             "validate": int}
TUNE_METHODS = ("cmaes", "grid")
PARAM_KEYS = ("bounds", "scale", "start")
GAIN_TABLES = ("kp", "kd", "weight")
SCALES = ("kp_scale", "kd_scale", "weight_scale", "gain_scale")
MAX_ROLLOUTS = 10_000_000
OBJECTIVE_METRICS = ("torque_ratio_max", "foot_slip_max")   # besides tracking_rms.OUTPUT
MARGIN_METRICS = ("zmp_margin_min",)    # to maximize: a negative weight in tune.objective


class SpecError(ValueError):
    """A sweep spec has an unknown key, a wrong type or a bad value."""


@dataclasses.dataclass(frozen=True)
class Axis:
    """One swept axis: ``name`` as written in ``[grid]``, its ``kind`` (poles, pole,
    threshold, gain, scale, scalar, push), the ``target`` it acts on (barrier, output or
    parameter name), the pole index for kind "pole", and the values."""

    name: str
    kind: str
    target: str
    values: tuple
    index: int = 0


@dataclasses.dataclass(frozen=True)
class PushTable:
    """The spec's ``[push]``: the push on the torso of every rollout (the values not swept).
    ``direction`` in degrees in the ground plane (0: +x), ``at`` in seconds after the
    motion starts, ``duration`` in seconds. A key the spec leaves out is the scenario's
    own push's (``Scenario.push``, ``of_push``), or no push."""

    magnitude: float = 0.0
    direction: float = 0.0
    at: float = PUSH_AT
    duration: float = PUSH_FOR

    @classmethod
    def of_push(cls, push) -> PushTable:
        """A scenario's ``Push`` as the table's values; ValueError for a push with a
        vertical force (the table's push lies in the ground plane)."""
        fx, fy, fz = (float(f) for f in push.force)
        if fz != 0.0:
            raise ValueError(f"the scenario's push {push.force} has a vertical force; a "
                             "sweep's [push] lies in the ground plane")
        return cls(float(np.hypot(fx, fy)), float(np.degrees(np.arctan2(fy, fx)) % 360.0),
                   float(push.at), float(push.duration))


@dataclasses.dataclass(frozen=True)
class PerturbTable:
    """The spec's ``[perturb]``: standard deviations of the Gaussian initial velocity
    perturbation (base linear m/s, base angular rad/s, each hinge joint rad/s)."""

    base_linear: float = 0.0
    base_angular: float = 0.0
    joints: float = 0.0


PUSH_KEYS = tuple(f.name for f in dataclasses.fields(PushTable))
PUSH_DEFAULTS = dataclasses.asdict(PushTable())
PERTURB_KEYS = tuple(f.name for f in dataclasses.fields(PerturbTable))


@dataclasses.dataclass(frozen=True)
class SweepSpec:
    path: str
    scenario: str
    barrier: bool
    duration: float | None
    settle: float | None
    control_dt: float
    repeats: int
    seed: int
    batch: int
    violation_tol: float
    target: str | None          # barrier the report and tuning look at (None: no barrier)
    description: str
    params: dict[str, Any]       # fixed overrides (params TOML form)
    axes: tuple                  # of Axis, in file order (the first varies slowest)
    push: PushTable              # fixed push values (those not swept)
    perturb: PerturbTable
    tune: TuneTable
    barriers: tuple              # enforced barrier names of the scenario
    monitors: tuple
    outputs: tuple               # output names of the scenario
    pole_counts: dict            # barrier name -> number of poles (relative degree)
    rows: tuple | None = None    # explicit settings instead of the grid product
    noise_period: int | None = None  # rollout k draws perturbation k % noise_period
    safe_sets: tuple = ()        # the user's safe sets, "ABSOLUTE/FILE.py:NAME"
    precision: str = "float64"   # the mjx engine's BatchConfig.precision

    @property
    def run(self):
        """The sweep's run, a ``runspec.RunSpec`` (walking's speed: the default)."""
        from safewbc_jax.sim.runspec import RunSpec
        return RunSpec(self.scenario, self.barrier, self.duration, self.settle, self.control_dt,
                       safe_sets=tuple(self.safe_sets))

    @property
    def n_settings(self) -> int:
        if self.rows is not None:
            return len(self.rows)
        return int(np.prod([len(a.values) for a in self.axes])) if self.axes else 1

    @property
    def n_rollouts(self) -> int:
        return self.n_settings * self.repeats

    def fingerprint(self) -> str:
        """Hash of everything that decides the rollouts (not the seed, batch, path or
        description): a sweep directory holds one spec."""
        d = {k: v for k, v in dataclasses.asdict(self).items()
             if k not in ("path", "seed", "batch", "description", "tune", "safe_sets")
             and not (k == "precision" and v == "float64")}   # hashes from before the key
        # a user's file by name and content, not by where it lies
        by_content = lambda ref: [ref.rsplit(":", 1)[1], userfile.digest(ref)]  # noqa: E731
        if self.safe_sets:
            d["safe_sets"] = [by_content(r) for r in self.safe_sets]
        if userfile.is_ref(self.scenario):
            d["scenario"] = by_content(self.scenario)
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]

    def setting(self, index: int) -> dict:
        """{axis name: value} of setting ``index`` (row-major over the axes)."""
        if self.rows is not None:
            return dict(zip((a.name for a in self.axes), self.rows[index]))
        out = {}
        for a in reversed(self.axes):
            index, j = divmod(index, len(a.values))
            out[a.name] = a.values[j]
        return {a.name: out[a.name] for a in self.axes}

    def settings_array(self) -> np.ndarray:
        """(n_settings, n_axes) float array of every setting, row-major."""
        if self.rows is not None:
            return np.asarray(self.rows, float).reshape(len(self.rows), len(self.axes))
        if not self.axes:
            return np.zeros((1, 0))
        grids = np.meshgrid(*[np.asarray(a.values, float) for a in self.axes], indexing="ij")
        return np.stack([g.reshape(-1) for g in grids], axis=1)

    def with_rows(self, axes: tuple, rows) -> "SweepSpec":
        """A copy whose settings are the listed ``rows`` (one value per axis of ``axes``)
        instead of the grid product."""
        rows = tuple(tuple(float(x) for x in r) for r in rows)
        if not rows or any(len(r) != len(axes) for r in rows):
            raise ValueError("with_rows: every row needs one value per axis")
        return dataclasses.replace(self, axes=tuple(axes), rows=rows)


def _fmt(v) -> str:
    return repr(v) if not isinstance(v, str) else json.dumps(v)


def _number(src, key, value, *, positive=False, nonneg=False, integer=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        want = "an integer" if integer else "a number"
        raise SpecError(f"{src}: {key} = {_fmt(value)}: expected {want}, "
                        f"got {type(value).__name__}")
    if integer and not isinstance(value, int):
        raise SpecError(f"{src}: {key} = {_fmt(value)}: expected an integer")
    if not math.isfinite(value):
        raise SpecError(f"{src}: {key} = {_fmt(value)}: not finite")
    if positive and value <= 0:
        raise SpecError(f"{src}: {key} = {_fmt(value)}: must be > 0")
    if nonneg and value < 0:
        raise SpecError(f"{src}: {key} = {_fmt(value)}: must be >= 0")
    return int(value) if integer else float(value)


def _axis_values(src, key, value) -> tuple:
    """The values of one [grid] axis: a list, or {values|linspace|logspace = ...}."""
    where = f"grid.{_quote(key)}"
    if isinstance(value, dict):
        if len(value) != 1 or next(iter(value)) not in ("values", "linspace", "logspace"):
            raise SpecError(f"{src}: {where} = {_fmt(value)}: expected a list of numbers or one "
                            "of {values = [...]}, {linspace = [start, stop, n]}, "
                            "{logspace = [start, stop, n]}")
        (form, arg), = value.items()
        if form == "values":
            return _axis_values(src, key, arg)
        if not isinstance(arg, list) or len(arg) != 3:
            raise SpecError(f"{src}: {where}.{form} = {_fmt(arg)}: expected [start, stop, n]")
        a = _number(src, f"{where}.{form}[0]", arg[0])
        b = _number(src, f"{where}.{form}[1]", arg[1])
        n = _number(src, f"{where}.{form}[2]", arg[2], integer=True)
        if n < 1:
            raise SpecError(f"{src}: {where}.{form} = {_fmt(arg)}: n = {n} gives an empty grid")
        if form == "logspace":
            if a <= 0 or b <= 0:
                raise SpecError(f"{src}: {where}.logspace = {_fmt(arg)}: endpoints must be > 0")
            grid = np.geomspace(a, b, n)
        else:
            grid = np.linspace(a, b, n)
        return tuple(float(x) for x in grid)
    if not isinstance(value, list):
        raise SpecError(f"{src}: {where} = {_fmt(value)}: expected a list of numbers, got "
                        f"{type(value).__name__}")
    if not value:
        raise SpecError(f"{src}: {where} = []: empty grid (give at least one value)")
    vals = tuple(_number(src, f"{where}[{i}]", v) for i, v in enumerate(value))
    if len(set(vals)) != len(vals):
        raise SpecError(f"{src}: {where} = {_fmt(value)}: repeated values")
    return vals


def _quote(key: str) -> str:
    return f'"{key}"' if "." in key else key


def _spec_folder(src) -> Path:
    return Path(src).parent if Path(src).is_file() else Path.cwd()


def _safe_set_refs(src, value) -> tuple:
    """sweep.safe_sets: a list of "FILE.py:NAME", FILE relative to the spec's folder ->
    the references with absolute paths (SpecError on a malformed one; the files are loaded,
    once, by ``_scenario_info``)."""
    from safewbc_jax.control import safesets

    if not isinstance(value, list) or not all(isinstance(x, str) for x in value):
        raise SpecError(f"{src}: sweep.safe_sets = {_fmt(value)}: expected a list of "
                        "\"FILE.py:NAME\" strings")
    try:
        return tuple(userfile.absolute(ref, _spec_folder(src), "safe set", safesets.SafeSetError)
                     for ref in value)
    except safesets.SafeSetError as e:
        raise SpecError(f"{src}: sweep.safe_sets: {e}") from None


def _scenario_info(src, name, safe_sets=()):
    """(enforced barriers, monitored barriers, outputs, pole counts) of a scenario with
    the user's ``safe_sets``, or a SpecError naming the scenarios there are (the batched
    path runs them all). ``name``: a scenario's name or a user's "ABSOLUTE/FILE.py:NAME"."""
    from safewbc_jax import scenarios
    from safewbc_jax.control import safesets

    known = scenarios.names()
    if not isinstance(name, str) or name not in known and not userfile.is_ref(name):
        raise SpecError(f"{src}: sweep.scenario = {_fmt(name)}: no such scenario; "
                        f"scenarios are {', '.join(known)}, or a Scenario of your own as "
                        "\"FILE.py:NAME\" (FILE from the spec's folder)")
    try:
        sc = scenarios.get_scenario(name, True, safe_sets)
    except safesets.SafeSetError as e:
        raise SpecError(f"{src}: sweep.safe_sets: {e}") from None
    except ValueError as e:          # the user's scenario file
        raise SpecError(f"{src}: sweep.scenario: {e}") from None
    params = sc.default_params()
    return (tuple(b.name for b in sc.barriers), tuple(b.name for b in sc.monitors),
            tuple(o.name for o in sc.outputs),
            {k: int(np.size(v)) for k, v in params.poles.items()}, params,
            PushTable() if sc.push is None else PushTable.of_push(sc.push))


_POLE_RE = re.compile(r"^p([1-9][0-9]*)$")


def _parse_axis(src, key, values, info) -> Axis:
    from safewbc_jax.control.params import SCALARS

    barriers, monitors, outputs, pole_counts = info
    where = f"grid.{_quote(key)}"
    parts = key.split(".")
    head = parts[0]
    bad = lambda why: SpecError(f"{src}: {where}: {why}")  # noqa: E731
    if head == "poles":
        if len(parts) not in (2, 3):
            raise bad("expected poles.BARRIER or poles.BARRIER.pI")
        b = parts[1]
        if b not in pole_counts:
            raise bad(f"no barrier {b!r}; barriers of this scenario are {sorted(pole_counts)}")
        if any(v <= 0 for v in values):
            v = next(v for v in values if v <= 0)
            raise SpecError(f"{src}: {where} = {_fmt(list(values))}: pole {v!r} is not > 0 "
                            "(Theorem 1 needs positive poles)")
        if len(parts) == 2:
            return Axis(key, "poles", b, values)
        m = _POLE_RE.match(parts[2])
        if not m or int(m.group(1)) > pole_counts[b]:
            raise bad(f"{parts[2]!r} is not a pole of {b!r}: it has "
                      f"{', '.join(f'p{i + 1}' for i in range(pole_counts[b]))}")
        return Axis(key, "pole", b, values, int(m.group(1)) - 1)
    if head == "threshold":
        if len(parts) != 2 or parts[1] not in pole_counts:
            raise bad(f"expected threshold.BARRIER with BARRIER one of {sorted(pole_counts)}")
        return Axis(key, "threshold", parts[1], values)
    if head in GAIN_TABLES or head in SCALES:
        if len(parts) != 2 or parts[1] not in outputs:
            raise bad(f"expected {head}.OUTPUT with OUTPUT one of {list(outputs)}")
        if any(v < 0 if head == "weight" else v <= 0 for v in values):
            raise SpecError(f"{src}: {where} = {_fmt(list(values))}: must be "
                            f"{'>= 0' if head == 'weight' else '> 0'}")
        return Axis(key, "gain" if head in GAIN_TABLES else "scale", parts[1], values)
    if head in SCALARS and len(parts) == 1:
        if any(v < 0 for v in values) or head in ("mu", "f_min") and any(v <= 0 for v in values):
            raise SpecError(f"{src}: {where} = {_fmt(list(values))}: must be positive")
        return Axis(key, "scalar", head, values)
    if head == "push" and len(parts) == 2 and parts[1] in PUSH_KEYS:
        _check_push_values(src, where, parts[1], values)
        return Axis(key, "push", parts[1], values)
    raise bad("unknown axis; axes are poles.BARRIER[.pI], threshold.BARRIER, kp|kd|weight.OUTPUT, "
              "kp_scale|kd_scale|weight_scale|gain_scale.OUTPUT, push.magnitude|direction|at|"
              f"duration, or one of {', '.join(SCALARS)}")


def _check_push_values(src, where, key, values):
    if key == "magnitude" and any(v < 0 for v in values):
        raise SpecError(f"{src}: {where} = {_fmt(list(values))}: magnitudes must be >= 0 "
                        "(turn the push with direction)")
    if key == "at" and any(v < 0 for v in values):
        raise SpecError(f"{src}: {where} = {_fmt(list(values))}: push times must be >= 0")
    if key == "duration" and any(v <= 0 for v in values):
        raise SpecError(f"{src}: {where} = {_fmt(list(values))}: push durations must be > 0")


def _table(src, data, name):
    v = data.get(name, {})
    if not isinstance(v, dict):
        raise SpecError(f"{src}: {name} = {_fmt(v)}: expected a table [{name}]")
    return v


def load_spec(path, text: str | None = None) -> SweepSpec:
    """Read and validate a sweep spec (``text`` instead of reading ``path`` when given)."""
    import tomllib

    src = str(path)
    if text is None:
        p = Path(path)
        if not p.is_file():
            raise SpecError(f"sweep spec {src} does not exist")
        text = p.read_text()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SpecError(f"{src}: not valid TOML: {e}") from None
    return parse_spec(data, src)


def parse_spec(data: dict, src: str = "spec") -> SweepSpec:
    for k in data:
        if k not in SECTIONS:
            raise SpecError(f"{src}: unknown key {k!r} = {_fmt(data[k])}; a spec has the tables "
                            f"{', '.join('[' + s + ']' for s in SECTIONS)}")
    sw = _table(src, data, "sweep")
    for k, v in sw.items():
        if k not in SWEEP_KEYS:
            raise SpecError(f"{src}: unknown key sweep.{k} = {_fmt(v)}; "
                            f"known: {', '.join(SWEEP_KEYS)}")
        want = SWEEP_KEYS[k]
        if want is str and not isinstance(v, str) or want is bool and not isinstance(v, bool):
            raise SpecError(f"{src}: sweep.{k} = {_fmt(v)}: expected "
                            f"{'a string' if want is str else 'true or false'}")
    if "scenario" not in sw:
        raise SpecError(f"{src}: sweep.scenario is missing (the scenario to roll out)")
    scenario = sw["scenario"]
    if userfile.is_ref(scenario):          # FILE from the spec's folder
        scenario = userfile.absolute(scenario, _spec_folder(src), "scenario")
    safe_sets = _safe_set_refs(src, sw["safe_sets"]) if "safe_sets" in sw else ()
    barriers, monitors, outputs, pole_counts, defaults, push0 = _scenario_info(src, scenario,
                                                                              safe_sets)
    num = lambda k, **kw: _number(src, f"sweep.{k}", sw[k], **kw) if k in sw else None  # noqa: E731
    duration = num("duration", positive=True)
    settle = num("settle", positive=True)
    control_dt = num("control_dt", positive=True) or 1e-3
    repeats = num("repeats", positive=True, integer=True) or 1
    seed = num("seed", nonneg=True, integer=True) or 0
    batch = num("batch", positive=True, integer=True) or 64
    tol = num("violation_tol", nonneg=True) or 0.0
    barrier_on = sw.get("barrier", True)
    prec = sw.get("precision", "float64")
    from safewbc_jax.control import precision as precision_mod

    try:
        precision_mod.check(prec, "sweep.precision")
    except ValueError as e:
        raise SpecError(f"{src}: {e}") from None
    enforced = barriers if barrier_on else ()
    all_b = tuple(barriers) + tuple(monitors)
    target = sw.get("target")
    if target is None:
        target = barriers[0] if barriers else (monitors[0] if monitors else None)
    elif target not in all_b:
        raise SpecError(f"{src}: sweep.target = {_fmt(target)}: no barrier {target!r} in "
                        f"scenario {scenario!r}; its barriers are {list(all_b) or 'none'}")

    params = _table(src, data, "params")
    from safewbc_jax.control.params import ParamsError, apply_overrides

    try:
        apply_overrides(defaults, params, f"{src}: [params]")
    except ParamsError as e:
        raise SpecError(str(e)) from None

    grid = _table(src, data, "grid")
    info = (barriers, monitors, outputs, pole_counts)
    axes = tuple(_parse_axis(src, k, _axis_values(src, k, v), info) for k, v in grid.items())
    for b in pole_counts:
        whole = [a for a in axes if a.kind == "poles" and a.target == b]
        single = [a for a in axes if a.kind == "pole" and a.target == b]
        if whole and single:
            raise SpecError(f"{src}: grid.\"{whole[0].name}\" and grid.\"{single[0].name}\" "
                            f"both set the poles of {b!r}; sweep one or the other")
    for o in outputs:
        kinds = {a.name.split(".")[0] for a in axes
                 if a.target == o and a.kind in ("gain", "scale")}
        for g in GAIN_TABLES:
            clash = {g, f"{g}_scale"} | ({"gain_scale"} if g in ("kp", "kd") else set())
            if len(kinds & clash) > 1:
                raise SpecError(f"{src}: grid sets {g} of output {o!r} through "
                                f"{sorted(kinds & clash)}; sweep one of them")

    push_tab = _table(src, data, "push")
    push: dict[str, float] = {}
    for k, v in push_tab.items():
        if k not in PUSH_KEYS:
            raise SpecError(f"{src}: unknown key push.{k} = {_fmt(v)}; "
                            f"known: {', '.join(PUSH_KEYS)}")
        if any(a.kind == "push" and a.target == k for a in axes):
            raise SpecError(f"{src}: push.{k} = {_fmt(v)} is also swept as grid.\"push.{k}\"; "
                            "give it in one place")
        push[k] = _number(src, f"push.{k}", v)
        _check_push_values(src, f"push.{k}", k, [push[k]])

    # a swept key's fixed value is unused: the table's default (the fingerprint of a spec
    # does not change with the scenario's own push)
    swept_push = {a.target: getattr(PushTable(), a.target) for a in axes if a.kind == "push"}

    pert_tab = _table(src, data, "perturb")
    perturb: dict[str, float] = {}
    for k, v in pert_tab.items():
        if k not in PERTURB_KEYS:
            raise SpecError(f"{src}: unknown key perturb.{k} = {_fmt(v)}; known: "
                            f"{', '.join(PERTURB_KEYS)}")
        perturb[k] = _number(src, f"perturb.{k}", v, nonneg=True)

    tune = _parse_tune(src, _table(src, data, "tune"), info, axes, target, defaults)

    spec = SweepSpec(path=src, scenario=scenario, barrier=barrier_on, duration=duration,
                     settle=settle, control_dt=control_dt, repeats=repeats, seed=seed,
                     batch=batch, violation_tol=tol, target=target,
                     description=sw.get("description", ""), params=params, axes=axes,
                     push=dataclasses.replace(push0, **swept_push, **push),
                     perturb=PerturbTable(**perturb),
                     tune=tune,
                     barriers=tuple(enforced),
                     monitors=tuple(monitors) + (() if barrier_on else tuple(barriers)),
                     outputs=outputs, pole_counts=pole_counts, safe_sets=safe_sets,
                     precision=prec)
    if spec.n_rollouts > MAX_ROLLOUTS:
        raise SpecError(f"{src}: the grid times sweep.repeats gives {spec.n_rollouts} rollouts "
                        f"(more than {MAX_ROLLOUTS}); shrink the grid")
    return spec


# --------------------------------------------------------------------------------------
# The [tune] table
# --------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class TuneParam:
    """One tuned parameter: the ``axis`` it sets (any controller axis of [grid]), its
    bounds, its scale ("log" or "linear") and the search's start value (None: the spec's
    value, clipped into the bounds)."""

    axis: Axis
    lo: float
    hi: float
    scale: str
    start: float | None = None

    @property
    def name(self) -> str:
        return self.axis.name

    def to_value(self, u):
        """Unit-box coordinate(s) in [0, 1] -> parameter value(s)."""
        u = np.clip(np.asarray(u, float), 0.0, 1.0)
        if self.scale == "log":
            return np.exp(np.log(self.lo) + u * (np.log(self.hi) - np.log(self.lo)))
        return self.lo + u * (self.hi - self.lo)

    def to_unit(self, v):
        v = np.clip(np.asarray(v, float), self.lo, self.hi)
        if self.scale == "log":
            return (np.log(v) - np.log(self.lo)) / (np.log(self.hi) - np.log(self.lo))
        return (v - self.lo) / (self.hi - self.lo)


@dataclasses.dataclass(frozen=True)
class TuneTable:
    """The spec's ``[tune]``, checked, with its defaults. ``objective``: the metric names,
    ``weights``: {metric: weight} (tune.objective as a table, or 1.0 each); ``barrier``:
    the barrier whose poles tune-poles tunes (None: none enforced); ``params``: the tuned
    parameters (empty: the tune-poles preset); ``population`` and ``budget`` None: the
    tuner's defaults."""

    objective: tuple[str, ...]
    weights: dict[str, float]
    barrier: str | None = None
    method: str = "cmaes"
    params: tuple[TuneParam, ...] = ()
    rounds: int = 3
    points: int = 4
    shrink: float = 0.5
    pole_min: float = 0.5
    pole_max: float = 200.0
    equal_poles: bool = False
    population: int | None = None
    sigma: float = 0.3
    budget: int | None = None
    validate: int = 64


def _parse_objective(src, v, outputs) -> dict:
    """tune.objective: a list of metric names (weights 1) or a table {name = weight}."""
    allowed = ([f"tracking_rms.{o}" for o in outputs] + list(OBJECTIVE_METRICS)
               + list(MARGIN_METRICS))
    if isinstance(v, str):
        v = [v]
    if isinstance(v, list):
        if not v or not all(isinstance(x, str) for x in v):
            raise SpecError(f"{src}: tune.objective = {_fmt(v)}: expected a non-empty list "
                            "of metric names such as \"tracking_rms.com\", or a table "
                            "{name = weight}")
        v = {x: 1.0 for x in v}
    if not isinstance(v, dict) or not v:
        raise SpecError(f"{src}: tune.objective = {_fmt(v)}: expected a list of metric names "
                        "or a table {name = weight}")
    out = {}
    for x, w in v.items():
        if x not in allowed:
            raise SpecError(f"{src}: tune.objective = {_fmt(v)}: {x!r} is not a "
                            f"metric to minimize in this scenario; use {', '.join(allowed)}")
        w = _number(src, f"tune.objective.{_quote(x)}", w)
        if x in MARGIN_METRICS and w > 0:
            raise SpecError(f"{src}: tune.objective.{x} = {w!r}: {x} is a margin (larger is "
                            "better); give it a negative weight to reward it")
        if w == 0:
            raise SpecError(f"{src}: tune.objective.{_quote(x)} = 0: a zero weight; leave "
                            "the metric out")
        out[x] = w
    return out


def _parse_tune_param(src, key, value, info, axes, defaults) -> TuneParam:
    where = f"tune.params.{_quote(key)}"
    if isinstance(value, list):
        value = {"bounds": value}
    if not isinstance(value, dict):
        raise SpecError(f"{src}: {where} = {_fmt(value)}: expected [low, high] or "
                        "{ bounds = [low, high], scale = \"log\" | \"linear\", start = x }")
    for k in value:
        if k not in PARAM_KEYS:
            raise SpecError(f"{src}: unknown key {where}.{k} = {_fmt(value[k])}; known: "
                            f"{', '.join(PARAM_KEYS)}")
    b = value.get("bounds")
    if not isinstance(b, list) or len(b) != 2:
        raise SpecError(f"{src}: {where}.bounds = {_fmt(b)}: expected [low, high]")
    lo = _number(src, f"{where}.bounds[0]", b[0])
    hi = _number(src, f"{where}.bounds[1]", b[1])
    if not lo < hi:
        raise SpecError(f"{src}: {where}.bounds = {_fmt(b)}: low must be below high")
    if key.split(".")[0] == "push":
        raise SpecError(f"{src}: {where}: pushes are the distribution a candidate must "
                        "survive, not a parameter to tune; sweep them in [grid]")
    if key.split(".")[0] == "threshold":
        raise SpecError(f"{src}: {where}: a threshold defines the safe set itself; tuning "
                        "it would move the constraint (fix it in [params])")
    axis = _parse_axis(src, key, (lo, hi), info)
    scale = value.get("scale", "log" if lo > 0 else "linear")
    if scale not in ("log", "linear"):
        raise SpecError(f"{src}: {where}.scale = {_fmt(scale)}: expected \"log\" or \"linear\"")
    if scale == "log" and lo <= 0:
        raise SpecError(f"{src}: {where}: scale = \"log\" needs bounds > 0, got {_fmt(b)}")
    start = value.get("start")
    if start is not None:
        start = _number(src, f"{where}.start", start)
        if not lo <= start <= hi:
            raise SpecError(f"{src}: {where}.start = {start!r}: outside the bounds {_fmt(b)}")
    return TuneParam(axis, lo, hi, scale, start)


def _parse_tune(src, tab, info, axes, target, defaults) -> TuneTable:
    """The [tune] table of ``safewbc tune`` (and its ``tune-poles`` preset), every key
    checked here, before anything compiles."""
    barriers, monitors, outputs, pole_counts = info
    tune: dict[str, Any] = {}
    for k, v in tab.items():
        if k not in TUNE_KEYS:
            raise SpecError(f"{src}: unknown key tune.{k} = {_fmt(v)}; "
                            f"known: {', '.join(TUNE_KEYS)}")
        if k == "objective":
            tune["weights"] = _parse_objective(src, v, outputs)
        elif k == "barrier":
            if not isinstance(v, str) or v not in barriers:
                raise SpecError(f"{src}: tune.barrier = {_fmt(v)}: not an enforced barrier of "
                                f"this scenario; enforced: {list(barriers) or 'none'}")
            tune[k] = v
        elif k == "equal_poles":
            if not isinstance(v, bool):
                raise SpecError(f"{src}: tune.equal_poles = {_fmt(v)}: expected true or false")
            tune[k] = v
        elif k == "method":
            if v not in TUNE_METHODS:
                raise SpecError(f"{src}: tune.method = {_fmt(v)}: expected one of "
                                f"{', '.join(TUNE_METHODS)}")
            tune[k] = v
        elif k == "params":
            if not isinstance(v, dict) or not v:
                raise SpecError(f"{src}: tune.params = {_fmt(v)}: expected a table of "
                                "parameters to tune, e.g. \"poles.left_fist.p1\" = "
                                "{ bounds = [2.0, 200.0] }")
            tune[k] = tuple(_parse_tune_param(src, kk, vv, info, axes, defaults)
                            for kk, vv in v.items())
        elif k in ("rounds", "points", "population", "budget", "validate"):
            tune[k] = _number(src, f"tune.{k}", v, positive=k != "validate", nonneg=True,
                              integer=True)
            if k == "points" and tune[k] < 2:
                raise SpecError(f"{src}: tune.points = {v!r}: needs at least 2 per pole")
            if k == "population" and tune[k] < 2:
                raise SpecError(f"{src}: tune.population = {v!r}: CMA-ES needs at least 2 "
                                "candidates a generation")
        else:
            tune[k] = _number(src, f"tune.{k}", v, positive=True)
    weights = tune.pop("weights", None) or {f"tracking_rms.{o}": 1.0 for o in outputs}
    tune.setdefault("barrier", target if target in barriers else None)
    t = TuneTable(objective=tuple(weights), weights=weights, **tune)
    if not 0 < t.shrink < 1:
        raise SpecError(f"{src}: tune.shrink = {t.shrink!r}: must be between 0 and 1")
    if not 0 < t.sigma <= 1:
        raise SpecError(f"{src}: tune.sigma = {t.sigma!r}: the initial step as a "
                        "fraction of each parameter's range (log range on a log scale) must be "
                        "in (0, 1]")
    if t.pole_min >= t.pole_max:
        raise SpecError(f"{src}: tune.pole_min = {t.pole_min!r} must be below "
                        f"tune.pole_max = {t.pole_max!r}")
    return t
