"""Whether an estimate's stated uncertainty is honest, and how far it is from the best any filter could do.

Consistency (Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*, §5.4):
a node's estimation error eₖ = x̂ₖ − xₖ against the covariance Pₖ it reported for x̂ₖ (the ``P`` sent with
the previous tick's update, the covariance of x̂ₖ₊₁ then) gives the normalised estimation error squared

    NEESₖ = eₖ′ Pₖ⁻¹ eₖ,

χ²-distributed with m degrees of freedom when the filter's P is its true error covariance. Over K ticks
the average (ANEES) is consistent at 95 % when K·ANEES lies in the two-sided χ²(K·m) interval; below it the
filter is *conservative* (P larger than its errors — what a minimax or H∞ bound is built to be), above it
*optimistic*. The network's ANEES pools the nodes and ticks: the nodes of a consensus filter share their
errors, so its interval (χ²(N·K·m)) is an approximation; a Monte-Carlo set of seeds gives independent
samples (``flocktrack sweep --seeds``). The conservativeness index COIN = λ_max(P̄^{-1/2} Σ̂ P̄^{-1/2}) (Σ̂ the
errors' second moment, P̄ the mean reported covariance) is ≤ 1 for a conservative node.

Efficiency: a centralized Kalman predictor over every sensor's measurements (the scenario's true model,
ideal links, :class:`agent.estimators.kalman.KalmanPredictor` with the tick's visibility weights bᵢ) gives,
for a linear-Gaussian target, the posterior Cramér–Rao bound of one-step prediction, trace(P_centralₖ).
``efficiency`` = MSE / mean trace(P_central) over the scored ticks after the start-up transient (≥ 1 in
expectation; 1 is the best any filter can do); one run's errors are few independent samples, so the ratio to the reference's own MSE on the
same data (``network_vs_central_mse``) is given beside it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.estimators.kalman import KalmanPredictor
from dashboards.nees import chi2_interval, nees


def consistency(errors: np.ndarray, covariances: np.ndarray) -> dict | None:
    """ANEES, its χ² interval, the verdict and COIN of one set of errors (K × m) against the covariances
    reported for them (K × m × m). None without a usable sample (:func:`dashboards.nees.nees`: finite,
    symmetric, positive definite)."""
    eps = nees(errors, covariances)
    keep = np.flatnonzero(np.isfinite(eps))
    if not keep.size:
        return None
    E, P = np.asarray(errors, float)[keep], np.asarray(covariances, float)[keep]
    K, m = E.shape
    anees = float(eps[keep].mean())
    lo, hi = chi2_interval(K * m, K)
    w, V = np.linalg.eigh(P.mean(axis=0))
    root = V @ np.diag(w ** -0.5) @ V.T
    coin = float(np.linalg.eigvalsh(root @ (E.T @ E / K) @ root).max())
    verdict = "consistent" if lo <= anees <= hi else ("conservative" if anees < lo else "optimistic")
    return {"anees": anees, "interval": [lo, hi], "consistent": verdict == "consistent", "verdict": verdict,
            "coin": coin, "samples": K, "dof": m}


@dataclass(frozen=True)
class Reference:
    """The model of the centralized reference: x₊ = A x + w (Q), yᵢ = bᵢ Cᵢ x + vᵢ (Rᵢ), from x̂₀, P₀."""

    A: np.ndarray
    Q: np.ndarray
    Cs: tuple[np.ndarray, ...]
    Rs: tuple[np.ndarray, ...]
    x0: np.ndarray
    P0: np.ndarray

    @classmethod
    def of(cls, sc) -> "Reference | None":
        """The scenario's true model (None for a scenario without one shared linear target model)."""
        try:
            n = sc.sensors.n
            return cls(np.array(sc.A, float), sc.B @ sc.Qw @ sc.B.T, tuple(sc.C_of(i) for i in range(n)),
                       tuple(sc.R_of(i) for i in range(n)), sc.initial_estimates().mean(axis=0),
                       sc.initial_covariance())
        except (AttributeError, TypeError, ValueError):
            return None

    def run(self, measurements: dict[int, dict[int, tuple[float, np.ndarray]]], ticks: int) -> dict[int, tuple]:
        """(x̂ₖ, Pₖ) of the centralized predictor for every tick: the tick's prior, then the update with
        every sensor's ``(b, y)`` of that tick."""
        m = self.A.shape[0]
        kf = KalmanPredictor(self.A, self.Q, np.zeros((0, m)), np.zeros((0, 0)), self.x0, self.P0)
        out: dict[int, tuple] = {}
        for k in range(ticks):
            out[k] = (kf.x.copy(), kf.P.copy())
            seen = measurements.get(k, {})
            rows = [(i, b, y) for i, (b, y) in sorted(seen.items()) if b > 0 and np.isfinite(y).all()]
            if not rows:
                kf.x, kf.P = self.A @ kf.x, self.A @ kf.P @ self.A.T + self.Q
                continue
            kf.C = np.vstack([b * self.Cs[i] for i, b, _y in rows])
            kf.R = _block_diag([self.Rs[i] for i, _b, _y in rows])
            kf.step(np.concatenate([y for _i, _b, y in rows]))
        return out


def _block_diag(blocks: list[np.ndarray]) -> np.ndarray:
    from scipy.linalg import block_diag

    return block_diag(*blocks)


