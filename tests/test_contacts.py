"""Contact constraints (safewbc_jax.model.contacts) against direct evaluation, MuJoCo and scipy.

References are built independently of the module under test: sole poses from MuJoCo's
site_xpos/site_xmat, polygons from scipy's ConvexHull, sole wrenches summed by hand from
point forces at known points, generalized forces from mujoco.mj_applyFT.
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import ad_reference
from conftest import random_state, trajectory_point
from scipy.spatial import ConvexHull

from safewbc_jax.model import contacts, robot

FEET = ("left-sole", "right-sole")
MU, GAMMA, F_MIN = 0.7, 0.03, 15.0
MODES = ((1.0, 1.0), (1.0, 0.0), (0.0, 1.0))


# --------------------------------------------------------------------------------------
# helpers (independent of safewbc_jax.model.contacts)
# --------------------------------------------------------------------------------------

def _yaw_quat(yaw):
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def _configs(ctrl_mj):
    """Stand keyframe, and stand with a yawed and shifted (also lifted) base."""
    stand = ctrl_mj.key_qpos[0].copy()
    moved = stand.copy()
    moved[:3] += [0.31, -0.27, 0.15]
    moved[3:7] = _yaw_quat(0.8)
    return {"stand": stand, "yawed_shifted": moved}


def _mj_sites(m, q):
    d = mujoco.MjData(m)
    d.qpos[:] = q
    mujoco.mj_kinematics(m, d)
    return {f: (d.site_xpos[m.site(f).id].copy(), d.site_xmat[m.site(f).id].reshape(3, 3).copy())
            for f in FEET}


def _ref_corners(p, r, length, width):
    loc = np.array([[sx * length / 2, sy * width / 2, 0.0] for sx in (1, -1) for sy in (1, -1)])
    return p + loc @ r.T


def _ref_polygon(sites, mode, length, width):
    """scipy hull of the contact soles' corners: CCW vertices (k, 2) and equations."""
    pts = np.concatenate([_ref_corners(*sites[f], length, width)[:, :2]
                          for f, c in zip(FEET, mode) if c])
    hull = ConvexHull(pts)
    return pts[hull.vertices], hull.equations  # equations: n . x + off <= 0 inside


def _ref_signed_distance(verts, eqs, c):
    slack = -(eqs[:, :2] @ c + eqs[:, 2])
    if slack.min() >= 0:
        return slack.min()
    a, b = verts, np.roll(verts, -1, axis=0)
    t = b - a
    s = np.clip(np.sum((c - a) * t, 1) / np.sum(t * t, 1), 0, 1)
    return -np.min(np.linalg.norm(c - (a + s[:, None] * t), axis=1))


def _sole_wrench(p, r, points, forces):
    """Contact-frame wrench at the sole origin of world point forces (ground on robot)."""
    f = forces.sum(0)
    m = np.cross(points - p, forces).sum(0)
    return np.concatenate([r.T @ f, r.T @ m])


def _random_forces(rng, n):
    fz = rng.uniform(20.0, 300.0, n)
    ft = rng.uniform(-0.5, 0.5, (n, 2)) * fz[:, None]
    return np.column_stack([ft, fz])


@pytest.fixture(scope="module")
def sole_size(sim_mj):
    """Sole rectangle of the simulation model's collision boxes (length along site x)."""
    half = sim_mj.geom_size[sim_mj.geom("left-sole").id]
    return 2 * half[1], 2 * half[0]


@pytest.fixture(scope="module")
def jit():
    return {
        "ineq": jax.jit(contacts.contact_inequalities),
        # ZMP and its margin from one compiled function (compiling is the slow part here)
        "zmp": jax.jit(lambda *a: (contacts.zmp(*a), contacts.zmp_margin(*a))),
        "rows": jax.jit(contacts.zmp_rows),
        "poly": jax.jit(contacts.support_polygon),
        "sj": jax.jit(contacts.stacked_contact_jacobian),
        "sd": jax.jit(ad_reference.stacked_contact_drift),
        "hull": jax.jit(jax.vmap(contacts.convex_hull_2d)),
    }


# --------------------------------------------------------------------------------------
# sole geometry
# --------------------------------------------------------------------------------------

