"""The MJCF models against the published figures, and the stand keyframe."""

import json
import re
import subprocess
import sys

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from safewbc_jax.base import paths
from safewbc_jax.model import chains, modelgen, statemap
from safewbc_jax.model.modelinfo import model_info, sim_loop_residual

PARAMS = json.loads((paths.models_dir() / "digit_v3_parameters.json").read_text())


def test_params_copy_matches_shared():
    shared = paths.models_dir().parent.parent / "shared" / "digit" / "digit_v3_parameters.json"
    if not shared.is_file():
        pytest.skip("shared/digit not beside the repository")
    assert json.loads(shared.read_text()) == PARAMS


# How far a regenerated model may differ from the committed one, number by number.
#
# Every number in the MJCF is printed with 10 significant digits (modelgen._f). Numbers
# that come from the published figures through a few products and trigonometric calls
# (frames, inertias, rod anchors) can change in the last printed digit when another CPU
# or BLAS rounds one product differently: a relative 1e-9 (plus 1e-12 absolute, for
# values printed near zero) covers one unit in the 10th digit and nothing more.
STRUCTURE_RTOL, STRUCTURE_ATOL = 1e-9, 1e-12
# The stand keyframe is the result of a Newton solve with a finite-difference Jacobian
# and a null-space pull towards the nominal posture (modelgen.solve_stand). It stops when
# the residual is below 1e-13 and the step below 1e-10; the pull converges linearly, so
# where it stops along the constraint manifold depends on the floating-point path: seen
# 1e-9 apart between an Intel and an AMD machine. 1e-6 (m, rad, or quaternion units)
# allows 1,000 times that, and is still a micrometre: far below what the physics or the
# controller resolves, and the keyframe test below checks the committed pose closes every
# loop and puts both soles flat on the floor to 1e-9.
KEYFRAME_ATOL = 1e-6


def _numbers(text: str):
    try:
        return np.array([float(t) for t in text.split()])
    except ValueError:
        return None


def mjcf_differences(a: str, b: str) -> list[str]:
    """What differs between two MJCF texts: elements (tag, order, count), attribute names,
    non-numeric values exactly, numeric values within the tolerances above."""
    import xml.etree.ElementTree as ET

    out = []

    def walk(ea, eb, path):
        here = f"{path}/{ea.tag}" + (f"[{ea.get('name')}]" if ea.get("name") else "")
        if ea.tag != eb.tag:
            out.append(f"{here}: element {ea.tag!r} vs {eb.tag!r}")
            return
        if set(ea.attrib) != set(eb.attrib):
            out.append(f"{here}: attributes {sorted(ea.attrib)} vs {sorted(eb.attrib)}")
        keyframe = ea.tag == "key"
        for k in sorted(set(ea.attrib) & set(eb.attrib)):
            va, vb = ea.attrib[k], eb.attrib[k]
            na, nb = _numbers(va), _numbers(vb)
            if na is None or nb is None:
                if va != vb:
                    out.append(f"{here}@{k}: {va!r} vs {vb!r}")
            elif na.shape != nb.shape:
                out.append(f"{here}@{k}: {na.size} numbers vs {nb.size}")
            else:
                tol = (KEYFRAME_ATOL if keyframe
                       else STRUCTURE_ATOL + STRUCTURE_RTOL * np.maximum(abs(na), abs(nb)))
                bad = np.abs(na - nb) > tol
                if bad.any():
                    i = int(np.argmax(bad))
                    out.append(f"{here}@{k}[{i}]: {na[i]!r} vs {nb[i]!r}")
        ca, cb = list(ea), list(eb)
        if len(ca) != len(cb):
            out.append(f"{here}: {len(ca)} children vs {len(cb)}")
        for x, y in zip(ca, cb):
            walk(x, y, here)

    walk(ET.fromstring(a), ET.fromstring(b), "")
    return out


