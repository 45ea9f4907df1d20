"""Where a sensor's exchange payloads go each tick: range-based link dropping at the transport, and, in a
run placed on several hosts, one copy per host.

Sensor i's payload of a round goes to every sensor j that hears it by the tick's link table
(``tick.links[j]`` holds i) on j's own key ``agent/i/to/j/xchg``. The observers (recorder, dashboard) get the
tick's payloads once, every round in one :class:`~agent.wire.Rounds` on ``agent/i/xchg``, when the tick ends
(:meth:`ExchangeRoutes.send_observed`) — a sensor that hears nobody this tick sends them that only.

On one host that is all. With a placement (``--hosts``: every sensor's host), Zenoh routes a put once to
each router with a matching subscription, so three hearers on another host would cost three copies across
the host link. There, the hearers on i's own host keep their addressed keys, and each other host with
hearers gets one :class:`~agent.wire.ViaXchg` on ``agent/i/via/<host>/xchg`` naming them (``to``), which that
host's router hands to its sensors; the sensors not named drop it unread (counted as
``other_hearers_payloads``). A payload crosses each host link at most once per round.
"""

from __future__ import annotations

import re

from ..wire import HOST_NAME, Rounds, Xchg, ViaXchg, host_inbox, inbox, via_key, xchg_key

_SPAN = re.compile(rf"({HOST_NAME.pattern}):(\d+)(?:-(\d+))?")


class ExchangeRoutes:
    """Sensor ``i``'s keys for its exchange payloads; ``hosts``: the host of every sensor (None: one host)."""

    def __init__(self, i: int, hosts: list[str] | None = None):
        self.i = int(i)
        self.hosts = hosts
        self._observers = f"agent/{self.i}/xchg"             # the observers' copy, every tick
        self.direct: list[str] = []                          # this tick's addressed keys
        self.via: list[str] = []                             # this tick's per-host keys
        self.remote: list[int] = []                          # the hearers on other hosts (ViaXchg.to)
        self.sent: list[dict] = []                           # this tick's payloads so far, by round

    @property
    def host(self) -> str | None:
        return None if self.hosts is None else self.hosts[self.i]

    def inboxes(self) -> list[str]:
        """What this sensor subscribes to for its neighbours' payloads: its own inbox, and its host's."""
        return [inbox(self.i)] + ([host_inbox(self.host)] if self.hosts is not None else [])

    def route(self, links: list[list[int]]) -> None:
        """This tick's keys, from its link table (``links[j]``: the sensors j hears)."""
        hearers = [j for j, heard in enumerate(links) if j != self.i and self.i in heard]
        mine = self.host
        if self.hosts is None or len(self.hosts) != len(links):
            near, far = hearers, []
        else:
            near = [j for j in hearers if self.hosts[j] == mine]
            far = [j for j in hearers if self.hosts[j] != mine]
        self.direct = [xchg_key(self.i, j) for j in near]
        self.remote = far
        self.sent = []
        self.via = [via_key(self.i, h) for h in dict.fromkeys(self.hosts[j] for j in far)] if far else []

    def send(self, role, msg: Xchg) -> None:
        """Publish ``msg`` on this tick's keys (``role.publish_to``: encoded once per kind of copy), and keep
        its payload for the observers."""
        if self.direct:
            role.publish_to(self.direct, msg)
        if self.via:
            role.publish_to(self.via, ViaXchg(src=msg.src, k=msg.k, r=msg.r, payload=msg.payload, to=self.remote))
        self.sent.append(msg.payload)

    def send_observed(self, role, k: int) -> None:
        """The observers' copy of tick ``k``'s payloads, every round sent, in one message."""
        role.publish(self._observers, Rounds(src=self.i, k=k, payloads=self.sent))
        self.sent = []

    def for_me(self, msg: Xchg) -> bool:
        """Is a payload from this host's inbox addressed to this sensor? (A plain one from its own inbox is.)"""
        return not isinstance(msg, ViaXchg) or self.i in msg.to


def format_hosts(hosts: list[str]) -> str:
    """Every sensor's host as runs: ``["a", "a", "b"]`` → ``"a:0-1,b:2"`` (the ``--hosts`` argument)."""
    out: list[str] = []
    start = 0
    for j in range(1, len(hosts) + 1):
        if j == len(hosts) or hosts[j] != hosts[start]:
            out.append(f"{hosts[start]}:{start}" + (f"-{j - 1}" if j - 1 > start else ""))
            start = j
    return ",".join(out)


def parse_hosts(text: str, n: int) -> list[str]:
    """The inverse of :func:`format_hosts` for ``n`` sensors; ValueError naming what is wrong."""
    hosts: list[str | None] = [None] * n
    for part in text.split(","):
        m = _SPAN.fullmatch(part.strip())
        if m is None:
            raise ValueError(f"{part!r} is not HOST:FIRST[-LAST] (e.g. a:0-3)")
        lo = int(m[2])
        hi = int(m[3]) if m[3] is not None else lo
        if not lo <= hi < n:
            raise ValueError(f"{part!r}: sensors are 0..{n - 1}")
        for j in range(lo, hi + 1):
            if hosts[j] is not None:
                raise ValueError(f"{part!r}: agent/{j} is placed twice")
            hosts[j] = m[1]
    missing = [j for j, h in enumerate(hosts) if h is None]
    if missing:
        raise ValueError(f"agent/{missing[0]} has no host")
    return [str(h) for h in hosts]
