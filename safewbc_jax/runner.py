"""``safewbc run SCENARIO``: a deployment run in MuJoCo with its outputs on disk."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from safewbc_jax import plots, scenarios
from safewbc_jax.metrics import summarize
from safewbc_jax.params import apply_overrides, load_overrides


def check_video_backend(path: str) -> None:
    """Fail early, before any compile, when a video cannot be written."""
    if not path.endswith(".mp4"):
        raise ValueError(f"--video {path!r}: the file name must end in .mp4")
    try:
        import imageio.v3  # noqa: F401
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise RuntimeError("--video needs imageio and imageio-ffmpeg: "
                           "pip install 'safewbc-jax[video]'") from None
    import mujoco

    try:
        r = mujoco.Renderer(mujoco.MjModel.from_xml_string("<mujoco/>"), 32, 32)
        r.close()
    except Exception as e:  # noqa: BLE001
        raise RuntimeError(
            f"--video: MuJoCo cannot render offscreen here ({e}). Install a GL backend and "
            "select it, e.g. 'apt-get install libegl1' with MUJOCO_GL=egl, or "
            "'apt-get install libosmesa6' with MUJOCO_GL=osmesa.") from None


# Default push start (s after walking starts): 0.05 s into the fourth step, a right-stance
# step of the default walk, where a push to the right (-y) carries the CoM over the stance
# foot and the planner pulls the left swing foot in towards it (the paper's collision case).
PUSH_AT = 2.55


def run_scenario(name: str, *, duration=None, out=None, barrier=True, params_file=None,
                 video=None, settle=None, control_dt=1e-3, quiet=False,
                 record_qps_every=0, speed=0.2, push=None, push_at=None, push_for=0.15) -> dict:
    """Validate everything, run, write metrics.json, log.npz and figures; return metrics."""
    from safewbc_jax.sim.mujoco_loop import RunConfig, run

    scenario = scenarios.get_scenario(name, barrier)
    if name == "push" and push is None:
        push = (0.0, -30.0, 0.0)  # the paper's lateral push
    if push is not None and (len(push) != 3 or not all(np.isfinite(push))):
        raise ValueError(f"--force must be three finite numbers FX,FY,FZ, got {push!r}")
    if push_at is None:
        push_at = PUSH_AT
    if push_for <= 0:
        raise ValueError(f"--for must be positive, got {push_for}")
    params = scenario.default_params()
    if params_file is not None:
        params = apply_overrides(params, load_overrides(params_file), str(params_file))
    if duration is not None and not duration > 0:
        raise ValueError(f"--duration must be positive, got {duration}")
    if video:
        check_video_backend(video)
    out_dir = Path(out) if out else Path("runs") / (name + ("" if barrier else "_no_barrier"))
    out_dir.mkdir(parents=True, exist_ok=True)
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))  # noqa: E731
    say(f"[safewbc] {name}: compiling the controller (about a minute on a 2-core CPU) ...")
    cfg = RunConfig(duration=duration, control_dt=control_dt, barrier_on=barrier, settle=settle,
                    record_qps_every=record_qps_every, speed=speed,
                    push_force=None if push is None else tuple(float(f) for f in push),
                    push_at=push_at, push_for=push_for)
    log, info = run(scenario, params, cfg,
                    progress=None if quiet else lambda k, n: say(f"[safewbc] step {k}/{n}"))
    metrics = summarize(log, info, name, control_dt)
    metrics["barrier_on"] = bool(barrier)
    if push is not None:
        metrics["push"] = {"force_N": list(cfg.push_force), "at_s": push_at, "for_s": push_for}
    metrics["threshold"] = {k: float(v) for k, v in params.threshold.items()}
    metrics["poles"] = {k: np.asarray(v).tolist() for k, v in params.poles.items()}
    (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
    qps = {k: v for k, v in log.items() if k.startswith("qp_")}
    np.savez_compressed(out_dir / "log.npz", **{k: v for k, v in log.items()
                                                 if v.dtype != object and k not in qps})
    if qps:
        np.savez_compressed(out_dir / "qps.npz", **qps)
    labels = {o.name: list(o.labels) for o in scenario.outputs}
    plots.output_figures(log, info, labels, out_dir)
    plots.barrier_figure(log, info, out_dir, f"{name}: barrier values"
                         + ("" if barrier else " (--no-barrier)"))
    if info.get("walking"):
        plots.walking_figures(log, info, out_dir)
    if video:
        from safewbc_jax.sim.video import render_video

        render_video(log, video)
    return metrics


def format_summary(m: dict) -> str:
    lines = [f"scenario {m['scenario']}  ({m['duration_s']:.2f} s of motion after {m['settle_s']} s "
             f"standing; barrier {'on' if m['barrier_on'] else 'off'})",
             f"  fell: {m['fell']}   QPs solved {m['qp_solved']}, fallbacks {m['fallbacks']}, "
             f"failed {m['qp_failed']}",
             f"  step latency p50 {m['step_latency_us']['p50']:.0f} us, p99 "
             f"{m['step_latency_us']['p99']:.0f} us  (terms + assembly "
             f"{m['latency_breakdown_us_p50']['terms_and_assembly']:.0f} / solve "
             f"{m['latency_breakdown_us_p50']['solve']:.0f})",
             "  tracking RMS: " + ", ".join(f"{k} {v:.4f}" for k, v in m["tracking_rms"].items())]
    if m["barrier_min"]:
        lines.append("  barrier min h: " + ", ".join(f"{k} {v * 1000:+.1f} mm"
                                                     for k, v in m["barrier_min"].items()))
    if "avg_forward_speed" in m:
        lines.append(f"  walking: avg forward speed {m['avg_forward_speed']:.3f} m/s, steps "
                     f"{m['steps_taken']}, leg collisions {m['leg_collisions']}, swing clearance "
                     f"min {m['swing_clearance_min'] * 1000:.1f} mm, missed touchdowns "
                     f"{m['missed_touchdowns']}")
    lines.append(f"  ZMP margin min {m['zmp_margin_min'] * 1000:.1f} mm, foot slip max "
                 f"{m['foot_slip_max'] * 1000:.2f} mm, torque ratio max {m['torque_ratio_max']:.2f}, "
                 f"loop residual max {m['loop_residual_max'] * 1000:.3f} mm")
    return "\n".join(lines)
