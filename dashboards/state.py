"""A pure, testable model of what the dashboard shows, fed message by message.

:class:`DashboardState` knows nothing about Zenoh, Viser or files: :meth:`DashboardState.ingest` takes one
decoded message (with the wall-clock or log time it arrived at), :meth:`DashboardState.snapshot` returns
what the 3-D scene draws at a tick, :meth:`DashboardState.series` the time series the plots draw. The live
dashboard feeds it from its bus, the replay from a recording, the tests and the benchmark from synthetic
messages.

Per tick k a :class:`Frame` collects the world's ``tick`` (links, alive flags, positions at the start of
the tick), the ``truth``, every node's ``estimate`` and ``state`` and the ``fusion/estimate``. A frame is
*finalized* — scored and appended to the series, in tick order — as soon as it holds the tick, the truth
and an estimate and a state from every alive sensor, or when the world is ``lag`` ticks further (what is
still missing then counts as dropped), or at ``world/end``. What a live subscriber really receives is not
that tidy, and the series must stay plottable whatever comes (a browser's uPlot panel shows nothing at all
once its data is malformed):

* the dashboard usually joins a run that is already going (it starts its web server before it
  subscribes), so its first frame may lack the world's tick and the truth that went by before it listened;
  such a *leading partial frame* is not scored (counted in ``partial_start``) — scoring it made a first row
  of NaN (and a burst of "missing" messages that nobody dropped);
* a tick nothing at all arrived about (a starved machine, a dashboard that fell behind) becomes one gap
  row (NaN, counted as missing), so that the plots break the line there instead of joining across it;
* a message about a tick already finalized is late (counted in ``late``), a duplicated one overwrites;
  rows are appended with k strictly increasing, whatever the arrival order;
* a metric that is not finite (an overflowing TMSEE, a NaN in a message that was not validated) is
  recorded as NaN — a gap — never as ±inf.

Per finalized tick the series hold

* eᵢ(k) = ‖x̂ᵢ,ₖ − xₖ‖ over the position components and the network RMSE √(mean eᵢ²);
* TMSEE(k) = Σᵢ ‖x̂ᵢ,ₖ − xₖ‖² (full state) and its lower bound where the pre-run design has one;
* the consensus disagreement √(mean ‖x̂ᵢ − x̄‖²) and the error of the mean estimate;
* the algebraic connectivity λ₂ of the tick's graph and its number of links;
* the network NEES: the mean over the nodes of εᵢ = eᵢ′Pᵢ⁻¹eᵢ, eᵢ = x̂ᵢ,ₖ − xₖ against the covariance the
  node reported for x̂ᵢ,ₖ (the ``P`` of its estimate of tick k − 1), with the 95 % χ² interval of that mean
  (:mod:`dashboards.nees`), and each node's own εᵢ;
* the suspicions: how many (i, j) pairs "i discarded j's payloads" the resilient consensus reported
  (``Estimate.aux["suspected"]``; NaN when no estimate carries the key: resilience off);
* the message rate and the dropped messages per second (bus drops + missing sensor estimates/states)
  over the last ``rate_window_s`` seconds.

These are the same definitions as ``flocktrack/record/metrics.py`` (a test checks they agree on a recording),
computed here without importing it (floors: ``dashboards`` imports only ``agent``).
"""

from __future__ import annotations

import json
import math
import tomllib
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from agent.wire import Control, End, Estimate, Message, State, Tick, Truth, valid_suspects

from .nees import network_nees

NAN = float("nan")


# ============================================================================ run description

