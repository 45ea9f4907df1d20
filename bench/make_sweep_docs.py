"""Regenerate the committed sweep results under ``docs/``: the foundation scenarios against link loss and
consensus rounds (``flocktrack sweep``), their figures, their CSV summaries and the generated tables in
``docs/sweeps.md``.

    python bench/make_sweep_docs.py [--jobs J] [--work DIR] [--only NAME ...] [--quick]

The runs go to ``--work`` (default ``runs/sweep_docs/``, not committed) and are resumed from there, so a
second invocation only redraws. ``--quick`` (few seeds and ticks) checks the pipeline in a minute; it
writes to ``DIR/quick`` and never touches ``docs/``. Budget: under 10 min on two busy cores (about 1000 s of run time).

Writes, per sweep NAME:
  docs/sweep_NAME_summary.csv   per cell and metric: n, mean, bootstrap 95 % CI, std, median, p10, p90
                                (the per-node RMSEs left out)
  docs/sweep_NAME_*.png         the error traces and metric-vs-parameter figures
and the block between ``<!-- sweep:NAME:begin -->`` and ``<!-- sweep:NAME:end -->`` in docs/sweeps.md
(the prose around the blocks is hand-written and left alone).
"""

from __future__ import annotations

import argparse
import csv
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from flocktrack.experiment.sweep import SweepConfig, run_sweep
from flocktrack.experiment.grid import parse_grid

DOCS = ROOT / "docs"

#: name, scenario, grid, seeds, ticks, figures to publish, what the sweep asks
SWEEPS = [
    dict(name="intelligent_loss", scenario="scenarios/gu_hu_intelligent.toml",
         grid=["faults.link_loss=0,0.1,0.3,0.5", "estimator=kalman,minimax"], seeds=3, ticks=800,
         figures=["traces_rmse", "network_rmse_vs_link_loss", "final_rmse_vs_link_loss",
                  "disagreement_mean_vs_link_loss"],
         question="Gu & Hu's intelligent target, 10 flocking sensors, 5 consensus rounds: distributed Kalman vs "
                  "distributed minimax as every directed link drops with probability p each tick."),
    dict(name="intelligent_rounds", scenario="scenarios/gu_hu_intelligent.toml",
         grid=["rounds=0,1,5", "estimator=kalman,minimax"], seeds=3, ticks=800,
         figures=["traces_rmse", "network_rmse_vs_rounds", "disagreement_mean_vs_rounds"],
         question="The same target without faults: how many consensus rounds per tick the filters need."),
    dict(name="normal_loss", scenario="scenarios/gu_hu_normal.toml",
         grid=["faults.link_loss=0,0.1,0.3,0.5", "rounds=1,5"], seeds=3, ticks=300,
         figures=["traces_rmse", "network_rmse_vs_link_loss", "disagreement_mean_vs_link_loss"],
         question="Gu & Hu's normal (random-walk) target, distributed minimax: link loss × consensus rounds."),
    dict(name="chen_loss", scenario="scenarios/chen_switching.toml",
         grid=["faults.link_loss=0,0.25,0.5,0.75,1"], seeds=10, ticks=300,
         figures=["traces_rmse", "network_rmse_vs_link_loss", "disagreement_mean_vs_link_loss"],
         question="Chen et al.'s 3-sensor switching network with the constant-gain H∞ estimator (one exchange "
                  "per tick by design, so no rounds axis): link loss up to 1 (no links at all)."),
]

#: metrics in the generated tables: (summary.csv metric, column title)
TABLE_METRICS = [("network_rmse", "network RMSE"), ("final_rmse", "final RMSE"), ("max_error", "max error"),
                 ("disagreement_mean", "disagreement"), ("lambda2_mean", "mean λ₂"),
                 ("connected_fraction", "connected")]


def _fmt(v: str) -> str:
    if v in ("", None):
        return "–"
    x = float(v)
    return f"{x:.3g}" if abs(x) < 1e4 else f"{x:.2e}"


