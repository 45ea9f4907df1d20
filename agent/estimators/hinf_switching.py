"""Constant-gain distributed H∞ estimation under switching topology (Chen, Qin, He & Liu).

Model (paper Section 2): a target ``x(k+1) = A x(k) + w0(k)`` (1) is observed by n sensors,
``yᵢ(k) = bᵢ(k) C x(k) + wᵢ₁(k)`` (2), where bᵢ(k) = βᵢ when sensor i sees the target at k and 0
otherwise. The sensors talk over a switching undirected graph with weights gᵢⱼ(k); Hₚ = Lₚ + Bₚ.
Every sensor runs the same constant-gain predictor (3)

    x̂ᵢ(k+1) = A x̂ᵢ(k) + A K (yᵢ(k) − bᵢ(k) C x̂ᵢ(k) + zᵢ(k)),
    zᵢ(k)    = Σ_{j∈Nᵢ(k)} gᵢⱼ(k) C (x̂ⱼ(k) − x̂ᵢ(k)) + wᵢ₂(k),

whose stacked error obeys η(k+1) = (Iₙ⊗A − Hₚ(k)⊗AKC) η(k) + D w(k)  (7).

Design-time functions (pure numpy/scipy; computed before a run by the runtime, which knows every
graph, and handed to each sensor as its gain ``K``):

* :func:`riccati`            — the H∞ ARE (9), by fixed-point iteration from P₀ = I.
* :func:`riccati_admissible` — the sign conditions of Lemma 3.1 / Theorem 3.3 (see the note on the
  paper's typo there).
* :func:`constant_gain`      — Theorem 3.3's K = max(1/λ₀, 1) M Cᵀ (C M Cᵀ + R)⁻¹.
* :func:`gamma_bound`        — Theorem 3.9's bound γ ≤ λ₁(W) − Θ with P̄ from (15).
* :func:`tmsee_lower_bound`  — Theorem 3.5's recursion (12) for the TMSEE lower bound tr Z(k).

Run-time: :class:`HinfSwitchingEstimator`, one node of (3) behind the :class:`Estimator` interface;
after the run, :func:`energy_ratio` measures the H∞ performance (8) it was designed for.

Findings about the paper that matter to a user (measured on its Section 4 example, R = 1,
Q = 0.01 I, γ = 0.1, K = [0.9376, 0.5884]ᵀ; see tests/unit/test_hinf_switching.py):

1. **Typo in Theorem 3.3.** The condition printed as ``I − γP⁻¹ > 0`` must be ``I − γP > 0``
   (⟺ P⁻¹ − γI > 0 ⟺ M = (P⁻¹ − γI)⁻¹ > 0): the proof uses
   (P⁻¹ − γI)⁻¹ = P + γP(I − γP)⁻¹P, which is the correct identity, while the printed one is not.
   The printed condition fails at the paper's own γ = 0.1 (λ_min(P) = 0.0805 < 0.1).
   :func:`riccati_admissible` checks the corrected condition. With it the example is admissible for
   γ ≲ 0.4389, while P > 0 alone holds up to γ ≈ 0.48717 — slightly *below* the Theorem 3.9 bound
   0.48739, so that bound is not quite sufficient even for P > 0 (at γ = 0.4873 the iteration
   converges to an indefinite P with λ_min ≈ −905).
2. **Theorem 3.3's gain is not stabilising on every graph.** The proof claims
   (A − λμAK₀C) P (·)ᵀ − P ≤ −Q for every λμ ≥ 1, which is false for large λμ: with the example's
   gain every graph but G1 is unstable on its own (spectral radius of (7) 2.66, 2.34, 2.18 for
   G2, G3, G4). Switching every tick (the paper's listing of bᵢ(k), gᵢⱼ(k)) is stable (≈ 0.94 per
   tick), and so are dwells of 2 and 3 ticks; holding each graph ≥ 4 ticks diverges (e.g. the
   text's "every 1 s" = 10 ticks at T = 0.1 grows ≈ 1.54× per tick).
   :func:`error_transition` gives the matrix of (7) to check a schedule before running it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.linalg

from agent.estimators.base import Estimator, Payload, TickContext, valid_inbox
from agent.estimators.spec import EstimatorSpec, GraphFacts, RunTrace
from agent.schema import Matrix, ScenarioError, check_covariance
from agent.seeding import rng_for
from agent.estimators.consensus import disagreement
from agent.estimators.riccati import is_positive_definite, iterate_to_fixed_point, sym

__all__ = [
    "riccati", "riccati_iterate", "riccati_conditions", "riccati_admissible", "lambda0",
    "constant_gain", "gamma_bound", "tmsee_lower_bound", "error_transition",
    "HinfSwitchingEstimator",
]


def _mat(M, name: str) -> np.ndarray:
    a = np.atleast_2d(np.asarray(M, dtype=float))
    if a.ndim != 2:
        raise ValueError(f"{name} must be a matrix, got shape {a.shape}")
    return a


def _check_model(A, C, Q, R) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    A, C, Q, R = _mat(A, "A"), _mat(C, "C"), _mat(Q, "Q"), _mat(R, "R")
    m = A.shape[0]
    if A.shape != (m, m):
        raise ValueError(f"A must be square, got {A.shape}")
    if C.shape[1] != m:
        raise ValueError(f"C must have {m} columns (state dimension), got {C.shape}")
    q = C.shape[0]
    if Q.shape != (m, m):
        raise ValueError(f"Q must be {m}×{m}, got {Q.shape}")
    if R.shape != (q, q):
        raise ValueError(f"R must be {q}×{q}, got {R.shape}")
    return A, C, Q, R


def _W(C: np.ndarray, R: np.ndarray) -> np.ndarray:
    """W = Cᵀ R⁻¹ C (Theorem 3.9)."""
    return sym(C.T @ np.linalg.solve(R, C))


# --------------------------------------------------------------------------------------- ARE (9)

def riccati_iterate(A, C, Q, R, gamma: float, P0=None, tol: float = 1e-13,
                    max_iter: int = 100_000) -> tuple[np.ndarray, int, bool]:
    """Iterate the H∞ ARE (9) P ← A (P⁻¹ + CᵀR⁻¹C − γI)⁻¹ Aᵀ + Q from P0 (default I).

    Returns ``(P, iterations, converged)`` exactly as the iteration leaves it, whatever its
    inertia. If an iterate makes P⁻¹ + Ω singular the result is a NaN matrix, not converged.
    """
    A, C, Q, R = _check_model(A, C, Q, R)
    m = A.shape[0]
    Omega = _W(C, R) - float(gamma) * np.eye(m)
    P0 = np.eye(m) if P0 is None else _mat(P0, "P0")
    try:
        return iterate_to_fixed_point(P0, Omega, A, Q, tol=tol, max_iter=max_iter)
    except np.linalg.LinAlgError:
        return np.full((m, m), np.nan), 0, False


def riccati(A, C, Q, R, gamma: float, P0=None, tol: float = 1e-13,
            max_iter: int = 100_000) -> np.ndarray:
    """Solve the H∞ algebraic Riccati equation (9)

        P = A (P⁻¹ + Cᵀ R⁻¹ C − γ Iₘ)⁻¹ Aᵀ + Q

    by fixed-point iteration from P₀ = I (shared :func:`iterate_to_fixed_point` with
    Ω = CᵀR⁻¹C − γI). γ = 0 gives the Kalman DARE (15).

    The converged matrix is returned **whatever its inertia**: above the admissible γ the
    iteration converges to an indefinite matrix (paper Fig. 7: λ_min(P) ≈ −37.24 at γ = 0.49 in the
    Section 4 example). Check it with :func:`riccati_admissible`.

    Raises ``RuntimeError`` if the iteration does not converge (or hits a singular P⁻¹ + Ω):
    then there is no fixed point to return. :func:`riccati_iterate` gives the raw last iterate.
    """
    P, it, ok = riccati_iterate(A, C, Q, R, gamma, P0=P0, tol=tol, max_iter=max_iter)
    if not ok:
        why = "hit a singular P⁻¹ + CᵀR⁻¹C − γI" if not np.all(np.isfinite(P)) else \
            f"did not converge in {it} iterations"
        raise RuntimeError(f"ARE (9) fixed-point iteration at γ = {gamma} {why}; "
                           "γ is probably far above the admissible range (see gamma_bound)")
    return P


def riccati_conditions(P, C, R, gamma: float) -> dict[str, bool]:
    """The sign conditions around ARE (9), each reported separately.

    * ``"P_pd"``:       P > 0.
    * ``"lemma_3_1"``:  P⁻¹ + CᵀR⁻¹C − γI > 0 (Lemma 3.1).
    * ``"M_pd"``:       P⁻¹ − γI > 0 ⟺ I − γP > 0, so that M = (P⁻¹ − γI)⁻¹ > 0 — the condition
                        the proof of Theorem 3.3 actually uses (corrected from the printed one).
    * ``"printed_thm_3_3"``: I − γP⁻¹ > 0 as printed in Theorem 3.3 (⟺ P > γI); informational
                        only — it is a typo and fails at the paper's own γ = 0.1.
    """
    P = _mat(P, "P")
    C, R = _mat(C, "C"), _mat(R, "R")
    m = P.shape[0]
    I = np.eye(m)
    g = float(gamma)
    out = {"P_pd": is_positive_definite(P), "lemma_3_1": False, "M_pd": False,
           "printed_thm_3_3": False}
    if not np.all(np.isfinite(P)):
        return out
    try:
        Pinv = np.linalg.inv(P)
    except np.linalg.LinAlgError:
        return out
    out["lemma_3_1"] = is_positive_definite(Pinv + _W(C, R) - g * I)
    out["M_pd"] = is_positive_definite(Pinv - g * I)
    out["printed_thm_3_3"] = is_positive_definite(I - g * Pinv)
    return out


def riccati_admissible(P, C, R, gamma: float) -> bool:
    """True iff P solves (9) admissibly: P > 0, P⁻¹ + CᵀR⁻¹C − γI > 0 (Lemma 3.1) and
    P⁻¹ − γI > 0, i.e. I − γP > 0 (Theorem 3.3, corrected; see :func:`riccati_conditions`)."""
    c = riccati_conditions(P, C, R, gamma)
    return c["P_pd"] and c["lemma_3_1"] and c["M_pd"]


# ------------------------------------------------------------------------------ Lemma 2.1, Thm 3.3

def lambda0(H_list: Sequence[np.ndarray]) -> float:
    """λ₀ of Lemma 2.1: the smallest eigenvalue over all Hₚ = Lₚ + Bₚ.

    Values within 1e-12·max(1, ‖Hₚ‖) of zero are returned as exactly 0.0. (Same as
    ``topology.graph.lambda0``; duplicated because ``agent`` may not import ``topology``.)
    """
    if len(H_list) == 0:
        raise ValueError("λ₀ needs at least one H matrix")
    vals = []
    for H in H_list:
        h = _mat(H, "H")
        if h.shape[0] != h.shape[1]:
            raise ValueError(f"H matrices must be square, got {h.shape}")
        lam = float(np.linalg.eigvalsh(sym(h)).min())
        scale = max(1.0, float(np.abs(h).max()))
        vals.append(0.0 if abs(lam) <= 1e-12 * scale else lam)
    return min(vals)


def constant_gain(A, C, Q, R, gamma: float, H: Sequence[np.ndarray]) -> np.ndarray:
    """Theorem 3.3's static gain

        K = max(1/λ₀, 1) · M Cᵀ (C M Cᵀ + R)⁻¹,   M = (P⁻¹ − γI)⁻¹,

    with P the solution of ARE (9) and λ₀ of Lemma 2.1 over ``H`` (the list of Hₚ = Lₚ + Bₚ of all
    graphs the network may switch among). Returns K of shape (m, q).

    Raises ``ValueError`` if P is not admissible (says which condition fails) or if λ₀ ≤ 0
    (some graph has a component that never sees the target: Assumption 1 fails).

    Caveat (module docstring, finding 2): the theorem does not guarantee that (7) is stable on
    each graph; check your schedule with :func:`error_transition`.
    """
    A, C, Q, R = _check_model(A, C, Q, R)
    lam0 = lambda0(H)
    if lam0 <= 0:
        raise ValueError(f"λ₀ = {lam0:.3g} ≤ 0: some graph has a connected component in which no "
                         "sensor sees the target (Assumption 1 / Lemma 2.1 fail), so no constant "
                         "gain of Theorem 3.3 exists")
    P = riccati(A, C, Q, R, gamma)
    cond = riccati_conditions(P, C, R, gamma)
    failed = [k for k in ("P_pd", "lemma_3_1", "M_pd") if not cond[k]]
    if failed:
        names = {"P_pd": "P > 0", "lemma_3_1": "P⁻¹ + CᵀR⁻¹C − γI > 0 (Lemma 3.1)",
                 "M_pd": "P⁻¹ − γI > 0 (Theorem 3.3, M = (P⁻¹ − γI)⁻¹ > 0)"}
        lam = np.linalg.eigvalsh(P) if np.all(np.isfinite(P)) else [np.nan]
        raise ValueError(f"ARE (9) solution at γ = {gamma} is not admissible: "
                         f"{'; '.join(names[k] for k in failed)} fails "
                         f"(eig(P) = {np.round(lam, 6).tolist()}); lower γ (see gamma_bound)")
    m = A.shape[0]
    M = sym(np.linalg.inv(np.linalg.inv(P) - float(gamma) * np.eye(m)))
    S = C @ M @ C.T + R
    K0 = np.linalg.solve(S.T, (M @ C.T).T).T          # M Cᵀ S⁻¹
    return max(1.0 / lam0, 1.0) * K0


# -------------------------------------------------------------------------------------- Thm 3.9

def gamma_bound(A, C, Q, R) -> float:
    """Theorem 3.9's bound on the H∞ level: 0 ≤ γ ≤ λ₁(W) − Θ, with

        W = Cᵀ R⁻¹ C,
        Θ = (σₙ²(A) λₙ(P̄) − λₙ(P̄) + λₙ(Q)) / (λₙ²(P̄) − λₙ(Q) λₙ(P̄)),

    λ₁ the largest and λₙ the smallest eigenvalue, σₙ the smallest singular value, and P̄ > 0 the
    solution of the Kalman ARE (15) (= ARE (9) at γ = 0), computed with
    ``scipy.linalg.solve_discrete_are``. Returns λ₁(W) − Θ (may be negative: then the theorem
    admits no γ > 0).

    This is the paper's bound for P > 0, derived from necessary inequalities; it is not a
    guarantee. In the Section 4 example the bound is 0.48739 but P > 0 only up to ≈ 0.48717, and
    M = (P⁻¹ − γI)⁻¹ > 0 (needed by Theorem 3.3) only up to ≈ 0.4389. Always check the ARE solution
    with :func:`riccati_admissible`.
    """
    A, C, Q, R = _check_model(A, C, Q, R)
    Pbar = scipy.linalg.solve_discrete_are(A.T, C.T, Q, R)
    if not is_positive_definite(Pbar):
        raise ValueError("the Kalman ARE (15) has no positive definite solution P̄ "
                         "(Theorem 3.9 needs one; is Q > 0 and (A, C) detectable?)")
    ln_P = float(np.linalg.eigvalsh(sym(Pbar)).min())
    ln_Q = float(np.linalg.eigvalsh(sym(Q)).min())
    sn_A = float(np.linalg.svd(A, compute_uv=False).min())
    den = ln_P * ln_P - ln_Q * ln_P
    if den <= 0:
        raise ValueError(f"Θ of Theorem 3.9 is undefined: λₙ(P̄) = {ln_P:.6g} equals "
                         f"λₙ(Q) = {ln_Q:.6g}")
    theta = (sn_A ** 2 * ln_P - ln_P + ln_Q) / den
    return float(np.linalg.eigvalsh(_W(C, R)).max() - theta)


# -------------------------------------------------------------------------------------- Thm 3.5

def tmsee_lower_bound(A, C, Qw, Rn, gamma: float, H_seq: Sequence[np.ndarray], Z0) -> np.ndarray:
    """Theorem 3.5's lower bound tr Z(k), k = 0 … len(H_seq), for the TMSEE
    E(k) = Σᵢ E‖x̂ᵢ(k) − x(k)‖², from the Riccati difference equation (12)

        Z(k+1) = (Iₙ⊗A) (Z(k)⁻¹ + (Hₚ(k)⊗C)ᵀ R̄⁻¹ (Hₚ(k)⊗C) − γ I_{nm})⁻¹ (Iₙ⊗A)ᵀ + 1 1ᵀ ⊗ Q_w.

    Instantiation (the paper writes D₁D₁ᵀ and D₂D₂ᵀ for unit-variance noises):

    * R̄ = D₁D₁ᵀ → Iₙ ⊗ Rₙ, with ``Rn`` (q×q) the covariance of the noise that enters node i's
      innovation yᵢ − bᵢCx̂ᵢ + zᵢ, i.e. measurement plus communication noise, wᵢ₁ + wᵢ₂ (the paper's
      D₁ = diag([I_q I_q], …) with unit variances gives 2I). It enters at every node and every tick
      (yᵢ = wᵢ₁ and zᵢ ⊇ wᵢ₂ even when bᵢ = 0 or Nᵢ = ∅), exactly as in (3).
    * D₂D₂ᵀ → 1 1ᵀ ⊗ Q_w: the target's process noise (``Qw`` = Cov w0, e.g. B Bᵀ σ²) is common to
      every node's error (η(k+1) = … − D₂ w0(k)). It is singular; only Z is inverted, never it.
    * Z(0) = ``Z0`` = E[η(0) η(0)ᵀ] (nm×nm) of the stacked initial errors; for deterministic initial
      errors η(0) this is the rank-one η(0)η(0)ᵀ and then E(0) = tr Z(0) exactly.

    Z may be singular, so the inverse is never formed: (Z⁻¹ + Ω)⁻¹ = (I + Z Ω)⁻¹ Z (a linear solve),
    which is the same matrix when Z is invertible and its limit when it is not.

    Why it is a lower bound (γ = 0): the innovation of node i is exactly row block i of
    (Hₚ⊗C)(X − X̂) + v with X = 1⊗x, so every filter (13) with any time-varying gain K(k) —
    in particular (3) with K(k) = diag(K, …, K) — is a linear predictor for the stacked system
    X(k+1) = (Iₙ⊗A) X + D₂ w0, Y = (Hₚ⊗C) X + v. The Kalman predictor (this recursion at γ = 0)
    minimises the error covariance over all such gains, so E(k) ≥ tr Z(k) when Z(0) is the true
    initial error covariance and R̄, Q_w the true noise covariances.

    With γ > 0 the argument no longer holds: subtracting γI from the information makes Z_γ(k) ≥
    Z_0(k) (Riccati monotonicity), so tr Z_γ is a *larger* number that is not guaranteed to lie
    below E(k) — the paper's proof asserts it without argument. For the Section 4 example with
    γ = 0.1 it still lies below the Monte-Carlo TMSEE of the constant-gain filter (which is far
    from optimal); see the tests. Use γ = 0 for a guaranteed bound.

    Raises ``ValueError`` if Z(k)⁻¹ + Ω stops being positive definite (γ too large for (12)).
    """
    A, C = _mat(A, "A"), _mat(C, "C")
    Qw, Rn = _mat(Qw, "Qw"), _mat(Rn, "Rn")
    m, q = A.shape[0], C.shape[0]
    if len(H_seq) == 0:
        n = _mat(Z0, "Z0").shape[0] // m
    else:
        n = _mat(H_seq[0], "H").shape[0]
    nm = n * m
    Z = sym(_mat(Z0, "Z0"))
    if Z.shape != (nm, nm):
        raise ValueError(f"Z0 must be {nm}×{nm} (n = {n} nodes × m = {m} states), got {Z.shape}")
    if Qw.shape != (m, m) or Rn.shape != (q, q) or C.shape[1] != m:
        raise ValueError("shapes: need A (m×m), C (q×m), Qw (m×m), Rn (q×q)")
    An = np.kron(np.eye(n), A)
    Qbar = np.kron(np.ones((n, n)), Qw)
    Rn_inv = np.linalg.inv(Rn)
    I = np.eye(nm)
    out = [float(np.trace(Z))]
    for k, H in enumerate(H_seq):
        HC = np.kron(_mat(H, "H"), C)
        Omega = HC.T @ np.kron(np.eye(n), Rn_inv) @ HC - float(gamma) * I
        try:
            post = sym(np.linalg.solve(I + Z @ Omega, Z))      # (Z⁻¹ + Ω)⁻¹
        except np.linalg.LinAlgError as exc:
            raise ValueError(f"(12) at k = {k}: Z⁻¹ + Ω is singular (γ = {gamma} too large)") from exc
        lam = np.linalg.eigvalsh(post)
        if lam.min() < -1e-9 * max(1.0, float(np.abs(lam).max())):
            raise ValueError(f"(12) at k = {k}: Z⁻¹ + Ω is not positive definite "
                             f"(γ = {gamma} too large for the stacked recursion)")
        Z = sym(An @ post @ An.T + Qbar)
        out.append(float(np.trace(Z)))
    return np.asarray(out)


def error_transition(A, C, K, H) -> np.ndarray:
    """The stacked error matrix of (7) for one graph: Iₙ ⊗ A − Hₚ ⊗ (A K C).

    Its spectral radius tells whether holding that graph lets the errors grow; the product over a
    schedule's period tells whether the switching loop is stable.
    """
    A, C, K, H = _mat(A, "A"), _mat(C, "C"), _mat(K, "K"), _mat(H, "H")
    n = H.shape[0]
    return np.kron(np.eye(n), A) - np.kron(H, A @ K @ C)


# -------------------------------------------------------------------------------- the node, (3)

class HinfSwitchingEstimator(Estimator):
    """One sensor node of Chen et al.'s constant-gain distributed H∞ filter (3).

    Per tick (DESIGN.md tick protocol, one exchange round):

    * ``start(ctx, y)``: stores yᵢ(k) and bᵢ(k) = ``ctx.b``; draws the communication noise
      wᵢ₂(k) ~ N(0, ``comm_noise_cov``) from ``rng``. It is drawn **once per tick, whether or not
      any neighbour is heard**, so the node's random stream does not depend on which links dropped
      (and a lockstep run reproduces a LocalBus run). It enters zᵢ even with no neighbours, as in
      the paper's definition of zᵢ (and as Theorem 3.5's noise model assumes).
    * ``payload(0) = {"x": x̂ᵢ(k)}``.
    * ``absorb(0, inbox)``: keeps well-formed payloads (``valid_inbox``) from senders in
      ``ctx.neighbours`` and forms zᵢ = C Σⱼ gᵢⱼ (x̂ⱼ − x̂ᵢ) + wᵢ₂ with gᵢⱼ = ``ctx.weight_of(j)``.
      A missing or malformed neighbour is a dropped link (gᵢⱼ = 0 this tick).
    * ``finish()``: x̂ᵢ ← A x̂ᵢ + A K (yᵢ − bᵢ C x̂ᵢ + zᵢ)   (3).

    ``K`` is the design-time gain (:func:`constant_gain`, Theorem 3.3). The filter carries no
    covariance: :attr:`P` is None.

    Parameters
    ----------
    A (m×m), C (q×m), K (m×q), x0 (m,): model, gain and the initial estimate x̂ᵢ(0).
    comm_noise_cov: (q×q) covariance of wᵢ₂ (None: no communication noise is simulated).
    rng: the node's seeded generator; required when ``comm_noise_cov`` is given (every random draw
         must come from a seeded generator — DESIGN.md "Determinism").
    """

    rounds = 1

    def __init__(self, A, C, K, x0, comm_noise_cov=None,
                 rng: np.random.Generator | None = None, resilient_f: int = 0) -> None:
        self.resilient_f = int(resilient_f)  # W-MSR trimming of the neighbour term (0 = eq. (3) as printed)
        self._A = _mat(A, "A")
        self._C = _mat(C, "C")
        m, q = self._A.shape[0], self._C.shape[0]
        if self._A.shape != (m, m) or self._C.shape[1] != m:
            raise ValueError(f"A must be m×m and C q×m, got {self._A.shape} and {self._C.shape}")
        K = np.asarray(K, dtype=float)
        if K.ndim == 1 and q == 1:
            K = K.reshape(m, 1)
        if K.shape != (m, q):
            raise ValueError(f"K must be {m}×{q}, got {K.shape}")
        self._K = K
        self._AK = self._A @ K
        self._m, self._q = m, q
        self._x = self._vec(x0, m, "x0")
        self._noise_factor: np.ndarray | None = None
        if comm_noise_cov is not None:
            S = sym(_mat(comm_noise_cov, "comm_noise_cov"))
            if S.shape != (q, q):
                raise ValueError(f"comm_noise_cov must be {q}×{q}, got {S.shape}")
            w, V = np.linalg.eigh(S)
            if w.min() < -1e-12 * max(1.0, float(np.abs(w).max())):
                raise ValueError("comm_noise_cov must be positive semidefinite")
            if rng is None:
                raise ValueError("comm_noise_cov needs a seeded rng (np.random.Generator)")
            self._noise_factor = V * np.sqrt(np.clip(w, 0.0, None))
        self._rng = rng
        self._ctx: TickContext | None = None
        self._y = np.zeros(q)
        self._b = 0.0
        self._w2 = np.zeros(q)
        self._z = np.zeros(q)

    @staticmethod
    def _vec(v, n: int, name: str) -> np.ndarray:
        a = np.asarray(v, dtype=float).reshape(-1)
        if a.shape != (n,):
            raise ValueError(f"{name} must have {n} entries, got {a.shape[0]}")
        return a.copy()

    # -- Estimator interface ---------------------------------------------------------------
    def start(self, ctx: TickContext, y: np.ndarray) -> None:
        self._ctx = ctx
        self._y = self._vec(y, self._q, "y")
        self._b = float(ctx.b)
        if self._noise_factor is not None:
            self._w2 = self._noise_factor @ self._rng.standard_normal(self._q)
        self._z = self._w2.copy()            # zᵢ with no neighbour heard (yet)

    def payload(self, r: int) -> Payload:
        if r != 0:
            raise ValueError(f"HinfSwitchingEstimator has one exchange round, got r = {r}")
        return {"x": self._x.copy()}

    def absorb(self, r: int, inbox: Mapping[int, Payload]) -> None:
        if r != 0:
            raise ValueError(f"HinfSwitchingEstimator has one exchange round, got r = {r}")
        if self._ctx is None:
            raise RuntimeError("absorb() before start()")
        nbrs = set(self._ctx.neighbours)
        good = valid_inbox(inbox, self.payload_shapes())
        xs = {j: np.asarray(p["x"], dtype=float) for j, p in good.items() if j in nbrs}
        w = {j: self._ctx.weight_of(j) for j in xs}
        self._z = self._C @ disagreement(self._x, xs, w, trim=self.resilient_f) + self._w2

    def finish(self) -> None:
        if self._ctx is None:
            raise RuntimeError("finish() before start()")
        innov = self._y - self._b * (self._C @ self._x) + self._z
        self._x = self._A @ self._x + self._AK @ innov          # (3)
        self._ctx = None

    @property
    def x(self) -> np.ndarray:
        return self._x.copy()

    @property
    def P(self) -> None:
        return None

    @property
    def K(self) -> np.ndarray:
        return self._K.copy()

    def payload_shapes(self) -> dict[str, tuple[int, ...]]:
        return {"x": (self._m,)}

    def report(self) -> dict[str, np.ndarray]:
        """The neighbour-term noise wᵢ₂(k) of this tick (when there is one): part of w(k) in (7)–(8)."""
        return {} if self._noise_factor is None else {"w2": self._w2.copy()}

    def _set_x(self, x: np.ndarray) -> None:
        self._x = self._vec(x, self._m, "x")


# ----------------------------------------------------------------------------- the runtime's spec

@dataclass(frozen=True)
class HinfParams:
    """``[estimator]`` keys of Chen et al.'s estimator: γ of ARE (9), its design weights R and Q
    (default: the identity and the filter's process noise), the covariance of the neighbour-term noise
    wᵢ₂, and λ₀ (a lower bound on λ_min(L + B); a range topology must give it, a schedule's graphs give it)."""

    gamma: float = 0.1
    R_design: Matrix | None = None
    Q_design: Matrix | None = None
    comm_noise: Matrix | None = None
    lambda0: float | None = None


def _check(sc: Any, p: HinfParams) -> None:
    src, m, q = sc.source, sc.m, sc.C.shape[0]
    if p.R_design is not None:
        check_covariance(src, "estimator.R_design", p.R_design, q, "design weight R of ARE (9)")
    if p.Q_design is not None:
        check_covariance(src, "estimator.Q_design", p.Q_design, m, "design weight Q of ARE (9)")
    if p.comm_noise is not None:
        check_covariance(src, "estimator.comm_noise", p.comm_noise, q, "covariance of the neighbour-term noise",
                         semi=True)
    if not p.gamma >= 0:
        raise ScenarioError(src, "estimator.gamma", "γ must be ≥ 0")
    if sc.topology.kind == "range" and p.lambda0 is None:
        raise ScenarioError(src, "estimator.lambda0", "a range topology has no finite list of graphs to take "
                            "λ₀ from", "give lambda0 (a lower bound on λ_min(L + B)) or use a schedule")


def _design(sc: Any, p: HinfParams, facts: GraphFacts) -> dict[str, Any]:
    """The constant gain K (Theorem 3.3) from λ₀ over the schedule's graphs (or the given lambda0), and
    for a schedule the TMSEE lower bound (12) tick by tick."""
    H = list(facts.H_graphs) if facts.H_graphs is not None else [np.eye(1) * float(p.lambda0)]
    Rd = np.eye(sc.C.shape[0]) if p.R_design is None else np.array(p.R_design, float)
    Qd = sc.filter_Q() if p.Q_design is None else np.array(p.Q_design, float)
    out: dict[str, Any] = {"K": np.asarray(constant_gain(sc.A, sc.C, Qd, Rd, p.gamma, H), float).tolist(),
                           # for the run's energy ratio (8): P of ARE (9), γ, and how w enters x(k+1) − A x(k)
                           "P": riccati(sc.A, sc.C, Qd, Rd, p.gamma).tolist(), "gamma": float(p.gamma),
                           "B": np.asarray(sc.B, float).tolist()}
    if facts.H_per_tick is None:
        return out
    n, m = sc.sensors.n, sc.m
    Rn = sc.R + (np.zeros_like(sc.R) if p.comm_noise is None else np.array(p.comm_noise, float))
    Qw = sc.B @ sc.Qw @ sc.B.T
    off = np.zeros((n, m)) if sc.estimator.x0_offsets is None else np.array(sc.estimator.x0_offsets, float)
    Z0 = np.zeros((n * m, n * m))
    for i in range(n):
        Z0[i * m:(i + 1) * m, i * m:(i + 1) * m] = np.outer(off[i], off[i])
    lower = tmsee_lower_bound(sc.A, sc.C, Qw, Rn, p.gamma, list(facts.H_per_tick), Z0)
    out["tmsee_lower"] = np.asarray(lower, float)[: sc.run.ticks].tolist()
    return out


def _build(sc: Any, i: int, p: HinfParams, design: Mapping[str, Any]) -> HinfSwitchingEstimator:
    if "K" not in design:
        raise ValueError("hinf_switching needs the design gain K (computed by the runtime from the schedule)")
    comm = None if p.comm_noise is None else np.array(p.comm_noise, float)
    return HinfSwitchingEstimator(sc.A, sc.C, np.array(design["K"], float), sc.initial_estimates()[i],
                                  comm_noise_cov=comm, rng=rng_for(sc.run.seed, "agent", i, "comm_noise"),
                                  resilient_f=sc.estimator.resilient_f)


def energy_ratio(design: Mapping[str, Any], trace: RunTrace | None) -> dict[str, Any]:
    """``"hinf"``: the run's H∞ performance (8), ‖η‖²₂ ≤ (1/γ)(‖w‖²₂ + η(0)ᵀRη(0)), measured.

    ‖η‖²₂ = Σₖ Σᵢ ‖ηᵢ(k)‖² over the ticks 0…K; ‖w‖²₂ = Σₖ (‖B w₀(k)‖² + Σᵢ ‖wᵢ₁(k)‖² + ‖wᵢ₂(k)‖²), the
    target's disturbance, every sensor's measurement noise and neighbour-term noise as drawn in the run. For
    the initial term, R is the least weighting Theorem 3.3's initial condition ηᵢ(0)ᵀP⁻¹ηᵢ(0) ≤
    (1/γ)ηᵢ(0)ᵀRηᵢ(0) admits: η(0)ᵀRη(0) = γ Σᵢ ηᵢ(0)ᵀP⁻¹ηᵢ(0). ``network_ratio`` ≤ ``bound`` = 1/γ is what
    the theorem promises; ``node_ratio`` (Σₖ‖ηᵢ‖² over the target's and node i's own disturbances and its
    initial term) is given beside it and is not covered by the theorem."""
    if trace is None or len(trace.errors) < 2 or "P" not in design:
        return {"hinf": None}
    E = trace.errors
    K, n = len(E) - 1, E.shape[1]
    gamma, Pinv = float(design["gamma"]), np.linalg.inv(np.array(design["P"], float))
    w0 = trace.w @ np.array(design["B"], float).T if trace.w.size else np.zeros((K, 0))
    target = float(np.sum(w0 ** 2))
    own = []
    for i in range(n):
        w2 = [trace.extra(k, i, "w2") for k in range(K)]
        own.append(float(np.sum(np.square(trace.v[i]))) + sum(float(np.sum(np.square(w))) for w in w2 if w is not None))
    start = [gamma * float(E[0, i] @ Pinv @ E[0, i]) for i in range(n)]
    lhs = [float(np.sum(E[:, i] ** 2)) for i in range(n)]
    rhs = target + sum(own) + sum(start)
    return {"hinf": {"gamma": gamma, "bound": 1.0 / gamma if gamma > 0 else None,
                     "network_ratio": sum(lhs) / rhs if rhs > 0 else None,
                     "holds": bool(gamma > 0 and rhs > 0 and sum(lhs) / rhs <= 1.0 / gamma),
                     "error_energy": sum(lhs), "disturbance_energy": target + sum(own), "initial_term": sum(start),
                     "node_ratio": [lhs[i] / (target + own[i] + start[i]) if target + own[i] + start[i] > 0
                                    else None for i in range(n)]}}


SPEC = EstimatorSpec(name="hinf_switching", params=HinfParams, check=_check, design=_design, build=_build,
                     summary=energy_ratio,
                     doc="Chen et al.'s H∞ consensus estimator (3) under switching topologies")