@dataclass(frozen=True)
class RunInfo:
    """What the dashboard needs to know about a run before the first message."""

    n: int
    pos_dims: int = 2
    T: float = 0.1
    link_range: float = math.inf      #: ``[topology] range`` (communication range; drawn as circles)
    sensing_range: float = math.inf
    ticks: int | None = None
    name: str = "run"
    mode: str = "lockstep"
    estimator: str = ""
    speed: float = 1.0                 #: the run's realtime factor ([run] speed)
    tmsee_lower: tuple[float, ...] | None = None

    @classmethod
    def from_scenario_data(cls, data: dict, design: dict | None = None) -> "RunInfo":
        """From a scenario's TOML data (validated through :mod:`agent.scenario` when it parses)."""
        lower = None
        if design and design.get("tmsee_lower") is not None:
            lower = tuple(float(v) for v in design["tmsee_lower"])
        try:
            from agent.scenario import parse_scenario

            sc = parse_scenario(data)
            return cls(n=sc.sensors.n, pos_dims=sc.pos_dims, T=sc.run.T, link_range=float(sc.topology.range),
                       sensing_range=float(sc.sensors.sensing_range), ticks=sc.run.ticks, name=sc.run.name,
                       mode=sc.run.mode, estimator=sc.estimator.name, speed=float(sc.run.speed),
                       tmsee_lower=lower)
        except Exception:  # a scenario from a newer/older schema: read the few keys directly
            run, sens, topo, tgt = (data.get(s, {}) for s in ("run", "sensors", "topology", "target"))
            dims = int(tgt.get("dim", 2)) if tgt.get("model", "double_integrator") == "double_integrator" \
                else len(sens.get("C", [[0], [0]]))
            return cls(n=int(sens.get("n", 0)), pos_dims=dims, T=float(run.get("T", 0.1)),
                       link_range=float(topo.get("range", math.inf)),
                       sensing_range=float(sens.get("sensing_range", math.inf)), ticks=run.get("ticks"),
                       name=str(run.get("name", "run")), mode=str(run.get("mode", "lockstep")),
                       estimator=str(data.get("estimator", {}).get("name", "")),
                       speed=float(run.get("speed", 1.0)), tmsee_lower=lower)

    @classmethod
    def from_toml_text(cls, text: str, design_json: str | None = None) -> "RunInfo":
        return cls.from_scenario_data(tomllib.loads(text), json.loads(design_json) if design_json else None)

    @classmethod
    def from_files(cls, scenario: str | Path, design: str | Path | None = None) -> "RunInfo":
        """From a scenario file; the design defaults to ``design.json`` beside it (a run directory)."""
        scenario = Path(scenario)
        if design is None and (scenario.parent / "design.json").is_file():
            design = scenario.parent / "design.json"
        dsg = json.loads(Path(design).read_text()) if design else None
        return cls.from_scenario_data(tomllib.loads(scenario.read_text()), dsg)


# ============================================================================ per-tick frames

@dataclass
class Frame:
    """Everything received about tick k."""

    k: int
    t: float = NAN
    tick: Tick | None = None
    truth: np.ndarray | None = None
    est: dict[int, np.ndarray] = field(default_factory=dict)        #: x̂ᵢ,ₖ (scored at k)
    est_next: dict[int, np.ndarray] = field(default_factory=dict)   #: x̂ᵢ,ₖ₊₁
    cov: dict[int, np.ndarray] = field(default_factory=dict)        #: P of x̂ᵢ,ₖ₊₁ (when the filter has one)
    state_pos: dict[int, np.ndarray] = field(default_factory=dict)  #: position after tick k
    fusion: np.ndarray | None = None
    suspects: dict[int, np.ndarray] = field(default_factory=dict)  #: whom node i discarded (valid ids only)
    nees: np.ndarray | None = None      #: (n,) each node's NEES εᵢ at tick k (set when finalized)
    done: bool = False

    def expected(self, n: int) -> list[int]:
        if self.tick is not None and len(self.tick.alive) == n:
            return [i for i in range(n) if self.tick.alive[i]]
        return list(range(n))

    def complete(self, n: int, fusion: bool = False) -> bool:
        """Tick, truth, an estimate and a state from every alive sensor (and the fusion estimate when the
        run has a fusion solver) are in; O(1) when they are not."""
        if self.tick is None or self.truth is None or (fusion and self.fusion is None):
            return False
        m = sum(self.tick.alive) if len(self.tick.alive) == n else n
        if len(self.est) < m or len(self.state_pos) < m:
            return False
        return all(i in self.est and i in self.state_pos for i in self.expected(n))


@dataclass
class Snapshot:
    """What the 3-D scene draws for one tick (positions are 3-D; z = 0 for a planar flock)."""

    k: int
    t: float
    n: int
    positions: np.ndarray          #: (n, 3) sensor positions at the start of tick k (NaN: unknown)
    alive: np.ndarray              #: (n,) bool
    errors: np.ndarray             #: (n,) own position error eᵢ(k) (NaN: no estimate)
    est_pos: np.ndarray            #: (n, 3) each node's estimate of the target position (NaN: none)
    est_next: dict[int, np.ndarray]
    cov_pos: dict[int, np.ndarray]  #: position block of P per node that sent one
    edges: np.ndarray              #: (E, 2) int, i < j: this tick's links
    neighbours: list[list[int]]
    truth_pos: np.ndarray | None   #: (3,)
    trail: np.ndarray              #: (L, 3) the target's recent positions, oldest first
    fusion_pos: np.ndarray | None  #: (3,)
    row: dict                      #: the tick's series row (rmse, λ₂, rates, …) if finalized
    suspicions: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))  #: (S, 2) i suspects j
    nees: np.ndarray | None = None  #: (n,) each node's NEES εᵢ (NaN: not scored; None: tick not finalized)

    def suspects_of(self, i: int) -> list[int]:
        """Whom sensor ``i`` suspected at this tick."""
        return [int(j) for a, j in self.suspicions if a == i]


