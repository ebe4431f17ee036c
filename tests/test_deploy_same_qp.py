"""The deployed step builds the controller's own QP: at 100 random states per scenario
(walking in both stances as well as standing), the QP of ``Controller``'s step generated as
C (``deploy.codegen``; one call: the gait, the QP and the exact elimination, on flat
vectors) equals the pure functions' (``control_step.prepare`` jitted on its pytrees, and
the numpy elimination ``reduce.eliminate_equalities_np`` of that QP) to 1e-9; the C
``prepare``, ``conclude`` and acceptance (``accept_solution``) equal the same flat
functions jitted by XLA, every output, to 1e-12; and the XLA step's kernel count stays
bounded.

Tolerance: both sides evaluate the same float64 expressions, compiled in two different
programs (XLA may fuse and reorder them differently), and the two eliminations factor
the same matrices with different LAPACK paths; 1e-9 relative to each array's largest
entry is ~1e4 eps, above the reordering noise (~1e-13 seen) and the eliminations'
cond x eps (~1e-11 seen), far below any change to the QP (a gain, a row, a state).
"""

import jax
import numpy as np
import pytest

from safewbc_jax.control import qp as qp_assembly
from safewbc_jax.control import step as control_step, walking
from safewbc_jax.model import spatial
from safewbc_jax.control.step import Measurement
from safewbc_jax.deploy.controller import Controller
from safewbc_jax.solvers.problem import FIELDS
from safewbc_jax.solvers.piqp_path import REDUCED_QP_SETTINGS, PiqpSolver
from safewbc_jax.solvers.result import failed
from safewbc_jax.solvers.status import SolveStatus
from safewbc_jax.solvers import policy, reduce

N_STATES = 100
TOL = 1e-9
# C against XLA, the same flat functions: only the order of sums (dot products, the
# factorisations) and libm's last bit differ; 6e-14 relative seen over the five scenarios
TOL_C = 1e-12
# XLA's cost analysis of the deployed step (``Controller.kernels(cost=True)``), which is
# deterministic for a jaxlib version and a backend. Kernels (each costs ~1 us on the CPU
# whatever its size): at most what the step had before its lean rewrite (squat 286, arms
# 304, walk 471; measured after it: 220, 250, 415). Flops and bytes accessed: 5% above
# what the lean step measured on jax 0.10.2 (squat 0.568 MFLOP and 1.433 MB, arms 0.632
# and 1.623, walk 0.728 and 1.915; before it 1.305/2.73, 1.372/3.03, 1.449/3.31), a
# margin for another CPU's fusion choices, far below what undoing a part of the rewrite
# costs (M as the sum over the bodies' Jacobians alone is +0.6 MFLOP; P as one 78 x 78
# sum that each block's slice recomputes, +0.09; the whole 78-variable QP written out
# again, +0.23 MB).
COST_BOUND = {"squat": (286, 0.568e6, 1.433e6), "arms": (304, 0.632e6, 1.623e6),
              "walk": (471, 0.728e6, 1.915e6)}


def _random_case(rng, ctl, q0, k):
    """A state near the stand (hinges +-0.08 rad, base +-2 cm and a small tilt, rates
    +-0.3) and a ControllerState: standing before the motion, or (walking) in a left or
    right stance part-way through a step, with sole forces that load the stance foot."""
    nq = q0.size
    q = q0.copy()
    q[:3] += rng.uniform(-0.02, 0.02, 3)
    tilt = rng.normal(0.0, 0.03, 3)
    w = np.concatenate([[1.0], 0.5 * tilt])
    w /= np.linalg.norm(w)
    q[3:7] = np.asarray(spatial.quat_mul(q0[3:7], w))     # the stand's orientation, tilted
    q[7:] += rng.uniform(-0.08, 0.08, nq - 7)
    v = rng.uniform(-0.3, 0.3, ctl.model.nv)
    st = control_step.init_state(ctl.ctx, q, v, np, np.float64)[0]
    dt, settle = ctl.control_dt, ctl.scenario.settle
    stance = (walking.BOTH, walking.LEFT, walking.RIGHT)[k % 3] if ctl.walking else walking.BOTH
    tau = rng.uniform(0.05, 1.5) if stance != walking.BOTH else rng.uniform(-0.5, 1.5)
    t = settle + tau
    force = np.array([300.0, 0.0]) if stance == walking.LEFT else (
        np.array([0.0, 300.0]) if stance == walking.RIGHT else np.array([230.0, 230.0]))
    gait = st.gait if not ctl.walking else st.gait._replace(     # () without a gait
        stance=np.asarray(stance, float), tau_step=np.asarray(rng.uniform(0.0, 0.25)),
        stance0=np.array([0.0, 0.1 * stance, 0.0]), swing0=np.array([0.0, -0.1 * stance, 0.0]))
    st = st._replace(gait=gait, t0=np.asarray(0.0), prev_t=np.asarray(t - dt),
                     prev_tau=np.asarray(tau - dt))
    return st, Measurement(q, v, t, force)


def _close(name, a, b, tol=TOL):
    a, b = np.asarray(a, float), np.asarray(b, float)
    assert a.shape == b.shape, name
    fin = np.isfinite(b)
    assert np.array_equal(fin, np.isfinite(a)) and np.array_equal(a[~fin], b[~fin],
                                                                   equal_nan=True), name
    scale = max(1.0, float(np.abs(b[fin]).max(initial=0.0)))
    err = float(np.abs(a[fin] - b[fin]).max(initial=0.0))
    assert err <= tol * scale, f"{name}: max |diff| {err:.3g} (scale {scale:.3g})"
    return err / scale


