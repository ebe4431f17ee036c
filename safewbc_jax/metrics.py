"""Run summaries with the names ``metrics.json`` uses (shared by the MuJoCo loop and the
batched MJX rollouts)."""

from __future__ import annotations

import numpy as np

TRACKING_SKIP_S = 0.5   # tracking RMS counts from this long after the motion starts
LATENCY_SKIP = 20       # first control steps (compilation, caches) left out of latency


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def _tracking_rms(err):
    """RMS over time of the error norm and of each component; a NaN component (no
    reference: not an output in that domain, e.g. the CoM x, y while walking) is left out
    of that time step (walking runs only: a diverged rollout's NaN must stay visible)."""
    fin = np.isfinite(err)
    rows = fin.any(axis=1)
    norm = _rms(np.sqrt(np.sum(np.where(fin, err, 0.0) ** 2, axis=1))[rows])
    comps = [_rms(err[fin[:, i], i]) for i in range(err.shape[1])]
    return norm, comps


def summarize(log: dict, run: dict, scenario_name: str, control_dt: float,
              solver: str = "piqp", threshold_of=None) -> dict:
    tau = log["tau"]
    motion = tau >= 0
    track = tau >= TRACKING_SKIP_S
    tracking, components = {}, {}
    for nm in run["outputs"]:
        err = log[f"y_{nm}"] - log[f"yd_{nm}"]
        if run.get("walking"):
            tracking[nm], comps = _tracking_rms(err[track])
        else:
            tracking[nm] = _rms(np.linalg.norm(err[track], axis=1))
            comps = [_rms(err[track, i]) for i in range(err.shape[1])]
        for i, c in enumerate(comps):
            components[f"{nm}[{i}]"] = c
    lat = log["t_qp"] + log["t_solve"]
    lat = lat[LATENCY_SKIP:] if lat.size > LATENCY_SKIP else lat
    pct = lambda a, p: float(np.percentile(a, p)) if a.size else float("nan")  # noqa: E731
    fb = log["fallback"]
    barrier_min = {}
    for name in run["barriers"] + run["monitors"]:
        h = log[f"h_{name}"]
        barrier_min[name] = float(np.min(h)) if h.size else float("nan")
    zmp = log["zmp_margin"]
    u = log["u"]
    out = {
        "scenario": scenario_name,
        "solver": solver,
        "sim_dt": run["sim_dt"],
        "control_dt": control_dt,
        "duration_s": float(max(tau[-1], 0.0) + control_dt) if tau.size else 0.0,
        "settle_s": run["settle"],
        "fell": bool(run["fell"]),
        "control_steps": int(tau.size),
        "qp_solved": int(np.sum(fb == "none")),
        "qp_failed": int(np.sum(fb == "failed")),
        "fallbacks": int(np.sum(fb == "relaxed")),
        "step_latency_us": {"p50": pct(lat, 50), "p99": pct(lat, 99)},
        "latency_breakdown_us_p50": {"terms_and_assembly": pct(log["t_qp"][LATENCY_SKIP:], 50),
                                     "solve": pct(log["t_solve"][LATENCY_SKIP:], 50)},
        "eq_residual_max": float(np.nanmax(log["eq_residual"])) if np.any(np.isfinite(log["eq_residual"])) else float("nan"),
        "tracking_rms": tracking,
        "tracking_rms_components": components,
        "barrier_min": barrier_min,
        "barriers_enforced": run["barriers"],
        "zmp_margin_min": float(np.nanmin(zmp[motion])) if np.any(motion) and np.any(np.isfinite(zmp[motion])) else float("nan"),
        "foot_slip_max": float(np.max(log["slip"])) if log["slip"].size else 0.0,
        "torque_ratio_max": float(np.max(np.abs(u) / run["torque_limit"])) if u.size else 0.0,
        "loop_residual_max": float(np.max(log["loop_residual"])) if log["loop_residual"].size else 0.0,
        "compile_s": float(log.get("compile_s", np.nan)),
    }
    if run.get("walking"):
        t = log["t"]
        walk = tau >= 0
        com = log["y_com"]
        tw = t[walk]
        if tw.size > 2:
            half = tw[0] + 0.5 * (tw[-1] - tw[0])
            i0, i1 = np.searchsorted(t, half), len(t) - 1
            out["avg_forward_speed"] = float((com[i1, 0] - com[i0, 0]) / max(t[i1] - t[i0], 1e-9))
        else:
            out["avg_forward_speed"] = float("nan")
        out["steps_taken"] = int(run["steps_taken"])
        lc = log["leg_contact"].astype(bool)
        out["leg_collisions"] = int(np.sum(lc[1:] & ~lc[:-1]) + (lc[0] if lc.size else 0))
        out["leg_contact_steps"] = int(np.sum(lc))
        ss = walk & (log["stance"] != 0)
        out["swing_clearance_min"] = float(np.min(log["clearance"][ss])) if np.any(ss) else float("nan")
        out["missed_touchdowns"] = int(log["missed_touchdowns"][-1]) if log["missed_touchdowns"].size else 0
    if "torso" in run["outputs"] and np.any(motion):
        pitch, pitch_d = log["y_torso"][motion, 1], log["yd_torso"][motion, 1]
        out["torso_pitch_max_reached"] = float(np.max(pitch))
        out["torso_pitch_ref_max"] = float(np.max(pitch_d))
    return out
