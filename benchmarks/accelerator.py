"""The batched closed loop on an accelerator: robot-steps/s, compile time, memory per
rollout and agreement with the CPU, one command.

For each --scenarios, --precisions and --batches (B rollouts, --duration s of motion after
the scenario's settle, lateral pushes of 0 to 30 N drawn from a seed, so that the rollouts
differ):

  compile_s        the compile of the closed loop (``rollout.memory_bytes`` of the program
                   ``run_batch`` runs, chunk "auto": one compile per batch, which the runs
                   after it reuse)
  memory           bytes of the compiled program (arguments, outputs, temporaries); from
                   the first two batches, bytes per rollout and the largest batch that
                   fits in 24, 80 and 141 GB (90% of it)
  robot_steps_s    B x control steps / the time of one ``run_batch`` call, after a
                   warm-up call of 1 ms of motion after the shortest settle (1 s; the
                   durations are run-time values of the same compiled program)
  mjx_steps_s      bare ``mjx.step`` (vmapped, scanned) at the same batch and precision, in
                   physics steps/s and in control steps/s (``n_sub`` physics steps each);
                   a compile of its own per batch (about 20 s on a 2-core CPU), so
                   --physics-batches can name the batches that time it
  ratio            closed loop time per control step over bare physics per control step
  max_diff         the largest difference of each metric of the first --ref rollouts from
                   a float64 run of the same rollouts on the CPU (barrier minima and
                   positions in m, tracking RMS relative, counts as counts)

"auto" in --batches adds the largest batch that fits in the device's memory
(``memory_stats()["bytes_limit"]``; on a CPU: 24 GB), from the memory model of the first
two batches. Needs: jax (with CUDA on a GPU: ``pip install "jax[cuda12]==0.10.2"``),
mujoco==3.17.0, mujoco-mjx==3.17.0 and this package (``pip install -e . --no-deps``
beside them). The defaults are 41 M robot-steps (2 scenarios x 2 precisions x 5,120
rollouts x 2,000 control steps; the warm-ups 10 M more): 1.7 minutes at the 500k
robot-steps/s goal, plus eight compiles of the closed loop, four of bare physics and two
CPU references (benchmarks/README.md has what a GPU measured, where one has run it). On a
CPU run it small:

    python benchmarks/accelerator.py                               # a GPU, the defaults
    python benchmarks/accelerator.py --scenarios arms --batches 2 3 --duration 0.05 \\
        --precisions mixed --ref 2                                 # a CPU, smoke size
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time

import numpy as np

NEEDS = {"jax": "jax (0.10.x; jax[cuda12] on an NVIDIA GPU)", "mujoco": "mujoco==3.17.0",
         "mujoco.mjx": "mujoco-mjx==3.17.0", "safewbc_jax": "this package (pip install -e .)"}
GB = 1e9
MEMORIES_GB = (24, 80, 141)
COUNTS = ("fell", "qp_failed", "bad_measurements", "steps_taken")


def missing_packages() -> list[str]:
    out = []
    for mod, what in NEEDS.items():
        try:
            importlib.import_module(mod)
        except Exception as e:                 # ImportError, or a jax/mjx version clash
            out.append(f"{what} ({type(e).__name__}: {e})")
    return out


def pushes(batch: int, seed: int):
    from safewbc_jax.control.push import PUSH_AT, PUSH_FOR, Push

    fy = -30.0 * np.random.default_rng(seed).uniform(0, 1, batch)
    return Push(np.stack([np.zeros(batch), fy, np.zeros(batch)], 1),
                np.full(batch, PUSH_AT), np.full(batch, PUSH_FOR))


def bare_physics(cfg, batch: int, n_physics: int) -> float:
    """mjx.step steps/s of the plant of ``cfg`` at ``batch``, its precision (second call)."""
    import jax

    from safewbc_jax.control import precision
    from safewbc_jax.sim.mjx.rollout import plant
    from safewbc_jax.sim.mjx.imports import import_mjx

    pl = plant(cfg)
    step = jax.vmap(precision.physics(import_mjx().step, pl.data0.qvel.dtype), in_axes=(None, 0))
    d0 = jax.tree_util.tree_map(lambda a: np.broadcast_to(a, (batch,) + a.shape), pl.data0)
    fn = jax.jit(lambda d: jax.lax.scan(lambda c, _: (step(pl.mjx_model, c), None), d, None,
                                        length=n_physics)[0].qpos)
    jax.block_until_ready(fn(d0))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(d0))
    return batch * n_physics / (time.perf_counter() - t0)


def diff(metrics: dict, ref: dict, rows: int) -> dict:
    """The largest difference of each metric over the first ``rows`` rollouts (relative
    for tracking RMS)."""
    out = {}
    for k, r in ref.items():
        a, r = np.asarray(metrics[k])[:rows], np.asarray(r)[:rows]
        if a.dtype == bool or r.dtype == bool:
            a, r = a.astype(int), r.astype(int)
        d = np.abs(a - r)
        if k.startswith("tracking_rms."):
            d = d / np.maximum(np.abs(r), 1e-12)
        out[k] = float(np.nanmax(d)) if np.any(np.isfinite(d)) else 0.0
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", nargs="+", default=["arms", "walk"])
    ap.add_argument("--batches", nargs="+", default=["1024", "4096"],
                    help="rollouts per batch, or 'auto' (the largest that fits)")
    ap.add_argument("--precisions", nargs="+", default=["float64", "mixed"])
    ap.add_argument("--duration", type=float, default=0.5, help="s of motion after settle")
    ap.add_argument("--ref", type=int, default=8,
                    help="rollouts checked against a CPU float64 run of the same rollouts")
    ap.add_argument("--physics-steps", type=int, default=200)
    ap.add_argument("--physics-batches", nargs="+", type=int, default=None,
                    help="the batches at which bare mjx.step is timed (default: every "
                         "batch; each is a compile of its own)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    bad = [b for b in args.batches if b != "auto" and not (b.isdigit() and int(b) > 0)]
    if bad or len([b for b in args.batches if b != "auto"]) < 2:
        ap.error("--batches: at least two positive integers (the memory model's), and "
                 f"optionally 'auto'; got {args.batches}")
    if args.physics_batches is not None:
        off = [b for b in args.physics_batches if str(b) not in args.batches]
        if off:
            ap.error(f"--physics-batches {off}: not among --batches {args.batches}")
    missing = missing_packages()
    if missing:
        print("accelerator.py needs:\n  " + "\n  ".join(missing), file=sys.stderr)
        return 2

    import jax

    import safewbc_jax
    from safewbc_jax.control import precision
    from safewbc_jax.sim.mjx import rollout as R
    from safewbc_jax.solvers import jax_qp

    safewbc_jax.enable_x64()
    if not jax.config.jax_compilation_cache_dir:
        # memory_bytes compiles the program run_batch then runs: the persistent cache
        # lets the second find the first's executable instead of compiling again
        import tempfile

        jax.config.update("jax_compilation_cache_dir",
                          tempfile.mkdtemp(prefix="safewbc-accelerator-xla-"))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    for p in args.precisions:
        precision.check(p, "--precisions")
    for s in args.scenarios:
        if s not in R.BATCHED_SCENARIOS:
            ap.error(f"--scenarios: {s!r} is not one of {', '.join(R.BATCHED_SCENARIOS)}")
    dev = jax.devices()[0]
    stats = dev.memory_stats() if hasattr(dev, "memory_stats") else None
    dev_mem = (stats or {}).get("bytes_limit", 24 * GB)
    cpu = jax.devices("cpu")[0]
    print(f"device: {dev.device_kind} ({dev.platform}), {dev_mem / GB:.0f} GB; jax "
          f"{jax.__version__}; {args.duration} s of motion; pushes 0-30 N lateral", flush=True)
    fixed_b = [int(b) for b in args.batches if b != "auto"]
    with jax_qp.blas_threads(1):
        for sc in args.scenarios:
            ref = None
            for prec in args.precisions:
                cfg = R.BatchConfig(sc, duration=args.duration, precision=prec)
                pl = R.plant(cfg)
                n_steps, _ = pl.schedule(cfg)
                batches, mem = list(fixed_b), {}
                k = 0
                while k < len(batches):
                    b = batches[k]
                    t0 = time.perf_counter()
                    mem[b] = R.memory_bytes(cfg, b, chunk="auto")   # run_batch's program
                    compile_s = time.perf_counter() - t0
                    if k == 1:
                        b0, b1 = batches[:2]
                        per = (mem[b1] - mem[b0]) / (b1 - b0)
                        fixed = mem[b0] - per * b0
                        fits = {g: R.largest_batch(fixed, per, g * GB) for g in MEMORIES_GB}
                        print(f"{sc} {prec}: memory {per / 1e6:.2f} MB per rollout + "
                              f"{fixed / 1e6:.0f} MB; largest batch in "
                              + ", ".join(f"{g} GB: {n:,}" for g, n in fits.items()),
                              flush=True)
                        if "auto" in args.batches:
                            auto = R.largest_batch(fixed, per, dev_mem)
                            if auto > 0 and auto not in batches:
                                batches.append(auto)
                    push = pushes(b, args.seed)
                    params = R.default_params(sc, b)
                    # warm-up: the compiled program, 1,001 control steps
                    R.run_batch(R.BatchConfig(sc, duration=1e-3, settle=1.0, precision=prec),
                                params, push)
                    t0 = time.perf_counter()
                    met, _ = R.run_batch(cfg, params, push)
                    run_s = time.perf_counter() - t0
                    rate = b * n_steps / run_s
                    if args.physics_batches is None or b in args.physics_batches:
                        phys = bare_physics(cfg, b, args.physics_steps)
                        phys_ctl = phys / pl.n_sub
                        bare = (f"mjx.step {phys:11,.0f} steps/s ({phys_ctl:,.0f} control "
                                f"steps/s)  ratio {phys_ctl / rate:5.2f}")
                    else:
                        bare = "mjx.step not timed (--physics-batches)  ratio -"
                    nref = min(args.ref, b)
                    if ref is None or len(next(iter(ref.values()))) < nref:
                        ref_cfg = R.BatchConfig(sc, duration=args.duration)
                        with jax.default_device(cpu):
                            # the first nref rollouts of any batch: the same pushes
                            ref, _ = R.run_batch(ref_cfg, R.default_params(sc, nref),
                                                 pushes(nref, args.seed), chunk=None)
                    d = diff(met, ref, nref)
                    worst = {k: v for k, v in d.items()
                             if k.startswith(("barrier_min", "tracking_rms")) or k in COUNTS}
                    print(f"{sc:5s} {prec:7s} B={b:<6d} compile {compile_s:6.1f} s  "
                          f"{rate:11,.0f} robot-steps/s  {bare}  "
                          f"memory {mem[b] / GB:6.2f} GB  fell {int(np.sum(met['fell']))}",
                          flush=True)
                    print("      max diff from CPU float64 over "
                          f"{nref} rollouts: " + ", ".join(f"{k} {v:.3g}"
                                                           for k, v in sorted(worst.items())),
                          flush=True)
                    k += 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
