"""A-ECBFs: pole placement, Theorem 1, the closed-loop guarantee on a double integrator, and
the rows built by AD on Digit against MuJoCo and finite differences."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import scipy.linalg
from conftest import random_state, mj_integrate, trajectory_point

from safewbc_jax.control import barriers as bf
from safewbc_jax import scenarios
from safewbc_jax.control import step as control_step
from safewbc_jax.control.safesets import SafeSet, SafeSetError

THRESHOLD = 0.195


def _row_from_terms(h, j_h, j_h_dot_v, v, k_alpha):
    """The relative-degree-2 A-ECBF row (eq. 28) of h(q) from its kinematic terms:
    eta = [h, J_h v], L_F^2 h = J_h_dot v, L_G L_F h = J_h."""
    eta = jnp.stack([jnp.asarray(h), jnp.asarray(j_h) @ v])
    return bf.aecbf_inequality(eta, j_h_dot_v, j_h, k_alpha)


def _k_ref(poles):
    """K_alpha = [k_0, ..., k_{r-1}] from numpy's polynomial with roots -poles."""
    return np.poly(-np.asarray(poles, float))[::-1][:-1]


# --------------------------------------------------------------------------------------
# Pole placement and Theorem 1 algebra
# --------------------------------------------------------------------------------------

@pytest.mark.parametrize("poles", [[3.0], [2.0, 5.0], [1.5, 1.5], [1.0, 2.0, 4.0]])
def test_k_alpha_places_the_closed_loop_roots(poles):
    k = np.asarray(bf.k_alpha_from_poles(jnp.asarray(poles)))
    np.testing.assert_allclose(k, _k_ref(poles), rtol=1e-14)
    a = np.asarray(bf.closed_loop_matrix(k))
    f, g, _ = (np.asarray(x) for x in bf.integrator_chain(len(poles)))
    np.testing.assert_allclose(a, f - g @ k[None], atol=0)
    eig = np.sort_complex(np.linalg.eigvals(a))
    want = np.sort_complex(-np.asarray(poles, complex))
    # a double root is only determined to ~sqrt(eps) by an eigen-solver
    tol = 1e-6 if len(set(poles)) < len(poles) else 1e-10
    np.testing.assert_allclose(eig, want, atol=tol)


def test_k_alpha_batched_matches_single():
    poles = jnp.array([[1.0, 2.0], [3.0, 7.0], [0.5, 0.5]])
    batched = bf.k_alpha_from_poles(poles)
    mapped = jax.vmap(bf.k_alpha_from_poles)(poles)
    for i in range(3):
        np.testing.assert_allclose(batched[i], _k_ref(poles[i]), rtol=1e-14)
    np.testing.assert_allclose(mapped, batched, rtol=0, atol=0)


def test_b_functions_are_the_nested_operators():
    """B_i = (d/dt + p_i) B_{i-1} applied to a known signal h(t), by AD in t, against
    b_functions / b_function_rates from eta = [h, h', h'']; and B_r = h''' + K_alpha eta."""
    poles = jnp.array([0.7, 2.0, 3.5])

    def h(t):
        return jnp.exp(-0.3 * t) * jnp.cos(2.0 * t) + 0.5 * t ** 2

    def nested(i):
        f = h
        for k in range(i):
            f = (lambda g, p: (lambda t: jax.grad(g)(t) + p * g(t)))(f, poles[k])
        return f

    t0 = 0.4
    d = [h]
    for _ in range(3):
        d.append(jax.grad(d[-1]))
    eta = jnp.array([d[0](t0), d[1](t0), d[2](t0)])
    h3 = d[3](t0)
    bs = bf.b_functions(eta, poles)
    rates = bf.b_function_rates(eta, poles, h3)
    for i in range(3):
        assert float(bs[i]) == pytest.approx(float(nested(i)(t0)), rel=1e-13, abs=1e-13)
        assert float(rates[i]) == pytest.approx(float(jax.grad(nested(i))(t0)), rel=1e-12,
                                                abs=1e-12)
    b3 = float(nested(3)(t0))
    k = bf.k_alpha_from_poles(poles)
    assert b3 == pytest.approx(float(h3 + k @ eta), rel=1e-12)
    # without h''' the last rate is undefined
    assert np.isnan(float(bf.b_function_rates(eta, poles)[2]))


