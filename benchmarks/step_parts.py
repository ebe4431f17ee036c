"""Where the jitted step's time goes, in a tight loop, and what MuJoCo's C functions take.

Four timed calls at the stand of a standing scenario, alternating rounds in one process.
Each call includes the host copy of its outputs, packed into one vector.
- **robot terms**: ``controller.robot_terms`` jitted: kinematics, M, h, the constraint
  Jacobians and drifts, and every output's (y, J_y, J_y_dot v).
- **rest**: given those terms as input, ``controller.build_qp``, the exact elimination
  (``reduce.eliminate_equalities``) and the PIQP checks (``policy.checks``), jitted.
- **whole**: the two in one jitted function, which is the deployed step less its gait
  and clock logic.
- **mujoco**: MuJoCo's C functions on the controller model: forward kinematics, the
  composite inertias and the dense M (``mj_crb``, ``mj_fullM``), h (``mj_rne``), ten site
  Jacobians with their time derivatives (``mj_jacSite``, ``mj_jacDot``), and the CoM
  Jacobian (``mj_jacSubtreeCom``). This is the robot-terms part that a MuJoCo-C engine
  would take over.

``--gap-ms G`` busy-waits G ms after each call, as a control loop does between its
steps. The script also prints the context switches per call (``getrusage``). It runs
under any jax that runs the package; under jaxlib 0.4.31 it times XLA:CPU's classic
runtime.

    python benchmarks/step_parts.py [--scenario squat] [--calls 500] [--rounds 4]
        [--gap-ms 0] [--cpu 0] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys

SCENARIOS = ("squat", "bow", "arms")     # standing: no gait state in the terms


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="squat", choices=SCENARIOS)
    ap.add_argument("--calls", type=int, default=500, help="timed calls per round and part")
    ap.add_argument("--rounds", type=int, default=4, help="alternating rounds")
    ap.add_argument("--gap-ms", type=float, default=0.0, help="busy wait after each call")
    ap.add_argument("--cpu", type=int, default=0, help="pin to this core (-1: no pinning)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.calls < 1 or args.rounds < 1 or args.gap_ms < 0:
        ap.error("--calls and --rounds must be at least 1, --gap-ms at least 0")

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from alternate import alternating_p50

    import jax
    import jax.numpy as jnp
    import mujoco
    import numpy as np

    import safewbc_jax
    from safewbc_jax.base import paths
    from safewbc_jax.control import terms as controller
    from safewbc_jax.deploy import kernels
    from safewbc_jax.app.cli import pin_to_cpu
    from safewbc_jax.deploy.controller import Controller
    from safewbc_jax.deploy.packing import FlatTree, Packer
    from safewbc_jax.sim.mujoco_loop import load_at_stand
    from safewbc_jax.solvers import policy, reduce

    safewbc_jax.enable_x64()
    pinned = pin_to_cpu(args.cpu)
    _, _, _, sm, d = load_at_stand()
    q0, v0 = sm.to_controller(d.qpos, d.qvel)
    ctl = Controller(args.scenario, engine="xla")
    ctl.start(q0, v0, warm_up=False)
    model, sc, params, start = ctl.model, ctl.scenario, ctl.params, ctl.start_data
    in_contact = jnp.asarray(sc.in_contact, float)
    qj, vj, tau = jnp.asarray(q0), jnp.asarray(v0), jnp.asarray(0.3)

    def terms_of(q, v):
        return controller.robot_terms(model, sc, q, v)

    terms0 = jax.tree_util.tree_map(np.asarray, jax.jit(terms_of)(qj, vj))
    flat_terms = FlatTree(terms0)
    qp0 = jax.tree_util.tree_map(np.asarray, jax.jit(lambda q, v, t: controller.build_qp(
        model, sc, params, terms_of(q, v), q, v, t, start, in_contact)[0])(
            qj, vj, tau))
    # the structure the deployed step takes (trees before p_structure: p_block_diagonal)
    structure = getattr(reduce, "p_structure", reduce.p_block_diagonal)
    bounded, p_blockdiag = reduce.bounded_variables(qp0), structure(qp0)
    packers = {k: Packer() for k in ("rest", "whole")}

    def rest(terms, q, v, t, packer):
        qpm, _ = controller.build_qp(model, sc, params, terms, q, v, t, start, in_contact)
        red, rmap = reduce.eliminate_equalities(qpm, bounded, p_blockdiag)
        # as the deployed step writes it: the full QP's equality rows, not the whole QP
        return packer.pack(((qpm.A, qpm.b), red, rmap, policy.checks(red, jnp)))

    fns = {
        "robot terms": (lambda q, v: flat_terms.pack(terms_of(q, v), jnp), (qj, vj)),
        "rest": (lambda tf, q, v, t: rest(flat_terms.unpack(tf, jnp), q, v, t, packers["rest"]),
                 (jnp.asarray(flat_terms.pack(terms0)), qj, vj, tau)),
        "whole": (lambda q, v, t: rest(terms_of(q, v), q, v, t, packers["whole"]),
                  (qj, vj, tau)),
    }
    calls = {}
    counts = {}
    for name, (fn, a) in fns.items():
        jf = jax.jit(fn)
        calls[name] = (lambda jf=jf, a=a: np.asarray(jf(*a)))
        counts[name] = kernels.count(fn, *a)["total"]

    mc = mujoco.MjModel.from_xml_path(str(paths.controller_xml()))
    dc = mujoco.MjData(mc)
    dc.qpos[:], dc.qvel[:] = q0, v0
    M, h = np.zeros((mc.nv, mc.nv)), np.zeros(mc.nv)
    jp, jr, jcom = np.zeros((3, mc.nv)), np.zeros((3, mc.nv)), np.zeros((3, mc.nv))
    sites = range(min(mc.nsite, 10))

    def mujoco_terms():
        mujoco.mj_kinematics(mc, dc)
        mujoco.mj_comPos(mc, dc)
        mujoco.mj_crb(mc, dc)
        mujoco.mj_fullM(mc, dc, M)
        mujoco.mj_comVel(mc, dc)
        mujoco.mj_rne(mc, dc, 0, h)
        for s in sites:
            mujoco.mj_jacSite(mc, dc, jp, jr, s)
            mujoco.mj_jacDot(mc, dc, jp, jr, dc.site_xpos[s], mc.site_bodyid[s])
        mujoco.mj_jacSubtreeCom(mc, dc, jcom, 0)

    calls["mujoco"] = mujoco_terms
    p50, switches = alternating_p50(calls, args.rounds, args.calls, args.gap_ms * 1e-3)
    out = {"scenario": args.scenario, "jax": jax.__version__, "pinned_cpu": pinned,
           "gap_ms": args.gap_ms, "kernels": counts,
           "p50_us": {k: round(float(np.median(v)), 1) for k, v in p50.items()},
           "p50_us_per_round": {k: [round(x, 1) for x in v] for k, v in p50.items()},
           "context_switches_per_call": switches}
    if args.json:
        print(json.dumps(out))
        return out
    print(f"{args.scenario}, jax {jax.__version__}, core {pinned}, gap {args.gap_ms} ms: p50 "
          f"per call (medians of {args.rounds} alternating rounds of {args.calls})")
    for k, v in out["p50_us"].items():
        kern = f", {counts[k]} kernels" if k in counts else ""
        cs = out["context_switches_per_call"][k]
        print(f"  {k}: {v} us{kern}; context switches per call {cs[0]} voluntary, "
              f"{cs[1]} involuntary")
    return out


if __name__ == "__main__":
    main()