def test_sole_constants_match_the_collision_boxes(sim_mj, sole_size):
    assert contacts.SOLE_LENGTH == pytest.approx(sole_size[0], abs=1e-12)
    assert contacts.SOLE_WIDTH == pytest.approx(sole_size[1], abs=1e-12)
    d = mujoco.MjData(sim_mj)
    d.qpos[:] = sim_mj.key_qpos[0]
    mujoco.mj_kinematics(sim_mj, d)
    for f in FEET:
        g, s = sim_mj.geom(f).id, sim_mj.site(f).id
        rs, rg = d.site_xmat[s].reshape(3, 3), d.geom_xmat[g].reshape(3, 3)
        # the box's long (y) axis is the site's x axis, the box's z the site's z
        assert abs(rs[:, 0] @ rg[:, 1]) == pytest.approx(1.0, abs=1e-9)
        assert rs[:, 2] @ rg[:, 2] == pytest.approx(1.0, abs=1e-9)
        # the site is the centre of the box's bottom face
        centre = rs.T @ (d.geom_xpos[g] - d.site_xpos[s])
        np.testing.assert_allclose(centre, [0, 0, sim_mj.geom_size[g][2]], atol=1e-9)


# --------------------------------------------------------------------------------------
# friction pyramid and torsion
# --------------------------------------------------------------------------------------

def _direct_friction(lam, mu, gamma, f_min):
    fx, fy, fz, _, _, mz = lam
    k = mu / np.sqrt(2)
    return np.array([fx - k * fz, -fx - k * fz, fy - k * fz, -fy - k * fz, f_min - fz,
                     mz - gamma * fz, -mz - gamma * fz])


def test_friction_rows_match_direct_evaluation(ctrl_mj, rm, jit):
    rng = np.random.default_rng(3)
    q = jnp.asarray(ctrl_mj.key_qpos[0])
    g, h, soft = (np.asarray(x) for x in jit["ineq"](rm, q, jnp.ones(2), MU, GAMMA, F_MIN, 0.0))
    n = contacts.N_FRICTION_ROWS
    np.testing.assert_array_equal(soft[:2 * n], 0.0)
    np.testing.assert_array_equal(soft[2 * n:], 1.0)
    k = MU / np.sqrt(2)
    n_in = n_out = 0
    for i in range(600):
        fz = rng.uniform(-50.0, 400.0)
        # half the samples strictly inside the pyramid, the rest anywhere around it
        s = 0.95 if i % 2 == 0 else 2.0
        lam_foot = np.array([rng.uniform(-s, s) * k * abs(fz), rng.uniform(-s, s) * k * abs(fz),
                             fz, rng.normal(0, 20), rng.normal(0, 20),
                             rng.uniform(-s, s) * GAMMA * abs(fz)])
        other = rng.normal(0, 100, 6)
        for foot in (0, 1):
            lam = np.concatenate([lam_foot, other] if foot == 0 else [other, lam_foot])
            rows = (g @ lam - h)[foot * n:(foot + 1) * n]
            direct = _direct_friction(lam_foot, MU, GAMMA, F_MIN)
            np.testing.assert_allclose(rows, direct, rtol=0, atol=1e-10)
            inside = (abs(lam_foot[0]) <= k * lam_foot[2] and abs(lam_foot[1]) <= k * lam_foot[2]
                      and lam_foot[2] >= F_MIN and abs(lam_foot[5]) <= GAMMA * lam_foot[2])
            assert bool(np.all(rows <= 0)) == inside
            n_in += inside
            n_out += not inside
    assert n_in > 100 and n_out > 100


