"""Typed scenario schema and loader: TOML → frozen dataclasses, with errors that name the file, the
key and what was expected (and how to fix it).

A scenario has these tables (every key optional unless marked *required*; see ``scenarios/*.toml``):

``[run]``        name, ticks, T (s), seed, mode ("lockstep" | "realtime"), deadline_s, burn_in, speed,
                 pace ("fixed" | "adaptive")
``[target]``     kind ("normal" | "intelligent"), model ("double_integrator" | "matrices" | "continuous"), dim,
                 A, B, Q (covariance of w in x⁺ = Ax + Bw), x0 (*required*), ke, estimate_source
``[sensors]``    n (*required*), C, R | (D, v_std), positions | (grid_rows, spacing, jitter, origin), motion
                 ("flocking" | "static"), sensing_range, beta
``[estimator]``  name (a registered estimator, :func:`agent.estimators.registry.names`), the common keys
                 rounds, eta, Q, P0, x0, x0_offsets, resilient_f — and the chosen estimator's own keys
                 (its spec's parameters dataclass, e.g. S for minimax, gamma for hinf_switching)
``[topology]``   kind ("range" | "schedule"), range, dwell_ticks, [[topology.graphs]] (edges, b, weights)
``[control]``    flocking gains kc, kr, kd, h1, h2, l1, l2, u_max
``[faults]``     seed, link_loss, [[faults.events]] (see topology/faults.py)

A file with ``[uavs]`` is the other kind of world: García Carrillo et al.'s UAVs and fusion role
(:attr:`Scenario.uav`, a :class:`agent.models_uav.CarrilloScenario`).

Overrides (``--set section.key=value``, sweep grids, :meth:`Scenario.with_overrides`) all go through
:func:`override` on the TOML mapping before validation: one mechanism. This module reads a file only in
:func:`scenario_data` / :func:`load_scenario`.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from .estimators.registry import default_name, fusion_specs
from .estimators.registry import names as estimator_names
from .estimators.registry import spec_of
from .estimators.spec import NoParams
from .models import double_integrator
from .schema import (LIMITS, Matrices, Matrix, Pairs, ScenarioError, Vector, build_table, check_covariance,
                     check_shape)
from .seeding import rng_for
from .suggest import did_you_mean
from .wire import BYZANTINE_MODES, FAULT_DIRECTIONS, FAULT_KINDS, FAULT_LIMITS, MAX_EVADE_ACCEL

if TYPE_CHECKING:
    from .models_uav import CarrilloScenario

__all__ = ["Scenario", "ScenarioError", "load_scenario", "parse_scenario", "scenario_data", "override",
           "parse_fault_event", "validate_fault_event", "FAULT_KINDS"]


# ----------------------------------------------------------------------------- sections

@dataclass(frozen=True)
class RunCfg:
    name: str = "run"
    ticks: int = 100
    T: float = 0.1
    seed: int = 0
    mode: Literal["lockstep", "realtime"] = "lockstep"
    #: per-wait deadline (lockstep: only guards against dead processes; a sensor's round waits this long, the
    #: target's and the world's waits, which enclose the rounds, (R + 2) and (R + 3) times it)
    deadline_s: float = 5.0
    burn_in: int = 0         #: ticks excluded from the RMSE summaries
    speed: float = 1.0       #: realtime factor: a tick lasts T / speed seconds of wall-clock time
    #: realtime: "adaptive" — the clock yields while the flock cannot keep it and comes back when it can
    #: (topology/pace.py); "fixed" — it keeps T / speed whatever the flock does
    pace: Literal["fixed", "adaptive"] = "adaptive"


@dataclass(frozen=True)
class TargetCfg:
    x0: Vector = field(default_factory=list)
    kind: Literal["normal", "intelligent"] = "normal"
    #: double_integrator (A, B from T), matrices (discrete A, B), continuous (ẋ = Ax + Bw, w held over a tick)
    model: Literal["double_integrator", "matrices", "continuous"] = "double_integrator"
    dim: int = 2
    A: Matrix | None = None
    B: Matrix | None = None
    Q: Matrix | None = None
    ke: float = 0.0
    estimate_source: str = "mean"  #: "mean" of all node estimates, or "node:<i>"


@dataclass(frozen=True)
class SensorsCfg:
    n: int = 0
    C: Matrix | Matrices | None = None   #: one q×m matrix, or one matrix per sensor
    R: Matrix | None = None
    D: Matrix | Matrices | None = None   #: yᵢ = Cᵢx + Dᵢvᵢ, vᵢ ~ N(0, v_std² I) (instead of R)
    v_std: float = 1.0
    positions: Matrix | None = None
    grid_rows: int = 2
    spacing: float = 8.0
    jitter: float = 0.0
    origin: Vector = field(default_factory=lambda: [0.0, 0.0])
    motion: Literal["flocking", "static"] = "static"
    sensing_range: float = math.inf
    beta: float = 1.0


@dataclass(frozen=True)
class EstimatorCommon:
    """The ``[estimator]`` keys every estimator shares (its own keys are its spec's ``params``)."""

    name: str = ""           #: a registered estimator (agent.estimators.registry.names()); "" = the default
    rounds: int = 1
    eta: str = "1/(dmax+1)"
    Q: Matrix | None = None
    P0: Matrix | None = None
    x0: Vector | None = None
    x0_offsets: Matrix | None = None
    resilient_f: int = 0  #: W-MSR: tolerate up to f Byzantine neighbours (0 = plain consensus)


@dataclass(frozen=True)
class EstimatorCfg(EstimatorCommon):
    """``[estimator]``: the common keys and ``params``, the chosen estimator's own (its spec's dataclass)."""

    params: Any = field(default_factory=NoParams)


@dataclass(frozen=True)
class GraphCfg:
    edges: Pairs = field(default_factory=list)
    b: Vector = field(default_factory=list)
    weights: Vector | None = None


@dataclass(frozen=True)
class TopologyCfg:
    kind: Literal["range", "schedule"] = "range"
    range: float = math.inf
    dwell_ticks: int = 1
    graphs: list[GraphCfg] = field(default_factory=list)


@dataclass(frozen=True)
class ControlCfg:
    kc: float = 1.0
    kr: float = 30.0
    kd: float = 2.0
    h1: float = 100.0
    h2: float = 220.0
    l1: float = 20.0
    l2: float = 60.0
    u_max: float | None = None


@dataclass(frozen=True)
class FaultEventCfg:
    """One scheduled fault (Jepsen-style nemesis with explicit heal); see topology/faults.py."""

    kind: Literal[FAULT_KINDS] = "link_loss"      #: (the one list of fault kinds: agent.wire.FAULT_KINDS)
    start: int = 0
    heal: int | None = None
    targets: str = "all"      #: all | agents:1,2 | links:0-1,2-3 | random:k | most_connected | halves | groups:0,0,1,…
    p: float = 1.0            #: link_loss / duplicate / reorder probability
    direction: Literal[FAULT_DIRECTIONS] = "both"
    delay_ticks: int = 1      #: delay in ticks (lockstep-friendly: a payload held k ticks arrives late)
    jitter_ticks: int = 0     #: + a uniform integer in [−jitter_ticks, jitter_ticks] per payload (≥ 0 overall)
    delay_ms: float = 0.0     #: delay in wall-clock ms instead of ticks (> 0 switches to ms; realtime: what
    jitter_ms: float = 0.0    #:   misses its round's deadline is lost); + uniform ±jitter_ms per payload
    mode: Literal[BYZANTINE_MODES] = "bias"
    bias: Vector | None = None
    magnitude: float = 50.0   #: outlier norm; "huge" Byzantine factor is 1e6
    noise_scale: float = 3.0
    accel: float = 2.0


@dataclass(frozen=True)
class FaultsCfg:
    seed: int | None = None   #: default: the run seed
    link_loss: float = 0.0    #: shorthand: every directed link drops with this probability, all run long
    events: list[FaultEventCfg] = field(default_factory=list)


@dataclass(frozen=True)
class Scenario:
    run: RunCfg
    target: TargetCfg
    sensors: SensorsCfg
    estimator: EstimatorCfg = field(default_factory=EstimatorCfg)
    topology: TopologyCfg = field(default_factory=TopologyCfg)
    control: ControlCfg = field(default_factory=ControlCfg)
    faults: FaultsCfg = field(default_factory=FaultsCfg)
    source: str = "<scenario>"
    #: García Carrillo et al.'s UAV/fusion world when the file has [uavs] (``kind == "uav_fusion"``)
    uav: CarrilloScenario | None = None
    #: the TOML mapping this scenario was parsed from (overrides apply to it, then it is parsed again)
    data: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def kind(self) -> Literal["flock", "uav_fusion"]:
        """Which world: a flock of sensors running a distributed estimator (the default), or García
        Carrillo et al.'s UAVs whose measurements go to a fusion role."""
        return "flock" if self.uav is None else "uav_fusion"

    # ------------------------------------------------------------------ derived model matrices
    @property
    def A(self) -> np.ndarray:
        return self.target_matrices()[0]

    @property
    def B(self) -> np.ndarray:
        return self.target_matrices()[1]

    def target_matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """Discrete-time (A, B) of x⁺ = Ax + Bw over one tick (a continuous plant is discretised
        exactly with w held over the tick: A = e^{A_c T}, B = ∫₀ᵀ e^{A_c s} ds B_c)."""
        t = self.target
        if t.model == "double_integrator":
            return double_integrator(self.run.T, t.dim)
        if t.model == "continuous":
            from scipy.linalg import expm

            Ac, Bc = np.array(t.A, float), np.array(t.B, float)
            m, p = Bc.shape
            M = np.zeros((m + p, m + p))
            M[:m, :m], M[:m, m:] = Ac, Bc
            E = expm(M * self.run.T)
            return E[:m, :m], E[:m, m:]
        return np.array(t.A, float), np.array(t.B, float)

    @property
    def m(self) -> int:
        return len(self.target.x0)

    @property
    def pos_dims(self) -> int:
        """Number of leading state components that are the target's position."""
        if self.target.model == "double_integrator":
            return self.target.dim
        if self.target.model == "continuous":
            return self.m  # a plant state (Chua circuit) is scored as a whole
        return int(np.array(self.C).shape[0])

    @property
    def per_node_C(self) -> bool:
        return np.ndim(self.sensors.C) == 3

    @property
    def C(self) -> np.ndarray:
        """The common measurement matrix (sensor 0's when each sensor has its own)."""
        return self.C_of(0)

    def C_of(self, i: int) -> np.ndarray:
        C = np.array(self.sensors.C, float)
        return C[i] if C.ndim == 3 else C

    def D_of(self, i: int) -> np.ndarray | None:
        if self.sensors.D is None:
            return None
        D = np.array(self.sensors.D, float)
        return D[i] if D.ndim == 3 else D

    def R_of(self, i: int) -> np.ndarray:
        """Measurement-noise covariance of sensor i: R, or v_std²·DᵢDᵢᵀ."""
        D = self.D_of(i)
        if D is not None:
            return self.sensors.v_std ** 2 * D @ D.T
        return np.array(self.sensors.R, float)

    @property
    def R(self) -> np.ndarray:
        return self.R_of(0)

    @property
    def Qw(self) -> np.ndarray:
        """Covariance of the target's process noise w (zero for a noise-free target)."""
        B = self.B
        return np.zeros((B.shape[1], B.shape[1])) if self.target.Q is None else np.array(self.target.Q, float)

    def filter_Q(self) -> np.ndarray:
        """Filter process noise in state space: estimator.Q if given, else B·target.Q·Bᵀ."""
        if self.estimator.Q is not None:
            return np.array(self.estimator.Q, float)
        return self.B @ self.Qw @ self.B.T

    def initial_positions(self) -> np.ndarray:
        """Sensor start positions (explicit, or a jittered grid drawn from the scenario seed)."""
        s = self.sensors
        if s.positions is not None:
            return np.array(s.positions, float)
        rng = rng_for(self.run.seed, "layout")
        cols = math.ceil(s.n / s.grid_rows)
        pts = [(c * s.spacing, r * s.spacing) for r in range(s.grid_rows) for c in range(cols)][: s.n]
        P = np.array(pts, float) + np.array(s.origin, float)
        if s.jitter > 0:
            P = P + rng.uniform(-s.jitter, s.jitter, size=P.shape)
        return P

    def initial_covariance(self) -> np.ndarray:
        """Every node's P₀: estimator.P0, else the identity."""
        P0 = self.estimator.P0
        return np.eye(self.m) if P0 is None else np.array(P0, float)

    def initial_estimates(self) -> np.ndarray:
        """Each node's x̂₀ (n × m): estimator.x0 (default 0) plus the node's x0_offsets row."""
        e = self.estimator
        x0 = np.zeros(self.m) if e.x0 is None else np.array(e.x0, float)
        X = np.tile(x0, (self.sensors.n, 1))
        if e.x0_offsets is not None:
            X = X + np.array(e.x0_offsets, float)
        return X

    def with_overrides(self, **kw: Any) -> "Scenario":
        """Copy with dotted overrides, e.g. ``{"run.ticks": 10, "estimator.name": "kalman"}`` (validated)."""
        return parse_scenario(override(self.data, kw), self.source)


_SECTIONS = {"run": RunCfg, "target": TargetCfg, "sensors": SensorsCfg, "estimator": EstimatorCfg,
             "topology": TopologyCfg, "control": ControlCfg, "faults": FaultsCfg}
_REQUIRED = {"run", "target", "sensors"}
_REQUIRED_KEYS = {"target": ("x0",), "sensors": ("n",)}


# ----------------------------------------------------------------------------- cross-field validation

def validate(sc: Scenario) -> Scenario:
    """Cross-field checks, one function per section, then the estimator's own (its spec's ``check``).
    Returns the scenario unchanged."""
    for check in (_check_run, _check_target, _check_sensors, _check_estimator, _check_topology, _check_faults):
        check(sc)
    return sc


def _check_run(sc: Scenario) -> None:
    src, r = sc.source, sc.run
    if not 1 <= r.ticks <= LIMITS["ticks"]:
        raise ScenarioError(src, "run.ticks", f"must be in [1, {LIMITS['ticks']:.0e}], got {r.ticks}",
                            "or give run.duration (s)")
    if not r.T >= LIMITS["T_min"] or not math.isfinite(r.T):
        raise ScenarioError(src, "run.T", f"sample time must be ≥ {LIMITS['T_min']:g} s, got {r.T}",
                            "T is the tick in seconds, e.g. T = 0.1")
    if not r.speed > 0:
        raise ScenarioError(src, "run.speed", f"realtime factor must be > 0, got {r.speed}", "e.g. speed = 1.0")
    if r.mode == "realtime" and r.T / r.speed < LIMITS["realtime_tick_min"]:
        raise ScenarioError(src, "run.T", f"a realtime tick of T / speed = {r.T / r.speed:g} s is shorter than "
                            f"{LIMITS['realtime_tick_min'] * 1e3:g} ms, which no process keeps",
                            "raise T, lower run.speed, or run in lockstep")


def _check_target(sc: Scenario) -> None:
    src, t, m = sc.source, sc.target, sc.m
    if t.model == "double_integrator":
        if m != 2 * t.dim:
            raise ScenarioError(src, "target.x0", f"a {t.dim}-D double integrator has {2 * t.dim} states "
                                f"[position, velocity], got {m}", f"give x0 {2 * t.dim} numbers")
        if t.A is not None or t.B is not None:
            raise ScenarioError(src, "target.A", "A/B are derived from T for model = \"double_integrator\"",
                                "remove A and B, or set model = \"matrices\"")
    else:
        if t.A is None or t.B is None:
            raise ScenarioError(src, "target.A" if t.A is None else "target.B",
                                f"is required when model = \"{t.model}\"")
        check_shape(src, "target.A", t.A, (m, m), "m × m with m = len(x0)")
        if np.shape(t.B)[0] != m:
            raise ScenarioError(src, "target.B", f"expected {m} rows (m = len(x0)), got {np.shape(t.B)[0]}")
    p = sc.B.shape[1]
    if t.Q is not None:
        check_covariance(src, "target.Q", t.Q, p, f"covariance of w, {p} × {p}", semi=True)
    if t.kind == "intelligent":
        if t.ke == 0:
            raise ScenarioError(src, "target.ke", "an intelligent target needs a non-zero gain ke")
        es, n = t.estimate_source, sc.sensors.n
        if es != "mean" and not (es.startswith("node:") and es[5:].isdigit() and int(es[5:]) < n):
            raise ScenarioError(src, "target.estimate_source",
                                f"expected \"mean\" or \"node:<i>\" with i < {n}, got {es!r}")


def _check_measurements(sc: Scenario) -> None:
    """C (one, or one per sensor where the estimator allows it), and R or D."""
    src, s, m = sc.source, sc.sensors, sc.m
    if s.C is None or (s.R is None and s.D is None):
        raise ScenarioError(src, "sensors.C" if s.C is None else "sensors.R", "is required",
                            "give the measurement matrix C (q × m) and noise covariance R (q × q) — or D "
                            "(yᵢ = Cᵢx + Dᵢvᵢ)")
    if np.ndim(s.C) == 3:
        if len(s.C) != s.n:
            raise ScenarioError(src, "sensors.C", f"one matrix per sensor expected ({s.n}), got {len(s.C)}")
        for i, Ci in enumerate(s.C):
            if np.shape(Ci)[1] != m:
                raise ScenarioError(src, f"sensors.C[{i}]", f"expected {m} columns (m = len(x0)), got {np.shape(Ci)[1]}")
        if sc.kind == "flock" and not spec_of(sc.estimator.name).per_sensor_C:
            allowed = [nm for nm in estimator_names() if spec_of(nm).per_sensor_C]
            raise ScenarioError(src, "sensors.C", f"per-sensor C is supported by the {', '.join(allowed)} "
                                "estimator only", "give one common C")
    q = np.shape(sc.C)[0]
    if np.ndim(s.C) == 2:
        check_shape(src, "sensors.C", s.C, (q, m), f"q × m with m = {m}")
    if s.D is None:
        check_covariance(src, "sensors.R", s.R, q, f"q × q with q = {q}")
        return
    if np.ndim(s.D) == 3 and len(s.D) != s.n:
        raise ScenarioError(src, "sensors.D", f"one matrix per sensor expected ({s.n}), got {len(s.D)}")
    for i in range(s.n):
        Di, Ci = sc.D_of(i), sc.C_of(i)
        if Di.shape[0] != Ci.shape[0]:
            raise ScenarioError(src, "sensors.D", f"sensor {i}: D must have as many rows as C ({Ci.shape[0]})")
        check_covariance(src, "sensors.D", Di @ Di.T, Di.shape[0], "DᵢDᵢᵀ")
    if not s.v_std > 0:
        raise ScenarioError(src, "sensors.v_std", f"must be > 0, got {s.v_std}")


def _check_sensors(sc: Scenario) -> None:
    src, s, t = sc.source, sc.sensors, sc.target
    if not 1 <= s.n <= LIMITS["sensors"]:
        raise ScenarioError(src, "sensors.n", f"need 1 … {LIMITS['sensors']} sensors, got {s.n}",
                            "the runtime starts one OS process per sensor")
    _check_measurements(sc)
    if s.positions is not None:
        check_shape(src, "sensors.positions", s.positions, (s.n, np.shape(s.positions)[1]), "n rows")
        if np.shape(s.positions)[1] not in (1, 2, 3):
            raise ScenarioError(src, "sensors.positions", "positions must be 1-, 2- or 3-D")
    if s.motion == "flocking":
        if t.model != "double_integrator":
            raise ScenarioError(src, "sensors.motion", "flocking follows a double-integrator target's position "
                                "and velocity", "use motion = \"static\" or a double_integrator target")
        if s.positions is not None and np.shape(s.positions)[1] != t.dim:
            raise ScenarioError(src, "sensors.positions", f"flocking sensors live in the target's {t.dim}-D space")


def _check_estimator(sc: Scenario) -> None:
    """The common keys, then the chosen estimator's own check (its spec)."""
    src, e, m, n = sc.source, sc.estimator, sc.m, sc.sensors.n
    if e.rounds < 0:
        raise ScenarioError(src, "estimator.rounds", f"must be ≥ 0, got {e.rounds}")
    if e.resilient_f < 0:
        raise ScenarioError(src, "estimator.resilient_f", f"must be ≥ 0, got {e.resilient_f}")
    if e.eta not in ("1/(dmax+1)", "1/dmax"):
        try:
            float(e.eta)
        except ValueError:
            raise ScenarioError(src, "estimator.eta", f"expected \"1/(dmax+1)\", \"1/dmax\" or a number, "
                                f"got {e.eta!r}") from None
    if e.x0 is not None and len(e.x0) != m:
        raise ScenarioError(src, "estimator.x0", f"expected {m} numbers, got {len(e.x0)}")
    if e.x0_offsets is not None:
        check_shape(src, "estimator.x0_offsets", e.x0_offsets, (n, m), "one row per sensor")
    if e.Q is not None:
        check_covariance(src, "estimator.Q", e.Q, m, "filter process noise, m × m", semi=True)
    if e.P0 is not None:
        check_covariance(src, "estimator.P0", e.P0, m, "initial covariance, m × m")
    if sc.kind == "flock":   # (a UAV-fusion scenario's sensors run no [estimator])
        spec_of(e.name).check(sc, e.params)


def _check_graph(sc: Scenario, gi: int, g: GraphCfg) -> None:
    src, n, key = sc.source, sc.sensors.n, f"topology.graphs[{gi}]"
    if len(g.b) != n:
        raise ScenarioError(src, f"{key}.b", f"expected {n} visibility weights (one per sensor), got {len(g.b)}")
    if any(v < 0 for v in g.b):
        raise ScenarioError(src, f"{key}.b", "visibility weights must be ≥ 0")
    for ei, (a, bb) in enumerate(g.edges):
        if not (0 <= a < n and 0 <= bb < n) or a == bb:
            raise ScenarioError(src, f"{key}.edges[{ei}]", f"edge [{a}, {bb}] must join two different "
                                f"sensors in 0..{n - 1}", "use sensor ids 0 … n−1 and no self-loops")
    if g.weights is not None and len(g.weights) != len(g.edges):
        raise ScenarioError(src, f"{key}.weights", "expected one weight per edge")


def _check_topology(sc: Scenario) -> None:
    src, tp = sc.source, sc.topology
    if tp.kind == "range":
        if not tp.range > 0:
            raise ScenarioError(src, "topology.range", f"must be > 0, got {tp.range}")
        _check_ever_linked(sc)
        return
    if not tp.graphs:
        raise ScenarioError(src, "topology.graphs", "a schedule needs at least one [[topology.graphs]]")
    if tp.dwell_ticks < 1:
        raise ScenarioError(src, "topology.dwell_ticks", f"must be ≥ 1, got {tp.dwell_ticks}")
    for gi, g in enumerate(tp.graphs):
        _check_graph(sc, gi, g)
    if not any(v > 0 for g in tp.graphs for v in g.b):
        raise ScenarioError(src, "topology.graphs", "no graph of the schedule lets any sensor see the target "
                            "(every b is 0), so no estimator can track it",
                            "give at least one sensor b > 0 in some graph")


def _check_ever_linked(sc: Scenario) -> None:
    """Static sensors none of which is within range of another are never linked: no consensus, no flock —
    refused (flocking sensors close in, so their start proves nothing)."""
    s, r = sc.sensors, sc.topology.range
    if s.n < 2 or s.motion != "static" or not math.isfinite(r) or sc.kind != "flock":
        return
    P = sc.initial_positions()
    d = np.sqrt(((P[:, None, :] - P[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    if d.min() > r:
        raise ScenarioError(sc.source, "topology.range", f"no two of the {s.n} static sensors are ever linked: "
                            f"the closest two are {d.min():.4g} apart, the range is {r:g}",
                            f"raise topology.range above {d.min():.4g} or place the sensors closer")


def _check_faults(sc: Scenario) -> None:
    src, fc, n = sc.source, sc.faults, sc.sensors.n
    if not 0.0 <= fc.link_loss <= 1.0:
        raise ScenarioError(src, "faults.link_loss", f"a probability in [0, 1] is expected, got {fc.link_loss}")
    for i, e in enumerate(fc.events):
        validate_fault_event(e, n, src, f"faults.events[{i}]", n_meas=np.shape(sc.sensors.C)[0])


def validate_fault_event(e: FaultEventCfg, n: int, src: str, key: str, n_meas: int | None = None) -> None:
    """Checks of one fault event against a flock of ``n`` sensors (a scenario's ``[[faults.events]]`` or a
    live ``control/inject``); raises :class:`ScenarioError` naming ``key``."""
    if e.start < 0 or (e.heal is not None and e.heal <= e.start):
        raise ScenarioError(src, f"{key}.heal", f"heal ({e.heal}) must come after start ({e.start})",
                            "give heal > start, or leave heal out for a permanent fault")
    if not 0.0 <= e.p <= 1.0:
        raise ScenarioError(src, f"{key}.p", f"a probability in [0, 1] is expected, got {e.p}")
    for name, hi in FAULT_LIMITS.items():      # (the bounds the wire enforces on a live event)
        v = getattr(e, name)
        if not (math.isfinite(v) and 0 <= v <= hi):
            raise ScenarioError(src, f"{key}.{name}", f"must be in [0, {hi:g}], got {v}")
    if not (math.isfinite(e.accel) and abs(e.accel) <= MAX_EVADE_ACCEL):
        raise ScenarioError(src, f"{key}.accel", f"must be in [-{MAX_EVADE_ACCEL:g}, {MAX_EVADE_ACCEL:g}] m/s², "
                            f"got {e.accel}", "e.g. accel = 2.0 (an evading target's extra acceleration)")
    if e.delay_ms > 0 and e.jitter_ticks > 0:
        raise ScenarioError(src, f"{key}.jitter_ticks", "a delay in ms takes its jitter in ms",
                            "use jitter_ms with delay_ms (jitter_ticks goes with delay_ticks)")
    t = e.targets
    head, _, rest = t.partition(":")
    try:
        if head in ("all", "most_connected", "halves") and not rest:
            ok = True
        elif head == "agents":
            ok = all(0 <= int(x) < n for x in rest.split(","))
        elif head == "random":
            ok = 1 <= int(rest) <= n
        elif head == "links":
            ok = all(0 <= int(a) < n and 0 <= int(b) < n and a != b
                     for a, b in (x.split("-") for x in rest.split(",")))
        elif head == "groups":
            ok = len(rest.split(",")) == n and all(int(x) >= 0 for x in rest.split(","))
        else:
            ok = False
    except ValueError:
        ok = False
    if not ok:
        raise ScenarioError(src, f"{key}.targets", f"cannot read target selector {t!r}",
                            f"use all, agents:1,2, links:0-1,2-3, random:k (k ≤ {n}), most_connected, halves, "
                            f"or groups:<one group id per sensor>")
    if e.kind == "partition" and head not in ("halves", "groups"):
        raise ScenarioError(src, f"{key}.targets", "a partition needs targets = \"halves\" or \"groups:…\"")
    if n_meas is not None and e.bias is not None and len(e.bias) != n_meas:
        raise ScenarioError(src, f"{key}.bias", f"expected {n_meas} numbers (one per measurement component)")


def parse_fault_event(table: dict, n: int, src: str = "control/inject", key: str = "inject",
                      n_meas: int | None = None) -> FaultEventCfg:
    """One fault event from a plain table (keys of :class:`FaultEventCfg`), typed and validated."""
    e = build_table(FaultEventCfg, table, src, key)
    validate_fault_event(e, n, src, key, n_meas)
    return e


def parse_uav_scenario(data: dict, source: str) -> Scenario:
    """A fusion scenario (``[uavs]``, ``[fusion]``, … as in scenarios/carrillo_uav.toml): the UAV world of
    García Carrillo et al. on the tick runtime — UAV agents without a distributed estimator (their
    measurements go to the fusion role), a target replayed from the seeded simulation, no links."""
    from .models_uav import config_from_tables

    d = {k: v for k, v in data.items() if k != "run"}
    run = dict(data.get("run", {}))
    rc_keys = {"name", "T", "mode", "deadline_s", "speed", "seed", "duration", "ticks", "burn_in"}
    for k in run:
        if k not in rc_keys:
            raise ScenarioError(source, f"run.{k}", "unknown key",
                                f"{did_you_mean(k, rc_keys)}use one of: {', '.join(sorted(rc_keys))}")
    T = run.get("T", 0.05)
    duration = run.get("duration", 100.0)
    if isinstance(run.get("ticks"), int) and isinstance(T, (int, float)):
        duration = run["ticks"] * float(T)  # --ticks N: the first N·T seconds
    try:
        cfg = config_from_tables({"run": {"seed": run.get("seed", 1), "duration": duration}, **d})
    except (ValueError, TypeError) as exc:
        msg = str(exc)
        key = msg[1:msg.index("]")] if msg.startswith("[") and "]" in msg else "-"
        raise ScenarioError(source, key, msg, "see scenarios/carrillo_uav.toml for every key") from None
    cfg.make_estimators(source)  # [fusion]: the named fusion estimator and its keys (ScenarioError names them)
    _check_fusion_mode(cfg, source)
    T = float(T)
    if not T > 0 or not cfg.duration > 0:
        raise ScenarioError(source, "run.T", "T and duration must be > 0")
    n = cfg.uav.n
    sigma = cfg.uav.sigma_rel
    sc = Scenario(
        run=RunCfg(name=str(run.get("name", "carrillo_uav")), ticks=int(math.ceil(cfg.duration / T)), T=T,
                   seed=cfg.seed, mode=run.get("mode", "lockstep"), deadline_s=float(run.get("deadline_s", 5.0)),
                   speed=float(run.get("speed", 1.0))),
        target=TargetCfg(x0=[0.0, 0.0, 0.0, 0.0], model="double_integrator", dim=2),
        sensors=SensorsCfg(n=n, C=[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]], R=[[sigma ** 2, 0.0], [0.0, sigma ** 2]],
                           positions=[[0.0, 0.0]] * n, motion="static"),
        estimator=EstimatorCfg(name="none", rounds=0),
        # distributed fusion: every UAV hears every other (their consensus rounds); central: no links
        topology=TopologyCfg(kind="schedule", dwell_ticks=1, graphs=[GraphCfg(
            edges=[[i, j] for i in range(n) for j in range(i + 1, n)] if cfg.fusion_mode == "distributed" else [],
            b=[1.0] * n)]),
        source=source, uav=cfg, data=data)
    if sc.run.mode not in ("lockstep", "realtime"):
        raise ScenarioError(source, "run.mode", f"expected \"lockstep\" or \"realtime\", got {sc.run.mode!r}")
    return validate(sc)


def _check_fusion_mode(cfg, source: str) -> None:
    """``[fusion] mode`` and its ADMM keys (agent.models_uav.CarrilloScenario.fusion_mode)."""
    mode = cfg.fusion.get("mode", "central")
    if mode not in ("central", "distributed"):
        raise ScenarioError(source, "fusion.mode", f"expected \"central\" or \"distributed\", got {mode!r}",
                            f"{did_you_mean(str(mode), ('central', 'distributed'))}write mode = \"central\" (one fusion "
                            "process) or mode = \"distributed\" (consensus ADMM between the UAVs)")
    if mode == "distributed":
        have = fusion_specs()
        able = [name for name, spec in have.items() if spec.distributed is not None]
        name = cfg.fusion.get("estimator", next((n for n, spec in have.items() if spec.default), None))
        if name not in able:
            raise ScenarioError(source, "fusion.estimator", f"the distributed mode cannot run {name!r}",
                                "write " + " or ".join(f'estimator = "{a}"' for a in able) + " (scenarios/carrillo_robust.toml)")
    it, rho = cfg.fusion.get("admm_iterations", 8), cfg.fusion.get("admm_rho", 0.05)
    if isinstance(it, bool) or not isinstance(it, int) or not 1 <= it <= 100:
        raise ScenarioError(source, "fusion.admm_iterations", f"expected a whole number in 1…100, got {it!r}",
                            "e.g. admm_iterations = 8 (ADMM iterations, i.e. exchange rounds, per tick)")
    if isinstance(rho, bool) or not isinstance(rho, (int, float)) or not (math.isfinite(rho) and rho > 0):
        raise ScenarioError(source, "fusion.admm_rho", f"expected a finite number > 0, got {rho!r}",
                            "e.g. admm_rho = 0.05 (the ADMM penalty, per m² of the states)")


def _estimator_section(table: Any, source: str) -> EstimatorCfg:
    """``[estimator]``: the common keys, and the rest handed to the chosen estimator's spec."""
    table = {} if table is None else table
    if not isinstance(table, dict):
        raise ScenarioError(source, "estimator", f"expected a table, got {table!r}", "write [estimator] as a TOML table")
    name, known = table.get("name", default_name()), estimator_names()
    if name not in known:
        hint = did_you_mean(name, known, quote="'") if isinstance(name, str) else ""
        raise ScenarioError(source, "estimator.name", f"expected one of {', '.join(map(repr, known))}, got {name!r}",
                            f"{hint}write estimator.name as one of {', '.join(map(repr, known))}")
    own = set(spec_of(name).param_names())
    others = {k for nm in known for k in spec_of(nm).param_names()} - own   # kept for a switch of name (sweeps)
    common = build_table(EstimatorCommon, {k: v for k, v in table.items() if k not in own | others}, source,
                         "estimator", also_known=own | others)
    params = build_table(spec_of(name).params, {k: v for k, v in table.items() if k in own}, source, "estimator")
    kw = {f.name: getattr(common, f.name) for f in fields(EstimatorCommon)}
    return EstimatorCfg(**{**kw, "name": name}, params=params)


def parse_scenario(data: Mapping[str, Any], source: str = "<scenario>") -> Scenario:
    """Build and validate a scenario from an already-parsed TOML mapping."""
    if "uavs" in data:
        return parse_uav_scenario(dict(data), source)
    for k in data:
        if k not in _SECTIONS:
            raise ScenarioError(source, k, "unknown table", f"{did_you_mean(k, _SECTIONS)}use one of: {', '.join(_SECTIONS)}")
    for k in _REQUIRED:
        if k not in data:
            raise ScenarioError(source, k, "table is required", f"add a [{k}] table")
    kw = {name: build_table(cls, data[name], source, name, required=_REQUIRED_KEYS.get(name, ()))
          for name, cls in _SECTIONS.items() if name in data and cls is not EstimatorCfg}
    kw["estimator"] = _estimator_section(data.get("estimator"), source)
    return validate(Scenario(source=source, data=data, **kw))


def _read_toml(path: Path) -> dict:
    try:
        size = path.stat().st_size
        if size > LIMITS["file_bytes"]:   # not parsed at all: TOML of a 10⁴ × 10⁴ matrix is ~0.5 GB
            raise ScenarioError(str(path), "-", f"is {size / 2**20:.0f} MiB; a scenario is at most "
                                f"{LIMITS['file_bytes'] // 2**20} MiB", "is this the right file?")
        text = path.read_text()
    except OSError as exc:
        raise ScenarioError(str(path), "-", f"cannot read the file ({exc.strerror})", "check the path") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(str(path), "-", f"is not valid TOML ({exc})", "fix the TOML syntax") from None


def toml_value(text: str) -> Any:
    """A ``--set`` value as TOML (``3``, ``[[1.0]]``, ``"x"``); text that is not TOML stays a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def override(data: Mapping[str, Any], dotted: Mapping[str, Any]) -> dict:
    """A copy of the TOML mapping ``data`` with ``{"section.key": value}`` set (None values skipped)."""
    out = {k: (dict(v) if isinstance(v, dict) else v) for k, v in data.items()}
    for key, value in dotted.items():
        if value is not None:
            sect, _, name = key.partition(".")
            out.setdefault(sect, {})[name] = value
    return out


def parse_sets(sets: Iterable[str], source: str) -> dict[str, Any]:
    """``["section.key=value", …]`` (TOML values) as ``{"section.key": value}``."""
    out: dict[str, Any] = {}
    for s in sets:
        dotted, sep, raw = s.partition("=")
        if not sep or "." not in dotted:
            raise ScenarioError(source, s, "override must look like section.key=value", "e.g. --set run.ticks=100")
        out[dotted] = toml_value(raw)
    return out


def scenario_data(path: str | Path, sets: Iterable[str] = (), **named: Any) -> dict:
    """The scenario file's TOML mapping with ``--set section.key=value`` overrides (TOML values) and
    ``named`` ones (``{"run.ticks": 10}``; None = not given) applied."""
    data = _read_toml(Path(path))
    return override(override(data, parse_sets(sets, str(path))), named)


def load_scenario(path: str | Path, sets: Iterable[str] = (), **named: Any) -> Scenario:
    """Read a TOML scenario file, apply overrides (as :func:`scenario_data`), validate once."""
    return parse_scenario(scenario_data(path, sets, **named), str(path))