def test_admissible_bounds_algebra():
    eta0 = jnp.array([0.2, -1.0])
    # p_1 >= -h_dot / h = 5; p_2 only needs > 0 (its bound would need h'')
    np.testing.assert_allclose(bf.admissible_pole_bounds(eta0, jnp.array([6.0, 1.0])),
                               [5.0, 0.0], rtol=1e-15)
    # with h''(x0) given, the literal bound -B_1_dot / B_1 of the theorem, depending on p_1
    h2 = 3.0
    for p1 in (6.0, 9.0):
        b1 = -1.0 + p1 * 0.2
        b1dot = h2 + p1 * -1.0
        got = bf.admissible_pole_bounds(eta0, jnp.array([p1, 1.0]), h_r0=h2)
        assert float(got[1]) == pytest.approx(max(0.0, -b1dot / b1), rel=1e-14)
    # moving away from the boundary: no restriction
    np.testing.assert_allclose(bf.admissible_pole_bounds(jnp.array([0.2, 1.0]),
                                                         jnp.array([1.0, 1.0])), [0.0, 0.0])
    # outside the safe set: nothing is admissible
    assert np.all(np.isinf(bf.admissible_pole_bounds(jnp.array([-0.1, 0.0]),
                                                     jnp.array([1.0, 1.0]))))
    # relative degree 3: p_2's bound uses B_1 = h' + p_1 h
    eta3 = np.array([1.0, -0.5, -4.0])
    p = np.array([1.0, 2.0, 3.0])
    b1, b1dot = eta3[1] + p[0] * eta3[0], eta3[2] + p[0] * eta3[1]
    got = np.asarray(bf.admissible_pole_bounds(jnp.asarray(eta3), jnp.asarray(p)))
    # entry i is conditional on the earlier poles: p_2 = 2 < 9 leaves B_2(x0) < 0, so no p_3
    np.testing.assert_allclose(got, [0.5, -b1dot / b1, np.inf], rtol=1e-14)
    got = np.asarray(bf.admissible_pole_bounds(jnp.asarray(eta3), jnp.array([1.0, 9.0, 3.0])))
    np.testing.assert_allclose(got, [0.5, 9.0, 0.0], rtol=1e-14)
    np.testing.assert_allclose(bf.check_poles("x", eta3, [1.0, 9.0, 3.0]), [0.5, 9.0, 0.0])
    with pytest.raises(bf.PoleError, match="p_2"):
        bf.check_poles("x", eta3, p)


# --------------------------------------------------------------------------------------
# Closed loop of a double integrator x_ddot = u: the comparison bound of the ECBF
# --------------------------------------------------------------------------------------

def _simulate(x0, xd0, poles, u_nom_fn, x_min=0.0, t_end=4.0, dt=1e-3, degree=2):
    """RK4 on x_ddot = u(x, x_dot), u the value closest to u_nom meeting the A-ECBF row
    (the 1-D min-norm QP): u = max(u_nom, b) since the row is a u >= b with a = 1 (degree
    2, h = x - x_min) or a = 1 (degree 1, h = x_dot - x_min)."""
    k = bf.k_alpha_from_poles(jnp.asarray(poles))

    def control(s, t):
        x, xd = s
        if degree == 2:
            a, b = _row_from_terms(x - x_min, jnp.ones(1), 0.0, jnp.array([xd]), k)
        else:
            a, b = bf.aecbf_inequality(jnp.array([xd - x_min]), 0.0, jnp.ones(1), k)
        return jnp.maximum(u_nom_fn(x, xd, t), b / a[0]), b / a[0]

    def rhs(s, t):
        return jnp.array([s[1], control(s, t)[0]])

    def step(s, t):
        k1 = rhs(s, t)
        k2 = rhs(s + 0.5 * dt * k1, t + 0.5 * dt)
        k3 = rhs(s + 0.5 * dt * k2, t + 0.5 * dt)
        k4 = rhs(s + dt * k3, t + dt)
        u, b = control(s, t)
        return s + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4), (s, u, b)

    n = int(round(t_end / dt))
    ts = dt * jnp.arange(n + 1)
    s_end, (ss, us, bs) = jax.lax.scan(step, jnp.array([x0, xd0]), ts[:-1])
    ss = jnp.concatenate([ss, s_end[None]])
    return np.asarray(ts), np.asarray(ss), np.asarray(us), np.asarray(bs)


