"""The UAV target-tracking simulation of García Carrillo et al., Section IV-A (pure numpy).

* :class:`UnicycleTarget` — a kinematic unicycle ground target (the paper's [35]) in a rectangular
  area (600 m × 300 m): constant speed, piecewise-constant turn rate redrawn every few seconds, and a
  steering rule that turns it back towards the centre when it is about to leave the area.
* :class:`UavRelativeSim` — UAV agents orbiting the target, each measuring the target's position
  relative to its own, asynchronously at about ``rate_hz`` (jittered periods, random phase), with
  Gaussian noise, outliers (the noise *replaced* by a vector of length U(40, 70) m in a uniformly random
  direction) for a configurable fraction of the measurements, and Gaussian GPS noise on the UAV's own
  position. Every draw comes from the caller's ``numpy.random.Generator``.

Beyond the paper, ``outlier_model`` selects how the outlier fraction f is realised:

* ``"uniform"`` (the paper's): f·M measurements, their noise replaced by a U(40, 70) m vector in a
  uniformly random direction;
* ``"student_t"``: *every* measurement's noise is heavy-tailed, a bivariate Student-t with scale σ_rel
  and ν degrees of freedom, ν chosen so that P(‖n‖ > 40 m) = f (:func:`student_nu_for`; ν = 3.2 at
  1 %, 0.75 at 20 %; ``student_nu`` > 0 fixes ν instead) — no clean/outlier split, outliers of every size;
* ``"burst"``: the outliers come in runs of ``burst_length`` consecutive measurements of one UAV
  (≈ f·M in total), each run displaced by one U(40, 70) m vector (a false target) plus the usual noise.

The paper does not state the noise figures; PAPER_NOTES 004: ≈ 5.7 m per axis in total (here
σ_rel = 5.5 m relative + σ_gps = 1.5 m GPS per axis, √(5.5² + 1.5²) = 5.70 m), which reproduces the
published RMS measurement error within a few % for 1–15 % outliers. The published 35.24 m at 20 %
cannot occur with 40–70 m outliers (the RMS is then at most ≈ 26 m).

:func:`config_from_tables` builds both from the plain dict of ``scenarios/carrillo_uav.toml`` (the
caller parses the file; this module does no I/O).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from .estimators.relative_measurement import RelativeMeasurement


@dataclass(frozen=True)
class UnicycleConfig:
    x0: tuple[float, float] = (0.0, 0.0)      #: start position (m)
    heading0: float = 2.3                      #: start heading (rad, 0 = +x)
    speed: float = 6.0                         #: constant ground speed (m/s)
    turn_rate_max: float = 0.25                #: |ω| of the random segments (rad/s)
    segment_s: tuple[float, float] = (2.0, 8.0)  #: duration range of a constant-ω segment (s)
    sharp_turn_prob: float = 0.15              #: probability that a segment is a sharp turn
    sharp_turn_rate: float = 0.8               #: |ω| of a sharp turn (rad/s), lasting 1–2.5 s
    area: tuple[float, float, float, float] = (-450.0, 150.0, -50.0, 250.0)  #: xmin, xmax, ymin, ymax
    margin: float = 40.0                       #: distance to the boundary where steering back starts (m)
    wall_turn_rate: float = 0.5                #: |ω| while steering back (rad/s)
    dt: float = 0.01                           #: integration step (s)


@dataclass(frozen=True)
class UavConfig:
    n: int = 2                                 #: number of UAV agents (ids 1..n)
    rate_hz: float = 5.0                       #: mean measurement rate of each UAV (≈ 10 Hz in total)
    jitter: float = 0.3                        #: period jitter: T·(1 + jitter·U(−1, 1))
    orbit_radius: float = 100.0                #: UAV orbit radius around the target (m)
    orbit_rate: float = 0.12                   #: angular rate of the orbit (rad/s)
    sigma_rel: float = 5.5                     #: relative-measurement noise σ per axis (m)
    sigma_gps: float = 1.5                     #: GPS noise σ per axis (m)
    outlier_fraction: float = 0.05             #: fraction of measurements that are outliers
    outlier_range: tuple[float, float] = (40.0, 70.0)  #: outlier vector length range (m)
    outlier_mode: str = "exact"                #: "exact" (round(f·M) chosen) | "bernoulli" (each w.p. f)
    delay_mean: float = 0.0                    #: mean exponential transport delay (s) → arrival order
    outlier_model: str = "uniform"             #: "uniform" (the paper's) | "student_t" | "burst" (module doc)
    burst_length: int = 5                      #: consecutive outliers of one UAV per burst ("burst")
    student_nu: float = 0.0                    #: ν of "student_t" (0: from the outlier fraction)


@dataclass
class UavStream:
    """One simulated run: measurement arrays (time order) plus truth.

    t, agent (M,);  z, gps (M, 2) as measured;  R, gps_R (2, 2) nominal covariances;
    truth_pos, truth_vel, uav_pos (M, 2) true values at each measurement time;  outlier (M,) bool;
    arrival (M,) arrival times (t + transport delay);  dense: (t, pos, vel) of the target every dt.
    """

    t: np.ndarray
    agent: np.ndarray
    z: np.ndarray
    gps: np.ndarray
    R: np.ndarray
    gps_R: np.ndarray
    truth_pos: np.ndarray
    truth_vel: np.ndarray
    uav_pos: np.ndarray
    outlier: np.ndarray
    arrival: np.ndarray
    dense: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    def record(self, i: int) -> RelativeMeasurement:
        return RelativeMeasurement(int(self.agent[i]), float(self.t[i]), self.z[i], self.R, self.gps[i], self.gps_R)

    def records(self) -> list[RelativeMeasurement]:
        """Measurement records in time order."""
        return [self.record(i) for i in range(len(self))]

    def arrival_order(self) -> np.ndarray:
        """Indices in order of arrival (stable for equal arrival times)."""
        return np.argsort(self.arrival, kind="stable")

    def measured_target(self) -> np.ndarray:
        """Raw measured target positions gps + z (M, 2)."""
        return self.gps + self.z

    def measurement_rmse(self) -> float:
        e = self.measured_target() - self.truth_pos
        return float(np.sqrt(np.mean(np.sum(e * e, axis=1))))


def student_nu_for(fraction: float, sigma: float, radius: float) -> float:
    """ν of the bivariate Student-t with scale σ for which P(‖n‖ > radius) = fraction:
    P(‖n‖ > r) = (1 + r²/(νσ²))^(−ν/2) (‖n‖²/(2σ²) ~ F(2, ν)), solved by bisection on log ν."""
    if not 0.0 < fraction < 1.0:
        raise ValueError("the fraction must lie in (0, 1)")
    a = (radius / sigma) ** 2

    def tail(nu):
        return (1.0 + a / nu) ** (-nu / 2.0)

    lo, hi = 1e-3, 1e4          # tail() decreases in ν
    for _ in range(200):
        mid = math.sqrt(lo * hi)
        if tail(mid) > fraction:
            lo = mid
        else:
            hi = mid
    return math.sqrt(lo * hi)


class UnicycleTarget:
    """Kinematic unicycle ṗ = v(cos θ, sin θ), θ̇ = ω, simulated on a fine grid (see module doc)."""

    def __init__(self, cfg: UnicycleConfig = UnicycleConfig()):
        self.cfg = cfg

    def simulate(self, duration: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
        c = self.cfg
        nstep = int(math.ceil(duration / c.dt)) + 1
        t = np.arange(nstep) * c.dt
        pos = np.empty((nstep, 2))
        vel = np.empty((nstep, 2))
        omega = np.empty(nstep)
        x, y = c.x0
        th = c.heading0
        xmin, xmax, ymin, ymax = c.area
        cx, cy = 0.5 * (xmin + xmax), 0.5 * (ymin + ymax)
        seg_end = 0.0
        w_seg = 0.0
        for k in range(nstep):
            tk = t[k]
            if tk >= seg_end:
                if rng.random() < c.sharp_turn_prob:
                    w_seg = c.sharp_turn_rate * (1.0 if rng.random() < 0.5 else -1.0)
                    seg_end = tk + rng.uniform(1.0, 2.5)
                else:
                    w_seg = rng.uniform(-c.turn_rate_max, c.turn_rate_max)
                    seg_end = tk + rng.uniform(*c.segment_s)
            w = w_seg
            near = (x < xmin + c.margin or x > xmax - c.margin or y < ymin + c.margin or y > ymax - c.margin)
            if near:
                want = math.atan2(cy - y, cx - x)
                err = (want - th + math.pi) % (2.0 * math.pi) - math.pi
                if abs(err) > 0.35:
                    w = c.wall_turn_rate * (1.0 if err > 0 else -1.0)
            pos[k] = (x, y)
            vel[k] = (c.speed * math.cos(th), c.speed * math.sin(th))
            omega[k] = w
            # exact arc over one step
            if abs(w) > 1e-12:
                x += c.speed / w * (math.sin(th + w * c.dt) - math.sin(th))
                y += -c.speed / w * (math.cos(th + w * c.dt) - math.cos(th))
            else:
                x += c.speed * math.cos(th) * c.dt
                y += c.speed * math.sin(th) * c.dt
            th += w * c.dt
        return {"t": t, "pos": pos, "vel": vel, "omega": omega}


def _interp(tq: np.ndarray, t: np.ndarray, Y: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(tq, t, Y[:, j]) for j in range(Y.shape[1])], axis=1)


class UavRelativeSim:
    """UAVs measuring the target's relative position (see module doc). ``generate(duration, rng)``."""

    def __init__(self, uav: UavConfig = UavConfig(), target: UnicycleConfig = UnicycleConfig()):
        if uav.outlier_mode not in ("exact", "bernoulli"):
            raise ValueError("outlier_mode must be 'exact' or 'bernoulli'")
        if uav.outlier_model not in ("uniform", "student_t", "burst"):
            raise ValueError("outlier_model must be 'uniform', 'student_t' or 'burst'")
        if uav.burst_length < 1:
            raise ValueError("burst_length must be ≥ 1")
        if not 0.0 <= uav.outlier_fraction <= 1.0:
            raise ValueError("outlier_fraction must lie in [0, 1]")
        self.uav = uav
        self.target = UnicycleTarget(target)

    def measurement_times(self, duration: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        u = self.uav
        T = 1.0 / u.rate_hz
        ts, ids = [], []
        for i in range(1, u.n + 1):
            tk = rng.uniform(0.0, T)
            while tk <= duration:
                ts.append(tk)
                ids.append(i)
                tk += T * (1.0 + u.jitter * rng.uniform(-1.0, 1.0))
        t = np.array(ts)
        a = np.array(ids, np.int64)
        o = np.lexsort((a, t))
        return t[o], a[o]

    def generate(self, duration: float, rng: np.random.Generator) -> UavStream:
        u = self.uav
        dense = self.target.simulate(duration, rng)
        t, agent = self.measurement_times(duration, rng)
        M = t.shape[0]
        tp = _interp(t, dense["t"], dense["pos"])
        tv = _interp(t, dense["t"], dense["vel"])
        phase = 2.0 * math.pi * (agent - 1) / max(u.n, 1)
        ang = u.orbit_rate * t + phase
        uav_pos = tp + u.orbit_radius * np.stack([np.cos(ang), np.sin(ang)], axis=1)
        noise = rng.normal(0.0, u.sigma_rel, size=(M, 2))
        if u.outlier_model == "student_t":
            out = self._student_t(noise, rng)
        elif u.outlier_model == "burst":
            out = self._bursts(noise, agent, rng)
        else:
            out = self._uniform(noise, rng)
        z = tp - uav_pos + noise
        gps = uav_pos + rng.normal(0.0, u.sigma_gps, size=(M, 2))
        delay = rng.exponential(u.delay_mean, size=M) if u.delay_mean > 0 else np.zeros(M)
        return UavStream(t=t, agent=agent, z=z, gps=gps, R=np.eye(2) * u.sigma_rel ** 2,
                         gps_R=np.eye(2) * u.sigma_gps ** 2, truth_pos=tp, truth_vel=tv, uav_pos=uav_pos,
                         outlier=out, arrival=t + delay, dense=dense)

    def _uniform(self, noise: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The paper's outliers (module doc), written into ``noise``; returns the outlier mask."""
        u = self.uav
        M = noise.shape[0]
        if u.outlier_mode == "exact":
            k = int(round(u.outlier_fraction * M))
            out = np.zeros(M, bool)
            out[rng.choice(M, size=k, replace=False)] = True
        else:
            out = rng.random(M) < u.outlier_fraction
        k = int(out.sum())
        mag = rng.uniform(u.outlier_range[0], u.outlier_range[1], size=k)
        phi = rng.uniform(0.0, 2.0 * math.pi, size=k)
        noise[out] = mag[:, None] * np.stack([np.cos(phi), np.sin(phi)], axis=1)
        return out

    def _student_t(self, noise: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Bivariate Student-t noise n = g/√(χ²_ν/ν) (g the Gaussian draw already in ``noise``); the mask
        flags ‖n‖ beyond the outlier range's lower end."""
        u = self.uav
        nu = u.student_nu if u.student_nu > 0 else student_nu_for(u.outlier_fraction, u.sigma_rel,
                                                                   u.outlier_range[0])
        w = rng.chisquare(nu, size=noise.shape[0]) / nu
        noise /= np.sqrt(w)[:, None]
        return np.hypot(noise[:, 0], noise[:, 1]) > u.outlier_range[0]

    def _bursts(self, noise: np.ndarray, agent: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Runs of ``burst_length`` consecutive outliers of one UAV (non-overlapping), round(f·M/L) runs,
        each adding one U(40, 70) m vector in a random direction to the noise."""
        u = self.uav
        M, L = noise.shape[0], u.burst_length
        out = np.zeros(M, bool)
        seqs = [np.flatnonzero(agent == i) for i in range(1, u.n + 1)]
        k = int(round(u.outlier_fraction * M / L))
        placed, tries = 0, 0
        while placed < k and tries < 100 * (k + 1):
            tries += 1
            sq = seqs[int(rng.integers(len(seqs)))]
            if sq.size < L:
                continue
            run = sq[int(rng.integers(sq.size - L + 1)):][:L]
            if out[run].any():
                continue
            out[run] = True
            mag = rng.uniform(u.outlier_range[0], u.outlier_range[1])
            phi = rng.uniform(0.0, 2.0 * math.pi)
            noise[run] += mag * np.array([math.cos(phi), math.sin(phi)])
            placed += 1
        return out


# ----------------------------------------------------------------------------- configuration


def _build(cls, table: dict | None, where: str):
    table = dict(table or {})
    names = {f.name: f for f in fields(cls)}
    unknown = sorted(set(table) - set(names))
    if unknown:
        raise ValueError(f"[{where}] unknown key(s) {unknown}; known: {sorted(names)}")
    kw: dict[str, Any] = {}
    for k, v in table.items():
        default = getattr(cls, k, None) if not isinstance(getattr(cls, k, None), property) else None
        if isinstance(default, tuple):
            v = tuple(float(e) for e in v)
        elif isinstance(default, bool):
            v = bool(v)
        elif isinstance(default, int) and not isinstance(default, bool):
            v = int(v)
        elif isinstance(default, float):
            v = float(v)
        kw[k] = v
    return cls(**kw)


FUSION_MODE_KEYS = ("mode", "admm_iterations", "admm_rho")   #: [fusion] keys of the mode, not of the estimator


@dataclass(frozen=True)
class CarrilloScenario:
    """Everything ``scenarios/carrillo_uav.toml`` specifies (see that file for every key)."""

    seed: int = 1
    duration: float = 100.0
    target: UnicycleConfig = UnicycleConfig()
    uav: UavConfig = UavConfig()
    fusion: dict = field(default_factory=dict)
    baselines: dict = field(default_factory=dict)
    table: dict = field(default_factory=dict)

    def sim(self, **uav_overrides) -> UavRelativeSim:
        from dataclasses import replace

        return UavRelativeSim(replace(self.uav, **uav_overrides), self.target)

    @property
    def fusion_mode(self) -> str:
        """``[fusion] mode``: "central" (one fusion process, the default) or "distributed" (each UAV fuses its
        own measurements and agrees with the others by consensus ADMM, :mod:`agent.estimators.admm_fusion`)."""
        return str(self.fusion.get("mode", "central"))

    def admm(self) -> dict:
        """``[fusion] admm_iterations`` (per tick) and ``admm_rho`` of the distributed mode."""
        return {"iterations": int(self.fusion.get("admm_iterations", 8)), "rho": float(self.fusion.get("admm_rho", 0.05))}

    def make_estimators(self, source: str = "scenario") -> dict:
        """The fusion role's estimators from ``[fusion]`` and ``[baselines]``: {<[fusion] estimator>: …,
        "bls": …, "kalman_q<q>": …, "robust_kalman_q<q>": …} (fresh objects). The fusion estimator is the
        :class:`agent.estimators.spec.FusionSpec` named by ``[fusion] estimator`` (errors name ``source``)."""
        from .estimators.fusion_baselines import BatchLeastSquares, KalmanCV, RobustKalmanCV
        from .estimators.registry import build_fusion

        name, son = build_fusion({k: v for k, v in self.fusion.items() if k not in FUSION_MODE_KEYS}, source)
        W = son.W
        b = self.baselines
        out = {name: son,
               "bls": BatchLeastSquares(W=int(b.get("bls_window", W)), q=son.q, max_lateness=son.window.max_lateness,
                                        dt_floor=son.dt_floor, whitening=son.window.whitening)}
        for q in b.get("kalman_q", [5000.0, 1.0]):
            out[f"kalman_q{float(q):g}"] = KalmanCV(q=float(q), max_lateness=son.window.max_lateness)
        for q in b.get("robust_kalman_q", []):
            out[f"robust_kalman_q{float(q):g}"] = RobustKalmanCV(q=float(q), max_lateness=son.window.max_lateness)
        return out


def config_from_tables(data: dict) -> CarrilloScenario:
    """Build a :class:`CarrilloScenario` from the parsed TOML tables (unknown keys are errors)."""
    run = dict(data.get("run", {}))
    known_top = {"run", "target", "uavs", "fusion", "baselines", "table"}
    unknown = sorted(set(data) - known_top)
    if unknown:
        raise ValueError(f"unknown table(s) {unknown}; known: {sorted(known_top)}")
    tgt = dict(data.get("target", {}))
    tgt.pop("kind", None)
    return CarrilloScenario(seed=int(run.get("seed", 1)), duration=float(run.get("duration", 100.0)),
                            target=_build(UnicycleConfig, tgt, "target"),
                            uav=_build(UavConfig, data.get("uavs"), "uavs"),
                            fusion=dict(data.get("fusion", {})), baselines=dict(data.get("baselines", {})),
                            table=dict(data.get("table", {})))


class StreamTarget:
    """The target of a generated run replayed on the tick grid: x = [p, v] at t = kT (``step`` advances k)."""

    def __init__(self, stream: UavStream, T: float):
        self.dense, self.T, self.k = stream.dense, float(T), 0
        self.x = self._at(0)

    def _at(self, k: int) -> np.ndarray:
        t = min(k * self.T, float(self.dense["t"][-1]))
        p = _interp(np.array([t]), self.dense["t"], self.dense["pos"])[0]
        v = _interp(np.array([t]), self.dense["t"], self.dense["vel"])[0]
        return np.concatenate([p, v])

    def step(self) -> np.ndarray:
        self.k += 1
        self.x = self._at(self.k)
        return self.x.copy()
