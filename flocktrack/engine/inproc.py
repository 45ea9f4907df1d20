"""The in-process engine: every role on one :class:`agent.bus.LocalBus`, lockstep, deterministic.

Delivery is FIFO and synchronous. When the bus goes idle while some role still waits (a message that
will never come), the deadline fires — the in-process equivalent of a lockstep deadline — so the run
always completes. It fires innermost first (:attr:`agent.roles.common.Role.wait_depth`) and earliest first:
for the sensors waiting on the earliest round (``wait_key`` (k, r)), in a fixed order — every neighbour of
theirs has sent that round, so what they lack will never come; a sensor in a later round waits only for
them — then the target's and the world's wait only when nothing inside them still waits. A payload lost on
the way costs the rounds that wanted it and nothing more, and a tick closes on every state its sensors
could still send, never ahead of them.
"""

from __future__ import annotations

from collections.abc import Callable

from agent.bus import LocalBus
from agent.scenario import Scenario

from flocktrack.engine.build import Roles, build_roles
from flocktrack.record.metrics import MetricsCollector


def run_inproc(sc: Scenario, progress: Callable[[int, int], None] | None = None,
               bus: LocalBus | None = None) -> tuple[MetricsCollector, Roles, LocalBus]:
    bus = LocalBus() if bus is None else bus
    roles = build_roles(sc)
    metrics = MetricsCollector.for_scenario(sc, roles.design)
    metrics.subscribe(bus)
    for r in roles.all():
        r.attach(bus)
    roles.world.start()
    last_k = -1
    while not roles.world.finished:
        bus.drain()
        if roles.world.finished:
            break
        if bus.idle:
            if any([r.on_idle() for r in roles.all()]):
                continue
            stuck = [r for r in roles.all() if r.waiting]
            if not stuck:
                raise RuntimeError(f"in-process run stalled at tick {roles.world.k} with no role waiting")
            inner = min(r.wait_depth for r in stuck)
            stuck = [r for r in stuck if r.wait_depth == inner]
            first = min(r.wait_key for r in stuck)
            for r in stuck:
                if r.wait_key == first:
                    r.on_deadline()
        if progress is not None and roles.world.k != last_k:
            last_k = roles.world.k
            progress(last_k, sc.run.ticks)
    bus.drain()
    return metrics, roles, bus
