"""Where a sweep's runs execute: the :class:`Executor` interface and its local implementation.

The sweep (:mod:`flocktrack.experiment.sweep`) plans the runs, triages what is done, and writes the CSVs and
figures; an executor only runs tasks and hands each result back as it arrives. Every executor leaves a
finished run in ``runs/<run_id>/`` (whole or not at all) before it reports it, so the sweep reads the same
files whoever ran them.

* :class:`PoolExecutor` (``--executor local``): a ``ProcessPoolExecutor`` of ``--jobs`` processes on this
  machine, each writing its run directly to the sweep's disk (:func:`flocktrack.experiment.runs.execute_run`);
  one run or one job runs in this process.
* :class:`flocktrack.experiment.dask_executor.DaskExecutor` (``--executor dask``): a Dask cluster, local or
  remote; the runs come back as data.
"""

from __future__ import annotations

import multiprocessing as mp
import signal
from collections.abc import Callable
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Protocol

from .runs import execute_run


class ExecutorError(Exception):
    """An executor cannot start (an unreachable scheduler, a worker with another flocktrack): one line."""


class Executor(Protocol):
    """Runs a sweep's tasks and calls ``on_result`` with each run's result, in the sweep's thread."""

    #: how many runs go at once (the progress bar's "running")
    slots: int
    #: a link to watch the runs (the Dask dashboard), or None
    dashboard: str | None

    def describe(self, n_tasks: int) -> str:
        """Where the runs go, for the sweep's first line: ``"2 processes"``, ``"Dask … (4 workers)"``."""

    def run(self, tasks: list[dict], on_result: Callable[[dict], None]) -> None:
        """Run every task; a run that fails is a result (``status`` failed), never an exception."""

    def info(self) -> dict:
        """What ``sweep.json`` records about the executor."""

    def close(self) -> None:
        """Release what the executor started (processes, clusters)."""


class PoolExecutor:
    """``--jobs`` processes on this machine (spawned: the parent may run rich's refresh thread, and forking a
    threaded process can leave a lock held in the child)."""

    dashboard = None

    def __init__(self, jobs: int):
        self.jobs = self.slots = max(1, jobs)

    def describe(self, n_tasks: int) -> str:
        return f"{min(self.jobs, max(n_tasks, 1))} processes"

    def info(self) -> dict:
        return {"kind": "local", "jobs": self.jobs}

    def run(self, tasks: list[dict], on_result: Callable[[dict], None]) -> None:
        if self.jobs == 1 or len(tasks) <= 1:
            for task in tasks:
                on_result(execute_run(task))
            return
        pending = list(tasks)
        while pending:  # a worker killed by the OS breaks the pool: record its runs, start a new pool for the rest
            pool = ProcessPoolExecutor(max_workers=min(self.jobs, len(pending)), mp_context=mp.get_context("spawn"),
                                       initializer=_worker_init)
            try:
                pending = _drain(pool, pending, on_result)
            except BaseException:  # Ctrl-C / SIGTERM: stop now; finished runs are kept, the rest resumes next time
                _stop_pool(pool)
                raise
            pool.shutdown(wait=True)

    def close(self) -> None:
        pass


def _drain(pool: ProcessPoolExecutor, tasks: list[dict], on_result: Callable[[dict], None]) -> list[dict]:
    """Run ``tasks`` on ``pool``; the tasks to run again on a new pool when this one broke."""
    futs = {pool.submit(execute_run, t): t for t in tasks}
    again: list[dict] = []
    broken = False
    not_done = set(futs)
    while not_done:
        done, not_done = wait(not_done, return_when=FIRST_COMPLETED)
        for f in done:
            t = futs[f]
            try:
                res = f.result()
            except BrokenProcessPool:
                if broken:
                    again.append(t)
                    continue
                broken = True
                res = {"run_id": t["run_id"], "status": "failed", "wall_s": 0.0,
                       "error": "a worker process died (killed, out of memory) during this or a concurrent run"}
            except Exception as exc:
                res = {"run_id": t["run_id"], "status": "failed", "wall_s": 0.0, "error": f"{type(exc).__name__}: {exc}"}
            on_result(res)
    return again


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
