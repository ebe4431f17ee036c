"""ALIP model, foot-placement planner and swing reference (safewbc_jax.control.alip)."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import scipy.linalg
from conftest import random_state

from safewbc_jax.control import alip

H, M, G, T = 0.9, 47.228138, 9.81, 0.35
LAM = np.sqrt(G / H)


# --------------------------------------------------------------------------------------
# Dynamics
# --------------------------------------------------------------------------------------

def _rk4(f, x, t, n):
    h = t / n
    for _ in range(n):
        k1 = f(x)
        k2 = f(x + 0.5 * h * k1)
        k3 = f(x + 0.5 * h * k2)
        k4 = f(x + h * k3)
        x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


@pytest.mark.parametrize("h,m,t", [(0.9, 47.2, 0.35), (1.1, 30.0, 0.2), (0.6, 80.0, 0.7)])
def test_propagate_matches_rk4_and_expm(h, m, t):
    a = np.asarray(alip.alip_system_matrix(h, m, G))
    assert np.allclose(a, [[0, 1 / (m * h)], [m * G, 0]])
    x0 = np.array([0.07, -0.3 * m * h])
    x_cf = np.asarray(alip.alip_propagate(x0, t, h, m, G))
    x_rk = _rk4(lambda x: a @ x, x0, t, 2000)
    scale = np.abs(x_cf)
    assert np.all(np.abs(x_cf - x_rk) <= 1e-10 * np.maximum(scale, 1.0))
    phi = np.asarray(alip.alip_matrix(h, G, m, t))
    assert np.allclose(phi, scipy.linalg.expm(a * t), rtol=1e-12, atol=0)
    # both axes at once, batched times
    both = np.stack([x0, 2 * x0])
    out = np.asarray(alip.alip_propagate(both, t, h, m, G))
    assert np.allclose(out, np.stack([x_cf, 2 * x_cf]), rtol=1e-13)
    ts = np.linspace(0, t, 5)
    out_t = np.asarray(alip.alip_propagate(np.broadcast_to(x0, (5, 2)), ts, h, m, G))
    assert np.allclose(out_t[-1], x_cf, rtol=1e-13)
    assert np.allclose(out_t[0], x0, rtol=1e-15)


def test_periodic_orbit_momenta():
    """The lateral desired momenta generate the symmetric period-two orbit of width w."""
    w = 0.3
    for side in (alip.LEFT, alip.RIGHT):
        ldes = np.asarray(alip.desired_end_momentum(0.0, w, side, T, H, M, G))
        # the next step (stance -side) starts at p = side w / 2 (right stance: CoM left of
        # the foot) with L = -ldes and ends at the same p with L = ldes
        p0 = side * w / 2
        pT, LT = np.asarray(alip.alip_propagate([p0, -ldes[1]], T, H, M, G))
        assert np.isclose(LT, ldes[1], rtol=1e-12)
        assert np.isclose(pT, p0, rtol=1e-12)  # symmetric: the CoM returns to the same offset
        assert np.sign(ldes[1]) == side


# --------------------------------------------------------------------------------------
# Hybrid ALIP simulation of the planner
# --------------------------------------------------------------------------------------

_plan = jax.jit(alip.plan_foot_placement, static_argnames="average_velocity")


def simulate(p0, L0, v_des, w, n_steps=20, side=alip.LEFT, ticks=10, push=None,
             h_true=H, average_velocity=False):
    """Replan at every control tick of every step, propagate the true ALIP (height
    ``h_true``), switch stance to the last plan at tau = T. ``push = (step, dL [2])`` adds
    dL to the momenta at mid-step. Returns per-step records."""
    p, L = np.array(p0, float), np.array(L0, float)
    dt = T / ticks
    rec = {k: [] for k in ("u", "L_end", "v_avg", "side", "p0", "L0")}
    for k in range(n_steps):
        rec["p0"].append(p.copy()), rec["L0"].append(L.copy()), rec["side"].append(side)
        p_start = p.copy()
        for i in range(ticks):
            if push is not None and push[0] == k and i == ticks // 2:
                L = L + np.asarray(push[1])
            plan = _plan(p, L, i * dt, T, H, M, G, v_des, w, side,
                         average_velocity=average_velocity)
            p, L = (np.asarray(a) for a in alip._propagate_pl(p, L, dt, h_true, M, G))
        u = np.asarray(plan.u)
        rec["u"].append(u), rec["L_end"].append(L.copy())
        rec["v_avg"].append((p - p_start) / T)
        p, L = p - u, L
        side = -side
    return {k: np.asarray(v) for k, v in rec.items()}


START = ([0.06, -0.12], [-0.2 * M * H, 0.25 * M * H])


@pytest.mark.parametrize("v_des", [0.0, 0.2, 0.5])
def test_planner_converges_sagittal_and_lateral(v_des):
    w = 0.25
    r = simulate(*START, v_des, w)
    last = slice(-10, None)
    v_end = r["L_end"][last, 0] / (M * H)
    assert np.all(np.abs(v_end - v_des) <= 0.01 * max(v_des, 0.1)), v_end
    # lateral: alternating steps of width w, -w from a left stance foot
    assert np.allclose(np.abs(r["u"][last, 1]), w, rtol=0.01)
    assert np.allclose(r["u"][last, 1], -r["side"][last] * w, rtol=0.01)
    # periodic with period two, zero mean lateral velocity
    assert np.allclose(r["p0"][-1], r["p0"][-3], atol=1e-9)
    assert np.allclose(r["L0"][-1], r["L0"][-3], atol=1e-8)
    assert abs(r["v_avg"][-2:, 1].mean()) < 1e-3
    # steady step length = mean velocity * T
    assert np.allclose(r["u"][last, 0], r["v_avg"][last, 0] * T, atol=1e-9)


@pytest.mark.parametrize("v_des", [0.0, 0.2, 0.5])
def test_planner_average_velocity_mode(v_des):
    r = simulate(*START, v_des, 0.3, average_velocity=True)
    v = r["v_avg"][-10:, 0]
    assert np.all(np.abs(v - v_des) <= 0.01 * max(v_des, 0.1)), v
    # the default mode makes L_end/(mH) = v_des, so its mean velocity is lower by
    # 2 tanh(lT/2)/(lT)
    r0 = simulate(*START, v_des, 0.3)
    ratio = 2 * np.tanh(LAM * T / 2) / (LAM * T)
    assert np.allclose(r0["v_avg"][-4:, 0], ratio * v_des, atol=1e-9)


def test_plan_is_invariant_along_an_undisturbed_step():
    p, L = np.array(START[0]), np.array(START[1])
    us = []
    for tau in np.linspace(0, T, 8):
        pt, Lt = alip._propagate_pl(p, L, tau, H, M, G)
        us.append(np.asarray(_plan(pt, Lt, tau, T, H, M, G, 0.3, 0.25, alip.RIGHT).u))
    assert np.allclose(us, us[0], atol=1e-12)


@pytest.mark.parametrize("side", [alip.LEFT, alip.RIGHT])
def test_planner_recovers_from_lateral_push(side):
    w, v_des = 0.25, 0.2
    dl = np.array([0.0, -0.4 * M * H])  # 0.4 m/s to the right at mid-step
    r = simulate(*START, v_des, w, n_steps=20, side=side, push=(8, dl))
    assert np.all(np.abs(r["p0"]) < 0.6)
    after = slice(11, None)
    assert np.allclose(np.abs(r["u"][after, 1]), w, rtol=0.01)
    assert np.allclose(r["L_end"][after, 0] / (M * H), v_des, rtol=0.01)
    # the step taken right after the push is displaced towards the push
    assert r["u"][8, 1] < r["u"][6, 1]
    if side == alip.RIGHT:
        # pushed towards the stance foot's side: the planned left foot lands next to the
        # right one, inside the paper's 0.07 m collision margin (the A-ECBF's job)
        assert r["u"][8, 1] < 0.07


def test_planner_stable_with_height_mismatch():
    """True CoM height 5 % off the planner's: still a period-two gait near the command."""
    r = simulate(*START, 0.3, 0.25, n_steps=40, h_true=0.95)
    assert np.allclose(r["p0"][-1], r["p0"][-3], atol=1e-6)
    assert np.allclose(r["L_end"][-6:, 0] / (M * H), 0.3, rtol=0.1)
    assert np.allclose(np.abs(r["u"][-6:, 1]), 0.25, rtol=0.1)


