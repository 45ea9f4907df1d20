"""Experiment sweeps: a scenario × a grid of overrides × seeds, in parallel, into one tidy CSV and figures.

    flocktrack sweep SCENARIO --grid KEY=V1,V2,... [--grid ...] [--seeds S] [--set KEY=V ...]
                              [--ticks N] [--jobs J] [--no-resume] [--no-figures] --out DIR

* ``--grid KEY=V1,V2,…`` (repeatable): ``KEY`` is a dotted scenario key ``section.key`` (or a shorthand:
  ``estimator`` → ``estimator.name``, ``rounds`` → ``estimator.rounds``, ``range`` → ``topology.range``,
  ``link_loss`` → ``faults.link_loss``, ``ticks`` → ``run.ticks``); the values are TOML values (numbers,
  strings — bare words are strings —, booleans, arrays: ``--grid 'sensors.origin=[0,0],[5,5]'``). ``seed``
  is reserved: ``--seeds S`` runs seeds 0 … S−1 (``run.seed``) for every cell of the Cartesian product.
* Every run is the in-process engine (:func:`flocktrack.run.run_inproc_to_dir`, the same numbers as a
  lockstep run over Zenoh) in ``DIR/runs/<run_id>/``, on a ``ProcessPoolExecutor`` of ``--jobs`` workers
  (default ``os.cpu_count()``); a rich progress bar on a terminal, plain lines otherwise.
* Every cell is validated before anything runs. A grid key the scenario schema does not know (or a
  ``--set`` that breaks every cell) stops the sweep at once with the scenario's error; a cell whose
  *value* is invalid, or a run that raises, is reported and recorded as failed, and the sweep goes on.
* Resumable: a run is written to ``runs/.<run_id>.tmp`` and renamed when complete, so a run directory
  with a ``summary.json`` is finished; it is not recomputed unless its resolved scenario changed.
* Output: ``DIR/results.csv`` (tidy: one row per run and metric — the grid keys, ``seed``, ``run_id``,
  ``status``, ``metric``, ``value``, ``error``; the scalar metrics of ``summary.json`` and
  ``per_node_rmse[i]``), ``DIR/summary.csv`` (per cell and metric: n, mean, bootstrap 95 % CI, std,
  median, 10/90 % quantiles), ``DIR/sweep.json`` (grid, seeds, timings, failures) and
  ``DIR/figures/*.png`` (:mod:`dashboards.sweep_plots`).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import itertools
import json
import math
import multiprocessing as mp
import os
import re
import shutil
import signal
import sys
import time
import tomllib
import traceback
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import tomli_w

from agent.scenario import ScenarioError, parse_scenario

from .resources import add_scenario_argument

#: grid-key shorthands → dotted scenario keys
SHORTHANDS = {
    "estimator": "estimator.name",
    "rounds": "estimator.rounds",
    "range": "topology.range",
    "link_loss": "faults.link_loss",
    "ticks": "run.ticks",
}
#: summary.json fields that identify a run rather than measure it (not written as metrics)
IDENTITY_FIELDS = {"scenario", "estimator", "seed", "ticks", "n_sensors", "rounds", "burn_in",
                   "ticks_scored", "ticks_seen"}
#: metrics drawn against the first numeric grid key (when the runs have them)
FIGURE_METRICS = ["network_rmse", "final_rmse", "max_error", "disagreement_mean", "mean_estimate_rmse",
                  "connected_fraction"]
#: metrics.csv columns drawn against time
TRACE_COLUMNS = {"rmse": "network RMSE (position)", "disagreement": "consensus disagreement"}
CSV_FIXED = ["seed", "run_id", "status", "metric", "value", "error"]


# ============================================================================ the grid

@dataclass(frozen=True)
class Axis:
    key: str      #: the dotted scenario key, e.g. "estimator.rounds"
    label: str    #: what figures and run ids call it (the shorthand when there is one)
    values: tuple

    @property
    def numeric(self) -> bool:
        return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in self.values)


def split_values(text: str) -> list[str]:
    """Split ``V1,V2,…`` at the commas that are not inside brackets, braces or quotes."""
    out, cur, depth, quote = [], [], 0, ""
    for ch in text:
        if quote:
            cur.append(ch)
            if ch == quote:
                quote = ""
            continue
        if ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            out.append("".join(cur).strip())
            cur = []
            continue
        cur.append(ch)
    out.append("".join(cur).strip())
    return out


def parse_value(text: str):
    """A TOML value (``0.1``, ``true``, ``[1, 2]``, ``"x"``); anything else is taken as a bare string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def canonical_key(key: str, source: str = "--grid") -> tuple[str, str]:
    """(dotted key, label) for a ``--grid`` key; raises :class:`ScenarioError` for a malformed or reserved one."""
    key = key.strip()
    label = key
    dotted = SHORTHANDS.get(key, key)
    if dotted in ("seed", "run.seed"):
        raise ScenarioError(source, dotted, "the seed is not a grid key", "use --seeds S (runs seeds 0 … S−1)")
    sect, dot, name = dotted.partition(".")
    if not dot or not sect or not name or "." in name:
        raise ScenarioError(source, key, "grid key must look like section.key",
                            f"e.g. --grid estimator.rounds=1,2,5, or a shorthand: {', '.join(SHORTHANDS)}")
    for short, full in SHORTHANDS.items():
        if full == dotted:
            label = short
    return dotted, label


