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
                 weights: Mapping[int, float] | None = None) -> np.ndarray:
    """Σⱼ gᵢⱼ (ξⱼ − ξᵢ) over the neighbours present in ``others`` (ascending id order)."""
    acc = np.zeros_like(np.asarray(own, dtype=float))
    for j in sorted(others):
        w = 1.0 if weights is None else float(weights[j])
        acc = acc + w * (np.asarray(others[j], dtype=float) - own)
    return acc


def consensus_round(own: Mapping[str, np.ndarray], others: Mapping[int, Mapping[str, np.ndarray]],
                    eta: float, keys: Sequence[str] | None = None) -> dict[str, np.ndarray]:
    """One round of (16)/(18b) on every entry of a payload: ξᵢ ← ξᵢ + η Σⱼ (ξⱼ − ξᵢ)."""
    keys = list(own) if keys is None else list(keys)
    return {k: own[k] + eta * disagreement(own[k], {j: p[k] for j, p in others.items()}) for k in keys}