def test_planner_jit_vmap():
    rng = np.random.default_rng(0)
    n = 64
    p = rng.normal(0, 0.1, (n, 2))
    L = rng.normal(0, 10.0, (n, 2))
    tau = rng.uniform(0, T, n)
    side = np.where(rng.uniform(size=n) < 0.5, alip.LEFT, alip.RIGHT)
    vdes = rng.uniform(0, 0.5, n)
    f = jax.jit(jax.vmap(alip.plan_foot_placement,
                         in_axes=(0, 0, 0, None, None, None, None, 0, None, 0)))
    out = f(p, L, tau, T, H, M, G, vdes, 0.25, side)
    assert out.u.shape == (n, 2) and out.u.dtype == jnp.float64
    for i in (0, 17, 63):
        one = alip.plan_foot_placement(p[i], L[i], tau[i], T, H, M, G, vdes[i], 0.25, side[i])
        for a, b in zip(out, one):
            assert np.allclose(a[i], b, rtol=1e-13, atol=1e-15)
    # broadcasting without vmap gives the same
    direct = jax.jit(alip.plan_foot_placement)(p, L, tau, T, H, M, G, vdes, 0.25, side)
    assert np.allclose(direct.u, out.u, rtol=1e-13, atol=1e-15)
    # one-step-ahead: the next step ends exactly at L_des
    p_plus, L_plus = alip.impact_map(out.p_end, out.L_end, out.u)
    _, L_next = alip._propagate_pl(p_plus, L_plus, T, H, M, G)
    assert np.allclose(L_next, out.L_des, rtol=1e-11, atol=1e-9)


