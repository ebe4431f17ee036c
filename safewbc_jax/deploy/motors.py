"""The robot's motors: joint torques in the controller's actuator order to motor torques in
the robot's motor order, from the controller model and the published figures
(``models/digit_v3_parameters.json``), not from a simulator."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from safewbc_jax.base import paths
from safewbc_jax.control.step import MotorArrays


@dataclasses.dataclass(frozen=True)
class MotorMap:
    """The robot's motors in its motor order (``actuators`` of the published figures):
    name, index of each motor's joint torque in u, gear ratio, joint-side torque limit."""

    names: tuple
    u_index: np.ndarray
    gear: np.ndarray
    joint_limit: np.ndarray      # N m, joint side
    motor_limit: np.ndarray      # N m, motor side (published motor_torque_limit)

    @classmethod
    def build(cls, ctrl_model=None, figures: dict | None = None) -> "MotorMap":
        """From the controller MjModel (``paths.controller_xml()``) and the published
        figures the models were written from (``paths.figures_json()``, installed with the
        package); raises ValueError where the two disagree."""
        import json

        import mujoco

        mc = (mujoco.MjModel.from_xml_path(str(paths.controller_xml())) if ctrl_model is None
              else ctrl_model)
        if figures is None:
            figures = json.loads(paths.figures_json().read_text())
        acts = figures["actuators"]
        idx = []
        for a in acts:
            i = mujoco.mj_name2id(mc, mujoco.mjtObj.mjOBJ_ACTUATOR, a["name"])
            if i < 0 or mc.joint(int(mc.actuator_trnid[i, 0])).name != a["joint"]:
                raise ValueError(f"motor {a['name']!r} (joint {a['joint']!r}) is not an "
                                 "actuator of the controller model on that joint")
            if not np.isclose(mc.actuator_gear[i, 0], a["gear"], rtol=1e-9):
                raise ValueError(f"motor {a['name']!r}: gear {a['gear']} published, "
                                 f"{mc.actuator_gear[i, 0]} in the controller model")
            idx.append(i)
        if sorted(idx) != list(range(mc.nu)):
            raise ValueError("the published motors do not cover the controller's actuators")
        f = lambda k: np.array([float(a[k]) for a in acts])  # noqa: E731
        gear, lim_j, lim_m = f("gear"), f("joint_torque_limit"), f("motor_torque_limit")
        if not np.allclose(lim_m * gear, lim_j, rtol=1e-9):
            raise ValueError("published motor torque limit x gear != joint torque limit")
        return cls(tuple(a["name"] for a in acts), np.array(idx), gear, lim_j, lim_m)

    def arrays(self) -> MotorArrays:
        return self._arrays

    @functools.cached_property
    def _arrays(self) -> MotorArrays:
        return MotorArrays(self.u_index, self.gear, self.motor_limit)

    def to_motor(self, u) -> np.ndarray:
        """Joint torques u (controller actuator order) -> motor torques u / gear, in motor
        order, clipped to the motor limits (``MotorArrays.to_motor``)."""
        return self._arrays.to_motor(np.asarray(u, float))