def _bound(eta0, poles, ts):
    return np.asarray(jax.vmap(lambda t: bf.comparison_bound(jnp.asarray(eta0),
                                                             jnp.asarray(poles), t))(ts))


def test_comparison_bound_matches_scipy_expm():
    eta0, poles = np.array([1.0, -0.5]), np.array([2.0, 3.0])
    a = np.array([[0.0, 1.0], -_k_ref(poles)])
    for t in (0.0, 0.3, 1.7):
        want = (scipy.linalg.expm(a * t) @ eta0)[0]
        assert float(bf.comparison_bound(eta0, poles, t)) == pytest.approx(want, rel=1e-12,
                                                                            abs=1e-15)
    # closed form for distinct poles: h = A e^{-2t} + B e^{-3t}, A + B = 1, -2A - 3B = -0.5
    t = 1.3
    assert float(bf.comparison_bound(eta0, poles, t)) == pytest.approx(
        2.5 * np.exp(-2 * t) - 1.5 * np.exp(-3 * t), rel=1e-12)


def test_double_integrator_constraint_always_active_is_tight():
    """u_nom = -50 pushes into x < x_min all the time: the row is active along the whole
    run and h(t) equals the comparison bound C e^{(F - G K) t} eta0 (and stays >= 0)."""
    poles = [2.0, 3.0]
    x0, xd0 = 1.0, -0.5
    bf.check_poles("double-integrator", [x0, xd0], poles)  # p_1 >= 0.5
    ts, ss, us, bs = _simulate(x0, xd0, poles, lambda x, xd, t: -50.0)
    h = ss[:, 0]
    bound = _bound([x0, xd0], poles, ts)
    assert np.all(bs[:] >= -50.0)  # active everywhere: u = b
    np.testing.assert_allclose(us, bs, atol=0)
    assert np.abs(h - bound).max() <= 1e-10
    assert h.min() >= 0.0
    assert h[-1] < 1e-2 * h[0]  # it did approach the boundary


def test_double_integrator_pd_into_unsafe_set_respects_the_bound():
    """A lightly damped PD controller aiming at x = -0.3 (unsafe). The row is inactive at
    first and becomes active; h(t) >= comparison bound >= 0 throughout, while the nominal
    loop alone crosses into x < 0."""
    poles = [2.0, 4.0]
    x0, xd0 = 1.0, 0.8

    def u_nom(x, xd, t):
        return -4.0 * (x + 0.3) - 0.4 * xd

    ts, ss, us, bs = _simulate(x0, xd0, poles, u_nom, t_end=6.0)
    h = ss[:, 0]
    bound = _bound([x0, xd0], poles, ts)
    nominal = np.array([u_nom(x, xd, 0.0) for x, xd in ss[:-1]])
    active = bs > nominal
    assert (~active[:100]).all() and active.any()
    assert np.all(h - bound >= -1e-9), (h - bound).min()
    assert bound.min() >= 0.0 and h.min() >= -1e-12
    assert (h - bound).max() > 1e-2  # the bound is not trivially tight here
    # the unconstrained PD loop (exact solution) crosses into x < 0
    _, ss_free, _, _ = _simulate(x0, xd0, poles, u_nom, x_min=-1e9, t_end=6.0)
    assert ss_free[:, 0].min() < -0.3


def test_double_integrator_inadmissible_pole_crosses_zero():
    """Theorem 1 matters: with h_dot(0)/h(0) = -5 a pole p_1 = 1 < 5 is rejected, and the
    closed loop with the row active indeed leaves the safe set (h = -e^{-t} + 2 e^{-3t})."""
    x0, xd0 = 1.0, -5.0
    with pytest.raises(bf.PoleError):
        bf.check_poles("double-integrator", [x0, xd0], [1.0, 3.0])
    ts, ss, _, _ = _simulate(x0, xd0, [1.0, 3.0], lambda x, xd, t: -50.0, t_end=3.0)
    np.testing.assert_allclose(ss[:, 0], -np.exp(-ts) + 2 * np.exp(-3 * ts), atol=1e-10)
    assert ss[:, 0].min() < -0.1
    # admissible poles from the same start keep h >= 0
    bf.check_poles("double-integrator", [x0, xd0], [5.0, 6.0])
    _, ss, _, _ = _simulate(x0, xd0, [5.0, 6.0], lambda x, xd, t: -50.0, t_end=3.0)
    assert ss[:, 0].min() >= 0.0


