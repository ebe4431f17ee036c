"""TSID 1.10's whole-body step on Digit's tree, as the anchor the controller step is timed
against (``benchmarks/controller_step.py``). Optional: ``available()`` is False where TSID is
not installed (``../shared/anchors/README.md`` says how), and nothing else needs it.

The problem is the anchor's (``shared/anchors/README.md``): the controller model's 36-DoF
tree (free joint + 30 hinges; the rods and loop closures are not in it), two ``Contact6d``
on the soles (4 corners of the controller's sole rectangle, mu 0.7, 1-1000 N), CoM,
base (torso site) orientation, joint posture, actuation bounds (motor joints:
gear x ctrlrange; the 10 unactuated hinges wide), solved by ``SolverHQuadProgFast``. One
step = ``computeProblemData`` + ``solve`` + ``getActuatorForces`` on the state given.
TSID is built with OpenMP: set ``OMP_NUM_THREADS=1`` before it is imported.
"""

from __future__ import annotations

import os
import time

import numpy as np


def available() -> bool:
    try:
        import pinocchio  # noqa: F401
        import tsid  # noqa: F401
    except ImportError:
        return False
    return True


class TsidStep:
    """``step(q, v)`` on the controller model's MuJoCo coordinates (q: position, unit
    quaternion w-first, hinges; v: world linear, local angular base velocity, hinge
    rates) -> joint torques of the 30 hinges. References: the CoM, torso orientation and
    posture of the state ``start(q, v)`` was given."""

    def __init__(self, xml: str, sole_length: float, sole_width: float):
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        import mujoco
        import pinocchio as pin
        import tsid

        self.pin, self.tsid = pin, tsid
        self.model = pin.buildModelFromMJCF(xml)
        self.robot = tsid.RobotWrapper(self.model, tsid.FLOATING_BASE_SYSTEM, False)
        mc = mujoco.MjModel.from_xml_path(xml)
        na = self.robot.na
        lo, hi = np.full(na, -1e4), np.full(na, 1e4)    # unactuated hinges: wide bounds
        for a in range(mc.nu):
            jname = mc.joint(int(mc.actuator_trnid[a, 0])).name
            iv = self.model.joints[self.model.getJointId(jname)].idx_v - 6
            g = mc.actuator_gear[a, 0]
            lo[iv], hi[iv] = np.sort(g * mc.actuator_ctrlrange[a])
        self.bounds = (lo, hi)
        hl, hw = 0.5 * sole_length, 0.5 * sole_width
        self.corners = np.array([[hl, hw, 0], [hl, -hw, 0], [-hl, hw, 0], [-hl, -hw, 0]]).T
        self._objects = []      # TSID keeps C++ references only: keep the Python objects

    def to_pin(self, q, v):
        """MuJoCo (q, v) of the tree -> pinocchio's (quaternion x, y, z, w; local base
        linear velocity)."""
        q, v = np.asarray(q, float), np.asarray(v, float)
        w, x, y, z = q[3:7]
        rot = self.pin.Quaternion(w, x, y, z).toRotationMatrix()
        qp = np.concatenate([q[:3], [x, y, z, w], q[7:]])
        vp = np.concatenate([rot.T @ v[:3], v[3:6], v[6:]])
        return qp, vp

    def start(self, q, v):
        tsid = self.tsid
        qp, vp = self.to_pin(q, v)
        form = tsid.InverseDynamicsFormulationAccForce("tsid", self.robot, False)
        form.computeProblemData(0.0, qp, vp)
        data = form.data()
        keep = self._objects
        for side in ("left", "right"):
            c = tsid.Contact6d(f"contact_{side}", self.robot, f"{side}-sole", self.corners,
                               np.array([0.0, 0.0, 1.0]), 0.7, 1.0, 1000.0)
            c.setKp(30.0 * np.ones(6))
            c.setKd(2.0 * np.sqrt(30.0) * np.ones(6))
            fid = self.robot.model().getFrameId(f"{side}-sole")
            c.setReference(self.robot.framePosition(data, fid))
            form.addRigidContact(c, 1e-5)
            keep.append(c)
        com = tsid.TaskComEquality("com", self.robot)
        com.setKp(100.0 * np.ones(3))
        com.setKd(20.0 * np.ones(3))
        form.addMotionTask(com, 1.0, 1, 0.0)
        torso = tsid.TaskSE3Equality("torso", self.robot, "torso")
        torso.setKp(100.0 * np.ones(6))
        torso.setKd(20.0 * np.ones(6))
        torso.setMask(np.array([0, 0, 0, 1, 1, 1.0]))
        form.addMotionTask(torso, 1.0, 1, 0.0)
        posture = tsid.TaskJointPosture("posture", self.robot)
        posture.setKp(10.0 * np.ones(self.robot.na))
        posture.setKd(2.0 * np.sqrt(10.0) * np.ones(self.robot.na))
        form.addMotionTask(posture, 1e-2, 1, 0.0)
        bounds = tsid.TaskActuationBounds("bounds", self.robot)
        bounds.setBounds(*self.bounds)
        form.addActuationTask(bounds, 1.0, 0, 0.0)
        refs = [tsid.TrajectoryEuclidianConstant("com_ref", self.robot.com(data)),
                tsid.TrajectorySE3Constant("torso_ref", self.robot.framePosition(
                    data, self.robot.model().getFrameId("torso"))),
                tsid.TrajectoryEuclidianConstant("posture_ref", qp[7:])]
        for task, ref in zip((com, torso, posture), refs):
            task.setReference(ref.computeNext())
        keep += [com, torso, posture, bounds, *refs]
        self.form = form
        self.solver = tsid.SolverHQuadProgFast("qp")
        self.solver.resize(form.nVar, form.nEq, form.nIn)
        self.sizes = (form.nVar, form.nEq, form.nIn)
        self.t = 0.0

    def step(self, q, v):
        """One TSID step at (q, v) (MuJoCo coordinates): problem data, QP, torques; returns
        (torques, solver status 0 = solved, wall time of the step in us: the three TSID
        calls, not the coordinate conversion)."""
        qp, vp = self.to_pin(q, v)
        self.t += 1e-3
        t0 = time.perf_counter()
        hqp = self.form.computeProblemData(self.t, qp, vp)
        sol = self.solver.solve(hqp)
        tau = self.form.getActuatorForces(sol)
        return tau, sol.status, (time.perf_counter() - t0) * 1e6
