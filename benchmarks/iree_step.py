"""IREE as the engine of the deployed step's QP build, side by side with XLA:CPU.

What runs: the deployed step's jitted part up to the full QP (``control_step.prepare``:
gait, robot terms, outputs, barrier rows, contacts, assembly; in, out and packed as
``deploy.Controller`` packs them, as flat float64 vectors), at the stand of a scenario.
The exact elimination and the PIQP checks are left out: they call LAPACK through XLA
custom calls, which IREE cannot take. For the same reason only the standing scenarios
run: walking's rigid swing-leg velocity solves a 5x5 system through LAPACK.

The same function goes to both engines. It is exported to StableHLO (``jax.export``) and
compiled by IREE for this CPU: llvm-cpu, f64 kept (``--iree-input-demote-f64-to-f32=false``),
executables linked as system shared libraries (the embedded ELF linker cannot resolve
libm's f64 ``cos``). IREE runs it with its in-process ``local-sync`` driver. The script
checks that both engines give the same outputs at ``--states`` random states near the
stand. Then it times both, alternating rounds in one process. Each call includes the
host copy of its outputs.

IREE 3.13's ``RaiseSpecialOps`` pass turns an ``insert_slice`` of a ``collapse_shape``
into an invalid ``tensor.expand_shape`` (e.g. 35x3 to 35x2x1). JAX's ``concatenate``
lowers to that pattern. The script first compiles the module as exported and reports
whether it still fails. It then compiles it with a ``stablehlo.optimization_barrier`` on
every operand of every ``stablehlo.concatenate``. A barrier returns its operand
unchanged, so the function is the same.

IREE is optional and not a dependency: install it into the same venv to run this.

    pip install iree-base-compiler==3.13.0 iree-base-runtime==3.13.0
    python benchmarks/iree_step.py [--scenario squat] [--states 5] [--calls 400]
        [--rounds 5] [--cpu 0] [--keep DIR] [--json]
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import os
import re
import sys
import tempfile
import time

# walking is left out: its rigid swing-leg velocity solves a 5x5 system through LAPACK
SCENARIOS = ("squat", "bow", "arms")
_CONCAT = re.compile(r"^(\s*)(%[\w.#]+) = stablehlo\.concatenate (.*?), dim = (\d+) : "
                     r"\((.*?)\) -> (.*)$")
_STAT = re.compile(r"//\s*(D->H Syncs|Submissions|Dispatches|Executables):\s*(\d+)")
IREE_FLAGS = ("--iree-hal-target-device=local",
              "--iree-hal-local-target-device-backends=llvm-cpu",
              "--iree-llvmcpu-target-cpu=host", "--iree-input-demote-f64-to-f32=false",
              "--iree-llvmcpu-link-embedded=false")
TOL = 1e-9


def barrier_concatenates(mlir: str) -> tuple[str, int]:
    """The StableHLO text with each operand of every ``stablehlo.concatenate`` passed
    through ``stablehlo.optimization_barrier`` (the value unchanged); and how many
    concatenates were rewritten."""
    out, n = [], 0
    for line in mlir.splitlines(keepends=True):
        m = _CONCAT.match(line.rstrip("\n"))
        if m is None:
            out.append(line)
            continue
        ind, res, ops, dim, types, rest = m.groups()
        ops = [o.strip() for o in ops.split(",")]
        tys = re.findall(r"tensor<[^>]*>", types)
        if len(ops) != len(tys):
            raise ValueError(f"cannot read the concatenate {line.strip()[:120]!r}")
        names = [f"%obar{n}_{i}" for i in range(len(ops))]
        out += [f"{ind}{nm} = stablehlo.optimization_barrier {o} : {t}\n"
                for nm, o, t in zip(names, ops, tys)]
        out.append(f"{ind}{res} = stablehlo.concatenate {', '.join(names)}, dim = {dim} : "
                   f"({types}) -> {rest}\n")
        n += 1
    return "".join(out), n


def _compile(mlir: str, workdir: str, tag: str):
    """(vmfb bytes or None, seconds, the first error line or "", IREE's static stats)."""
    from iree.compiler import CompilerToolError, compile_str

    stats = os.path.join(workdir, f"{tag}.stats.txt")
    t0 = time.perf_counter()
    try:
        vmfb = compile_str(mlir, input_type="stablehlo", extra_args=[
            *IREE_FLAGS, "--iree-scheduling-dump-statistics-format=pretty",
            f"--iree-scheduling-dump-statistics-file={stats}"])
        err = ""
    except CompilerToolError as e:
        vmfb = None
        err = next((ln.strip() for ln in str(e).splitlines() if "error:" in ln), str(e))[:300]
    secs = time.perf_counter() - t0
    found = {}
    if vmfb is not None and os.path.exists(stats):
        found = {k: int(v) for k, v in _STAT.findall(open(stats).read())}
    return vmfb, secs, err, found


def _case(rng, ctl, q0, v0):
    """(ControllerState, Measurement): a random state near the stand (hinges +-0.05 rad,
    rates +-0.2) with both soles loaded, part-way through the motion (the clock started at
    t = 0, the last step one control period ago)."""
    import numpy as np

    q, v = q0.copy(), v0.copy()
    q[7:] += rng.uniform(-0.05, 0.05, q.size - 7)
    v = v + rng.uniform(-0.2, 0.2, v.size)
    dt, settle = ctl.control_dt, ctl.scenario.settle
    t = settle + rng.uniform(0.05, 1.0)
    from safewbc_jax.control import step as control_step
    from safewbc_jax.deploy.controller import Measurement

    st = control_step.init_state(ctl.ctx, q, v, np, np.float64)[0]
    st = st._replace(t0=np.asarray(0.0), prev_t=np.asarray(t - dt),
                     prev_tau=np.asarray(t - settle - dt))
    return st, Measurement(q, v, t, np.array([230.0, 230.0]))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="squat", choices=SCENARIOS)
    ap.add_argument("--states", type=int, default=5, help="random states for the agreement")
    ap.add_argument("--calls", type=int, default=400, help="timed calls per round and engine")
    ap.add_argument("--rounds", type=int, default=5, help="alternating rounds")
    ap.add_argument("--cpu", type=int, default=0, help="pin to this core (-1: no pinning)")
    ap.add_argument("--keep", default=None, help="folder to keep the .mlir, .vmfb, stats in")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    for name in ("states", "calls", "rounds"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be at least 1")
    try:
        import iree.compiler  # noqa: F401
        import iree.runtime as rt
    except ImportError as e:
        sys.exit(f"IREE is not installed ({e}); install it into this venv with\n"
                 "    pip install iree-base-compiler==3.13.0 iree-base-runtime==3.13.0")

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from alternate import alternating_p50

    import jax
    import jax.numpy as jnp
    import numpy as np

    import safewbc_jax
    from safewbc_jax.control import step as control_step
    from safewbc_jax.app.cli import pin_to_cpu
    from safewbc_jax.deploy.controller import Controller, Measurement
    from safewbc_jax.deploy.packing import FlatTree, Packer
    from safewbc_jax.sim.mujoco_loop import load_at_stand

    safewbc_jax.enable_x64()
    pinned = pin_to_cpu(args.cpu)
    workdir = args.keep or tempfile.mkdtemp(prefix="iree_step_")
    os.makedirs(workdir, exist_ok=True)

    _, _, _, sm, d = load_at_stand()
    q0, v0 = sm.to_controller(d.qpos, d.qvel)
    ctl = Controller(args.scenario, engine="xla")
    ctl.start(q0, v0, warm_up=False)
    ctx = ctl.ctx
    fixed_tree = (ctl.params, ctl.start_data, ctl.run_values)
    state0 = control_step.init_state(ctx, q0, v0, np, np.float64)[0]
    F = {k: FlatTree(t) for k, t in (("fixed", fixed_tree), ("state", state0),
                                     ("meas", Measurement(q0, v0, 0.0, np.zeros(2))))}
    out_packer = Packer()

    def build(fixed, state, meas):
        st, prep, qpm = control_step.prepare(ctx, *F["fixed"].unpack(fixed, jnp),
                                             F["state"].unpack(state, jnp),
                                             F["meas"].unpack(meas, jnp))
        return F["state"].pack(st, jnp), out_packer.pack((prep, qpm))

    rng = np.random.default_rng(0)
    fixed = F["fixed"].pack(fixed_tree)
    cases = []
    for _ in range(args.states):
        st, meas = _case(rng, ctl, q0, v0)
        cases.append((fixed, F["state"].pack(st), F["meas"].pack(meas)))

    xla = jax.jit(build)
    mlir = jax.export.export(xla)(*cases[0]).mlir_module()
    customs = sorted(set(re.findall(r'custom_call_target = "(\w+)"|stablehlo\.custom_call @(\w+)',
                                    mlir)))
    rewritten, n_concat = barrier_concatenates(mlir)
    with open(os.path.join(workdir, "step.mlir"), "w") as f:
        f.write(mlir)
    with open(os.path.join(workdir, "step_barriers.mlir"), "w") as f:
        f.write(rewritten)
    _, s_plain, err_plain, _ = _compile(mlir, workdir, "plain")
    vmfb, s_comp, err, stats = _compile(rewritten, workdir, "barriers")
    res = {"scenario": args.scenario, "pinned_cpu": pinned,
           "iree": importlib.metadata.version("iree-base-compiler"),
           "states": args.states, "custom_calls": [a or b for a, b in customs],
           "concatenates": n_concat,
           "as_exported": {"compiles": not err_plain, "error": err_plain,
                           "seconds": round(s_plain, 1)},
           "with_barriers": {"compiles": vmfb is not None, "error": err,
                             "seconds": round(s_comp, 1), "static": stats}}
    if vmfb is None:
        return _report(res, args.json)
    with open(os.path.join(workdir, "step.vmfb"), "wb") as f:
        f.write(vmfb)
    config = rt.Config("local-sync")
    sys_ctx = rt.SystemContext(config=config)
    module = rt.VmModule.copy_buffer(sys_ctx.instance, vmfb)
    sys_ctx.add_vm_module(module)
    fn = sys_ctx.modules[module.name]["main"]

    def run_iree(*a):
        return [np.asarray(o.to_host()) for o in fn(*a)]

    def run_xla(*a):
        return [np.asarray(o) for o in xla(*a)]

    worst, where = 0.0, {}
    for c in cases:
        for k, (a, b) in enumerate(zip(run_iree(*c), run_xla(*c))):
            fin = np.isfinite(a) & np.isfinite(b)
            scale = max(float(np.max(np.abs(b[fin]), initial=0.0)), 1.0)
            # |difference| / scale where both are finite; inf where only one is, or where
            # both are not finite and differ (NaN against inf, or infinities of two signs)
            diff = np.where(fin, np.abs(np.where(fin, a - b, 0.0)) / scale,
                            np.where(np.isnan(a) & np.isnan(b) | (a == b), 0.0, np.inf))
            worst = max(worst, float(np.max(diff, initial=0.0)))
            if k == 1 and np.max(diff, initial=0.0) > TOL:    # which leaf of (Prepared, QP)
                leaves = jax.tree_util.tree_flatten_with_path(out_packer.unpack(diff))[0]
                for path, leaf in leaves:
                    if np.max(leaf, initial=0.0) > TOL:
                        key = jax.tree_util.keystr(path)
                        where[key] = max(where.get(key, 0.0), float(np.max(leaf)))
    res["max_rel_difference"] = worst
    res["agree"] = worst <= TOL and not where
    res["differing"] = where
    c = cases[0]
    times, _ = alternating_p50({"xla": lambda: run_xla(*c), "iree": lambda: run_iree(*c)},
                               args.rounds, args.calls)
    res["p50_us_per_round"] = {k: [round(x, 1) for x in v] for k, v in times.items()}
    res["p50_us"] = {k: round(float(np.median(v)), 1) for k, v in times.items()}
    res["iree_over_xla"] = round(res["p50_us"]["iree"] / res["p50_us"]["xla"], 2)
    return _report(res, args.json)


def _report(res: dict, as_json: bool) -> dict:
    if as_json:
        print(json.dumps(res))
        return res
    ae, wb = res["as_exported"], res["with_barriers"]
    print(f"{res['scenario']}: the step's QP build exported ({len(res['custom_calls'])} custom "
          f"calls, {res['concatenates']} concatenates), IREE {res['iree']}")
    print("  as exported: " + ("compiles" if ae["compiles"] else f"fails: {ae['error']}")
          + f" ({ae['seconds']} s)")
    print("  with barriers on the concatenates: "
          + ("compiles" if wb["compiles"] else f"fails: {wb['error']}") + f" ({wb['seconds']} s)"
          + ("; " + ", ".join(f"{k} {v}" for k, v in wb["static"].items())
             if wb["static"] else ""))
    if "p50_us" in res:
        print(f"  outputs agree at {res['states']} random states: {res['agree']} (max difference "
              f"{res['max_rel_difference']:.1e} of each output's scale, tolerance {TOL:g})"
              + "".join(f"; {k} {v:.1e}" for k, v in res["differing"].items()))
        p = res["p50_us"]
        print(f"  p50 per call: XLA {p['xla']} us, IREE {p['iree']} us, IREE / XLA "
              f"{res['iree_over_xla']}x (medians of {len(res['p50_us_per_round']['xla'])} "
              "alternating rounds)")
    return res


if __name__ == "__main__":
    main()
