"""Feeding a dashboard's state the way its subscriber would: per-tick lists of (key, message) — a None message
counts as a message received that carries nothing to draw — tick j ingested at time t0 + (k0 + j)·dt."""

from __future__ import annotations

from dashboards.state import DashboardState


def feed(st: DashboardState, msgs, t0: float = 0.0, dt: float = 0.1, k0: int = 0) -> None:
    """Ingest each tick's messages into ``st``, tick j at time t0 + (k0 + j)·dt."""
    for j, tick in enumerate(msgs):
        now = t0 + (k0 + j) * dt
        for key, m in tick:
            if m is None:
                st.count(now)
            else:
                st.ingest(key, m, now)
