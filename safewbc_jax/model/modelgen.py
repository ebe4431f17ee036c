"""Write the Digit MJCF models from the published figures.

``python -m safewbc_jax.model.modelgen`` regenerates ``models/digit.xml`` (the simulation
model: rods on ball joints closed by equality constraints, compliant springs, collision
shapes MJX supports) and ``models/digit_controller.xml`` (the controller's tree: floating
base and the 30 hinges, rods left out) from ``digit_v3_parameters.json``, and solves the
``stand`` keyframe: both soles flat on the floor, every loop closed, the CoM over the
middle of the soles at ``STAND_COM_HEIGHT``, as near the nominal posture as those allow.

The figures file is looked up in ``$SAFEWBC_DIGIT_PARAMS``, then ``../shared/digit/`` next
to the repository, then the copy kept in ``models/``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
MODELS = REPO / "models"

# Collision filtering bits (contype/conaffinity): the floor touches only the soles, the
# lower legs of one side touch only the lower legs of the other side.
_FLOOR, _LEFT, _RIGHT = 1, 2, 4

# Lower-leg bodies that get leg-on-leg collision capsules (per side, name suffix).
LEG_COLLISION_BODIES = ("shin", "tarsus", "toe-roll")

# Simulation options. See ../shared/digit/README.md (the batch-256 hang): implicit Euler
# damping off, no damping and a small armature on the rod ball joints keep the batched
# XLA CPU step from hanging at batch 256.
SIM_TIMESTEP = 0.001
SIM_SOLVER_ITERATIONS = 4
SIM_LS_ITERATIONS = 8
ROD_BALL_ARMATURE = 1e-4
ROD_BALL_DAMPING = 0.0
LOOP_SOLREF = (0.002, 1.0)

# Nominal standing posture of public code (left side; the right side mirrors it with
# opposite signs). toe-A/toe-B and the springs are not regularised.
NOMINAL_LEFT = {
    "hip-roll": 0.31, "hip-yaw": 0.0, "hip-pitch": 0.2, "knee": 0.19, "shin": 0.0,
    "tarsus": 0.0, "toe-pitch": -0.126, "toe-roll": 0.0, "shoulder-roll": -0.15,
    "shoulder-pitch": 1.1, "shoulder-yaw": 0.0, "elbow": -0.145,
}
# CoM height of the stand keyframe (m): the nominal posture's knee angle gives about this
# height, which is also the bowing scenario's CoM reference.
STAND_COM_HEIGHT = 0.95
ARM_JOINTS = ("shoulder-roll", "shoulder-pitch", "shoulder-yaw", "elbow")
SPRING_JOINTS = ("shin", "heel-spring")


def find_params_file() -> Path:
    """Locate ``digit_v3_parameters.json`` (see the module docstring)."""
    env = os.environ.get("SAFEWBC_DIGIT_PARAMS")
    candidates = [Path(env)] if env else []
    candidates += [REPO.parent / "shared" / "digit" / "digit_v3_parameters.json",
                   MODELS / "digit_v3_parameters.json"]
    try:   # an installed package keeps its copy in safewbc_jax/models
        from safewbc_jax.base import paths

        candidates.append(paths.figures_json())
    except FileNotFoundError:
        pass
    for c in candidates:
        if c.is_file():
            return c
    raise FileNotFoundError(
        "digit_v3_parameters.json not found; looked in: " + ", ".join(map(str, candidates)))


def load_params(path: Path | None = None) -> dict:
    return json.loads((path or find_params_file()).read_text())


def nominal_posture() -> dict[str, float]:
    """Nominal joint angles (rad) for both sides, keyed by joint name."""
    out = {}
    for j, val in NOMINAL_LEFT.items():
        out[f"left-{j}"] = val
        out[f"right-{j}"] = -val if val != 0.0 else 0.0
    return out


def _f(x) -> str:
    return " ".join(f"{float(v):.10g}" for v in np.atleast_1d(x))


def _rot_xyz(euler_deg) -> np.ndarray:
    """Rotation matrix of intrinsic x-y-z Euler angles in degrees (MJCF eulerseq='xyz')."""
    a, b, c = np.deg2rad(euler_deg)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    rz = np.array([[np.cos(c), -np.sin(c), 0], [np.sin(c), np.cos(c), 0], [0, 0, 1]])
    return rx @ ry @ rz


def _is_rod(body: dict) -> bool:
    return body.get("joint", {}).get("type") == "ball"


def _side(name: str) -> int:
    return _LEFT if name.startswith("left-") else _RIGHT


def _sole_box(params: dict, foot: dict) -> dict:
    parent = next(b for b in params["bodies"] if b["name"] == foot["parent"])
    return next(c for c in parent["collision_primitives"] if c["type"] == "box")


def sole_site_in_foot(params: dict, foot: dict) -> np.ndarray:
    """Centre of the sole box's bottom face in the foot frame (the foot frame's z axis is
    the box's normal, pointing into the foot)."""
    box = _sole_box(params, foot)
    rbox = _rot_xyz(box["euler_deg"])
    bottom = np.asarray(box["pos"]) - box["size"][2] * rbox[:, 2]
    rfoot = _rot_xyz(foot["euler_deg"])
    return rfoot.T @ (bottom - np.asarray(foot["pos"]))


