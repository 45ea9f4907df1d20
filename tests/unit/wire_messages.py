"""Real wire messages for the unit tests, and a listener that keeps what a role publishes on a LocalBus."""

from __future__ import annotations

import numpy as np

from agent.bus import LocalBus
from agent.wire import Estimate, Message, Tick


def tick(k: int, links: list[list[int]], *, alive: list[bool] | None = None, t: float | None = None,
         dims: int = 2) -> Tick:
    """The world's tick k over ``len(links)`` sensors (unit weights, every sensor sees the target)."""
    n = len(links)
    return Tick(k=k, t=0.1 * k if t is None else t, n=n, links=links, weights=[[1.0] * len(li) for li in links],
                b=[1.0] * n, delta_max=max((len(li) for li in links), default=0),
                alive=[True] * n if alive is None else alive, positions=np.zeros((n, dims)))


def estimate(src: int, k: int, x, P=None) -> Estimate:
    """Sensor ``src``'s estimate of tick k (x̂ₖ = x̂ₖ₊₁ = ``x``)."""
    x = np.asarray(x, float)
    return Estimate(src=src, k=k, x=x, x_next=x, P=None if P is None else np.asarray(P, float), name="kf")


def send(bus: LocalBus, key: str, msg: Message) -> None:
    """Publish ``msg`` on ``key`` and deliver everything that follows from it."""
    bus.publish(key, msg)
    bus.drain()


class Heard:
    """Every message published on ``patterns`` of ``bus`` once it is drained, decoded as a subscriber gets it."""

    def __init__(self, bus: LocalBus, *patterns: str):
        self.got: list[tuple[str, Message]] = []
        for p in patterns:
            bus.subscribe(p, lambda key, msg: self.got.append((key, msg)))

    def on(self, key: str) -> list[Message]:
        """The messages heard on ``key``, in order."""
        return [m for k, m in self.got if k == key]
