"""Shared consensus pieces (Gu & Hu (16)/(18b); Chen's neighbour term zᵢ of (3)).

Both estimators need the weighted disagreement Σ_{j∈Nᵢ} gᵢⱼ (ξⱼ − ξᵢ) of a node with its neighbours:
Gu & Hu use it on the information vector χ with rate η, Chen on the estimates x̂ (times C).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np


def consensus_rate(delta_max: int, rule: str = "1/(dmax+1)") -> float:
    """Common consensus rate η for (16): must satisfy η ≤ 1/δ_max and be equal at every node.

    ``"1/(dmax+1)"`` (default) is strictly inside the Gershgorin bound; ``"1/dmax"`` is the paper's
    bound itself. An isolated graph (δ_max = 0) gives η = 0 (nothing to average) for "1/dmax".
    """
    if rule == "1/(dmax+1)":
        return 1.0 / (delta_max + 1.0)
    if rule == "1/dmax":
        return 1.0 / delta_max if delta_max > 0 else 0.0
    try:
        return float(rule)
    except ValueError as exc:  # pragma: no cover - scenario validation catches it first
        raise ValueError(f"unknown consensus rate rule {rule!r}") from exc


def disagreement(own: np.ndarray, others: Mapping[int, np.ndarray],
                 weights: Mapping[int, float] | None = None, trim: int = 0) -> np.ndarray:
    """Σⱼ gᵢⱼ (ξⱼ − ξᵢ) over the neighbours present in ``others`` (ascending id order).

    ``trim = f > 0`` makes it the W-MSR (weighted mean-subsequence-reduced) update that tolerates up
    to f Byzantine neighbours in an (2f+1)-robust graph: element by element, the f largest values above
    ξᵢ and the f smallest below it are discarded before summing (LeBlanc et al., IEEE JSAC 2013).
    It no longer preserves the network sum, so Gu & Hu's mean-equals-centralized invariant holds only
    for f = 0.
    """
    if trim > 0 and others:
        return trimmed_disagreement(own, others, weights, trim)
    own = np.asarray(own, dtype=float)
    acc = np.zeros_like(own)
    term = np.empty_like(own)
    for j in sorted(others):     # acc += w (ξⱼ − ξᵢ), in place (the same operations, bit for bit)
        np.subtract(others[j], own, out=term)
        if weights is not None:
            term *= float(weights[j])
        acc += term
    return acc


def trimmed_disagreement(own: np.ndarray, others: Mapping[int, np.ndarray],
                         weights: Mapping[int, float] | None, f: int) -> np.ndarray:
    """W-MSR neighbour sum (see :func:`disagreement`), vectorised over the elements of ξ."""
    own = np.asarray(own, dtype=float)
    ids = sorted(others)
    D = np.stack([np.asarray(others[j], dtype=float) - own for j in ids])           # (m, ...)
    W = np.array([1.0 if weights is None else float(weights[j]) for j in ids]).reshape((-1,) + (1,) * own.ndim)
    W = np.broadcast_to(W, D.shape)
    order = np.argsort(D, axis=0, kind="stable")
    Ds = np.take_along_axis(D, order, axis=0)
    Ws = np.take_along_axis(W, order, axis=0)
    m = D.shape[0]
    n_hi = np.minimum(f, (D > 0).sum(axis=0))                                      # drop ≤ f above ξᵢ
    n_lo = np.minimum(f, (D < 0).sum(axis=0))                                      # drop ≤ f below ξᵢ
    rank = np.arange(m).reshape((-1,) + (1,) * own.ndim)
    keep = (rank >= n_lo) & (rank < m - n_hi)
    return np.sum(np.where(keep, Ws * Ds, 0.0), axis=0)


def consensus_round(own: Mapping[str, np.ndarray], others: Mapping[int, Mapping[str, np.ndarray]],
                    eta: float, keys: Sequence[str] | None = None, trim: int = 0) -> dict[str, np.ndarray]:
    """One round of (16)/(18b) on every entry of a payload: ξᵢ ← ξᵢ + η Σⱼ (ξⱼ − ξᵢ)
    (W-MSR-trimmed when ``trim`` = f > 0)."""
    keys = list(own) if keys is None else list(keys)
    return {k: own[k] + eta * disagreement(own[k], {j: p[k] for j, p in others.items()}, trim=trim) for k in keys}
