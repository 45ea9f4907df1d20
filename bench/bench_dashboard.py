"""Benchmark: can the live dashboard keep up with 100 sensors at 10 Hz?

Two measurements, with synthetic messages of a 100-sensor flock (range links, 3 exchange rounds per
tick: per tick 1 tick + 1 truth + 100 × (1 meas + 3 xchg + 1 estimate + 1 state) + 1 target state =
603 messages, i.e. ≈ 6 000 messages/s at 10 Hz):

1. **pipeline** (in-process, no network): the cost per tick of decoding + ingesting a tick's messages
   (the same ``agent.bus.deliver`` path as over Zenoh; exchange payloads and measurements only counted),
   of one scene update (snapshot → batched arrays → Viser) and of one plot update (series → uPlot), with
   a real Viser server — and a headless Chromium attached to it when available, so updates go out on a
   websocket to a real page.
2. **paced** (the real thing): an embedded Zenoh router, a publisher *process* sending the messages at
   10 Hz, and the dashboard's own live loop (``dashboards.live.LiveDashboard`` + ``DashboardUI``) in this
   process; sampled every 0.5 s: how many ticks the dashboard's scored tick lags behind the publisher's,
   and the dashboard's CPU use.

    python bench/bench_dashboard.py [--n 100] [--hz 10] [--seconds 30] [--no-browser]
        → bench/results/dashboard.json

3. **viewers** (``--viewers``): the README's main job (``flocktrack run scenarios/demo.toml --dashboard``,
   realtime at speed 1.0, 1000 ticks) with 0, 1 and 5 connected tabs that read every frame but do not
   render, and with 5 tabs that also send (each, per second, 10 valid updates of its own widgets and 10
   invalid ones: out of range, wrong type, 10 kB strings, other tabs' and unknown widget ids, and a camera
   report): the flock's missed round deadlines (run.json) and the dashboard's CPU (its stats file) for each.
   The tabs run in a process of their own at nice 19 — they stand for browsers, usually on other machines;
   what they cost the flock here is the machine's, not the dashboard's.

    python bench/bench_dashboard.py --viewers [--ticks 1000] → bench/results/dashboard_viewers.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import resource
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as python -m dashboards does

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent import wire
from agent.bus import BusStats, deliver
from dashboards import plots
from dashboards.live import LiveDashboard, decoded_key
from dashboards.state import DashboardState, RunInfo, synthetic_tick
from dashboards.ui import DashboardUI

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def tick_bytes(n: int, k: int, rounds: int, T: float) -> list[tuple[str, bytes]]:
    """One tick of the synthetic flock as wire bytes (exchange payloads sized like the minimax filter's)."""
    out = []
    rng = np.random.default_rng(k)
    for key, m in synthetic_tick(n, k, T=T):
        if m is None:
            parts = key.split("/")
            if key == "target/state":
                m = wire.State(k=k, pos=rng.normal(size=2), vel=rng.normal(size=2))
            elif parts[2] == "meas":
                m = wire.Meas(src=int(parts[1]), k=k, t=k * T, y=rng.normal(size=2), b=1.0, pos=rng.normal(size=2))
            else:     # the observers' copy of the tick's exchange rounds
                m = wire.Rounds(src=int(parts[1]), k=k, payloads=[
                    {"x": rng.normal(size=4), "P": np.eye(4) * rng.uniform(1, 2)} for _ in range(rounds)])
        out.append((key, wire.encode(m)))
    return out


_COUNTED: dict[str, bool] = {}


def _counted(key: str) -> bool:
    """Would the dashboard only count this key (as its live loop decides, cached per key)?"""
    v = _COUNTED.get(key)
    if v is None:
        v = _COUNTED[key] = not decoded_key(key)
    return v


def attach_browser(port: int):
    """A headless Chromium on the dashboard page (None when not installed)."""
    if not os.path.exists(CHROMIUM):
        return None
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    pw = sync_playwright().start()
    browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(f"http://127.0.0.1:{port}/")
    page.wait_for_timeout(3000)
    return pw, browser, page


def detach_browser(b) -> None:
    if b:
        pw, browser, _ = b
        browser.close()
        pw.stop()


def stats(a) -> dict:
    a = np.asarray(a, float) * 1e3
    return {"mean_ms": float(a.mean()), "p50_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()), "samples": int(a.size)}


# ============================================================================ 1. pipeline

def bench_pipeline(n: int, ticks: int, rounds: int, use_browser: bool) -> dict:
    from flocktrack.launch.launcher import free_port

    info = RunInfo(n=n, link_range=12.0, name=f"bench-{n}", T=0.1)
    ticks_b = [tick_bytes(n, k, rounds, 0.1) for k in range(ticks)]
    per_tick = len(ticks_b[0])
    st = DashboardState(info)
    bs = BusStats()
    handler = [lambda key, m: st.ingest(key, m, now)]
    ui = DashboardUI(info, port=free_port(), live=True, send_control=lambda v, a: None)
    br = attach_browser(ui.port) if use_browser else None
    ingest_t, scene_t, arrays_t, plot_t = [], [], [], []
    try:
        for k, tb in enumerate(ticks_b):
            now = k * 0.1
            t0 = time.perf_counter()
            for key, data in tb:
                if _counted(key):
                    st.count(now)
                else:
                    deliver(bs, handler, key, data)
            ingest_t.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            snap = st.snapshot()
            err = st.series(last=200)["err"]
            plots.scene_arrays(snap, selected=3, error_scale=plots.auto_error_scale(err), link_range=12.0)
            arrays_t.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            ui.dirty = True
            ui.render_scene(snap, err)
            scene_t.append(time.perf_counter() - t0)
            if k % 5 == 4:  # plots every 0.5 s of a 10 Hz stream
                t0 = time.perf_counter()
                ui.render_plots(st.series(last=ui.plot_panel.max_points * 4))
                plot_t.append(time.perf_counter() - t0)
        assert st.finalized_k == ticks - 1 and bs.dropped == {}
        if br:
            br[2].wait_for_timeout(1000)
            n_uplot = br[2].locator(".uplot").count()
        else:
            n_uplot = None
    finally:
        detach_browser(br)
        ui.stop()
    ing = stats(ingest_t[5:])
    sc = stats(scene_t[5:])
    pl = stats(plot_t[1:])
    # CPU share at 10 Hz: ingest every tick, a scene update per tick (≤ 10/s), plots at 2/s
    share = (10 * ing["mean_ms"] + 10 * sc["mean_ms"] + 2 * pl["mean_ms"]) / 1000.0
    return {"n": n, "rounds": rounds, "messages_per_tick": per_tick, "ticks": ticks,
            "browser_attached": br is not None, "uplot_panels_in_page": n_uplot,
            "ingest_per_tick": ing, "ingest_us_per_message": ing["mean_ms"] * 1e3 / per_tick,
            "scene_arrays_per_update": stats(arrays_t[5:]), "scene_update_incl_viser": sc, "plot_update": pl,
            "cpu_share_at_10hz": share, "max_sustainable_hz_single_core": 10.0 / share if share > 0 else None}


# ============================================================================ 2. paced over Zenoh

def publisher(run: str, port: int, n: int, hz: float, seconds: float, rounds: int) -> int:
    """(child process) the router (as in a real run it lives in the launcher, not in the dashboard) and
    the synthetic flock published at ``hz`` ticks per second once the dashboard's token is up."""
    from agent.bus import ZenohBus
    from flocktrack.launch.launcher import open_router

    router = open_router(port)
    bus = ZenohBus(run, connect=f"tcp/127.0.0.1:{port}")
    members: set[str] = set()
    bus.watch_members(lambda name, alive: (members.add if alive else members.discard)(name))
    print("READY", flush=True)
    end = time.monotonic() + 120
    while "dashboard/0" not in members and time.monotonic() < end:
        bus.poll(0.05)
    ticks = int(seconds * hz)
    nxt = tick_bytes(n, 0, rounds, 1.0 / hz)
    time.sleep(0.5)
    t0 = time.monotonic()
    late = 0
    for k in range(ticks):
        due = t0 + k / hz
        d = due - time.monotonic()
        if d > 0:
            time.sleep(d)
        else:
            late += 1
        for key, data in nxt:
            bus.publish_raw(key, data)
        print(f"TICK {k} {time.time():.3f}", flush=True)
        nxt = tick_bytes(n, k + 1, rounds, 1.0 / hz)   # made while waiting for the next slot
    bus.publish("world/end", wire.End(k=ticks))
    time.sleep(0.5)
    bus.close()
    router.close()
    print(f"DONE late={late}", flush=True)
    return 0


def bench_paced(n: int, hz: float, seconds: float, rounds: int, use_browser: bool) -> dict:
    from agent.bus import ZenohBus
    from flocktrack.launch.launcher import free_port

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    run = f"bench-dash-{os.getpid()}"
    pub = subprocess.Popen([sys.executable, __file__, "--publisher", run, str(port), str(n), str(hz), str(seconds),
                            str(rounds)], stdout=subprocess.PIPE, text=True)
    assert pub.stdout.readline().strip() == "READY"
    info = RunInfo(n=n, link_range=12.0, name=run, T=1.0 / hz)
    sys.setswitchinterval(0.001)  # as dashboards.live.run_live does
    bus = ZenohBus(run, connect=endpoint)
    st = DashboardState(info)
    loop = LiveDashboard(st, None, bus)
    ui = DashboardUI(info, port=free_port(), live=True, send_control=loop.send_control)
    loop.ui = ui
    loop.attach()
    br = attach_browser(ui.port) if use_browser else None
    bus.declare_token("dashboard/0")  # the publisher starts once it sees it
    published = {"k": -1}

    def reader():
        for line in pub.stdout:
            if line.startswith("TICK"):
                published["k"] = int(line.split()[1])
            elif line.startswith("DONE"):
                published["done"] = line.strip()

    threading.Thread(target=reader, daemon=True).start()
    lags, samples = [], []
    cpu0, w0 = time.process_time(), time.monotonic()
    next_sample = w0 + 0.5
    try:
        while not st.ended and time.monotonic() - w0 < seconds + 30:
            loop.step()
            now = time.monotonic()
            if now >= next_sample and published["k"] >= 0:
                next_sample = now + 0.5
                lag = published["k"] - st.finalized_k
                lags.append(lag)
                samples.append({"t": round(now - w0, 2), "published": published["k"], "scored": st.finalized_k,
                                "shown_in_scene": ui.last_scene_k, "lag_ticks": lag})
        wall = time.monotonic() - w0
        cpu = time.process_time() - cpu0
        pub.wait(30)
    finally:
        detach_browser(br)
        bus.close()
        ui.stop()
        if pub.poll() is None:
            pub.kill()
    steady = lags[4:] or lags
    ticks = int(seconds * hz)
    return {"n": n, "hz": hz, "seconds": seconds, "rounds": rounds, "ticks_published": ticks,
            "messages_per_s": ticks * len(tick_bytes(n, 0, rounds, 1.0 / hz)) / seconds,
            "browser_attached": br is not None,
            "ticks_scored": len(st.series_buf),
            "finalized_last": st.finalized_k, "missing_total": st.missing_total, "bus_dropped": st.bus_dropped,
            "lag_ticks_max": int(max(steady)) if steady else None,
            "lag_ticks_mean": float(np.mean(steady)) if steady else None,
            "dashboard_cpu_share": cpu / wall, "scene_updates_per_s": ui.timings.scene_updates / wall,
            "scene_update_mean_ms": 1e3 * ui.timings.scene_s / max(1, ui.timings.scene_updates),
            "plot_updates_per_s": ui.timings.plot_updates / wall,
            "plot_update_mean_ms": 1e3 * ui.timings.plot_s / max(1, ui.timings.plot_updates),
            "publisher": published.get("done"), "samples": samples}


# ============================================================================ 3. viewers of the main job

VIEWER_CASES = (("no tab", 0, False), ("1 reading tab", 1, False), ("5 reading tabs", 5, False),
                ("5 tabs sending valid and invalid updates", 5, True))


def tabs_process(port: int, n: int, send: bool) -> int:
    """(child process, nice 19) ``n`` tabs on the dashboard at ``port`` until it closes; with ``send`` each
    sends 10 valid and 10 invalid updates a second."""
    from dashboards.probe import Tab

    os.nice(19)
    end = time.monotonic() + 120
    while time.monotonic() < end:
        try:
            tabs = [Tab(port) for _ in range(n)]
            break
        except OSError:
            time.sleep(0.2)
    else:
        return 1
    print("CONNECTED", flush=True)
    i = 0
    while not any(t.closed.is_set() for t in tabs):
        time.sleep(0.1)
        if send:
            i += 1
            for t in tabs:
                _send_updates(t, i)
    return 0


def _send_updates(tab, i: int) -> None:
    """One tenth of a second of a sending tab: a valid update of its own n·σ slider, and an invalid one."""
    nsig = tab.find("GuiSliderMessage", label="Ellipse n·σ")
    if nsig is not None:
        tab.press(nsig, float(1 + i % 5))
    bad = [(nsig, 10**18), (nsig, "two"), (nsig, "x" * 10_000), ("no-such-widget", True)]
    if tab.uuids:
        bad.append((tab.uuids[i % len(tab.uuids)], float("nan")))
    uuid, value = bad[i % len(bad)]
    if uuid is not None:
        tab.press(uuid, value)


def bench_viewers(ticks: int, out_root: Path, repeats: int = 3) -> list[dict]:
    """Every case ``repeats`` times, the cases interleaved (A B C D A B C D …) so that a slow spell of the
    machine falls on all of them; beside each run a 1 ms sleeper counts the machine's own stops."""
    rows = []
    for rep in range(repeats):
        for name, n, send in VIEWER_CASES:
            rows.append({"repeat": rep, **_viewer_run(name, n, send, ticks, out_root / f"{rep}_{name.replace(' ', '_')}")})
            print(rows[-1], flush=True)
    return rows


def _viewer_run(name: str, n: int, send: bool, ticks: int, out: Path) -> dict:
    from machine_gaps import GapMonitor

    from flocktrack.launch.launcher import free_port

    port = free_port()
    with GapMonitor() as gaps:
        run = subprocess.Popen([sys.executable, "-m", "flocktrack", "run", "scenarios/demo.toml", "--dashboard",
                                "--dashboard-port", str(port), "--no-linger", "--ticks", str(ticks), "--out",
                                str(out)], cwd=str(ROOT), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        tabs = subprocess.Popen([sys.executable, __file__, "--tabs", str(port), str(n), str(int(send))],
                                stdout=subprocess.PIPE, text=True) if n else None
        rc = run.wait(900)
        connected = False
        if tabs is not None:
            connected = tabs.stdout.readline().strip() == "CONNECTED"
            tabs.wait(30)
    info = json.loads((out / "run.json").read_text())
    dash = json.loads((out / "stats" / "dashboard-0.json").read_text()).get("role", {})
    guard = dash.get("guard", {})
    missed_ticks = sorted({int(k) for f in (out / "logs").glob("agent-*.log")
                           for k in re.findall(r"deadline on \((\d+), \d+\)", f.read_text(errors="replace"))})
    g = gaps.result() or {}
    return {"case": name, "tabs": n, "sending": send, "exit_code": rc, "tabs_connected": connected,
            "missed_deadlines": info.get("missed_deadlines"), "ticks_with_misses": missed_ticks[:100],
            "dashboard_exits": info.get("exits", {}).get("dashboard/0"),
            "dashboard_restarts": info.get("restarts", {}).get("dashboard/0", 0),
            "machine_stops_over_20ms": g.get("count"), "machine_stop_max_ms": g.get("max_ms"),
            "ticks_per_s": info.get("ticks_per_s"), "dashboard_cpu_s": dash.get("cpu_s"),
            "dashboard_wall_s": dash.get("wall_s"),
            "dashboard_cpu_share": (dash["cpu_s"] / dash["wall_s"]) if dash.get("wall_s") else None,
            "tabs_seen": guard.get("tabs_seen"), "updates_refused": guard.get("total_invalid_updates", 0),
            "throttled": guard.get("total_throttled", 0), "closed_for_rate": guard.get("closed_for_rate", 0),
            "dashboard_log_bytes": (out / "logs" / "dashboard-0.log").stat().st_size,
            # a dashboard that exited on its own: what it said last (the run's directory is temporary)
            "dashboard_log_tail": _tail(out / "logs" / "dashboard-0.log", 40)
            if any(info.get("exits", {}).get("dashboard/0") or []) else None}


def _tail(path: Path, n: int) -> list[str]:
    return path.read_text(errors="replace").splitlines()[-n:]


def viewer_summary(rows: list[dict]) -> dict:
    """Per case over the repeats: missed deadlines (each run, median, total), runs with none, the
    dashboard's CPU share (median)."""
    out = {}
    for name, _n, _send in VIEWER_CASES:
        rs = [r for r in rows if r["case"] == name]
        missed = [int(r["missed_deadlines"] or 0) for r in rs]
        out[name] = {"missed_each": missed, "missed_median": statistics.median(missed), "missed_total": sum(missed),
                     "runs_with_none": sum(m == 0 for m in missed),
                     "machine_stops_each": [r["machine_stops_over_20ms"] for r in rs],
                     "dashboard_cpu_share_median": round(statistics.median(r["dashboard_cpu_share"] or 0 for r in rs), 4)}
    return out


def machine_note() -> dict:
    """The machine and what else ran on it (the busiest processes at the start)."""
    top = subprocess.run(["ps", "-eo", "pcpu,comm", "--sort=-pcpu"], capture_output=True, text=True).stdout
    return {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
            "loadavg_at_start": os.getloadavg(), "busiest_processes_at_start": top.splitlines()[1:8]}


def main_viewers(ticks: int, out: Path, repeats: int = 3) -> int:
    import tempfile

    res = {"machine": machine_note(), "scenario": "scenarios/demo.toml (12 sensors, T = 0.04 s, realtime, speed 1.0)",
           "ticks": ticks}
    with tempfile.TemporaryDirectory() as d:
        res["cases"] = bench_viewers(ticks, Path(d), repeats)
    res["summary"] = viewer_summary(res["cases"])
    res["machine"]["loadavg_at_end"] = os.getloadavg()
    print(json.dumps(res["summary"], indent=1))
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")
    return 0


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--publisher":
        run, port, n, hz, seconds, rounds = sys.argv[2:8]
        return publisher(run, int(port), int(n), float(hz), float(seconds), int(rounds))
    if len(sys.argv) > 1 and sys.argv[1] == "--tabs":
        return tabs_process(int(sys.argv[2]), int(sys.argv[3]), bool(int(sys.argv[4])))
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=100)
    ap.add_argument("--hz", type=float, default=10.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--ticks", type=int, default=200, help="pipeline benchmark ticks")
    ap.add_argument("--no-browser", action="store_true")
    ap.add_argument("--out", default=None, help="default: bench/results/dashboard.json "
                                                "(--viewers: dashboard_viewers.json)")
    ap.add_argument("--viewers", action="store_true", help="the main job with 0, 1 and 5 tabs (see above)")
    ap.add_argument("--demo-ticks", type=int, default=1000, help="--viewers: ticks of each run")
    ap.add_argument("--repeats", type=int, default=3, help="--viewers: runs of each case (interleaved)")
    args = ap.parse_args()
    if args.viewers:
        return main_viewers(args.demo_ticks, Path(args.out or ROOT / "bench" / "results" / "dashboard_viewers.json"),
                            args.repeats)
    args.out = args.out or str(ROOT / "bench" / "results" / "dashboard.json")
    load0 = os.getloadavg()
    res = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
                       "loadavg_at_start": load0},
           "pipeline": bench_pipeline(args.n, args.ticks, args.rounds, not args.no_browser),
           "paced": bench_paced(args.n, args.hz, args.seconds, args.rounds, not args.no_browser),
           "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    res["machine"]["loadavg_at_end"] = os.getloadavg()
    p = res["pipeline"]
    z = res["paced"]
    print(f"pipeline N={p['n']}: ingest {p['ingest_per_tick']['mean_ms']:.2f} ms/tick "
          f"({p['ingest_us_per_message']:.1f} µs/msg), scene {p['scene_update_incl_viser']['mean_ms']:.2f} ms, "
          f"plots {p['plot_update']['mean_ms']:.2f} ms → {100 * p['cpu_share_at_10hz']:.0f}% of a core at 10 Hz")
    print(f"paced over Zenoh N={z['n']} at {z['hz']} Hz ({z['messages_per_s']:.0f} msg/s): lag max "
          f"{z['lag_ticks_max']} ticks, mean {z['lag_ticks_mean']:.2f}; dashboard CPU {100 * z['dashboard_cpu_share']:.0f}%; "
          f"{z['scene_updates_per_s']:.1f} scene updates/s, missing {z['missing_total']}, bus drops {z['bus_dropped']}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
