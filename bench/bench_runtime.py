"""Benchmark: lockstep ticks/s and per-process memory over Zenoh for N = 10, 30, 60, 100 sensors, beside
the same scenario on LocalBus and beside a bare Zenoh barrier (bench/zenoh_barrier.py) with the same
message sizes, neighbour counts and addressing; a round's wall time (median, p99) from the sensors' tick rows.

What explains the cost, per sensor per tick: CPU ms, voluntary context switches (≈ wake-ups of its
threads, summed over /proc/<pid>/task/*), and the messages its bus received — exchange payloads
(received + skipped by the pre-decode filter, minus the tick and truth) against the bound
rounds × (degree + 1) that delivery proportional to degree must meet.

    python bench/bench_runtime.py [--sizes 10 30 60 100] [--ticks 100]   → bench/results/runtime.json,
                                                                         bench/results/runtime.png
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent import wire
from agent.scenario import parse_scenario
from agent.scenario import scenario_data
from flocktrack.launch.launcher import free_port, open_router
from flocktrack.record.reader import read_recording
from flocktrack.engine.run import run_inproc_to_dir, run_zenoh_to_dir
from topology.graph import neighbour_lists, range_adjacency


def scenario(n: int, ticks: int, rounds: int):
    """gu_hu_normal with N static sensors in a 2-row strip (spacing 8, range 12): every N has the same
    degree (≈ 4), so what grows with N is the runtime's overhead, not the estimator's work. (Flocking
    sensors pack around the target, and the degree then grows with N: 5 → 19 from N = 10 to 100.)"""
    data = scenario_data(str(ROOT / "scenarios" / "gu_hu_normal.toml"), [], **{
        "run.ticks": ticks, "run.mode": "lockstep", "sensors.n": n, "sensors.grid_rows": 2,
        "sensors.motion": "static", "sensors.origin": [-4.0 * (n // 2), -8.0], "estimator.rounds": rounds})
    return data, parse_scenario(data, f"bench-N{n}")


def rss_mb(pid: int) -> float | None:
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def voluntary_switches(pid: int) -> int | None:
    """Voluntary context switches of all threads of a process so far (each is a wait that ended: a
    wake-up)."""
    total = 0
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            try:
                for line in open(f"/proc/{pid}/task/{task}/status"):
                    if line.startswith("voluntary_ctxt_switches:"):
                        total += int(line.split()[1])
            except OSError:
                continue
    except OSError:
        return None
    return total


def cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a process (all its threads) so far."""
    try:
        f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


class CpuTrace:
    """Samples of (wall time, CPU seconds) per process, to read the CPU spent between two instants
    (the first and last tick: steady state, without interpreter start-up and imports)."""

    def __init__(self, switches: bool = False) -> None:
        self.samples: dict[str, list[tuple[float, float]]] = {}
        self.switches: dict[str, list[tuple[float, float]]] = {}
        self.count_switches = switches

    def sample(self, name: str, pid: int) -> None:
        c = cpu_s(pid)
        if c is not None:
            self.samples.setdefault(name, []).append((time.time(), c))
        last = self.switches.get(name)
        # (the /proc/<pid>/task/* walk is slow with 100 processes: once a second is enough)
        if self.count_switches and (not last or time.time() - last[-1][0] > 1.0) \
                and (v := voluntary_switches(pid)) is not None:
            self.switches.setdefault(name, []).append((time.time(), float(v)))

    def between(self, t0: float, t1: float, what: str = "cpu") -> dict[str, float]:
        out = {}
        for name, s in (self.samples if what == "cpu" else self.switches).items():
            ts, cs = np.array([x[0] for x in s]), np.array([x[1] for x in s])
            # the last sample may precede t1 by a sampling period (a process exits right after the run)
            if len(ts) > 1 and ts[0] <= t0 and ts[-1] >= t1 - 1.5:
                out[name] = float(np.interp(t1, ts, cs) - np.interp(t0, ts, cs))
        return out


