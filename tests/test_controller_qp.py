"""The controller's QP at a real state: PIQP solutions against the dynamics, the exact
equality elimination against the full QP, parameter and pole validation."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from safewbc_jax import scenarios
from safewbc_jax.control import step as control_step, terms as controller
from safewbc_jax.control.params import ParamsError, apply_overrides, load_overrides, to_toml
from safewbc_jax.solvers import reduce
from safewbc_jax.solvers.piqp_path import PiqpSolver
from safewbc_jax.solvers.result import FALLBACK_NONE
from safewbc_jax.solvers.status import SolveStatus


def _arms_qp(ctrl_mj, rm, sc):
    params = sc.default_params()
    q = jnp.asarray(ctrl_mj.key_qpos[0])
    v = jnp.asarray(np.random.default_rng(3).normal(0, 0.2, rm.nv))
    start = control_step.start_data(rm, sc, q)

    def fn(q, v, tau):
        terms = controller.robot_terms(rm, sc, q, v)
        return controller.build_qp(rm, sc, params, terms, q, v, tau, start, jnp.ones(2))

    qpm, aux = jax.jit(fn)(q, v, jnp.asarray(6.0))
    return jax.tree_util.tree_map(np.asarray, qpm), aux


@pytest.fixture(scope="module")
def arms_qp(ctrl_mj, rm):
    """The arms scenario's QP (barrier row included) at the stand pose with a random
    velocity, half-way into the motion."""
    return _arms_qp(ctrl_mj, rm, scenarios.get_scenario("arms"))


def test_barriers_off_drops_the_rows_and_keeps_h(arms_qp, ctrl_mj, rm):
    """``barrier=False`` (``safewbc run --no-barrier``, ``BatchConfig.barrier``, a sweep's
    ``barrier = false``), by name or on a Scenario object, monitors every safe set: the QP
    as with the barrier but for its A-ECBF row, and h still reported."""
    arms = scenarios.get_scenario("arms")
    off = scenarios.get_scenario("arms", barrier=False)
    assert [b.name for b in off.barriers] == [] and \
        {b.name for b in off.monitors} == {"left_fist", "right_fist"}
    assert scenarios.get_scenario(arms, barrier=False) == off
    on, aux_on = arms_qp
    qp_off, aux_off = _arms_qp(ctrl_mj, rm, off)
    assert qp_off.G.shape[0] == on.G.shape[0] - 1
    # two compiled programs: XLA may fuse the shared arithmetic differently, so equal up
    # to rounding (1e-12 of each array's largest finite entry; the infinite bounds equal)
    def same(a, b, what):
        scale = max(np.abs(b[np.isfinite(b)]).max(), 1.0)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * scale, err_msg=what)
    for f in ("P", "q", "A", "b", "lb", "ub"):
        same(getattr(qp_off, f), getattr(on, f), f)
    same(qp_off.G, on.G[:-1], "G")          # the barrier row is the last
    same(qp_off.h, on.h[:-1], "h")
    np.testing.assert_array_equal(qp_off.soft, on.soft[:-1])
    for name in ("left_fist", "right_fist"):
        np.testing.assert_allclose(aux_off.barrier_h[name], aux_on.barrier_h[name],
                                   rtol=0, atol=1e-12)


def test_qp_shapes_and_soft_rows(arms_qp, rm):
    qpm, _ = arms_qp
    n = rm.nv + rm.nu + 22
    assert qpm.P.shape == (n, n) and qpm.A.shape == (rm.nv + 22, n)
    assert qpm.G.shape == (30 + 1, n)  # friction/torsion 14, CoP 8, ZMP 8, one barrier row
    np.testing.assert_array_equal(qpm.soft, [0] * 14 + [1] * 17)
    np.testing.assert_allclose(qpm.P, qpm.P.T, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(qpm.P) > 0)
    # the QP carries its block sizes (static data through jit), the model's
    assert (qpm.nv, qpm.nu, qpm.nc) == (rm.nv, rm.nu, 22) and qpm.has_blocks
    assert reduce.has_controller_structure(qpm) and reduce.p_block_diagonal(qpm)


def test_piqp_solution_satisfies_dynamics(arms_qp, rm):
    qpm, _ = arms_qp
    r = PiqpSolver().solve(qpm)
    x = r.x
    assert r.status == SolveStatus.SOLVED and r.fallback == FALLBACK_NONE
    nv = qpm.nv
    qdd, u, lam = qpm.split(x)
    m, h = qpm.A[:nv, :nv], -qpm.b[:nv]
    jt = -qpm.split(qpm.A[:nv])[2]
    # M q_ddot + h = B u + J^T lambda (eq. 1), to 1e-8 relative to the force scale.
    res = m @ qdd + h - np.asarray(rm.B) @ u - jt @ lam
    assert np.abs(res).max() <= 1e-8 * max(1.0, np.abs(h).max())
    assert np.abs(qpm.A @ x - qpm.b).max() <= 1e-8 * max(1.0, np.abs(qpm.b).max())
    assert np.max(qpm.G @ x - qpm.h) <= 1e-8
    assert np.all(np.abs(u) <= np.asarray(rm.torque_limit) + 1e-8)


def test_reduced_qp_is_the_same_problem(arms_qp, rm):
    qpm, _ = arms_qp
    bounded = reduce.bounded_variables(qpm)
    assert bounded.size == 0
    red, rmap = reduce.eliminate_equalities_np(qpm, bounded)
    red_j, rmap_j = jax.jit(lambda qp: reduce.eliminate_equalities(qp, bounded))(qpm)
    red_b, _ = reduce.eliminate_equalities_np(qpm, bounded, p_blockdiag=True)
    np.testing.assert_allclose(red_b.P, red.P, rtol=1e-12, atol=1e-12)
    assert not red.has_blocks and red.A.shape == (0, rm.nu)
    np.testing.assert_allclose(rmap_j.N, rmap.N, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(red_j.P, red.P, rtol=1e-9, atol=1e-9)
    # Every u gives an X on the equality manifold.
    u = np.random.default_rng(0).normal(0, 30, rm.nu)
    x = rmap.x0 + rmap.N @ u
    assert np.abs(qpm.A @ x - qpm.b).max() <= 1e-9 * max(1.0, np.abs(qpm.b).max())
    # Solving the reduced QP gives the full QP's optimum. The internal-force directions of
    # lambda cost only Gamma (1e-7 .. 1e-4), so the optimum is flat along them: compare at
    # tight solver tolerances.
    tight = dict(eps_abs=1e-12, eps_rel=1e-14, eps_duality_gap_abs=1e-12,
                 eps_duality_gap_rel=1e-14)
    r_red = PiqpSolver(**tight).solve(red)
    r_full = PiqpSolver(**tight).solve(qpm)
    assert r_red.fallback == r_full.fallback == FALLBACK_NONE
    x_full = r_full.x
    x_red = reduce.expand(r_red.x, rmap)
    scale = max(1.0, np.abs(x_full).max())
    assert np.abs(x_red - x_full).max() <= 1e-6 * scale
    cost = lambda x: 0.5 * x @ qpm.P @ x + qpm.q @ x  # noqa: E731
    assert cost(x_red) == pytest.approx(cost(x_full), rel=1e-7, abs=1e-7)


def test_g_layout_is_what_the_qp_claims_and_the_elimination_uses_it(arms_qp, rm):
    """qp.assemble claims (QP.ng_lambda) that G's contact rows are zero outside lambda and
    its barrier rows zero outside q_ddot; the elimination then multiplies those blocks
    only. The claim holds in the arrays, and the reduced QP is the one without the claim
    (same operations on the nonzero blocks, in another grouping: rounding only)."""
    qpm, _ = arms_qp
    k, nv, nu = qpm.ng_lambda, rm.nv, rm.nu
    assert k == qpm.G.shape[0] - 1            # the arms' one enforced barrier row
    assert not qpm.G[:k, :nv + nu].any() and not qpm.G[k:, nv:].any()
    assert np.abs(qpm.G[k:, :nv]).max() > 0 and np.abs(qpm.G[:k, nv + nu:]).max() > 0
    generic = dataclasses.replace(qpm, ng_lambda=None)
    for elim in (reduce.eliminate_equalities_np,
                 jax.jit(reduce.eliminate_equalities, static_argnums=(1, 2))):
        (got, gmap), (ref, rmap) = elim(qpm, None, True), elim(generic, None, True)
        for a, b in ((got.G, ref.G), (got.h, ref.h), (got.P, ref.P), (gmap.N, rmap.N)):
            a, b = np.asarray(a), np.asarray(b)
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max())


def test_barrier_row_in_the_qp(arms_qp, rm, ctrl_mj):
    """The barrier row of G is -(dh/dq) q_ddot <= K_alpha eta + J_dot v with the fist
    height computed independently from MuJoCo."""
    import mujoco

    qpm, aux = arms_qp
    d = mujoco.MjData(ctrl_mj)
    d.qpos[:] = ctrl_mj.key_qpos[0]
    mujoco.mj_kinematics(ctrl_mj, d)
    t, f = ctrl_mj.site("torso").id, ctrl_mj.site("left-fist").id
    pz = (d.site_xmat[t].reshape(3, 3).T @ (d.site_xpos[f] - d.site_xpos[t]))[2]
    h = -pz - scenarios.ARM_THRESHOLD
    assert float(aux.barrier_h["left_fist"]) == pytest.approx(h, abs=1e-12)
    row = -qpm.G[-1, :rm.nv]
    assert np.abs(qpm.G[-1, rm.nv:]).max() == 0.0
    assert np.linalg.norm(row) > 0.1  # the fist moves with the arm joints


def test_params_stay_float64_whatever_a_user_passes():
    """Python floats in ``replace``, a TOML override or a controller's params become
    float64 arrays that are not weakly typed: a weak leaf is another program for every
    jit over the params (a controller's start-up QP compiled again, 7 s)."""
    from safewbc_jax.deploy.controller import Controller

    sc = scenarios.get_scenario("arms")
    p = sc.default_params()
    assert jnp.asarray(0.5).weak_type            # the trap
    p2 = p.replace(threshold={**p.threshold, "left_fist": 0.5}, mu=0.4)
    p3 = apply_overrides(p, {"mu": 0.5, "threshold": {"left_fist": 0.2}})
    ctl = Controller("arms", dataclasses.replace(p, mu=jnp.asarray(0.3)))
    for q in (p2, p3, ctl.params):
        leaves = jax.tree_util.tree_leaves(q)
        assert len(leaves) == len(jax.tree_util.tree_leaves(p))
        assert all(a.dtype == jnp.float64 and not a.weak_type for a in leaves)
    assert float(p2.threshold["left_fist"]) == 0.5 and float(p3.mu) == 0.5
    assert float(ctl.params.mu) == 0.3


def test_params_overrides_validated(tmp_path):
    sc = scenarios.get_scenario("arms")
    p = sc.default_params()
    good = tmp_path / "good.toml"
    good.write_text("mu = 0.5\n[kp]\ncom = [90, 90, 120]\n[poles]\nleft_fist = [8.0, 12.0]\n")
    p2 = apply_overrides(p, load_overrides(good), str(good))
    assert float(p2.mu) == 0.5 and np.allclose(p2.poles["left_fist"], [8, 12])
    np.testing.assert_allclose(p2.kp["com"], [90, 90, 120])
    # Round trip through TOML.
    back = tmp_path / "all.toml"
    back.write_text(to_toml(p2))
    p3 = apply_overrides(p, load_overrides(back), str(back))
    for a, b in zip(jax.tree_util.tree_leaves(p2), jax.tree_util.tree_leaves(p3)):
        np.testing.assert_allclose(a, b)
    bad = {"nope = 1\n": "unknown key 'nope'",
           "[kp]\nfoot = 3\n": "no output 'foot'",
           "[poles]\nleft_fist = [-1.0, 3.0]\n": "poles must be > 0",
           "[poles]\nleft_fist = [1.0, 2.0, 3.0]\n": "expected a number or a list of 2",
           "mu = 'high'\n": "expected a finite number",
           "[kd]\ntorso = [1, 2]\n": "list of 3",
           # strings and nested tables in the gain and barrier tables name table and key
           "[kp]\ncom = \"stiff\"\n": "[kp] com = 'stiff': expected a number or a list of 3",
           "[threshold]\nleft_fist = \"low\"\n": "[threshold] left_fist = 'low': expected a number",
           "[weight]\ncom = [1, \"a\", 2]\n": "[weight] com = [1, 'a', 2]: expected",
           "[kd]\ncom = true\n": "[kd] com = True: expected a number",
           "[kp.com]\nx = 1\n": "[kp] com = {'x': 1}: expected a number",
           "[weight]\ncom = -1\n": "[weight] com = -1: must be non-negative",
           "[poles]\nleft_fist = [\"8\", 12]\n": "[poles] left_fist = ['8', 12]: expected"}
    for text, msg in bad.items():
        f = tmp_path / "bad.toml"
        f.write_text(text)
        with pytest.raises(ParamsError, match=msg.replace("[", r"\[").replace("(", r"\(")) as e:
            apply_overrides(p, load_overrides(f), str(f))
        assert str(f) in str(e.value)


@pytest.mark.slow
def test_bad_start_for_barrier_rejected_before_compile(tmp_path):
    """A threshold that puts the start outside the safe set (Theorem 1 inapplicable) is a
    clear error from the CLI, before any controller compiles."""
    import subprocess
    import sys
    import time

    f = tmp_path / "bad.toml"
    f.write_text("[threshold]\nleft_fist = 0.195\n")  # the paper's value: unsafe start here
    t0 = time.time()
    out = subprocess.run([sys.executable, "-m", "safewbc_jax.app.cli", "run", "arms", "--params",
                          str(f), "--out", str(tmp_path / "o"), "--cpu", "-1"],
                         capture_output=True, text=True)
    assert out.returncode == 2
    assert "left_fist" in out.stderr and "h(x0)" in out.stderr, out.stderr
    assert time.time() - t0 < 60
    assert not (tmp_path / "o" / "metrics.json").exists()