def parse_grid(spec: str) -> Axis:
    """``KEY=V1,V2,…`` → :class:`Axis`."""
    key, sep, vals = spec.partition("=")
    if not sep or not vals.strip():
        raise ScenarioError("--grid", spec, "expected KEY=V1,V2,…", "e.g. --grid 'faults.link_loss=0,0.1,0.3'")
    dotted, label = canonical_key(key)
    raw = split_values(vals)
    if any(r == "" for r in raw):
        raise ScenarioError("--grid", spec, "empty value in the list", "remove the stray comma")
    values = tuple(parse_value(r) for r in raw)
    reprs = [value_repr(v) for v in values]
    dup = sorted({r for r in reprs if reprs.count(r) > 1})
    if dup:
        raise ScenarioError("--grid", spec, f"repeated value(s) {', '.join(dup)}", "list each value once")
    return Axis(dotted, label, values)


def value_repr(v) -> str:
    """How a grid value is written in the CSV, run ids and figure labels (strings bare, the rest as TOML)."""
    if isinstance(v, str):
        return v
    return _toml_inline(v)


def _toml_inline(v) -> str:
    if isinstance(v, list):
        return "[" + ", ".join(_toml_inline(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k} = {_toml_inline(x)}" for k, x in v.items()) + "}"
    return tomli_w.dumps({"v": v}).partition("=")[2].strip()


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._+-]+", "x", text.strip("[]{} "))


@dataclass(frozen=True)
class RunSpec:
    run_id: str
    cell_index: int
    cell: tuple   #: values, in axis order
    seed: int


def expand(axes: list[Axis], seeds: list[int]) -> list[RunSpec]:
    """The Cartesian product of the axes × seeds, with stable, readable run ids."""
    cells = list(itertools.product(*(a.values for a in axes))) if axes else [()]
    bases = []
    for cell in cells:
        bases.append("_".join(f"{_slug(a.label)}-{_slug(value_repr(v))}" for a, v in zip(axes, cell)))
    for ci, cell in enumerate(cells):
        lossy = any(_slug(value_repr(v)) != value_repr(v) for v in cell) or len(bases[ci]) > 100
        if lossy or bases.count(bases[ci]) > 1:  # unique and still readable when values had to be mangled
            h = hashlib.sha1(json.dumps([[a.key, value_repr(v)] for a, v in zip(axes, cell)]).encode()).hexdigest()[:8]
            bases[ci] = f"{bases[ci][:80]}~{h}"
    specs: list[RunSpec] = []
    for ci, cell in enumerate(cells):
        for s in seeds:
            specs.append(RunSpec(f"{bases[ci]}_seed-{s}" if bases[ci] else f"seed-{s}", ci, cell, s))
    return specs


# ============================================================================ configuration and planning

@dataclass
class SweepConfig:
    scenario: str
    axes: list[Axis]
    seeds: list[int]
    out: Path
    sets: list[str] = field(default_factory=list)
    ticks: int | None = None
    jobs: int | None = None
    resume: bool = True
    figures: bool = True
    progress: bool = True  #: show a progress bar / progress lines on stderr


def run_data(cfg: SweepConfig, spec: RunSpec) -> dict:
    """The run's TOML mapping: the scenario, ``--set``, ``--ticks``, then the cell and the seed."""
    from agent.scenario import scenario_data

    named = {"run.ticks": cfg.ticks, "run.seed": spec.seed}
    named.update({a.key: v for a, v in zip(cfg.axes, spec.cell)})
    return scenario_data(cfg.scenario, cfg.sets, **named)


