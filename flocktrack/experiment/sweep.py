"""Experiment sweeps: a scenario × a grid of overrides × seeds, in parallel, into one tidy CSV and figures.

    flocktrack sweep SCENARIO --grid KEY=V1,V2,... [--grid ...] [--seeds S] [--set KEY=V ...]
                              [--ticks N] [--jobs J] [--no-resume] [--no-figures] --out DIR
                              [--transport inproc|zenoh] [--executor local|dask [--scheduler ADDRESS]
                               [--retries N] [--worker-dir DIR] [--fetch-recordings]]

* ``--grid KEY=V1,V2,…`` (repeatable): ``KEY`` is a dotted scenario key ``section.key`` (or a shorthand:
  ``estimator`` → ``estimator.name``, ``rounds`` → ``estimator.rounds``, ``range`` → ``topology.range``,
  ``link_loss`` → ``faults.link_loss``, ``ticks`` → ``run.ticks``); the values are TOML values (numbers,
  strings — bare words are strings —, booleans, arrays: ``--grid 'sensors.origin=[0,0],[5,5]'``). ``seed``
  is reserved: ``--seeds S`` runs seeds 0 … S−1 (``run.seed``) for every cell of the Cartesian product.
* Every run is the in-process engine (:func:`flocktrack.engine.run.run_inproc_to_dir`, the same numbers as a
  lockstep run over Zenoh) or, with ``--transport zenoh``, that lockstep run over Zenoh
  (:mod:`flocktrack.experiment.runs`), in ``DIR/runs/<run_id>/``. ``--executor local`` (the default) runs
  them on a ``ProcessPoolExecutor`` of ``--jobs`` workers (default ``os.cpu_count()``), ``--executor dask``
  on a Dask cluster (:mod:`flocktrack.experiment.dask_executor`); a rich progress bar on a terminal, plain
  lines otherwise.
* Every cell is validated before anything runs. A grid key the scenario schema does not know (or a
  ``--set`` that breaks every cell) stops the sweep at once with the scenario's error; a cell whose
  *value* is invalid, or a run that raises, is reported and recorded as failed, and the sweep goes on.
* Resumable: a run is written to ``runs/.<run_id>.tmp`` and renamed when complete, so a run directory
  with a ``summary.json`` is finished; it is not recomputed unless its resolved scenario changed.
* Output: ``DIR/results.csv`` (tidy: one row per run and metric — the grid keys, ``seed``, ``run_id``,
  ``status``, ``metric``, ``value``, ``error``; the scalar metrics of ``summary.json`` and
  ``per_node_rmse[i]``), ``DIR/summary.csv`` (per cell and metric: n, mean, bootstrap 95 % CI, std,
  median, 10/90 % quantiles), ``DIR/consistency.csv`` (per cell: the Monte-Carlo ANEES over the seeds and
  its verdict, :mod:`flocktrack.experiment.consistency`), ``DIR/sweep.json`` (grid, seeds, timings, failures,
  executor, each Dask run's host and where its recording stayed) and ``DIR/figures/*.png``
  (:mod:`dashboards.sweep_plots`).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import tomli_w

from agent.scenario import ScenarioError, parse_scenario

from flocktrack.resources import add_scenario_argument

from .executors import Executor, ExecutorError, PoolExecutor
from .grid import SHORTHANDS, Axis, RunSpec, expand, parse_grid
from .consistency import describe, write_consistency_csv
from .results import collect_rows, make_figures, write_results_csv, write_summary_csv


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
    transport: str = "inproc"   #: inproc, or zenoh (the lockstep run over Zenoh)
    executor: str = "local"     #: local (a process pool) or dask
    scheduler: str | None = None  #: dask: an existing cluster's scheduler (default: start a LocalCluster)
    retries: int = 2            #: dask: tries of a run beyond its first
    scheduler_timeout: float = 10.0
    worker_dir: str | None = None  #: dask: where workers keep recordings (default: their temp dir)
    fetch_recordings: bool = False  #: dask: ship recordings back into runs/<id>/


def run_data(cfg: SweepConfig, spec: RunSpec) -> dict:
    """The run's TOML mapping: the scenario, ``--set``, ``--ticks``, then the cell and the seed."""
    from agent.scenario import scenario_data

    named = {"run.ticks": cfg.ticks, "run.seed": spec.seed,
             "run.mode": "lockstep" if cfg.transport == "zenoh" else None}
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

