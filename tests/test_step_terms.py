"""The controller step's closed-form drift terms (robot.body_motion,
controller.constraint_drift) against the forward-mode AD reference, and under vmap."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import ad_reference
from conftest import random_state

from safewbc_jax import scenarios
from safewbc_jax.control import terms as controller
from safewbc_jax.model import robot


@pytest.fixture(scope="module")
def states(ctrl_mj):
    rng = np.random.default_rng(99)
    return [random_state(ctrl_mj, rng) for _ in range(6)]


@pytest.mark.parametrize("name", ["squat", pytest.param("arms", marks=pytest.mark.slow)])
def test_closed_form_terms_equal_the_ad_terms(rm, states, name):
    sc = scenarios.get_scenario(name)
    closed = jax.jit(lambda q, v: controller.robot_terms(rm, sc, q, v))
    ad = jax.jit(lambda q, v: ad_reference.robot_terms_ad(rm, sc, q, v))
    for q, v in states:
        a, b = closed(jnp.asarray(q), jnp.asarray(v)), ad(jnp.asarray(q), jnp.asarray(v))
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
            x, y = np.asarray(x), np.asarray(y)
            assert x.shape == y.shape
            np.testing.assert_allclose(x, y, rtol=0, atol=1e-11 * max(1.0, np.abs(y).max()))


def test_constraint_drift_equals_the_standalone_drifts(rm, states):
    for q, v in states[:3]:
        q, v = jnp.asarray(q), jnp.asarray(v)
        kin = robot.forward_kinematics(rm, q)
        got = controller.constraint_drift(rm, kin, robot.body_motion(rm, kin, v))
        ref = jnp.concatenate([ad_reference.chain_drift(rm, q, v), ad_reference.stacked_contact_drift(rm, q, v)])
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10 * max(1.0, float(jnp.abs(ref).max())))
        np.testing.assert_allclose(robot.bias_forces(rm, q, v), ad_reference.bias_forces_ad(rm, q, v),
                                   rtol=0, atol=1e-9)


@pytest.mark.slow
def test_terms_vmap_over_states(rm, states):
    sc = scenarios.get_scenario("squat")
    qs = jnp.stack([jnp.asarray(q) for q, _ in states[:3]])
    vs = jnp.stack([jnp.asarray(v) for _, v in states[:3]])
    batched = jax.vmap(lambda q, v: controller.robot_terms(rm, sc, q, v))(qs, vs)
    for i in range(3):
        one = controller.robot_terms(rm, sc, qs[i], vs[i])
        np.testing.assert_allclose(batched.Jdot_v[i], one.Jdot_v, atol=1e-12)
        np.testing.assert_allclose(batched.h[i], one.h, atol=1e-10)


def test_torso_euler_terms_equal_the_ad_terms(rm, states):
    closed = jax.jit(lambda q, v: robot.torso_euler_terms(rm, q, v))
    for q, v in states:
        q, v = jnp.asarray(q), jnp.asarray(v)
        y, j, jd = closed(q, v)
        np.testing.assert_allclose(y, robot.torso_euler(rm, q), atol=1e-14)
        np.testing.assert_allclose(j, robot.torso_euler_jacobian(rm, q), atol=1e-11)
        np.testing.assert_allclose(jd, robot.torso_euler_drift(rm, q, v),
                                   atol=1e-10 * max(1.0, float(jnp.abs(jd).max())))
