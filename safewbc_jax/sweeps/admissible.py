"""Theorem 1 at the start state of every rollout of a sweep, before anything long compiles.

A rollout starts at the ``stand`` keyframe with its own initial velocity perturbation, so
eta(x_0) = [h, h_dot] of each barrier differs between rollouts: h_dot(x_0) < 0 puts a
lower bound -h_dot / h on the first pole (``barriers.admissible_pole_bounds``). These
functions evaluate eta(x_0) for a batch of start states (one small jit, no closed loop)
and check the poles with ``barriers.check_poles``.
"""

from __future__ import annotations

import numpy as np

from safewbc_jax.sweeps.spec import SweepSpec

BLOCK = 256   # start states per call of the compiled eta function (one shape, one compile)


def start_etas(spec: SweepSpec, name: str, thresholds: np.ndarray, perturb_v: np.ndarray):
    """(N, r) eta(x_0) of barrier ``name`` for N start states (threshold, perturbation),
    through the batched path's own start-state function (``batch.rollout.start_etas``)
    in blocks of BLOCK (one compiled shape)."""
    from safewbc_jax.sim.mjx import rollout

    pl = rollout.plant(rollout.BatchConfig.of(spec.run))
    v = np.asarray(perturb_v, float)
    thr = np.asarray(thresholds, float)
    n = v.shape[0]
    out = []
    for s in range(0, n, BLOCK):
        vb, tb = v[s:s + BLOCK], thr[s:s + BLOCK]
        m = vb.shape[0]
        if m < BLOCK:   # pad: one compiled shape
            vb = np.concatenate([vb, np.repeat(vb[-1:], BLOCK - m, 0)])
            tb = np.concatenate([tb, np.repeat(tb[-1:], BLOCK - m, 0)])
        out.append(rollout.start_etas(pl, name, vb, tb)[:m])
    return np.concatenate(out, axis=0)


def check_sweep(spec: SweepSpec, base, settings: np.ndarray, seed: int, std: np.ndarray):
    """Raise PoleError (naming the rollout, its setting and the bound) unless every rollout
    of the sweep has Theorem-1 admissible poles at its own start state."""
    from safewbc_jax.control import barriers
    from safewbc_jax.sweeps import inputs

    if not spec.barrier or not spec.barriers:
        return
    n = spec.n_rollouts
    rollouts = np.arange(n)
    vals = settings[rollouts // spec.repeats]
    params = inputs.params_batch(base, spec.axes, vals)
    dv = inputs.perturbations(seed, rollouts, std, spec.noise_period)
    for name in spec.barriers:
        thr = np.asarray(params.threshold[name])
        poles = np.asarray(params.poles[name])
        # identical start states and poles need one check
        key = np.concatenate([thr[:, None], poles, dv], axis=1)
        _, first = np.unique(key, axis=0, return_index=True)
        etas = start_etas(spec, name, thr[first], dv[first])
        for e, k in zip(etas, first):
            try:
                barriers.check_poles(name, e, poles[k])
            except barriers.PoleError as err:
                setting = spec.setting(int(k) // spec.repeats)
                raise barriers.PoleError(
                    f"{spec.path}: rollout {k} (setting {setting}, perturbation draw "
                    f"{k % spec.repeats}): {err}; raise the pole grid's lower end or reduce "
                    "[perturb]") from None


def admissible_mask(name: str, candidates: np.ndarray, etas: np.ndarray) -> np.ndarray:
    """(C,) True where candidate poles (C, r) pass Theorem 1 at every start state (D, r)."""
    from safewbc_jax.control import barriers

    ok = np.ones(len(candidates), bool)
    uniq = np.unique(np.asarray(etas), axis=0)
    for c, p in enumerate(candidates):
        for e in uniq:
            try:
                barriers.check_poles(name, e, p)
            except barriers.PoleError:
                ok[c] = False
                break
    return ok


def first_pole_bound(etas: np.ndarray) -> float:
    """The least admissible p_1 over start states: max of -h_dot / h (0 at rest)."""
    e = np.asarray(etas)
    h, hd = e[:, 0], e[:, 1] if e.shape[1] > 1 else np.zeros(len(e))
    with np.errstate(divide="ignore", invalid="ignore"):
        b = np.where(h > 0, np.maximum(0.0, -hd / h), np.where(hd >= 0, 0.0, np.inf))
    return float(np.max(b)) + 0.0 if b.size else 0.0   # + 0.0: no "-0" in messages
