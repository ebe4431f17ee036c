"""Facts about the two Digit models at the ``stand`` keyframe (``safewbc model-info``)."""

from __future__ import annotations

import numpy as np

from safewbc_jax.model import digit


def model_info() -> dict:
    """Sizes, masses, loop residual and foot heights at ``stand``, torque limits."""
    import mujoco

    from safewbc_jax.base import paths

    ms = mujoco.MjModel.from_xml_path(str(paths.scene_xml()))
    mc = mujoco.MjModel.from_xml_path(str(paths.controller_xml()))
    d = mujoco.MjData(ms)
    mujoco.mj_resetDataKeyframe(ms, d, ms.key("stand").id)
    mujoco.mj_forward(ms, d)
    return {
        "sim_nq": int(ms.nq), "sim_nv": int(ms.nv), "sim_nbody": int(ms.nbody - 1),
        "ctrl_nq": int(mc.nq), "ctrl_nv": int(mc.nv), "nu": int(ms.nu),
        "mass_kg": float(ms.body_mass.sum()), "ctrl_mass_kg": float(mc.body_mass.sum()),
        "loop_residual_m": sim_loop_residual(ms, d),
        "foot_height_m": [float(d.site_xpos[ms.site(digit.sole(s)).id][2])
                          for s in digit.SIDES],
        "com_height_m": float(d.subtree_com[ms.body(digit.BASE).id][2]),
        "timestep_s": float(ms.opt.timestep),
        "torque_limit_Nm": {ms.actuator(a).name:
                            float(ms.actuator_gear[a, 0] * ms.actuator_ctrlrange[a, 1])
                            for a in range(ms.nu)},
    }


def loop_site_pairs(ms) -> tuple[np.ndarray, np.ndarray]:
    """(tip sites, anchor sites): each rod's tip and the anchor it should meet."""
    tips = [s for s in range(ms.nsite) if ms.site(s).name.endswith("-tip")]
    anchors = [ms.site(ms.site(s).name[:-4] + "-anchor").id for s in tips]
    return np.array(tips, int), np.array(anchors, int)


def foot_contact_ids(ms) -> dict:
    """Ids of what the walking gait and the leg-collision metric read from the simulator:
    ``sole_sites`` and ``sole_geoms`` (left, right), ``floor`` (geom), ``legs`` (2, k):
    the collision geoms of the left and of the right leg."""
    legs = [[g for g in range(ms.ngeom) if ms.geom(g).name.startswith(side)
             and ms.geom(g).name.endswith("-collision")] for side in ("left", "right")]
    if len(legs[0]) != len(legs[1]):
        raise ValueError("the two legs have different numbers of collision geoms")
    return {"sole_sites": np.array([ms.site(digit.sole(s)).id for s in digit.SIDES]),
            "sole_geoms": np.array([ms.geom(digit.sole(s)).id for s in digit.SIDES]),
            "floor": ms.geom("floor").id, "legs": np.array(legs, int)}


def control_substeps(ms, control_dt: float) -> int | None:
    """Simulation steps per control step, or None when ``control_dt`` is not a positive
    multiple of the simulation step."""
    n_sub = int(round(control_dt / ms.opt.timestep))
    if n_sub < 1 or abs(n_sub * ms.opt.timestep - control_dt) > 1e-12:
        return None
    return n_sub


def sim_loop_residual(ms, d, pairs=None) -> float:
    """Largest distance (m) between a rod's tip and the anchor it should meet; ``pairs``
    from ``loop_site_pairs`` (looked up by name when not given)."""
    return float(loop_residual(d.site_xpos, loop_site_pairs(ms) if pairs is None else pairs))


def loop_residual(site_xpos, pairs, xp=np):
    """``sim_loop_residual`` from the sites' world positions (..., nsite, 3); leading axes
    are a batch and stay in the result. ``xp``: numpy or jax.numpy."""
    tips, anchors = pairs
    gap = site_xpos[..., tips, :] - site_xpos[..., anchors, :]
    return xp.sqrt((gap * gap).sum(axis=-1).max(axis=-1))


def format_info(info: dict) -> str:
    lines = [
        f"simulation model : nq={info['sim_nq']} nv={info['sim_nv']} bodies={info['sim_nbody']} "
        f"nu={info['nu']} mass={info['mass_kg']:.3f} kg dt={info['timestep_s']} s",
        f"controller model : nq={info['ctrl_nq']} nv={info['ctrl_nv']} nu={info['nu']} "
        f"mass={info['ctrl_mass_kg']:.3f} kg (rods left out)",
        f"stand keyframe   : loop residual {info['loop_residual_m']:.2e} m, foot heights "
        f"{info['foot_height_m'][0]:.2e} / {info['foot_height_m'][1]:.2e} m, "
        f"CoM height {info['com_height_m']:.3f} m",
        "joint torque limits (N m):",
    ]
    for name, lim in info["torque_limit_Nm"].items():
        lines.append(f"  {name:<22s} {lim:8.2f}")
    return "\n".join(lines)