@pytest.mark.slow
@pytest.mark.parametrize("name", ["squat", "bow", "arms", "walk", "push"])
def test_deployed_step_builds_the_pure_functions_qp(stand, name):
    ctl = Controller(name, engine="c")        # the generated C step (deploy.codegen)
    ctl.start(*stand)
    fixed = (ctl.params, ctl.start_data, ctl.run_values)
    cs = ctl.compiled
    lay, xla_prepare, xla_conclude = cs.layouts, jax.jit(cs.prepare_fn), jax.jit(cs.conclude_fn)
    flat_fixed = cs.pack_fixed(*fixed)
    tally = lay.tally.pack(control_step.init_state(ctl.ctx, *stand, np, np.float64)[1])
    ref = jax.jit(lambda f, s, m: control_step.prepare(ctl.ctx, *f, s, m))
    rng = np.random.default_rng(14)
    xla_accept = jax.jit(cs.accept_fn)
    piqp = PiqpSolver(update=False, nominal_settings=REDUCED_QP_SETTINGS)
    bounded = None
    worst, stances, accepted = 0.0, set(), set()
    for k in range(N_STATES):
        state, meas = _random_case(rng, ctl, stand[0], k)
        new, qpm, red, rmap = ctl.prepare_flat(state, meas)
        new_ref, _, qp_ref = jax.tree_util.tree_map(np.asarray, ref(fixed, state, meas))
        for f in FIELDS:
            worst = max(worst, _close(f"{name} state {k}: QP {f}", getattr(qpm, f),
                                      getattr(qp_ref, f)))
        for a, b in zip(jax.tree_util.tree_leaves(new), jax.tree_util.tree_leaves(new_ref)):
            _close(f"{name} state {k}: controller state", a, b)
        if bounded is None:
            bounded = reduce.bounded_variables(qp_ref)
        # the structure the deployed elimination takes as static (qp.P_STRUCTURE)
        assert bounded.size == 0 and reduce.p_structure(qp_ref) == qp_assembly.P_STRUCTURE
        # the reference: the elimination with P as a dense matrix, on the pure functions' QP
        red_ref, rmap_ref = reduce.eliminate_equalities_np(qp_ref, bounded)
        for f in FIELDS:
            worst = max(worst, _close(f"{name} state {k}: reduced QP {f}", getattr(red, f),
                                      getattr(red_ref, f)))
        for a, b in zip(jax.tree_util.tree_leaves(rmap), jax.tree_util.tree_leaves(rmap_ref)):
            _close(f"{name} state {k}: map back to X", a, b)
        if ctl.walking:
            stances.add(float(new.gait.stance))
        # the same flat step by XLA: prepare's every output, and conclude's at a solution
        flat_in = (flat_fixed, lay.state.pack(state), cs.flat_measurement(meas))
        got, want = cs.prepare(*flat_in), xla_prepare(*flat_in)
        for what, a, b in zip(("state", "prepared", "packed QP"), got, want):
            worst = max(worst, _close(f"{name} state {k}: C/XLA {what}", a, b, TOL_C))
        # the host's acceptance after PIQP (``accept_solution``), C against XLA, at PIQP's
        # solution of the reduced QP and at a random point (refused: ok 0), and its
        # decision against numpy's (``policy.accept_batch``)
        packed = got[2]
        _, red_c, _, checks_c = cs.unpack_qp(packed[None])
        xr, st, it = (piqp.solve_nominal(red_c.row(0)) if k % 2 == 0
                      else (rng.standard_normal(cs.nr), SolveStatus.SOLVED, 3))
        solved_in = np.concatenate([xr, [st, it, piqp.feas_tol]])
        got_a, want_a = cs.accept(packed, solved_in), xla_accept(packed, solved_in)
        for what, a, b in zip(("solve record", "u", "motor", "ok"), got_a, want_a):
            worst = max(worst, _close(f"{name} state {k}: C/XLA accept {what}", a, b, TOL_C))
        st_np, _ = policy.accept_batch(xr[None], red_c, [st], piqp.feas_tol, checks_c)
        assert bool(got_a[3]) == (st_np[0] == SolveStatus.SOLVED), (name, k)
        accepted.add(bool(got_a[3]))
        sol = cs.flat_solution(failed(cs.nx)._replace(
            x=rng.standard_normal(cs.nx), status=0, fallback=k % 2, iterations=5,
            eq_residual=1e-9))
        got, want = cs.conclude(flat_fixed, tally, got[1], sol), xla_conclude(
            flat_fixed, tally, want[1], sol)
        for what, a, b in zip(("tally", "record"), got, want):
            worst = max(worst, _close(f"{name} state {k}: C/XLA conclude {what}", a, b,
                                      TOL_C))
    assert accepted == {True, False}, accepted
    if ctl.walking:      # both stances and standing were built
        assert stances == {walking.BOTH, walking.LEFT, walking.RIGHT}, stances
    if name in COST_BOUND:
        cost = ctl.kernels(cost=True)
        kernels, flops, nbytes = COST_BOUND[name]
        assert 50 < cost["kernels"] <= kernels, cost
        assert cost["flops"] <= 1.05 * flops and cost["bytes"] <= 1.05 * nbytes, cost
    print(f"{name}: worst relative difference {worst:.2e} over {N_STATES} states")