def test_foot_not_in_contact_gives_no_constraint(ctrl_mj, rm, jit):
    rng = np.random.default_rng(4)
    q = jnp.asarray(ctrl_mj.key_qpos[0])
    n = contacts.N_FRICTION_ROWS
    for mode, free in (((1.0, 0.0), 1), ((0.0, 1.0), 0)):
        g, h, _ = (np.asarray(x) for x in jit["ineq"](rm, q, jnp.asarray(mode), MU, GAMMA,
                                                      F_MIN, 0.01))
        np.testing.assert_array_equal(g[free * n:(free + 1) * n], 0.0)
        np.testing.assert_array_equal(h[free * n:(free + 1) * n], 1.0)
        # no row of any kind reads the free foot's wrench
        np.testing.assert_array_equal(g[:, 6 * free:6 * free + 6], 0.0)
        assert np.any(g[(1 - free) * n:(2 - free) * n] != 0)
    g, h, _ = (np.asarray(x) for x in jit["ineq"](rm, q, jnp.zeros(2), MU, GAMMA, F_MIN, 0.01))
    np.testing.assert_array_equal(g, 0.0)
    np.testing.assert_array_equal(h, 1.0)
    assert np.all(g @ rng.normal(0, 1e3, 12) <= h)


# --------------------------------------------------------------------------------------
# ZMP
# --------------------------------------------------------------------------------------

def _zmp_cases(rng, sites, mode, verts, z0):
    """(centre of pressure, stacked 12-wrench) pairs: point forces on the soles (CoP
    inside), and forces all acting at a chosen ground point c for points inside, outside
    and 1e-4 m either side of each edge."""
    cases = []
    feet = [f for f, c in zip(FEET, mode) if c]
    for _ in range(10):
        lam = np.zeros(12)
        num, den = np.zeros(2), 0.0
        for i, f in enumerate(FEET):
            if not mode[i]:
                continue
            p, r = sites[f]
            loc = rng.uniform(-0.5, 0.5, (5, 2)) * [contacts.SOLE_LENGTH, contacts.SOLE_WIDTH]
            pts = p + np.column_stack([loc, np.zeros(5)]) @ r.T
            forces = _random_forces(rng, 5)
            lam[6 * i:6 * i + 6] = _sole_wrench(p, r, pts, forces)
            num += forces[:, 2] @ pts[:, :2]
            den += forces[:, 2].sum()
        cases.append((num / den, lam))
    lo, hi = verts.min(0) - 0.1, verts.max(0) + 0.1
    targets = [rng.uniform(lo, hi) for _ in range(30)]
    for a, b in zip(verts, np.roll(verts, -1, 0)):  # scipy's vertices are CCW
        t = b - a
        outward = np.array([t[1], -t[0]]) / np.linalg.norm(t)
        for s in (0.5, rng.uniform(0.05, 0.95)):
            for off in (1e-4, -1e-4, 1e-2):
                targets.append(a + s * t + off * outward)
    for c in targets:
        lam = np.zeros(12)
        point = np.array([c[0], c[1], z0])
        for i, f in enumerate(FEET):
            if f in feet:
                lam[6 * i:6 * i + 6] = _sole_wrench(*sites[f], point[None], _random_forces(rng, 1))
        cases.append((c, lam))
    return cases


@pytest.mark.parametrize("config", ["stand", "yawed_shifted"])
def test_zmp_and_zmp_rows_against_point_forces(ctrl_mj, rm, jit, config):
    rng = np.random.default_rng(11)
    qn = _configs(ctrl_mj)[config]
    q = jnp.asarray(qn)
    sites = _mj_sites(ctrl_mj, qn)
    heights = [sites[f][0][2] for f in FEET]
    assert abs(heights[0] - heights[1]) < 1e-6  # both soles on one level ground
    for mode in MODES:
        z0 = np.mean([h for h, c in zip(heights, mode) if c])
        verts, eqs = _ref_polygon(sites, mode, contacts.SOLE_LENGTH, contacts.SOLE_WIDTH)
        g0, h0 = (np.asarray(x) for x in jit["rows"](rm, q, jnp.asarray(mode), 0.0))
        g2, h2 = (np.asarray(x) for x in jit["rows"](rm, q, jnp.asarray(mode), 0.02))
        n_in = n_out = 0
        for c, lam in _zmp_cases(rng, sites, mode, verts, z0):
            lam_j = jnp.asarray(lam)
            z, got = jit["zmp"](rm, q, lam_j, jnp.asarray(mode))
            np.testing.assert_allclose(z, c, rtol=0, atol=1e-9)
            slack = -(eqs[:, :2] @ c + eqs[:, 2])  # distance inside each edge line
            assert abs(slack.min()) > 1e-6  # the case is not ambiguous
            inside = slack.min() > 0
            assert bool(np.all(g0 @ lam <= h0)) == inside, (mode, c, slack)
            inside_2 = slack.min() > 0.02
            if abs(slack.min() - 0.02) > 1e-6:
                assert bool(np.all(g2 @ lam <= h2)) == inside_2, (mode, c, slack)
            ref = _ref_signed_distance(verts, eqs, c)
            assert float(got) == pytest.approx(ref, abs=1e-9)
            # a wrench put on a foot not in contact is ignored
            if 0.0 in mode:
                free = mode.index(0.0)
                lam_x = lam.copy()
                lam_x[6 * free:6 * free + 6] = rng.normal(0, 100, 6)
                assert np.array_equal(g0 @ lam_x <= h0, g0 @ lam <= h0)
            n_in += inside
            n_out += not inside
        assert n_in > 10 and n_out > 10


