"""The ``safewbc`` command line."""

from __future__ import annotations

import argparse
import json
import sys


def _cmd_model_info(args) -> int:
    from safewbc_jax.modelinfo import format_info, model_info

    info = model_info()
    print(json.dumps(info) if args.json else format_info(info))
    return 0


def _cmd_run(args) -> int:
    from safewbc_jax.runner import format_summary, run_scenario

    push = None
    if args.force is not None:
        try:
            push = tuple(float(f) for f in args.force.split(","))
        except ValueError:
            raise ValueError(f"--force {args.force!r}: expected FX,FY,FZ in newtons") from None
    m = run_scenario(args.scenario, duration=args.duration, out=args.out,
                     barrier=not args.no_barrier, params_file=args.params, video=args.video,
                     settle=args.settle, speed=args.speed, push=push, push_at=args.at,
                     push_for=args.push_for)
    print(format_summary(m))
    print(f"wrote {args.out or 'runs/' + args.scenario + ('' if not args.no_barrier else '_no_barrier')}"
          "/metrics.json, log.npz and figures")
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="safewbc", description=(
        "Safe whole-body task-space control of the humanoid Digit: an inverse-dynamics QP "
        "with acceleration-based exponential control barrier functions."))
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("model-info", help="sizes, mass, loop residual and foot heights of the models")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_model_info)

    from safewbc_jax.scenarios import SCENARIOS

    p = sub.add_parser("run", help="run a scenario in MuJoCo with the PIQP controller "
                       "(walk and push are work in progress: the robot falls after a few steps)")
    p.add_argument("scenario", choices=sorted(SCENARIOS) + ["push", "walk"])
    p.add_argument("--speed", type=float, default=0.2, help="walk/push: forward speed (m/s)")
    p.add_argument("--force", default=None, help="push: FX,FY,FZ on the torso (N); "
                   "default 0,-30,0 (the paper's)")
    p.add_argument("--at", type=float, default=None, help="push: start, s after walking starts")
    p.add_argument("--for", dest="push_for", type=float, default=0.15, help="push: duration (s)")
    p.add_argument("--duration", type=float, default=None, help="seconds of motion")
    p.add_argument("--settle", type=float, default=None, help="seconds standing before the motion")
    p.add_argument("--out", default=None, help="output folder (default runs/SCENARIO)")
    p.add_argument("--no-barrier", action="store_true", help="drop the A-ECBF rows")
    p.add_argument("--params", default=None, help="TOML of ControllerParams overrides")
    p.add_argument("--video", default=None, help="write an MP4 (offscreen rendering)")
    p.add_argument("--cpu", type=int, default=None, metavar="N",
                   help="pin the run to CPU core N (default: the last core; -1: no pinning). "
                        "A real-time loop runs on one core: XLA's thread pool spread over "
                        "shared cores adds wake-up latency to every control step")
    p.set_defaults(func=_cmd_run)
    return ap


def pin_to_cpu(cpu: int | None) -> int | None:
    """Pin this process (and the threads it starts later, XLA's among them) to one core,
    before JAX starts its CPU backend. Returns the core, or None when not pinned."""
    import os

    if cpu == -1 or not hasattr(os, "sched_setaffinity"):
        return None
    cores = sorted(os.sched_getaffinity(0))
    cpu = cores[-1] if cpu is None else cpu
    if cpu not in cores:
        raise ValueError(f"--cpu {cpu}: this process may run on cores {cores}")
    os.sched_setaffinity(0, {cpu})
    return cpu


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "run":
            pin_to_cpu(args.cpu)
        return args.func(args)
    except (ValueError, RuntimeError, FileNotFoundError) as e:
        print(f"safewbc: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
