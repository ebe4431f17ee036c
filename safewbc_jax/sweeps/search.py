"""The searches of ``safewbc tune``, over the unit box [0, 1]^d of the tuned parameters.

Both have the same three calls: ``ask()`` gives the next generation's candidates (n, d),
``tell(x, values)`` takes their values (lower is better; the tuner's ranking of safe and
unsafe candidates, :func:`safewbc_jax.sweeps.tuning.rank_value`) and ``done()`` says the
search has converged or used its rounds. Each is deterministic for a seed, so a killed
tuning run resumes by replaying its finished generations from their tables.

* :class:`Cmaes`: CMA-ES (Hansen's covariance matrix adaptation evolution strategy) from
  the ``cmaes`` package, bounded to the box. It stops early on the package's own criteria
  (the spread of the values over recent generations, the step size).
* :class:`GridRefine`: successive grid refinement: ``points`` values per parameter over a
  box, then a box ``shrink`` times as wide centred on the best candidate so far, for
  ``rounds`` rounds.
"""

from __future__ import annotations

import numpy as np


class Cmaes:
    """CMA-ES over [0, 1]^d from ``x0`` with initial step ``sigma`` (a fraction of the
    box) and ``population`` candidates a generation (None: 4 + floor(3 ln d))."""

    def __init__(self, x0, sigma: float, population: int | None, seed: int):
        from cmaes import CMA

        x0 = np.clip(np.asarray(x0, float), 0.0, 1.0)
        d = x0.size
        self._cma = CMA(mean=x0, sigma=float(sigma), bounds=np.tile([0.0, 1.0], (d, 1)),
                        seed=int(seed), population_size=population)

    @property
    def population(self) -> int:
        return self._cma.population_size

    def ask(self) -> np.ndarray:
        return np.stack([self._cma.ask() for _ in range(self.population)])

    def tell(self, x, values) -> None:
        self._cma.tell([(np.asarray(xi, float), float(v)) for xi, v in zip(x, values)])

    def done(self) -> bool:
        return bool(self._cma.should_stop())


class GridRefine:
    """``points`` evenly spaced values per coordinate over the current box (the whole
    unit box first); after each round the box is re-centred on the best candidate so far
    and shrunk by ``shrink``, clipped to the unit box."""

    def __init__(self, dim: int, points: int, rounds: int, shrink: float):
        self.lo, self.hi = np.zeros(dim), np.ones(dim)
        self.points, self.rounds, self.shrink = int(points), int(rounds), float(shrink)
        self.round = 0
        self.best_x: np.ndarray | None = None
        self.best_v = np.inf

    @property
    def population(self) -> int:
        return self.points ** self.lo.size

    def ask(self) -> np.ndarray:
        axes = [np.linspace(a, b, self.points) for a, b in zip(self.lo, self.hi)]
        g = np.meshgrid(*axes, indexing="ij")
        return np.unique(np.round(np.stack([x.reshape(-1) for x in g], axis=1), 12), axis=0)

    def tell(self, x, values) -> None:
        values = np.asarray(values, float)
        j = int(np.argmin(values))
        if values[j] < self.best_v:
            self.best_x, self.best_v = np.asarray(x[j], float), float(values[j])
        half = self.shrink * (self.hi - self.lo) / 2
        centre = self.best_x if self.best_x is not None else (self.lo + self.hi) / 2
        self.lo = np.maximum(centre - half, 0.0)
        self.hi = np.minimum(centre + half, 1.0)
        self.hi = np.maximum(self.hi, self.lo + 1e-12)
        self.round += 1

    def done(self) -> bool:
        return self.round >= self.rounds
