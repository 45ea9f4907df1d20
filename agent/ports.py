"""What a node writes and reads: the key expressions of a role, declared next to its code.

Every role class carries a ``PORTS`` (``SensorRole.PORTS``, ``WorldRole.PORTS``, the recorder's, the
dashboard's, the launcher's). Keys are relative to ``ft/<run>/`` and may hold ``{i}``, the node's id (and
``{host}``, its host's name)::

    class SensorRole(Role):
        PORTS = Ports(writes=("agent/{i}/state", ...), reads=("world/tick", "agent/*/to/{i}/xchg", ...))

The run plan (``flocktrack.plan``) collects them into one description of the run; from it the launcher,
the compose file, the router's access-control list and the recorder take what they need. A node's bus
counts (and logs, once per key) every publication outside its declared writes
(:meth:`agent.bus.ZenohBus.restrict_writes`); in secure mode the router denies it.
"""

from __future__ import annotations

from dataclasses import dataclass


def slug(name: str) -> str:
    """A node's name where a slash is not allowed — a file, a compose service, a certificate's common name:
    ``agent/3`` → ``agent-3``."""
    return name.replace("/", "-")


def _fill(keys: tuple[str, ...], i: int) -> tuple[str, ...]:
    return tuple(k.replace("{i}", str(int(i))) for k in keys)


@dataclass(frozen=True)
class Ports:
    """The keys a role writes (puts) and reads (subscribes to), relative to ``ft/<run>/``."""

    writes: tuple[str, ...] = ()
    reads: tuple[str, ...] = ()

    def of(self, i: int) -> Ports:
        """The ports of node ``i`` of this role (``{i}`` filled in)."""
        return Ports(_fill(self.writes, i), _fill(self.reads, i))

    def on_host(self, host: str) -> Ports:
        """These ports on ``host`` (``{host}`` filled in: what a sensor of a placed run reads of its host's)."""
        return Ports(tuple(k.replace("{host}", host) for k in self.writes),
                     tuple(k.replace("{host}", host) for k in self.reads))

    def __add__(self, other: Ports) -> Ports:
        """Both roles' keys, each once, in order (a role that extends another)."""
        return Ports(tuple(dict.fromkeys(self.writes + other.writes)), tuple(dict.fromkeys(self.reads + other.reads)))