def _table(sweep: dict, meta: dict, summary_rows: list[dict]) -> str:
    keys = list(meta["grid"])
    labels = [meta["labels"][k] for k in keys]
    cells: dict[tuple, dict[str, dict]] = {}
    for r in summary_rows:
        cells.setdefault(tuple(r[k] for k in keys), {})[r["metric"]] = r
    head = labels + ["n"] + [t for _, t in TABLE_METRICS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for cell, ms in cells.items():
        n = next(iter(ms.values())).get("n", "")
        vals = []
        for m, _ in TABLE_METRICS:
            r = ms.get(m)
            if r is None or r.get("mean", "") == "":
                vals.append("–")
            elif m in ("network_rmse", "final_rmse"):
                vals.append(f"{_fmt(r['mean'])} [{_fmt(r['ci95_lo'])}, {_fmt(r['ci95_hi'])}]")
            else:
                vals.append(_fmt(r["mean"]))
        lines.append("| " + " | ".join([*cell, n, *vals]) + " |")
    grid = " ".join(f"--grid '{g}'" for g in sweep["grid"])
    cmd = (f"flocktrack sweep {sweep['scenario']} {grid} --seeds {sweep['seeds']} --ticks {sweep['ticks']} "
           f"--out runs/sweep_docs/{sweep['name']}")
    figs = " ".join(f"![{f}](sweep_{sweep['name']}_{f}.png)" for f in sweep["figures"])
    return "\n".join([
        f"_{sweep['question']}_",
        "",
        f"`{cmd}` — {meta['runs']} runs ({meta['ok']} ok, {meta['failed']} failed), "
        f"{meta['run_wall_s_total']:.0f} s of run time. Means over seeds, [bootstrap 95 % CI]; "
        f"full table: [`sweep_{sweep['name']}_summary.csv`](sweep_{sweep['name']}_summary.csv).",
        "",
        *lines,
        "",
        figs,
    ])


def _replace_block(text: str, name: str, body: str) -> str:
    begin, end = f"<!-- sweep:{name}:begin -->", f"<!-- sweep:{name}:end -->"
    block = f"{begin}\n{body}\n{end}"
    if begin in text and end in text:
        a = text.index(begin)
        b = text.index(end) + len(end)
        return text[:a] + block + text[b:]
    return text.rstrip("\n") + f"\n\n### {name}\n\n{block}\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int)
    ap.add_argument("--work", default=str(ROOT / "runs" / "sweep_docs"))
    ap.add_argument("--only", action="append", help="run only this sweep (repeatable)")
    ap.add_argument("--quick", action="store_true", help="2 seeds, 60 ticks; to DIR/quick, docs/ untouched")
    args = ap.parse_args(argv)
    work = Path(args.work) / ("quick" if args.quick else "")
    t0 = time.perf_counter()
    md_path = DOCS / "sweeps.md"
    md = md_path.read_text() if md_path.exists() else "# Sweeps\n"
    for sw in SWEEPS:
        if args.only and sw["name"] not in args.only:
            continue
        seeds, ticks = (2, 60) if args.quick else (sw["seeds"], sw["ticks"])
        cfg = SweepConfig(scenario=str(ROOT / sw["scenario"]), axes=[parse_grid(g) for g in sw["grid"]],
                          seeds=list(range(seeds)), out=work / sw["name"], ticks=ticks, jobs=args.jobs)
        print(f"== {sw['name']}: {sw['scenario']} {' '.join(sw['grid'])} × {seeds} seeds, {ticks} ticks",
              file=sys.stderr, flush=True)
        meta = run_sweep(cfg)
        print(f"   {meta['ok']}/{meta['runs']} ok in {meta['wall_s']:.0f} s", file=sys.stderr, flush=True)
        if args.quick:
            continue
        out = cfg.out
        DOCS.mkdir(exist_ok=True)
        for f in sw["figures"]:
            shutil.copyfile(out / "figures" / f"{f}.png", DOCS / f"sweep_{sw['name']}_{f}.png")
        with (out / "summary.csv").open(newline="") as f:
            rows = [r for r in csv.DictReader(f) if not r["metric"].startswith("per_node")]
        with (DOCS / f"sweep_{sw['name']}_summary.csv").open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        meta = {**meta, "scenario": sw["scenario"]}
        md = _replace_block(md, sw["name"], _table(sw, meta, rows))
    if not args.quick:
        md_path.write_text(md)
    print(f"done in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