def test_zmp_sign_toe_and_heel(ctrl_mj, rm, jit):
    """A vertical push under the left toe puts the ZMP in front of the sole centre (world
    +x at the stand keyframe) and a push under its outer edge to the left (+y)."""
    qn = ctrl_mj.key_qpos[0]
    p, r = _mj_sites(ctrl_mj, qn)["left-sole"]
    for loc, axis, sign in (([0.1, 0, 0], 0, 1), ([-0.1, 0, 0], 0, -1), ([0, 0.03, 0], 1, 1)):
        pt = p + r @ np.array(loc)
        lam = np.zeros(12)
        lam[:6] = _sole_wrench(p, r, pt[None], np.array([[0.0, 0.0, 500.0]]))
        z = np.asarray(jit["zmp"](rm, jnp.asarray(qn), jnp.asarray(lam), jnp.array([1.0, 0.0]))[0])
        assert sign * (z[axis] - p[axis]) == pytest.approx(abs(loc[axis]), abs=1e-6)


def test_support_polygon_matches_scipy_on_the_robot(ctrl_mj, rm, jit):
    for name, qn in _configs(ctrl_mj).items():
        sites = _mj_sites(ctrl_mj, qn)
        for mode in MODES:
            verts, eqs = _ref_polygon(sites, mode, contacts.SOLE_LENGTH, contacts.SOLE_WIDTH)
            poly = jit["poly"](rm, jnp.asarray(qn), jnp.asarray(mode), 0.0)
            on = np.asarray(poly.active) > 0.5
            ours = np.asarray(poly.vertices)[on]
            assert _same_polygon(ours, verts), (name, mode)
            # margin moves every active half-plane inward, inactive ones are 0 <= 1
            poly2 = jit["poly"](rm, jnp.asarray(qn), jnp.asarray(mode), 0.03)
            np.testing.assert_allclose(np.asarray(poly.offsets - poly2.offsets)[on], 0.03,
                                       atol=1e-12)
            np.testing.assert_array_equal(np.asarray(poly2.normals)[~on], 0.0)
            np.testing.assert_array_equal(np.asarray(poly2.offsets)[~on], 1.0)


# --------------------------------------------------------------------------------------
# convex hull
# --------------------------------------------------------------------------------------

def _strip_collinear(v, tol=1e-8):
    v = list(v)
    changed = True
    while changed and len(v) > 3:
        changed = False
        for i in range(len(v)):
            a, b, c = np.asarray(v[i - 1]), np.asarray(v[i]), np.asarray(v[(i + 1) % len(v)])
            t = c - a
            dist = abs(t[0] * (b - a)[1] - t[1] * (b - a)[0]) / max(np.linalg.norm(t), 1e-300)
            if dist < tol:
                del v[i]
                changed = True
                break
    return np.array(v)


def _area(v):
    x, y = v[:, 0], v[:, 1]
    return 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)


def _same_polygon(ours, ref):
    a, b = _strip_collinear(ours), _strip_collinear(ref)
    if len(a) != len(b):
        return False
    dist = np.linalg.norm(a[:, None] - b[None], axis=-1)
    return bool(np.all(dist.min(1) < 1e-9) and np.all(dist.min(0) < 1e-9)
                and _area(ours) == pytest.approx(_area(ref), abs=1e-12))


