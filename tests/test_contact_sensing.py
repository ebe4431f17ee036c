"""The MuJoCo loop's contact sensing (``mujoco_loop.ContactSensing``: one geom-pair table
over ``d.contact.geom``) against a plain
reading of MuJoCo's contact list: one ``d.contact[i]`` object per contact, its two geom
ids tested by set membership, and ``mj_contactForce`` for each sole-floor contact."""

import copy

import mujoco
import numpy as np
import pytest

from safewbc_jax.model.modelinfo import foot_contact_ids
from safewbc_jax.sim.mujoco_loop import ContactSensing


def reference(ms, d, ids):
    floor, (left_sole, right_sole) = ids["floor"], ids["sole_geoms"].tolist()
    left_leg, right_leg = set(ids["legs"][0].tolist()), set(ids["legs"][1].tolist())
    force, legs, f6 = [0.0, 0.0], False, np.zeros(6)
    for i in range(d.ncon):
        a, b = (int(g) for g in d.contact[i].geom)
        for side, sole in enumerate((left_sole, right_sole)):
            if {a, b} == {floor, sole}:
                mujoco.mj_contactForce(ms, d, i, f6)
                force[side] += abs(f6[0])
        legs |= (a in left_leg and b in right_leg) or (a in right_leg and b in left_leg)
    return force[0], force[1], legs


def states(ms):
    """MjData at the stand and with the legs turned into each other (hip roll and yaw),
    each after 0, 5 and 30 unactuated steps: soles on the floor, leg-on-leg contacts,
    and both at once."""
    d = mujoco.MjData(ms)
    for roll, yaw in ((0.0, 0.0), (0.1, 0.0), (0.1, -0.5), (0.0, -0.5), (0.2, 0.5)):
        mujoco.mj_resetDataKeyframe(ms, d, ms.key("stand").id)
        for side, sign in (("left", 1), ("right", -1)):
            d.qpos[ms.joint(f"{side}-hip-roll").qposadr[0]] += sign * roll
            d.qpos[ms.joint(f"{side}-hip-yaw").qposadr[0]] += sign * yaw
        mujoco.mj_forward(ms, d)
        for n in (0, 5, 25):
            for _ in range(n):
                mujoco.mj_step(ms, d)
            yield d


@pytest.mark.parametrize("cone", ["pyramidal", "elliptic"])
def test_contact_sensing_matches_a_plain_reading_of_the_contact_list(sim_mj, cone):
    """The model's pyramidal friction cone, and an elliptic copy: the sole forces are
    mj_contactForce's normal component either way."""
    ms = sim_mj
    if cone == "elliptic":
        ms = copy.deepcopy(sim_mj)
        ms.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    assert ms.opt.cone == getattr(mujoco.mjtCone, f"mjCONE_{cone.upper()}")
    ids = foot_contact_ids(ms)
    sense = ContactSensing(ms, ids)
    seen = {"legs": 0, "both soles": 0, "no contact": 0}
    for d in states(ms):
        got, want = sense(ms, d), reference(ms, d, ids)
        # the same mj_contactForce values added in the same (MuJoCo's) order: equal up
        # to the last bit; 1e-12 relative leaves room for nothing but that
        assert got[:2] == pytest.approx(want[:2], rel=1e-12, abs=1e-12)
        assert got[2] == want[2]
        seen["legs"] += want[2]
        seen["both soles"] += min(want[:2]) > 1.0
        seen["no contact"] += d.ncon == 0
    # the states cover what the tables decide: leg-on-leg contacts and loaded soles
    assert seen["legs"] >= 3 and seen["both soles"] >= 3, seen