def per_tick_ms(cpu: dict[str, float], ticks: int) -> dict:
    """CPU milliseconds per tick, by role (agent/3 → agent) and in total."""
    by: dict[str, float] = {}
    for name, c in cpu.items():
        role = name.split("/")[0]
        by[role] = by.get(role, 0.0) + c
    return {"total": 1e3 * sum(by.values()) / ticks, **{r: 1e3 * c / ticks for r, c in sorted(by.items())}}


def zenoh_run(n: int, ticks: int, rounds: int) -> dict:
    data, sc = scenario(n, ticks, rounds)
    peak: dict[int, float] = {}
    trace = CpuTrace(switches=True)
    me = os.getpid()

    def hook(launcher):
        trace.sample("router/0", me)  # the embedded router lives in this (the launcher's) process
        for c in launcher.children.values():
            if c.proc and c.proc.poll() is None:
                m = rss_mb(c.proc.pid)
                if m:
                    peak[c.proc.pid] = max(peak.get(c.proc.pid, 0.0), m)
                trace.sample(c.name, c.proc.pid)

    t_start = time.time_ns()
    with tempfile.TemporaryDirectory() as d:
        _summary, info = run_zenoh_to_dir(sc, data, Path(d), quiet=True, on_poll=hook, timeout_s=1800)
        rec = read_recording(Path(d) / "recording.mcap")
        bus = [json.loads((Path(d) / "stats" / f"agent-{i}.json").read_text()) for i in range(n)]
        # a round's wall time, per sensor tick: from its beginning to its state sent, over its rounds
        lat = []
        for i in range(n):
            with (Path(d) / "stats" / f"agent-{i}-ticks.csv").open() as f:
                lat += [(float(r["total_ms"]) - float(r["start_ms"])) / int(r["rounds"])
                        for r in csv.DictReader(f) if int(r["rounds"]) > 0]
    # when each message was recorded (the wall clock, ns; the log time is the simulated k·T)
    timed = [(key, m, t) for (key, m, _), t in zip(rec.messages, rec.wall)]
    t_tick = {m.k: t for key, m, t in timed if key == "world/tick"}
    ks = sorted(t_tick)
    steady = (t_tick[ks[-1]] - t_tick[ks[0]]) / 1e9
    cpu = trace.between(t_tick[ks[0]] / 1e9, t_tick[ks[-1]] / 1e9)
    sw = trace.between(t_tick[ks[0]] / 1e9, t_tick[ks[-1]] / 1e9, "switches")
    sensors = [c for name, c in cpu.items() if name.startswith("agent/")]
    degrees = [len(x) for x in tick_links(rec)]
    # exchange payloads a sensor's bus took in per tick (all it received but the tick and the truth)
    xchg_in = [b["received"] / ticks - 2 for b in bus]
    return {"ticks_per_s": (len(ks) - 1) / steady, "wall_s_including_startup": info["wall_s"],
            "startup_s": (t_tick[ks[0]] - t_start) / 1e9,   # launch → tick 0 (every process up)
            "cpu_ms_per_tick": per_tick_ms(cpu, len(ks) - 1),
            # processes whose CPU was sampled over the whole run (the total is partial when < n + 4)
            "cpu_processes_sampled": len(cpu), "cpu_total_incomplete": len(cpu) < n + 4,
            "per_sensor_per_tick": {
                "cpu_ms": 1e3 * float(np.mean(sensors)) / (len(ks) - 1),
                "voluntary_switches": float(np.mean([c for nm, c in sw.items() if nm.startswith("agent/")]))
                / (len(ks) - 1),
                "xchg_received": float(np.mean(xchg_in)), "xchg_received_max": float(np.max(xchg_in)),
                "bound_rounds_x_degree_plus_1": rounds * (float(np.mean(degrees)) + 1),
                "mean_degree": float(np.mean(degrees))},
            "round_ms": {"median": float(np.median(lat)), "p99": float(np.percentile(lat, 99))},
            "rss_mb": {"median": float(np.median(list(peak.values()))), "max": float(max(peak.values())),
                       "processes": len(peak)}}


