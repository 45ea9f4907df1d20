"""Where a sensor's tick went: one row per tick, so that a bad tick can be explained from the run's own output.

For tick k the sensor records, in milliseconds:

* ``start_ms``   — from the world's tick reaching the process to the sensor beginning the tick (waiting for the
  target's truth, or for its own previous tick to finish);
* ``compute_ms`` — the estimator's and the controller's work on the role's thread (measure, start, every round's
  absorb, finish, control), wall time;
* ``publish_ms`` — encoding and handing over its messages (meas, each round's payloads, estimate, state), wall
  time;
* ``wait_ms``    — the rest of the tick on the role's thread: waiting for the neighbours' payloads (and
  decoding them as they come);
* ``receive_ms`` — the process's CPU during the tick less the role thread's CPU in compute and publish: what the
  process spent receiving — the transport's threads and the decoding and validating of every message that came;
* ``cpu_ms``, ``total_ms`` — the process's CPU and the wall time from the tick's arrival to its state sent;
* ``rounds``, ``deadline_rounds`` — the exchange rounds, and how many of them ended by deadline (a payload
  that did not come in time).

With ``$FLOCKTRACK_STATS_DIR`` set (the launcher sets it to the run's ``stats/``) the rows are appended to
``stats/<process>-ticks.csv`` in batches as the run goes, and the rest when the process ends.
"""

from __future__ import annotations

import csv
import time
from pathlib import Path

COLUMNS = ("k", "start_ms", "compute_ms", "publish_ms", "wait_ms", "receive_ms", "cpu_ms", "total_ms", "rounds",
           "deadline_rounds")


class TickTiming:
    """The timing rows of one sensor; ``path`` the CSV they go to (None: kept in memory, the last ``keep``).
    ``stagger``: the first batch is that many rows (mod ``batch``) shorter, so that a flock's sensors, which
    all begin at tick 0, write their files at different ticks instead of all in the same one."""

    def __init__(self, path: str | Path | None = None, *, batch: int = 100, keep: int = 1000, stagger: int = 0,
                 clock=time.monotonic, cpu=time.process_time, thread_cpu=time.thread_time):
        self.path = None if path is None else Path(path)
        self.batch, self.keep = int(batch), int(keep)
        self._due = self.batch - int(stagger) % self.batch    # rows held when the next batch is written
        self.clock, self.cpu, self.thread_cpu = clock, cpu, thread_cpu
        self.rows: list[tuple] = []
        self._written = False
        self._open: dict | None = None

    def begin(self, k: int, arrived: float | None) -> None:
        """Tick ``k`` begins now; its world tick reached the process at ``arrived`` (``clock`` time)."""
        now = self.clock()
        self._open = {"k": k, "arrived": now if arrived is None else arrived, "begin": now, "cpu": self.cpu(),
                      "compute": 0.0, "publish": 0.0, "busy_cpu": 0.0, "rounds": 0, "deadline_rounds": 0}

    def spent(self, kind: str) -> _Spent:
        """Time the block as ``compute`` or ``publish`` of the open tick (nothing when none is open): its wall
        time, and its CPU on this thread (what ``receive_ms`` leaves out)."""
        return _Spent(self, kind)

    def round_closed(self, by_deadline: bool) -> None:
        if self._open is not None:
            self._open["rounds"] += 1
            self._open["deadline_rounds"] += bool(by_deadline)

    def end(self) -> tuple | None:
        """Close the open tick: its row (None when no tick was open)."""
        o, self._open = self._open, None
        if o is None:
            return None
        now, cpu = self.clock(), self.cpu() - o["cpu"]
        busy = o["compute"] + o["publish"]
        row = (o["k"], _ms(o["begin"] - o["arrived"]), _ms(o["compute"]), _ms(o["publish"]),
               _ms(max(now - o["begin"] - busy, 0.0)), _ms(max(cpu - o["busy_cpu"], 0.0)), _ms(cpu),
               _ms(now - o["arrived"]),
               o["rounds"], o["deadline_rounds"])
        self.rows.append(row)
        if self.path is not None and len(self.rows) >= self._due:
            self.flush()
        elif self.path is None and len(self.rows) > 2 * self.keep:
            del self.rows[:-self.keep]
        return row

    def flush(self) -> None:
        """Append the rows held to ``path`` (the header first, once)."""
        if self.path is None or not self.rows:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a" if self._written else "w", newline="") as f:
            w = csv.writer(f)
            if not self._written:
                w.writerow(COLUMNS)
            w.writerows(self.rows)
        self._written = True
        self.rows = []
        self._due = self.batch


class _Spent:
    """One ``with timing.spent(kind):`` block. A plain object: ~40 of them a sensor tick, and as a generator
    (``contextlib.contextmanager``) each cost three times as much."""

    __slots__ = ("timing", "kind", "t0", "c0")

    def __init__(self, timing: TickTiming, kind: str):
        self.timing, self.kind = timing, kind

    def __enter__(self) -> None:
        self.t0, self.c0 = self.timing.clock(), self.timing.thread_cpu()

    def __exit__(self, *exc) -> bool:
        o = self.timing._open
        if o is not None:
            o[self.kind] += self.timing.clock() - self.t0
            o["busy_cpu"] += self.timing.thread_cpu() - self.c0
        return False


def _ms(s: float) -> float:
    return round(s * 1e3, 3)
