"""Binomial confidence intervals for violation and fall rates."""

from __future__ import annotations

import numpy as np

Z95 = 1.959963984540054  # two-sided 95% standard normal quantile


def wilson_interval(k, n, z: float = Z95):
    """Wilson score interval for k successes in n trials (Wilson 1927; Newcombe 1998,
    method 3): the p with |p_hat - p| <= z sqrt(p (1 - p) / n),

        centre = (p_hat + z^2 / 2n) / (1 + z^2 / n),
        half   = z / (1 + z^2 / n) * sqrt(p_hat (1 - p_hat) / n + z^2 / 4n^2).

    Unlike the Wald interval it stays inside [0, 1] and is not empty at k = 0 or k = n.
    Vectorized over k and n; returns (low, high); (nan, nan) where n = 0."""
    k = np.asarray(k, float)
    n = np.asarray(n, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = k / n
        z2 = z * z
        den = 1.0 + z2 / n
        centre = (p + z2 / (2 * n)) / den
        half = z / den * np.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
        lo = np.where(n > 0, np.clip(centre - half, 0.0, 1.0), np.nan)
        hi = np.where(n > 0, np.clip(centre + half, 0.0, 1.0), np.nan)
    # exact ends: k = 0 -> low 0, k = n -> high 1 (the formula gives them up to rounding)
    lo = np.where((n > 0) & (k == 0), 0.0, lo)
    hi = np.where((n > 0) & (k == n), 1.0, hi)
    if lo.ndim == 0:
        return float(lo), float(hi)
    return lo, hi
