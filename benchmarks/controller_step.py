"""Latency of the deployed controller step, per scenario, side by side with TSID.

For each scenario, the MuJoCo loop of ``safewbc run`` (``sim.mujoco_loop.run``: the
deployed ``Controller`` driving the simulated robot, the scenario's whole motion, push
included) records every step's wall time: the whole ``Controller.step`` (what a robot's
loop waits for: measurement check, the jitted step, PIQP, the motor map), and its parts,
the jitted step (gait, QP, elimination: one XLA call) and the PIQP solve of the reduced QP
with the acceptance checks. Where TSID is installed (``benchmarks/tsid_anchor.py``;
``../shared/anchors/README.md``), its whole-body step runs right after each of ours, on
the same measured state, in the same process (its torques are not applied), and the ratio
of the p50s is printed. Also: the deadline misses at the 1 kHz control period, the
kernels XLA runs for the jitted step (``Controller.kernels``), and the run's figures
(fell, barrier minima), so that a faster step is seen to be the same controller.

    python benchmarks/controller_step.py [--scenarios squat,bow,arms,walk,push]
        [--engine c,xla] [--native] [--duration S] [--cpu N] [--no-tsid] [--json]

``--engine``: the deployed step generated as C (``deploy.codegen``, the start time then
includes the generation and the C compile, and a second start, from the build cache, is
timed too) and/or jitted by XLA, one after the other for each scenario.

Pin to one core (the default: core 0) and keep the machine otherwise idle; the p99 and
the max are what other processes disturb first.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

SCENARIOS = ("squat", "bow", "arms", "walk", "push")


def _stats(a, skip):
    import numpy as np

    a = np.asarray(a, float)[skip:]
    return {"p50": round(float(np.percentile(a, 50)), 1), "p99": round(float(np.percentile(a, 99)), 1),
            "max": round(float(a.max()), 1)}


def _round(x):
    """A metric value as plain JSON: floats to 5 decimals, 0-d arrays as scalars."""
    import numpy as np

    a = np.asarray(x)
    if a.ndim == 0:
        return round(float(a), 5) if a.dtype.kind == "f" else a.item()
    return a.tolist()


def bench_scenario(name, duration, tsid_step, engine="xla", control_dt=1e-3, native=False):
    from safewbc_jax import scenarios
    from safewbc_jax.control import metrics
    from safewbc_jax.control.push import Push
    from safewbc_jax.app.runner import check_run_options
    from safewbc_jax.sim.mujoco_loop import RunConfig, run

    sc = scenarios.get_scenario(name)
    opts = check_run_options(name, sc, duration=duration)
    push = (Push.single(opts.push, opts.push_at, opts.push_for)
            if opts.push is not None else None)
    cfg = RunConfig(sc, duration=opts.duration, settle=opts.settle, speed=opts.speed,
                    push=push, control_dt=control_dt, count_kernels=engine == "xla",
                    engine=engine, native=native)
    tsid_us, tsid_bad = [], [0]
    started = [False]

    def observer(meas):
        if tsid_step is None:
            return
        if not started[0]:
            tsid_step.start(meas.q, meas.v)
            started[0] = True
        _, status, us = tsid_step.step(meas.q, meas.v)
        tsid_us.append(us)
        tsid_bad[0] += int(status != 0)

    t0 = time.perf_counter()
    log, info = run(cfg, sc.default_params(), observer=observer)
    wall = time.perf_counter() - t0
    kern = info.get("kernels")
    skip = metrics.LATENCY_SKIP
    lat = log["latency"]
    m = info["metrics"]
    res = {
        "scenario": name, "engine": engine, "steps": int(lat.size), "wall_s": round(wall, 1),
        "compile_s": round(float(info["compile_s"]), 1),
        "command_us": _stats(lat, skip),
        "deadline_misses": metrics.deadline_misses(lat[skip:], control_dt),
        "breakdown_us": {"jitted_step": _stats(log["t_qp"], skip),
                         "piqp_solve": _stats(log["t_solve"], skip),
                         "rest_of_step": _stats(lat - log["t_qp"] - log["t_solve"], skip)},
        "kernels": kern,
        "figures": {"fell": bool(info["fell"]), "qp_failed": int(m.get("qp_failed", 0)),
                    "fallbacks": int(m.get("fallbacks", 0)),
                    **{k: _round(m[k]) for k in sorted(m)
                       if k.startswith(("barrier_min.", "tracking_rms.", "zmp_margin_min",
                                        "steps_taken", "avg_forward_speed"))}},
    }
    if tsid_step is not None:
        res["tsid_us"] = _stats(tsid_us, skip)
        res["tsid_failed"] = tsid_bad[0]
        res["tsid_qp_sizes"] = list(tsid_step.sizes)
        res["ratio_p50_to_tsid"] = round(res["command_us"]["p50"] / res["tsid_us"]["p50"], 2)
        res["ratio_p99_to_tsid"] = round(res["command_us"]["p99"] / res["tsid_us"]["p99"], 2)
    return res


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default=",".join(SCENARIOS),
                    help=f"comma-separated, of {', '.join(SCENARIOS)}")
    ap.add_argument("--duration", type=float, default=None,
                    help="s of motion per scenario (default: each scenario's own)")
    ap.add_argument("--cpu", type=int, default=0, help="pin to this core (-1: no pinning)")
    ap.add_argument("--no-tsid", action="store_true", help="leave TSID out even if installed")
    ap.add_argument("--engine", default="c,xla",
                    help="the deployed step's engines, comma-separated, run one after the "
                    "other for each scenario: c, xla (default: both)")
    ap.add_argument("--native", action="store_true",
                    help="build the C engine with -march=native (safewbc run --native)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    names = [s.strip() for s in args.scenarios.split(",") if s.strip()]
    bad = [s for s in names if s not in SCENARIOS]
    if bad or not names:
        ap.error(f"--scenarios {args.scenarios!r}: expected names of {', '.join(SCENARIOS)}")
    engines = [e.strip() for e in args.engine.split(",") if e.strip()]
    if not engines or any(e not in ("c", "xla") for e in engines):
        ap.error(f"--engine {args.engine!r}: expected c, xla or c,xla")
    os.environ.setdefault("OMP_NUM_THREADS", "1")     # TSID's OpenMP (before it loads)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import tsid_anchor

    import safewbc_jax
    from safewbc_jax.app.cli import pin_to_cpu
    from safewbc_jax.base import paths
    from safewbc_jax.model import contacts

    safewbc_jax.enable_x64()
    pinned = pin_to_cpu(args.cpu)
    use_tsid = not args.no_tsid and tsid_anchor.available()
    out = {"pinned_cpu": pinned, "cpu_count": os.cpu_count(), "tsid": use_tsid,
           "scenarios": []}
    if not use_tsid and not args.json:
        print("TSID: " + ("left out (--no-tsid)" if args.no_tsid else
                          "not installed (see ../shared/anchors/README.md): no ratios"))
    for k, name in enumerate(names):
        # the engines alternate their order from one scenario to the next
        for engine in (engines if k % 2 == 0 else engines[::-1]):
            tstep = (tsid_anchor.TsidStep(str(paths.controller_xml()), contacts.SOLE_LENGTH,
                                          contacts.SOLE_WIDTH) if use_tsid else None)
            r = bench_scenario(name, args.duration, tstep, engine, native=args.native)
            if engine == "c":       # a second start: the build found in the cache
                r["cached_start_s"] = round(_cached_start(name, args.native), 2)
            out["scenarios"].append(r)
            if not args.json:
                _print(r)
    if args.json:
        print(json.dumps(out))
    return out


def _cached_start(name, native=False):
    """Seconds of ``Controller.start`` with the C engine when the build is cached."""
    from safewbc_jax.deploy.codegen.export import stand_state
    from safewbc_jax.deploy.controller import Controller

    q, v = stand_state()
    return Controller(name, engine="c", native=native).start(q, v)


def _print(r):
    c, b = r["command_us"], r["breakdown_us"]
    dm = r["deadline_misses"]
    start = f"start {r['compile_s']} s" + (f" (cached {r['cached_start_s']} s)"
                                           if "cached_start_s" in r else "")
    print(f"{r['scenario']} [{r['engine']}]: {r['steps']} steps, {start}; Controller.step "
          f"p50 {c['p50']} us, p99 {c['p99']} us, max {c['max']} us; over "
          f"{dm['period_us']:.0f} us: {dm['count']} ({100 * dm['rate']:.1f}%)")
    kern = ("" if not r["kernels"] else f" ({r['kernels']['total']} kernels: "
            + ", ".join(f"{k} {v}" for k, v in r["kernels"].items() if k != "total") + ")")
    print(f"    generated/jitted step p50 {b['jitted_step']['p50']} us{kern}, PIQP p50 "
          f"{b['piqp_solve']['p50']} us, the rest p50 {b['rest_of_step']['p50']} us")
    if "tsid_us" in r:
        t = r["tsid_us"]
        print(f"    TSID (QP {r['tsid_qp_sizes']}) p50 {t['p50']} us, p99 {t['p99']} us; ours / "
              f"TSID: p50 {r['ratio_p50_to_tsid']}x, p99 {r['ratio_p99_to_tsid']}x")
    print("    figures: " + ", ".join(f"{k} {v}" for k, v in r["figures"].items()))


if __name__ == "__main__":
    main()
