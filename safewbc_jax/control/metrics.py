"""The run metrics, defined once: init / accumulate / finalize.

Two accumulators, written for numpy or jax.numpy (``xp``) so that the same function runs
traced in JAX or, per step, in numpy:

* ``ControlAcc``: what the controller sees: QP outcomes, refused measurements, tracking,
  barrier minima, ZMP margin, torque ratio, the equality residual, walking's forward speed;
* ``PlantAcc``: what a simulator measures of the robot, from its own sensing: foot slip,
  loop-closure residual, leg-on-leg contacts, the swing clearance, the fall.

``finalize`` turns both into the flat metric columns (names of ``metrics.json``, nested
names joined by "."; arrays with a leading batch axis come out as arrays), and
``summarize`` into the nested ``metrics.json`` of one run.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from safewbc_jax.control import gait as gait_mod

TRACKING_SKIP_S = 0.5   # tracking RMS counts from this long after the motion starts
LATENCY_SKIP = 20       # first control steps (compilation, caches) left out of latency
NO_HALF = -1.0          # t_half of a run whose forward speed is not measured


class ControlAcc(NamedTuple):
    """Running controller-side metrics (one robot; a leading batch axis in the batch)."""

    steps: Any          # accepted measurements
    bad: Any            # refused measurements
    n_none: Any
    n_relaxed: Any
    n_failed: Any
    track_sq: dict         # output -> (dim,) sum of squared errors of tracked components
    track_n: dict          # output -> (dim,) steps each component was tracked
    track_rows: dict       # output -> steps with any component tracked
    y_max: dict            # output -> (dim,) max over the motion of y and of y^d
    yd_max: dict
    h_min: dict            # barrier or monitor -> min h
    zmp_min: Any
    torque_max: Any
    eq_max: Any
    com_x_half: Any     # walking: CoM x where the second half of the motion begins,
    t_half_seen: Any    # the time it was taken at (NaN: not yet), the last CoM x and
    com_x_end: Any      # its time
    t_end: Any


def control_init(scenario, xp=np, dtype=np.float64) -> ControlAcc:
    z = xp.zeros((), dtype)
    i0 = xp.zeros((), np.int32)
    inf, nan = xp.asarray(np.inf, dtype), xp.asarray(np.nan, dtype)
    outs = scenario.outputs
    return ControlAcc(
        steps=i0, bad=i0, n_none=i0, n_relaxed=i0, n_failed=i0,
        track_sq={o.name: xp.zeros(o.dim, dtype) for o in outs},
        track_n={o.name: xp.zeros(o.dim, np.int32) for o in outs},
        track_rows={o.name: i0 for o in outs},
        y_max={o.name: xp.full(o.dim, -np.inf, dtype) for o in outs},
        yd_max={o.name: xp.full(o.dim, -np.inf, dtype) for o in outs},
        h_min={b.name: inf for b in scenario.barriers + scenario.monitors},
        zmp_min=inf, torque_max=z, eq_max=xp.asarray(-np.inf, dtype),
        com_x_half=nan, t_half_seen=nan, com_x_end=nan, t_end=nan)


def control_refused(acc: ControlAcc, refused, xp=np) -> ControlAcc:
    """Count a refused measurement (``refused`` True)."""
    return acc._replace(bad=acc.bad + xp.where(refused, 1, 0).astype(np.int32))


def control_accumulate(acc: ControlAcc, rec, t_rel, t_half, torque_limit, xp=np) -> ControlAcc:
    """One step's ``control_step.StepRecord`` into the accumulator. ``t_rel``: time since
    the first measurement (s); ``t_half``: where the forward speed's window begins
    (negative: not measured). Refused steps (``rec.ok`` False) count only as refused.

    Tracking counts from TRACKING_SKIP_S into the motion; a component whose reference is
    NaN (not tracked in this domain) is left out of that step. The ZMP margin counts in
    the motion, where the QP was solved; a margin of -inf (no normal force under the feet,
    a robot falling) is kept."""
    from safewbc_jax.solvers.result import FALLBACK_FAILED, FALLBACK_NONE, FALLBACK_RELAXED

    ok, tau = rec.ok, rec.tau
    cnt = lambda c: xp.where(ok & c, 1, 0).astype(np.int32)  # noqa: E731
    track = ok & (tau >= TRACKING_SKIP_S)
    motion = ok & (tau >= 0)
    sq, n, rows, ymax, ydmax = {}, {}, {}, {}, {}
    for name, y in rec.y.items():
        yd = rec.yd[name]
        fin = xp.isfinite(yd) & track
        err = xp.where(fin, y - xp.where(fin, yd, 0.0), 0.0)
        sq[name] = acc.track_sq[name] + err ** 2
        n[name] = acc.track_n[name] + fin.astype(np.int32)
        rows[name] = acc.track_rows[name] + xp.where(xp.any(fin), 1, 0).astype(np.int32)
        ymax[name] = xp.where(motion, xp.maximum(acc.y_max[name], y), acc.y_max[name])
        ydmax[name] = xp.where(motion & xp.isfinite(yd), xp.maximum(acc.yd_max[name], yd),
                               acc.yd_max[name])
    h_min = {k: xp.where(ok, xp.minimum(acc.h_min[k], rec.h[k]), acc.h_min[k]) for k in acc.h_min}
    zmp_ok = motion & (rec.fallback != FALLBACK_FAILED) & ~xp.isnan(rec.zmp_margin)
    ratio = xp.max(xp.abs(rec.u) / torque_limit)
    eq_ok = ok & xp.isfinite(rec.eq_residual)
    acc = acc._replace(
        steps=acc.steps + cnt(True), n_none=acc.n_none + cnt(rec.fallback == FALLBACK_NONE),
        n_relaxed=acc.n_relaxed + cnt(rec.fallback == FALLBACK_RELAXED),
        n_failed=acc.n_failed + cnt(rec.fallback == FALLBACK_FAILED),
        track_sq=sq, track_n=n, track_rows=rows, y_max=ymax, yd_max=ydmax, h_min=h_min,
        zmp_min=xp.where(zmp_ok, xp.minimum(acc.zmp_min, rec.zmp_margin), acc.zmp_min),
        torque_max=xp.where(ok, xp.maximum(acc.torque_max, ratio), acc.torque_max),
        eq_max=xp.where(eq_ok, xp.maximum(acc.eq_max, rec.eq_residual), acc.eq_max))
    if "com" in rec.y:
        com_x = rec.y["com"][0]
        half = ok & (t_half >= 0) & xp.isnan(acc.t_half_seen) & (t_rel >= t_half)
        acc = acc._replace(com_x_half=xp.where(half, com_x, acc.com_x_half),
                           t_half_seen=xp.where(half, t_rel, acc.t_half_seen),
                           com_x_end=xp.where(ok, com_x, acc.com_x_end),
                           t_end=xp.where(ok, t_rel, acc.t_end))
    return control_refused(acc, ~ok, xp)


def half_time(n_steps: int, settle: float, dt: float) -> float:
    """Where the second half of a motion of ``n_steps`` control steps after ``settle``
    begins, in s after the first step (the first step time at or after the midpoint of the
    motion's first and last step times), minus half a step (so that the step at that time
    passes ``t_rel >= t_half`` whatever the rounding); NO_HALF if the motion has fewer
    than 3 steps."""
    t = np.arange(n_steps) * dt
    tw = t[t - settle >= 0]
    if tw.size <= 2:
        return NO_HALF
    return float(t[np.searchsorted(t, tw[0] + 0.5 * (tw[-1] - tw[0]))] - 0.5 * dt)


class PlantAcc(NamedTuple):
    """Running simulator-side metrics."""

    slip_max: Any
    loop_max: Any
    legs_prev: Any
    leg_collisions: Any
    leg_contact_steps: Any
    clearance_min: Any


def plant_init(xp=np, dtype=np.float64) -> PlantAcc:
    z = xp.zeros((), dtype)
    i0 = xp.zeros((), np.int32)
    return PlantAcc(slip_max=z, loop_max=z, legs_prev=xp.asarray(False), leg_collisions=i0,
                    leg_contact_steps=i0, clearance_min=xp.asarray(np.inf, dtype))


def plant_accumulate(acc: PlantAcc, live, rec, soles, soles0_xy, loop_residual, legs,
                     xp=np) -> PlantAcc:
    """One step's simulator measurements after its physics, where ``live``: ``soles``
    (2, 3) the left and right sole positions, ``soles0_xy`` (2, 2) where they stood at
    the start, the largest loop-closure residual (m), whether a leg touches the other.
    ``rec`` (the step's StepRecord) gives the domain: in single support the slip is the
    stance sole's, from where its step began; the swing clearance (left sole y minus
    right sole y) counts in single support during the motion. Every argument may carry
    the same leading batch axes."""
    single = rec.stance != 0
    stance_xy = xp.where((rec.stance > 0)[..., None], soles[..., 0, :2], soles[..., 1, :2])
    slip = xp.where(single, xp.linalg.norm(stance_xy - rec.stance0[..., :2], axis=-1),
                    xp.max(xp.linalg.norm(soles[..., :2] - soles0_xy, axis=-1), axis=-1))
    clearance = soles[..., 0, 1] - soles[..., 1, 1]
    ss = live & (rec.tau >= 0) & single
    mx = lambda old, new: xp.where(live, xp.maximum(old, new), old)  # noqa: E731
    i = lambda c: xp.where(c, 1, 0).astype(np.int32)  # noqa: E731
    return acc._replace(
        slip_max=mx(acc.slip_max, slip), loop_max=mx(acc.loop_max, loop_residual),
        leg_collisions=acc.leg_collisions + i(live & legs & ~acc.legs_prev),
        leg_contact_steps=acc.leg_contact_steps + i(live & legs),
        legs_prev=xp.where(live, legs, acc.legs_prev),
        clearance_min=xp.where(ss, xp.minimum(acc.clearance_min, clearance), acc.clearance_min))


def _finite_or_nan(a, empty):
    """``empty`` (+inf for minima, -inf for maxima never updated) -> NaN."""
    a = np.asarray(a, float)
    return np.where(a == empty, np.nan, a)


def finalize(scenario, acc: ControlAcc, plant: PlantAcc | None, fell, gait_state=()) -> dict:
    """Flat metric columns (numpy; a leading batch axis stays): names as in
    ``metrics.json`` with nested names joined by "." (``tracking_rms.com``,
    ``tracking_rms_components.com[0]``, ``barrier_min.left_fist``).

    Args:
        scenario: the run's ``Scenario``: an output's ``extremes`` components give the
            columns ``{label}_max_reached`` and ``{label}_ref_max`` (maxima over the motion
            of y and of y^d); its gait, if any, its own columns (``control.gait``) and the
            stepping columns (forward speed, leg contacts, swing clearance).
        acc: the controller's accumulators.
        plant: the simulator's, or None (a real robot).
        fell: whether the robot fell.
        gait_state: the gait's state at the end of the run (() without a gait).

    Returns:
        {column name: value}.
    """
    a = lambda x: np.asarray(x)  # noqa: E731
    out = {"fell": a(fell), "control_steps": a(acc.steps), "bad_measurements": a(acc.bad),
           "qp_solved": a(acc.n_none), "qp_failed": a(acc.n_failed),
           "fallbacks": a(acc.n_relaxed),
           "zmp_margin_min": _finite_or_nan(acc.zmp_min, np.inf),
           "torque_ratio_max": a(acc.torque_max),
           "eq_residual_max": _finite_or_nan(acc.eq_max, -np.inf)}
    if plant is not None:
        out.update({"foot_slip_max": a(plant.slip_max), "loop_residual_max": a(plant.loop_max)})
    for name, sq in acc.track_sq.items():
        sq, n, rows = a(sq), a(acc.track_n[name]), a(acc.track_rows[name])
        out[f"tracking_rms.{name}"] = np.where(
            rows > 0, np.sqrt(np.sum(sq, -1) / np.maximum(rows, 1)), np.nan)
        for i in range(sq.shape[-1]):
            out[f"tracking_rms_components.{name}[{i}]"] = np.where(
                n[..., i] > 0, np.sqrt(sq[..., i] / np.maximum(n[..., i], 1)), np.nan)
    for name, h in acc.h_min.items():
        out[f"barrier_min.{name}"] = _finite_or_nan(h, np.inf)
    for o in scenario.outputs:
        for i in getattr(o, "extremes", ()):
            label = o.labels[i]
            out[f"{label}_max_reached"] = _finite_or_nan(a(acc.y_max[o.name])[..., i], -np.inf)
            out[f"{label}_ref_max"] = _finite_or_nan(a(acc.yd_max[o.name])[..., i], -np.inf)
    gait_columns = gait_mod.columns(scenario.gait, gait_state)
    if gait_columns is not None:
        span = a(acc.t_end) - a(acc.t_half_seen)
        ok = ~a(fell) & np.isfinite(span) & (span > 0)
        out["avg_forward_speed"] = np.where(
            ok, (a(acc.com_x_end) - a(acc.com_x_half)) / np.where(ok, span, 1.0), np.nan)
        out.update({k: a(v) for k, v in gait_columns.items()})
        if plant is not None:
            out["leg_collisions"] = a(plant.leg_collisions)
            out["leg_contact_steps"] = a(plant.leg_contact_steps)
            out["swing_clearance_min"] = _finite_or_nan(plant.clearance_min, np.inf)
    return out


# the metric columns of a sweep's table: ``finalize``'s, less the per-component tracking
# and the outputs' extremes (a single run's metrics.json has them), plus fell_time_s
SINGLE_RUN_ONLY = ("tracking_rms_components.",)
EXTREMES = ("_max_reached", "_ref_max")


def table_columns(flat: dict, fell_step, control_dt: float) -> dict:
    """``finalize``'s columns as a sweep table has them (``SINGLE_RUN_ONLY`` left out),
    with ``fell_time_s``: the time of the control step the robot fell at (``fell_step``,
    -1 where it did not: NaN)."""
    out = {k: np.asarray(v) for k, v in flat.items()
           if not (k.startswith(SINGLE_RUN_ONLY) or k.endswith(EXTREMES))}
    fs = np.asarray(fell_step)
    out["fell_time_s"] = np.where(fs >= 0, fs * float(control_dt), np.nan)
    return out


def nest(flat: dict) -> dict:
    """Flat columns of one run -> the nested dict of ``metrics.json`` (Python scalars)."""
    out: dict[str, Any] = {}
    for key, val in flat.items():
        val = np.asarray(val)
        val = bool(val) if val.dtype == bool else (int(val) if val.dtype.kind in "iu"
                                                    else float(val))
        head, _, tail = key.partition(".")
        if tail:
            out.setdefault(head, {})[tail] = val
        else:
            out[key] = val
    return out


def latency(t_qp, t_solve, control_dt=None) -> dict:
    """p50 / p99 / max of the controller step's wall time and its parts (us), the first
    LATENCY_SKIP steps left out; with ``control_dt`` (s) the deadline misses: the steps
    whose wall time exceeds the control period, counted and as a fraction of the steps."""
    t_qp, t_solve = np.asarray(t_qp, float), np.asarray(t_solve, float)
    lat = t_qp + t_solve
    skip = LATENCY_SKIP if lat.size > LATENCY_SKIP else 0
    pct = lambda x, p: float(np.percentile(x[skip:], p)) if x[skip:].size else float("nan")  # noqa: E731
    out = {"step_latency_us": {"p50": pct(lat, 50), "p99": pct(lat, 99), "max": pct(lat, 100)},
           "latency_breakdown_us_p50": {"terms_and_assembly": pct(t_qp, 50),
                                        "solve": pct(t_solve, 50)}}
    if control_dt is not None:
        out["deadline_misses"] = deadline_misses(lat[skip:], control_dt)
    return out


def deadline_misses(step_us, control_dt) -> dict:
    """The steps whose wall time (us) exceeds the control period ``control_dt`` (s):
    {"period_us", "count", "rate"} (rate NaN without steps)."""
    step_us = np.asarray(step_us, float)
    period = 1e6 * float(control_dt)
    late = int(np.count_nonzero(step_us > period))
    return {"period_us": period, "count": late,
            "rate": late / step_us.size if step_us.size else float("nan")}


def summarize(flat: dict, info: dict, scenario_name: str, control_dt: float,
              solver: str = "piqp") -> dict:
    """``metrics.json`` of one run: the run's description (``info``: sim_dt, duration_s,
    settle, barriers, t_qp and t_solve in us per step, compile_s), the latencies, and the
    finalized metrics (``finalize``), nested."""
    m = nest(flat)
    out = {"scenario": scenario_name, "solver": solver,
           "engine": info.get("engine", "xla"), "sim_dt": info["sim_dt"],
           "control_dt": control_dt, "duration_s": info["duration_s"],
           "settle_s": info["settle"]}
    for k in ("fell", "control_steps", "bad_measurements", "qp_solved", "qp_failed",
              "fallbacks"):
        out[k] = m.pop(k)
    out.update(latency(info["t_qp"], info["t_solve"], control_dt))
    out["eq_residual_max"] = m.pop("eq_residual_max")
    for k in ("tracking_rms", "tracking_rms_components", "barrier_min"):
        out[k] = m.pop(k, {})
    # in the scenario's order (a dict through jax's tree functions comes back key-sorted)
    order = {n: i for i, n in enumerate(list(info["outputs"]) + list(info["barriers"])
                                        + list(info.get("monitors", ())))}
    for k in ("tracking_rms", "tracking_rms_components", "barrier_min"):
        out[k] = dict(sorted(out[k].items(),
                             key=lambda kv: (order.get(kv[0].split("[")[0], len(order)),
                                             kv[0])))
    out["barriers_enforced"] = list(info["barriers"])
    for k in ("zmp_margin_min", "foot_slip_max", "torque_ratio_max", "loop_residual_max"):
        out[k] = m.pop(k)
    out["compile_s"] = float(info.get("compile_s", np.nan))
    out.update(m)   # the outputs' extremes, the gait's columns
    return out
