"""The confidence interval of a mean over seeds: what the sweep's summary CSV and its figures' bands show.

Floors: numpy and SciPy only (no plotting), so a sweep's tables need no figure library.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import stats


def mean_ci(values: Sequence[float], level: float = 0.95, n_boot: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """(mean, lo, hi): the mean of the finite values and its percentile-bootstrap confidence interval
    at ``level`` (:func:`scipy.stats.bootstrap`, ``n_boot`` resamples).

    Deterministic (a fixed generator seed). One value, or all equal, gives lo = hi = mean; none gives NaNs."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return (float("nan"),) * 3
    m = float(v.mean())
    if v.size == 1 or np.all(v == v[0]):
        return m, m, m
    res = stats.bootstrap((v,), np.mean, n_resamples=n_boot, confidence_level=level, method="percentile",
                          rng=np.random.default_rng(seed))
    return m, float(res.confidence_interval.low), float(res.confidence_interval.high)
