"""Flocking controller of Gu & Hu (2009), eq. (20), with added velocity damping.

Each sensor i is a double integrator (19), z = [qᵢ, pᵢ], and applies

    uᵢ = −k_c ∂H_c/∂qᵢ − k_r Σ_{j∈Nᵢ} ∂H_s/∂qᵢ − k_d (pᵢ − v̂)                        (20) + damping

with the cohesion potential H_c = ½‖qᵢ − x̂‖² (x̂ the estimated target position) and the separation
potential between neighbours, with d = ‖qᵢ − qⱼ‖,

    H_s(d) = h₁ e^{−d/l₁} − h₂ e^{−d/l₂}      (paper: l₁ = 20, l₂ = 60),
    −∂H_s/∂qᵢ = (h₁/l₁ e^{−d/l₁} − h₂/l₂ e^{−d/l₂}) (qᵢ − qⱼ)/d,

repulsive below the pair distance d* = ln((h₁ l₂)/(h₂ l₁)) / (1/l₁ − 1/l₂) and attractive above it
(d* ≈ 9.3 for h₁ = 100, h₂ = 220).

**Deviation from the paper.** (20) as printed has no damping: each sensor is an undamped
oscillator about the target (q̈ = −k_c (q − x̂) + …), and the zero-order-hold discretisation (19)
of an undamped oscillator is *unstable* (the one-step map has determinant 1 + k_c T²/2 > 1), so the
flock's oscillation about the target grows instead of settling. We add −k_d (pᵢ − v̂), damping each
sensor's velocity towards the estimated target velocity v̂ (k_d = 0 recovers the printed law).
Reference values that work (PAPER_NOTES 000): communication range E = 12, h₁ = 100, h₂ = 220,
k_c = 1, k_r = 30, k_d = 2, 10 sensors on a jittered 2×5 grid of spacing 8, T = 0.04.

:func:`jittered_grid` builds such initial positions.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


class FlockingController:
    """Per-sensor flocking law (20) plus damping; pure function of the current local state.

    Parameters
    ----------
    kc, kr, kd : cohesion, separation and damping gains (kd = 0 is the printed (20)).
    h1, h2 :     separation potential amplitudes.
    l1, l2 :     separation potential length scales (paper: 20 and 60).
    u_max :      optional bound on ‖u‖ (the control is scaled down to it); None = unbounded.
    """

    def __init__(self, kc: float, kr: float, kd: float, h1: float, h2: float,
                 l1: float = 20.0, l2: float = 60.0, u_max: float | None = None):
        self.kc, self.kr, self.kd = float(kc), float(kr), float(kd)
        self.h1, self.h2, self.l1, self.l2 = float(h1), float(h2), float(l1), float(l2)
        self.u_max = None if u_max is None else float(u_max)

    def separation_potential(self, d: np.ndarray | float) -> np.ndarray:
        """H_s(d) = h₁ e^{−d/l₁} − h₂ e^{−d/l₂}."""
        d = np.asarray(d, dtype=float)
        return self.h1 * np.exp(-d / self.l1) - self.h2 * np.exp(-d / self.l2)

    def separation_force(self, d: np.ndarray | float) -> np.ndarray:
        """−dH_s/dd: positive = repulsive, negative = attractive."""
        d = np.asarray(d, dtype=float)
        return self.h1 / self.l1 * np.exp(-d / self.l1) - self.h2 / self.l2 * np.exp(-d / self.l2)

    def equilibrium_distance(self) -> float:
        """Pair distance d* where the separation force vanishes (nan if there is none)."""
        ratio = (self.h1 * self.l2) / (self.h2 * self.l1)
        rate = 1.0 / self.l1 - 1.0 / self.l2
        if ratio <= 0 or rate == 0:
            return float("nan")
        d = np.log(ratio) / rate
        return float(d) if d > 0 else float("nan")

    def control(self, q: np.ndarray, p: np.ndarray, target_pos: np.ndarray, target_vel: np.ndarray | None,
                neighbour_positions: Sequence[np.ndarray] | np.ndarray) -> np.ndarray:
        """u for one sensor at position ``q``, velocity ``p``, given the estimated target position and
        velocity (``target_vel=None`` damps towards zero velocity) and its neighbours' positions."""
        q = np.asarray(q, dtype=float)
        p = np.asarray(p, dtype=float)
        u = -self.kc * (q - np.asarray(target_pos, dtype=float))                      # −k_c ∂H_c/∂q
        nb = np.asarray(neighbour_positions, dtype=float).reshape(-1, q.shape[0])
        if nb.shape[0]:
            diff = q[None, :] - nb
            d = np.linalg.norm(diff, axis=1)
            ok = d > 0.0                       # coincident neighbour: direction undefined, skip it
            if np.any(ok):
                f = self.separation_force(d[ok])
                u = u + self.kr * np.sum((f / d[ok])[:, None] * diff[ok], axis=0)      # −k_r Σ ∂H_s/∂q
        v_ref = np.zeros_like(p) if target_vel is None else np.asarray(target_vel, dtype=float)
        u = u - self.kd * (p - v_ref)                                                 # damping (added)
        if self.u_max is not None:
            norm = float(np.linalg.norm(u))
            if norm > self.u_max:
                u = u * (self.u_max / norm)
        return u


def jittered_grid(n: int, rows: int, spacing: float, jitter: float, rng: np.random.Generator,
                  origin: Sequence[float] | np.ndarray = (0.0, 0.0)) -> np.ndarray:
    """n initial 2-D positions on a ``rows`` × ceil(n/rows) grid of the given spacing, each moved by a
    uniform jitter in [−jitter, jitter]² (drawn from ``rng``). The unjittered grid is centred on
    ``origin``. Returns an (n, 2) array, filled row by row."""
    cols = int(np.ceil(n / rows))
    idx = np.arange(n)
    r, c = idx // cols, idx % cols
    base = np.stack([c * spacing, r * spacing], axis=1).astype(float)
    base -= np.array([(cols - 1) * spacing, (rows - 1) * spacing]) / 2.0
    return base + np.asarray(origin, dtype=float) + rng.uniform(-jitter, jitter, size=(n, 2))