def _pad3(p: np.ndarray) -> np.ndarray:
    p = np.asarray(p, float)
    out = np.zeros(p.shape[:-1] + (3,))
    d = min(3, p.shape[-1])
    out[..., :d] = p[..., :d]
    return out


def _connected(links: list[list[int]]) -> bool:
    n = len(links)
    seen = [False] * n
    seen[0] = True
    stack, count = [0], 1
    while stack:
        for j in links[stack.pop()]:
            if 0 <= j < n and not seen[j]:
                seen[j] = True
                count += 1
                stack.append(j)
    return count == n


def algebraic_connectivity_of_links(links: list[list[int]]) -> float:
    """λ₂ of the graph Laplacian L = D − A built from neighbour lists (0 for a disconnected graph)."""
    n = len(links)
    if n < 2 or not _connected(links):
        return 0.0
    A = np.zeros((n, n))
    for i, nb in enumerate(links):
        if nb:
            A[i, nb] = 1.0
    A = np.maximum(A, A.T)
    L = np.diag(A.sum(axis=1)) - A
    return float(np.linalg.eigvalsh(L)[1])


class _Lambda2Cache:
    """λ₂ per distinct link table: a range graph changes only now and then, so most ticks are a hit."""

    def __init__(self, size: int = 64):
        self.size, self._d = size, {}
        self.hits = self.misses = 0

    def __call__(self, links: list[list[int]]) -> float:
        key = tuple(tuple(nb) for nb in links)
        v = self._d.get(key)
        if v is None:
            self.misses += 1
            if len(self._d) >= self.size:
                self._d.pop(next(iter(self._d)))
            v = self._d[key] = algebraic_connectivity_of_links(links)
        else:
            self.hits += 1
        return v


def edges_of_links(links: list[list[int]]) -> np.ndarray:
    e = [(i, j) for i, nb in enumerate(links) for j in nb if i < j]
    return np.array(e, dtype=int).reshape(-1, 2)


# ============================================================================ rates

class RateMeter:
    """Events per second over a sliding window, from 0.1 s buckets of a caller-supplied clock."""

    def __init__(self, window_s: float = 1.0, bucket_s: float = 0.1):
        self.window_s, self.bucket_s = float(window_s), float(bucket_s)
        self._buckets: deque[list] = deque()  # [bucket index, count]
        self.total = 0

    def add(self, now: float, count: int = 1) -> None:
        if count <= 0:
            return
        b = int(math.floor(now / self.bucket_s))
        if self._buckets and self._buckets[-1][0] == b:
            self._buckets[-1][1] += count
        elif self._buckets and self._buckets[-1][0] > b:  # clock went backwards (replay seek): keep it simple
            self._buckets[-1][1] += count
        else:
            self._buckets.append([b, count])
        self.total += count

    def rate(self, now: float) -> float:
        lo = int(math.floor(now / self.bucket_s)) - int(round(self.window_s / self.bucket_s)) + 1
        while self._buckets and self._buckets[0][0] < lo:
            self._buckets.popleft()
        return sum(c for _, c in self._buckets) / self.window_s


# ============================================================================ series