def test_relative_degree_one_velocity_barrier():
    """h = x_dot - v_min (relative degree 1): with the row active, h = h0 e^{-p t}."""
    ts, ss, _, _ = _simulate(0.0, 1.0, [1.5], lambda x, xd, t: -50.0, x_min=-0.5, degree=1,
                             t_end=2.0)
    h = ss[:, 1] + 0.5
    np.testing.assert_allclose(h, 1.5 * np.exp(-1.5 * ts), atol=1e-10)


# --------------------------------------------------------------------------------------
# The fist-height barrier on Digit, by AD, against MuJoCo and finite differences
# --------------------------------------------------------------------------------------



def _h_mujoco(m, q, side="left"):
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    f, t = m.site(f"{side}-fist").id, m.site("torso").id
    p = d.site_xmat[t].reshape(3, 3).T @ (d.site_xpos[f] - d.site_xpos[t])
    return -p[2] - THRESHOLD


def _yaw_rate_barrier(wmax=1.5):
    """A relative-degree-1 SafeSet mixing q and v on the floating base: the world yaw rate
    of the torso plus a left-elbow term stays below wmax,
    h(q, v) = wmax - (R(quat) omega_body)_z - q_elbow v_elbow."""
    from safewbc_jax.model import spatial

    def h(model, q, v, threshold, domain=None):
        k, kd = model.joint_qadr("left-elbow"), model.joint_dadr("left-elbow")
        return threshold - (spatial.quat_to_mat(q[3:7]) @ v[3:6])[2] - q[k] * v[kd]

    return SafeSet("yaw_rate", h, relative_degree=1, poles=(3.0,), threshold=wmax)


@pytest.fixture(scope="module")
def fist(rm):
    """The arm scenario's own safe sets (what the controller runs), at the paper's
    threshold c = 0.195 m."""
    left, right = scenarios.fist_barrier("left"), scenarios.fist_barrier("right")
    yaw = _yaw_rate_barrier()

    @jax.jit
    def row_left(q, v, p):
        return bf.aecbf_row(left.h_fn(rm, THRESHOLD), q, v, p, 2)

    @jax.jit
    def row_yaw(q, v, p):
        return bf.aecbf_row(yaw.h_fn(rm, yaw.threshold), q, v, p, 1)

    return {
        "left": left, "right": right, "yaw": yaw,
        "h": jax.jit(left.h_fn(rm, THRESHOLD)), "h_right": jax.jit(right.h_fn(rm, THRESHOLD)),
        "row": row_left, "row_yaw": row_yaw,
    }


@pytest.fixture(scope="module")
def robot_states(ctrl_mj):
    rng = np.random.default_rng(42)
    return [random_state(ctrl_mj, rng) for _ in range(3)]


@pytest.fixture(scope="module")
def safe_rest_q(ctrl_mj, rm):
    """Stand with the left elbow bent so that the left fist is below the threshold."""
    q = ctrl_mj.key_qpos[0].copy()
    q[rm.joint_qadr("left-elbow")] = 0.6
    return q


def test_fist_barrier_value_matches_mujoco(ctrl_mj, rm, fist, robot_states, safe_rest_q):
    for q, _ in robot_states + [(safe_rest_q, None)]:
        assert float(fist["h"](jnp.asarray(q))) == pytest.approx(_h_mujoco(ctrl_mj, q),
                                                                 abs=1e-12)
        assert float(fist["h_right"](jnp.asarray(q))) == pytest.approx(
            _h_mujoco(ctrl_mj, q, "right"), abs=1e-12)
    assert _h_mujoco(ctrl_mj, safe_rest_q) > 0.02
    assert fist["left"].name == "left_fist" and fist["left"].relative_degree == 2