def _rect(centre, yaw, length=contacts.SOLE_LENGTH, width=contacts.SOLE_WIDTH):
    c, s = np.cos(yaw), np.sin(yaw)
    loc = np.array([[sx * length / 2, sy * width / 2] for sx in (1, -1) for sy in (1, -1)])
    return np.asarray(centre) + loc @ np.array([[c, -s], [s, c]]).T


def _placements(rng):
    sets = []
    for _ in range(150):  # random
        sets.append(np.concatenate([_rect(rng.uniform(-0.3, 0.3, 2), rng.uniform(-np.pi, np.pi)),
                                    _rect(rng.uniform(-0.3, 0.3, 2), rng.uniform(-np.pi, np.pi))]))
    for yaw in (0.0, np.pi / 2, 0.37, -1.2):  # degenerate ones
        c, s = np.cos(yaw), np.sin(yaw)
        fwd, side = np.array([c, s]), np.array([-s, c])
        base = rng.uniform(-0.2, 0.2, 2)
        for other in (base + 0.22 * side,                 # side by side, aligned
                      base + contacts.SOLE_WIDTH * side,  # side by side, touching
                      base + 0.3 * fwd,                   # one behind the other, aligned
                      base,                               # on top of each other
                      base + 0.03 * fwd + 0.01 * side,    # overlapping
                      base + 0.5 * contacts.SOLE_WIDTH * side):  # overlapping, aligned
            sets.append(np.concatenate([_rect(base, yaw), _rect(other, yaw)]))
        sets.append(np.concatenate([_rect(base, yaw), _rect(base + 0.05 * fwd, yaw + 0.3)]))
    return np.stack(sets)


def test_convex_hull_against_scipy(jit):
    rng = np.random.default_rng(5)
    sets = _placements(rng)
    a, b, active = (np.asarray(x) for x in jit["hull"](jnp.asarray(sets)))
    assert a.shape == (len(sets), 8, 2) and active.shape == (len(sets), 8)
    for k, pts in enumerate(sets):
        on = active[k] > 0.5
        hull = ConvexHull(pts)
        ref = pts[hull.vertices]
        ours = a[k][on]
        # active edges come first and chain into one closed CCW loop
        n_on = int(on.sum())
        assert np.all(on[:n_on]) and not np.any(on[n_on:]), k
        np.testing.assert_allclose(b[k][on], np.roll(ours, -1, axis=0), atol=1e-9)
        assert _same_polygon(ours, ref), k
        assert len(_strip_collinear(ours, 1e-10)) == len(ours), k  # no redundant rows
        assert _area(ours) == pytest.approx(hull.volume, abs=1e-12)
        # every point is inside (left of) every active edge
        t = b[k][on] - ours
        rel = pts[None] - ours[:, None]
        cross = t[:, None, 0] * rel[..., 1] - t[:, None, 1] * rel[..., 0]
        assert (cross / np.linalg.norm(t, axis=1)[:, None]).min() >= -1e-9, k
        # unused slots are zero edges that give 0 <= 1
        nrm, d = contacts.halfplanes(jnp.asarray(a[k]), jnp.asarray(b[k]), jnp.asarray(active[k]))
        np.testing.assert_array_equal(np.asarray(nrm)[~on], 0.0)
        np.testing.assert_array_equal(np.asarray(d)[~on], 1.0)


# --------------------------------------------------------------------------------------
# contact Jacobian and drift
# --------------------------------------------------------------------------------------

