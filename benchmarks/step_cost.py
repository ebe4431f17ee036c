"""What one control step computes, by XLA's own cost analysis: flops, bytes accessed and
kernels of every scenario's deployed step, and of the parts of one standing scenario's.

The deployed step is ``Controller``'s jitted ``prepare`` with the elimination, on its
flat vectors, at the stand (``Controller.kernels(cost=True)``). A walking scenario's
stance is data of its one compiled program: the left and the right stance run the same
program, so they cost the same. Each part is compiled alone, from the outputs of the
parts before it as inputs, so that no part is charged for another's work; XLA may
recompute a cheap producer inside several consumers when they are compiled together,
so the parts need not add up to the whole.

The figures are deterministic for a jaxlib version and a CPU backend
(``tests/test_deploy_same_qp.py`` bounds the deployed step's). XLA counts a custom call
(a LAPACK factorisation or triangular solve) as no flops.

    python benchmarks/step_cost.py [--scenarios squat,bow,arms,walk,push]
        [--parts squat] [--c] [--json]

``--c``: also each part, and the whole deployed prepare, as the C engine generates and
builds it (``deploy.codegen``: ``opt_flags`` and the CPU's level), timed per call with its code
and data warm: the bare C function called through ctypes on fixed inputs, 300 calls to
warm up, then the median of 5 runs of 2,000 calls. Pin the process to one idle core.
"""

from __future__ import annotations

import argparse
import json

STANDING = ("squat", "bow", "arms")


def deployed(names, q0, v0) -> dict:
    from safewbc_jax.deploy.controller import Controller

    out = {}
    for name in names:
        ctl = Controller(name, engine="xla")
        ctl.start(q0, v0, warm_up=False)
        out[name] = ctl.kernels(cost=True)
    return out


def c_time_us(fn, *args) -> float:
    """Warm time per call (us) of ``fn(*args)`` (pytrees of arrays) as generated C."""
    import jax
    import numpy as np

    from safewbc_jax.deploy.codegen import build, emit

    leaves = [np.asarray(a) for a in jax.tree_util.tree_leaves(args)]
    cf = emit.emit_function("part", jax.make_jaxpr(fn)(*args))   # inputs: the leaves
    call = build.CCall(build.load(build.build(emit.c_file([cf]))[0]), cf)
    return bare_us(call, [np.ascontiguousarray(a, dtype=dt)
                          for a, dt in zip(leaves, call.in_dtypes)])


def bare_us(call, ins) -> float:
    """The median time per call (us) of a built ``CCall``'s C function on ``ins``."""
    import time

    import numpy as np

    ptrs = [a.ctypes.data for a in ins] + call.out_ptrs
    for _ in range(300):
        call.c(*ptrs)
    runs = []
    for _ in range(5):
        t = time.perf_counter_ns()
        for _ in range(2000):
            call.c(*ptrs)
        runs.append((time.perf_counter_ns() - t) / 2000 / 1e3)
    return float(np.median(runs))