def test_fist_barrier_row_against_finite_differences(ctrl_mj, rm, fist, robot_states):
    """J_h by central differences along each tangent direction (mj_integratePos), eta[1] =
    J_h v and J_h_dot v = d/dt(J_h(q(t)) v(t)) - J_h a along a trajectory with
    q_ddot = a; then b = -K_alpha eta - J_h_dot v with K from numpy's polynomial."""
    rng = np.random.default_rng(3)
    poles = np.array([2.0, 6.0])
    zero = jnp.zeros(rm.nv)

    def jac(q):
        return fist["row"](q, zero, jnp.asarray(poles)).a_row

    for q0, v0 in robot_states:
        row = fist["row"](jnp.asarray(q0), jnp.asarray(v0), jnp.asarray(poles))
        eps = 1e-6
        fd = np.array([(_h_mujoco(ctrl_mj, mj_integrate(ctrl_mj, q0, e))
                        - _h_mujoco(ctrl_mj, mj_integrate(ctrl_mj, q0, -e))) / (2 * eps)
                       for e in eps * np.eye(rm.nv)])
        np.testing.assert_allclose(row.a_row, fd, atol=1e-8)
        assert np.abs(fd).max() > 0.1  # the barrier does depend on q
        assert float(row.eta[0]) == pytest.approx(_h_mujoco(ctrl_mj, q0), abs=1e-12)
        assert float(row.eta[1]) == pytest.approx(fd @ v0, abs=1e-7)

        a = rng.normal(0.0, 2.0, rm.nv)
        eps = 1e-4
        qp, vp = trajectory_point(ctrl_mj, q0, v0, a, eps)
        qm, vm = trajectory_point(ctrl_mj, q0, v0, a, -eps)
        j0 = np.asarray(jac(jnp.asarray(q0)))
        jdot_v = (np.asarray(jac(jnp.asarray(qp))) @ vp
                  - np.asarray(jac(jnp.asarray(qm))) @ vm) / (2 * eps) - j0 @ a
        scale = max(1.0, abs(jdot_v))
        assert abs(float(row.drift) - jdot_v) <= 1e-6 * scale, (float(row.drift), jdot_v)
        b_ref = -_k_ref(poles) @ np.asarray(row.eta) - jdot_v
        assert float(row.b) == pytest.approx(b_ref, abs=1e-6 * scale)
        # and the algebraic form (eq. 28 from the kinematic terms: eta = [h, J_h v]) gives
        # the same row
        a_alg, b_alg = _row_from_terms(row.eta[0], row.a_row, row.drift, jnp.asarray(v0),
                                       bf.k_alpha_from_poles(poles))
        np.testing.assert_allclose(a_alg, row.a_row, atol=0)
        assert float(b_alg) == pytest.approx(float(row.b), rel=1e-13, abs=1e-13)


@pytest.mark.parametrize("family", ["fists", "swing_foot"])
def test_closed_form_terms_equal_the_rows_by_automatic_differentiation(rm, robot_states, family):
    """The controller builds the fist and swing-foot rows from ``SafeSet.terms`` (closed
    form from one kinematics pass and ``robot.body_motion``); they equal the rows by AD of
    the same h (held to MuJoCo and finite differences above) to 1e-10 relative: both are
    float64 evaluations of the same derivatives, in different orders. One compiled
    function per family (alone on a 2-core CPU: fists 7.5 s, swing foot 3.6 s; as one
    test they came to 20 s of CPU under a full suite's load, the fast tier's limit); the
    swing foot's at two headings."""
    from safewbc_jax.control import walking
    from safewbc_jax.model import robot

    poles = jnp.asarray([2.0, 6.0])
    if family == "fists":
        cases = [(scenarios.fist_barrier(side), False) for side in ("left", "right")]
    else:
        cases = [(walking.swing_barrier(), True)]

    @jax.jit
    def rows(q, v, heading):
        kin = robot.forward_kinematics(rm, q)
        motion = robot.body_motion(rm, kin, v)
        out = []
        for b, walks in cases:
            dom = walking.Domain(*[None] * 8)._replace(heading=heading) if walks else None
            thr = b.threshold
            closed = bf.aecbf_row_from_terms(*b.terms(rm, kin, motion, thr, dom), v, poles)
            ad = bf.aecbf_row(b.h_fn(rm, thr, dom), q, v, poles, 2)
            out.append((closed, ad))
        return out

    yaws = (0.0, 0.7) if family == "swing_foot" else (0.0,)
    for (q, v), yaw in ((s, yaw) for s in robot_states for yaw in yaws):
        for (b, _), (closed, ad) in zip(cases, rows(jnp.asarray(q), jnp.asarray(v), yaw)):
            for f in ("a_row", "b", "eta", "drift"):
                x, y = np.asarray(getattr(closed, f)), np.asarray(getattr(ad, f))
                scale = max(1.0, float(np.abs(y).max()))
                assert np.abs(x - y).max() <= 1e-10 * scale, (b.name, f, x, y)
            assert np.abs(np.asarray(ad.a_row)).max() > 0.1     # a row that depends on q