def _geoms_xml(params: dict, body: dict, sim: bool, ind: str) -> list[str]:
    """Visual primitives (no collision) and, in the simulation model, collision shapes."""
    lines = []
    for c in body.get("collision_primitives", []):
        kind = c["type"]
        size = c["size"]
        lines.append(f'{ind}<geom class="visual" type="{kind}" size="{_f(size)}" '
                     f'pos="{_f(c["pos"])}" euler="{_f(c["euler_deg"])}"/>')
    name = body["name"]
    if not sim or "-" not in name:
        return lines
    suffix = name.split("-", 1)[1]
    side = _side(name)
    other = _RIGHT if side == _LEFT else _LEFT
    if suffix in ("shin", "tarsus"):
        prim = [c for c in body["collision_primitives"] if c["type"] in ("cylinder", "capsule")
                and abs(c["euler_deg"][1] - 90.0) < 1e-9][0]
        lines.append(f'{ind}<geom name="{name}-collision" class="leg" type="capsule" '
                     f'size="{_f(prim["size"])}" pos="{_f(prim["pos"])}" '
                     f'euler="{_f(prim["euler_deg"])}" contype="{side}" conaffinity="{other}"/>')
    if suffix == "toe-roll":
        box = _sole_box(params, {"parent": name})
        rbox = _rot_xyz(box["euler_deg"])
        centre = np.asarray(box["pos"])
        half = box["size"][1] - 0.03
        a, b = centre - half * rbox[:, 1], centre + half * rbox[:, 1]
        lines.append(f'{ind}<geom name="{name}-collision" class="leg" type="capsule" size="0.03" '
                     f'fromto="{_f(a)} {_f(b)}" contype="{side}" conaffinity="{other}"/>')
        lines.append(f'{ind}<geom name="{name.rsplit("-", 2)[0]}-sole" class="sole" type="box" '
                     f'size="{_f(box["size"])}" pos="{_f(box["pos"])}" '
                     f'euler="{_f(box["euler_deg"])}" contype="{_FLOOR}" conaffinity="0"/>')
    return lines


