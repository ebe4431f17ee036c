"""``safewbc run SCENARIO``: a deployment run in MuJoCo with its outputs on disk."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np

from safewbc_jax import scenarios
from safewbc_jax.base import userfile
from safewbc_jax.ui import plots
from safewbc_jax.control.metrics import summarize
from safewbc_jax.control.step import DEFAULT_CONTROL_DT, DEFAULT_SPEED
from safewbc_jax.control.params import apply_overrides, load_overrides
from safewbc_jax.ui.progress import Progress
from safewbc_jax.control.push import PUSH_AT, PUSH_FOR, Push


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


# Ranges of the run options (safewbc run). A run logs every control step in memory (about
# 1 kB per step), so 600 s at 1 kHz is ~0.6 GB; a push above 1,000 N for the default
# 0.15 s gives the 48 kg robot a velocity change above 3 m/s, far past a recoverable push.
MAX_DURATION = 600.0
MAX_SETTLE = 60.0
MAX_PUSH_N = 1000.0


def _finite(opt: str, value) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{opt} {value!r}: expected a number") from None
    if not np.isfinite(x):
        raise ValueError(f"{opt} {value!r}: expected a finite number")
    return x


class RunOptions(NamedTuple):
    """The effective numeric options of ``safewbc run``: seconds of motion and of settle,
    walking's speed command (m/s), the push (N, world frame; None: no push), its start (s
    into the motion) and its duration (s)."""

    duration: float
    settle: float
    speed: float
    push: tuple | None
    push_at: float
    push_for: float


def check_run_options(name: str, scenario, *, duration=None, settle=None, speed=None,
                      push=None, push_at=None, push_for=None) -> RunOptions:
    """Check every numeric option of ``safewbc run`` before anything compiles and fill in
    the defaults. Raises ValueError naming the option, its value and the allowed range;
    an option that would have no effect in this scenario (``--speed`` when not walking,
    ``--at``/``--for`` without a push) is refused rather than ignored. Returns the
    effective options (``RunOptions``)."""
    walking = scenario.gait is not None
    duration = scenario.duration if duration is None else _finite("--duration", duration)
    if not 0 < duration <= MAX_DURATION:
        raise ValueError(f"--duration {duration:g}: seconds of motion must be in (0, "
                         f"{MAX_DURATION:g}]")
    settle = scenario.settle if settle is None else _finite("--settle", settle)
    if not scenario.blend <= settle <= MAX_SETTLE:
        raise ValueError(f"--settle {settle:g}: must be in [{scenario.blend:g}, {MAX_SETTLE:g}] s "
                         f"(at least the {scenario.blend:g} s reference blend)")
    if speed is not None and not walking:
        from safewbc_jax.scenarios import WALKING

        raise ValueError(f"--speed applies to the walking scenarios {list(WALKING)}, not {name!r}")
    if walking:
        speed = (DEFAULT_SPEED if speed is None else
                 scenario.gait.check_speed(_finite("--speed", speed), "--speed"))
    if push is None and scenario.push is not None:     # the scenario's own push
        push = tuple(float(f) for f in scenario.push.force)
        push_at = float(scenario.push.at) if push_at is None else push_at
        push_for = float(scenario.push.duration) if push_for is None else push_for
    if push is None:
        if push_at is not None or push_for is not None:
            raise ValueError("--at and --for time a push: give --force FX,FY,FZ (or run the "
                             "push scenario)")
    else:
        push = tuple(_finite("--force", f) for f in push)
        if len(push) != 3:
            raise ValueError(f"--force {push!r}: expected three numbers FX,FY,FZ (N)")
        if np.linalg.norm(push) > MAX_PUSH_N:
            raise ValueError(f"--force {','.join(f'{f:g}' for f in push)}: |F| = "
                             f"{np.linalg.norm(push):.0f} N, the allowed range is |F| <= "
                             f"{MAX_PUSH_N:g} N")
        push_at = PUSH_AT if push_at is None else _finite("--at", push_at)
        push_for = PUSH_FOR if push_for is None else _finite("--for", push_for)
        if not push_for > 0:
            raise ValueError(f"--for {push_for:g}: the push duration must be > 0 s")
        if not (0 <= push_at and push_at + push_for <= duration):
            raise ValueError(f"--at {push_at:g} --for {push_for:g}: the push must lie within "
                             f"the {duration:g} s of motion (0 <= at, at + for <= {duration:g})")
    return RunOptions(duration, settle, DEFAULT_SPEED if speed is None else speed, push,
                      PUSH_AT if push_at is None else push_at,
                      PUSH_FOR if push_for is None else push_for)


def run_scenario(name: str, *, duration=None, out=None, barrier=True, params_file=None,
                 video=None, settle=None, control_dt=DEFAULT_CONTROL_DT, quiet=False,
                 record_qps_every=0, speed=None, push=None, push_at=None, push_for=None,
                 safe_sets=(), engine="auto", native=False) -> dict:
    """Validate everything, run, write metrics.json, log.npz and figures; return metrics.
    Options left None take the scenario's defaults (``check_run_options``). ``safe_sets``:
    the user's safe sets to add, "FILE.py:NAME" references (``safesets.load``) or SafeSets."""
    from safewbc_jax.sim.mujoco_loop import RunConfig, run

    if isinstance(safe_sets, str):
        safe_sets = (safe_sets,)
    scenario = scenarios.get_scenario(name, barrier, tuple(safe_sets))
    opts = check_run_options(name, scenario, duration=duration, settle=settle, speed=speed,
                             push=push, push_at=push_at, push_for=push_for)
    duration, settle, speed, push, push_at, push_for = opts
    params = scenario.default_params()
    if params_file is not None:
        params = apply_overrides(params, load_overrides(params_file), str(params_file))
    if video:
        check_video_backend(video)
    # default folder: runs/SCENARIO[+SAFE_SET...][_no_barrier], so that a run with a user's
    # safe set does not overwrite the plain one
    # (get_scenario appends the user's safe sets after the scenario's own)
    added = "".join(f"+{s.name}" for s in scenario.safe_sets[len(scenario.safe_sets)
                                                             - len(safe_sets):])
    base = scenario.name if userfile.is_ref(name) else name
    suffix = "" if barrier else "_no_barrier"
    out_dir = Path(out) if out else Path("runs") / (base + added + suffix)
    out_dir.mkdir(parents=True, exist_ok=True)
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))  # noqa: E731
    say(f"[safewbc] {name}: compiling the controller (about a minute on a small CPU) ...")
    # the scenario as resolved above: the user's safe sets are in it already
    cfg = RunConfig(scenario, barrier=barrier, duration=duration, settle=settle,
                    control_dt=control_dt, speed=speed, record_qps_every=record_qps_every,
                    push=None if push is None else Push.single(push, push_at, push_for),
                    engine=engine, native=native)
    # a tqdm bar of the control steps on stderr (one line per phase off a terminal)
    bar = Progress(f"[safewbc] {name}", unit="steps", phase="compiling", quiet=quiet)
    try:
        log, info = run(cfg, params,
                        progress=None if quiet else lambda k, n, ph: bar.update_to(k, ph, n))
    except BaseException:
        bar.close()
        raise
    bar.close("fell" if info["fell"] else "done")
    metrics = summarize(info["metrics"], info, name, control_dt)
    metrics["barrier_on"] = bool(barrier)
    if push is not None:
        metrics["push"] = {"force_N": [float(f) for f in push], "at_s": push_at,
                           "for_s": push_for}
    metrics["safe_sets"] = [s if isinstance(s, str) else s.name for s in safe_sets]
    metrics["out_dir"] = str(out_dir)
    metrics["barrier_unit"] = {s.name: s.unit for s in scenario.safe_sets}
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
    lines = [f"scenario {m['scenario']}  ({m['duration_s']:.2f} s of motion after "
             f"{m['settle_s']} s standing; barrier {'on' if m['barrier_on'] else 'off'}; "
             f"step engine {m.get('engine', 'xla')})",
             f"  fell: {m['fell']}   QPs solved {m['qp_solved']}, fallbacks {m['fallbacks']}, "
             f"failed {m['qp_failed']}",
             f"  step latency p50 {m['step_latency_us']['p50']:.0f} us, p99 "
             f"{m['step_latency_us']['p99']:.0f} us  (terms + assembly "
             f"{m['latency_breakdown_us_p50']['terms_and_assembly']:.0f} / solve "
             f"{m['latency_breakdown_us_p50']['solve']:.0f})",
             "  tracking RMS: " + ", ".join(f"{k} {v:.4f}" for k, v in m["tracking_rms"].items())]
    if "deadline_misses" in m:
        dm = m["deadline_misses"]
        lines.insert(3, f"  over the {dm['period_us']:.0f} us control period: {dm['count']} steps "
                        f"({100 * dm['rate']:.1f}%), max {m['step_latency_us']['max']:.0f} us")
    if m["barrier_min"]:
        unit = m.get("barrier_unit", {})   # h in milli-units: mm, mrad, mm/s
        lines.append("  barrier min h: " + ", ".join(f"{k} {v * 1000:+.1f} m{unit.get(k, 'm')}"
                                                     for k, v in m["barrier_min"].items()))
    if "avg_forward_speed" in m:
        lines.append(f"  walking: avg forward speed {m['avg_forward_speed']:.3f} m/s, steps "
                     f"{m['steps_taken']}, leg collisions {m['leg_collisions']}, swing clearance "
                     f"min {m['swing_clearance_min'] * 1000:.1f} mm, missed touchdowns "
                     f"{m['missed_touchdowns']}")
    lines.append(f"  ZMP margin min {m['zmp_margin_min'] * 1000:.1f} mm, foot slip max "
                 f"{m['foot_slip_max'] * 1000:.2f} mm, torque ratio max "
                 f"{m['torque_ratio_max']:.2f}, "
                 f"loop residual max {m['loop_residual_max'] * 1000:.3f} mm")
    return "\n".join(lines)
