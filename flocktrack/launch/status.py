"""The live status line of ``flocktrack run`` over Zenoh: what the run is doing, in one line.

    starting · 9/16 processes up
    tick 412/1000 · 24.8 ticks/s (target 25.0) · RMSE 0.083 · deadlines 0 · sensors 12/12

It listens to ``world/tick`` (k, who is alive), ``target/truth`` and ``agent/*/estimate`` through its own
Zenoh client — the RMSE is the one of metrics.csv (position error, RMS over the sensors reporting the
tick) for the newest tick that has both — and takes the number of missed round deadlines from the
launcher, which sees every process's log. Until the first tick it counts the run's processes whose
liveliness token is up (the flock coming up). On a terminal the line is redrawn in place (4 Hz); otherwise
(a log file, CI) one plain line every 10 % of the run.
"""

from __future__ import annotations

import math
import sys
import time
from collections import deque
from collections.abc import Callable

import numpy as np


class StatusBoard:
    """What the line says, from the run's messages and its members — no transport (:class:`RunStatus` puts it
    on the run's Zenoh bus). ``deadlines()``: the missed round deadlines so far; ``processes``: how many of the
    run's processes declare a token; ``clock``: the time a tick is stamped with (the rate)."""

    def __init__(self, ticks: int, n: int, pos_dims: int, *, target_rate: float | None = None,
                 deadlines: Callable[[], int] = lambda: 0, processes: int | None = None,
                 clock: Callable[[], float] = time.monotonic, rounds: int | None = None):
        self.ticks, self.n, self.d, self.target_rate = int(ticks), int(n), int(pos_dims), target_rate
        self.deadlines, self.clock = deadlines, clock
        self.rounds = rounds              # exchange rounds per sensor and tick (the pace warning's denominator)
        self._pace: tuple[float, int, int] | None = None   # (time, tick, deadlines) at the window's start
        self.k = -1
        self.done = False                 # world/end seen: every tick is through
        self.alive = 0
        self.processes = processes        # how many of the run's processes declare a token (start-up progress)
        self.members: set[str] = set()
        self.rmse: float | None = None
        self._truth: dict[int, np.ndarray] = {}
        self._est: dict[int, dict[int, np.ndarray]] = {}
        self._stamps: deque[tuple[float, int]] = deque(maxlen=64)

    def subscribe(self, bus) -> None:
        """Listen on ``bus`` (a :class:`agent.bus.Bus`) to what the line is made of."""
        bus.subscribe("world/tick", self._on_tick)
        bus.subscribe("target/truth", self._on_truth)
        bus.subscribe("agent/*/estimate", self._on_estimate)
        bus.subscribe("world/end", self._on_end)

    def on_member(self, name: str, alive: bool) -> None:
        """A member's liveliness token appeared or went (``name``: e.g. ``agent/3``)."""
        (self.members.add if alive else self.members.discard)(name)

    # ------------------------------------------------------------------ messages
    def _on_tick(self, key, msg) -> None:
        if msg.k > self.k:
            self.k = msg.k
            self.alive = sum(bool(a) for a in msg.alive)
            self._stamps.append((self.clock(), msg.k))
            for d in (self._truth, self._est):          # keep a few ticks only
                for kk in [kk for kk in d if kk < msg.k - 8]:
                    del d[kk]

    def _on_end(self, key, msg) -> None:
        self.done = True

    def _on_truth(self, key, msg) -> None:
        self._truth[msg.k] = msg.x
        self._score(msg.k)

    def _on_estimate(self, key, msg) -> None:
        self._est.setdefault(msg.k, {})[msg.src] = msg.x
        self._score(msg.k)

    def _score(self, k: int) -> None:
        x, est = self._truth.get(k), self._est.get(k)
        if x is None or not est:
            return
        errs = [float(np.linalg.norm(e[: self.d] - x[: self.d])) for e in est.values() if e.shape == x.shape]
        if errs and all(math.isfinite(e) for e in errs):
            self.rmse = float(np.sqrt(np.mean(np.square(errs))))

    # ------------------------------------------------------------------ the line
    def rate(self) -> float | None:
        """Ticks per second over the last few seconds."""
        if len(self._stamps) < 2:
            return None
        (t0, k0), (t1, k1) = self._stamps[0], self._stamps[-1]
        return (k1 - k0) / (t1 - t0) if t1 > t0 else None

    def pace_warning(self, window_s: float = 10.0, share: float = 0.05) -> str | None:
        """Once every ``window_s`` of a realtime run: when at least ``share`` of the flock's exchange rounds in
        the window ended by deadline (a payload that did not come in time), or the flock kept less than
        1 − ``share`` of the target rate (the world's clock yielded to it, topology/pace.py), what to do about it."""
        if not self.target_rate or not self.rounds or self.k < 0 or self.done:
            return None
        now, d = self.clock(), self.deadlines()
        if self._pace is None:
            self._pace = (now, self.k, d)
            return None
        t0, k0, d0 = self._pace
        if now - t0 < window_s:
            return None
        self._pace = (now, self.k, d)
        rounds = (self.k - k0) * max(self.alive, 1) * self.rounds
        missed = (d - d0) / rounds if rounds > 0 else 0.0
        kept = (self.k - k0) / (now - t0)
        advice = "the machine cannot keep this rate — lower run.speed or sensors.n"
        if missed >= share:
            return (f"{100 * min(missed, 1.0):.0f} % of rounds missed in the last {now - t0:.0f} s "
                    f"({d - d0} deadlines in {self.k - k0} ticks): {advice}")
        if kept < (1 - share) * self.target_rate:
            return (f"{kept:.1f} of {self.target_rate:.1f} ticks/s in the last {now - t0:.0f} s (the clock yields "
                    f"to a flock that cannot keep it): {advice}")
        return None

    def line(self) -> str:
        if self.k < 0 and not self.done and self.processes:
            up = len([m for m in self.members if not m.startswith("launcher/")])
            return f"starting · {min(up, self.processes)}/{self.processes} processes up"
        k = self.ticks if self.done else max(self.k, 0)
        parts = [f"tick {k}/{self.ticks}"]
        r = self.rate()
        rate = "–" if r is None else f"{r:.1f}"
        parts.append(f"{rate} ticks/s" + (f" (target {self.target_rate:.1f})" if self.target_rate else ""))
        parts.append("RMSE –" if self.rmse is None else f"RMSE {self.rmse:.3g}")
        parts.append(f"deadlines {self.deadlines()}")
        parts.append(f"sensors {self.alive}/{self.n}")
        if self.target_rate and r is not None and r < 0.8 * self.target_rate and k > 10:
            parts.append("behind realtime")
        return " · ".join(parts)