def parts(name, q0, v0, c: bool = False) -> dict:
    """The parts of a standing scenario's step, each compiled alone (and, with ``c``, the
    warm time of each as generated C, and of the whole deployed prepare)."""
    import jax
    import jax.numpy as jnp

    from safewbc_jax.control import terms as controller
    from safewbc_jax.deploy import kernels
    from safewbc_jax.model import robot
    from safewbc_jax.deploy.controller import Controller
    from safewbc_jax.control.outputs import StepTerms
    from safewbc_jax.solvers import reduce
    from safewbc_jax.control.step import Measurement
    import numpy as np

    ctl = Controller(name, engine="xla")
    ctl.start(q0, v0, warm_up=False)
    m, sc, params, start = ctl.model, ctl.scenario, ctl.params, ctl.start_data
    q, v, tau = jnp.asarray(q0), jnp.asarray(v0), jnp.asarray(0.3)
    in_contact = jnp.asarray(sc.in_contact, q.dtype)
    kin = jax.jit(lambda q: robot.forward_kinematics(m, q))(q)
    motion = jax.jit(lambda k, v: robot.body_motion(m, k, v))(kin, v)
    dyn = jax.jit(lambda k, mo: robot.dynamics(m, k, mo))(kin, motion)
    terms = jax.jit(lambda q, v: controller.robot_terms(m, sc, q, v))(q, v)

    def build(t, q, v, tau):
        return controller.build_qp(m, sc, params, t, q, v, tau, start, in_contact)[0]

    qp = jax.jit(build)(terms, q, v, tau)
    bounded, blockdiag = reduce.bounded_variables(qp), reduce.p_structure(qp)
    rows = {
        "kinematics (FK of every body)": (lambda q: robot.forward_kinematics(m, q), q),
        "body motion (velocities, bias accelerations)":
            (lambda k, v: robot.body_motion(m, k, v), kin, v),
        "M, h, CoM terms": (lambda k, mo: robot.dynamics(m, k, mo), kin, motion),
        "constraint Jacobians and drifts":
            (lambda k, mo: controller.constraint_terms(m, k, mo), kin, motion),
        "outputs": (lambda q, v, d, k, mo: {o.name: o.evaluate(m, q, v, StepTerms(d, k, mo))
                                            for o in sc.outputs}, q, v, dyn, kin, motion),
        "robot terms (all of the above)":
            (lambda q, v: controller.robot_terms(m, sc, q, v), q, v),
        "QP build (references, barriers, contacts, assembly)": (build, terms, q, v, tau),
        "elimination": (lambda qp: reduce.eliminate_equalities(qp, bounded, blockdiag), qp),
    }
    out = {k: kernels.cost(f, *a) for k, (f, *a) in rows.items()}
    if c:
        for k, (f, *a) in rows.items():
            out[k]["c_us"] = round(c_time_us(f, *a), 1)
        cctl = Controller(name, engine="c")
        cctl.start(q0, v0, warm_up=False)
        cs = cctl.compiled
        meas = cs.flat_measurement(Measurement(q0, v0, 0.0, np.zeros(2)))
        whole = cs.pack_fixed(cctl.params, cctl.start_data, cctl.run_values)
        state = cs.layouts.state.pack(cctl.state)
        out["the deployed prepare (the whole step before PIQP)"] = {
            **cctl.kernels(cost=True), "c_us": round(bare_us(cs.prepare, [whole, state, meas]), 1)}
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default="squat,bow,arms,walk,push")
    ap.add_argument("--parts", default="squat", help="a standing scenario ('' : none)")
    ap.add_argument("--c", action="store_true",
                    help="also the parts' warm time as generated C (builds each: minutes)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    import safewbc_jax
    from safewbc_jax import scenarios

    names = [s for s in args.scenarios.split(",") if s]
    bad = [s for s in names if s not in scenarios.names()]
    if bad:
        ap.error(f"--scenarios: unknown {', '.join(bad)}; available: "
                 f"{', '.join(scenarios.names())}")
    if args.parts and args.parts not in STANDING:
        ap.error(f"--parts {args.parts!r}: a standing scenario ({', '.join(STANDING)})")
    safewbc_jax.enable_x64()
    import jax

    from safewbc_jax.sim.mujoco_loop import load_at_stand

    _, _, _, sm, d = load_at_stand()
    q0, v0 = sm.to_controller(d.qpos, d.qvel)
    out = {"jax": jax.__version__, "deployed": deployed(names, q0, v0),
           "parts": parts(args.parts, q0, v0, args.c) if args.parts else {}}
    if args.json:
        print(json.dumps(out))
        return out

    def line(label, c):
        print(f"  {label:<52} {c['flops'] / 1e6:7.3f} MFLOP {c['bytes'] / 1e6:7.3f} MB "
              f"{c['kernels']:5d} kernels" + (f" {c['c_us']:7.1f} us as C" if "c_us" in c
                                              else ""))

    print(f"jax {jax.__version__}: the deployed step (prepare with the elimination), at the stand")
    for k, c in out["deployed"].items():
        line(k + (" (either stance: one program)" if k in ("walk", "push") else ""), c)
    if out["parts"]:
        print(f"parts of {args.parts}'s step, each compiled alone")
        for k, c in out["parts"].items():
            line(k, c)
    return out


if __name__ == "__main__":
    main()