def test_relative_degree_one_row_against_finite_differences(ctrl_mj, rm, fist, robot_states):
    """h(q, v): L_G h = dh/dv by central differences in v, and L_F h = d/dt h(q(t), v) along
    q(t) = mj_integratePos(q, v t) (q_ddot = 0, MuJoCo's quaternion integration)."""
    yaw = fist["yaw"]
    h1 = jax.jit(yaw.h_fn(rm, yaw.threshold))
    q0, v0 = robot_states[0]
    row = fist["row_yaw"](jnp.asarray(q0), jnp.asarray(v0), jnp.array([3.0]))
    hq = lambda q, v: float(h1(jnp.asarray(q), jnp.asarray(v)))  # noqa: E731
    eps = 1e-6
    dv = np.array([(hq(q0, v0 + e) - hq(q0, v0 - e)) / (2 * eps) for e in eps * np.eye(rm.nv)])
    np.testing.assert_allclose(row.a_row, dv, atol=1e-9)
    assert np.count_nonzero(np.abs(dv) > 1e-3) == 4  # omega_body (3) and the elbow rate
    eps = 1e-5
    lf = (hq(mj_integrate(ctrl_mj, q0, v0, eps), v0)
          - hq(mj_integrate(ctrl_mj, q0, v0, -eps), v0)) / (2 * eps)
    assert abs(lf) > 0.1
    assert float(row.drift) == pytest.approx(lf, rel=1e-7, abs=1e-9)
    assert float(row.eta[0]) == pytest.approx(hq(q0, v0), abs=1e-14)
    assert float(row.b) == pytest.approx(-3.0 * hq(q0, v0) - lf, rel=1e-7, abs=1e-9)


def _start_check(rm, sc, s, q, v, threshold, poles):
    """Theorem 1 as the controller checks it before compiling (``deploy.check_barrier_poles``
    through ``control_step.start_eta_fn``)."""
    eta = control_step.start_eta_fn(rm, sc, s, jnp.asarray(q))(jnp.asarray(v), threshold)
    control_step.check_start_poles(s.name, np.asarray(eta)[None], np.asarray(poles)[None],
                                   batched=False)


@pytest.mark.slow
def test_check_poles_on_the_robot(rm, fist, safe_rest_q, ctrl_mj):
    left = fist["left"]
    sc = scenarios.get_scenario("arms")
    q = jnp.asarray(safe_rest_q)
    j = fist["row"](q, jnp.zeros(rm.nv), jnp.ones(2)).a_row
    v = -0.5 * j / (j @ j)  # h_dot = -0.5: the fist moving up, towards the limit
    eta0 = np.asarray(fist["row"](q, v, jnp.ones(2)).eta)
    assert eta0[0] > 0 and eta0[1] == pytest.approx(-0.5, rel=1e-12)
    want = -eta0[1] / eta0[0]
    bounds = np.asarray(bf.admissible_pole_bounds(jnp.asarray(eta0), jnp.array([2 * want, 1.0])))
    assert bounds[0] == pytest.approx(want, rel=1e-14) and bounds[1] == 0.0

    p_bad = 0.5 * want
    with pytest.raises(bf.PoleError) as err:
        bf.check_poles(left.name, eta0, [p_bad, 10.0])
    msg = str(err.value)
    assert left.name in msg and "p_1" in msg
    assert f"{p_bad:.6g}" in msg and f"{want:.6g}" in msg
    with pytest.raises(bf.PoleError, match="left_fist"):
        _start_check(rm, sc, left, safe_rest_q, v, THRESHOLD, [p_bad, 10.0])
    _start_check(rm, sc, left, safe_rest_q, v, THRESHOLD, [1.01 * want, 10.0])
    np.testing.assert_allclose(bf.check_poles(left.name, eta0, [1.01 * want, 10.0]),
                               [want, 0.0], rtol=1e-14)
    assert isinstance(err.value, ValueError)
    # non-positive poles
    for bad in ([2 * want, 0.0], [2 * want, -1.0], [-1.0, 2.0]):
        with pytest.raises(bf.PoleError, match="must be > 0"):
            bf.check_poles(left.name, eta0, bad)
    # at rest (paper remark): any positive poles are admissible
    eta_rest = np.asarray(fist["row"](q, jnp.zeros(rm.nv), jnp.ones(2)).eta)
    assert eta_rest[1] == 0.0
    for p in ([1e-3, 1e-3], [0.1, 50.0], [7.0, 0.2]):
        np.testing.assert_allclose(bf.check_poles(left.name, eta_rest, p), [0.0, 0.0])
    _start_check(rm, sc, left, safe_rest_q, np.zeros(rm.nv), THRESHOLD, [1e-3, 1e-3])
    # at the stand keyframe this model's fist is above the paper's limit: outside the set
    stand = ctrl_mj.key_qpos[0]
    assert _h_mujoco(ctrl_mj, stand) < 0
    with pytest.raises(bf.PoleError, match=r"h\(x0\)"):
        _start_check(rm, sc, left, stand, np.zeros(rm.nv), THRESHOLD, [1.0, 1.0])
    # wrong count
    with pytest.raises(bf.PoleError, match="poles given"):
        bf.check_poles(left.name, eta0, [1.0])