class SeriesBuffer:
    """Columns of floats appended one row per finalized tick, and per-node matrices (rows × n: ``err``, each
    node's own position error, and ``nees_node``, its own NEES); keeps the last ``max_rows`` (None: all)."""

    MATRICES = ("err", "nees_node")

    def __init__(self, columns: list[str], n: int, max_rows: int | None = None):
        self.columns = list(columns)
        self.n = n
        self.max_rows = max_rows
        cap = 256
        self._cols = {c: np.full(cap, NAN) for c in self.columns}
        self._mats = {m: np.full((cap, n), NAN) for m in self.MATRICES}
        self._len = 0

    def __len__(self) -> int:
        return self._len

    def append(self, row: dict, err: np.ndarray, nees_node: np.ndarray | None = None) -> bool:
        """Append one row (``nees_node`` None: NaN); a row whose k is not above the last one is refused
        (False): the plots need x strictly increasing, and :meth:`arrays` seeks by k."""
        if self._len and not row["k"] > self._cols["k"][self._len - 1]:
            return False
        mats = self._mats
        if self.max_rows is not None and self._len >= 2 * self.max_rows:  # drop the older half, amortised O(1)
            keep = self.max_rows
            for a in (*self._cols.values(), *mats.values()):
                a[:keep] = a[self._len - keep:self._len]
            self._len = keep
        if self._len == len(mats["err"]):
            cap = 2 * len(mats["err"])
            for c in self.columns:
                self._cols[c] = np.concatenate([self._cols[c], np.full(cap - len(self._cols[c]), NAN)])
            for m in self.MATRICES:
                mats[m] = np.concatenate([mats[m], np.full((cap - len(mats[m]), self.n), NAN)])
        i = self._len
        for c in self.columns:
            v = row.get(c, NAN)
            self._cols[c][i] = NAN if v is None else v
        mats["err"][i] = err
        mats["nees_node"][i] = NAN if nees_node is None else nees_node
        self._len += 1
        return True

    def arrays(self, upto_k: int | None = None, last: int | None = None) -> dict[str, np.ndarray]:
        """Copies of the columns and of the matrices (rows × n), rows with k ≤ ``upto_k``, the last ``last``
        of them (and never more than ``max_rows``)."""
        end = self._len
        if upto_k is not None:
            end = int(np.searchsorted(self._cols["k"][:self._len], upto_k, side="right"))
        start = 0
        limit = min(x for x in (last, self.max_rows, end) if x is not None)
        start = max(0, end - limit)
        out = {c: self._cols[c][start:end].copy() for c in self.columns}
        for m, a in self._mats.items():
            out[m] = a[start:end].copy()
        return out


SERIES_COLUMNS = ["k", "t", "rmse", "tmsee", "tmsee_lower", "disagreement", "mean_err", "fusion_err",
                  "lambda2", "lambda2_alive", "links", "reporting", "missing", "msg_rate", "drop_rate", "wall",
                  "nees", "nees_lo", "nees_hi", "nees_scored", "suspected"]


# ============================================================================ the model