def _check_sets(cfg: SweepConfig) -> None:
    grid_keys = {a.key for a in cfg.axes}
    if len(grid_keys) != len(cfg.axes):
        raise ScenarioError("--grid", ", ".join(a.key for a in cfg.axes), "the same key is given twice",
                            "give each key one --grid with all its values")
    for s in cfg.sets:
        dotted = s.partition("=")[0].strip()
        if dotted == "run.seed":
            raise ScenarioError("--set", s, "the seed is set by --seeds", "remove --set run.seed")
        if dotted in grid_keys:
            raise ScenarioError("--set", s, "this key is also a --grid key", "keep only one of them")
    if not cfg.seeds:
        raise ScenarioError("--seeds", str(len(cfg.seeds)), "need at least one seed", "e.g. --seeds 5")


def plan(cfg: SweepConfig) -> tuple[list[RunSpec], dict[int, str]]:
    """Expand and validate every cell (cheap: parse only). Returns the runs and {cell index: error}.

    Raises :class:`ScenarioError` — before anything runs — when a grid key is unknown to the scenario
    schema, or when no cell at all is valid (e.g. a bad ``--set``)."""
    _check_sets(cfg)
    specs = expand(cfg.axes, cfg.seeds)
    first_of_cell: dict[int, RunSpec] = {}
    for r in specs:
        first_of_cell.setdefault(r.cell_index, r)
    errors: dict[int, Exception] = {}
    for ci, r in first_of_cell.items():
        data = run_data(cfg, r)  # a missing or malformed scenario file raises here, for every cell alike
        try:
            parse_scenario(data, cfg.scenario)
        except Exception as exc:
            errors[ci] = exc
    sections = {a.key.partition(".")[0] for a in cfg.axes}
    for exc in errors.values():
        if (isinstance(exc, ScenarioError) and exc.problem.startswith("unknown")
                and (exc.key in {a.key for a in cfg.axes} or exc.key in sections)):
            raise exc
    if errors and len(errors) == len(first_of_cell):
        exc = next(iter(errors.values()))
        if isinstance(exc, ScenarioError):
            raise exc
        raise ScenarioError(cfg.scenario, "-", f"no cell of the grid is valid ({type(exc).__name__}: {exc})")
    return specs, {ci: (str(e) if isinstance(e, ScenarioError) else f"{type(e).__name__}: {e}")
                   for ci, e in errors.items()}


# ============================================================================ running

def _execute(task: dict) -> dict:
    """One run (in a worker process): parse, run in-process to a temporary directory, rename."""
    from .run import run_inproc_to_dir

    final = Path(task["dir"])
    tmp = final.parent / f".{final.name}.tmp"
    t0 = time.perf_counter()
    try:
        if tmp.exists():
            shutil.rmtree(tmp)
        sc = parse_scenario(task["data"], task["source"])
        _, info = run_inproc_to_dir(sc, task["data"], tmp)
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
        return {"run_id": task["run_id"], "status": "ok", "wall_s": info["wall_s"]}
    except Exception as exc:  # a failing cell must not abort the sweep
        shutil.rmtree(tmp, ignore_errors=True)
        msg = str(exc) if isinstance(exc, ScenarioError) else f"{type(exc).__name__}: {exc}"
        return {"run_id": task["run_id"], "status": "failed", "error": msg, "wall_s": time.perf_counter() - t0,
                "traceback": traceback.format_exc(limit=6)}


