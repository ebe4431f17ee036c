"""The ``safewbc`` command line."""

from __future__ import annotations

import argparse
import json
import sys


def _cmd_model_info(args) -> int:
    from safewbc_jax.model.modelinfo import format_info, model_info

    info = model_info()
    print(json.dumps(info) if args.json else format_info(info))
    return 0


def _cmd_export_c(args) -> int:
    from safewbc_jax import scenarios
    from safewbc_jax.control.params import apply_overrides, load_overrides
    from safewbc_jax.deploy.codegen.export import export_c

    barrier = not args.no_barrier
    sc = scenarios.get_scenario(args.scenario, barrier, tuple(args.safe_set))
    if args.speed is not None and sc.gait is None:
        raise ValueError(f"--speed applies to the walking scenarios, not {args.scenario!r}")
    params = sc.default_params()
    if args.params is not None:
        params = apply_overrides(params, load_overrides(args.params), str(args.params))
    print(f"[safewbc] {args.scenario}: writing the controller as C ...", file=sys.stderr)
    e = export_c(sc, args.out, params, barrier=barrier, speed=args.speed)
    print(f"wrote {e.out}/safewbc_step.c, safewbc_step.h, main.c and Makefile; "
          f"build and run the example with: make -C {e.out}")
    return 0


def _cmd_run(args) -> int:
    _compile_cache(args)      # the start's XLA programs (Theorem 1, the start data, ...)
    from safewbc_jax.app.runner import format_summary, run_scenario

    push = None
    if args.force is not None:
        try:
            push = tuple(float(f) for f in args.force.split(","))
        except ValueError:
            raise ValueError(f"--force {args.force!r}: expected FX,FY,FZ in newtons, "
                             "e.g. --force 0,-30,0") from None
    m = run_scenario(args.scenario, duration=args.duration, out=args.out,
                     barrier=not args.no_barrier, params_file=args.params, video=args.video,
                     settle=args.settle, speed=args.speed, push=push, push_at=args.at,
                     push_for=args.push_for, quiet=args.quiet, safe_sets=tuple(args.safe_set),
                     engine=args.engine, native=args.native)
    print(format_summary(m))
    print(f"wrote {m['out_dir']}/metrics.json, log.npz and figures")
    return 0