def _chain_sites(params: dict, rod_tips: dict | None) -> dict[str, list[tuple[str, np.ndarray]]]:
    """Sites that mark the closed chains: ``<rod>-anchor`` (anchor_in_body1 on body1),
    ``<rod>-ball`` (the rod's ball-joint centre, on the rod's parent) and, in the simulation
    model, ``<rod>-tip`` (the rod point that meets the anchor)."""
    bodies = {b["name"]: b for b in params["bodies"]}
    out: dict[str, list] = {}
    for lc in params["loop_closures"]:
        rod = bodies[lc["body2"]]
        out.setdefault(lc["body1"], []).append((f'{lc["name"]}-anchor', lc["anchor_in_body1"]))
        out.setdefault(rod["parent"], []).append((f'{lc["name"]}-ball', rod["pos"]))
        if rod_tips is not None:
            out.setdefault(rod["name"], []).append((f'{lc["name"]}-tip', rod_tips[lc["name"]]))
    return out


def _body_xml(params: dict, body: dict, children: dict, sim: bool, depth: int,
              sites: dict) -> list[str]:
    ind = "  " * depth
    name = body["name"]
    pos = body["pos"] if body["parent"] is not None else [0.0, 0.0, 1.0]
    lines = [f'{ind}<body name="{name}" pos="{_f(pos)}" euler="{_f(body["euler_deg"])}">']
    ind2 = ind + "  "
    if "inertial" in body:
        inr = body["inertial"]
        lines.append(f'{ind2}<inertial pos="{_f(inr["pos"])}" mass="{inr["mass"]!r}" '
                     f'fullinertia="{_f(inr["fullinertia"])}"/>')
    j = body.get("joint")
    if j is not None:
        if j["type"] == "free":
            lines.append(f'{ind2}<freejoint name="base"/>')
        elif j["type"] == "hinge":
            rng = (f'range="{_f(j["range_deg"])}" limited="true"' if j.get("range_deg")
                   else 'limited="false"')
            lines.append(f'{ind2}<joint name="{j["name"]}" type="hinge" axis="{_f(j["axis"])}" '
                         f'{rng} stiffness="{j["stiffness"]!r}" damping="{j["damping"]!r}" '
                         f'armature="{j["armature"]!r}" frictionloss="{j["frictionloss"]!r}"/>')
        elif j["type"] == "ball":
            lines.append(f'{ind2}<joint name="{name}-ball" type="ball" '
                         f'damping="{ROD_BALL_DAMPING!r}" armature="{ROD_BALL_ARMATURE!r}"/>')
    lines += _geoms_xml(params, body, sim, ind2)
    if name == "base":
        lines.append(f'{ind2}<site name="torso" pos="0 0 0" size="0.02"/>')
    if name.endswith("-foot"):
        side = name.rsplit("-", 1)[0]
        lines.append(f'{ind2}<site name="{side}-sole" pos="{_f(sole_site_in_foot(params, body))}" '
                     f'size="0.01"/>')
    if name.endswith("-hand"):
        side = name.rsplit("-", 1)[0]
        lines.append(f'{ind2}<site name="{side}-fist" pos="0 0 0" size="0.015"/>')
    for sname, spos in sites.get(name, []):
        lines.append(f'{ind2}<site name="{sname}" pos="{_f(spos)}" size="0.005" group="4"/>')
    for child in children.get(name, []):
        if _is_rod(child) and not sim:
            continue
        lines += _body_xml(params, child, children, sim, depth + 1, sites)
    lines.append(f"{ind}</body>")
    return lines


