"""Contact constraints of the feet: contact Jacobians, friction pyramid, torsion, ZMP.

Paper, section "Contact constraints". Each foot c in contact holds its sole fixed,

    J_cont(q) q_ddot + J_cont_dot(q, v) v = 0                              (eq. 3)

and carries a wrench lambda^c = [f_x, f_y, f_z, m_x, m_y, m_z] that must lie in the
pyramidal friction cone and satisfy the torsional (soft-finger) limit

    |f_x| <= mu/sqrt(2) f_z,   |f_y| <= mu/sqrt(2) f_z,   f_z > 0,         (eqs. 4-6)
    |m_z| <= gamma f_z,                                                    (eq. 7)

while the zero moment point of the summed wrench lambda^w = sum_c Ad^T lambda^c (eq. 8)
stays inside the support polygon P (eq. 9).

Conventions used throughout
---------------------------
* The contact frame of a foot is its sole site (``left-sole`` / ``right-sole``): origin at
  the centre of the sole's bottom face, z normal to the sole pointing up into the foot,
  x along the foot.
* lambda^c is the wrench of the GROUND ON THE ROBOT, applied at the sole site origin and
  expressed in the contact frame. The contact Jacobian is the sole Jacobian expressed in
  that frame, J_cont = blockdiag(R^T, R^T) J_world, so that J_cont^T lambda^c is the
  generalized force of the wrench and eq. 1 reads M q_ddot + h = B u + J_cont^T lambda.
* The stacked wrench of both feet is lambda = [lambda^left (6); lambda^right (6)] (12 entries).
* ``in_contact`` is a length-2 array (left, right); an entry > 0.5 means "in contact". A
  foot not in contact gives rows ``0 <= 1`` (its wrench is forced to zero elsewhere), so
  every output has the same shape in single, double and no support: a batched solver can
  vmap over contact modes.

The sole is a 0.235 m x 0.08 m rectangle: the collision boxes ``left-sole`` /
``right-sole`` of ``models/digit.xml`` have half sizes (0.04, 0.1175, 0.0115) in a box
frame whose y axis is the sole site's x axis (checked in ``tests/test_contacts.py``). The
controller model carries no collision geoms, hence the constants below.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.model import robot, spatial
from safewbc_jax.model.robot import RobotModel
from safewbc_jax.model import digit

FEET = digit.SOLES
SOLE_LENGTH = 2 * 0.1175  # m, along the sole site's x (digit.xml sole box half size 0.1175)
SOLE_WIDTH = 2 * 0.04     # m, along the sole site's y (digit.xml sole box half size 0.04)

N_FRICTION_ROWS = 7       # per foot: 4 pyramid faces, unilateral f_z >= f_min, 2 torsion
N_HULL = 8                # corners of both soles = most edges the support polygon can have
N_ZMP_ROWS = N_HULL
N_COP_ROWS = 4            # per foot: its own centre of pressure inside its sole
N_CONTACT_ROWS = 2 * N_FRICTION_ROWS + 2 * N_COP_ROWS + N_ZMP_ROWS  # 30

_TOL = 1e-9  # m: points closer than this are one point; turns this small count as straight


# --------------------------------------------------------------------------------------
# Sole frames and contact Jacobians (eq. 3)
# --------------------------------------------------------------------------------------

def _site_frames(model: RobotModel, q, frames, jacobians=False, kin=None):
    """World positions (k, 3) and rotations (k, 3, 3) of several sites from ONE forward
    kinematics pass (the same formulas as robot.frame_pose / frame_jacobian), and with
    ``jacobians`` their world [linear; angular] Jacobians (k, 6, nv). ``kin``: the
    forward kinematics (xpos, xrot) of q when already computed."""
    xpos, xrot = robot.forward_kinematics(model, q) if kin is None else kin
    sites = [model.site_id(f) for f in frames]
    bodies = [model.site_body[s] for s in sites]
    # static (python int) indices: XLA then prunes the bodies the feet do not depend on
    p = jnp.stack([xpos[b] + xrot[b] @ model.site_pos[s] for s, b in zip(sites, bodies)])
    r = jnp.stack([xrot[b] @ model.site_rot[s] for s, b in zip(sites, bodies)])
    if not jacobians:
        return p, r
    jp, jr = robot.point_jacobians(model, xpos, xrot, np.array(bodies), p)
    return p, r, jnp.concatenate([jp, jr], axis=1)


def sole_poses(model: RobotModel, q, kin=None):
    """World positions (2, 3) and rotations (2, 3, 3) of the left and right sole sites."""
    return _site_frames(model, q, FEET, kin=kin)


def _contact_jacobians(model: RobotModel, q, frames, kin=None):
    _, r, j = _site_frames(model, q, frames, jacobians=True, kin=kin)
    rt = jnp.swapaxes(r, 1, 2)
    return jnp.concatenate([rt @ j[:, :3], rt @ j[:, 3:]], axis=1)  # (k, 6, nv)


def contact_jacobian(model: RobotModel, q, frame: str):
    """J_cont of eq. 3 for one foot: the sole site's 6 x nv Jacobian with both its
    linear and angular rows expressed in the contact (sole) frame,
    J_cont = blockdiag(R^T, R^T) J_world. Then J_cont^T lambda^c is the generalized force
    of the contact-frame wrench lambda^c applied at the sole origin."""
    return _contact_jacobians(model, q, (frame,))[0]


def stacked_contact_jacobian(model: RobotModel, q, kin=None):
    """[J_cont^left; J_cont^right] (12 x nv), rows in the order of the stacked lambda."""
    return _contact_jacobians(model, q, FEET, kin).reshape(12, -1)


# --------------------------------------------------------------------------------------
# Friction pyramid and torsion (eqs. 4-7)
# --------------------------------------------------------------------------------------

def friction_rows(mu, gamma, f_min):
    """Rows G_c lambda^c <= h_c of eqs. 4-7 for one contact wrench (7 x 6, 7):

        [ f_x - mu/sqrt(2) f_z <= 0,  -f_x - mu/sqrt(2) f_z <= 0,
          f_y - mu/sqrt(2) f_z <= 0,  -f_y - mu/sqrt(2) f_z <= 0,
         -f_z <= -f_min,
          m_z - gamma f_z <= 0,       -m_z - gamma f_z <= 0 ].

    The strict f_z > 0 of eq. 6 becomes f_z >= f_min > 0 (a QP needs closed sets)."""
    mu_p = jnp.asarray(mu) / jnp.sqrt(2.0)
    gamma = jnp.asarray(gamma)
    z = jnp.zeros_like(mu_p)
    o = jnp.ones_like(mu_p)
    g = jnp.stack([
        jnp.stack([o, z, -mu_p, z, z, z]),
        jnp.stack([-o, z, -mu_p, z, z, z]),
        jnp.stack([z, o, -mu_p, z, z, z]),
        jnp.stack([z, -o, -mu_p, z, z, z]),
        jnp.stack([z, z, -o, z, z, z]),
        jnp.stack([z, z, -gamma, z, z, o]),
        jnp.stack([z, z, -gamma, z, z, -o]),
    ])
    h = jnp.stack([z, z, z, z, -jnp.asarray(f_min) * o, z, z])
    return g, h


def _contact_flags(in_contact):
    return jnp.asarray(in_contact) > 0.5


def stacked_friction_rows(in_contact, mu, gamma, f_min):
    """The rows of eqs. 4-7 for both feet over the stacked 12-vector lambda: (14 x 12, 14), left
    foot's 7 rows then the right foot's. A foot not in contact gets rows 0 <= 1."""
    g, h = friction_rows(mu, gamma, f_min)
    c = _contact_flags(in_contact)
    zero = jnp.zeros_like(g)
    rows_g, rows_h = [], []
    for i in range(2):
        gi = jnp.concatenate([g, zero] if i == 0 else [zero, g], axis=1)
        rows_g.append(jnp.where(c[i], gi, 0.0))
        rows_h.append(jnp.where(c[i], h, 1.0))
    return jnp.concatenate(rows_g, axis=0), jnp.concatenate(rows_h)


def cop_rows(in_contact, margin=0.0, sole=(SOLE_LENGTH, SOLE_WIDTH)):
    """Each foot's own centre of pressure inside its sole (shrunk by ``margin``):
    |m_x| <= (W/2 - margin) f_z and |m_y| <= (L/2 - margin) f_z in the contact frame,
    as rows over the stacked lambda (8 x 12, 8).

    Not in the paper, which bounds only the ZMP of the summed wrench: in double support
    that lets one foot's pressure leave its sole (the foot tips on an edge) while the
    global ZMP stays inside the hull. A flat foot holds only a wrench whose centre of
    pressure lies on the sole; these rows say so, and imply the global ZMP rows."""
    half_l = 0.5 * sole[0] - margin
    half_w = 0.5 * sole[1] - margin
    g = jnp.array([[0, 0, -half_w, 1.0, 0, 0], [0, 0, -half_w, -1.0, 0, 0],
                   [0, 0, -half_l, 0, 1.0, 0], [0, 0, -half_l, 0, -1.0, 0]])
    c = _contact_flags(in_contact)
    zero = jnp.zeros_like(g)
    rows_g, rows_h = [], []
    for i in range(2):
        gi = jnp.concatenate([g, zero] if i == 0 else [zero, g], axis=1)
        rows_g.append(jnp.where(c[i], gi, 0.0))
        rows_h.append(jnp.where(c[i], 0.0, 1.0) * jnp.ones(4))
    return jnp.concatenate(rows_g, axis=0), jnp.concatenate(rows_h)


# --------------------------------------------------------------------------------------
# Wrench in the world frame (eq. 8) and ZMP
# --------------------------------------------------------------------------------------

def adjoint_wrench_map(p, r):
    """Ad^T of eq. 8 for one contact: the 6 x 6 matrix taking a wrench [f; m] given in a
    frame with world position p and rotation r (applied at p) to the same wrench in world
    coordinates about the world origin, [R f; R m + p x (R f)]."""
    z = jnp.zeros((3, 3), r.dtype)
    return jnp.block([[r, z], [spatial.skew(p) @ r, r]])


def _wrench_map(poses, in_contact):
    c = _contact_flags(in_contact)
    p, r = poses
    return jnp.concatenate([jnp.where(c[i], adjoint_wrench_map(p[i], r[i]), 0.0)
                            for i in range(2)], axis=1)


def wrench_map(model: RobotModel, q, in_contact=(1.0, 1.0)):
    """W (6 x 12) with lambda^w = W lambda = sum_c Ad^T lambda^c (eq. 8), lambda^w =
    [F; M] the total world-frame ground reaction force and its moment about the world
    origin. Columns of a foot not in contact are zero."""
    return _wrench_map(sole_poses(model, q), in_contact)


def _ground_height(poses, in_contact):
    p, _ = poses
    c = _contact_flags(in_contact).astype(p.dtype)
    return (c @ p[:, 2]) / jnp.maximum(jnp.sum(c), 1.0)


def ground_height(model: RobotModel, q, in_contact=(1.0, 1.0)):
    """Height z0 of the ground plane the ZMP lies on: the mean height of the sole sites in
    contact (0 when none is)."""
    return _ground_height(sole_poses(model, q), in_contact)


def _zmp_from_world_wrench(wrench, z0):
    """(p_x F_z, p_y F_z) and F_z for the world wrench [F; M] (moment about the origin)."""
    f, m = wrench[:3], wrench[3:]
    return jnp.stack([z0 * f[0] - m[1], m[0] + z0 * f[1]]), f[2]


def zmp(model: RobotModel, q, lambdas, in_contact=(1.0, 1.0)):
    """Zero moment point (x, y) on the ground plane z = z0 (eq. 9's p_zmp).

    With lambda^w = [F; M] from eq. 8 (ground reaction on the robot, moment about the
    world origin), the ZMP is the point p = (x, y, z0) about which the wrench has no
    horizontal moment: M = p x F + tau e_z. Its x and y rows, M_x = y F_z - z0 F_y and
    M_y = z0 F_x - x F_z, give

        p_x = (z0 F_x - M_y) / F_z,     p_y = (M_x + z0 F_y) / F_z.

    For z0 = 0 this is p_x = -M_y/F_z, p_y = M_x/F_z. The paper prints
    p_x = lambda^w_my/lambda^w_fz, p_y = -lambda^w_mx/lambda^w_fz: the same point when its
    moment has the opposite sign to ours (a moment written f x r instead of r x f, or the
    robot's moment on the ground paired with the ground's force). Here the signs are
    derived for the right-handed moment r x f, and the tests check that point forces at
    known points on the soles give their centre of pressure.

    z0 is :func:`ground_height` (the soles in contact are taken as lying on one level
    ground plane). ``lambdas`` is the stacked (12,) wrench; a foot not in contact is
    ignored. Undefined (inf/nan) where F_z = 0."""
    poses = sole_poses(model, q)
    w = _wrench_map(poses, in_contact) @ lambdas
    num, fz = _zmp_from_world_wrench(w, _ground_height(poses, in_contact))
    return num / fz


# --------------------------------------------------------------------------------------
# Support polygon: fixed-shape convex hull
# --------------------------------------------------------------------------------------

class SupportPolygon(NamedTuple):
    """Convex support polygon with a fixed number (8) of edge slots.

    Edge i runs from ``vertices[i]`` to ``vertices[(i + 1) % 8]`` counter-clockwise (seen
    from above); slots past the last edge repeat the first vertex and are inactive.
    Each active edge gives the half-plane normals[i] . p <= offsets[i] (unit outward
    normal), already moved inward by the margin; an inactive slot has normal 0 and offset
    1 (0 <= 1). ``height`` is the ground height z0 of :func:`ground_height`."""

    vertices: jax.Array  # (8, 2) hull vertices, unshrunk
    normals: jax.Array   # (8, 2)
    offsets: jax.Array   # (8,)
    active: jax.Array    # (8,) 1.0 for a real edge
    height: jax.Array    # ()


def convex_hull_2d(points, tol=_TOL):
    """Convex hull of n planar points by gift wrapping with exactly n steps (fixed shape).

    Returns (a, b, active): edge start and end points (n x 2 each) counter-clockwise and
    1.0 for real edges. Starting at the lowest-x point (lowest y among ties, a hull
    vertex), each step goes to the point that keeps every point on its left (cross
    product >= -tol per metre), the farthest such point so that collinear points are
    skipped; after the hull closes the remaining steps are the zero edge (start, start),
    inactive. Duplicate points are allowed."""
    pts = jnp.asarray(points)
    n = pts.shape[0]
    xmin = jnp.min(pts[:, 0])
    start = jnp.argmin(jnp.where(pts[:, 0] <= xmin + tol, pts[:, 1], jnp.inf))
    p0 = pts[start]

    def step(carry, _):
        cur, done = carry
        p = pts[cur]
        u = pts - p
        dist = jnp.linalg.norm(u, axis=1)
        far = dist > tol
        cross = u[:, None, 0] * u[None, :, 1] - u[:, None, 1] * u[None, :, 0]
        # signed distance of the most right-hand point from the line p -> pts[j]
        score = jnp.min(cross, axis=1) / jnp.where(far, dist, 1.0)
        valid = far & (score >= -tol)
        best = jnp.argmax(jnp.where(valid, dist, -1.0))
        fallback = jnp.argmax(jnp.where(far, score, -jnp.inf))
        nxt = jnp.where(jnp.any(valid), best, jnp.where(jnp.any(far), fallback, cur))
        active = (~done) & far[nxt]
        a = jnp.where(active, p, p0)
        b = jnp.where(active, pts[nxt], p0)
        closed = jnp.linalg.norm(pts[nxt] - p0) <= tol
        done = done | closed | ~active
        return (jnp.where(done, start, nxt), done), (a, b, active)

    _, (a, b, active) = jax.lax.scan(step, (start, jnp.zeros((), bool)), None, length=n)
    return a, b, active.astype(pts.dtype)


def halfplanes(a, b, active, margin=0.0):
    """Unit outward normals and offsets of CCW edges a -> b, n . p <= d - margin inside;
    inactive edges give 0 . p <= 1."""
    t = b - a
    length = jnp.linalg.norm(t, axis=1)
    on = active > 0.5
    safe = jnp.where(on, length, 1.0)
    nrm = jnp.stack([t[:, 1], -t[:, 0]], axis=1) / safe[:, None]
    d = jnp.sum(nrm * a, axis=1) - margin
    return jnp.where(on[:, None], nrm, 0.0), jnp.where(on, d, 1.0)


def _corners(p, r, sole):
    hl, hw = 0.5 * sole[0], 0.5 * sole[1]
    local = jnp.array([[hl, hw, 0.0], [-hl, hw, 0.0], [-hl, -hw, 0.0], [hl, -hw, 0.0]],
                      dtype=p.dtype)
    return (p[None] + local @ r.T)[:, :2]


def _support_polygon(poses, in_contact, margin, sole):
    c = _contact_flags(in_contact)
    p, r = poses
    cl, cr = _corners(p[0], r[0], sole), _corners(p[1], r[1], sole)
    pts = jnp.concatenate([jnp.where(c[0], cl, cr), jnp.where(c[1], cr, cl)], axis=0)
    a, b, active = convex_hull_2d(pts)
    active = active * jnp.any(c).astype(active.dtype)
    nrm, d = halfplanes(a, b, active, margin)
    return SupportPolygon(vertices=a, normals=nrm, offsets=d, active=active,
                          height=_ground_height(poses, in_contact))


def support_polygon(model: RobotModel, q, in_contact, margin=0.0,
                    sole=(SOLE_LENGTH, SOLE_WIDTH)) -> SupportPolygon:
    """The support polygon P of eq. 9, shrunk inward by ``margin`` (m).

    Single support: the rectangle of the sole in contact. Double support: the convex hull
    of both soles' 8 corners. Both come from the same 8-point hull: a foot not in contact
    lends its 8-point slots the other foot's corners (duplicates), so the shapes never
    change. No foot in contact: every slot inactive."""
    return _support_polygon(sole_poses(model, q), in_contact, margin, sole)


def zmp_rows(model: RobotModel, q, in_contact, margin=0.0, sole=(SOLE_LENGTH, SOLE_WIDTH),
             kin=None):
    """The ZMP condition (eq. 9) as linear rows over the stacked lambda (12): (G 8 x 12, h 8).

    For an edge n . p <= d - margin of :func:`support_polygon`, multiplying by F_z > 0
    (the world vertical force, positive whenever every contact has f_z >= f_min and the
    soles are nearly level) and using p F_z from :func:`zmp` gives the row

        n_x (z0 F_x - M_y) + n_y (M_x + z0 F_y) - (d - margin) F_z <= 0,

    linear in lambda^w = W lambda. Inactive edges give 0 <= 1."""
    poses = sole_poses(model, q, kin)
    poly = _support_polygon(poses, in_contact, margin, sole)
    w = _wrench_map(poses, in_contact)
    nx, ny, d, z0 = poly.normals[:, 0], poly.normals[:, 1], poly.offsets, poly.height
    zero = jnp.zeros_like(nx)
    coef = jnp.stack([nx * z0, ny * z0, -d, ny, -nx, zero], axis=1)  # on [F; M]
    on = poly.active > 0.5
    g = jnp.where(on[:, None], coef @ w, 0.0)
    h = jnp.where(on, 0.0, 1.0)
    return g, h


def _segment_distance(p, a, b):
    t = b - a
    s = jnp.clip(jnp.sum((p - a) * t, axis=-1) / jnp.maximum(jnp.sum(t * t, axis=-1), 1e-300),
                 0.0, 1.0)
    return jnp.linalg.norm(p - (a + s[..., None] * t), axis=-1)


def polygon_signed_distance(poly: SupportPolygon, p):
    """Signed Euclidean distance of a point to the boundary of the (unshrunk) polygon of
    ``poly`` with margin 0: positive inside, negative outside; -inf if it has no edge."""
    a = poly.vertices
    b = jnp.roll(a, -1, axis=0)
    on = poly.active > 0.5
    nrm, d = halfplanes(a, b, poly.active)
    inside_d = jnp.min(jnp.where(on, d - nrm @ p, jnp.inf))
    outside_d = jnp.min(jnp.where(on, _segment_distance(p[None], a, b), jnp.inf))
    return jnp.where(jnp.any(on), jnp.where(inside_d >= 0, inside_d, -outside_d), -jnp.inf)


def zmp_margin(model: RobotModel, q, lambdas, in_contact, sole=(SOLE_LENGTH, SOLE_WIDTH)):
    """Signed distance (m) of the ZMP to the support polygon's boundary, positive inside
    (a metric; the polygon is unshrunk). -inf when no foot is in contact or F_z <= 0."""
    poses = sole_poses(model, q)
    poly = _support_polygon(poses, in_contact, 0.0, sole)
    w = _wrench_map(poses, in_contact) @ lambdas
    num, fz = _zmp_from_world_wrench(w, poly.height)
    ok = fz > 0
    p = num / jnp.where(ok, fz, 1.0)
    return jnp.where(ok, polygon_signed_distance(poly, p), -jnp.inf)


# --------------------------------------------------------------------------------------
# Everything on lambda, and torque bounds
# --------------------------------------------------------------------------------------

def contact_inequalities(model: RobotModel, q, in_contact, mu, gamma, f_min, zmp_margin=0.0,
                         kin=None):
    """All contact inequalities on the stacked lambda (12), G_lambda lambda <= h:

        rows  0- 6: left foot friction pyramid, f_z >= f_min, torsion  (eqs. 4-7)
        rows  7-13: right foot, same
        rows 14-21: each foot's centre of pressure inside its sole (``cop_rows``)
        rows 22-29: ZMP inside the support polygon shrunk by zmp_margin  (eq. 9)

    Returns (G_lambda (30 x 12), h (30,), soft_mask (30,)) with soft_mask 1.0 on the
    centre-of-pressure and ZMP rows (the fallback may relax them) and 0.0 on the friction
    rows. Feet not in contact and unused hull slots give rows 0 <= 1."""
    gf, hf = stacked_friction_rows(in_contact, mu, gamma, f_min)
    gc, hc = cop_rows(in_contact, zmp_margin)
    gz, hz = zmp_rows(model, q, in_contact, zmp_margin, kin=kin)
    g = jnp.concatenate([gf, gc, gz], axis=0)
    h = jnp.concatenate([hf, hc, hz])
    soft = jnp.concatenate([jnp.zeros(hf.shape, h.dtype), jnp.ones(hc.shape, h.dtype),
                            jnp.ones(hz.shape, h.dtype)])
    return g, h, soft


def torque_limit_bounds(model: RobotModel):
    """(lb, ub) on the motor torques u: -torque_limit <= u <= torque_limit (N m)."""
    return -model.torque_limit, model.torque_limit
