"""Which neighbours' information payloads are consistent with a node's own (Gu & Hu (18a)/(18b)).

W-MSR trimming (:func:`agent.estimators.consensus.trimmed_disagreement`) keeps a Byzantine neighbour's value
whenever it lies inside the honest range, and when it lies outside, it trims it on one side while an honest
value goes on the other: the honest sum is no longer preserved, and the nodes next to an attacker drift. The
gate removes the attacker from the round before W-MSR sees it, using what an honest payload must look like.

An honest payload of round r is a convex mixture of sensors' (18a) triples, all with the same C, R, S:

* χ¹ = β C′R⁻¹C and χ³ = β C′(R⁻¹ − S⁻¹)C for one β = Σ wⱼ bⱼ² ≥ 0 (the same β in both);
* χ² = Σ wⱼ bⱼ C′R⁻¹ yⱼ, so that its measurement-space residual u = (C′R⁻¹)⁺ (χ² − χ¹ x̂) is
  Σ wⱼ bⱼ² C (x − x̂) + Σ wⱼ bⱼ vⱼ.

Between two honest payloads of nodes with the same β the prediction error C (x − x̂) cancels — it is common
to the whole flock, also when the target manoeuvres outside the model — and what is left is measurement
noise of covariance at most 2R (mixture weights are at most one). So a node, whose own payload is honest,
discards neighbour j's payload of the round when

* χ¹ⱼ is not a non-negative multiple β ≤ ``beta_max`` of C′R⁻¹C, or χ³ⱼ not the same multiple of C′(R⁻¹ − S⁻¹)C
  (a scaled, forged or garbled information matrix), or
* d² = Δu′ (2R)⁻¹ Δu > χ²_p(1 − α), with Δu = uⱼ − uᵢ (a measurement that lies: biased, stale, replayed).

At α = 10⁻⁴ per test, a fault-free 300-tick run of ``gu_hu_normal`` discards 6 payloads in 3 000 node-ticks.
W-MSR then trims what is left (a liar that stays inside the gate is inside the honest range as well).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy.stats import chi2

ALPHA = 1e-4   #: false-alarm probability of one test of an honest payload


class InformationGate:
    """The gate of one node: ``C``, ``R⁻¹``, ``S⁻¹`` its (the flock's) measurement model, ``beta_max`` the
    largest visibility weight squared a payload may carry (β of (18a) mixtures)."""

    def __init__(self, C: np.ndarray, R_inv: np.ndarray, S_inv: np.ndarray, *, beta_max: float = 1.0,
                 alpha: float = ALPHA):
        CtRi = C.T @ R_inv
        self.G1 = CtRi @ C                       # χ¹ of b = 1
        self.G3 = C.T @ (R_inv - S_inv) @ C      # χ³ of b = 1
        self._g11 = float(np.sum(self.G1 * self.G1))
        self._M = np.linalg.pinv(CtRi)            # χ² → measurement space
        self._S_inv = 0.5 * R_inv                # (2R)⁻¹
        self.threshold = float(chi2.ppf(1.0 - alpha, C.shape[0]))
        self.beta_max = float(beta_max)

    def residual(self, payload: Mapping[str, np.ndarray], x: np.ndarray) -> np.ndarray:
        """u = (C′R⁻¹)⁺ (χ² − χ¹ x̂): a payload's measurement-space residual against the prediction x̂."""
        return self._M @ (payload["chi2"] - payload["chi1"] @ x)

    def suspects(self, own: Mapping[str, np.ndarray], others: Mapping[int, Mapping[str, np.ndarray]],
                 x: np.ndarray) -> list[int]:
        """The neighbours in ``others`` whose payload is inconsistent with ``own`` at the prediction ``x``."""
        u_own = self.residual(own, x)
        tol2 = 1e-12 * self._g11
        G1, G3, vdot = self.G1, self.G3, np.vdot
        out = []
        for j, p in others.items():
            c1, c3 = p["chi1"], p["chi3"]
            beta = float(vdot(c1, G1)) / self._g11
            e1, e3 = c1 - beta * G1, c3 - beta * G3
            if not -1e-12 <= beta <= self.beta_max * (1 + 1e-9) or vdot(e1, e1) > tol2 or vdot(e3, e3) > tol2:
                out.append(j)          # not the information matrices of honest (18a) mixtures
                continue
            du = self.residual(p, x) - u_own
            if float(du @ self._S_inv @ du) > self.threshold:
                out.append(j)          # a measurement that lies
        return out
