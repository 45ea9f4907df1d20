"""Distributed robust moving-horizon fusion by consensus ADMM: one node per UAV, each fusing its own
measurements and agreeing with the others on the target's trajectory (García Carrillo et al., Section V:
"distributing the solver among the agents" — their stated future work).

The problem
-----------
The central window of :mod:`robust_mhe` is, over the target states X (N × 4: [p, v] at each of the window's N
nodes, the union of every UAV's measurement times) and each UAV's private positions Uᵢ,

    min  a(X) + m(X) + Σᵢ fᵢ(X, Uᵢ),

a = the arrival cost on the oldest node, m = the motion rows (2) between consecutive nodes (Huber, as in the
window), fᵢ = UAV i's own rows: the GPS rows (3) and relative rows (4) of its measurements (Huber at the
common threshold δ). As a consensus problem (Boyd et al., "Distributed optimization … ADMM", 2011, §7.1)
with Fᵢ = fᵢ + (a + m)/M over the M UAVs taking part,

    min Σᵢ Fᵢ(Xᵢ, Uᵢ)  s.t.  Xᵢ = Z,

and scaled ADMM, node i's three steps per iteration (Boyd (7.6)):

    (Xᵢ, Uᵢ) ← argmin Fᵢ + ρ/2‖Xᵢ − Z + Yᵢ‖²      — its own robust window: Newton on its Huber rows;
    Z        ← mean over the M nodes of (Xⱼ + Yⱼ)   — every node computes it from the same payloads,
                                                       in sender order, so every node holds the same Z;
    Yᵢ       ← Yᵢ + Xᵢ − Z.

Fᵢ is convex, so Z → the central solution; warm-started from the previous tick (Z and Yᵢ shifted to the new
window) a few iterations per tick suffice (``iterations``; the tests hold the RMSE within 5 % of the
central :class:`robust_mhe.RobustMHE` on the same data). A UAV's measurements never leave its process:
only node times, consensus vectors and, when one of its nodes leaves the window, that node's posterior.

The tick protocol (the sensor role's exchange rounds, :mod:`agent.estimators.base`)
-------------------------------------------------------------------------------------
``rounds = 1 + iterations``. Round 0: each node reports its own window nodes (time and current state), its
arrival cost (with the eviction count, the scale σ̂ and the last normalised residual ν̃) — the union of the
reports is the window of the tick, the newest arrival cost reported is everybody's (so a node that missed
one, or rejoins empty, takes it over), and M = the nodes heard. Rounds 1…: one ADMM iteration each; after
the first, a node drops its own relative rows whose residual exceeds ``reject``·σ̂ (the central estimator's
gross-outlier re-solve). A node not heard in a round ends consensus for the tick: the rest is solved alone,
and its payloads say so, so that the others leave too; the duals start again from 0 at the next tick (a
node reports in round 0 whether it ended the last one in consensus). Solving alone is also what a node with
no peer does every tick — it keeps estimating from its own data.

Window and arrival cost: as in :class:`robust_mhe.RobustMHE` — at the end of a tick with N ≥ W nodes the
oldest leaves (and, chained, the next ones of the same UAV); its owner folds it into the arrival cost with
:func:`robust_window.fold_node` at the consensus solution (the others take the result over in the next round 0)
and the scale σ̂ (δ = c·σ̂) moves with it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from .base import Estimator, Payload, TickContext
from .riccati import huber_curvature, huber_psi, predict, white_noise_acceleration
from .robust_window import HUBER_C, ArrivalCost, RobustScale, fold_node
from .son_layout import motion_weights
from .relative_measurement import RelativeMeasurement

__all__ = ["AdmmFusionNode", "ArrivalRecord", "run_lockstep"]

_NO_TIME = -1e300          #: the arrival time of the initial arrival cost (no node has left yet)


@dataclass(frozen=True)
class ArrivalRecord:
    """The arrival cost every node agrees on: the posterior (mean, cov) of [p, v] at the time ``t`` of the
    last node that left the window (``evictions`` so far; 0: none yet, the initial prior), the scale σ̂ and
    the normalised residual ν̃ that node added to it."""

    evictions: int = 0
    t: float = _NO_TIME
    mean: np.ndarray = field(default_factory=lambda: np.zeros(4))
    cov: np.ndarray = field(default_factory=lambda: np.eye(4))
    sigma: float = 1.0
    nu: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def pack(self) -> np.ndarray:
        return np.concatenate([[self.evictions, self.t], self.mean, self.cov.ravel(), [self.sigma], self.nu])

    @classmethod
    def unpack(cls, v: np.ndarray) -> "ArrivalRecord":
        return cls(int(v[0]), float(v[1]), v[2:6].copy(), v[6:22].reshape(4, 4).copy(), float(v[22]), v[23:25].copy())

    def newer_than(self, other: "ArrivalRecord") -> bool:
        return (self.t, self.evictions) > (other.t, other.evictions)


@dataclass
class _Axis:
    """One axis' local problem (x and y decouple: diagonal covariances): dense rows H (m × n), right-hand
    side z, weights w (1/M on the shared rows, 0 on a rejected row), quadratic-row mask; variables
    [p₀, v₀, p₁, v₁, …, then one u per own node]."""

    H: np.ndarray
    z: np.ndarray
    w: np.ndarray
    quad: np.ndarray
    rel_rows: np.ndarray     # row index of each own node's relative row


class AdmmFusionNode(Estimator):
    """UAV ``i``'s node of the distributed robust moving-horizon fusion (module doc).

    ``records(k)``: this UAV's own relative measurements that arrive during tick k (its data; nobody
    else's). Window, motion and threshold parameters are :class:`robust_mhe.RobustMHE`'s; ``iterations``
    ADMM iterations per tick with penalty ``rho`` (in the states' units: m, m/s); ``T`` the tick period.
    After :meth:`finish`, :attr:`newest` / :attr:`t_newest` are the consensus estimate at the window's newest
    node, :attr:`x` that estimate predicted to the end of the tick.
    """

    def __init__(self, i: int, records: Callable[[int], Sequence[RelativeMeasurement]], W: int = 15,
                 q: float = 3.0, iterations: int = 8, rho: float = 0.05, c: float = HUBER_C, reject: float = 3.0,
                 scale_window: int = 300, dt_floor: float = 0.02, whitening: str = "chol",
                 robust_motion: bool = True, p0_sigma: float = 1e3, v0_sigma: float = 20.0, T: float = 0.05,
                 max_nodes: int | None = None):
        if W < 2 or iterations < 1 or not rho > 0 or not T > 0:
            raise ValueError("W ≥ 2, iterations ≥ 1, rho > 0 and T > 0")
        self.i, self.records = int(i), records
        self.W, self.q, self.c, self.reject, self.rho = int(W), float(q), float(c), float(reject), float(rho)
        self.dt_floor, self.robust_motion, self.T = float(dt_floor), bool(robust_motion), float(T)
        self._mode = 0 if whitening == "chol" else 1
        self.p0_sigma, self.v0_sigma = float(p0_sigma), float(v0_sigma)
        self.rounds = 1 + int(iterations)
        self.cap = int(max_nodes or 2 * W + 8)       # own nodes a round-0 report can carry
        self.scale = RobustScale(int(scale_window), sigma0=1.0, c=self.c)
        self.arrival = ArrivalRecord()
        self._own: dict[float, RelativeMeasurement] = {}        # own window nodes by time
        self._z: dict[tuple[float, int], np.ndarray] = {}        # consensus state per node (t, owner)
        self._y: dict[tuple[float, int], np.ndarray] = {}        # scaled dual per node
        self._u: dict[float, np.ndarray] = {}                    # own private agent position per own node
        self._parts_prev: tuple[int, ...] = ()
        self._solved_key: tuple | None = None
        self._moved = False
        self._clean = False          # the last tick ended in consensus (round 0 tells the others)
        self.newest = np.zeros(4)
        self.t_newest = math.nan
        self._x = np.zeros(4)
        self.counters = {"ticks_alone": 0, "ticks_consensus": 0, "rounds_broken": 0, "rejected_rows": 0,
                         "evicted": 0, "adopted_arrival": 0, "bad_payloads": 0}

    # ------------------------------------------------------------------ Estimator interface
    @property
    def x(self) -> np.ndarray:
        return self._x

    def start(self, ctx: TickContext, y: np.ndarray) -> None:
        self._k, self._t_end = ctx.k, (ctx.k + 1) * self.T
        for rec in self.records(ctx.k):
            if rec.agent == 0 or rec.R[0, 1] != 0.0 or rec.gps_R[0, 1] != 0.0:
                raise ValueError("the distributed fusion takes relative measurements with diagonal covariances")
            if rec.t > self.arrival.t and rec.t not in self._own:
                self._own[rec.t] = rec
        self._peers = tuple(ctx.neighbours)
        self._parts: tuple[int, ...] = (self.i,)
        self._nodes: list[tuple[float, int]] = []
        self._rejected: set[float] = set()
        self._alone = True

    def payload(self, r: int) -> Payload:
        if r == 0:
            return self._report()
        if not self._nodes:
            return {"xy": np.zeros(0), "sig": self._signature()}
        if not self._alone:
            self._local_step()
        xy = self._X + self._Y
        return {"xy": xy.ravel().copy(), "sig": self._signature()}

    def absorb(self, r: int, inbox: Mapping[int, Payload]) -> None:
        if r == 0:
            self._join(inbox)
            return
        if self._alone:
            return
        heard = {}
        for j in self._parts:
            if j == self.i:
                continue
            p = inbox.get(j)
            if p is None or not self._fits(p):
                break
            heard[j] = p["xy"].reshape(-1, 4)
        else:
            # the sum in sender order (self included at its place) so every node computes the same Z
            acc = None
            for j in self._parts:
                v = (self._X + self._Y) if j == self.i else heard[j]
                acc = v.copy() if acc is None else acc + v
            self._Z = acc / len(self._parts)
            self._Y = self._Y + self._X - self._Z
            if r == 1:
                self._reject_gross(self._Z)
            return
        self.counters["rounds_broken"] += 1
        self._go_alone()

    def finish(self) -> None:
        self._moved = False
        if not self._nodes:
            self._x = self._predicted(self._t_end)
            return
        if self._alone:
            self.counters["ticks_alone"] += 1
        else:
            self.counters["ticks_consensus"] += 1
        Z = self._Z
        self._z = {key: Z[n].copy() for n, key in enumerate(self._nodes)}
        self._y = {key: self._Y[n].copy() for n, key in enumerate(self._nodes)}
        self._parts_prev = self._parts
        self._clean = not self._alone
        self._solved_key = self._problem_key() if self._alone else None
        self._moved = self._nodes[-1][0] != self.t_newest
        self.newest, self.t_newest = Z[-1].copy(), self._nodes[-1][0]
        self._evict()
        self._x = self._predicted(self._t_end)

    def predict_only(self, ctx: TickContext, q: int) -> None:
        """A tick sat out (the world marks this UAV dead, or its tick was lost): its measurements of the
        tick are not fused and nothing is exchanged."""
        self._t_end = (ctx.k + 1) * self.T
        self._x = self._predicted(self._t_end)

    def report(self) -> dict[str, np.ndarray]:
        """Beside the published estimate: the newest node's state and time, when this tick moved them."""
        if self._moved:
            return {"t_newest": np.array([self.t_newest]), "newest": self.newest.copy()}
        return {}

    def reinitialise(self, neighbour_estimates, neighbour_covariances=None) -> None:
        """A restarted node takes the window over from its peers' round-0 reports instead."""

    # ------------------------------------------------------------------ round 0: who is here, which window
    def _report(self) -> Payload:
        mine = sorted(self._own)[-self.cap:]
        rows = np.zeros((self.cap, 5))
        for n, t in enumerate(mine):
            rows[n, 0] = t
            rows[n, 1:] = self._z.get((t, self.i), self._guess(t))
        return {"nodes": rows, "count": np.array([float(len(mine))]), "arrival": self.arrival.pack(),
                "clean": np.array([1.0 if self._clean else 0.0])}

    def _guess(self, t: float) -> np.ndarray:
        """A new own node's first state: the newest consensus state before it predicted to t, else the
        measured target position at rest."""
        before = [key for key in self._z if key[0] < t]
        if before:
            key = max(before)
            F, _ = white_noise_acceleration(t - key[0], self.q)
            return F @ self._z[key]
        p = self._own[t].target_position
        return np.array([p[0], p[1], 0.0, 0.0])

    def _join(self, inbox: Mapping[int, Payload]) -> None:
        reports = {self.i: self._report()}
        for j in sorted(inbox):
            p = inbox[j]
            if j in self._peers and self._valid_report(p):
                reports[j] = p
            elif j in self._peers:
                self.counters["bad_payloads"] += 1
        newest = self.arrival
        for j in sorted(reports):
            a = ArrivalRecord.unpack(reports[j]["arrival"])
            if a.newer_than(newest):
                newest = a
        if newest is not self.arrival:
            self.arrival = newest
            self.scale.push(newest.nu)
            self.scale.sigma = newest.sigma
            self.counters["adopted_arrival"] += 1
        t_a = self.arrival.t
        self._own = {t: m for t, m in self._own.items() if t > t_a}
        states: dict[tuple[float, int], np.ndarray] = {}
        for j, p in reports.items():
            rows = p["nodes"][: int(p["count"][0])]
            for row in rows:
                if row[0] > t_a:
                    states[(float(row[0]), j)] = row[1:].copy()
        self._nodes = sorted(states)
        if not self._nodes:
            return
        self._parts = tuple(sorted(reports))
        # the duals carry over only if every participant ended the last tick in consensus with the same others
        same = self._parts == self._parts_prev and all(reports[j]["clean"][0] == 1.0 for j in self._parts)
        self._Z = np.array([self._z.get(key, states[key]) for key in self._nodes])
        self._Y = np.array([self._y[key] if same and key in self._y else np.zeros(4) for key in self._nodes])
        self._delta = self.scale.delta
        self._build()
        if len(self._parts) == 1:
            self._go_alone()
        else:
            self._alone = False
            self._X = self._Z.copy()

    def _valid_report(self, p: Payload) -> bool:
        try:
            ok = (p["nodes"].shape == (self.cap, 5) and p["count"].shape == (1,) and p["arrival"].shape == (25,)
                  and p["clean"].shape == (1,)
                  and 0 <= p["count"][0] <= self.cap and np.isfinite(p["nodes"]).all()
                  and np.isfinite(p["arrival"]).all())
            return bool(ok and np.all(np.linalg.eigvalsh(p["arrival"][6:22].reshape(4, 4)) > 0))
        except (KeyError, AttributeError, np.linalg.LinAlgError):
            return False

    def _problem_key(self) -> tuple:
        """What the alone window solution depends on (the window, its arrival cost, δ)."""
        return (tuple(self._nodes), self.arrival.evictions, self.arrival.t, self._delta)

    def _signature(self) -> np.ndarray:
        """[N, Σ node times, 1 if this node has left consensus for the tick]: a peer whose window differs, or
        that went alone (it missed a payload), breaks the round for the others too."""
        return np.array([float(len(self._nodes)), float(sum(t for t, _ in self._nodes)), float(self._alone)])

    def _fits(self, p: Payload) -> bool:
        xy, sig = p.get("xy"), p.get("sig")
        return (isinstance(xy, np.ndarray) and xy.shape == (4 * len(self._nodes),) and np.isfinite(xy).all()
                and isinstance(sig, np.ndarray) and sig.shape == (3,) and np.array_equal(sig, self._signature()))

    # ------------------------------------------------------------------ the local problem
    def _prior(self) -> ArrivalCost:
        """The arrival cost on the window's oldest node."""
        return self._prior_at(self._nodes[0][0], self._Z[0])

    def _build(self) -> None:
        """The two axes' rows for this tick's window (shared rows weighted 1/M)."""
        nodes = self._nodes
        N = len(nodes)
        own = [n for n, (t, j) in enumerate(nodes) if j == self.i]
        self._own_idx = own
        M = len(self._parts)
        aW, az = self._prior().per_axis()
        self._axes = []
        for a in range(2):
            m = 2 + 2 * (N - 1) + 2 * len(own)
            H = np.zeros((m, 2 * N + len(own)))
            z, w, quad = np.zeros(m), np.full(m, 1.0 / M), np.zeros(m, bool)
            H[0:2, 0:2] = aW[a]
            z[0:2] = az[a]
            quad[0:2] = True
            r = 2
            for n in range(1, N):
                dt = nodes[n][0] - nodes[n - 1][0]
                Wm = motion_weights(dt, self.q, self.dt_floor, self._mode)
                for row in range(2):
                    a0, a1 = Wm[row, 0], Wm[row, 1]
                    H[r, 2 * n - 2:2 * n + 2] = (-a0, -(a0 * dt + a1), a0, a1)
                    quad[r] = not self.robust_motion
                    r += 1
            rel = np.empty(len(own), np.int64)
            for jj, n in enumerate(own):
                rec = self._own[nodes[n][0]]
                cu = 2 * N + jj
                wg, wr = 1.0 / math.sqrt(rec.gps_R[a, a]), 1.0 / math.sqrt(rec.R[a, a])
                H[r, cu], z[r], w[r] = wg, wg * rec.gps[a], 1.0
                H[r + 1, cu], H[r + 1, 2 * n], z[r + 1] = -wr, wr, wr * rec.z[a]
                w[r + 1] = 0.0 if nodes[n][0] in self._rejected else 1.0
                rel[jj] = r + 1
                r += 2
            self._axes.append(_Axis(H, z, w, quad, rel))
        self._U = np.array([self._u.get(nodes[n][0], self._own[nodes[n][0]].gps) for n in own]).reshape(-1, 2)

    def _solve(self, X: np.ndarray, V: np.ndarray | None, iters: int, tol: float) -> np.ndarray:
        """argmin Fᵢ(X, U) (+ ρ/2‖X − V‖² if V is given) from (X, self._U); updates self._U. Per axis,
        Newton's method on the piecewise-quadratic Huber objective (Hessian HᵀΘH with Θ = ψ′ the rows'
        curvature, :func:`riccati.huber_curvature`) with a backtracking line search — the active set is
        found in a few steps from a warm start."""
        N = len(self._nodes)
        out = np.empty_like(X)
        d = self._delta
        for a, ax in enumerate(self._axes):
            x = np.concatenate([np.column_stack([X[:, a], X[:, 2 + a]]).ravel(), self._U[:, a]])
            v = None if V is None else np.column_stack([V[:, a], V[:, 2 + a]]).ravel()
            f = self._axis_objective(ax, x, v)
            for _ in range(iters):
                res = ax.z - ax.H @ x
                psi = np.where(ax.quad, res, huber_psi(res, d))
                theta = np.where(ax.quad, 1.0, huber_curvature(res, d))
                g = -ax.H.T @ (ax.w * psi)
                A = ax.H.T @ ((ax.w * theta)[:, None] * ax.H)
                if v is not None:
                    g[: 2 * N] += self.rho * (x[: 2 * N] - v)
                    A[np.arange(2 * N), np.arange(2 * N)] += self.rho
                if float(np.max(np.abs(g))) < tol:
                    break
                A[np.diag_indices_from(A)] += 1e-9 * (1.0 + float(np.max(np.diag(A))))
                step = -np.linalg.solve(A, g)
                slope = float(g @ step)
                t = 1.0
                while True:
                    xn = x + t * step
                    fn = self._axis_objective(ax, xn, v)
                    if fn <= f + 1e-4 * t * slope or t < 1e-6:
                        break
                    t *= 0.5
                x, f = xn, fn
                if t == 1.0:   # a full step: done if it stayed on the same piece (its exact minimiser)
                    rn = ax.z - ax.H @ x
                    if np.array_equal(np.where(ax.quad, 1.0, huber_curvature(rn, d)), theta):
                        break
                if float(np.max(np.abs(t * step))) < tol:
                    break
            out[:, a], out[:, 2 + a] = x[0:2 * N:2], x[1:2 * N:2]
            self._U[:, a] = x[2 * N:]
        return out

    def _axis_objective(self, ax: _Axis, x: np.ndarray, v: np.ndarray | None) -> float:
        r = ax.z - ax.H @ x
        d = self._delta
        a = np.abs(r)
        h = np.where(ax.quad | (a <= d), 0.5 * r * r, d * a - 0.5 * d * d)
        f = float(ax.w @ h)
        if v is not None:
            e = x[: v.shape[0]] - v
            f += 0.5 * self.rho * float(e @ e)
        return f

    def _local_step(self) -> None:
        self._X = self._solve(self._X, self._Z - self._Y, iters=20, tol=1e-10)

    def _go_alone(self) -> None:
        """No (more) consensus this tick: solve the window alone, all shared rows at full weight, the
        central estimator's gross-outlier re-solve included."""
        if len(self._parts) > 1:
            self._parts = (self.i,)
            self._build()
        self._alone = True
        self._Y = np.zeros_like(self._Z)
        if self._problem_key() == self._solved_key:      # nothing new since the last tick: same solution
            self._X = self._Z
            return
        X = self._solve(self._Z, None, iters=50, tol=1e-10)
        if self._reject_gross(X):
            X = self._solve(X, None, iters=50, tol=1e-10)
        self._Z = self._X = X

    def _reject_gross(self, X: np.ndarray) -> bool:
        """Drop own relative rows whose residual at X exceeds reject·σ̂ (for the rest of the tick)."""
        lim = self.reject * self.scale.sigma
        new = False
        for jj, n in enumerate(self._own_idx):
            t = self._nodes[n][0]
            rec = self._own[t]
            r = (rec.z - (X[n, :2] - self._U[jj])) / np.sqrt(np.diag(rec.R))
            if t not in self._rejected and np.max(np.abs(r)) > lim:
                self._rejected.add(t)
                for ax in self._axes:
                    ax.w[ax.rel_rows[jj]] = 0.0
                self.counters["rejected_rows"] += 1
                new = True
        return new

    # ------------------------------------------------------------------ the window moves on
    def _evict(self) -> None:
        """At N ≥ W the oldest node leaves (and, chained, the next ones of the same owner); its owner folds
        it into the arrival cost, the others take that over in the next round 0."""
        own_u = {self._nodes[n][0]: self._U[jj].copy() for jj, n in enumerate(self._own_idx)}
        self._u = own_u
        nodes = list(self._nodes)
        owner = nodes[0][1]
        while len(nodes) >= self.W and nodes[0][1] == owner:
            t0, _ = nodes.pop(0)
            self.counters["evicted"] += 1
            if owner == self.i:
                rec = self._own.pop(t0)
                prior = self._prior_at(t0, self._z[(t0, owner)])
                s = np.sqrt(np.diag(rec.R))
                Wr, Wg = np.diag(1.0 / s), np.diag(1.0 / np.sqrt(np.diag(rec.gps_R)))
                mean, cov, nu = fold_node(prior, rec, Wr, Wg, self._z[(t0, owner)], own_u.pop(t0), self._delta,
                                          self.reject * self.scale.sigma)
                self.scale.push(nu)
                self.arrival = ArrivalRecord(self.arrival.evictions + 1, t0, mean, cov, self.scale.sigma, nu)
            self._z.pop((t0, owner), None)
            self._y.pop((t0, owner), None)
            if owner != self.i:
                break               # the owner's posterior arrives in the next round 0
        self._nodes = nodes

    def _prior_at(self, t0: float, state: np.ndarray) -> ArrivalCost:
        """The arrival cost on a node at time t0 whose current state is ``state``: the initial prior around
        its position before any node has left, else the last posterior predicted to t0."""
        a = self.arrival
        if a.evictions == 0:
            p2, v2 = self.p0_sigma ** 2, self.v0_sigma ** 2
            return ArrivalCost(np.array([state[0], state[1], 0.0, 0.0]), np.diag([p2, p2, v2, v2]))
        F, Q = white_noise_acceleration(max(t0 - a.t, 0.0), self.q, self.dt_floor)
        return ArrivalCost(*predict(a.mean, a.cov, F, Q))

    def _predicted(self, t: float) -> np.ndarray:
        if math.isfinite(self.t_newest):
            F, _ = white_noise_acceleration(max(t - self.t_newest, 0.0), self.q)
            return F @ self.newest
        return self._x


def run_lockstep(nodes: Mapping[int, AdmmFusionNode], T: float, ticks: range,
                 alive: Callable[[int, int], bool] | None = None,
                 on_tick: Callable[[int], None] | None = None,
                 lost: Callable[[int, int, int, int], bool] | None = None) -> None:
    """Run the nodes through ``ticks`` in one process, every payload delivered (the in-process reference a
    lockstep run over Zenoh must equal). ``alive(k, i)``: whether node i takes part in tick k (default:
    always); one that does not sits the tick out (:meth:`AdmmFusionNode.predict_only`) and is nobody's
    neighbour. ``on_tick(k)`` after every tick; ``lost(k, r, i, j)``: whether i's round-r payload of tick k
    fails to reach j (a dropped link)."""
    ids = sorted(nodes)
    for k in ticks:
        up = [i for i in ids if alive is None or alive(k, i)]
        for i in ids:
            if i in up:
                nbrs = tuple(j for j in up if j != i)
                nodes[i].start(TickContext(k=k, t=k * T, n=len(ids), neighbours=nbrs, T=T), np.zeros(0))
            else:
                nodes[i].predict_only(TickContext(k=k, t=k * T, n=len(ids), b=0.0, T=T), 0)
        for r in range(nodes[ids[0]].rounds):
            out = {i: nodes[i].payload(r) for i in up}
            for i in up:
                nodes[i].absorb(r, {j: out[j] for j in up if j != i and not (lost and lost(k, r, j, i))})
        for i in up:
            nodes[i].finish()
        if on_tick is not None:
            on_tick(k)
