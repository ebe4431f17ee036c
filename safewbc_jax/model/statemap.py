"""The explicit map from the simulator's state to the controller's, and back for commands.

The simulator (models/digit.xml) has the rods on ball joints (nq = 61, nv = 54); the
controller model has the floating base and the 30 hinges only (nq = 37, nv = 36). The
controller reads (q, v) by picking the free joint and the hinges by name, as it would read
a real robot's estimator; it commands the 20 motors with ctrl = u / gear (u: joint torque).
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class StateMap:
    """Index arrays: controller q = qpos[qpos_idx], v = qvel[qvel_idx]; simulator actuator
    a drives controller actuator ``act_idx[a]``."""

    qpos_idx: np.ndarray
    qvel_idx: np.ndarray
    act_idx: np.ndarray
    gear: np.ndarray

    def to_controller(self, qpos, qvel):
        """(qpos, qvel) of the simulator -> (q, v) of the controller (numpy or JAX)."""
        return qpos[..., self.qpos_idx], qvel[..., self.qvel_idx]

    def to_ctrl(self, u):
        """Controller joint torques u (N m, controller actuator order) -> simulator motor
        commands (motor torque, simulator actuator order)."""
        return u[..., self.act_idx] / self.gear


def build_state_map(sim_model, ctrl_model) -> StateMap:
    """Match joints and actuators of the two MuJoCo models by name."""
    import mujoco

    qpos_idx: list[int] = []
    qvel_idx: list[int] = []
    for j in range(ctrl_model.njnt):
        name = ctrl_model.joint(j).name
        js = mujoco.mj_name2id(sim_model, mujoco.mjtObj.mjOBJ_JOINT, name)
        if js < 0:
            raise ValueError(f"controller joint {name!r} is not in the simulation model")
        if sim_model.jnt_type[js] != ctrl_model.jnt_type[j]:
            raise ValueError(f"joint {name!r} has different types in the two models")
        nq = {0: 7, 3: 1}[int(ctrl_model.jnt_type[j])]
        nv = {0: 6, 3: 1}[int(ctrl_model.jnt_type[j])]
        if ctrl_model.jnt_qposadr[j] != len(qpos_idx):
            raise ValueError("controller joints must be listed in qpos order")
        qpos_idx += list(range(sim_model.jnt_qposadr[js], sim_model.jnt_qposadr[js] + nq))
        qvel_idx += list(range(sim_model.jnt_dofadr[js], sim_model.jnt_dofadr[js] + nv))
    act_idx = []
    for a in range(sim_model.nu):
        name = sim_model.actuator(a).name
        ac = mujoco.mj_name2id(ctrl_model, mujoco.mjtObj.mjOBJ_ACTUATOR, name)
        if ac < 0:
            raise ValueError(f"simulator actuator {name!r} is not in the controller model")
        act_idx.append(ac)
    return StateMap(np.array(qpos_idx), np.array(qvel_idx), np.array(act_idx),
                    sim_model.actuator_gear[:, 0].copy())


def load_stand():
    """(simulation MjModel, controller MjModel, StateMap, MjData at the simulation model's
    "stand" keyframe, forward kinematics done)."""
    import mujoco

    from safewbc_jax.base import paths

    ms = mujoco.MjModel.from_xml_path(str(paths.scene_xml()))
    mc = mujoco.MjModel.from_xml_path(str(paths.controller_xml()))
    d = mujoco.MjData(ms)
    mujoco.mj_resetDataKeyframe(ms, d, ms.key("stand").id)
    mujoco.mj_forward(ms, d)
    return ms, mc, build_state_map(ms, mc), d
