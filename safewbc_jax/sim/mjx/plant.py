"""The batched path's plant: what every rollout of a batch shares (``BatchConfig``) and the
host-side constants built from it once per config (``Plant``: the controller and MJX models,
index maps, the start state), with the checks of a config that run before anything
compiles (``BatchError``).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from safewbc_jax.control import step as control_step
from safewbc_jax.control import precision as precision_mod
from safewbc_jax.base import userfile
from safewbc_jax.control import safesets
from safewbc_jax.deploy.controller import MotorMap
from safewbc_jax.sim.mjx.imports import import_mjx
from safewbc_jax.model.modelinfo import control_substeps, foot_contact_ids, loop_site_pairs
from safewbc_jax.control.params import ControllerParams
from safewbc_jax.sim.runspec import RunSpec
from safewbc_jax.control.scenario import Scenario, Start
from safewbc_jax.scenarios import SCENARIOS, WALKING, get_scenario
from safewbc_jax.sim.mujoco_loop import load_at_stand
from safewbc_jax.model import digit

BATCHED_SCENARIOS = tuple(SCENARIOS) + WALKING   # squat, bow, arms, walk, push


@dataclasses.dataclass(frozen=True)
class BatchConfig(RunSpec):
    """What every rollout of a batch shares: the run (``runspec.RunSpec``) and the batch's
    own options (static: one compile per config and batch size, durations aside).

    Checked when a batch runs (``plant``), not when it is built.

    Args:
        scenario: "squat", "bow", "arms", "walk", "push", a user's "FILE.py:NAME", or a
            ``Scenario`` object.
        barrier: False: every safe set monitored only.
        duration: s of motion; None: the scenario's default.
        settle: s of standing before it; None: the scenario's default.
        control_dt: the control period, s, a multiple of the simulation step.
        speed: walking: the commanded mean forward speed, m/s.
        safe_sets: the user's safe sets, "FILE.py:NAME" references (``safesets.load``).
        decimate: k > 0 keeps every k-th control step's trajectory; 0: none.
        precision: "float64", or "mixed" (MJX physics and the QP's interior point in
            float32; ``safewbc_jax/control/precision.py``).
    """

    decimate: int = 0
    precision: str = "float64"        # "float64" or "mixed" (safewbc_jax/control/precision.py)


class BatchError(ValueError):
    """Bad input to a batch (shapes, scenario, config), raised before anything compiles."""


# ----------------------------------------------------------------------------- the plant

@dataclasses.dataclass(frozen=True, eq=False)
class Plant:
    """Host-side constants of one config: models, index maps, the start state."""

    cfg: BatchConfig
    scenario: Any
    model: Any            # RobotModel (controller)
    mjx_model: Any
    data0: Any            # mjx.Data at the stand keyframe (precision.physics keeps its dtypes)
    ctx: control_step.Context
    qpos_idx: np.ndarray
    qvel_idx: np.ndarray
    motor_of_ctrl: np.ndarray  # the motor (MotorMap order) of each simulator actuator
    ctrl_lo: np.ndarray
    ctrl_hi: np.ndarray
    base_id: int
    sole_sites: np.ndarray
    tip_sites: np.ndarray
    anchor_sites: np.ndarray
    sole0_xy: np.ndarray
    start: Start
    q0: np.ndarray
    v0: np.ndarray
    n_sub: int
    sim_dt: float
    nv_sim: int
    walking: bool
    floor_geom: int
    sole_geoms: np.ndarray   # (2,) left, right
    leg_geoms: np.ndarray    # (2, k) collision geoms of the left and the right leg
    contact_rows: np.ndarray  # (ncon, 4) efc rows of each MJX contact's pyramid, -1 padded

    def schedule(self, cfg: BatchConfig) -> tuple[int, float]:
        """The run-time values of a config (configs that differ only in duration and
        settle share one compiled function).

        Args:
            cfg: a config of this plant's scenario.

        Returns:
            ``(control steps, settle seconds)``.

        Raises:
            BatchError: a duration or settle out of range.
        """
        return _schedule(self.scenario, cfg)


def _schedule(scenario, cfg: BatchConfig) -> tuple[int, float]:
    try:
        n, settle, _ = control_step.schedule(scenario, cfg.duration, cfg.settle,
                                             cfg.control_dt, "BatchConfig.")
    except ValueError as e:
        raise BatchError(str(e)) from None
    return n, settle


def _check_config(cfg: BatchConfig) -> None:
    if not isinstance(cfg.scenario, Scenario) and cfg.scenario not in BATCHED_SCENARIOS \
            and not userfile.is_ref(cfg.scenario):
        known = ", ".join(BATCHED_SCENARIOS)
        raise BatchError(f"scenario {cfg.scenario!r} is not available in the batched path "
                         f"(available: {known}, a Scenario of your own as FILE.py:NAME, or a "
                         "Scenario object)")
    if not np.isfinite(cfg.speed):
        raise BatchError(f"BatchConfig.speed = {cfg.speed!r}: must be a finite number")
    if int(cfg.decimate) != cfg.decimate or cfg.decimate < 0:
        raise BatchError(f"BatchConfig.decimate = {cfg.decimate!r}: must be an integer >= 0")
    try:
        precision_mod.check(cfg.precision, "BatchConfig.precision")
    except ValueError as e:
        raise BatchError(str(e)) from None
    if not isinstance(cfg.safe_sets, tuple) or not all(isinstance(r, str) for r in cfg.safe_sets):
        raise BatchError(f"BatchConfig.safe_sets = {cfg.safe_sets!r}: must be a tuple of "
                         "\"FILE.py:NAME\" references (safesets.load)")


def _contact_rows(mjx, ms) -> np.ndarray:
    """The efc rows of each of MJX's (fixed) contact slots: 2 (condim - 1) pyramid edges
    (1 for a frictionless contact), -1 padded to 4."""
    if ms.opt.cone != 0:
        raise BatchError("the batched path reads contact forces of pyramidal cones only")
    con = mjx.make_data(ms)._impl.contact
    addr, dim = np.asarray(con.efc_address), np.asarray(con.dim)
    n = np.where(dim == 1, 1, 2 * (dim - 1))
    width = max(int(n.max()) if n.size else 1, 1)
    rows = np.full((addr.size, width), -1)
    for i, (a, k) in enumerate(zip(addr, n)):
        if a >= 0:
            rows[i, :k] = a + np.arange(k)
    return rows


def plant(cfg: BatchConfig) -> Plant:
    """The host-side constants of a config, validated first; cached per scenario, barrier,
    control period, safe sets (by their files' contents) and precision.

    Args:
        cfg: the batch's config.

    Returns:
        Its plant.

    Raises:
        BatchError: a scenario not available in the batched path, a bad field of ``cfg``,
            or a user's file (scenario or safe set) that cannot be used.
    """
    _check_config(cfg)
    try:
        sc = get_scenario(cfg.scenario, cfg.barrier, cfg.safe_sets)
    except ValueError as e:          # a user's file: SafeSetError, or the scenario's
        raise BatchError(str(e)) from None
    _schedule(sc, cfg)               # before the plant
    # the cache key names each user's file by its resolved path and content: an edited
    # file gets a new plant, and "a.py:X" and "./a.py:X" share one
    refs = tuple(userfile.absolute(r, Path.cwd(), "safe set", safesets.SafeSetError)
                 for r in cfg.safe_sets)
    scenario = cfg.scenario          # a Scenario object is its own key (hashed by value)
    own_file = isinstance(scenario, str) and userfile.is_ref(scenario)
    if own_file:
        scenario = userfile.absolute(scenario, Path.cwd(), "scenario")
    files = ((scenario,) if own_file else ()) + refs
    return _plant(scenario, cfg.barrier, float(cfg.control_dt), refs,
                  tuple(userfile.digest(r) for r in files), cfg.precision)


@functools.lru_cache(maxsize=8)
def _plant(scenario, barrier: bool, control_dt: float, safe_sets: tuple = (),
           digests: tuple = (), precision: str = "float64") -> Plant:
    cfg = BatchConfig(scenario=scenario, barrier=barrier, control_dt=control_dt,
                      safe_sets=safe_sets, precision=precision)
    mjx = import_mjx()
    ms, mc, model, sm, d = load_at_stand()
    sc = get_scenario(cfg.scenario, cfg.barrier, cfg.safe_sets)
    n_sub = control_substeps(ms, cfg.control_dt)
    if n_sub is None:
        raise BatchError(f"BatchConfig.control_dt = {cfg.control_dt}: must be a positive "
                         f"multiple of the simulation step {ms.opt.timestep}")

    q0, v0 = (np.asarray(a) for a in sm.to_controller(d.qpos, d.qvel))
    start = control_step.start_data(model, sc, q0)
    motors = MotorMap.build(mc)
    ctx = control_step.Context(model, sc, cfg.control_dt, motors.arrays(),
                               precision_mod.qp_settings(cfg.precision))

    sim_dtype = precision_mod.physics_dtype(cfg.precision)
    mx, dx = mjx.put_model(ms), mjx.put_data(ms, d)
    if sim_dtype != jnp.float64:
        mx, dx = precision_mod.cast_floats((mx, dx), sim_dtype)

    tips, anchors = loop_site_pairs(ms)
    ids = foot_contact_ids(ms)
    soles = ids["sole_sites"]
    return Plant(
        cfg=cfg, scenario=sc, model=model, mjx_model=mx, data0=dx,
        ctx=ctx,
        qpos_idx=np.asarray(sm.qpos_idx), qvel_idx=np.asarray(sm.qvel_idx),
        motor_of_ctrl=np.argsort([ms.actuator(n).id for n in motors.names]),
        ctrl_lo=ms.actuator_ctrlrange[:, 0].copy(), ctrl_hi=ms.actuator_ctrlrange[:, 1].copy(),
        base_id=ms.body(digit.BASE).id, sole_sites=soles, tip_sites=tips, anchor_sites=anchors,
        sole0_xy=d.site_xpos[soles, :2].copy(),
        start=start, q0=q0, v0=v0, n_sub=n_sub, sim_dt=float(ms.opt.timestep), nv_sim=ms.nv,
        walking=ctx.walking,
        floor_geom=ids["floor"], sole_geoms=ids["sole_geoms"], leg_geoms=ids["legs"],
        contact_rows=_contact_rows(mjx, ms))


def default_params(scenario: str | Scenario, batch: int,
                   safe_sets: Sequence[str] = ()) -> ControllerParams:
    """The scenario's default ControllerParams with a leading batch axis on every leaf.

    Args:
        scenario: a scenario's name, a user's "FILE.py:NAME", or a ``Scenario``.
        batch: the batch size B.
        safe_sets: the user's safe sets, as in ``BatchConfig``.

    Returns:
        The params, each leaf broadcast to (B,) + its shape.

    Raises:
        ValueError: an unknown scenario, or a safe set that cannot be used
            (``SafeSetError``).
        RuntimeError: JAX's 64-bit floats are off.
    """
    p = get_scenario(scenario, True, safe_sets).default_params()
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (batch,) + a.shape), p)
