"""``safewbc tune-poles``: the poles of one A-ECBF, a preset of ``safewbc tune``
(:mod:`.tuning`).

The spec's ``tune.barrier`` names the barrier; its poles are the tuned parameters (log
scale) over [pole_min, pole_max], narrowed by the spec's pole axes of that barrier, one
parameter ``poles.B`` with ``equal_poles``. The search is the successive grid refinement
(``tune.method = "grid"``): ``points`` log-spaced values per pole, ``rounds`` rounds, each
box ``shrink`` times as wide as the last around the best candidate so far. The rest
(Theorem 1's repair and refusal, the ranking, the held-out validation, the params TOML) is
``tune``'s. ``safewbc tune SPEC`` on the same spec runs CMA-ES over the same poles.
"""

from __future__ import annotations

from safewbc_jax.sweeps import tuning
from safewbc_jax.sweeps.spec import SweepSpec


def poles_config(spec: SweepSpec, *, budget=None, validate=None) -> tuning.TuneConfig:
    """The preset: grid refinement over the poles of ``tune.barrier``."""
    return tuning.config(spec, method="grid", budget=budget, validate=validate,
                         params=tuning.poles_preset(spec))


def tune_poles(spec: SweepSpec, out, *, work=None, batch=None, seed=None, executor=None,
               progress=None, quiet=False, engine="mjx", workers=None, budget=None,
               validate=None) -> tuning.TuneResult:
    """Grid refinement over the poles of ``tune.barrier``; ``work`` defaults to OUT
    without .toml + "_rounds". The other arguments are :func:`tuning.tune`'s."""
    return tuning.tune(spec, out, cfg=poles_config(spec, budget=budget, validate=validate),
                       work=work, batch=batch, seed=seed, executor=executor,
                       progress=progress, quiet=quiet, engine=engine, workers=workers,
                       title="tune-poles")
