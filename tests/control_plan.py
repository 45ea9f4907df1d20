"""A test's hand on a live run's control plane: ``run_zenoh_to_dir(..., on_poll=ControlPlan(plan))`` sends
``control/<verb>`` with its arguments once the world has announced tick k, for every ``k: (verb, args)`` of
the plan (the way a user's ``flocktrack fault`` would, through its own Zenoh session)."""

from __future__ import annotations

import time

from agent.bus import ZenohBus
from agent.wire import Control


class ControlPlan:
    """The launcher's ``on_poll`` hook. ``sent``: the ticks whose controls went out; ``k``: the newest tick
    heard; ``sent_at[verb]``: when (time.monotonic()) a verb went out. :meth:`close` after the run."""

    def __init__(self, plan: dict[int, tuple[str, dict]]):
        self.plan, self.bus, self.k = dict(plan), None, -1
        self.sent: set[int] = set()
        self.sent_at: dict[str, float] = {}

    def __call__(self, launcher) -> None:
        if self.bus is None:
            self.bus = ZenohBus(launcher.run, connect=launcher.endpoint)
            self.bus.subscribe("world/tick", lambda key, m: setattr(self, "k", max(self.k, m.k)))
        self.bus.poll(0)
        for k, (verb, args) in self.plan.items():
            if self.k >= k and k not in self.sent:
                self.send(verb, args)
                self.sent.add(k)

    def send(self, verb: str, args: dict | None = None) -> None:
        self.bus.publish(f"control/{verb}", Control(verb=verb, args=args or {}))
        self.sent_at[verb] = time.monotonic()

    def close(self) -> None:
        if self.bus is not None:
            self.bus.close()