def tick_links(rec) -> list[list[int]]:
    """Every sensor's neighbour list in every recorded tick (flattened)."""
    return [nb for key, m, _ in rec.messages if key == "world/tick" for nb in m.links]


def inproc_run(n: int, ticks: int, rounds: int) -> dict:
    data, sc = scenario(n, ticks, rounds)
    with tempfile.TemporaryDirectory() as d:
        _s, info = run_inproc_to_dir(sc, data, Path(d))
    return {"ticks_per_s": info["ticks_per_s"]}


def barrier_run(n: int, ticks: int, rounds: int) -> dict:
    data, sc = scenario(n, ticks, rounds)
    adj = range_adjacency(sc.initial_positions(), sc.topology.range)
    nb = neighbour_lists(adj)
    m = sc.m
    xbytes = len(wire.encode(wire.Xchg(src=0, k=1, r=0, payload={"chi1": np.eye(m), "chi2": np.ones(m),
                                                                  "chi3": np.eye(m)})))
    sbytes = len(wire.encode(wire.State(src=0, k=1, pos=np.ones(2), vel=np.ones(2))))
    tbytes = len(wire.encode(wire.Tick(k=1, t=0.1, n=n, links=nb, weights=[[1.0] * len(x) for x in nb], b=[1.0] * n,
                                       delta_max=int(max(map(len, nb))), alive=[True] * n,
                                       positions=sc.initial_positions())))
    port = free_port()
    router = open_router(port)
    ep = f"tcp/127.0.0.1:{port}"
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as f:
        json.dump(nb, f)
    common = ["--n", str(n), "--rounds", str(rounds), "--ticks", str(ticks), "--connect", ep, "--nbrs", f.name,
              "--xbytes", str(xbytes), "--sbytes", str(sbytes), "--tbytes", str(tbytes)]
    script = str(ROOT / "bench" / "zenoh_barrier.py")
    workers = [subprocess.Popen([sys.executable, script, "worker", "--id", str(i), *common]) for i in range(n)]
    trace, done = CpuTrace(), threading.Event()

    def sampler() -> None:
        while not done.wait(0.05):
            trace.sample("router/0", os.getpid())
            for i, w in enumerate(workers):
                trace.sample(f"worker/{i}", w.pid)
            if coord:
                trace.sample("coordinator/0", coord[0].pid)

    coord: list[subprocess.Popen] = []
    threading.Thread(target=sampler, daemon=True).start()
    try:
        coord.append(subprocess.Popen([sys.executable, script, "coordinator", *common], stdout=subprocess.PIPE,
                                      text=True))
        stdout, _ = coord[0].communicate(timeout=1800)
        res = json.loads(stdout.strip().splitlines()[-1])
    finally:
        done.set()
        for w in workers:
            try:
                w.wait(30)
            except subprocess.TimeoutExpired:
                w.kill()
        router.close()
    cpu = trace.between(res["t0_wall"], res["t1_wall"])
    return {"ticks_per_s": res["ticks_per_s"], "cpu_ms_per_tick": per_tick_ms(cpu, res["ticks"]),
            "message_bytes": {"xchg": xbytes, "state": sbytes, "tick": tbytes},
            "mean_degree": float(np.mean([len(x) for x in nb]))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 30, 60, 100])
    ap.add_argument("--ticks", type=int, default=100)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "runtime.json"))
    a = ap.parse_args()
    results = {"ticks": a.ticks, "rounds": a.rounds, "machine": {"cpus": os.cpu_count(),
                                                                  "loadavg_at_start": list(os.getloadavg())},
               "date": time.strftime("%Y-%m-%d"), "sizes": {}}
    for n in a.sizes:
        r = {"barrier": barrier_run(n, a.ticks, a.rounds), "zenoh": zenoh_run(n, a.ticks, a.rounds),
             "localbus": inproc_run(n, a.ticks, a.rounds)}
        r["zenoh_vs_barrier"] = r["zenoh"]["ticks_per_s"] / r["barrier"]["ticks_per_s"]
        # the runtime's CPU per tick against its floors measured in this run: the bare barrier's transport plus
        # LocalBus's whole computation (one process, so its wall time per tick is its CPU)
        floor = r["barrier"]["cpu_ms_per_tick"]["total"] + 1e3 / r["localbus"]["ticks_per_s"]
        r["floor_cpu_ms_per_tick"] = floor
        r["cpu_over_floor"] = r["zenoh"]["cpu_ms_per_tick"]["total"] / floor
        # on a CPU-bound machine ticks/s ∝ 1 / CPU per tick: the ratio the CPU budget alone allows
        r["barrier_cpu_over_zenoh_cpu"] = (r["barrier"]["cpu_ms_per_tick"]["total"]
                                           / max(r["zenoh"]["cpu_ms_per_tick"]["total"], 1e-9))
        results["sizes"][str(n)] = r
        print(f"N={n}: zenoh {r['zenoh']['ticks_per_s']:.2f} ticks/s, barrier {r['barrier']['ticks_per_s']:.2f}, "
              f"ratio {r['zenoh_vs_barrier']:.2f}, LocalBus {r['localbus']['ticks_per_s']:.2f}, "
              f"round median {r['zenoh']['round_ms']['median']:.1f} ms, "
              f"RSS median {r['zenoh']['rss_mb']['median']:.0f} MB; CPU/tick zenoh "
              f"{r['zenoh']['cpu_ms_per_tick']['total']:.1f} ms vs barrier {r['barrier']['cpu_ms_per_tick']['total']:.1f}"
              f" + LocalBus {1e3 / r['localbus']['ticks_per_s']:.1f} = {r['cpu_over_floor']:.2f} × the floor",
              flush=True)
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(results, indent=2))
    figure(results, Path(a.out).with_suffix(".png"))