class DashboardState:
    """Everything the dashboard shows, built from the message stream alone.

    ``keep_frames``: frames kept behind the newest one (None keeps all: replay); ``max_points``: series
    rows kept (None keeps all); ``trail_len``: ticks of target trail; ``lag``: a frame is finalized at the
    latest when the world is ``lag`` ticks further.
    """

    def __init__(self, info: RunInfo, *, keep_frames: int | None = 400, max_points: int | None = 3000,
                 trail_len: int = 200, lag: int = 2, rate_window_s: float = 1.0):
        self.info = info
        self.n = int(info.n)
        self.d = int(info.pos_dims)
        self.keep_frames, self.trail_len, self.lag = keep_frames, int(trail_len), int(lag)
        self.frames: dict[int, Frame] = {}
        self.series_buf = SeriesBuffer(SERIES_COLUMNS, self.n, max_points)
        self.rows: dict[int, dict] = {}          # finalized rows still in frames (for snapshots)
        self.truth_pos: dict[int, np.ndarray] = {}
        self.msg_meter = RateMeter(rate_window_s)
        self.drop_meter = RateMeter(rate_window_s)
        self.latest_tick = -1                    # newest world/tick seen
        self.finalized_k = -1                    # newest finalized tick
        self._next_final: int | None = None      # smallest k not yet finalized
        self.newest_frame = -1                   # largest k any message was about
        self._evict_cursor: int | None = None    # frames below it are gone
        self._trail_cursor: int | None = None
        self.messages = 0
        self.bus_dropped = 0
        self.missing_total = 0
        self.late = 0                            # messages about a tick already finalized
        self.partial_start = 0                   # leading frames whose start went by before we listened
        self.gap_ticks = 0                       # ticks nothing at all arrived about
        self._last_expected = self.n             # sensors expected in the last scored tick
        self.ended = False
        self.end_reason = ""
        self.paused = False
        self.speed: float | None = None
        self.events: deque[tuple[int, str, dict]] = deque(maxlen=50)    # world/event acks
        self.late_ticks = 0     #: ticks the world closed without every sensor's state (world/event "late")
        self.controls: deque[tuple[int, str, dict]] = deque(maxlen=50)  # control/** seen
        self.last_now = 0.0
        self.has_fusion = False                  # a fusion solver publishes: wait for its estimate too
        self.invalid_suspects = 0                # values of aux["suspected"] that name no possible suspect
        self._last_err = np.full(self.n, NAN)   # newest known own error per node
        self._lambda2 = _Lambda2Cache()

    # ------------------------------------------------------------------ feeding
    def count(self, now: float, n: int = 1) -> None:
        """Messages seen but not decoded (exchange payloads, measurements): counted in the rate only."""
        self.messages += n
        self.msg_meter.add(now, n)
        self.last_now = now

    def note_bus_dropped(self, total: int, now: float) -> None:
        """The bus's cumulative drop counter (invalid messages); the increase counts as dropped."""
        if total > self.bus_dropped:
            self.drop_meter.add(now, total - self.bus_dropped)
            self.bus_dropped = total

    def _frame(self, k: int) -> Frame | None:
        """The frame of tick k to add a message to; None when tick k is already scored (the message is late:
        counted, and the scored frame left as scored)."""
        f = self.frames.get(k)
        if f is not None and f.done:
            self.late += 1
            return None
        if f is None:
            if self._next_final is not None and k < self._next_final:
                self.late += 1
                return None
            f = self.frames[k] = Frame(k)
            if self._next_final is None:
                self._next_final = self._evict_cursor = self._trail_cursor = k
            self.newest_frame = max(self.newest_frame, k)
        return f

    def ingest(self, key: str, msg: Message, now: float) -> None:
        """One decoded message that arrived on relative ``key`` at time ``now`` (seconds)."""
        self.count(now)
        if isinstance(msg, Tick):
            if key != "world/tick":
                return
            f = self._frame(msg.k)
            if f is not None:
                f.tick, f.t = msg, msg.t
            self.latest_tick = max(self.latest_tick, msg.k)
        elif isinstance(msg, Truth):
            f = self._frame(msg.k)
            if f is not None:
                f.truth, f.t = msg.x, msg.t if math.isnan(f.t) else f.t
            if f is not None:
                self.truth_pos[msg.k] = _pad3(msg.x[: self.d])
        elif isinstance(msg, Estimate):
            if key.startswith("fusion/"):
                self.has_fusion = True       # even when late: from now on a tick waits for its fusion estimate
            f = self._frame(msg.k)
            if f is None:
                return
            if key.startswith("agent/"):
                if 0 <= msg.src < self.n:
                    f.est[msg.src] = msg.x
                    f.est_next[msg.src] = msg.x_next
                    if msg.P is not None:
                        f.cov[msg.src] = msg.P
                    aux = msg.aux if isinstance(msg.aux, dict) else {}
                    if "suspected" in aux:
                        f.suspects[msg.src], dropped = valid_suspects(msg.src, aux["suspected"], self.n)
                        self.invalid_suspects += dropped
            elif key.startswith("fusion/"):
                f.fusion = msg.x
                self.has_fusion = True
        elif isinstance(msg, State):
            if key.startswith("agent/") and 0 <= msg.src < self.n:
                f = self._frame(msg.k)
                if f is not None:
                    f.state_pos[msg.src] = msg.pos
        elif isinstance(msg, Control):
            if key == "world/event" and msg.verb == "late":
                self.late_ticks += 1      # (a tick closed without some states: counted, not the last event)
            elif key == "world/event":
                self.events.append((msg.k, msg.verb, dict(msg.args)))
                if msg.verb == "pause":
                    self.paused = True
                elif msg.verb in ("resume", "step"):
                    self.paused = False
                elif msg.verb == "speed":
                    self.speed = float(msg.args.get("factor", NAN))
            elif key.startswith("control/"):
                self.controls.append((msg.k, msg.verb, dict(msg.args)))
        elif isinstance(msg, End):
            self.ended, self.end_reason = True, msg.reason
            self.finalize_all(now)
            return
        self._advance(now)

    def finalize_all(self, now: float | None = None) -> None:
        """Score every pending frame (end of run / end of a recording)."""
        now = self.last_now if now is None else now
        self._advance(now, force=True)
        if self._next_final is not None:
            self._next_final = max(self._next_final, self.newest_frame + 1)
        self._evict()

    # ------------------------------------------------------------------ finalizing
    def _advance(self, now: float, force: bool = False) -> None:
        """Finalize frames in tick order while the next one is complete or given up (``force``: all)."""
        self.last_now = now
        moved = False
        while self._next_final is not None and self._next_final <= self.newest_frame:
            k = self._next_final
            f = self.frames.get(k)
            world = max(self.latest_tick, self.newest_frame)
            if f is not None and f.done:
                self._next_final += 1
                continue
            if f is None:
                if world < k + self.lag and not force:
                    break           # nothing heard of tick k yet: it may still come
                # nothing at all arrived about ticks k … nxt−1: one gap row (once something was scored), and
                # on to the next tick we heard of — in one step, however long the gap
                nxt = min((j for j in self.frames if j > k), default=self.newest_frame + 1)
                if self.finalized_k >= 0:
                    self._gap(k, nxt - k, now)
                    moved = True
                self._next_final = nxt
                continue
            if force or f.complete(self.n, self.has_fusion) or world >= k + self.lag:
                if self.finalized_k < 0 and f.tick is None and self.latest_tick > k:
                    self._discard(f)    # we joined during tick k: its world tick went by before we listened
                else:
                    self._finalize(f, now)
                    moved = True
                self._next_final += 1
            else:
                break
        if moved:
            self._evict()

    def _discard(self, f: Frame) -> None:
        self.partial_start += 1
        self.frames.pop(f.k, None)
        self.truth_pos.pop(f.k, None)

    def _gap(self, k: int, count: int, now: float) -> None:
        """One row of NaN at tick k standing for ``count`` ticks nothing arrived about (their estimates and
        states count as missing, for the sensors the last scored tick expected)."""
        missing = 2 * self._last_expected * count
        self.gap_ticks += count
        self.missing_total += missing
        self.drop_meter.add(now, missing)
        row = {"k": k, "t": NAN, "wall": now, "reporting": 0, "missing": missing,
               "msg_rate": self.msg_meter.rate(now), "drop_rate": self.drop_meter.rate(now)}
        self.series_buf.append(row, np.full(self.n, NAN))

    def _finalize(self, f: Frame, now: float) -> None:
        f.done = True
        d, n = self.d, self.n
        row: dict = {"k": f.k, "t": f.t, "wall": now}
        err = np.full(n, NAN)
        x = f.truth
        if x is not None and f.est:
            ids = sorted(i for i in f.est if f.est[i].shape == x.shape)
            if ids:
                X = np.array([f.est[i] for i in ids])
                e = np.linalg.norm(X[:, :d] - x[None, :d], axis=1)
                err[ids] = e
                row["rmse"] = float(np.sqrt(np.mean(e ** 2)))
                row["tmsee"] = float(np.sum((X - x[None, :]) ** 2))
                xbar = X.mean(axis=0)
                row["mean_err"] = float(np.linalg.norm(xbar[:d] - x[:d]))
                row["disagreement"] = float(np.sqrt(np.mean(np.sum((X - xbar[None, :]) ** 2, axis=1))))
            if f.fusion is not None and f.fusion.shape == x.shape:
                row["fusion_err"] = float(np.linalg.norm(f.fusion[:d] - x[:d]))
        row["reporting"] = len(f.est)
        f.nees = self._score_nees(f, row)
        if f.suspects:
            row["suspected"] = sum(len(v) for v in f.suspects.values())
        lower = self.info.tmsee_lower
        if lower is not None and 0 <= f.k < len(lower):
            row["tmsee_lower"] = lower[f.k]
        if f.tick is not None:
            row["lambda2"] = self._lambda2(f.tick.links)
            # λ₂ of the graph of the alive sensors (a dead sensor, isolated, makes λ₂ of the whole graph 0)
            alive = [i for i in range(len(f.tick.links)) if len(f.tick.alive) != len(f.tick.links) or f.tick.alive[i]]
            if len(alive) == len(f.tick.links):
                row["lambda2_alive"] = row["lambda2"]
            else:
                idx = {i: j for j, i in enumerate(alive)}
                row["lambda2_alive"] = self._lambda2([[idx[j] for j in f.tick.links[i] if j in idx] for i in alive])
            row["links"] = sum(len(nb) for nb in f.tick.links) // 2
        exp = f.expected(n)
        self._last_expected = len(exp)
        missing = sum((i not in f.est) + (i not in f.state_pos) for i in exp)
        row["missing"] = missing
        if missing:
            self.missing_total += missing
            self.drop_meter.add(now, missing)
        row["msg_rate"] = self.msg_meter.rate(now)
        row["drop_rate"] = self.drop_meter.rate(now)
        for c, v in row.items():            # a gap, never ±inf (nor a NaN from an unvalidated message)
            if isinstance(v, float) and not math.isfinite(v) and c != "t":
                row[c] = NAN
        err[~np.isfinite(err)] = NAN
        if not self.series_buf.append(row, err, f.nees):
            return
        self.rows[f.k] = row
        known = ~np.isnan(err)
        self._last_err[known] = err[known]
        self.finalized_k = max(self.finalized_k, f.k)

    def _score_nees(self, f: Frame, row: dict) -> np.ndarray:
        """(n,) each node's NEES at tick k against the covariance it reported for x̂ᵢ,ₖ (frame k − 1's
        ``cov``), over the full state; the network's mean and its χ² interval into ``row``
        (:func:`dashboards.nees.network_nees`). NaN for a node without an estimate or such a covariance."""
        out = np.full(self.n, NAN)
        prev, x = self.frames.get(f.k - 1), f.truth
        if prev is None or not prev.cov or x is None or x.ndim != 1 or not x.size:
            return out
        m = x.size
        ids = [i for i in sorted(f.est) if i in prev.cov and f.est[i].shape == x.shape and prev.cov[i].shape == (m, m)]
        if not ids:
            return out
        r = network_nees(np.array([f.est[i] for i in ids]) - x[None, :], np.array([prev.cov[i] for i in ids]))
        out[ids] = r["per_node"]
        if r["scored"]:
            row.update(nees=r["mean"], nees_lo=r["lo"], nees_hi=r["hi"], nees_scored=r["scored"])
        return out

    def _evict(self) -> None:
        if self.keep_frames is None or self._evict_cursor is None:
            return
        lo = min(self.newest_frame - self.keep_frames, self._next_final or 0)
        while self._evict_cursor < lo:
            self.frames.pop(self._evict_cursor, None)
            self.rows.pop(self._evict_cursor, None)
            self._evict_cursor += 1
        lo_trail = self.newest_frame - max(self.keep_frames, self.trail_len)
        while self._trail_cursor < lo_trail:
            self.truth_pos.pop(self._trail_cursor, None)
            self._trail_cursor += 1

    # ------------------------------------------------------------------ reading
    @property
    def shown_k(self) -> int:
        """The tick the scene shows: the newest finalized one (else the newest with a world tick)."""
        if self.finalized_k >= 0:
            return self.finalized_k
        with_tick = [k for k, f in self.frames.items() if f.tick is not None]
        return max(with_tick) if with_tick else -1

    def ticks_available(self) -> list[int]:
        return sorted(k for k, f in self.frames.items() if f.done)

    def snapshot(self, k: int | None = None) -> Snapshot | None:
        """The scene at tick ``k`` (default :attr:`shown_k`); None before the first tick."""
        k = self.shown_k if k is None else k
        f = self.frames.get(k)
        if f is None:
            return None
        n, d = self.n, self.d
        pos = np.full((n, 3), NAN)
        alive = np.ones(n, bool)
        links: list[list[int]] = [[] for _ in range(n)]
        if f.tick is not None and f.tick.n == n:
            pos = _pad3(f.tick.positions)
            alive = np.array(f.tick.alive, bool) if len(f.tick.alive) == n else alive
            links = [list(nb) for nb in f.tick.links]
        else:  # no world tick for this frame: the previous tick's reported states
            prev = self.frames.get(k - 1)
            for i, p in (prev.state_pos.items() if prev else ()):
                pos[i] = _pad3(p)
        errors = np.full(n, NAN)
        est_pos = np.full((n, 3), NAN)
        for i, x in f.est.items():
            est_pos[i] = _pad3(x[:d])
            if f.truth is not None and x.shape == f.truth.shape:
                errors[i] = float(np.linalg.norm(x[:d] - f.truth[:d]))
        cov_pos = {i: P[:d, :d] for i, P in f.cov.items()}
        trail_ks = [j for j in range(k - self.trail_len + 1, k + 1) if j in self.truth_pos]
        trail = np.array([self.truth_pos[j] for j in trail_ks]).reshape(-1, 3)
        pairs = [(i, int(j)) for i, js in sorted(f.suspects.items()) for j in js]
        return Snapshot(k=k, t=f.t, n=n, positions=pos, alive=alive, errors=errors, est_pos=est_pos,
                        est_next=dict(f.est_next), cov_pos=cov_pos, edges=edges_of_links(links), neighbours=links,
                        truth_pos=self.truth_pos.get(k) if f.truth is not None else None, trail=trail,
                        fusion_pos=None if f.fusion is None else _pad3(f.fusion[:d]), row=dict(self.rows.get(k, {})),
                        suspicions=np.array(pairs, dtype=int).reshape(-1, 2),
                        nees=None if f.nees is None else f.nees.copy())

    def series(self, upto_k: int | None = None, last: int | None = None) -> dict[str, np.ndarray]:
        """The plotted series (columns of :data:`SERIES_COLUMNS`, and ``err`` and ``nees_node``: rows × n)."""
        return self.series_buf.arrays(upto_k, last)

    def summary(self) -> dict:
        """Headline numbers for the status panel."""
        row = self.rows.get(self.finalized_k, {})
        return {"k": self.finalized_k, "latest_tick": self.latest_tick, "t": row.get("t", NAN),
                "rmse": row.get("rmse", NAN), "lambda2": row.get("lambda2", NAN), "links": row.get("links", NAN),
                "msg_rate": self.msg_meter.rate(self.last_now), "drop_rate": self.drop_meter.rate(self.last_now),
                "messages": self.messages, "bus_dropped": self.bus_dropped, "missing": self.missing_total,
                "paused": self.paused, "speed": self.speed, "ended": self.ended}


