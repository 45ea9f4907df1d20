"""The realtime world's pace under overload (``run.pace = "adaptive"``): the clock yields when the flock cannot
keep it.

A realtime tick lasts the nominal period T / speed. When the machine cannot run the flock's rounds in it, a
fixed clock closes ticks whatever has arrived: sensors sit out rounds and whole ticks (their states come
after the tick closed), and against an adversarial target — Gu & Hu's intelligent target pushes by
k_e (x − x̂), so every tick without an update widens the gap it pushes on — the estimates diverge rather
than degrade (measured: 64 sensors at 10 Hz on a 2-core machine that holds 32: network RMSE 169, the target
gone at 10³ m). So the world measures, at each tick's close, when the sensors' states came in — from the tick's
publication, a missing state counting as never — and

* stretches the next period by ``STRETCH`` (up to ``MAX_STRETCH`` × nominal) when the flock ran out of it: more
  than a tenth of the states never came (deciding on the arrival times instead stretched flocks that keep
  their pace: the world takes the states in late when it waits for a core itself);
* sets it back towards nominal — by at most ``RELAX`` a tick, to no less than the period in which the median
  state would come at ``BUSY``, never below nominal — when the median state came within ``IDLE`` of the period:
  a load burst's stretch is undone within a few ticks after it, a flock that needs a little more than the
  nominal period gets about that much, and one that fits in it is back at it (measured: bringing it back
  only to the median / ``IDLE`` kept a 40-sensor flock whose median state comes at ~80 % of a 10 Hz period
  stretched after every stall — 7 ticks/s);
* holds it in between.

The median decides, not the last state: a few sensors that waited out a round for a payload that never came
(a neighbour that sat out the tick) end by the round's deadline, which scales with the period, and would hold
a stretched clock stretched for ever; one sensor that is dead and not yet noticed does not slow the flock
either. (Measured: deciding by the 90th percentile kept a 12-sensor flock stretched for a whole run after a
2 s load burst; coming back in one step instead of by ``RELAX`` made an overloaded flock fail, stretch,
recover and fail again until its sensors fell out of step with each other.)

It is the default, because a fixed clock above capacity does not degrade, it collapses: 40 sensors at 10 Hz on
2 cores, 5 minutes on the fixed clock, missed 185 489–243 624 round deadlines in each of 3 runs and the network
RMSE reached 10⁵–10⁹ (the intelligent target pushes on every missed update); adaptive, 7.3 ticks/s kept,
114 missed in a minute, RMSE 0.039. Near capacity it costs pace — a flock at the edge fails a tick now and then,
and the rounds of a stretched tick (which scale with its period) end later, so the clock comes back slowly.
``run.pace = "fixed"`` keeps the clock whatever happens, for runs whose timing matters more than their
estimates.

Every tick carries its period (``Tick.period``), and the sensors and
the target fit their round slots and deadlines into it (agent/runner.py ``WaitBudget.scaled``), so a stretched
tick gives every round more time, not only the world. The world's stats count the ticks run stretched and the
largest stretch (``stats/world-0.json``: ``pace_stretched_ticks``, ``pace_max_stretch``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

STRETCH = 1.5       #: the next period × this when the flock ran out of the current one
MAX_STRETCH = 8.0   #: a period never exceeds this × nominal
BUSY = 0.9          #: a period comes back to no less than where the median state would come at this fraction
IDLE = 0.75         #: within this fraction: back towards nominal (to where the median would come at BUSY)
RELAX = 0.9         #: a period shrinks to no less than this × itself a tick
MISSING = 0.1       #: more than this share of the states never came: stretch


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

    def change(self, before: float) -> str | None:
        """A log line when the clock begins or ends yielding (the period left or reached nominal), else None."""
        if self.period == before or (before != self.nominal and self.period != self.nominal):
            return None
        what = "cannot keep its pace" if self.period > before else "keeps its pace again"
        return f"the flock {what}; the period is {self.period * 1e3:.0f} ms (nominal {self.nominal * 1e3:.0f} ms)"

    def close(self, expected: int, arrivals: Sequence[float]) -> float:
        """Tick closed: ``arrivals`` are the seconds from its publication to each state that came in time, of
        ``expected`` sensors. Returns the next tick's period."""
        if expected <= 0:
            return self.period
        if len(arrivals) < (1 - MISSING) * expected:
            self.period = min(self.nominal * MAX_STRETCH, self.period * STRETCH)
        elif (median := arrival_quantile(expected, arrivals, 0.5)) < IDLE * self.period:
            self.period = max(self.nominal, RELAX * self.period, min(self.period, median / BUSY))
        if self.period > self.nominal * (1 + 1e-9):
            self.stretched_ticks += 1
            self.max_stretch = max(self.max_stretch, round(self.stretch, 3))
        return self.period


def arrival_quantile(expected: int, arrivals: Sequence[float], q: float) -> float:
    """The ``q`` quantile of ``expected`` arrival times of which ``arrivals`` came (the rest never: inf)."""
    ranked = sorted(arrivals)
    idx = min(expected - 1, max(0, math.ceil(q * expected) - 1))
    return ranked[idx] if idx < len(ranked) else math.inf