def test_contact_jacobian_transpose_is_mujoco_generalized_force(ctrl_mj, rm, jit):
    rng = np.random.default_rng(9)
    for _ in range(6):
        q, _ = random_state(ctrl_mj, rng)
        d = mujoco.MjData(ctrl_mj)
        d.qpos[:] = q
        mujoco.mj_kinematics(ctrl_mj, d)
        mujoco.mj_comPos(ctrl_mj, d)
        for f in FEET:
            s = ctrl_mj.site(f).id
            p, r = d.site_xpos[s].copy(), d.site_xmat[s].reshape(3, 3)
            lam = rng.normal(0, 100, 6)
            qfrc = np.zeros(ctrl_mj.nv)
            mujoco.mj_applyFT(ctrl_mj, d, r @ lam[:3], r @ lam[3:], p,
                              int(ctrl_mj.site_bodyid[s]), qfrc)
            i = FEET.index(f)
            j = np.asarray(jit["sj"](rm, jnp.asarray(q)))[6 * i:6 * i + 6]
            np.testing.assert_allclose(j.T @ lam, qfrc, rtol=0,
                                       atol=1e-10 * max(1.0, np.abs(qfrc).max()))




def test_contact_drift_against_finite_differences(ctrl_mj, rm, jit):
    """J_cont_dot v = d/dt (J_cont(q(t)) v(t)) - J_cont a along q_ddot = a != 0."""
    rng = np.random.default_rng(21)
    eps = 1e-4
    for _ in range(2):
        q0, v0 = random_state(ctrl_mj, rng)
        a = rng.normal(0, 2.0, rm.nv)
        qp, vp = trajectory_point(ctrl_mj, q0, v0, a, eps)
        qm, vm = trajectory_point(ctrl_mj, q0, v0, a, -eps)
        j0 = np.asarray(jit["sj"](rm, jnp.asarray(q0)))
        fd = (np.asarray(jit["sj"](rm, jnp.asarray(qp))) @ vp
              - np.asarray(jit["sj"](rm, jnp.asarray(qm))) @ vm) / (2 * eps) - j0 @ a
        ad = np.asarray(jit["sd"](rm, jnp.asarray(q0), jnp.asarray(v0)))
        for i in range(2):  # per foot
            err = np.abs(ad - fd)[6 * i:6 * i + 6].max()
            assert err <= 1e-5 * max(1.0, np.abs(fd[6 * i:6 * i + 6]).max()), (FEET[i], err)


def test_stacked_contact_terms(ctrl_mj, rm, jit):
    rng = np.random.default_rng(2)
    q, v = (jnp.asarray(x) for x in random_state(ctrl_mj, rng))
    j, dr = jit["sj"](rm, q), jit["sd"](rm, q, v)
    assert j.shape == (12, rm.nv) and dr.shape == (12,)
    # the stacked rows are the per-foot terms, left foot first (eager, no compile)
    np.testing.assert_allclose(j[6:], contacts.contact_jacobian(rm, q, "right-sole"), atol=1e-14)
    # J_cont = blockdiag(R^T, R^T) J_world
    _, r = robot.frame_pose(rm, q, "left-sole")
    jw = robot.frame_jacobian(rm, q, "left-sole")
    np.testing.assert_allclose(j[:3], r.T @ jw[:3], atol=1e-14)
    np.testing.assert_allclose(j[3:6], r.T @ jw[3:], atol=1e-14)


# --------------------------------------------------------------------------------------
# shapes, jit, vmap, torque limits
# --------------------------------------------------------------------------------------

def test_fixed_shapes_jit_and_vmap(ctrl_mj, rm, jit):
    rng = np.random.default_rng(8)
    qs = [random_state(ctrl_mj, rng)[0] for _ in range(4)]
    qs[0] = ctrl_mj.key_qpos[0]
    shapes = set()
    for mode in MODES + ((0.0, 0.0),):
        out = jit["ineq"](rm, jnp.asarray(qs[0]), jnp.asarray(mode), MU, GAMMA, F_MIN, 0.01)
        shapes.add(tuple(x.shape for x in out))
    assert shapes == {((contacts.N_CONTACT_ROWS, 12), (contacts.N_CONTACT_ROWS,),
                       (contacts.N_CONTACT_ROWS,))}
    modes = jnp.asarray([MODES[i % 3] for i in range(4)])
    batched = jax.jit(jax.vmap(contacts.contact_inequalities,
                               in_axes=(None, 0, 0, None, None, None, None)))
    g, h, soft = batched(rm, jnp.asarray(np.stack(qs)), modes, MU, GAMMA, F_MIN, 0.01)
    assert g.shape == (4, 30, 12) and h.shape == (4, 30) and soft.shape == (4, 30)
    for i in range(4):
        gi, hi, si = jit["ineq"](rm, jnp.asarray(qs[i]), modes[i], MU, GAMMA, F_MIN, 0.01)
        np.testing.assert_allclose(g[i], gi, atol=1e-12)
        np.testing.assert_allclose(h[i], hi, atol=1e-12)
        np.testing.assert_array_equal(soft[i], si)
    lam = jnp.asarray(np.tile([0.0, 0.0, 400.0, 0.0, 0.0, 0.0], 2))
    zb = jax.jit(jax.vmap(contacts.zmp_margin, in_axes=(None, 0, None, 0)))(
        rm, jnp.asarray(np.stack(qs)), lam, modes)
    assert zb.shape == (4,)
    # flight: no polygon, no margin
    assert float(jit["zmp"](rm, jnp.asarray(qs[0]), lam, jnp.zeros(2))[1]) == -np.inf