def settled(scored: list[int], central: dict[int, tuple] | None, factor: float = 2.0) -> list[int]:
    """The scored ticks from the end of the reference's start-up transient on: from the first tick whose
    trace(P_central) is within ``factor`` × its median over the scored ticks. Until then the prior (x̂₀, P₀)
    — a guess, not a distribution the target's start was drawn from — dominates both the bound and the
    errors: a P₀ larger than the start's real error makes every filter look conservative and better than
    the bound there, and its few large traces would outweigh the whole steady state in a mean."""
    return _settled(scored, _traces(central), factor)


def _traces(central: dict[int, tuple] | None) -> dict[int, float]:
    """trace(P_centralₖ) by tick, once."""
    return {k: float(np.trace(P)) for k, (_, P) in (central or {}).items()}


def _settled(scored: list[int], traces: dict[int, float], factor: float) -> list[int]:
    known = [traces[k] for k in scored if k in traces]
    if not known:
        return scored
    limit = factor * float(np.median(known))
    for j, k in enumerate(scored):
        if k in traces and traces[k] <= limit:
            return scored[j:]
    return scored


def innovation_consistency(est: dict[int, dict[int, np.ndarray]], cov: dict[int, dict[int, np.ndarray]],
                           meas: dict[int, dict[int, tuple[float, np.ndarray]]], ref: Reference,
                           ticks: list[int]) -> dict[str, dict]:
    """NIS per node: the innovation νₖ = yₖ − bₖCᵢx̂ₖ of its own measurement against the covariance its
    filter implies for it, Sₖ = bₖ²CᵢPₖCᵢ′ + Rᵢ — NISₖ = νₖ′Sₖ⁻¹νₖ, χ²(q) for an honest P. Unlike the
    NEES it needs no truth: a deployed sensor can run it on itself."""
    out: dict[str, dict] = {}
    nodes = sorted({i for k in ticks for i in meas.get(k, {})})
    for i in nodes:
        if i >= len(ref.Cs):
            continue
        C, R = ref.Cs[i], ref.Rs[i]
        nu, S = [], []
        for k in ticks:
            if i in meas.get(k, {}) and i in est.get(k, {}) and i in cov.get(k, {}):
                b, y = meas[k][i]
                if y.shape == (C.shape[0],) and est[k][i].shape == (C.shape[1],):
                    nu.append(y - b * C @ est[k][i])
                    S.append(b * b * C @ cov[k][i] @ C.T + R)
        c = consistency(np.array(nu), np.array(S)) if nu else None
        if c is not None:
            out[str(i)] = c
    return out


def report(truth: dict[int, np.ndarray], est: dict[int, dict[int, np.ndarray]],
           cov: dict[int, dict[int, np.ndarray]], scored: list[int], central: dict[int, tuple] | None, *,
           meas: dict[int, dict[int, tuple[float, np.ndarray]]] | None = None, ref: Reference | None = None) -> dict:
    """The ``credibility`` section of summary.json: per node and for the network, the consistency of each
    node's x̂ₖ against the covariance it reported for it (``cov[k][i]``: the P sent at tick k − 1), and the
    efficiency against the centralized reference (``central``: :meth:`Reference.run`), both over the scored
    ticks after the start-up transient (:func:`settled`; ``from_tick``); with the measurements and the
    reference's model, each node's NIS (:func:`innovation_consistency`)."""
    traces = _traces(central)
    scored = _settled(scored, traces, 2.0)
    nodes = sorted({i for k in scored for i in est.get(k, {})})
    per_node, pooled_e, pooled_P = {}, [], []
    for i in nodes:
        ks = [k for k in scored if i in est.get(k, {}) and i in cov.get(k, {}) and k in truth]
        if not ks:
            continue
        E = np.array([est[k][i] - truth[k] for k in ks])
        P = np.array([cov[k][i] for k in ks])
        c = consistency(E, P)
        if c is not None:
            per_node[str(i)] = c
            pooled_e.append(E)
            pooled_P.append(P)
    out: dict = {"from_tick": scored[0] if scored else None, "nees": per_node}
    if meas and ref is not None:
        out["nis"] = innovation_consistency(est, cov, meas, ref, scored)
    if pooled_e:
        E, P = np.concatenate(pooled_e), np.concatenate(pooled_P)
        out["network"] = consistency(E, P)
        out["consistent_nodes"] = sum(1 for c in per_node.values() if c["consistent"])
    if central:
        ks = [k for k in scored if k in central and k in truth]
        bound = float(np.mean([traces[k] for k in ks])) if ks else math.nan
        ref_mse = float(np.mean([np.sum((central[k][0] - truth[k]) ** 2) for k in ks])) if ks else math.nan
        eff, rel = {}, {}
        for i in nodes:
            errs = [np.sum((est[k][i] - truth[k]) ** 2) for k in ks if i in est.get(k, {})]
            if errs and bound > 1e-12:
                eff[str(i)] = float(np.mean(errs)) / bound
            if errs and ref_mse > 1e-12:
                rel[str(i)] = float(np.mean(errs)) / ref_mse
        out["efficiency"] = {
            "central_trace_P_mean": bound, "central_mse": ref_mse,
            "central_mse_over_trace": ref_mse / bound if bound > 1e-12 else None,
            "per_node": eff, "network": float(np.mean(list(eff.values()))) if eff else None,
            # the same ratio against the reference's own errors on this run's data (one realisation's
            # errors are strongly correlated in time: against the bound a single run is noisy)
            "per_node_vs_central_mse": rel, "network_vs_central_mse": float(np.mean(list(rel.values()))) if rel else None}
    return out
