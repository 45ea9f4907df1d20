"""Cut-and-heal times of a host's network link, measured on a 3-host mesh of network namespaces.

    python bench/bench_netcut.py [--trials 20] [--down 3] [--every 5] [--out bench/results/netcut.json]

The multi-host test's set-up (flocktrack.testbed.netns): three "hosts" (namespaces on a switch), each running
`flocktrack run gu_hu_normal --placement hosts.toml --host NAME` — its own router of the mesh, launcher and
recorder shard — with the 10 sensors split a: 0–3 (with the world and the target), b: 4–6, c: 7–9, here in
realtime. Host b's cable is
pulled ``--trials`` times, each for ``--down`` s, ``--every`` s after the previous heal. Per trial, from
host a's liveliness view: ``detect_s`` = cut → the last of b's sensors seen gone; ``recover_s`` = heal → the
last of them seen back. Targets: detection ≤ 2 s, recovery ≤ 1 s after the heal. Needs root and
iproute2. Writes the trials and their median / p95 / max.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from bench_recovery import stats  # noqa: E402 - after the sys.path lines above (median / p95 / max with gaps)
from flocktrack.testbed import netns  # noqa: E402 - same

HOSTS = ["a", "b", "c"]
WHERE = {"agent/0-3": "a", "agent/4-6": "b", "agent/7-9": "c", "*": "a"}
VICTIMS = [4, 5, 6]     # host b's sensors

TARGETS = {"detect_s": 2.0, "recover_s": 1.0}


def trials(timeline: list[dict]) -> list[dict]:
    cuts = [e for e in timeline if e["event"] in ("cut", "heal")]
    victims = {f"agent/{i}" for i in VICTIMS}
    out = []
    for j in range(0, len(cuts) - 1, 2):
        cut, heal = cuts[j], cuts[j + 1]
        nxt = cuts[j + 2]["t"] if j + 2 < len(cuts) else math.inf

        def first(alive: bool, lo: float, hi: float) -> dict[str, float]:
            seen: dict[str, float] = {}
            for e in timeline:
                if e["event"] == "member" and e["name"] in victims and e["alive"] is alive and lo < e["t"] < hi:
                    seen.setdefault(e["name"], e["t"])
            return seen

        lost, back = first(False, cut["t"], heal["t"]), first(True, heal["t"], nxt)
        out.append({"trial": j // 2, "detect_s": round(max(lost.values()) - cut["t"], 3) if len(lost) == len(victims) else None,
                    "recover_s": round(max(back.values()) - heal["t"], 3) if len(back) == len(victims) else None})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--down", type=float, default=3.0)
    ap.add_argument("--every", type=float, default=5.0)
    ap.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "netcut.json")
    a = ap.parse_args(argv)
    why = netns.available()
    if why:
        sys.exit(f"bench_netcut: {why}")
    T, at_tick = 0.04, 50
    wall = at_tick * T + a.trials * (a.down + a.every) + 10.0
    ticks = int(wall / T)
    print(f"[netcut] {a.trials} cuts of host b ({a.down:g} s each, every {a.every:g} s), {ticks} realtime ticks "
          f"(~{wall:.0f} s)", flush=True)
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="netcut_") as d, netns.Network(len(HOSTS)) as net:
        r = netns.placed_run(net, WHERE, "gu_hu_normal", Path(d), "--ticks", str(ticks), "--mode", "realtime",
                             names=HOSTS, cut={"port": "p1", "at_tick": at_tick, "down_s": a.down, "repeat": a.trials,
                                               "every_s": a.every}, timeout_s=wall + 120)
        timeline = json.loads((Path(d) / "timeline.json").read_text())
        info = {"rc": max((rc if rc is not None else 124) for rc in r["rcs"])}
    rows = trials(timeline)
    res = {"date": time.strftime("%Y-%m-%d"), "trials": rows, "down_s": a.down, "every_s": a.every,
           "rc": info.get("rc"), "wall_s": round(time.monotonic() - t0, 1), "targets": TARGETS,
           "detect_s": stats([r["detect_s"] for r in rows]), "recover_s": stats([r["recover_s"] for r in rows])}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1))
    for k in ("detect_s", "recover_s"):
        s = res[k]
        print(f"[netcut] {k}: median {s.get('median')} s, p95 {s.get('p95')} s, max {s.get('max')} s "
              f"over {s['n']} trials ({s['missing']} missing); target ≤ {TARGETS[k]} s", flush=True)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