# ============================================================================ replay

class ReplayModel:
    """A recording fed once through an unbounded :class:`DashboardState`; the slider seeks by tick.

    ``messages``: (key, decoded message or None, log time ns) in recording order — None for messages
    that are only counted (exchange payloads, measurements).
    """

    def __init__(self, info: RunInfo, messages, trail_len: int = 200):
        self.info = info
        self.state = DashboardState(info, keep_frames=None, max_points=None, trail_len=trail_len)
        t0 = None
        for key, msg, t_ns in messages:
            now = t_ns / 1e9
            if t0 is None:
                t0 = now
            if msg is None:
                self.state.count(now)
            else:
                self.state.ingest(key, msg, now)
        self.state.finalize_all()
        self.ticks = self.state.ticks_available()

    def __len__(self) -> int:
        return len(self.ticks)

    @property
    def first(self) -> int:
        return self.ticks[0] if self.ticks else 0

    @property
    def last(self) -> int:
        return self.ticks[-1] if self.ticks else 0

    def seek(self, k: int) -> int:
        """The recorded tick nearest to ``k`` at or before it (clamped to the recording)."""
        if not self.ticks:
            return -1
        i = int(np.searchsorted(self.ticks, k, side="right")) - 1
        return self.ticks[max(0, i)]

    def snapshot(self, k: int) -> Snapshot | None:
        return self.state.snapshot(self.seek(k))

    def series(self, k: int, last: int | None = None) -> dict[str, np.ndarray]:
        return self.state.series(upto_k=self.seek(k), last=last)


