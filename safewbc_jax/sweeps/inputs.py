"""The inputs of a sweep's rollouts, from its spec: the parameters of each rollout (the
fixed ones and its swept axes), its push and its initial velocity perturbation. Rollout k
draws its perturbation from a generator seeded by (seed, k), so it does not depend on the
chunking, the batch size, the engine or the number of devices."""

from __future__ import annotations

import dataclasses

import numpy as np

from safewbc_jax.control.push import Push
from safewbc_jax.sweeps.spec import SweepSpec


def base_params(spec: SweepSpec):
    """The scenario's default ControllerParams with the spec's fixed overrides."""
    from safewbc_jax.control.params import apply_overrides

    p = spec.run.get_scenario().default_params()
    return apply_overrides(p, spec.params, f"{spec.path}: [params]")


def params_batch(base, axes, values: np.ndarray):
    """ControllerParams whose leaves have a leading batch axis: row i of ``values``
    (B, len(axes)) sets the swept axes of rollout i on top of ``base``. numpy float64."""
    import dataclasses as dc

    b = values.shape[0]
    stack = lambda x: np.repeat(np.asarray(x, np.float64)[None], b, axis=0)  # noqa: E731
    fields = {}
    for f in dc.fields(base):
        v = getattr(base, f.name)
        fields[f.name] = {k: stack(x) for k, x in v.items()} if isinstance(v, dict) else stack(v)
    for j, a in enumerate(axes):
        col = np.asarray(values[:, j], np.float64)
        if a.kind == "poles":
            fields["poles"][a.target][:] = col[:, None]
        elif a.kind == "pole":
            fields["poles"][a.target][:, a.index] = col
        elif a.kind == "threshold":
            fields["threshold"][a.target][:] = col
        elif a.kind == "gain":
            fields[a.name.split(".")[0]][a.target][:] = col[:, None]
        elif a.kind == "scale":
            kind = a.name.split(".")[0]
            if kind == "gain_scale":
                fields["kp"][a.target] *= col[:, None]
                fields["kd"][a.target] *= np.sqrt(col)[:, None]
            else:
                fields[kind[:-len("_scale")]][a.target] *= col[:, None]
        elif a.kind == "scalar":
            fields[a.target][:] = col
    return type(base)(**fields)


def pushes(spec: SweepSpec, values: np.ndarray) -> tuple[Push, dict]:
    """The rollouts' pushes from the fixed push and the swept push axes: (the batched
    ``Push``; its table columns: magnitude, direction in degrees, at,
    duration, and the force vector fx, fy, fz)."""
    b = values.shape[0]
    out = {k: np.full(b, float(v)) for k, v in dataclasses.asdict(spec.push).items()}
    for j, a in enumerate(spec.axes):
        if a.kind == "push":
            out[a.target] = np.asarray(values[:, j], float)
    rad = np.deg2rad(out["direction"])
    out["fx"] = out["magnitude"] * np.cos(rad)
    out["fy"] = out["magnitude"] * np.sin(rad)
    out["fz"] = np.zeros(b)
    force = np.stack([out["fx"], out["fy"], out["fz"]], axis=1)
    return Push(force, out["at"].copy(), out["duration"].copy()), out


def velocity_std(spec: SweepSpec, sim_model) -> np.ndarray:
    """(nv_sim,) standard deviation of the initial velocity perturbation per simulator DoF:
    the free joint's linear and angular parts, and the hinges. Ball joints (the rods of the
    closed chains) are left alone."""
    import mujoco

    std = np.zeros(sim_model.nv)
    for j in range(sim_model.njnt):
        adr = int(sim_model.jnt_dofadr[j])
        t = int(sim_model.jnt_type[j])
        if t == mujoco.mjtJoint.mjJNT_FREE:
            std[adr:adr + 3] = spec.perturb.base_linear
            std[adr + 3:adr + 6] = spec.perturb.base_angular
        elif t == mujoco.mjtJoint.mjJNT_HINGE:
            std[adr] = spec.perturb.joints
    return std


def perturbations(seed: int, rollouts: np.ndarray, std: np.ndarray,
                  period: int | None = None) -> np.ndarray:
    """(len(rollouts), nv) initial velocity perturbations: rollout k draws from its own
    generator seeded by (seed, k), so a rollout's perturbation does not depend on the
    chunking, the batch size or the number of devices. With ``period`` P, rollout k uses
    draw k mod P (rollouts P apart meet the same draws)."""
    out = np.zeros((len(rollouts), std.size))
    if not np.any(std):
        return out
    keys = np.asarray(rollouts) if not period else np.asarray(rollouts) % int(period)
    for i, k in enumerate(keys):
        rng = np.random.default_rng([int(seed), int(k)])
        out[i] = rng.standard_normal(std.size) * std
    return out
