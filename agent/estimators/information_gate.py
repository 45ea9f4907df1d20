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

A lie smaller than the noise passes that test every tick, and still moves the flock's estimate by its size over
the number of sensors. So each round-0 payload — a neighbour's own raw (18a) triple, when its β is the node's own
— also feeds a running residual per neighbour, m ← (1 − λ) m + λ Δu/√β, tested against its covariance
(λ/(2 − λ)) (1 − (1 − λ)²ⁿ) 2R at ``ALPHA_RUN``: a steady bias of half the noise's σ shows within ~1/λ ticks.

A lie told in every round — a replayed neighbour's payload with its estimate moved — is no larger in round 0,
but the honest payloads of later rounds are mixtures that agree ever more closely (on ``gu_hu_normal`` the mean
d²/p between honest neighbours falls from 1.0 in round 0 to 0.19, 0.07, 0.03, 0.016 in rounds 1–4), while the
lie stays. So for each round r ≥ 1 the gate keeps, per neighbour, a running mean m of the visibility-normalised
residual difference z = uⱼ/βⱼ − uᵢ/βᵢ (zero-mean between honest payloads whatever their β: the prediction error
cancels) and a slower running second moment V of z, and tests m′V⁻¹m against the same scaled χ² at
``ALPHA_SPREAD`` (stricter than ``ALPHA_RUN``: V is itself an estimate, and a flag holds from tick to tick): a
test that needs no model of how far apart honest mixtures are, only that they are unbiased.
A neighbour that any running test flags is discarded in every round, from that round on, until its tests
clear.

At these settings a fault-free 400-tick run of ``gu_hu_normal`` discards 6 payloads in 4 000 node-ticks (0.15 %
of them), the flocking demo 44 in 4 800. W-MSR then trims what is left (a liar that stays inside the gate is
inside the honest range as well).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy.stats import chi2

ALPHA = 1e-4   #: false-alarm probability of one test of an honest payload
LAMBDA = 0.02  #: forgetting factor of each neighbour's running residual (a memory of ~1/λ ticks)
ALPHA_RUN = 1e-3   #: false-alarm probability of one test of a running residual
LAMBDA_V = 0.005   #: forgetting factor of the running second moment of a later round's residual
WARMUP = 30        #: updates of a later round's second moment before it is tested
ALPHA_SPREAD = 1e-6   #: false-alarm probability of one test of a later round's running residual


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
        self.run_threshold = float(chi2.ppf(1.0 - ALPHA_RUN, C.shape[0]))
        self.spread_threshold = float(chi2.ppf(1.0 - ALPHA_SPREAD, C.shape[0]))
        self._run: dict[int, tuple[np.ndarray, int]] = {}   # neighbour → (running residual, updates)
        self._spread: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, int]] = {}  # (j, r) → (m, V, updates)
        self._flags: dict[int, set[int]] = {}   # neighbour → the rounds whose running test flags it

    @property
    def drifting(self) -> set[int]:
        """The neighbours some running test flags: discarded in every round while it does."""
        return {j for j, f in self._flags.items() if f}

    def _flag(self, j: int, r: int, on: bool) -> None:
        if on:
            self._flags.setdefault(j, set()).add(r)
        elif j in self._flags:
            self._flags[j].discard(r)

    def residual(self, payload: Mapping[str, np.ndarray], x: np.ndarray) -> np.ndarray:
        """u = (C′R⁻¹)⁺ (χ² − χ¹ x̂): a payload's measurement-space residual against the prediction x̂."""
        return self._M @ (payload["chi2"] - payload["chi1"] @ x)

    def suspects(self, own: Mapping[str, np.ndarray], others: Mapping[int, Mapping[str, np.ndarray]],
                 x: np.ndarray, r: int = 0) -> list[int]:
        """The neighbours in ``others`` whose payload of round ``r`` is inconsistent with ``own`` at the
        prediction ``x``; each round also updates the neighbours' running tests (round 0 the running residual,
        later rounds the running agreement)."""
        u_own = self.residual(own, x)
        beta_own = float(np.vdot(own["chi1"], self.G1)) / self._g11
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
            u = self.residual(p, x)
            du = u - u_own
            lies = float(du @ self._S_inv @ du) > self.threshold     # a measurement that lies
            if not lies and beta > 1e-9 and beta_own > 1e-9:
                if r > 0:                # a lie told in every round, against the later rounds' closer agreement
                    self._flag(j, r, self._spread_off(j, r, u / beta - u_own / beta_own))
                elif abs(beta - beta_own) <= 1e-9 * beta:
                    self._flag(j, 0, self._runs_off(j, du / np.sqrt(beta)))   # a small lie, every tick
            if lies or self._flags.get(j):
                out.append(j)
        return out

    def _runs_off(self, j: int, z: np.ndarray) -> bool:
        """Fold the noise-scale residual z (≈ vⱼ − vᵢ ~ N(0, 2R) between honest raw payloads) into neighbour j's
        running mean m ← (1 − λ) m + λ z, and test m against its own covariance
        (λ / (2 − λ)) (1 − (1 − λ)^{2n}) 2R at ``ALPHA_RUN``: a bias a fraction of the noise shows within ~1/λ ticks."""
        m, n = self._run.get(j, (np.zeros_like(z), 0))
        m, n = (1 - LAMBDA) * m + LAMBDA * z, n + 1
        self._run[j] = (m, n)
        scale = _ewma_variance(n)
        return float(m @ self._S_inv @ m) / scale > self.run_threshold

    def _spread_off(self, j: int, r: int, z: np.ndarray) -> bool:
        """Fold round ``r``'s normalised residual difference z into neighbour j's running mean m (λ = ``LAMBDA``)
        and second moment V (λ = ``LAMBDA_V``), and test m′V⁻¹m / ((λ/(2 − λ)) (1 − (1 − λ)^{2n})) against χ²
        at ``ALPHA_SPREAD`` once V has ``WARMUP`` updates. V is not centred: a steady lie only makes it larger,
        so the test stays conservative for a neighbour that lies from its first tick."""
        m, V, n = self._spread.get((j, r), (np.zeros_like(z), np.zeros((z.size, z.size)), 0))
        m = (1 - LAMBDA) * m + LAMBDA * z
        V = (1 - LAMBDA_V) * V + LAMBDA_V * np.outer(z, z)
        n += 1
        self._spread[(j, r)] = (m, V, n)
        if n < WARMUP:
            return False
        Vn = V / (1 - (1 - LAMBDA_V) ** n)          # the EWMA's start-up bias removed
        scale = _ewma_variance(n)
        try:
            t = float(m @ np.linalg.solve(Vn, m))
        except np.linalg.LinAlgError:
            return False
        return t / scale > self.spread_threshold


def _ewma_variance(n: int) -> float:
    """The variance of a running mean m ← (1 − λ) m + λ z after ``n`` updates from 0, per unit variance of z:
    (λ / (2 − λ)) (1 − (1 − λ)^{2n}), λ = ``LAMBDA``."""
    return LAMBDA / (2 - LAMBDA) * (1 - (1 - LAMBDA) ** (2 * n))
