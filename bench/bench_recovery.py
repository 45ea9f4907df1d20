"""Recovery times, measured from recordings: how fast a crashed sensor and a restarted router come back.

    python bench/bench_recovery.py [--trials 20] [--period 40] [--speed 0.25] [--out bench/results/recovery.json]

Two realtime runs of the main job (scenarios/demo.toml, 12 sensors, the launcher with its embedded
router), each with a seeded fault plan of ``--trials`` faults, one every ``--period`` ticks:

* **crash** — ``{kind: crash, targets: agents:i, start: s, heal: s + 1}`` (the launcher SIGKILLs sensor
  i at tick s and restarts it at the heal, the next tick; sensors taken in turn). Per trial:
  ``member_s``: from the heal (the restart) to the first tick whose membership has the sensor alive
  again (the world's link table); ``good_s``: to the sensor's first estimate whose error is below twice
  the median error of the other sensors at that tick; ``good_from_kill_s``: the same from the kill.
* **router_restart** — ``{kind: router_restart, start: s}``: the launcher closes and reopens the embedded
  router. ``all_back_s``: from the fault's event to the first tick for which every sensor's estimate is
  in the recording (the time of the last of them).

Times are the recorder's receive times of the messages (one clock), so they include the recorder's own
reconnection after a router restart. Prints a table; writes every trial and the median / p95 / max to
``--out``; ``--plot`` draws the distributions (docs/recovery.png).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.scenario import parse_scenario, scenario_data  # noqa: E402 - after the sys.path insert above
from flocktrack.record.reader import read_recording  # noqa: E402 - after the sys.path insert above
from flocktrack.engine.run import run_zenoh_to_dir  # noqa: E402 - after the sys.path insert above

TARGETS = {"member_s": 1.0, "good_s": 1.0, "all_back_s": 2.0}   # the targets (rejoin ≤ 1 s, router ≤ 2 s)


def plan(kind: str, trials: int, period: int, n: int, first: int = 30) -> list[dict]:
    if kind == "crash":
        return [{"kind": "crash", "targets": f"agents:{(1 + j) % n}", "start": first + j * period,
                 "heal": first + j * period + 1} for j in range(trials)]
    return [{"kind": "router_restart", "start": first + j * period} for j in range(trials)]


def run(kind: str, trials: int, period: int, speed: float, out: Path) -> Path:
    data = scenario_data(str(ROOT / "scenarios" / "demo.toml"), [],
                         **{"run.mode": "realtime", "run.speed": speed, "run.ticks": 30 + trials * period + 20})
    n = int(data["sensors"]["n"])
    data["faults"] = {"events": plan(kind, trials, period, n)}
    sc = parse_scenario(data, f"demo.toml + {kind} plan")
    t0 = time.monotonic()
    summary, info = run_zenoh_to_dir(sc, data, out, quiet=True, timeout_s=3600)
    print(f"[recovery] {kind}: {sc.run.ticks} ticks in {time.monotonic() - t0:.0f} s (rc {info['rc']})", flush=True)
    return out / "recording.mcap"


def _index(path: Path):
    rec = read_recording(path)
    ticks, truth, est, events = {}, {}, defaultdict(dict), []
    for (key, m, _), t in zip(rec.messages, rec.wall):   # t: when it was recorded (wall clock, ns)
        if key == "world/tick":
            ticks[m.k] = (t, m)
        elif key == "target/truth":
            truth[m.k] = np.asarray(m.x)[:2]
        elif key.endswith("/estimate") and key.startswith("agent/"):
            est[m.src].setdefault(m.k, (t, np.asarray(m.x)[:2]))
        elif key == "world/event" and m.verb == "fault":
            events.append((t, m.k, m.args))
    return ticks, truth, est, events


def crash_trials(path: Path) -> list[dict]:
    ticks, truth, est, events = _index(path)
    starts = {int(a["id"]): (t, k, [int(x) for x in a["agents"]]) for t, k, a in events
              if a["kind"] == "crash" and a["phase"] == "start"}
    heals = {int(a["id"]): (t, k) for t, k, a in events if a["kind"] == "crash" and a["phase"] == "heal"}
    out = []
    for fid, (t_kill, k_kill, agents) in sorted(starts.items()):
        if fid not in heals or not agents:
            continue
        v = agents[0]
        t_heal, k_heal = heals[fid]
        member = next((t for k, (t, m) in sorted(ticks.items()) if k >= k_heal and t > t_heal and m.alive[v]), None)
        good = None
        for k in sorted(x for x in est[v] if x >= k_heal):
            t, x = est[v][k]
            if k not in truth:
                continue
            others = [np.linalg.norm(e[k][1] - truth[k]) for i, e in est.items() if i != v and k in e]
            if others and np.linalg.norm(x - truth[k]) <= 2 * float(np.median(others)):
                good = t
                break
        s = 1e-9
        out.append({"agent": v, "kill_tick": k_kill, "heal_tick": k_heal,
                    "member_s": None if member is None else round((member - t_heal) * s, 3),
                    "good_s": None if good is None else round((good - t_heal) * s, 3),
                    "good_from_kill_s": None if good is None else round((good - t_kill) * s, 3)})
    return out


def router_trials(path: Path, n: int) -> list[dict]:
    ticks, truth, est, events = _index(path)
    out = []
    for t_ev, k_ev, a in events:
        if a["kind"] != "router_restart" or a["phase"] != "start":
            continue
        back = None
        for k in sorted(k for k in ticks if k > k_ev):
            ts = [est[i][k][0] for i in range(n) if k in est[i]]
            if len(ts) == n and min(ts) > t_ev:
                back = max(ts)
                break
        out.append({"tick": k_ev, "all_back_s": None if back is None else round((back - t_ev) * 1e-9, 3)})
    return out


def stats(xs: list) -> dict:
    v = [x for x in xs if x is not None]
    if not v:
        return {"n": 0, "missing": len(xs)}
    return {"n": len(v), "missing": len(xs) - len(v), "median": round(float(np.median(v)), 3),
            "p95": round(float(np.percentile(v, 95)), 3), "max": round(max(v), 3), "min": round(min(v), 3)}


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = [("crash → member again", [t["member_s"] for t in res["crash"]["trials"]], TARGETS["member_s"]),
              ("crash → error < 2× flock's", [t["good_s"] for t in res["crash"]["trials"]], TARGETS["good_s"]),
              ("router restart → all estimating", [t["all_back_s"] for t in res["router_restart"]["trials"]],
               TARGETS["all_back_s"])]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.2))
    for ax, (title, xs, target) in zip(axes, series):
        v = sorted(x for x in xs if x is not None)
        ax.step(v, np.arange(1, len(v) + 1) / max(len(v), 1), where="post")
        ax.axvline(target, color="tab:red", ls="--", label=f"target {target:g} s")
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("seconds")
        ax.set_ylim(0, 1.02)
        ax.legend(fontsize=8, loc="lower right")
    axes[0].set_ylabel("fraction of trials")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--period", type=int, default=40, help="ticks between faults (default 40)")
    ap.add_argument("--speed", type=float, default=0.25, help="realtime factor (0.25: the pace of docs/reliability.md)")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "recovery.json"))
    ap.add_argument("--plot", default=None, help="PNG of the distributions (e.g. docs/recovery.png)")
    ap.add_argument("--keep", default=None, help="keep the run directories here")
    a = ap.parse_args(argv)
    base = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="recovery-"))
    n = int(scenario_data(str(ROOT / "scenarios" / "demo.toml"), [])["sensors"]["n"])
    res: dict = {"bench": "recovery times", "timestamp": time.strftime("%Y-%m-%dT%H:%M:%S"), "scenario": "demo.toml",
                 "sensors": n, "speed": a.speed, "period_ticks": a.period, "targets_s": TARGETS}
    crash = crash_trials(run("crash", a.trials, a.period, a.speed, base / "crash"))
    router = router_trials(run("router_restart", a.trials, a.period, a.speed, base / "router"), n)
    res["crash"] = {"trials": crash, **{k: stats([t[k] for t in crash]) for k in ("member_s", "good_s", "good_from_kill_s")}}
    res["router_restart"] = {"trials": router, "all_back_s": stats([t["all_back_s"] for t in router])}
    Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
    print(f"{'measure':38s} {'n':>3s} {'median':>8s} {'p95':>8s} {'max':>8s}  target")
    for name, st, tgt in [("crash → member again (from restart)", res["crash"]["member_s"], TARGETS["member_s"]),
                          ("crash → error < 2× flock's (from restart)", res["crash"]["good_s"], TARGETS["good_s"]),
                          ("crash → error < 2× flock's (from kill)", res["crash"]["good_from_kill_s"], None),
                          ("router restart → all estimating", res["router_restart"]["all_back_s"], TARGETS["all_back_s"])]:
        if st.get("n"):
            print(f"{name:38s} {st['n']:3d} {st['median']:8.3f} {st['p95']:8.3f} {st['max']:8.3f}  {tgt or ''}")
        else:
            print(f"{name:38s} none measured ({st})")
    if a.plot:
        plot(res, Path(a.plot))
    return 0


if __name__ == "__main__":
    sys.exit(main())
