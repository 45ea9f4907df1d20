"""Soak: the runtime held for minutes, its processes watched — does anything grow, stall or drift?

    python bench/soak.py [--minutes 10] [--phases demo,faults,flock30] [--out bench/results/soak.json]
                         [--plot docs/soak.png]

Phases (each a realtime run of the launcher with its embedded router, one process per role):

* ``demo``    scenarios/demo.toml as the README runs it (12 sensors, T = 0.04 s at its realtime factor);
* ``faults``  the same with a fault plan that cycles link loss (p = 0.3), a partition into halves, a crash
              of one sensor (restarted at the heal) and a router restart, one every 30 s of wall time,
              each healed 10 s later;
* ``flock30`` the demo's flock with 30 sensors, a tick every ``--flock-period`` s of wall time (the demo's
              T = 0.04 s of model time — the minimax filter is stable only for T ≈ 0.03–0.046 against this
              target — at realtime factor T / period).

Every 5 s the launcher's ``on_poll`` hook samples each child process (and the launcher itself): resident
memory (/proc/PID/statm) and open file descriptors (/proc/PID/fd), and the recording's size. After the run:
missed round deadlines per 1000 ticks (the launcher counts the children's ``deadline on`` lines), late
payloads (sum of the sensors' ``late_payloads``), the estimation error per tenth of the run (the
network RMSE's median and max per window: bounded, not drifting), and per process the RSS growth after
warm-up — the median RSS of the last fifth against that of the second fifth (target ≤ 5 %). A process that
was restarted is judged on its last incarnation. Prints progress; writes the JSON (every sample) and, with
``--plot``, RSS and error over time.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from agent.scenario import parse_scenario, scenario_data  # noqa: E402 - after the sys.path insert above
from flocktrack.engine.run import run_zenoh_to_dir  # noqa: E402 - after the sys.path insert above
from machine_gaps import (  # noqa: E402 - bench/ is this script's directory
    GapMonitor, by_speed, missed_by_tick, speed_summary, tick_walls)

PAGE = os.sysconf("SC_PAGE_SIZE")
SAMPLE_S = 5.0
GROWTH_TARGET = 0.05


def proc_sample(pid: int) -> tuple[int, int] | None:
    """(RSS bytes, open fds) of a live process, None if it is gone."""
    try:
        rss = int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * PAGE
        return rss, len(os.listdir(f"/proc/{pid}/fd"))
    except (OSError, ValueError, IndexError):
        return None


def fault_cycle(ticks: int, tick_wall_s: float, n: int, every_s: float = 30.0, heal_s: float = 10.0) -> list[dict]:
    """Link loss, partition, crash, router restart in turn, one every ``every_s`` of wall time."""
    step, heal = max(1, round(every_s / tick_wall_s)), max(1, round(heal_s / tick_wall_s))
    kinds = [{"kind": "link_loss", "p": 0.3}, {"kind": "partition", "targets": "halves"},
             {"kind": "crash", "targets": None}, {"kind": "router_restart"}]
    out, j = [], 0
    for start in range(step, ticks - heal, step):
        ev = dict(kinds[j % len(kinds)], start=start)
        if ev["kind"] == "crash":
            ev["targets"] = f"agents:{1 + (j // len(kinds)) % (n - 1)}"
        if ev["kind"] != "router_restart":
            ev["heal"] = start + heal
        out.append(ev)
        j += 1
    return out


def phase_data(name: str, minutes: float, flock_period: float) -> tuple[dict, str]:
    sets = {"run.mode": "realtime", **({"sensors.n": 30} if name == "flock30" else {})}
    data = scenario_data(str(ROOT / "scenarios" / "demo.toml"), [], **sets)
    run = data["run"]
    if name == "flock30":
        data.setdefault("sensors", {}).pop("positions", None)     # the demo's 12 fixed starts: let 30 be placed
        run["speed"] = round(float(run["T"]) / flock_period, 6)
    tick_wall = float(run["T"]) / float(run.get("speed", 1.0))
    run["ticks"] = int(minutes * 60.0 / tick_wall)
    if name == "faults":
        data["faults"] = {"events": fault_cycle(run["ticks"], tick_wall, int(data["sensors"]["n"]))}
    return data, f"demo.toml ({name})"


def run_phase(name: str, minutes: float, flock_period: float, work: Path) -> dict:
    data, label = phase_data(name, minutes, flock_period)
    sc = parse_scenario(data, label)
    samples: list[dict] = []
    t0 = time.monotonic()
    last = [-math.inf]

    def on_poll(launcher) -> None:
        now = time.monotonic()
        if now - last[0] < SAMPLE_S:
            return
        last[0] = now
        row: dict = {"t": round(now - t0, 1), "procs": {}}
        for nm, c in list(launcher.children.items()):
            pid = c.pid
            s = proc_sample(pid) if pid else None
            if s is not None:
                row["procs"][nm] = {"pid": pid, "rss": s[0], "fds": s[1]}
        s = proc_sample(os.getpid())
        row["procs"]["launcher"] = {"pid": os.getpid(), "rss": s[0], "fds": s[1]}
        rec = launcher.run_dir / "recording.mcap"
        row["recording_bytes"] = rec.stat().st_size if rec.exists() else 0
        samples.append(row)
        if len(samples) % 12 == 1:
            print(f"[soak {name}] {row['t']:6.0f} s  {len(row['procs'])} processes, "
                  f"recording {row['recording_bytes'] / 1e6:.1f} MB", flush=True)

    print(f"[soak {name}] {sc.sensors.n} sensors, {sc.run.ticks} ticks of T = {sc.run.T} s at speed {sc.run.speed} "
          f"(~{minutes:g} min)", flush=True)
    with GapMonitor() as gaps:      # the machine's stops and speed beside the run (bench/machine_gaps.py)
        summary, info = run_zenoh_to_dir(sc, data, work, quiet=True, on_poll=on_poll,
                                         timeout_s=minutes * 60 * 3 + 300)
    res = analyse(name, sc, summary, info, samples, work)
    g = gaps.result()
    res["machine_speed"] = speed_summary(g)
    res["missed_by_speed"] = by_speed(g, tick_walls(work / "recording.mcap"), missed_by_tick(work / "logs"))
    print(f"[soak {name}] the machine's speed {res['machine_speed']}; ticks and missed deadlines in its slow "
          f"phases and the rest: {res['missed_by_speed']}", flush=True)
    return res


def growth(series: list[tuple[float, int, int]]) -> dict:
    """RSS growth of one process incarnation after warm-up (module doc)."""
    if len(series) < 10:
        return {"samples": len(series)}
    rss = np.array([r for _, r, _ in series], float)
    n = len(rss)
    warm, end = np.median(rss[n // 5: 2 * n // 5]), np.median(rss[4 * n // 5:])
    fds = [f for _, _, f in series]
    return {"samples": n, "rss_warm_mb": round(warm / 1e6, 2), "rss_end_mb": round(end / 1e6, 2),
            "growth": round(float(end / warm - 1.0), 4), "fds_min": min(fds), "fds_max": max(fds)}


def analyse(name: str, sc, summary: dict, info: dict, samples: list[dict], work: Path) -> dict:
    per: dict[str, list] = {}
    for row in samples:
        for nm, p in row["procs"].items():
            series = per.setdefault(nm, [])
            if series and series[-1][3] != p["pid"]:   # restarted: judge the last incarnation
                series.clear()
            series.append((row["t"], p["rss"], p["fds"], p["pid"]))
    procs = {nm: growth([(t, r, f) for t, r, f, _ in s]) for nm, s in sorted(per.items())}
    late = 0
    for f in (work / "stats").glob("agent-*.json"):
        late += int(json.loads(f.read_text()).get("role", {}).get("late_payloads", 0))
    rmse = []
    with open(work / "metrics.csv") as fh:
        for row in csv.DictReader(fh):
            v = row.get("network_rmse") or row.get("rmse")
            rmse.append(float(v) if v not in (None, "", "nan") else math.nan)
    windows = []
    for part in np.array_split(np.array(rmse, float), 10):
        ok = part[np.isfinite(part)]
        windows.append({"median": round(float(np.median(ok)), 4) if ok.size else None,
                        "max": round(float(np.max(ok)), 4) if ok.size else None, "ticks": int(part.size)})
    ticks = max(1, sc.run.ticks)
    worst = max((p.get("growth", 0.0) for p in procs.values()), default=0.0)
    return {"phase": name, "sensors": sc.sensors.n, "T": sc.run.T, "speed": sc.run.speed, "ticks": sc.run.ticks,
            "wall_s": info.get("wall_s"), "ticks_per_s": info.get("ticks_per_s"), "rc": info.get("rc"),
            "missed_deadlines": info.get("missed_deadlines"),
            "unrecorded_messages": info.get("unrecorded_messages"),
            "missed_deadlines_per_1000_ticks": round(1000.0 * (info.get("missed_deadlines") or 0) / ticks, 2),
            "late_payloads": late, "late_payloads_per_1000_ticks": round(1000.0 * late / ticks, 2),
            "restarts": info.get("restarts"), "recording_bytes": samples[-1]["recording_bytes"] if samples else None,
            "network_rmse": summary.get("network_rmse"), "error_windows": windows,
            "rss_growth_worst": worst, "rss_growth_ok": worst <= GROWTH_TARGET, "processes": procs,
            "samples": samples}


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    phases = res["phases"]
    fig, axes = plt.subplots(2, len(phases), figsize=(5 * len(phases), 6), squeeze=False)
    for j, ph in enumerate(phases):
        ax = axes[0][j]
        names = sorted({nm for row in ph["samples"] for nm in row["procs"]})
        for nm in names:
            ts = [row["t"] for row in ph["samples"] if nm in row["procs"]]
            rs = [row["procs"][nm]["rss"] / 1e6 for row in ph["samples"] if nm in row["procs"]]
            ax.plot(ts, rs, lw=0.8, label=nm if nm in ("launcher", "world/0", "recorder/0", "agent/0") else None)
        ax.set_title(f"{ph['phase']}: RSS per process (worst growth {ph['rss_growth_worst']:+.1%})")
        ax.set_xlabel("s")
        ax.set_ylabel("MB")
        ax.legend(fontsize=7)
        ax = axes[1][j]
        w = ph["error_windows"]
        ax.plot(range(1, len(w) + 1), [x["median"] for x in w], "o-", label="median")
        ax.plot(range(1, len(w) + 1), [x["max"] for x in w], "s--", label="max")
        ax.set_title(f"{ph['phase']}: network RMSE per tenth of the run")
        ax.set_xlabel("tenth of the run")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


PHASE_ORDER = ("demo", "faults", "flock30")


def _earlier_phases(out: Path, rerun: list[str]) -> list[dict]:
    """The phases of ``out`` that this run does not repeat, each with its own date: rerunning one phase keeps
    the others' results instead of dropping them."""
    try:
        old = json.loads(out.read_text())
    except (OSError, ValueError):
        return []
    kept = [p for p in old.get("phases", []) if isinstance(p, dict) and p.get("phase") not in rerun]
    for p in kept:
        p.setdefault("date", old.get("date"))
    return kept


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--phases", default="demo,faults,flock30")
    ap.add_argument("--flock-period", type=float, default=0.25, help="flock30: wall-clock s per tick")
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "soak.json")
    ap.add_argument("--plot", type=Path)
    a = ap.parse_args(argv)
    res: dict = {"date": time.strftime("%Y-%m-%d"), "cpus": os.cpu_count(), "minutes": a.minutes,
                 "phases": _earlier_phases(a.out, a.phases.split(","))}
    for name in a.phases.split(","):
        with tempfile.TemporaryDirectory(prefix=f"soak_{name}_") as d:
            ph = run_phase(name, a.minutes, a.flock_period, Path(d))
        ph["date"] = time.strftime("%Y-%m-%d")
        res["phases"].append(ph)
        res["phases"].sort(key=lambda p: PHASE_ORDER.index(p["phase"]) if p["phase"] in PHASE_ORDER else 99)
        print(f"[soak {name}] rc {ph['rc']}: {ph['ticks']} ticks in {ph['wall_s']} s, missed deadlines "
              f"{ph['missed_deadlines_per_1000_ticks']}/1000 ticks, late payloads {ph['late_payloads_per_1000_ticks']}"
              f"/1000 ticks, worst RSS growth {ph['rss_growth_worst']:+.1%}, recording "
              f"{(ph['recording_bytes'] or 0) / 1e6:.1f} MB, network RMSE {ph['network_rmse']}", flush=True)
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(res, indent=1))
    if a.plot:
        plot(res, a.plot)
    print(f"wrote {a.out}")
    return 0 if all(ph["rc"] == 0 and ph["rss_growth_ok"] for ph in res["phases"]) else 1


if __name__ == "__main__":
    sys.exit(main())