class SweepProgress:
    """A rich progress bar on a terminal, one plain line per finished run otherwise; failures always shown."""

    def __init__(self, total: int, enabled: bool = True):
        self.total, self.done, self.failed = total, 0, 0
        self.enabled = enabled
        self._bar = None
        if enabled and sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                       TimeRemainingColumn)

            self._bar = Progress(TextColumn("[bold]sweep"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("{task.fields[failed]}"), TimeElapsedColumn(), TimeRemainingColumn(),
                                 console=Console(stderr=True), transient=False)
            self._task = self._bar.add_task("sweep", total=total, failed="")
            self._bar.start()

    def note(self, text: str) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.console.print(text, markup=False, highlight=False)
        else:
            print(text, file=sys.stderr, flush=True)

    def advance(self, res: dict, quiet_ok: bool = False) -> None:
        """Count a finished run; ``quiet_ok``: already reported (resumed, or an invalid cell) — no line."""
        self.done += 1
        ok = res["status"] == "ok"
        self.failed += not ok
        if self._bar is not None:
            self._bar.update(self._task, completed=self.done,
                             failed=f"[red]{self.failed} failed" if self.failed else "")
            if not ok and not quiet_ok:
                self.note(f"FAILED {res['run_id']}: {res.get('error')}")
        elif self.enabled and not quiet_ok:
            tail = f"{res['wall_s']:.1f} s" if ok else f"FAILED: {res.get('error')}"
            print(f"sweep [{self.done}/{self.total}] {res['run_id']} {tail}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()


def _is_done(run_dir: Path, data: dict) -> str:
    """'' (not done), 'done', or 'stale' (finished with a different resolved scenario)."""
    if not (run_dir / "summary.json").exists():
        return ""
    try:
        same = (run_dir / "scenario.toml").read_text() == tomli_w.dumps(data)
    except OSError:
        same = False
    return "done" if same else "stale"


def _triage(cfg: SweepConfig, specs: list, cell_errors: dict, runs_dir: Path) -> tuple[dict, list, int, int]:
    """Which runs are invalid (failed before running), done (resumed), stale or new: (results so far,
    tasks to run, how many resumed, how many stale)."""
    results: dict[str, dict] = {}
    tasks: list[dict] = []
    skipped = stale = 0
    for r in specs:
        if r.cell_index in cell_errors:
            results[r.run_id] = {"run_id": r.run_id, "status": "failed", "error": cell_errors[r.cell_index],
                                 "wall_s": 0.0}
            continue
        data = run_data(cfg, r)
        state = _is_done(runs_dir / r.run_id, data) if cfg.resume else ""
        if state == "done":
            skipped += 1
            results[r.run_id] = {"run_id": r.run_id, "status": "ok", "wall_s": _old_wall(runs_dir / r.run_id),
                                 "resumed": True}
            continue
        stale += state == "stale"
        tasks.append({"run_id": r.run_id, "dir": str(runs_dir / r.run_id), "data": data, "source": cfg.scenario})
    return results, tasks, skipped, stale


def run_sweep(cfg: SweepConfig) -> dict:
    """Plan, run what is not done, write ``results.csv``, ``summary.csv``, ``sweep.json`` and figures.

    Returns the ``sweep.json`` content. Raises :class:`ScenarioError` before running anything when the
    grid is invalid (see :func:`plan`)."""
    started = datetime.now(timezone.utc)
    t0 = time.perf_counter()
    specs, cell_errors = plan(cfg)
    out = Path(cfg.out)
    runs_dir = out / "runs"
    runs_dir.mkdir(parents=True, exist_ok=True)
    jobs = max(1, cfg.jobs or os.cpu_count() or 1)

    results, tasks, skipped, stale = _triage(cfg, specs, cell_errors, runs_dir)
    prog = SweepProgress(len(specs), cfg.progress)
    n_cells = len({r.cell_index for r in specs})
    prog.note(f"sweep {cfg.scenario}: {n_cells} cells × {len(cfg.seeds)} seeds = {len(specs)} runs, "
              f"{len(tasks)} to run on {min(jobs, max(len(tasks), 1))} processes"
              + (f", {skipped} already done" if skipped else "") + (f", {stale} stale (re-run)" if stale else "")
              + (f", {len(cell_errors)} invalid cells" if cell_errors else ""))
    for ci, err in sorted(cell_errors.items()):
        prog.note(f"invalid cell {ci}: {err}")
    for rid in results:  # already done (resumed) or invalid before running
        prog.advance(results[rid], quiet_ok=True)
    try:
        if jobs == 1 or len(tasks) <= 1:
            for task in tasks:
                res = _execute(task)
                results[res["run_id"]] = res
                prog.advance(res)
        else:
            _run_pool(tasks, jobs, results, prog)
    finally:
        prog.close()

    wall = time.perf_counter() - t0
    rows = collect_rows(cfg.axes, specs, runs_dir, results)
    write_results_csv(out / "results.csv", cfg.axes, rows)
    write_summary_csv(out / "summary.csv", cfg.axes, rows)
    figures: list[str] = []
    fig_error = None
    if cfg.figures:
        try:
            figures = [str(p.relative_to(out)) for p in make_figures(out, cfg.axes, specs, results)]
        except Exception as exc:  # figures are a view; never lose the CSV to a plotting problem
            fig_error = f"{type(exc).__name__}: {exc}"
            prog.note(f"figures failed: {fig_error}")
    meta = _sweep_meta(cfg, specs, results, jobs, skipped, stale, len(tasks), started, wall)
    meta.update(figures=figures, figures_error=fig_error)
    (out / "sweep.json").write_text(json.dumps(meta, indent=2, default=_json_default) + "\n")
    return meta


def _sweep_meta(cfg: SweepConfig, specs: list, results: dict, jobs: int, skipped: int, stale: int,
                executed: int, started: datetime, wall: float) -> dict:
    """``sweep.json``: the grid, what ran, what failed and how long it took."""
    failures = [{"run_id": r.run_id, "cell": {a.key: v for a, v in zip(cfg.axes, r.cell)}, "seed": r.seed,
                 "error": results[r.run_id].get("error"), "traceback": results[r.run_id].get("traceback")}
                for r in specs if results[r.run_id]["status"] != "ok"]
    return {
        "scenario": cfg.scenario,
        "grid": {a.key: list(a.values) for a in cfg.axes},
        "labels": {a.key: a.label for a in cfg.axes},
        "seeds": list(cfg.seeds),
        "sets": list(cfg.sets),
        "ticks": cfg.ticks,
        "jobs": jobs,
        "runs": len(specs),
        "ok": sum(1 for r in specs if results[r.run_id]["status"] == "ok"),
        "failed": len(failures),
        "resumed": skipped,
        "rerun_stale": stale,
        "executed": executed,
        "started": started.isoformat(timespec="seconds"),
        "finished": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "wall_s": wall,
        "run_wall_s_total": sum(float(results[r.run_id].get("wall_s") or 0.0) for r in specs),
        "run_wall_s": {r.run_id: results[r.run_id].get("wall_s") for r in specs},
        "failures": failures,
        "figures": [],
        "figures_error": None,
        "outputs": {"results": "results.csv", "summary": "summary.csv", "runs": "runs/", "figures": "figures/"},
    }


def _worker_init() -> None:
    # Ctrl-C goes to the whole process group; the parent alone decides (it terminates the workers), so a
    # worker neither dies half-way through writing nor swallows the interrupt and takes the next run
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """Cancel what has not started and terminate the workers (ours) of a pool, without waiting for runs."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        if proc.is_alive():
            proc.terminate()
    for proc in procs:
        proc.join(timeout=5)


def _run_pool(tasks: list[dict], jobs: int, results: dict, prog: SweepProgress) -> None:
    pending = list(tasks)
    while pending:  # a worker killed by the OS breaks the pool: record its runs, start a new pool for the rest
        # spawn, not fork: the parent may run rich's refresh thread, and forking a threaded process can
        # leave a lock held in the child
        pool = ProcessPoolExecutor(max_workers=min(jobs, len(pending)), mp_context=mp.get_context("spawn"),
                                   initializer=_worker_init)
        try:
            futs = {pool.submit(_execute, t): t for t in pending}
            pending = []
            broken = False
            not_done = set(futs)
            while not_done:
                done, not_done = wait(not_done, return_when=FIRST_COMPLETED)
                for f in done:
                    t = futs[f]
                    try:
                        res = f.result()
                    except BrokenProcessPool:
                        if not broken:
                            broken = True
                            res = {"run_id": t["run_id"], "status": "failed", "wall_s": 0.0,
                                   "error": "a worker process died (killed, out of memory) during this or a concurrent run"}
                        else:
                            pending.append(t)
                            continue
                    except Exception as exc:
                        res = {"run_id": t["run_id"], "status": "failed", "wall_s": 0.0,
                               "error": f"{type(exc).__name__}: {exc}"}
                    results[res["run_id"]] = res
                    prog.advance(res)
        except BaseException:  # Ctrl-C / SIGTERM: stop now; finished runs are kept, the rest resumes next time
            _stop_pool(pool)
            raise
        pool.shutdown(wait=True)


def _old_wall(run_dir: Path) -> float | None:
    try:
        return float(json.loads((run_dir / "run.json").read_text())["wall_s"])
    except (OSError, ValueError, KeyError):
        return None


def _json_default(v):
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(type(v))


# ============================================================================ tidy results

def scalar_metrics(summary: dict) -> list[tuple[str, float | None]]:
    """The scalar metrics of a ``summary.json``: numbers (dicts of numbers flattened as ``a.b``), lists of
    numbers with one entry per node as ``name[i]``; per-tick series and identity fields are left out."""
    out: list[tuple[str, float | None]] = []
    n = summary.get("n_sensors")

    def is_num(v) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    def walk(prefix: str, v) -> None:
        if v is None or is_num(v):
            out.append((prefix, None if v is None else float(v)))
        elif isinstance(v, bool):
            out.append((prefix, float(v)))
        elif isinstance(v, dict):
            for k in sorted(v):
                walk(f"{prefix}.{k}", v[k])
        elif isinstance(v, list) and n is not None and len(v) == n and prefix.startswith("per_node"):
            for i, x in enumerate(v):
                out.append((f"{prefix}[{i}]", float(x) if is_num(x) else None))

    for k in sorted(summary):
        if k not in IDENTITY_FIELDS:
            walk(k, summary[k])
    return out


def collect_rows(axes: list[Axis], specs: list[RunSpec], runs_dir: Path, results: dict) -> list[dict]:
    rows: list[dict] = []
    for r in specs:
        res = results[r.run_id]
        base = {a.key: value_repr(v) for a, v in zip(axes, r.cell)}
        base.update(seed=r.seed, run_id=r.run_id)
        summary = None
        if res["status"] == "ok":
            try:
                summary = json.loads((runs_dir / r.run_id / "summary.json").read_text())
            except (OSError, ValueError) as exc:
                res.update(status="failed", error=f"cannot read summary.json ({exc})")
        if summary is None:
            rows.append({**base, "status": "failed", "metric": "", "value": "", "error": res.get("error", "")})
            continue
        for name, v in scalar_metrics(summary):
            rows.append({**base, "status": "ok", "metric": name, "value": "" if v is None or not math.isfinite(v)
                         else repr(v), "error": ""})
    return rows


def _columns(axes: list[Axis]) -> list[str]:
    return [a.key for a in axes] + CSV_FIXED


def write_results_csv(path: Path, axes: list[Axis], rows: list[dict]) -> None:
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=_columns(axes))
        w.writeheader()
        w.writerows(rows)


def read_results_csv(path: str | Path) -> list[dict]:
    with Path(path).open(newline="") as f:
        return list(csv.DictReader(f))


def aggregate(axes: list[Axis], rows: list[dict]) -> list[dict]:
    """Per (cell, metric): n, failed, mean with bootstrap 95 % CI, std, median, 10 % and 90 % quantiles."""
    from dashboards.confidence import mean_ci

    keys = [a.key for a in axes]
    groups: dict[tuple, list[float]] = {}
    failed: dict[tuple, int] = {}
    order: list[tuple] = []
    cells_seen: list[tuple] = []
    for row in rows:
        cell = tuple(row[k] for k in keys)
        if cell not in cells_seen:
            cells_seen.append(cell)
        if row["status"] != "ok":
            failed[cell] = failed.get(cell, 0) + 1
            continue
        g = cell + (row["metric"],)
        if g not in groups:
            groups[g] = []
            order.append(g)
        if row["value"] != "":
            groups[g].append(float(row["value"]))
    out = []
    for g in order:
        v = np.asarray(groups[g], float)
        m, lo, hi = mean_ci(v)
        rec = dict(zip(keys, g[:-1]))
        rec.update(metric=g[-1], n=int(v.size), failed=failed.get(g[:-1], 0), mean=m, ci95_lo=lo, ci95_hi=hi,
                   std=float(v.std(ddof=1)) if v.size > 1 else float("nan"),
                   median=float(np.median(v)) if v.size else float("nan"),
                   p10=float(np.percentile(v, 10)) if v.size else float("nan"),
                   p90=float(np.percentile(v, 90)) if v.size else float("nan"))
        out.append(rec)
    for cell in cells_seen:  # a cell where every run failed still gets a line
        if not any(tuple(rec[k] for k in keys) == cell for rec in out):
            out.append({**dict(zip(keys, cell)), "metric": "", "n": 0, "failed": failed.get(cell, 0)})
    return out


def write_summary_csv(path: Path, axes: list[Axis], rows: list[dict]) -> list[dict]:
    agg = aggregate(axes, rows)
    cols = [a.key for a in axes] + ["metric", "n", "failed", "mean", "ci95_lo", "ci95_hi", "std", "median", "p10",
                                    "p90"]
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=cols)
        w.writeheader()
        for rec in agg:
            w.writerow({c: (_fmt_num(rec[c]) if isinstance(rec.get(c), float) else rec.get(c, "")) for c in cols})
    return agg


def _fmt_num(v: float) -> str:
    return "" if not math.isfinite(v) else f"{v:.6g}"


# ============================================================================ figures

def _read_columns(path: Path, names: list[str]) -> dict[str, np.ndarray]:
    with path.open(newline="") as f:
        rd = csv.DictReader(f)
        cols: dict[str, list[float]] = {n: [] for n in names}
        for row in rd:
            for n in names:
                s = row.get(n, "")
                cols[n].append(float(s) if s not in ("", None) else math.nan)
    return {n: np.asarray(v, float) for n, v in cols.items()}


def _x_axis(axes: list[Axis]) -> int | None:
    """The axis figures put on x / colour the trace lines by: the first numeric one, else the first."""
    for i, a in enumerate(axes):
        if a.numeric and len(a.values) > 1:
            return i
    return 0 if axes else None


def _cell_label(axes: list[Axis], idx: list[int], cell: tuple) -> str:
    return ", ".join(f"{axes[i].label}={value_repr(cell[i])}" for i in idx)


def make_figures(out: Path, axes: list[Axis], specs: list[RunSpec], results: dict) -> list[Path]:
    """``figures/traces_<col>.png`` (error vs time) and ``figures/<metric>_vs_<key>.png``."""
    from dashboards import sweep_plots as sp

    out = Path(out)
    fig_dir = out / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    runs_dir = out / "runs"
    ok = [r for r in specs if results[r.run_id]["status"] == "ok"]
    if not ok:
        return []
    xi = _x_axis(axes)
    others = [i for i in range(len(axes)) if i != xi]
    scen = _scenario_name(runs_dir / ok[0].run_id)
    written: list[Path] = []

    # --- error traces: one panel per combination of the other keys, one line per value of the x key
    by_cell: dict[tuple, list[RunSpec]] = {}
    for r in ok:
        by_cell.setdefault(_hkey(r.cell), []).append(r)
    series = {r.run_id: _read_columns(runs_dir / r.run_id / "metrics.csv", ["t", *TRACE_COLUMNS]) for r in ok}
    for col, ylabel in TRACE_COLUMNS.items():
        panels: dict[tuple, sp.Panel] = {}
        for rs in by_cell.values():
            cell = rs[0].cell
            pkey = _hkey(cell[i] for i in others)
            panel = panels.setdefault(pkey, sp.Panel(_cell_label(axes, others, cell) or scen))
            length = max(series[r.run_id][col].size for r in rs)
            Y = np.full((len(rs), length), np.nan)
            for j, r in enumerate(rs):
                y = series[r.run_id][col]
                Y[j, : y.size] = y
            longest = max(rs, key=lambda r: series[r.run_id]["t"].size)
            t = series[longest.run_id]["t"]
            if np.isnan(t).all():
                t = np.arange(length, dtype=float)
            label = _cell_label(axes, [xi], cell) if xi is not None else "all seeds"
            value = cell[xi] if xi is not None and axes[xi].numeric else None
            panel.traces.append(sp.Trace(label, t, Y, value))
        if all(np.isnan(tr.Y).all() for p in panels.values() for tr in p.traces):
            continue
        written.append(sp.error_traces(list(panels.values()), fig_dir / f"traces_{col}.png", ylabel=ylabel,
                                       title=f"{scen}: {ylabel} over time"))

    # --- scalar metrics against the x key, one line per combination of the other keys
    if xi is not None:
        ax_x = axes[xi]
        vals: dict[tuple[str, str, tuple], list[float]] = {}
        for r in ok:
            summary = json.loads((runs_dir / r.run_id / "summary.json").read_text())
            sm = dict(scalar_metrics(summary))
            for m in FIGURE_METRICS:
                if sm.get(m) is not None:
                    vals.setdefault((m, value_repr(r.cell[xi]), _hkey(r.cell[i] for i in others)), []).append(sm[m])
        for m in FIGURE_METRICS:
            keys = [k for k in vals if k[0] == m]
            if not keys:
                continue
            groups: dict[tuple, sp.Series] = {}
            for xv in ax_x.values:
                for cell in itertools.product(*(axes[i].values for i in others)) if others else [()]:
                    v = vals.get((m, value_repr(xv), _hkey(cell)))
                    if v is None:
                        continue
                    label = ", ".join(f"{axes[i].label}={value_repr(c)}" for i, c in zip(others, cell))
                    s = groups.setdefault(_hkey(cell), sp.Series(label, [], []))
                    s.x.append(xv if ax_x.numeric else value_repr(xv))
                    s.values.append(np.asarray(v, float))
            written.append(sp.metric_vs_param(list(groups.values()), fig_dir / f"{m}_vs_{_slug(ax_x.label)}.png",
                                              xlabel=ax_x.label if ax_x.label == ax_x.key
                                              else f"{ax_x.label} ({ax_x.key})",
                                              ylabel=m, title=f"{scen}: {m} vs {ax_x.label}",
                                              categorical=not ax_x.numeric))
    return written


def _hkey(values) -> tuple[str, ...]:
    """A hashable key for grid values (arrays are lists)."""
    return tuple(value_repr(v) for v in values)


def _scenario_name(run_dir: Path) -> str:
    try:
        return json.loads((run_dir / "summary.json").read_text()).get("scenario", "")
    except (OSError, ValueError):
        return ""


# ============================================================================ CLI

def _seeds(text: str) -> list[int]:
    """``S`` → 0 … S−1."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seeds, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError("need at least one seed")
    return list(range(n))


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_scenario_argument(p)
    p.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2,...",
                   help="a grid axis (repeatable): a dotted scenario key or a shorthand "
                        f"({', '.join(f'{k}={v}' for k, v in SHORTHANDS.items())}) and its TOML values")
    p.add_argument("--seeds", type=_seeds, default=list(range(10)), metavar="S",
                   help="run seeds 0 … S−1 for every cell (default 10)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override a scenario key for every run")
    p.add_argument("--ticks", type=int, help="override run.ticks for every run")
    p.add_argument("--jobs", type=int, help="worker processes (default: os.cpu_count())")
    p.add_argument("--no-resume", action="store_true", help="recompute runs that are already done")
    p.add_argument("--no-figures", action="store_true", help="skip DIR/figures/")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--out", required=True, help="output directory (re-use it to resume)")


def config_from_args(args: argparse.Namespace) -> SweepConfig:
    return SweepConfig(scenario=args.scenario, axes=[parse_grid(g) for g in args.grid], seeds=args.seeds,
                       out=Path(args.out), sets=list(args.set or []), ticks=args.ticks, jobs=args.jobs,
                       resume=not args.no_resume, figures=not args.no_figures, progress=not args.quiet)


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run the sweep; ScenarioError (bad grid) propagates to the CLI, which prints it and exits 2."""
    from .extras import has, install_line

    if not args.no_figures and not has("matplotlib"):   # say so before the runs, not after them
        print(f"error: the sweep's figures need matplotlib: {install_line('figures')} (or give --no-figures)",
              file=sys.stderr)
        return 2
    cfg = config_from_args(args)

    def on_term(_signum, _frame):
        raise KeyboardInterrupt

    old_term = signal.signal(signal.SIGTERM, on_term)  # SIGTERM stops the workers too, like Ctrl-C
    try:
        meta = run_sweep(cfg)
    except KeyboardInterrupt:
        print(f"\nsweep interrupted; finished runs are kept in {cfg.out}/runs/ — run the same command again to "
              f"resume", file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, old_term)
    out = Path(cfg.out)
    print(f"sweep {cfg.scenario}: {meta['ok']}/{meta['runs']} runs ok"
          + (f", {meta['failed']} failed (see {out}/sweep.json)" if meta["failed"] else "")
          + (f", {meta['resumed']} resumed" if meta["resumed"] else "")
          + f" in {meta['wall_s']:.1f} s; wrote {out}/results.csv, summary.csv, sweep.json"
          + (f", {len(meta['figures'])} figures in {out}/figures/" if meta["figures"] else ""))
    return 1 if meta["failed"] else 0


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``sweep`` sub-command to the ``flocktrack`` CLI (``experiment.register(sub)``)."""
    p = subparsers.add_parser("sweep", help="run a scenario over a grid of overrides × seeds, in parallel",
                              description=__doc__.split("\n\n")[0])
    add_arguments(p)
    p.set_defaults(fn=cmd_sweep)
    return p


def main(argv: list[str] | None = None) -> int:
    """``python -m flocktrack.experiment SCENARIO …`` (the same as ``flocktrack sweep``)."""
    ap = argparse.ArgumentParser(prog="flocktrack sweep", description=__doc__.split("\n\n")[0])
    add_arguments(ap)
    args = ap.parse_args(argv)
    try:
        return cmd_sweep(args)
    except ScenarioError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
