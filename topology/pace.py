"""The realtime world's pace under overload: the clock yields when the flock cannot keep it.

A realtime tick lasts the nominal period T / speed. When the machine cannot run the flock's rounds in it, a
fixed clock closes ticks whatever has arrived: sensors sit out rounds and whole ticks (their states come
after the tick closed), and against an adversarial target — Gu & Hu's intelligent target pushes by
k_e (x − x̂), so every tick without an update widens the gap it pushes on — the estimates diverge rather
than degrade (measured: 64 sensors at 10 Hz on a 2-core machine that holds 32: network RMSE 169, the target
gone at 10³ m). So the world measures, at each tick's close, when the sensors' states came in — the
``QUANTILE`` of their arrival times from the tick's publication, a missing state counting as never — and

* stretches the next period by ``STRETCH`` (up to ``MAX_STRETCH`` × nominal) when that time was past
  ``BUSY`` of the period: the flock did not finish its rounds in time;
* sets it back towards nominal — straight to the arrival time / ``IDLE``, never below nominal — when the
  flock finished within ``IDLE`` of the period; a load burst's stretch is undone in the first tick after it;
* holds it in between.

The quantile, not the last arrival, decides: one sensor that is dead and not yet noticed, or descheduled for
one tick, does not slow the whole flock. Every tick carries its period (``Tick.period``), and the sensors and
the target fit their round slots and deadlines into it (agent/runner.py ``WaitBudget.scaled``), so a stretched
tick gives every round more time, not only the world. The world's stats count the ticks run stretched and the
largest stretch (``stats/world-0.json``: ``pace_stretched_ticks``, ``pace_max_stretch``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

STRETCH = 1.5       #: the next period × this when the flock ran out of the current one
MAX_STRETCH = 4.0   #: a period never exceeds this × nominal
BUSY = 0.9          #: the quantile of the states' arrival past this fraction of the period: stretch
IDLE = 0.6          #: within this fraction: back towards nominal (arrival / IDLE)
QUANTILE = 0.9      #: which arrival decides (a missing state counts as never)


class PaceGovernor:
    """The period of the next realtime tick from the arrival times of this tick's states."""

    def __init__(self, nominal_s: float):
        self.nominal = float(nominal_s)
        self.period = self.nominal
        self.stretched_ticks = 0
        self.max_stretch = 1.0

    def set_nominal(self, nominal_s: float) -> None:
        """A new nominal period (the run's speed changed): the stretch factor is kept."""
        factor = self.period / self.nominal
        self.nominal = float(nominal_s)
        self.period = self.nominal * factor

    @property
    def stretch(self) -> float:
        return self.period / self.nominal

    def close(self, expected: int, arrivals: Sequence[float]) -> float:
        """Tick closed: ``arrivals`` are the seconds from its publication to each state that came in time, of
        ``expected`` sensors. Returns the next tick's period."""
        if expected <= 0:
            return self.period
        late = arrival_quantile(expected, arrivals, QUANTILE)
        if late > BUSY * self.period:
            self.period = min(self.nominal * MAX_STRETCH, self.period * STRETCH)
        elif late < IDLE * self.period:
            self.period = max(self.nominal, min(self.period, late / IDLE))
        if self.period > self.nominal * (1 + 1e-9):
            self.stretched_ticks += 1
            self.max_stretch = max(self.max_stretch, round(self.stretch, 3))
        return self.period


def arrival_quantile(expected: int, arrivals: Sequence[float], q: float) -> float:
    """The ``q`` quantile of ``expected`` arrival times of which ``arrivals`` came (the rest never: inf)."""
    ranked = sorted(arrivals)
    idx = min(expected - 1, max(0, math.ceil(q * expected) - 1))
    return ranked[idx] if idx < len(ranked) else math.inf