# --------------------------------------------------------------------------------------
# Angular momentum of the robot against MuJoCo
# --------------------------------------------------------------------------------------

def test_robot_momentum_matches_mujoco(ctrl_mj, rm):
    rng = np.random.default_rng(7)
    f = jax.jit(alip.robot_momentum)
    fs = jax.jit(alip.alip_state_from_robot)
    for _ in range(10):
        q, v = random_state(ctrl_mj, rng)
        point = rng.normal(0, 0.5, 3)
        d = mujoco.MjData(ctrl_mj)
        d.qpos[:], d.qvel[:] = q, v
        mujoco.mj_forward(ctrl_mj, d)
        mujoco.mj_subtreeVel(ctrl_mj, d)
        mass = ctrl_mj.body_subtreemass[1]
        com, vcom, lcom = d.subtree_com[1], d.subtree_linvel[1], d.subtree_angmom[1]
        lpt = lcom + mass * np.cross(com - point, vcom)
        mom = f(rm, jnp.asarray(q), jnp.asarray(v), jnp.asarray(point))

        def rel(a, b):
            return np.linalg.norm(np.asarray(a) - b) / np.linalg.norm(b)

        assert np.isclose(float(mom.mass), mass, rtol=1e-12)
        assert rel(mom.com, com) < 1e-12
        assert rel(mom.com_vel, vcom) < 1e-9
        assert rel(mom.L_com, lcom) < 1e-9
        assert rel(mom.L_point, lpt) < 1e-9
        # ALIP state in a yawed heading frame
        yaw = rng.uniform(-np.pi, np.pi)
        st = fs(rm, jnp.asarray(q), jnp.asarray(v), jnp.asarray(point), yaw)
        c, s = np.cos(yaw), np.sin(yaw)
        rt = np.array([[c, s], [-s, c]])  # world -> heading
        assert np.allclose(st.p, rt @ (com - point)[:2], rtol=1e-12, atol=1e-12)
        assert np.allclose(st.L, rt @ np.array([lpt[1], -lpt[0]]), rtol=1e-9, atol=1e-9)
        assert np.isclose(st.z, com[2] - point[2], rtol=1e-12)


def test_alip_momentum_is_mH_velocity_for_a_point_mass():
    """L^alip = m H p_dot for a point mass at height H moving horizontally."""
    v = np.array([0.3, -0.2, 0.0])
    pc = np.array([0.1, 0.05, H])
    L = alip.angular_momentum_about_point(np.zeros(3), M, pc, v, np.zeros(3))
    st = alip.alip_state(pc, L, np.zeros(3))
    assert np.allclose(st.L, M * H * v[:2], rtol=1e-14)


# --------------------------------------------------------------------------------------
# Swing-foot reference
# --------------------------------------------------------------------------------------

def test_swing_reference_profile_and_derivatives():
    p0, u = np.array([-0.2, -0.25]), np.array([0.15, -0.27])
    ref = jax.jit(alip.swing_foot_reference, static_argnames="exact_landing")
    r0 = ref(0.0, T, p0, u)
    assert np.allclose(r0.pos, [p0[0], p0[1], 0.0], atol=1e-15)  # s(0) = 0, z(0) = 0
    assert abs(float(ref(T, T, p0, u).pos[2])) < 1e-15
    assert np.isclose(float(ref(T / 2, T, p0, u).pos[2]), 0.08, rtol=1e-14)
    taus = np.linspace(0, T, 201)
    zs = np.asarray(jax.vmap(lambda t: ref(t, T, p0, u).pos)(taus))[:, 2]
    assert zs.min() >= -1e-15 and np.isclose(zs.max(), 0.08, rtol=1e-12)
    # landing: paper's s reaches 1 - e^-5; exact_landing reaches u
    assert np.allclose(ref(T, T, p0, u).pos[:2], p0 + (1 - np.exp(-5)) * (u - p0), rtol=1e-14)
    assert np.allclose(ref(T, T, p0, u, exact_landing=True).pos[:2], u, rtol=1e-14)
    # after touchdown the foot stays on the ground
    late = ref(1.2 * T, T, p0, u)
    assert float(late.pos[2]) == 0.0 and float(late.vel[2]) == 0.0
    # derivatives against central finite differences and forward-mode AD
    h = 1e-6
    for exact in (False, True):
        for tau in (0.01, 0.1, 0.175, 0.3, 0.34):
            r = ref(tau, T, p0, u, exact_landing=exact)
            rp, rm_ = ref(tau + h, T, p0, u, exact_landing=exact), ref(tau - h, T, p0, u,
                                                                       exact_landing=exact)
            assert np.allclose(r.vel, (rp.pos - rm_.pos) / (2 * h), rtol=1e-6, atol=1e-8)
            assert np.allclose(r.acc, (rp.vel - rm_.vel) / (2 * h), rtol=1e-6, atol=1e-6)
            _, dpos = jax.jvp(lambda t: alip.swing_foot_reference(t, T, p0, u,
                                                                  exact_landing=exact).pos,
                              (jnp.float64(tau),), (jnp.float64(1.0),))
            assert np.allclose(dpos, r.vel, rtol=1e-12, atol=1e-14)


