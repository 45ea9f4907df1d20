"""dashboards/loop_safe.py: an event that other threads may set while its loop waits on it — the flag is
raised at once, the waiters are woken only by their own loop."""

from __future__ import annotations

import asyncio
import sys
import threading

from dashboards.loop_safe import LoopSafeEvent


def _loop_thread():
    loop = asyncio.new_event_loop()
    errors: list = []
    loop.set_exception_handler(lambda _loop, ctx: errors.append(ctx))
    t = threading.Thread(target=loop.run_forever, daemon=True)
    t.start()
    return loop, t, errors


def _stop(loop, t) -> None:
    loop.call_soon_threadsafe(loop.stop)
    t.join(5)
    loop.close()


def test_a_set_from_another_thread_raises_the_flag_and_leaves_the_waking_to_the_loop():
    loop, t, _ = _loop_thread()
    try:
        ev = LoopSafeEvent()
        waiting = asyncio.run_coroutine_threadsafe(ev.wait(), loop)
        for _ in range(100):                    # the waiter is parked on the loop
            if ev._waiters:
                break
            threading.Event().wait(0.01)
        assert ev._waiters
        ev.set()                                # this thread has no loop: the flag only
        assert ev.is_set()
        threading.Event().wait(0.1)
        assert not waiting.done()
        loop.call_soon_threadsafe(ev.set)       # as Viser's push does next: the loop wakes its waiter
        assert waiting.result(5) is True
        ev.clear()
        assert not ev.is_set()
    finally:
        _stop(loop, t)


def test_a_set_event_returns_from_wait_at_once():
    ev = LoopSafeEvent()
    ev.set()
    assert asyncio.run(asyncio.wait_for(ev.wait(), 1)) is True


def test_sets_from_threads_while_tabs_wait_and_clear_never_raise_and_never_lose_the_last_wake():
    loop, t, loop_errors = _loop_thread()
    ev = LoopSafeEvent()
    sent = {"n": 0}
    woke = {"n": 0}
    stop = asyncio.Event()

    async def consumer():
        while True:
            await ev.wait()
            ev.clear()
            woke["n"] += 1
            if stop.is_set():
                return

    errors: list = []

    def producer():
        try:
            for _ in range(5000):
                ev.set()                                    # both sets, as Viser's buffer makes them
                loop.call_soon_threadsafe(ev.set)
                sent["n"] += 1
        except Exception as exc:  # noqa: BLE001 — what the test looks for
            errors.append(exc)

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)        # threads interleave inside set(), where the race is
    try:
        consumers = [asyncio.run_coroutine_threadsafe(consumer(), loop) for _ in range(8)]   # (tabs)
        producers = [threading.Thread(target=producer) for _ in range(3)]
        for p in producers:
            p.start()
        for p in producers:
            p.join(60)
        loop.call_soon_threadsafe(stop.set)
        loop.call_soon_threadsafe(ev.set)                   # the last wake reaches the consumer
        for done in consumers:
            done.result(10)
    finally:
        sys.setswitchinterval(switch)
        _stop(loop, t)
    assert errors == [] and loop_errors == []
    assert sent["n"] == 15000 and 8 <= woke["n"]
    assert not ev._waiters
