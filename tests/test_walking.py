"""The walking domain (safewbc_jax.control.walking): outputs selected by the stance side, the gait's
domain switching, the passive stance ankle and the contact mode in the QP, the swing leg's
rigid-spring velocity, and a short walk in MuJoCo."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from conftest import random_state

from safewbc_jax import scenarios
from safewbc_jax.control import terms as controller, walking
from safewbc_jax.model import chains, spatial
from safewbc_jax.control.outputs import StepTerms

LEFT, RIGHT, BOTH = walking.LEFT, walking.RIGHT, walking.BOTH


def _mj_sites(m, q):
    """World position, rotation and 6D Jacobian (MuJoCo's own) of both sole sites."""
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_forward(m, d)
    out = {}
    for side in ("left", "right"):
        sid = m.site(f"{side}-sole").id
        jp, jr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
        mujoco.mj_jacSite(m, d, jp, jr, sid)
        out[side] = (d.site_xpos[sid].copy(), d.site_xmat[sid].reshape(3, 3).copy(), jp)
    return out


def _euler_zyx(r):
    """[roll, pitch, yaw] of R = Rz(yaw) Ry(pitch) Rx(roll), written out independently."""
    return np.array([np.arctan2(r[2, 1], r[2, 2]), -np.arcsin(r[2, 0]),
                     np.arctan2(r[1, 0], r[0, 0])])


def _domain(stance, heading=0.0):
    g = walking.Gait(stance=stance, heading=heading)
    return jax.tree_util.tree_map(jnp.asarray, g.domain())


@pytest.mark.parametrize("stance", [LEFT, pytest.param(RIGHT, marks=pytest.mark.slow)])
def test_swing_outputs_select_the_foot_opposite_the_stance(ctrl_mj, rm, stance):
    rng = np.random.default_rng(3)
    pos_out, rot_out = walking.SwingFootPosition(), walking.SwingFootOrientation()
    ev_pos = jax.jit(lambda q, v, dom: pos_out.evaluate(rm, q, v, StepTerms(domain=dom)))
    ev_rot = jax.jit(lambda q, v, dom: rot_out.evaluate(rm, q, v, StepTerms(domain=dom)))
    swing = "right" if stance == LEFT else "left"
    dom = _domain(stance)
    for _ in range(3):
        q, v = random_state(ctrl_mj, rng, spread=0.2)
        sites = _mj_sites(ctrl_mj, q)
        p, jp, _ = ev_pos(jnp.asarray(q), jnp.asarray(v), dom)
        assert np.allclose(p, sites[swing][0], atol=1e-12)
        assert np.allclose(jp, sites[swing][2], atol=1e-10)
        th, _, _ = ev_rot(jnp.asarray(q), jnp.asarray(v), dom)
        assert np.allclose(th, _euler_zyx(sites[swing][1]), atol=1e-10)
        # value() (the settle blend's start) agrees with evaluate()
        assert np.allclose(pos_out.value(rm, jnp.asarray(q), dom), p, atol=1e-14)


@pytest.mark.parametrize("yaw", [0.0, 0.7])
def test_swing_barrier_is_positive_with_feet_apart_for_either_stance(ctrl_mj, rm, yaw):
    """h = lateral distance (heading frame) of the swing sole from the stance sole - c,
    positive when the feet are apart: the same number in left and right stance."""
    q = ctrl_mj.key_qpos[0].copy()
    # yaw the whole robot about z by rotating the base quaternion
    qz = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    qb = np.zeros(4)
    mujoco.mju_mulQuat(qb, qz, q[3:7])
    q[3:7] = qb
    sites = _mj_sites(ctrl_mj, q)
    d = sites["left"][0] - sites["right"][0]
    lateral = -np.sin(yaw) * d[0] + np.cos(yaw) * d[1]
    assert lateral > 0.15  # the stand pose: feet ~0.2 m apart
    for stance in (LEFT, RIGHT):
        h = walking.swing_clearance_h(rm, jnp.asarray(q), 0.07, _domain(stance, yaw))
        assert np.isclose(float(h), lateral - 0.07, atol=1e-12)
    # crossing the feet (left foot to the right of the right one) makes it negative
    dom = _domain(LEFT, yaw)
    hl = jax.grad(lambda qq: walking.swing_clearance_h(rm, qq, 0.07, dom))(jnp.asarray(q))
    assert np.all(np.isfinite(hl))


WALK = walking.make_scenario("walk", 1.0)


@jax.jit
def _walking_qp(rm, params, q, v, tau, start, dom):
    """The walking scenario's QP at one state and domain, jitted: one compile for every
    stance (the stance is a value of ``dom``), where the same functions run op by op took
    about 20 s on a 2-core CPU."""
    terms = controller.robot_terms(rm, WALK, q, v, dom)
    return controller.build_qp(rm, WALK, params, terms, q, v, tau, start, jnp.ones(2),
                               domain=dom)


def _qp_for(rm, ctrl_mj, stance, tau=0.1):
    q = jnp.asarray(ctrl_mj.key_qpos[0])
    v = jnp.zeros(rm.nv)
    start = dataclasses.replace(
        scenarios.start_state(rm, q), y0=controller.output_start_values(rm, WALK, q),
        settle=jnp.asarray(1.5), gait=walking.WalkStart(jnp.asarray(1.0), jnp.asarray(0.11)))
    dom = _domain(stance)._replace(tau_step=jnp.asarray(tau))
    return _walking_qp(rm, WALK.default_params(), q, v, jnp.asarray(tau), start, dom)


@pytest.mark.parametrize("stance", [LEFT, RIGHT, BOTH])
def test_domain_sets_contacts_and_passive_stance_ankle_in_the_qp(ctrl_mj, rm, stance):
    qpm, info = _qp_for(rm, ctrl_mj, stance)
    nv, nu = rm.nv, rm.nu
    nc_chain = controller.n_chain_rows(rm)
    names = rm.actuator_names
    ub = np.asarray(qpm.ub[nv:nv + nu])
    lb = np.asarray(qpm.lb[nv:nv + nu])
    stance_side = {LEFT: "left", RIGHT: "right", BOTH: None}[stance]
    for i, n in enumerate(names):
        passive = stance_side is not None and n in (f"{stance_side}-toe-A", f"{stance_side}-toe-B")
        if passive:
            assert ub[i] == 0.0 and lb[i] == 0.0, n
        else:
            assert ub[i] > 10.0 and lb[i] < -10.0, n
    # rows of the constraint kinematics: a foot in the air pins its wrench to zero
    A = np.asarray(qpm.A)
    c_rows = A[nv:]
    for foot, side in enumerate(("left", "right")):
        in_contact = stance == BOTH or stance_side == side
        for r in range(nc_chain + 6 * foot, nc_chain + 6 * foot + 6):
            lam_col = nv + nu + r
            if in_contact:
                assert np.any(c_rows[r, :nv] != 0.0) and c_rows[r, lam_col] == 0.0
            else:
                assert np.all(c_rows[r, :nv] == 0.0) and c_rows[r, lam_col] == 1.0
    # the swing output tracks the foot opposite the stance (BOTH: weight zero)
    ya, yd = info.outputs["swing_pos"]
    sites = _mj_sites(ctrl_mj, ctrl_mj.key_qpos[0])
    if stance != BOTH:
        swing = "right" if stance == LEFT else "left"
        assert np.allclose(ya, sites[swing][0], atol=1e-12)
        # the reference starts at the swing foot's start of step (domain swing0 = 0 here)
        assert np.all(np.isfinite(np.asarray(yd)))


def test_gait_switches_domains_and_swaps_feet():
    w = 9.81 * 47.0
    T = walking.STEP_T
    g = walking.Gait()
    soles = {"left": np.array([0.0, 0.1, 0.0]), "right": np.array([0.0, -0.1, 0.0])}
    assert not g.update(-0.01, 1e-3, soles, 0.0, w) and g.stance == BOTH
    assert tuple(g.domain().in_contact) == (1.0, 1.0)
    assert g.update(0.0, 1e-3, soles, 0.0, w)  # walking starts in left stance
    dom = g.domain()
    assert g.stance == LEFT and tuple(dom.in_contact) == (1.0, 0.0)
    assert np.allclose(dom.stance0, soles["left"]) and np.allclose(dom.swing0, soles["right"])
    dt = 1e-3
    n = 0
    # a strong contact before T/2 (a scuff at lift-off) does not end the step
    while g.tau_step < 0.5 * T - 2 * dt:
        assert not g.update(0.1, dt, soles, 0.5 * w, w)
        n += 1
    # between T/2 and T: a light touch does not end the step, a firm landing does
    g.tau_step = 0.6 * T
    assert not g.update(0.1, dt, soles, 0.1 * w, w)
    landed = {"left": np.array([0.0, 0.1, 0.0]), "right": np.array([0.25, -0.12, 0.0])}
    assert g.update(0.1, dt, landed, 0.3 * w, w)
    dom = g.domain()
    assert g.stance == RIGHT and g.steps == 1 and g.tau_step == 0.0
    assert tuple(dom.in_contact) == (0.0, 1.0)
    assert np.allclose(dom.stance0, landed["right"]) and np.allclose(dom.swing0, landed["left"])
    # from T on, any contact above TOUCH_FORCE ends the step
    g.tau_step = T
    assert not g.update(0.1, dt, landed, 0.5 * walking.TOUCH_FORCE, w)
    assert g.update(0.1, dt, landed, 2.0 * walking.TOUCH_FORCE, w)
    assert g.stance == LEFT and g.steps == 2 and g.missed_touchdowns == 0
    # no touchdown at all: forced switch at 2 T, counted
    g.tau_step = 2 * T - 0.5 * dt
    assert g.update(0.1, dt, landed, 0.0, w)
    assert g.stance == RIGHT and g.missed_touchdowns == 1


def test_gait_step_in_jax_follows_the_host_gait():
    """The batched rollouts advance the gait with ``gait_step`` in jax.numpy (jit, scan);
    the deployment loop with numpy through ``Gait``: the same switches, counts and feet
    over 3 s of random touchdown forces (firm, light and absent touches, so the early,
    late and forced rules all fire)."""
    rng = np.random.default_rng(3)
    w, dt, n = 9.81 * 47.0, 1e-3, 3000
    tau = np.arange(n) * dt - 0.2
    force = np.where(rng.random(n) < 0.02, rng.choice([0.3 * w, 2 * walking.TOUCH_FORCE], n), 0.0)
    force[1500:2400] = 0.0   # a long miss: forced switch
    soles = rng.normal(size=(n, 2, 3))

    g = walking.Gait()
    host = []
    for k in range(n):
        g.update(tau[k], dt, {"left": soles[k, 0], "right": soles[k, 1]}, force[k], w)
        host.append((g.stance, g.tau_step, *g.stance0, *g.swing0, g.steps, g.missed_touchdowns))

    def body(st, x):
        t, f, s = x
        st, _ = walking.gait_step(st, t, dt, s[0], s[1], f, w, xp=jnp)
        return st, jnp.concatenate([jnp.stack([st.stance, st.tau_step]), st.stance0, st.swing0,
                                    jnp.stack([st.steps, st.missed]).astype(float)])

    st0 = walking.GaitState.standing(jnp)
    _, dev = jax.jit(lambda: jax.lax.scan(body, st0, (tau, force, soles)))()
    host = np.array(host, float)
    np.testing.assert_array_equal(np.asarray(dev), host)
    assert host[-1, -2] >= 6 and host[-1, -1] >= 1   # steps taken, a forced switch counted


@pytest.mark.parametrize("stance", [LEFT, RIGHT, BOTH])
def test_rigid_spring_velocity_keeps_the_swing_leg_on_its_chains(ctrl_mj, rm, stance):
    rng = np.random.default_rng(11)
    q, v = (jnp.asarray(a) for a in random_state(ctrl_mj, rng, spread=0.1))
    vr = np.asarray(jax.jit(lambda qq, vv, st: walking.rigid_spring_velocity(rm, qq, vv, st))(
        q, v, stance))
    v = np.asarray(v)
    swing = {LEFT: "right", RIGHT: "left", BOTH: None}[stance]
    if swing is None:
        assert np.array_equal(vr, v)
        return
    pas = walking._leg_passive_dofs(rm, swing)
    assert len(pas) == 5
    changed = np.nonzero(vr != v)[0]
    assert set(changed) <= set(pas.tolist())
    names = chains.chain_names(rm)
    rows = np.array([i for i, n in enumerate(names) if n.startswith(swing)])
    springs = [rm.body_dadr[rm.joint_names.index(f"{swing}-{j}")] for j in ("shin", "heel-spring")]
    assert np.all(vr[springs] == 0.0)
    # d/dt n_kc along v_r by central differences: the swing leg's rods keep their lengths
    h = 1e-6
    f = jax.jit(lambda qq: chains.n_kc(rm, qq))
    rate = (np.asarray(f(spatial.integrate(q, jnp.asarray(vr), h)))
            - np.asarray(f(spatial.integrate(q, jnp.asarray(vr), -h)))) / (2 * h)
    assert np.max(np.abs(rate[rows])) < 1e-6
    # while the measured v generally does not (random rates)
    rate_v = (np.asarray(f(spatial.integrate(q, jnp.asarray(v), h)))
              - np.asarray(f(spatial.integrate(q, jnp.asarray(v), -h)))) / (2 * h)
    assert np.max(np.abs(rate_v[rows])) > 1e-2


@pytest.mark.slow
def test_short_walk(short_walk_deployment):
    """A few steps from standing (conftest: 2.2 s after a 1.2 s settle): no fall, steps
    about one per T, forward progress, the swing reference followed, the feet apart, no
    QP failure."""
    m, tmp_path = short_walk_deployment
    assert json.loads((tmp_path / "metrics.json").read_text()) == json.loads(json.dumps(m))
    assert not m["fell"]
    assert m["qp_failed"] == 0
    # about one step per T: 2.2 s / 0.35 s = 6.3
    assert 5 <= m["steps_taken"] <= 7, m["steps_taken"]
    assert m["missed_touchdowns"] == 0
    assert m["leg_collisions"] == 0 and m["swing_clearance_min"] > 0.1
    assert m["tracking_rms"]["swing_pos"] < 0.03     # m
    assert m["tracking_rms_components"]["com[2]"] < 0.02
    log = np.load(tmp_path / "log.npz")
    walk = log["tau"] >= 0
    com = log["y_com"][walk]
    assert com[-1, 0] - com[0, 0] > 0.15   # m forward (0.2 m/s for 2.2 s is 0.44 m)
    assert np.all(log["base_z"] > 0.8)


@pytest.mark.slow
def test_walking_zmp_margin_is_the_stance_sole_rectangle(short_walk_deployment, sim_mj,
                                                          ctrl_mj, rm):
    """In single support the logged ZMP margin is the distance of the ZMP to the stance
    sole's own rectangle (the domain's support polygon), evaluated here directly: the
    stance wrench lambda^c (contact frame = sole site frame, at its origin) gives the ZMP in
    the sole frame, p = (-m_y, m_x) / f_z, and the 0.235 m x 0.08 m rectangle its signed
    distance. Tolerance 1 mm: the direct evaluation takes the ZMP on the sole's own plane,
    the metric on the level plane through the sole origin, and the stance sole tilts by
    milliradians. The hull of both soles (the metric before the fix, one sole in the air)
    differs from it by more than 5 mm at some steps, so this test sees that mistake."""
    from safewbc_jax.model import contacts, statemap

    _, tmp_path = short_walk_deployment
    log = np.load(tmp_path / "log.npz")
    sm = statemap.build_state_map(sim_mj, ctrl_mj)
    both = jax.jit(lambda q, lam: contacts.zmp_margin(rm, q, lam, jnp.ones(2)))
    half = np.array([contacts.SOLE_LENGTH, contacts.SOLE_WIDTH]) / 2
    checked, old_gap = 0, 0.0
    # step k + 1 senses the state after step k's physics (log qpos[k]) and runs in the
    # domain the gait chose at the end of step k (log stance[k])
    for k in range(len(log["tau"]) - 1):
        stance, lam, got = log["stance"][k], log["lambda"][k + 1], log["zmp_margin"][k + 1]
        if stance == 0 or log["tau"][k + 1] < 0 or not np.isfinite(got):
            continue
        i = 0 if stance > 0 else 1
        w = lam[6 * i:6 * i + 6]
        if w[2] <= 0:
            continue
        p = np.array([-w[4], w[3]]) / w[2]          # ZMP in the stance sole's frame
        out = np.abs(p) - half
        want = (-np.linalg.norm(np.maximum(out, 0.0)) if np.any(out > 0)
                else float(np.min(-out)))
        assert abs(got - want) <= 1e-3, (k, got, want)
        checked += 1
        if checked % 10 == 0:
            q, _ = sm.to_controller(log["qpos"][k], np.zeros(sim_mj.nv))
            old_gap = max(old_gap, abs(float(both(jnp.asarray(q), jnp.asarray(lam))) - want))
    assert checked > 1000, checked
    assert old_gap > 5e-3, old_gap