class RunStatus(StatusBoard):
    """The :class:`StatusBoard` of run ``run`` through its own Zenoh client of the router at ``endpoint``, drawn
    on ``stream`` (stderr)."""

    def __init__(self, run: str, endpoint: str, ticks: int, n: int, pos_dims: int, *, target_rate: float | None,
                 config_file: str | None = None, stream=None, deadlines=lambda: 0, processes: int | None = None,
                 rounds: int | None = None):
        from agent.bus import ZenohBus

        super().__init__(ticks, n, pos_dims, target_rate=target_rate, deadlines=deadlines, processes=processes,
                         rounds=rounds)
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self._last_draw = 0.0
        self._last_decile = -1
        self._width = 0
        self.bus = ZenohBus(run, connect=endpoint, config_file=config_file)
        self.subscribe(self.bus)
        self.bus.watch_members(self.on_member)

    def poll(self) -> None:
        """Take in what arrived; redraw when due; warn when the run cannot keep its rate."""
        self.bus.poll(0)
        warning = self.pace_warning()
        if warning is not None:
            self.clear()
            print(f"warning: {warning}", file=self.stream, flush=True)
        now = time.monotonic()
        if self.tty:
            if now - self._last_draw >= 0.25:
                self._draw(self.line())
                self._last_draw = now
        else:
            decile = int(10 * max(self.k, 0) / max(self.ticks, 1))
            if decile != self._last_decile:
                self._last_decile = decile
                print(self.line(), file=self.stream, flush=True)

    def _draw(self, text: str) -> None:
        pad = max(0, self._width - len(text))
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()
        self._width = len(text)

    def clear(self) -> None:
        """Remove the line so a log line or a warning can be printed cleanly (terminal only)."""
        if self.tty and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0

    def close(self, final: bool = True) -> None:
        if final:
            self.bus.poll(0)
            if self.tty:
                self._draw(self.line())
                self.stream.write("\n")
            else:
                print(self.line(), file=self.stream, flush=True)
        self.bus.close()
