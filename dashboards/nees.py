"""Whether a stated uncertainty is honest, tick by tick: the normalised estimation error squared (NEES) of
estimates against the covariances reported for them, and the χ² acceptance interval of its average
(Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*, §5.4).

An estimate x̂ with error e = x̂ − x and reported covariance P has

    ε = e′ P⁻¹ e,

χ²-distributed with m = dim x degrees of freedom when P is the error's true covariance. The average of K
such values lies, at 95 %, in [χ²₀.₀₂₅(K·m), χ²₀.₉₇₅(K·m)] / K; below it the covariances are *conservative*
(larger than the errors), above it *optimistic*. The run's summary (``flocktrack/record/credibility.py``)
takes its NEES and intervals from here, so the live panel and summary.json agree to the last digit.

Floors: NumPy; SciPy's special functions only once an interval is asked for (a run without covariances
never loads SciPy into the dashboard's process).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

#: a covariance is taken as symmetric when P − P′ is within this fraction of its largest entry
SYMMETRY_RTOL = 1e-9


def usable_covariances(covariances: np.ndarray) -> np.ndarray:
    """(K,) bool: which of the covariances (K × m × m) are finite, symmetric (:data:`SYMMETRY_RTOL`) and
    positive definite — the ones a NEES can be taken against."""
    P = np.asarray(covariances, float)
    if P.ndim != 3 or P.shape[1] != P.shape[2] or P.shape[1] == 0:
        return np.zeros(len(P) if P.ndim else 0, bool)
    with np.errstate(all="ignore"):
        ok = np.isfinite(P).all(axis=(1, 2))
        scale = np.abs(np.where(ok[:, None, None], P, 0.0)).max(axis=(1, 2))
        asym = np.abs(np.where(ok[:, None, None], P - P.swapaxes(1, 2), 0.0)).max(axis=(1, 2))
        ok &= asym <= SYMMETRY_RTOL * scale
    idx = np.flatnonzero(ok)
    if idx.size:
        S = 0.5 * (P[idx] + P[idx].swapaxes(1, 2))
        ok[idx] = _min_eigenvalues(S) > 0
    return ok


def _min_eigenvalues(S: np.ndarray) -> np.ndarray:
    """The smallest eigenvalue of each symmetric matrix of the stack (−inf where it cannot be had)."""
    with np.errstate(all="ignore"):
        try:
            return np.linalg.eigvalsh(S)[:, 0]
        except np.linalg.LinAlgError:   # one matrix spoils the batch: each on its own
            out = np.full(len(S), -np.inf)
            for j, s in enumerate(S):
                try:
                    out[j] = np.linalg.eigvalsh(s)[0]
                except np.linalg.LinAlgError:
                    pass
            return out


def nees(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """(K,) εⱼ = eⱼ′ Pⱼ⁻¹ eⱼ of each error eⱼ (rows of ``errors``, K × m) against the covariance reported
    for it (``covariances``, K × m × m); NaN where the error is not finite, where Pⱼ is not finite,
    symmetric and positive definite (:func:`usable_covariances`), or where ε itself is not finite."""
    E = np.asarray(errors, float)
    P = np.asarray(covariances, float)
    K = len(E)
    out = np.full(K, np.nan)
    if E.ndim != 2 or P.shape != (K, E.shape[1], E.shape[1]):
        return out
    keep = np.flatnonzero(np.isfinite(E).all(axis=1) & usable_covariances(P))
    if keep.size:
        with np.errstate(all="ignore"):
            try:
                eps = np.einsum("ki,kij,kj->k", E[keep], np.linalg.inv(P[keep]), E[keep])
            except np.linalg.LinAlgError:
                eps = np.array([_one(E[j], P[j]) for j in keep])
        out[keep] = np.where(np.isfinite(eps), eps, np.nan)
    return out


def _one(e: np.ndarray, P: np.ndarray) -> float:
    try:
        return float(e @ np.linalg.inv(P) @ e)
    except np.linalg.LinAlgError:
        return float("nan")


@lru_cache(maxsize=256)
def chi2_interval(dof: int, samples: int, level: float = 0.95) -> tuple[float, float]:
    """The two-sided ``level`` acceptance interval of an average of ``samples`` NEES values with ``dof``
    degrees of freedom in all (``samples`` × m): the χ²(dof) quantiles (1 ∓ level)/2 over ``samples``.
    (The quantile is SciPy's ``chi2.ppf``, 2·P⁻¹(dof/2, q) of the regularised incomplete gamma function.)"""
    from scipy.special import gammaincinv

    a = (1 - level) / 2
    return float(2 * gammaincinv(dof / 2, a) / samples), float(2 * gammaincinv(dof / 2, 1 - a) / samples)


def network_nees(errors: np.ndarray, covariances: np.ndarray, level: float = 0.95) -> dict:
    """The NEES of one tick's node estimates (rows of ``errors``, one per node, against ``covariances``):
    ``per_node`` ε (NaN: not scored), ``mean`` over the n scored nodes and the ``level`` interval of that
    mean, χ²(n·m) / n (``lo``, ``hi``; NaN without a scored node), ``scored`` = n."""
    eps = nees(errors, covariances)
    ok = np.isfinite(eps)
    n = int(ok.sum())
    m = int(np.shape(errors)[1]) if np.ndim(errors) == 2 else 0
    if n == 0 or m == 0:
        return {"per_node": eps, "mean": float("nan"), "lo": float("nan"), "hi": float("nan"), "scored": 0}
    lo, hi = chi2_interval(n * m, n, level)
    return {"per_node": eps, "mean": float(eps[ok].mean()), "lo": lo, "hi": hi, "scored": n}