def model_xml(params: dict, sim: bool, keyframe: dict | None = None,
              rod_tips: dict | None = None) -> str:
    """MJCF text of the simulation model (``sim=True``) or the controller's tree."""
    children: dict[str | None, list] = {}
    for b in params["bodies"]:
        children.setdefault(b["parent"], []).append(b)
    root = children[None][0]
    title = "simulation model" if sim else "controller model (rods left out)"
    out = [f'<mujoco model="digit-v3-{"sim" if sim else "controller"}">',
           f"  <!-- Digit v3 {title}: written by safewbc_jax.model.modelgen from the published",
           "       figures in digit_v3_parameters.json. Do not edit by hand. -->",
           '  <compiler angle="degree" eulerseq="xyz" autolimits="true"/>']
    if sim:
        out += [f'  <option timestep="{SIM_TIMESTEP}" integrator="Euler" solver="Newton" '
                f'iterations="{SIM_SOLVER_ITERATIONS}" ls_iterations="{SIM_LS_ITERATIONS}" '
                'cone="pyramidal">',
                '    <flag eulerdamp="disable"/>',
                "  </option>"]
    out += ["  <default>",
            '    <default class="visual"><geom contype="0" conaffinity="0" group="1" '
            'rgba="0.55 0.55 0.6 1" mass="0"/></default>',
            '    <default class="leg"><geom group="3" rgba="0.9 0.4 0.2 0.4" mass="0" '
            'condim="3"/></default>',
            '    <default class="sole"><geom group="3" rgba="0.2 0.4 0.9 0.6" mass="0" '
            'condim="3" friction="1 0.02 0.0001"/></default>',
            "  </default>",
            "  <worldbody>"]
    out += _body_xml(params, root, children, sim, 2,
                     _chain_sites(params, rod_tips if sim else None))
    out.append("  </worldbody>")
    if sim:
        out.append("  <equality>")
        for lc in params["loop_closures"]:
            out.append(f'    <connect name="{lc["name"]}" body1="{lc["body1"]}" '
                       f'body2="{lc["body2"]}" anchor="{_f(lc["anchor_in_body1"])}" '
                       f'solref="{_f(LOOP_SOLREF)}"/>')
        out.append("  </equality>")
    out.append("  <actuator>")
    for a in params["actuators"]:
        out.append(f'    <motor name="{a["name"]}" joint="{a["joint"]}" gear="{a["gear"]!r}" '
                   f'ctrlrange="{_f([-a["motor_torque_limit"], a["motor_torque_limit"]])}"/>')
    out.append("  </actuator>")
    if keyframe is not None:
        out += ["  <keyframe>",
                f'    <key name="stand" qpos="{_f(keyframe["qpos"])}"/>',
                "  </keyframe>"]
    out.append("</mujoco>")
    return "\n".join(out) + "\n"


SCENE_XML = """<mujoco model="digit-v3-scene">
  <!-- The simulation model on a floor. Written by safewbc_jax.model.modelgen. -->
  <include file="digit.xml"/>
  <statistic center="0 0 0.8" extent="1.8"/>
  <visual>
    <headlight diffuse="0.6 0.6 0.6" ambient="0.3 0.3 0.3" specular="0 0 0"/>
    <global azimuth="150" elevation="-15"/>
  </visual>
  <asset>
    <texture type="2d" name="grid" builtin="checker" rgb1="0.25 0.3 0.35" rgb2="0.3 0.35 0.4"
             width="300" height="300" mark="edge" markrgb="0.2 0.2 0.2"/>
    <material name="grid" texture="grid" texrepeat="8 8" reflectance="0.1"/>
  </asset>
  <worldbody>
    <light pos="0 0 4" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="0 0 0.05" material="grid" contype="0" conaffinity="1"
          friction="1 0.02 0.0001"/>
  </worldbody>
</mujoco>
"""


# --------------------------------------------------------------------------------------
# The stand keyframe
# --------------------------------------------------------------------------------------

def _quat_from_two_vectors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation (w, x, y, z) taking direction a to direction b."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    w = 1.0 + a @ b
    q = np.concatenate([[w], np.cross(a, b)])
    return q / np.linalg.norm(q)


def _stand_residual(m, d, mujoco, chains, free_idx, x, q0, ids):
    qpos = q0.copy()
    qpos[free_idx] = x
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    mujoco.mj_comPos(m, d)
    res = []
    for b1, a1, b2p, p2, length in chains:
        pa = d.xpos[b1] + d.xmat[b1].reshape(3, 3) @ a1
        pb = d.xpos[b2p] + d.xmat[b2p].reshape(3, 3) @ p2
        res.append(np.linalg.norm(pa - pb) - length)
    soles = []
    for s in ids["soles"]:
        r = d.site_xmat[s].reshape(3, 3)
        p = d.site_xpos[s]
        res += [p[2], r[0, 2], r[1, 2], r[1, 0]]
        soles.append(p)
    com = d.subtree_com[ids["base"]]
    mid = 0.5 * (soles[0] + soles[1])
    res += [com[0] - mid[0], com[1] - mid[1], com[2] - STAND_COM_HEIGHT]
    return np.asarray(res), qpos


