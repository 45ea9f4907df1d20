"""What a lockstep world waits for before it publishes a tick on which a process fault acts.

The launcher executes the plan's process faults (crash, pause, router_restart; topology/faults.py) and
acknowledges each on ``launcher/event`` once it has taken effect. In lockstep the world holds the tick
of such a transition until:

* every acknowledgement is in — the crashed process is reaped, the paused one stopped, the continued
  one running, the restarted one spawned, the router about to close;
* a restarted sensor (crash heal) is a member again (its liveliness token is back), so it takes part
  from its heal tick on;
* after a router restart: the outage has been seen (every member's token vanished with the router) —
  the fault's tick is published into the outage and lost, as it would be on a real network — and then
  every member that was there before the restart is back before the next tick.

Without a launcher the world never holds; past ``timeout_s`` it gives up waiting (counted).
"""

from __future__ import annotations

from dataclasses import dataclass, field

Member = tuple[str, int]   # ('agent', 3), ('target', 0), …

LAUNCHER: Member = ("launcher", 0)


@dataclass
class FaultHold:
    timeout_s: float = 30.0
    members: set[Member] = field(default_factory=set)     # alive now (liveliness tokens)
    acks: dict[tuple[int, str], str] = field(default_factory=dict)   # (fault id, phase) → kind, not yet acknowledged
    returning: set[Member] = field(default_factory=set)   # awaited back
    outage: set[Member] | None = None                      # router restart acked, outage not yet seen: who to await
    since: float | None = None                             # wall clock when the current hold began
    timeouts: int = 0

    @property
    def launcher(self) -> bool:
        return LAUNCHER in self.members

    def expect(self, fault_id: int, phase: str, kind: str, me: Member) -> None:
        """A process-fault transition was published: wait for its ack (and, for a router restart, for
        the outage and the return of everyone alive now but ``me``)."""
        self.acks[(fault_id, phase)] = kind
        if kind == "router_restart" and phase == "start":
            self.outage = {m for m in self.members if m not in (me, LAUNCHER)}

    def ack(self, fault_id: int, phase: str, kind: str, agents: list[int]) -> bool:
        """The launcher's ack; returns whether it was awaited. After a crash the sensors are no members
        (their tokens may take a moment to go); a crash heal awaits the restarted sensors' return."""
        crashed = {("agent", i) for i in agents} if kind == "crash" else set()
        if phase == "start":
            self.members -= crashed
        if self.acks.pop((fault_id, phase), None) is None:
            return False
        if phase == "heal":
            self.returning |= crashed - self.members
        return True

    def member(self, m: Member, alive: bool) -> bool:
        """A liveliness change. Returns True when it shows that an awaited router outage has begun — every
        member we had before it is gone, the launcher included (a closing router drops its links one by
        one: the launcher's going alone does not prove the others are cut off yet). The held tick is then
        published, and lost in the outage; the next one waits for everyone's return."""
        (self.members.add if alive else self.members.discard)(m)
        if alive:
            self.returning.discard(m)
            return False
        if self.outage is not None:
            if LAUNCHER in self.members or self.outage & self.members:
                return False
            self.returning |= self.outage      # the router is down (its ack may have gone with it)
            self.outage = None
            self.acks = {a: kind for a, kind in self.acks.items() if kind != "router_restart"}
            return True
        if m == LAUNCHER:                      # the launcher itself is gone: nobody will answer
            self.acks.clear()
            self.returning.clear()
        return False

    @property
    def blocked(self) -> bool:
        return bool(self.acks or self.outage is not None or self.returning)

    def check_timeout(self, now: float, held: bool) -> bool:
        """Called with the wall clock while a tick may be held; True when the wait has lasted longer
        than ``timeout_s`` (then everything awaited is given up)."""
        if not held:
            self.since = None
            return False
        if self.since is None:
            self.since = now
            return False
        if now - self.since <= self.timeout_s:
            return False
        self.timeouts += 1
        self.acks.clear()
        self.returning.clear()
        self.outage = None
        self.since = None
        return True