def test_rows_jit_and_vmap_over_poles(rm, fist, robot_states):
    q0, v0 = robot_states[1]
    qj, vj = jnp.asarray(q0), jnp.asarray(v0)
    poles = jnp.array([[1.0, 2.0], [3.0, 3.0], [0.5, 10.0], [4.0, 8.0]])
    batched = jax.vmap(lambda p: fist["row"](qj, vj, p))(poles)
    assert batched.a_row.shape == (4, rm.nv) and batched.b.shape == (4,)
    for i in range(4):
        single = fist["row"](qj, vj, poles[i])
        np.testing.assert_allclose(batched.a_row[i], single.a_row, rtol=1e-14, atol=1e-14)
        assert float(batched.b[i]) == pytest.approx(float(single.b), rel=1e-13, abs=1e-13)
        k = _k_ref(poles[i])
        assert float(single.b) == pytest.approx(-k @ np.asarray(single.eta)
                                                - float(single.drift), rel=1e-13, abs=1e-13)


def test_safe_set_argument_validation(rm):
    h2 = lambda model, q, c, d=None: q[0] - c  # noqa: E731
    with pytest.raises(SafeSetError, match="relative_degree"):
        SafeSet("bad", h2, relative_degree=3)
    with pytest.raises(SafeSetError, match="1 poles for relative degree 2"):
        SafeSet("bad", h2, poles=(1.0,))
    with pytest.raises(SafeSetError, match="must be finite numbers > 0"):
        SafeSet("bad", h2, poles=(1.0, -2.0))
    with pytest.raises(SafeSetError, match="identifier"):
        SafeSet("left-fist", h2)
    with pytest.raises(SafeSetError, match="threshold"):
        SafeSet("bad", h2, threshold=float("nan"))
    with pytest.raises(SafeSetError, match=r"needs h\(model, q, v, threshold, domain\)"):
        SafeSet("bad", h2, relative_degree=1, poles=(1.0,))
    np.testing.assert_array_equal(SafeSet("ok", h2, poles=np.array([2.0, 3.0])).poles, (2.0, 3.0))
    # h evaluated (traced, nothing compiled) before a loop compiles: one number, or refused
    q0 = jnp.zeros(rm.nq).at[3].set(1.0)
    SafeSet("ok", h2).check(rm, q0, jnp.zeros(rm.nv))
    with pytest.raises(SafeSetError, match=r"'vec': h must return one number .*\(2,\)"):
        SafeSet("vec", lambda m, q, c, d=None: q[:2] - c).check(rm, q0, jnp.zeros(rm.nv))
    with pytest.raises(SafeSetError, match="'boom': evaluating h failed: KeyError"):
        SafeSet("boom", lambda m, q, c, d=None: d["stance"] * q[0]).check(rm, q0, jnp.zeros(rm.nv),
                                                                         {})
    with pytest.raises(ValueError, match="poles"):
        bf.aecbf_row(lambda q: q[0], jnp.zeros(rm.nq), jnp.zeros(rm.nv), jnp.ones(1), 2)