class SweepProgress:
    """A rich progress bar on a terminal, one plain line per finished run otherwise; failures always shown."""

    def __init__(self, total: int, enabled: bool = True, slots: int = 1):
        self.total, self.done, self.failed = total, 0, 0
        self.slots = slots  #: runs at once: "running" is the lesser of it and what is left
        self.enabled = enabled
        self._bar = None
        if enabled and sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                                       TimeRemainingColumn)

            self._bar = Progress(TextColumn("[bold]sweep"), BarColumn(), MofNCompleteColumn(),
                                 TextColumn("{task.fields[failed]}"), TextColumn("{task.fields[running]}"),
                                 TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True),
                                 transient=False)
            self._task = self._bar.add_task("sweep", total=total, failed="",
                                            running=f"{min(slots, total)} running" if total else "")
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
            running = min(self.slots, self.total - self.done)
            self._bar.update(self._task, completed=self.done, running=f"{running} running" if running else "",
                             failed=f"[red]{self.failed} failed" if self.failed else "")
            if not ok and not quiet_ok:
                self.note(f"FAILED {res['run_id']}: {res.get('error')}")
        elif self.enabled and not quiet_ok:
            tail = f"{res['wall_s']:.1f} s" if ok else f"FAILED: {res.get('error')}"
            print(f"sweep [{self.done}/{self.total}] {res['run_id']} {tail}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()


def _is_done(run_dir: Path, data: dict, transport: str) -> str:
    """'' (not done), 'done', or 'stale' (finished with a different resolved scenario or transport)."""
    if not (run_dir / "summary.json").exists():
        return ""
    try:
        same = ((run_dir / "scenario.toml").read_text() == tomli_w.dumps(data)
                and json.loads((run_dir / "run.json").read_text()).get("transport", "inproc") == transport)
    except (OSError, ValueError):
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
        state = _is_done(runs_dir / r.run_id, data, cfg.transport) if cfg.resume else ""
        if state == "done":
            skipped += 1
            results[r.run_id] = {"run_id": r.run_id, "status": "ok", "wall_s": _old_wall(runs_dir / r.run_id),
                                 "resumed": True}
            continue
        stale += state == "stale"
        tasks.append({"run_id": r.run_id, "dir": str(runs_dir / r.run_id), "data": data, "source": cfg.scenario,
                      "transport": cfg.transport})
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
    executor = make_executor(cfg, jobs) if tasks else PoolExecutor(jobs)  # (no cluster for nothing to run)
    prog = SweepProgress(len(specs), cfg.progress, slots=executor.slots)
    n_cells = len({r.cell_index for r in specs})
    prog.note(f"sweep {cfg.scenario}: {n_cells} cells × {len(cfg.seeds)} seeds = {len(specs)} runs, "
              f"{len(tasks)} to run on {executor.describe(len(tasks))}"
              + (f", {skipped} already done" if skipped else "") + (f", {stale} stale (re-run)" if stale else "")
              + (f", {len(cell_errors)} invalid cells" if cell_errors else ""))
    if executor.dashboard:
        prog.note(f"Dask dashboard: {executor.dashboard}")
    for ci, err in sorted(cell_errors.items()):
        prog.note(f"invalid cell {ci}: {err}")
    for rid in results:  # already done (resumed) or invalid before running
        prog.advance(results[rid], quiet_ok=True)

    def on_result(res: dict) -> None:
        results[res["run_id"]] = res
        prog.advance(res)

    try:
        executor.run(tasks, on_result)
    finally:
        prog.close()
        executor.close()

    wall = time.perf_counter() - t0
    rows = collect_rows(cfg.axes, specs, runs_dir, results)
    write_results_csv(out / "results.csv", cfg.axes, rows)
    write_summary_csv(out / "summary.csv", cfg.axes, rows)
    consistency = write_consistency_csv(out / "consistency.csv", cfg.axes, rows)
    figures: list[str] = []
    fig_error = None
    if cfg.figures:
        try:
            figures = [str(p.relative_to(out)) for p in make_figures(out, cfg.axes, specs, results)]
        except Exception as exc:  # figures are a view; never lose the CSV to a plotting problem
            fig_error = f"{type(exc).__name__}: {exc}"
            prog.note(f"figures failed: {fig_error}")
    meta = _sweep_meta(cfg, specs, results, jobs=jobs, skipped=skipped, stale=stale, executed=len(tasks),
                       started=started, wall=wall)
    meta.update(figures=figures, figures_error=fig_error, executor=executor.info() | {"kind": cfg.executor},
                consistency=consistency)
    if consistency:
        meta["outputs"]["consistency"] = "consistency.csv"
    (out / "sweep.json").write_text(json.dumps(meta, indent=2, default=_json_default) + "\n")
    return meta


def _sweep_meta(cfg: SweepConfig, specs: list, results: dict, *, jobs: int, skipped: int, stale: int,
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
        "transport": cfg.transport,
        "hosts": {r.run_id: results[r.run_id]["host"] for r in specs if results[r.run_id].get("host")},
        "recordings": {r.run_id: results[r.run_id]["recording"] for r in specs if results[r.run_id].get("recording")},
        "figures": [],
        "figures_error": None,
        "outputs": {"results": "results.csv", "summary": "summary.csv", "runs": "runs/", "figures": "figures/"},
    }


def make_executor(cfg: SweepConfig, jobs: int) -> Executor:
    """The executor ``cfg`` asks for: the local pool of ``jobs`` processes, or a Dask cluster."""
    if cfg.executor == "local":
        return PoolExecutor(jobs)
    from .dask_executor import DaskExecutor

    return DaskExecutor(scheduler=cfg.scheduler, jobs=jobs, sweep=Path(cfg.out).resolve().name, retries=cfg.retries,
                        timeout=cfg.scheduler_timeout, worker_dir=cfg.worker_dir,
                        fetch_recordings=cfg.fetch_recordings)


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
    p.add_argument("--jobs", type=int, help="worker processes (default: os.cpu_count()); with --executor dask and "
                                             "no --scheduler, the local cluster's workers")
    p.add_argument("--transport", choices=["inproc", "zenoh"], default="inproc",
                   help="inproc (default): the in-process engine; zenoh: the lockstep run over Zenoh")
    p.add_argument("--executor", choices=["local", "dask"], default="local",
                   help="local (default): a process pool on this machine; dask: a Dask cluster")
    p.add_argument("--scheduler", metavar="ADDRESS", help="dask: a cluster's scheduler (default: a local one)")
    p.add_argument("--scheduler-timeout", type=float, default=10.0, metavar="S",
                   help="dask: how long to wait for the scheduler and a worker (default 10 s)")
    p.add_argument("--retries", type=int, default=2, metavar="N",
                   help="dask: tries of a failed run (or of one whose worker died) beyond its first (default 2)")
    p.add_argument("--worker-dir", metavar="DIR", help="dask: where workers keep recordings (default: their tmp)")
    p.add_argument("--fetch-recordings", action="store_true",
                   help="dask: ship every recording back into runs/<id>/ instead of leaving it on its worker")
    p.add_argument("--no-resume", action="store_true", help="recompute runs that are already done")
    p.add_argument("--no-figures", action="store_true", help="skip DIR/figures/")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--out", required=True, help="output directory (re-use it to resume)")


def config_from_args(args: argparse.Namespace) -> SweepConfig:
    return SweepConfig(scenario=args.scenario, axes=[parse_grid(g) for g in args.grid], seeds=args.seeds,
                       out=Path(args.out), sets=list(args.set or []), ticks=args.ticks, jobs=args.jobs,
                       resume=not args.no_resume, figures=not args.no_figures, progress=not args.quiet,
                       transport=args.transport, executor=args.executor, scheduler=args.scheduler,
                       retries=args.retries, scheduler_timeout=args.scheduler_timeout, worker_dir=args.worker_dir,
                       fetch_recordings=args.fetch_recordings)


def cmd_sweep(args: argparse.Namespace) -> int:
    """Run the sweep; ScenarioError (bad grid) propagates to the CLI, which prints it and exits 2."""
    from flocktrack.extras import has, install_line

    if not args.no_figures and not has("matplotlib"):   # say so before the runs, not after them
        print(f"error: the sweep's figures need matplotlib: {install_line('figures')} (or give --no-figures)",
              file=sys.stderr)
        return 2
    if args.executor == "dask" and not has("distributed"):
        print(f"error: --executor dask needs distributed: {install_line('dask')}", file=sys.stderr)
        return 2
    cfg = config_from_args(args)

    def on_term(_signum, _frame):
        raise KeyboardInterrupt

    old_term = signal.signal(signal.SIGTERM, on_term)  # SIGTERM stops the workers too, like Ctrl-C
    try:
        meta = run_sweep(cfg)
    except ExecutorError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
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
          + (", consistency.csv" if meta.get("consistency") else "")
          + (f", {len(meta['figures'])} figures in {out}/figures/" if meta["figures"] else ""))
    for rec in meta.get("consistency") or []:
        print("  " + describe(rec, cfg.axes))
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
