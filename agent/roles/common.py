"""What every role shares: the bus handle, the run length, the deadline hook, and the fault plan's events
typed by wire.py."""

from __future__ import annotations

from collections import Counter

from ..bus import Bus
from ..ports import Ports
from ..wire import Control, FaultEvent, Message, WireError, encode, fault_event


class Role:
    """Base class of the message-driven roles. ``PORTS``: what the role writes and reads (:mod:`agent.ports`),
    declared by each role next to its code."""

    name = "role"
    PORTS = Ports()

    def __init__(self, ticks: int):
        self.ticks = int(ticks)
        self.bus: Bus | None = None
        self.counters: Counter = Counter()

    def ports(self) -> Ports:
        """This node's ports (``{i}`` = its id)."""
        return self.PORTS.of(getattr(self, "i", 0))

    def attach(self, bus: Bus) -> None:
        self.bus = bus
        self.subscribe(bus)

    def subscribe(self, bus: Bus) -> None:  # pragma: no cover - every role overrides
        raise NotImplementedError

    def publish(self, key: str, msg: Message) -> None:
        assert self.bus is not None, "attach() the role to a bus first"
        self.bus.publish(key, msg)

    def publish_to(self, keys: list[str], msg: Message) -> None:
        """The same message on several keys, encoded once (an exchange payload to each neighbour)."""
        assert self.bus is not None, "attach() the role to a bus first"
        data = encode(msg)
        for key in keys:
            self.bus.publish_raw(key, data)

    def start(self) -> None:
        """Called once after every role is attached (the world publishes tick 0 here)."""

    @property
    def waiting(self) -> bool:
        """True while the role waits for messages of the current tick."""
        return False

    @property
    def finished(self) -> bool:
        return False

    def on_deadline(self) -> None:
        """The wait for the current step timed out: go on with what has arrived."""

    #: how many other roles' waits this role's wait encloses: 0 for a sensor's exchange round, 1 for the
    #: intelligent target's wait for the sensors' estimates, 2 for the world's wait for every state. An outer
    #: wait may give up only after the waits inside it could have ended — a world that closed its tick while
    #: the sensors still waited out a round would run ahead of the whole flock (flocktrack/engine/inproc.py
    #: fires deadlines innermost first)
    wait_depth: int = 0

    @property
    def wait_key(self) -> tuple | None:
        """Identifies the current wait (e.g. (k, r)); a driver fires :meth:`on_deadline` when the same
        wait lasts longer than its deadline. None when not waiting."""
        if not self.waiting:
            return None
        return (getattr(self, "k", 0), getattr(self, "r", 0))

    def step_anchor(self, k: int) -> float | None:
        """When (``time.monotonic()``) this role learned that step ``k`` began — for a sensor, the moment the
        world's tick k reached it — or None if it does not say. A realtime step's waits end within a window
        from it (agent/runner.py WaitBudget.window_s)."""
        return None

    def step_period(self, k: int) -> float | None:
        """The wall-clock seconds step ``k`` lasts, as the realtime world announced it (``Tick.period``: the
        pace it keeps, stretched under overload — topology/pace.py), or None (or 0, a lockstep tick's): the nominal
        T / speed. The driver fits the step's waits into it (agent/runner.py WaitBudget.scaled)."""
        return None

    def waiting_for(self) -> str:
        """What the current wait still lacks, for the driver's ``deadline on`` log line (" — …"; "" if
        the role does not say)."""
        return ""

    def on_member(self, role: str, ident: int, alive: bool) -> None:
        """Membership change seen by the transport (a process appeared or vanished)."""

    def on_idle(self) -> bool:
        """Nothing more is arriving right now; return True if the role did something (released
        messages it was holding back)."""
        return False

    def on_timer(self, now: float) -> None:
        """Called by a process driver with the wall-clock time (s, ``time.monotonic``): after every batch of
        messages, at :meth:`next_timer`, and at least every idle poll."""

    def next_timer(self) -> float | None:
        """When the role next needs :meth:`on_timer` (``time.monotonic`` seconds; None: no timed work) — the
        driver sleeps until then, not in short polls (an idle flock costs nothing)."""
        return None

    def on_world_event(self, key: str, msg: Message) -> None:
        """``world/event`` (subscribe it to get fault-plan transitions, topology/faults.py): a ``fault`` is
        typed by :func:`agent.wire.fault_event` and handed to :meth:`on_fault`; a malformed one is counted
        (``rejected_events``) and dropped."""
        assert isinstance(msg, Control)
        if msg.verb != "fault":
            return
        try:
            ev = fault_event(msg.args)
        except WireError:
            self.counters["rejected_events"] += 1
            return
        self.on_fault(ev)

    def on_fault(self, ev: FaultEvent) -> None:
        """A fault starts or heals (:meth:`on_world_event`)."""