def test_mjcf_differences_sees_real_changes():
    """The comparison is not vacuous: each kind of real change is reported, a change in
    the last printed digit is not."""
    base = (paths.models_dir() / "digit.xml").read_text()
    assert mjcf_differences(base, base) == []
    key = re.search(r'qpos="([^"]*)"', base)
    vals = key.group(1).split()
    # the keyframe's base height within and beyond its tolerance
    near = base.replace(key.group(0), 'qpos="' + " ".join(
        vals[:2] + [repr(float(vals[2]) + 0.5 * KEYFRAME_ATOL)] + vals[3:]) + '"')
    far = base.replace(key.group(0), 'qpos="' + " ".join(
        vals[:2] + [repr(float(vals[2]) + 2 * KEYFRAME_ATOL)] + vals[3:]) + '"')
    assert mjcf_differences(base, near) == []
    assert len(mjcf_differences(base, far)) == 1
    mass = re.search(r'mass="([1-9][^"]*)"', base)   # a body's mass, not zero
    m = float(mass.group(1))
    for other, changed in ((m * (1 + 0.5e-9), False), (m * (1 + 1e-6), True)):
        text = base.replace(mass.group(0), f'mass="{other!r}"', 1)
        assert bool(mjcf_differences(base, text)) == changed, other
    # a joint removed, an attribute added, a non-numeric value changed
    joint = re.search(r"\n\s*<joint [^>]*/>", base).group(0)
    assert mjcf_differences(base, base.replace(joint, "", 1))
    assert mjcf_differences(base, base.replace("<joint ", "<joint user=\"1\" ", 1))
    assert mjcf_differences(base, base.replace('integrator="Euler"', 'integrator="RK4"'))


def test_generator_reproduces_committed_models(tmp_path):
    """Regenerating the models gives the committed files, number by number within the
    tolerances above (not byte for byte: the keyframe comes out of a numerical solve)."""
    modelgen.write_models(PARAMS, tmp_path)
    for name in ("digit.xml", "digit_controller.xml", "scene.xml"):
        diff = mjcf_differences((paths.models_dir() / name).read_text(),
                                (tmp_path / name).read_text())
        assert diff == [], f"{name}: " + "; ".join(diff[:10])


def test_bodies_masses_inertias_joints_actuators(sim_mj):
    m = sim_mj
    assert m.nbody - 1 == len(PARAMS["bodies"]) == 41
    total = sum(b["inertial"]["mass"] for b in PARAMS["bodies"] if "inertial" in b)
    assert m.body_mass.sum() == pytest.approx(total, abs=1e-9)
    for b in PARAMS["bodies"]:
        bid = m.body(b["name"]).id
        if "inertial" in b:
            assert m.body_mass[bid] == pytest.approx(b["inertial"]["mass"], abs=1e-12)
            ixx, iyy, izz, ixy, ixz, iyz = b["inertial"]["fullinertia"]
            full = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
            r = np.zeros(9)
            mujoco.mju_quat2Mat(r, m.body_iquat[bid])
            r = r.reshape(3, 3)
            np.testing.assert_allclose(r @ np.diag(m.body_inertia[bid]) @ r.T, full, atol=1e-9)
            np.testing.assert_allclose(m.body_ipos[bid], b["inertial"]["pos"], atol=1e-12)
        j = b.get("joint")
        if j and j["type"] == "hinge":
            jid = m.joint(j["name"]).id
            np.testing.assert_allclose(m.jnt_axis[jid], j["axis"], atol=1e-12)
            assert m.jnt_stiffness[jid] == j["stiffness"]
            assert m.dof_damping[m.jnt_dofadr[jid]] == j["damping"]
            assert m.dof_armature[m.jnt_dofadr[jid]] == j["armature"]
            assert m.dof_frictionloss[m.jnt_dofadr[jid]] == j["frictionloss"]
            if j.get("range_deg"):
                np.testing.assert_allclose(np.rad2deg(m.jnt_range[jid]), j["range_deg"], atol=1e-9)
            else:
                assert not m.jnt_limited[jid]
    types = np.bincount(m.jnt_type, minlength=4)
    assert (types[mujoco.mjtJoint.mjJNT_FREE], types[mujoco.mjtJoint.mjJNT_BALL],
            types[mujoco.mjtJoint.mjJNT_HINGE]) == (1, 6, 30)
    assert m.neq == 6 and m.nu == 20
    for a in PARAMS["actuators"]:
        aid = m.actuator(a["name"]).id
        assert m.actuator_gear[aid, 0] == a["gear"]
        assert m.actuator_gear[aid, 0] * m.actuator_ctrlrange[aid, 1] == pytest.approx(
            a["joint_torque_limit"], rel=1e-6)