def test_swing_reference_walking_profiles():
    """The minimum-jerk horizontal blend and the soft-landing vertical profile used by the
    walking domain: boundary values, the landing and the descent after T, and the
    derivatives against central differences."""
    p0, u = np.array([-0.2, -0.25]), np.array([0.15, -0.27])
    kw = dict(horizontal="minjerk", vertical="land")
    ref = jax.jit(lambda t: alip.swing_foot_reference(t, T, p0, u, **kw))
    r0 = ref(0.0)
    assert np.allclose(r0.pos, [p0[0], p0[1], 0.0], atol=1e-15)
    assert np.allclose(r0.vel, 0.0, atol=1e-15)            # no lift-off jump
    rT = ref(T)
    assert np.allclose(rT.pos[:2], u, rtol=1e-14)           # lands on u at T
    assert np.allclose(rT.vel[:2], 0.0, atol=1e-14)
    assert abs(float(rT.pos[2])) < 1e-15
    assert np.isclose(float(rT.vel[2]), -alip.LAND_SPEED, rtol=1e-12)  # soft landing
    zs = np.asarray(jax.vmap(lambda t: ref(t).pos)(np.linspace(0, T, 401)))[:, 2]
    # apex: at least the height, at most height + max of d s^2 (1 - s) = 4 d / 27
    assert zs.min() >= -1e-15 and 0.08 <= zs.max() <= 0.08 + 4 * alip.LAND_SPEED * T / 27
    # after T: keeps descending at the landing speed, stops LAND_DEPTH below the floor
    late = ref(T + 0.05)
    assert np.isclose(float(late.pos[2]), -alip.LAND_SPEED * 0.05, rtol=1e-12)
    assert np.isclose(float(late.vel[2]), -alip.LAND_SPEED, rtol=1e-12)
    rest = ref(T + 10 * alip.LAND_DEPTH / alip.LAND_SPEED)
    assert np.isclose(float(rest.pos[2]), -alip.LAND_DEPTH) and float(rest.vel[2]) == 0.0
    assert np.allclose(rest.pos[:2], u, rtol=1e-14)
    h = 1e-6
    for tau in (0.01, 0.1, 0.175, 0.3, 0.34, T + 0.05):
        r, rp, rm_ = ref(tau), ref(tau + h), ref(tau - h)
        assert np.allclose(r.vel, (rp.pos - rm_.pos) / (2 * h), rtol=1e-6, atol=1e-8)
        assert np.allclose(r.acc, (rp.vel - rm_.vel) / (2 * h), rtol=1e-6, atol=1e-6)
    # the paper's exponential starts the foot at (rate / T) |u - p0|; minjerk at rest
    paper = alip.swing_foot_reference(0.0, T, p0, u)
    assert np.allclose(paper.vel[:2], alip.SWING_RATE / T * (u - p0), rtol=1e-14)
    with pytest.raises(ValueError):
        alip.swing_foot_reference(0.1, T, p0, u, horizontal="cubic")


def test_reachable_speeds_are_the_step_clip_over_T():
    """walking.reachable_speeds (what ``safewbc run walk --speed`` accepts) against the
    planner itself: on its periodic orbit at the limit speeds the step is exactly the
    clip bound STEP_X, and 5 % beyond a limit it would need a step the clip cuts off."""
    from safewbc_jax.control import walking

    lo, hi = walking.reachable_speeds(T)
    assert (lo, hi) == pytest.approx((walking.STEP_X[0] / T, walking.STEP_X[1] / T))
    for v, bound in ((hi, walking.STEP_X[1]), (lo, walking.STEP_X[0])):
        r = simulate(*START, v, 0.22, n_steps=40, average_velocity=True)
        assert r["u"][-1, 0] == pytest.approx(bound, abs=1e-6)
        r = simulate(*START, 1.05 * v, 0.22, n_steps=40, average_velocity=True)
        assert abs(r["u"][-1, 0]) > abs(bound) * 1.04
