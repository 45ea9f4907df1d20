"""Drive one role in its own process over a :class:`agent.bus.ZenohBus` (a dora-rs style node loop).

The loop: deliver messages → if the role has waited on the same step longer than its deadline, fire
``on_deadline`` → give a realtime role its timer → until the role is finished or a stop signal comes.
Deadlines and restart policies are declared (scenario / launcher), not coded per role.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

from .ports import slug
from .roles.common import Role

log = logging.getLogger(__name__)


def process_age_s() -> float:
    """Seconds since this process was created — its fork, from /proc (a process forked from the launcher's
    pre-imported template, flocktrack/launch/forkserver.py, imported this module long before it existed)."""
    try:
        fields = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - int(fields[19]) / os.sysconf("SC_CLK_TCK")     # field 22: starttime, in clock ticks
    except (OSError, ValueError, IndexError):
        return float("nan")


def parse_member(name: str) -> tuple[str, int] | None:
    """'agent/3' → ('agent', 3)."""
    role, _, ident = name.partition("/")
    try:
        return role, int(ident)
    except ValueError:
        return None


class StopFlag:
    """Set by SIGTERM/SIGINT; the loop exits cleanly (token withdrawn, session closed)."""

    def __init__(self) -> None:
        self.event = threading.Event()

    def install(self) -> "StopFlag":
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self._on_signal)
        return self

    def _on_signal(self, *_) -> None:
        from .bus import wake_all

        self.event.set()
        wake_all()      # a poll blocked in its queue sees the flag now

    @property
    def set(self) -> bool:
        return self.event.is_set()


def quick_gil_handoff() -> None:
    """Zenoh's receiving thread needs the GIL for every sample (the bus's callbacks run on it, to keep the
    order of arrival): with the default 5 ms switch interval a role computing an update holds it off for up
    to 5 ms per sample. 1 ms, measured with a busy thread and 100-sample bursts (direct callbacks): p95
    latency 54 → 16 ms, max 130 → 24 ms. (The dashboard's process too: dashboards/live.py run_live.)"""
    import sys

    sys.setswitchinterval(0.001)


#: the Zenoh runtime of a role process (``ZENOH_RUNTIME``, read once, at the process's first session): the
#: receiving, transmitting, network and accepting tasks handed over to one ``app`` worker. Zenoh's default gives a
#: client two ``rx`` workers besides ``app``/``net``/``acc``/``tx``, and a sample then wakes a thread that wakes
#: another; a role's process has one link (to its router) and ~25 samples a tick, which one worker carries.
#: Measured with bench-like isolated samples (300 B, 2.5 ms apart, the subscriber busy 0.3 ms per sample): the
#: subscriber's CPU per sample 97 → 61 µs, voluntary switches 4.2 → 2.2; 40 sensors at 10 Hz: 3.21 → 2.95 ms CPU
#: per sensor per tick. The ``tx`` tasks too (a put wakes the worker that may be awake already, not a thread of
#: their own): N = 10 lockstep, all processes, 27.3 / 27.5 → 26.0 / 26.5 ms CPU a tick. (A put releases the GIL
#: while it waits for room in the queue, so a receive callback on the same worker cannot lock it out.) Routers
#: keep Zenoh's default (they carry every link).
ROLE_ZENOH_RUNTIME = ("(tx: (handover: app), rx: (handover: app), net: (handover: app), acc: (handover: app), "
                      "app: (worker_threads: 1))")


def lean_zenoh_runtime() -> None:
    """Give this role process :data:`ROLE_ZENOH_RUNTIME` unless ``ZENOH_RUNTIME`` is set already — call it
    first thing in a role's main, before any Zenoh session is opened (later it has no effect)."""
    os.environ.setdefault("ZENOH_RUNTIME", ROLE_ZENOH_RUNTIME)


#: the niceness of the run's observers (recorder, dashboard): when the flock's processes all wake at once
#: at a tick (a burst of every sensor's rounds), the kernel runs the sensors first and the observers in the
#: rest of the period — nothing of theirs is on the tick's critical path, and their queues absorb the wait
OBSERVER_NICE = 10


def observer_priority() -> None:
    """Lower this process's CPU priority to :data:`OBSERVER_NICE` — call it first thing in an observer's
    main, before any thread is started (Linux sets a thread's niceness; new threads inherit it)."""
    try:
        os.nice(OBSERVER_NICE)
    except OSError:       # not permitted here: run at the default priority
        pass


#: the node loop's heartbeat: the longest it waits for a message. It also wakes for the current wait's deadline
#: and the role's own timer (:meth:`Role.next_timer`: the realtime world's clock, payloads delayed in ms) when
#: they are due, so no mode needs a fine poll; at 50 ms an idle flock's wake-ups (20 a second per process)
#: cost next to nothing (a 10 ms realtime poll cost an idle 12-sensor flock 4 % of a core)
IDLE_POLL_S = 0.05


@dataclass(frozen=True)
class WaitBudget:
    """How long a role may wait on one step of its protocol before it goes on with what has arrived —
    declared per role and mode (agent/__main__.py ``role_budget``), enforced by :func:`drive`.

    A role's wait is identified by ``wait_key = (k, r)``: step k (a tick), sub-step r (an exchange round).

    - ``schedule=False`` (lockstep): every wait gets ``slot_s`` from the moment it began — deadlines only
      catch dead or stopped processes.
    - ``schedule=True`` (realtime): the sub-steps of a step share a slot schedule anchored at the step's
      first wait: wait (k, r) is due ``(r + 1 + head) · slot_s`` after it. Time a fast round leaves unused
      goes to the next one, and the first round's ``head`` extra slots absorb the spread of the moments
      the neighbours begin the tick (one descheduled for a few ms on a loaded machine would otherwise
      miss everybody's round 0).
    - ``window_s``: no wait of a step lasts past ``window_s`` after the moment the role learned of the step
      (:meth:`Role.step_anchor`: for a sensor, when the world's tick reached it). A role that begins a step
      late — descheduled, or still waiting out the last one — gets what is left of the step's window, not a
      whole new schedule, so one late tick does not make the next one late too.
    - ``final``: the step's last sub-step (a sensor's round R − 1). Nothing of the step comes after it but
      the tail the window keeps, so it waits until the window's end, not only its slot's: the time between
      the two (the part of the tail the role's late start did not take) would otherwise go unused while a
      neighbour's last payload is a few ms away.
    - ``warmup_s``: the budget of every wait of step 0, the run's first tick, in which routes and
      publishers are still being set up (the realtime world closes tick 0 on its states, not its clock).
    """

    slot_s: float
    schedule: bool = False
    head: float = 0.0
    warmup_s: float | None = None
    window_s: float | None = None
    period_s: float | None = None   #: realtime: the period the budget was made for (see :meth:`scaled`)
    final: int | None = None        #: the last sub-step of a step: due at the window's end

    #: a step's announced period is taken within this factor of the nominal one (a hostile tick cannot make a
    #: sensor wait for hours or not at all)
    MAX_SCALE = 64.0

    def scaled(self, period_s: float | None) -> WaitBudget:
        """This budget for a step that lasts ``period_s`` instead of :attr:`period_s` (the realtime world
        stretches its period while the flock cannot keep it, topology/pace.py; a live speed change sets a new
        one): slots and window in proportion; the warm-up as it is. Unchanged in lockstep or without a period."""
        if self.period_s is None or not period_s or period_s <= 0:
            return self
        f = min(self.MAX_SCALE, max(1.0 / self.MAX_SCALE, period_s / self.period_s))
        if f == 1.0:
            return self
        return replace(self, slot_s=self.slot_s * f, window_s=None if self.window_s is None else self.window_s * f,
                       period_s=self.period_s * f)

    @classmethod
    def lockstep(cls, deadline_s: float, *, rounds: int, depth: int) -> WaitBudget:
        """A lockstep wait: ``deadline_s``, and an outer one (:attr:`Role.wait_depth` ≥ 1) outlasts the waits
        inside it — a sensor's ``rounds`` rounds and its rejoin, then the target's wait — so a world whose
        sensors wait out a round for a stopped neighbour closes its tick on their states, not ahead of them
        (the in-process engine fires its deadlines innermost first, for the same reason)."""
        return cls(deadline_s if depth <= 0 else deadline_s * (rounds + 1 + depth))

    def due(self, key: tuple, began: float, step_began: float, anchor: float | None = None) -> float:
        """When wait ``key`` times out: begun at ``began``, its step's first wait at ``step_began``, the role
        told of the step at ``anchor`` (None: it does not say)."""
        if self.warmup_s is not None and key[0] == 0:
            return began + self.warmup_s
        if not self.schedule:
            return began + self.slot_s
        due = step_began + (key[1] + 1 + self.head) * self.slot_s
        if self.window_s is not None and anchor is not None:
            end = anchor + self.window_s
            due = end if self.final is not None and key[1] >= self.final else min(due, end)
        return due


def drive(role: Role, bus, name: str, deadline_s: float | WaitBudget, stop: StopFlag | None = None, *,
          expect: Iterable[str] = (), startup_timeout_s: float = 60.0, linger_s: float = 0.5,
          idle_s: float = IDLE_POLL_S) -> int:
    """Run ``role`` until it finishes. ``deadline_s``: a :class:`WaitBudget`, or seconds per wait.
    ``expect``: member names that must be alive before :meth:`Role.start` (the world's start barrier).
    ``idle_s``: see :data:`IDLE_POLL_S`. Returns a process exit code."""
    stop = stop or StopFlag()
    budget = deadline_s if isinstance(deadline_s, WaitBudget) else WaitBudget(float(deadline_s))
    members: set[str] = set()
    quick_gil_handoff()

    def on_member(member: str, alive: bool) -> None:
        (members.add if alive else members.discard)(member)
        pm = parse_member(member)
        if pm is not None:
            role.on_member(pm[0], pm[1], alive)

    if hasattr(bus, "restrict_writes"):
        bus.restrict_writes(role.ports().writes)
    timing = getattr(role, "timing", None)
    if timing is not None and os.environ.get("FLOCKTRACK_STATS_DIR"):
        timing.path = Path(os.environ["FLOCKTRACK_STATS_DIR"]) / (slug(name) + "-ticks.csv")
    role.attach(bus)
    bus.watch_members(on_member)
    bus.declare_token(name)
    log.info("%s: member of the run (%.2f s after the process started)", name, process_age_s())
    expect = set(expect)
    t_start = time.monotonic()
    while expect - members:
        if stop.set:
            return 0
        bus.poll(0.05)
        if time.monotonic() - t_start > startup_timeout_s:
            log.warning("%s: starting without %s after %.0f s", name, sorted(expect - members), startup_timeout_s)
            break
    role.start()
    try:
        _loop(role, bus, name, budget, stop, idle_s=idle_s)
    except Exception:
        write_stats(name, bus, role)
        raise
    # let the last publications leave before the session closes
    end = time.monotonic() + linger_s
    while time.monotonic() < end and not stop.set:
        bus.poll(0.02)
    write_stats(name, bus, role)
    return 0


def _loop(role: Role, bus, name: str, budget: WaitBudget, stop: StopFlag, *, idle_s: float) -> None:
    last_key, due = None, float("inf")
    step_began, anchor = time.monotonic(), None
    nominal, budget = budget, budget
    while not role.finished and not stop.set:
        # wake for the next message, the current wait's deadline, the role's timer or the idle poll, which first
        timer = role.next_timer()
        wake = min(due, timer) if timer is not None else due
        if bus.poll(max(0.0, min(idle_s, wake - time.monotonic()))) == 0:
            role.on_idle()
        now = time.monotonic()
        role.on_timer(now)
        key = role.wait_key
        if key != last_key:
            if key is not None and (last_key is None or key[0] != last_key[0]):
                step_began, anchor = now, role.step_anchor(key[0])
                budget = nominal.scaled(role.step_period(key[0]))
            last_key = key
            due = float("inf") if key is None else budget.due(key, now, step_began, anchor)
        elif key is not None and now >= due:
            log.info("%s: deadline on %s%s", name, key, role.waiting_for())
            role.on_deadline()
            # the same wait going on (e.g. a rejoin still short of estimates): one budget more from now
            due = max(budget.due(key, now, step_began, anchor), now + budget.slot_s)


def write_stats(name: str, bus, role: Role | None = None) -> None:
    """Dump this process's bus counters to ``$FLOCKTRACK_STATS_DIR/<name>.json`` (set by the launcher), and
    the last rows of its tick timing (:mod:`agent.roles.tick_timing`) to ``<name>-ticks.csv``."""
    import json

    d = os.environ.get("FLOCKTRACK_STATS_DIR")
    if not d:
        return
    timing = getattr(role, "timing", None)
    if timing is not None:
        timing.flush()          # the last rows of stats/<name>-ticks.csv
    out = bus.stats.as_dict()
    counters = getattr(role, "counters", None) or getattr(role, "stats", None)
    if counters:
        out["role"] = dict(counters)
    p = Path(d) / (slug(name) + ".json")
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(out, indent=1, sort_keys=True))



def profiled(name: str, fn):
    """``fn()``, under cProfile when ``$FLOCKTRACK_PROFILE_DIR`` is set (bench/: where a process's
    time goes); the stats land in ``<dir>/<name>.prof`` (``python -m pstats`` or snakeviz reads them)."""
    import os

    d = os.environ.get("FLOCKTRACK_PROFILE_DIR")
    if not d:
        return fn()
    import cProfile
    from pathlib import Path

    prof = cProfile.Profile(time.thread_time)  # CPU of this thread: waiting for others is not counted
    try:
        return prof.runcall(fn)
    finally:
        Path(d).mkdir(parents=True, exist_ok=True)
        prof.dump_stats(str(Path(d) / (slug(name) + ".prof")))