def controller_chains(m, params: dict):
    """The rods as (body1 id, anchor in body1, rod parent id, ball centre in rod parent,
    length) for a model without rod bodies. The length is the anchor distance in the zero
    configuration, where the published loops close."""
    import mujoco

    bodies = {b["name"]: b for b in params["bodies"]}
    d = mujoco.MjData(m)
    d.qpos[:] = 0.0
    d.qpos[3] = 1.0
    mujoco.mj_kinematics(m, d)
    out = []
    for lc in params["loop_closures"]:
        rod = bodies[lc["body2"]]
        b1 = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, lc["body1"])
        bp = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, rod["parent"])
        a1 = np.asarray(lc["anchor_in_body1"], float)
        p2 = np.asarray(rod["pos"], float)
        pa = d.xpos[b1] + d.xmat[b1].reshape(3, 3) @ a1
        pb = d.xpos[bp] + d.xmat[bp].reshape(3, 3) @ p2
        out.append((b1, a1, bp, p2, float(np.linalg.norm(pa - pb))))
    return out


def solve_stand(params: dict, tol: float = 1e-13, max_iter: int = 200) -> dict:
    """Solve the stand pose on the controller tree, then close the rods of the simulation
    model by turning each ball joint. Returns qpos of both models."""
    import mujoco

    mc = mujoco.MjModel.from_xml_string(model_xml(params, sim=False))
    dc = mujoco.MjData(mc)
    nominal = nominal_posture()
    jnames = [mujoco.mj_id2name(mc, mujoco.mjtObj.mjOBJ_JOINT, j) for j in range(mc.njnt)]
    q0 = np.zeros(mc.nq)
    q0[3] = 1.0
    for j, name in enumerate(jnames):
        if name in nominal:
            q0[mc.jnt_qposadr[j]] = nominal[name]
    # Unknowns: base height and the leg hinges except the springs (held at 0).
    free_idx = [2] + [int(mc.jnt_qposadr[j]) for j, n in enumerate(jnames)
                      if j > 0 and not any(n.endswith(s) for s in ARM_JOINTS + SPRING_JOINTS)]
    weight = np.array([0.0] + [1.0 if jnames[i] in nominal else 0.0 for i in
                               [list(mc.jnt_qposadr).index(k) for k in free_idx[1:]]])
    q0[2] = 1.0
    ids = {"soles": [mujoco.mj_name2id(mc, mujoco.mjtObj.mjOBJ_SITE, f"{s}-sole")
                     for s in ("left", "right")],
           "base": mujoco.mj_name2id(mc, mujoco.mjtObj.mjOBJ_BODY, "base")}
    chains = controller_chains(mc, params)
    x = q0[free_idx].copy()
    x_nom = x.copy()
    for _ in range(max_iter):
        r, _ = _stand_residual(mc, dc, mujoco, chains, free_idx, x, q0, ids)
        eps = 1e-7
        jac = np.empty((r.size, x.size))
        for k in range(x.size):
            xp, xm = x.copy(), x.copy()
            xp[k] += eps
            xm[k] -= eps
            rp = _stand_residual(mc, dc, mujoco, chains, free_idx, xp, q0, ids)[0]
            rm = _stand_residual(mc, dc, mujoco, chains, free_idx, xm, q0, ids)[0]
            jac[:, k] = (rp - rm) / (2 * eps)
        pinv = np.linalg.pinv(jac)
        null = np.eye(x.size) - pinv @ jac
        step = -pinv @ r + null @ (weight * (x_nom - x))
        x = x + step
        if np.max(np.abs(r)) < tol and np.max(np.abs(step)) < 1e-10:
            break
    r, qc = _stand_residual(mc, dc, mujoco, chains, free_idx, x, q0, ids)
    if np.max(np.abs(r)) > 1e-11:
        raise RuntimeError(f"stand keyframe did not converge: max residual {np.max(np.abs(r)):.3e}")

    # Simulation model: same free joint and hinges, rods turned to close the loops.
    ms = mujoco.MjModel.from_xml_string(model_xml(params, sim=True))
    ds = mujoco.MjData(ms)
    qs = np.zeros(ms.nq)
    for j in range(ms.njnt):
        name = mujoco.mj_id2name(ms, mujoco.mjtObj.mjOBJ_JOINT, j)
        adr = ms.jnt_qposadr[j]
        if ms.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            qs[adr:adr + 4] = [1, 0, 0, 0]
        else:
            jc = mujoco.mj_name2id(mc, mujoco.mjtObj.mjOBJ_JOINT, name)
            n = 7 if ms.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE else 1
            qs[adr:adr + n] = qc[mc.jnt_qposadr[jc]:mc.jnt_qposadr[jc] + n]
    # The rod's anchor is the rod point that meets anchor_in_body1 in the zero
    # configuration (as MuJoCo's connect constraint defines it), not the rounded
    # published anchor_in_body2, which is off by up to ~1e-6 m.
    anchor2 = {}
    ds.qpos[:] = ms.qpos0
    mujoco.mj_kinematics(ms, ds)
    for lc in params["loop_closures"]:
        b1 = mujoco.mj_name2id(ms, mujoco.mjtObj.mjOBJ_BODY, lc["body1"])
        rod = mujoco.mj_name2id(ms, mujoco.mjtObj.mjOBJ_BODY, lc["body2"])
        pa = ds.xpos[b1] + ds.xmat[b1].reshape(3, 3) @ np.asarray(lc["anchor_in_body1"])
        anchor2[lc["name"]] = ds.xmat[rod].reshape(3, 3).T @ (pa - ds.xpos[rod])
    ds.qpos[:] = qs
    mujoco.mj_kinematics(ms, ds)
    for lc in params["loop_closures"]:
        b1 = mujoco.mj_name2id(ms, mujoco.mjtObj.mjOBJ_BODY, lc["body1"])
        rod = mujoco.mj_name2id(ms, mujoco.mjtObj.mjOBJ_BODY, lc["body2"])
        jnt = ms.body_jntadr[rod]
        pa = ds.xpos[b1] + ds.xmat[b1].reshape(3, 3) @ np.asarray(lc["anchor_in_body1"])
        r0 = ds.xmat[rod].reshape(3, 3)  # ball at identity
        target = r0.T @ (pa - ds.xpos[rod])
        adr = ms.jnt_qposadr[jnt]
        qs[adr:adr + 4] = _quat_from_two_vectors(anchor2[lc["name"]], target)
    return {"sim_qpos": qs, "ctrl_qpos": qc, "rod_tips": anchor2}


def write_models(params: dict | None = None, out_dir: Path = MODELS) -> dict:
    """Write digit.xml, digit_controller.xml and scene.xml; return the stand poses."""
    params = params or load_params()
    stand = solve_stand(params)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "digit.xml").write_text(
        model_xml(params, True, {"qpos": stand["sim_qpos"]}, stand["rod_tips"]))
    (out_dir / "digit_controller.xml").write_text(
        model_xml(params, False, {"qpos": stand["ctrl_qpos"]}))
    (out_dir / "scene.xml").write_text(SCENE_XML)
    return stand


if __name__ == "__main__":
    s = write_models()
    print("wrote", MODELS, "stand base height", s["ctrl_qpos"][2])