def test_stand_keyframe_closed_flat_and_on_the_floor(sim_mj, ctrl_mj, rm):
    d = mujoco.MjData(sim_mj)
    mujoco.mj_resetDataKeyframe(sim_mj, d, sim_mj.key("stand").id)
    mujoco.mj_forward(sim_mj, d)
    assert sim_loop_residual(sim_mj, d) < 1e-9
    eq_rows = d.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY
    assert eq_rows.sum() == 18 and np.abs(d.efc_pos[eq_rows]).max() < 1e-9
    for side in ("left", "right"):
        s = sim_mj.site(f"{side}-sole").id
        assert abs(d.site_xpos[s][2]) < 1e-9
        np.testing.assert_allclose(d.site_xmat[s].reshape(3, 3)[:, 2], [0, 0, 1], atol=1e-9)
    # The controller's chain constraints hold at the same pose.
    sm = statemap.build_state_map(sim_mj, ctrl_mj)
    q, _ = sm.to_controller(d.qpos, d.qvel)
    np.testing.assert_allclose(q, ctrl_mj.key_qpos[0], atol=0)
    assert np.abs(np.asarray(chains.chain_residual(rm, jnp.asarray(q)))).max() < 1e-9
    # Near the nominal posture: every regularised joint within 0.2 rad.
    nominal = modelgen.nominal_posture()
    for name, val in nominal.items():
        assert abs(d.qpos[sim_mj.joint(name).qposadr[0]] - val) < 0.2, name


def test_collision_filter_only_soles_on_floor_and_leg_on_leg(sim_mj):
    m = sim_mj
    side = {}
    for g in range(m.ngeom):
        if m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0:
            continue
        body = m.body(m.geom_bodyid[g]).name
        side[g] = "floor" if m.geom(g).name == "floor" else body.split("-")[0]
    pairs = set()
    for a in side:
        for b in side:
            if a < b and ((m.geom_contype[a] & m.geom_conaffinity[b])
                          or (m.geom_contype[b] & m.geom_conaffinity[a])):
                pairs.add((m.geom(a).name, m.geom(b).name))
                assert side[a] != side[b], (m.geom(a).name, m.geom(b).name)
    assert ("left-sole", "floor") in pairs or ("floor", "left-sole") in pairs
    leg = [p for p in pairs if "floor" not in p]
    assert len(leg) == 9  # shin, tarsus, toe capsules of one leg x the other's
    supported = {int(mujoco.mjtGeom.mjGEOM_CAPSULE), int(mujoco.mjtGeom.mjGEOM_BOX),
                 int(mujoco.mjtGeom.mjGEOM_PLANE)}
    assert all(int(m.geom_type[m.geom(n).id]) in supported for p in pairs for n in p)


def test_model_loads_in_mjx(sim_mj):
    from safewbc_jax.sim.mjx.imports import import_mjx

    mjx = import_mjx()
    mx = mjx.put_model(sim_mj)
    assert mx.nv == sim_mj.nv


def test_state_map_and_ctrl_scaling(sim_mj, ctrl_mj):
    sm = statemap.build_state_map(sim_mj, ctrl_mj)
    assert sm.qpos_idx.shape == (ctrl_mj.nq,) and sm.qvel_idx.shape == (ctrl_mj.nv,)
    u = np.arange(1.0, 21.0)
    ctrl = sm.to_ctrl(u)
    for a in range(sim_mj.nu):
        ac = ctrl_mj.actuator(sim_mj.actuator(a).name).id
        assert ctrl[a] * sim_mj.actuator_gear[a, 0] == pytest.approx(u[ac])


def test_model_info_cli_json():
    out = subprocess.run([sys.executable, "-m", "safewbc_jax.app.cli", "model-info", "--json"],
                         capture_output=True, text=True, check=True)
    info = json.loads(out.stdout.strip().splitlines()[-1])
    for key in ("sim_nq", "sim_nv", "ctrl_nv", "nu", "mass_kg", "loop_residual_m", "foot_height_m"):
        assert key in info
    assert info == json.loads(json.dumps(model_info()))
    assert (info["sim_nq"], info["sim_nv"], info["ctrl_nv"], info["nu"]) == (61, 54, 36, 20)
    assert info["loop_residual_m"] < 1e-9 and max(map(abs, info["foot_height_m"])) < 1e-9