def figure(results: dict, out: Path) -> None:
    """CPU per tick vs N (runtime, barrier; total and per sensor) and ticks/s vs N (all three)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ns = sorted(int(n) for n in results["sizes"])
    r = [results["sizes"][str(n)] for n in ns]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8))
    full = [(n, x) for n, x in zip(ns, r) if not x["zenoh"].get("cpu_total_incomplete")]
    ax[0].plot([n for n, _ in full], [x["zenoh"]["cpu_ms_per_tick"]["total"] for _, x in full], "o-",
               label="runtime (Zenoh, lockstep)")
    ax[0].plot(ns, [x["barrier"]["cpu_ms_per_tick"]["total"] for x in r], "s--", label="bare Zenoh barrier")
    ax[0].set(xlabel="sensors N", ylabel="CPU ms per tick (all processes)", title="CPU per tick")
    ax[1].plot(ns, [x["zenoh"]["per_sensor_per_tick"]["cpu_ms"] for x in r], "o-",   # (NaN: not sampled)
               label="runtime sensor")
    ax[1].plot(ns, [x["barrier"]["cpu_ms_per_tick"]["worker"] / n for x, n in zip(r, ns)], "s--",
               label="barrier worker")
    ax[1].set(xlabel="sensors N", ylabel="CPU ms per tick per sensor", title="per sensor", ylim=(0, None))
    for key, style, label in (("zenoh", "o-", "runtime (Zenoh)"), ("barrier", "s--", "barrier"),
                              ("localbus", "^:", "LocalBus (1 process)")):
        ax[2].plot(ns, [x[key]["ticks_per_s"] for x in r], style, label=label)
    ax[2].set(xlabel="sensors N", ylabel="lockstep ticks/s", title="throughput", yscale="log")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle(f"flocktrack runtime, {results['rounds']} rounds, {results['ticks']} ticks, "
                 f"{results['machine']['cpus']} cores ({results['date']})", fontsize=10)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


if __name__ == "__main__":
    main()