# ============================================================================ synthetic input

def synthetic_tick(n: int, k: int, *, T: float = 0.1, link_range: float = 12.0, spacing: float = 8.0,
                   noise: float = 0.1, seed: int = 0, alive: list[bool] | None = None,
                   skip_estimates: tuple[int, ...] = ()) -> list[tuple[str, Message | None]]:
    """The messages of one tick of a made-up flock (tests, the benchmark): n sensors on a jittered grid
    following a target on a circle, range links, noisy estimates with covariances. Exchange payloads
    and measurements come as ``(key, None)`` (counted, not decoded, as the dashboard does)."""
    rng = np.random.default_rng([seed, k])
    t = k * T
    w = 0.2
    x = np.array([20 * math.cos(w * t), 20 * math.sin(w * t), -20 * w * math.sin(w * t), 20 * w * math.cos(w * t)])
    cols = max(1, math.ceil(math.sqrt(n)))
    grid = np.array([((i % cols) - (cols - 1) / 2, (i // cols) - (math.ceil(n / cols) - 1) / 2) for i in range(n)],
                    float) * spacing
    pos = grid + x[None, :2] + rng.normal(0, 0.3, (n, 2))
    alive = [True] * n if alive is None else list(alive)
    D = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    adj = (D <= link_range) & ~np.eye(n, dtype=bool)
    adj &= np.outer(alive, alive)
    links = [[int(j) for j in np.flatnonzero(adj[i])] for i in range(n)]
    out: list[tuple[str, Message | None]] = [
        ("world/tick", Tick(k=k, t=t, n=n, links=links, weights=[[1.0] * len(nb) for nb in links], b=[1.0] * n,
                            delta_max=max((len(nb) for nb in links), default=0), alive=alive, positions=pos)),
        ("target/truth", Truth(k=k, t=t, x=x)),
    ]
    P = np.eye(4) * noise ** 2
    for i in range(n):
        if not alive[i]:
            continue
        out.append((f"agent/{i}/meas", None))
        out.append((f"agent/{i}/xchg", None))      # (the tick's rounds, once)
        if i not in skip_estimates:
            xi = x + rng.normal(0, noise, 4)
            out.append((f"agent/{i}/estimate", Estimate(src=i, k=k, x=xi, x_next=xi, P=P, name="Synthetic")))
            out.append((f"agent/{i}/state", State(src=i, k=k, pos=pos[i], vel=x[2:].copy())))
    out.append(("target/state", None))
    return out