def _compile_cache(args) -> None:
    """Keep compiled XLA programs on disk (JAX's persistent compilation cache), so that a
    resumed or repeated sweep skips the minutes of compiling the closed-loop step, and a
    repeated run starts in seconds."""
    import os

    if getattr(args, "no_cache", False):
        return
    from safewbc_jax.base import runtime

    runtime.use_compile_cache(os.environ.get("JAX_COMPILATION_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "safewbc-jax", "xla"))


def _engine_args(p) -> None:
    """--engine, --workers, --no-cache and --quiet of ``sweep``, ``tune`` and
    ``tune-poles``."""
    p.add_argument("--engine", choices=("auto", "mjx", "mujoco"), default="auto",
                   help="mjx: batched MJX rollouts (JAX QP solver); mujoco: one deployment "
                   "loop (C MuJoCo + PIQP) per CPU; auto: mjx on an accelerator, on a CPU "
                   "the faster of the two as measured (docs/sweeps.md, 'Two engines')")
    p.add_argument("--workers", type=_int_at_least(1), default=None,
                   help="--engine mujoco: worker processes, one pinned to each CPU "
                   "(default: one per CPU this process may use)")
    p.add_argument("--ray", nargs="?", const="local", default=None, metavar="ADDRESS",
                   help="run each chunk as a task on a Ray cluster: ADDRESS (HOST:PORT of "
                   "its head, or auto), or with no address a Ray started on this machine "
                   "(pip install 'safewbc-jax[ray]'; docs/sweeps.md, 'On a cluster')")
    p.add_argument("--no-cache", action="store_true",
                   help="do not use the on-disk XLA compilation cache")
    p.add_argument("--quiet", action="store_true", help="no progress bar or messages on "
                   "stderr (errors and the final summary still print)")


def _check_engine(args) -> None:
    """--workers against the CPUs, and --workers without --engine mujoco (before anything
    compiles)."""
    from safewbc_jax.sweeps.pool import check_workers

    if args.ray is not None:
        from safewbc_jax.sweeps import cluster

        cluster.check_options(args.ray, workers=args.workers)
    if args.workers is not None:
        if args.engine == "mjx":
            raise ValueError(f"--workers {args.workers}: only the mujoco engine has workers "
                             "(--engine mujoco)")
        check_workers(args.workers)
    if args.ray is not None:
        cluster.connect(args.ray, args.quiet)   # a wrong address fails here, in seconds


def hosts_from_env(environ) -> tuple[int, int]:
    """(hosts, host index) of this process from the cluster's environment: a SLURM job
    array (SLURM_ARRAY_TASK_COUNT, SLURM_ARRAY_TASK_ID, SLURM_ARRAY_TASK_MIN and _STEP),
    else SLURM's tasks of one job step (SLURM_NTASKS, SLURM_PROCID). Raises ValueError
    naming what is missing or wrong."""
    def number(name):
        try:
            return int(environ[name])
        except ValueError:
            raise ValueError(f"--distributed: {name}={environ[name]!r} is not an integer"
                             ) from None

    if "SLURM_ARRAY_TASK_ID" in environ and "SLURM_ARRAY_TASK_COUNT" in environ:
        step = number("SLURM_ARRAY_TASK_STEP") if "SLURM_ARRAY_TASK_STEP" in environ else 1
        low = number("SLURM_ARRAY_TASK_MIN") if "SLURM_ARRAY_TASK_MIN" in environ else 0
        hosts = number("SLURM_ARRAY_TASK_COUNT")
        index = (number("SLURM_ARRAY_TASK_ID") - low) // max(step, 1)
    elif "SLURM_NTASKS" in environ and "SLURM_PROCID" in environ:
        hosts, index = number("SLURM_NTASKS"), number("SLURM_PROCID")
    else:
        raise ValueError("--distributed: found neither a SLURM job array "
                         "(SLURM_ARRAY_TASK_ID, SLURM_ARRAY_TASK_COUNT) nor SLURM tasks "
                         "(SLURM_NTASKS, SLURM_PROCID) in the environment; give --hosts N "
                         "--host-index I instead")
    if not (hosts >= 1 and 0 <= index < hosts):
        raise ValueError(f"--distributed: host index {index} of {hosts} hosts from the "
                         "environment: expected 0 <= index < hosts")
    return hosts, index


def _cmd_sweep(args) -> int:
    from pathlib import Path

    from safewbc_jax.sweeps.run import run_sweep
    from safewbc_jax.sweeps.spec import load_spec

    import os

    if args.host_index >= args.hosts:
        raise ValueError(f"--host-index {args.host_index}: must be below --hosts {args.hosts}")
    hosts, index = args.hosts, args.host_index
    if args.distributed:
        if args.hosts != 1 or args.host_index != 0:
            raise ValueError("--distributed reads the hosts from the environment: give it "
                             "or --hosts/--host-index, not both")
        hosts, index = hosts_from_env(os.environ)
    if args.ray is not None:
        from safewbc_jax.sweeps import cluster

        cluster.check_options(args.ray, hosts)
    spec = load_spec(args.spec)          # every check before anything compiles
    _check_engine(args)
    _compile_cache(args)
    try:
        r = run_sweep(spec, args.out, batch=args.batch, seed=args.seed,
                      spec_text=Path(args.spec).read_text(), max_chunks=args.max_chunks,
                      hosts=hosts, host_index=index, quiet=args.quiet, engine=args.engine,
                      workers=args.workers, ray=args.ray)
    except KeyboardInterrupt:
        print(f"safewbc: interrupted; the finished chunks are kept in {args.out}, rerun the "
              "same command to resume", file=sys.stderr)
        return 130
    rate = "" if r.chunks_run == 0 else f", {r.rollouts_per_s:.2f} rollouts/s"
    print(f"sweep {args.out}: {r.chunks_skipped + r.chunks_run}/{r.chunks_total} chunks done "
          f"({r.chunks_run} run now{rate}); table in {args.out}/chunks/*.parquet")
    if r.failed:
        from safewbc_jax.sweeps.cluster import describe_failures

        print(f"safewbc: {describe_failures(r.failed, args.out)}", file=sys.stderr)
        return 1
    return 0


def _cmd_report(args) -> int:
    from safewbc_jax.sweeps.report import make_report

    r = make_report(args.dir, args.dest)
    print(f"report of {r['rollouts']} rollouts: {r['summary']}"
          + "".join(f"\n  {f}" for f in r["figures"]))
    return 0


def _cmd_tune(args) -> int:
    from safewbc_jax.sweeps import tuning
    from safewbc_jax.sweeps.spec import load_spec

    from safewbc_jax.sweeps.tune import poles_config

    spec = load_spec(args.spec)          # the spec and its [tune] table, before any compile
    cfg = (poles_config(spec, budget=args.budget, validate=args.validate)
           if args.command == "tune-poles" else
           tuning.config(spec, method=args.method, budget=args.budget, validate=args.validate))
    _check_engine(args)
    _compile_cache(args)
    work = args.work or tuning.default_work(args.out, args.command)
    try:
        r = tuning.tune(spec, args.out, cfg=cfg, work=work, batch=args.batch, seed=args.seed,
                        quiet=args.quiet, engine=args.engine, workers=args.workers,
                        title=args.command, ray=args.ray)
    except KeyboardInterrupt:
        print(f"safewbc: interrupted; the finished generations are kept in {work}, rerun "
              "the same command to resume", file=sys.stderr)
        return 130
    print(r.summary())
    return 0


def _scenario_arg(value: str) -> str:
    """argparse type: a scenario's name or a "FILE.py:NAME" reference (loaded, and checked,
    by the run before anything compiles)."""
    from safewbc_jax import scenarios
    from safewbc_jax.base import userfile

    if value in scenarios.names() or userfile.is_ref(value):
        return value
    raise argparse.ArgumentTypeError(f"{value!r}: choose from "
                                     f"{', '.join(sorted(scenarios.names()))}"
                                     ", or FILE.py:NAME (a Scenario of your own)")


def _finite_float(text: str) -> float:
    """argparse type: a finite number (ranges that depend on the scenario are checked by
    ``runner.check_run_options``, still before anything compiles)."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if x != x or x in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number")
    return x


def _batch_arg(text: str):
    """--batch of ``safewbc sweep``: an integer >= 1 or 'auto'."""
    return "auto" if text == "auto" else _int_at_least(1)(text)


def _int_at_least(lo: int):
    def parse(text: str) -> int:
        try:
            n = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if n < lo:
            raise argparse.ArgumentTypeError(f"{n}: expected an integer >= {lo}")
        return n

    parse.__name__ = f"integer >= {lo}"
    return parse


def _numbers_text(text: str) -> bool:
    """Whether ``text`` is a number or a comma list of numbers (nan and inf included)."""
    try:
        [float(t) for t in text.split(",")]
    except ValueError:
        return False
    return True


def _join_dash_values(argv: list[str]) -> list[str]:
    """Pass a value that starts with '-' and reads as numbers on as ``--opt=value``:
    argparse takes "--force -20,-25,0" or "--duration -inf" for an option and refuses
    them with "expected one argument", before our range checks could name the problem."""
    out, i = [], 0
    while i < len(argv):
        a = argv[i]
        nxt = argv[i + 1] if i + 1 < len(argv) else ""
        if a.startswith("--") and "=" not in a and nxt.startswith("-") and _numbers_text(nxt):
            out.append(f"{a}={nxt}")
            i += 2
        else:
            out.append(a)
            i += 1
    return out


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="safewbc", description=(
        "Safe whole-body task-space control of the humanoid Digit: an inverse-dynamics QP "
        "with acceleration-based exponential control barrier functions."))
    sub = ap.add_subparsers(dest="command", required=True)
    p = sub.add_parser("model-info", help="sizes, mass, loop residual and foot heights of the "
                       "models")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd_model_info)

    from safewbc_jax import scenarios
    from safewbc_jax.control.step import DEFAULT_SPEED

    p = sub.add_parser("run", help="run a scenario in MuJoCo with the PIQP controller")
    p.add_argument("scenario", type=_scenario_arg, metavar="SCENARIO",
                   help=f"{', '.join(sorted(scenarios.names()))}, or FILE.py:NAME: a Scenario "
                   "of your own")
    p.add_argument("--speed", type=_finite_float, default=None, help="walk/push: commanded "
                   f"mean forward speed (m/s; default {DEFAULT_SPEED}; the ALIP planner at "
                   "T = 0.35 s reaches -0.857 to 1.143)")
    p.add_argument("--force", default=None, metavar="FX,FY,FZ",
                   help="push on the torso (N, world frame; |F| <= 1000); default for the push "
                   "scenario 0,-30,0 (the paper's, to the right). Negative components as typed: "
                   "--force -20,-25,0")
    p.add_argument("--at", type=_finite_float, default=None, help="push: start, s after the "
                   "motion (walking) starts (default 2.55: early in a right-stance step, where "
                   "a push to the right drives the left swing foot towards the stance foot)")
    p.add_argument("--for", dest="push_for", type=_finite_float, default=None,
                   help="push: duration (s, default 0.15)")
    p.add_argument("--duration", type=_finite_float, default=None,
                   help="seconds of motion (0 to 600; default: the scenario's)")
    p.add_argument("--settle", type=_finite_float, default=None,
                   help="seconds standing before the motion (1 to 60; default 1.5)")
    p.add_argument("--out", default=None, help="output folder (default runs/SCENARIO)")
    p.add_argument("--no-barrier", action="store_true",
                   help="drop the A-ECBF rows: every safe set monitored only")
    p.add_argument("--engine", choices=("auto", "c", "xla"), default="auto",
                   help="the deployed step: generated C built with the system compiler, "
                   "XLA, or auto (C where a C compiler exists; default)")
    p.add_argument("--native", action="store_true",
                   help="build the C engine for this CPU's instruction set (-march=native)")
    p.add_argument("--params", default=None, help="TOML of ControllerParams overrides")
    p.add_argument("--safe-set", dest="safe_set", action="append", default=[],
                   metavar="FILE.py:NAME", help="add the SafeSet NAME of a Python file "
                   "(repeatable; e.g. examples/bow_torso_lean.py:TORSO_LEAN)")
    p.add_argument("--video", default=None, help="write an MP4 (offscreen rendering)")
    p.add_argument("--cpu", type=int, default=None, metavar="N",
                   help="pin the run to CPU core N (default: the last core; -1: no pinning). "
                        "A real-time loop runs on one core: XLA's thread pool spread over "
                        "shared cores adds wake-up latency to every control step")
    p.add_argument("--quiet", action="store_true", help="no progress bar or messages on "
                   "stderr (errors and the final summary still print)")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("export-c", help="write a scenario's controller as C99: a folder that "
                       "'make' builds and runs with no Python")
    p.add_argument("scenario", type=_scenario_arg, metavar="SCENARIO",
                   help=f"{', '.join(sorted(scenarios.names()))}, or FILE.py:NAME")
    p.add_argument("--out", required=True, help="the folder to write")
    p.add_argument("--params", default=None, help="TOML of ControllerParams overrides")
    p.add_argument("--safe-set", dest="safe_set", action="append", default=[],
                   metavar="FILE.py:NAME", help="add the SafeSet NAME of a Python file "
                   "(repeatable)")
    p.add_argument("--no-barrier", action="store_true",
                   help="drop the A-ECBF rows: every safe set monitored only")
    p.add_argument("--speed", type=_finite_float, default=None,
                   help="walk/push: commanded mean forward speed (m/s)")
    p.set_defaults(func=_cmd_export_c)

    p = sub.add_parser("sweep", help="run a sweep spec (sweeps/*.toml) as chunks of batched "
                       "closed-loop rollouts into a Parquet table; a rerun resumes")
    p.add_argument("spec", help="sweep spec TOML (see sweeps/)")
    p.add_argument("--out", required=True, help="sweep directory (table, manifest)")
    p.add_argument("--batch", type=_batch_arg, default=None,
                   help="rollouts per chunk (default: the spec's sweep.batch, else 64); "
                   "'auto': on an accelerator, the most that fit in its memory")
    p.add_argument("--seed", type=_int_at_least(0), default=None,
                   help="seed of the perturbations (default: the spec's sweep.seed, else 0)")
    p.add_argument("--max-chunks", type=_int_at_least(1), default=None,
                   help="stop after this many chunks")
    p.add_argument("--hosts", type=_int_at_least(1), default=1, help="several hosts share "
                   "--out: run only the chunks k with k mod HOSTS = --host-index")
    p.add_argument("--host-index", type=_int_at_least(0), default=0,
                   help="this host's index (0-based, below --hosts)")
    p.add_argument("--distributed", action="store_true", help="take --hosts / --host-index "
                   "from SLURM's environment (a job array's task count and id, or a job "
                   "step's SLURM_NTASKS / SLURM_PROCID)")
    _engine_args(p)
    p.set_defaults(func=_cmd_sweep)

    p = sub.add_parser("report", help="figures and summary.md of a sweep directory or of a "
                       "tuning run's folder")
    p.add_argument("dir", help="sweep directory written by safewbc sweep, or the --work "
                   "folder of safewbc tune / tune-poles")
    p.add_argument("--dest", default=None, help="where to write (default: DIR)")
    p.set_defaults(func=_cmd_report)

    for name, text in (
            ("tune", "tune controller parameters (the spec's [tune] table: poles, gains, "
             "weights) for the least objective with no fall or violation over the spec's "
             "pushes and perturbations (CMA-ES or grid refinement), then validate on "
             "held-out draws; writes a params TOML for safewbc run --params"),
            ("tune-poles", "the poles of tune.barrier by successive grid refinement (a "
             "preset of safewbc tune); writes a params TOML for safewbc run --params")):
        p = sub.add_parser(name, help=text)
        p.add_argument("spec", help="sweep spec TOML: its scenario, pushes, perturbations "
                       "and [tune] table")
        p.add_argument("--out", required=True, help="params TOML to write")
        p.add_argument("--work", default=None, help="folder of the generations' sweep "
                       "tables and tuning.json (default: OUT without .toml + "
                       f"'{'_tune' if name == 'tune' else '_rounds'}'); a rerun resumes there")
        if name == "tune":
            p.add_argument("--method", choices=("cmaes", "grid"), default=None,
                           help="the search (default: tune.method, else cmaes)")
        p.add_argument("--budget", type=_int_at_least(1), default=None,
                       help="rollouts the search may use (default: tune.budget, else 10 "
                       "CMA-ES generations or the grid's rounds)")
        p.add_argument("--validate", type=_int_at_least(0), default=None,
                       help="held-out rollouts of the result (default: tune.validate, else "
                       "64; 0: none)")
        p.add_argument("--batch", type=_int_at_least(1), default=None,
                       help="rollouts per chunk")
        p.add_argument("--seed", type=_int_at_least(0), default=None,
                       help="seed of the search and of its perturbations (validation: "
                       "seed + 1)")
        _engine_args(p)
        p.set_defaults(func=_cmd_tune)
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
        raise ValueError(f"--cpu {cpu}: this process may run on cores {cores} (or -1: "
                         "no pinning)")
    os.sched_setaffinity(0, {cpu})
    return cpu


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(_join_dash_values(argv))
    from safewbc_jax.base import runtime

    runtime.enable_x64()
    if args.command == "run" or getattr(args, "engine", None) == "mujoco":
        runtime.use_cpu()      # one robot's step, or the CPU engine's driver: never a GPU
    try:
        if args.command == "run":
            pin_to_cpu(args.cpu)
        return args.func(args)
    except (ValueError, RuntimeError, FileNotFoundError) as e:
        print(f"safewbc: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
