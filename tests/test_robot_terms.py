"""Robot terms of the controller model against MuJoCo's C functions and finite differences."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import ad_reference
from conftest import mj_integrate, random_state, trajectory_point

from safewbc_jax.model import chains, robot, spatial

N_STATES = 20
FRAMES = ("left-sole", "right-sole", "left-fist", "right-fist", "torso")


@pytest.fixture(scope="module")
def states(ctrl_mj):
    rng = np.random.default_rng(1234)
    return [random_state(ctrl_mj, rng) for _ in range(N_STATES)]


@pytest.fixture(scope="module")
def jitted():
    return {
        "M": jax.jit(robot.mass_matrix),
        "h": jax.jit(robot.bias_forces),
        "fj": jax.jit(robot.frame_jacobian, static_argnums=2),
        "fd": jax.jit(robot.frame_drift, static_argnums=3),
        "fp": jax.jit(robot.frame_pose, static_argnums=2),
        "cj": jax.jit(robot.com_jacobian),
        "cp": jax.jit(robot.com_position),
        "cd": jax.jit(robot.com_drift),
        "ej": jax.jit(robot.torso_euler_jacobian),
        "ed": jax.jit(robot.torso_euler_drift),
        "e": jax.jit(robot.torso_euler),
        "nj": jax.jit(chains.chain_jacobian),
        "nd": jax.jit(ad_reference.chain_drift),
        "n": jax.jit(chains.n_kc),
    }


def _mj_forward(m, q, v):
    d = mujoco.MjData(m)
    d.qpos[:] = q
    d.qvel[:] = v
    mujoco.mj_forward(m, d)
    return d


def test_mass_matrix_and_bias_match_mujoco(ctrl_mj, rm, states, jitted):
    worst_m = worst_h = 0.0
    for q, v in states:
        d = _mj_forward(ctrl_mj, q, v)
        m_ref = np.zeros((ctrl_mj.nv, ctrl_mj.nv))
        mujoco.mj_fullM(ctrl_mj, d, m_ref)
        m_jax = np.asarray(jitted["M"](rm, jnp.asarray(q)))
        h_jax = np.asarray(jitted["h"](rm, jnp.asarray(q), jnp.asarray(v)))
        worst_m = max(worst_m, np.abs(m_jax - m_ref).max() / np.abs(m_ref).max())
        worst_h = max(worst_h, np.abs(h_jax - d.qfrc_bias).max() / np.abs(d.qfrc_bias).max())
        assert np.allclose(m_jax, m_jax.T, atol=1e-12)
    assert worst_m <= 1e-9, worst_m
    assert worst_h <= 1e-9, worst_h


def test_gravity_vector_is_weight(ctrl_mj, rm):
    """At rest h = G: its vertical base force is the total weight m g."""
    q = jnp.asarray(ctrl_mj.key_qpos[0])
    h = robot.bias_forces(rm, q, jnp.zeros(rm.nv))
    assert float(h[2]) == pytest.approx(ctrl_mj.body_mass.sum() * 9.81, rel=1e-12)


def test_frame_and_com_jacobians_match_mujoco(ctrl_mj, rm, states, jitted):
    for q, v in states[:8]:
        d = _mj_forward(ctrl_mj, q, v)
        for f in FRAMES:
            s = ctrl_mj.site(f).id
            jp, jr = np.zeros((3, ctrl_mj.nv)), np.zeros((3, ctrl_mj.nv))
            mujoco.mj_jacSite(ctrl_mj, d, jp, jr, s)
            j = np.asarray(jitted["fj"](rm, jnp.asarray(q), f))
            np.testing.assert_allclose(j[:3], jp, atol=1e-12)
            np.testing.assert_allclose(j[3:], jr, atol=1e-12)
            p, r = jitted["fp"](rm, jnp.asarray(q), f)
            np.testing.assert_allclose(p, d.site_xpos[s], atol=1e-12)
            np.testing.assert_allclose(r, d.site_xmat[s].reshape(3, 3), atol=1e-12)
        jc = np.zeros((3, ctrl_mj.nv))
        mujoco.mj_jacSubtreeCom(ctrl_mj, d, jc, ctrl_mj.body("base").id)
        np.testing.assert_allclose(jitted["cj"](rm, jnp.asarray(q)), jc, atol=1e-12)
        np.testing.assert_allclose(jitted["cp"](rm, jnp.asarray(q)), d.subtree_com[1], atol=1e-12)


def _fd_jacobian(f, q, nv, eps=1e-6):
    """Central differences of f along each tangent direction (MuJoCo's integrator)."""
    cols = []
    for k in range(nv):
        e = np.zeros(nv)
        e[k] = eps
        cols.append((f(_integrate(q, e)) - f(_integrate(q, -e))) / (2 * eps))
    return np.stack(cols, axis=-1)


def _integrate(q, v, dt=1.0):
    return mj_integrate(_integrate.model, q, v, dt)


@pytest.fixture(autouse=True, scope="module")
def _set_integrate_model(ctrl_mj):
    _integrate.model = ctrl_mj


def test_position_jacobians_against_finite_differences(rm, states, jitted):
    q, _ = states[0]
    qj = jnp.asarray(q)
    for f in ("left-sole", "right-fist"):
        fd = _fd_jacobian(lambda x: np.asarray(jitted["fp"](rm, jnp.asarray(x), f)[0]), q, rm.nv)
        np.testing.assert_allclose(jitted["fj"](rm, qj, f)[:3], fd, atol=1e-7)
    fd = _fd_jacobian(lambda x: np.asarray(jitted["cp"](rm, jnp.asarray(x))), q, rm.nv)
    np.testing.assert_allclose(jitted["cj"](rm, qj), fd, atol=1e-7)
    fd = _fd_jacobian(lambda x: np.asarray(jitted["e"](rm, jnp.asarray(x))), q, rm.nv)
    np.testing.assert_allclose(jitted["ej"](rm, qj), fd, atol=1e-7)
    fd = _fd_jacobian(lambda x: np.asarray(jitted["n"](rm, jnp.asarray(x))), q, rm.nv)
    np.testing.assert_allclose(jitted["nj"](rm, qj), fd, atol=1e-7)


def _trajectory_point(q0, v0, a, t):
    return trajectory_point(_integrate.model, q0, v0, a, t)


@pytest.mark.parametrize("which", ["frames", "com_torso_chains"])
def test_drift_terms_against_finite_differences_along_a_trajectory(rm, states, jitted, which):
    """J_dot v = d/dt (J(q(t)) v(t)) - J a on a trajectory with q_ddot = a != 0: the
    frames' drifts, and the CoM's, the torso angles' and the closed chains' (two tests, so
    that each compiles half of the drifts)."""
    rng = np.random.default_rng(7)
    eps = 1e-4
    for q0, v0 in states[:4]:
        a = rng.normal(0, 2.0, rm.nv)
        qp, vp = _trajectory_point(q0, v0, a, eps)
        qm, vm = _trajectory_point(q0, v0, a, -eps)
        terms = {f"frame:{f}": (lambda x, f=f: jitted["fj"](rm, x, f),
                                lambda x, v, f=f: jitted["fd"](rm, x, v, f)) for f in FRAMES}
        terms["com"] = (lambda x: jitted["cj"](rm, x), lambda x, v: jitted["cd"](rm, x, v))
        terms["torso_euler"] = (lambda x: jitted["ej"](rm, x), lambda x, v: jitted["ed"](rm, x, v))
        terms["chains"] = (lambda x: jitted["nj"](rm, x), lambda x, v: jitted["nd"](rm, x, v))
        terms = {k: t for k, t in terms.items() if k.startswith("frame:") == (which == "frames")}
        assert len(terms) == (len(FRAMES) if which == "frames" else 3)
        for name, (jac, drift) in terms.items():
            j0 = np.asarray(jac(jnp.asarray(q0)))
            fd = (np.asarray(jac(jnp.asarray(qp))) @ vp
                  - np.asarray(jac(jnp.asarray(qm))) @ vm) / (2 * eps) - j0 @ a
            ad = np.asarray(drift(jnp.asarray(q0), jnp.asarray(v0)))
            scale = max(1.0, np.abs(fd).max())
            assert np.abs(ad - fd).max() <= 1e-5 * scale, (name, np.abs(ad - fd).max())


def test_integrate_matches_mujoco(ctrl_mj, states):
    for q, v in states[:5]:
        ref = _integrate(q, v, 0.37)
        out = np.asarray(jax.jit(spatial.integrate)(jnp.asarray(q), jnp.asarray(v), 0.37))
        np.testing.assert_allclose(out, ref, atol=1e-12)


@pytest.mark.slow
def test_vmap_over_states(rm, states, jitted):
    qs = jnp.stack([jnp.asarray(q) for q, _ in states[:4]])
    batched = jax.vmap(robot.mass_matrix, in_axes=(None, 0))(rm, qs)
    for i in range(4):
        np.testing.assert_allclose(batched[i], jitted["M"](rm, qs[i]), atol=1e-12)


@pytest.mark.parametrize("kind", ["points", "relative", "orientations"])
def test_closed_form_frame_terms_equal_forward_mode_ad(rm, states, kind):
    """``robot.site_point_terms`` (points), ``position_in_terms`` (relative), and
    ``frame_orientation_terms`` (orientations): what the frame outputs and the fist and
    swing-foot barriers use in the control step, against forward-mode AD of the same values
    along the configuration manifold (``spatial.tangent_jacobian``,
    ``second_derivative_along``), whose Jacobians and drifts are held to MuJoCo above.
    1e-9 relative: float64 evaluations of the same derivatives, in a different order; an
    orientation at |cos pitch| < 0.05 (random base orientations reach it), where Euler
    rates are singular, is left out, and most are kept. Three tests, so that each compiles
    a part of the terms (the points together took 18-25 s on a 2-core CPU, near the fast
    tier's 20 s guard)."""
    frames = ("left-sole", "right-sole", "left-fist")
    points = kind != "orientations"

    def pose_terms(q, v):
        kin = robot.forward_kinematics(rm, q)
        motion = robot.body_motion(rm, kin, v)
        if kind == "orientations":
            return {f"r:{f}": robot.frame_orientation_terms(rm, kin, motion, f) for f in frames}
        if kind == "points":
            return {f"p:{f}": robot.site_point_terms(rm, kin, motion, f) for f in frames}
        return {"in:left-fist": robot.position_in_terms(rm, kin, motion, "left-fist", "torso"),
                "in:right-sole": robot.position_in_terms(rm, kin, motion, "right-sole",
                                                         "left-fist")}

    def values(q):
        if kind == "orientations":
            return {f"r:{f}": spatial.euler_zyx(robot.frame_pose(rm, q, f)[1]) for f in frames}
        if kind == "points":
            return {f"p:{f}": robot.frame_pose(rm, q, f)[0] for f in frames}
        return {"in:left-fist": robot.frame_position_in(rm, q, "left-fist", "torso"),
                "in:right-sole": robot.frame_position_in(rm, q, "right-sole", "left-fist")}

    def ad_terms(q, v):
        y = values(q)
        jac = jax.jacfwd(lambda t: values(spatial.integrate(q, t)))(jnp.zeros(rm.nv))
        drift = spatial.second_derivative_along(values, q, v)
        return {k: (y[k], jac[k], drift[k]) for k in y}

    closed_fn, ad_fn = jax.jit(pose_terms), jax.jit(ad_terms)
    kept = left_out = 0
    for q, v in states[:8]:
        closed, ad = closed_fn(jnp.asarray(q), jnp.asarray(v)), ad_fn(jnp.asarray(q), jnp.asarray(v))
        for k in ad:
            if k.startswith("r:") and abs(np.cos(float(ad[k][0][1]))) < 0.05:
                left_out += 1
                continue
            kept += 1
            for part, a, b in zip(("value", "J", "J_dot v"), closed[k], ad[k]):
                a, b = np.asarray(a), np.asarray(b)
                scale = max(1.0, float(np.abs(b).max()))
                assert np.abs(a - b).max() <= 1e-9 * scale, (k, part, np.abs(a - b).max())
    # 8 states: three points or two relative positions each (none left out), three
    # orientations each (at most 8 left out)
    n_points = {"points": 3, "relative": 2}.get(kind)
    assert (kept == 8 * n_points and left_out == 0) if points else (kept >= 16 and left_out <= 8), \
        (kept, left_out)
