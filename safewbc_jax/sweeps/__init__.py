"""Sweeps over controller parameters and pushes with batched closed-loop rollouts.

* :mod:`.spec`   sweep spec files (TOML): parsing, validation before anything compiles,
                 the plan of rollouts (settings x repeats) and their inputs;
* :mod:`.inputs` each rollout's parameters, push and perturbation from a spec;
* :mod:`.table`  the results table: one Parquet file per finished chunk, written
                 atomically, read back as one table; the manifest that makes resume safe;
* :mod:`.run`    ``safewbc sweep``: chunks of batched rollouts through
                 ``safewbc_jax.sim.mjx.rollout.run_batch``;
* :mod:`.stats`  Wilson score intervals for violation rates;
* :mod:`.report` ``safewbc report``: figures and ``summary.md``;
* :mod:`.tuning` ``safewbc tune``: poles, gains and weights with no fall or violation over
                 a push and perturbation distribution at the least objective, by
                 generations of sweeps, validated on held-out draws;
* :mod:`.search` the tuner's searches: CMA-ES and successive grid refinement;
* :mod:`.tune`   ``safewbc tune-poles``: the grid-refinement preset of ``tune`` over one
                 barrier's poles;
* :mod:`.tune_report` ``safewbc report`` of a tuning run.

Nothing here imports JAX at module import time except :mod:`.run` and the tuner (through
their entry points), so validating a spec is instant.
"""

from safewbc_jax.sweeps.spec import SpecError, SweepSpec, load_spec  # noqa: F401
from safewbc_jax.sweeps.stats import wilson_interval  # noqa: F401