def test_torque_limit_bounds(ctrl_mj, rm):
    lb, ub = contacts.torque_limit_bounds(rm)
    ref = ctrl_mj.actuator_gear[:, 0] * np.abs(ctrl_mj.actuator_ctrlrange).max(axis=1)
    np.testing.assert_allclose(ub, ref, atol=0)
    np.testing.assert_allclose(lb, -ref, atol=0)
    assert lb.shape == (rm.nu,) and np.all(np.asarray(ub) > 0)


def test_cop_rows_against_direct_evaluation():
    """Per-foot centre of pressure rows: satisfied iff -m_y/f_z and m_x/f_z lie inside the
    sole rectangle shrunk by the margin; rows of a foot in the air are 0 <= 1."""
    rng = np.random.default_rng(11)
    margin = 0.01
    for in_contact in ((1.0, 1.0), (1.0, 0.0), (0.0, 1.0)):
        g, h = contacts.cop_rows(jnp.asarray(in_contact), margin)
        for _ in range(300):
            lam = rng.normal(0, 1, 12)
            lam[[2, 8]] = rng.uniform(5, 100, 2)
            cop = rng.uniform(-0.2, 0.2, (2, 2))
            for i in range(2):
                lam[6 * i + 3] = cop[i, 1] * lam[6 * i + 2]    # m_x = y f_z
                lam[6 * i + 4] = -cop[i, 0] * lam[6 * i + 2]   # m_y = -x f_z
            inside = [(abs(cop[i, 0]) <= contacts.SOLE_LENGTH / 2 - margin)
                      and (abs(cop[i, 1]) <= contacts.SOLE_WIDTH / 2 - margin) for i in range(2)]
            ok = np.asarray(g) @ lam <= np.asarray(h) + 1e-12
            for i in range(2):
                rows = ok[4 * i:4 * i + 4]
                assert rows.all() == (inside[i] or not in_contact[i])


def test_wrench_map_sums_the_sole_wrenches_in_the_world_frame(ctrl_mj, rm):
    """W of eq. 8 at random poses against the sum written out with MuJoCo's site frames:
    each sole's wrench [f; m] (sole frame) is R f in the world and, about the world origin,
    R m + p x (R f); a foot not in contact adds nothing."""
    rng = np.random.default_rng(8)
    w_fn = jax.jit(contacts.wrench_map)
    for _ in range(3):
        qn, _ = random_state(ctrl_mj, rng)
        sites = _mj_sites(ctrl_mj, qn)
        lam = rng.normal(0, 100, 12)
        for mode in MODES:
            force, moment = np.zeros(3), np.zeros(3)
            for i, foot in enumerate(FEET):
                if mode[i]:
                    p, r = sites[foot]
                    f, m = r @ lam[6 * i:6 * i + 3], r @ lam[6 * i + 3:6 * i + 6]
                    force += f
                    moment += m + np.cross(p, f)
            w = np.asarray(w_fn(rm, jnp.asarray(qn), jnp.asarray(mode)))
            # forces of 100 N at lever arms of ~1 m: 1e-9 relative is rounding
            np.testing.assert_allclose(w @ lam, np.concatenate([force, moment]),
                                       rtol=0, atol=1e-9 * 100 * 10)
