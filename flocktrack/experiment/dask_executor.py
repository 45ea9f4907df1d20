"""Sweeps on a Dask cluster (``flocktrack sweep … --executor dask``): a :class:`distributed.LocalCluster` of
``--jobs`` single-threaded worker processes, or an existing cluster's scheduler (``--scheduler ADDRESS``).

A worker need not share the sweep's disk: it runs each task into a temporary directory of its own
(:func:`run_on_worker`) and returns the run as data — its result and every file of the run directory as
bytes — which the sweep writes to ``runs/<run_id>/`` atomically (:func:`flocktrack.experiment.runs.install_run`).
A run's recording stays on the worker (``WORKER_DIR/<sweep>/<run_id>/recording.mcap``, ``WORKER_DIR`` the
worker's temporary directory + ``flocktrack-sweeps`` unless ``--worker-dir`` says otherwise), its host and
path in ``runs/<run_id>/recording.json``; ``--fetch-recordings`` ships it back instead.

Faults are Dask's to handle, not ours: a run that raises is tried again ``--retries`` times
(``Client.submit(retries=…)``), and a run whose worker dies is moved to another worker until it has killed
``allowed-failures`` + 1 of them — set to ``--retries`` for the cluster this module starts; an existing
scheduler keeps its own ``distributed.scheduler.allowed-failures``. The sweep takes each run's first result
only, so a run directory is written once however often the run was tried.

At the start every worker must run this client's flocktrack version (:func:`version_problems`): a worker
without flocktrack, or with another version, would compute other numbers or none.
"""

from __future__ import annotations

import importlib.metadata
import json
import logging
import os
import shutil
import socket
import tempfile
import time
import traceback
import uuid
from collections.abc import Callable
from pathlib import Path

from flocktrack.extras import has, require

from .executors import ExecutorError
from .runs import RECORDING, failure, install_run, read_files, run_into


class RunError(Exception):
    """A run that raised on a worker: its message and traceback as text (so it unpickles anywhere)."""

    def __init__(self, error: str, tb: str):
        super().__init__(error, tb)
        self.error, self.tb = error, tb

    def __str__(self) -> str:
        return self.error


def worker_base(worker_dir: str | None, sweep: str) -> Path:
    """Where a worker keeps a sweep's runs: ``WORKER_DIR/<sweep>`` (default: its temporary directory +
    ``flocktrack-sweeps``), resolved on the worker."""
    return Path(worker_dir or Path(tempfile.gettempdir()) / "flocktrack-sweeps") / sweep


def run_on_worker(task: dict, *, sweep: str, worker_dir: str | None = None, fetch_recording: bool = False) -> dict:
    """One run on a Dask worker, into its own disk; the result with the run's files as bytes (``files``) and
    where its recording stays (``recording``: host, path, bytes) unless it is shipped among the files.
    Raises :class:`RunError` when the run fails (Dask then retries it)."""
    base = worker_base(worker_dir, sweep)
    tmp = base / f".{task['run_id']}.tmp"
    t0 = time.perf_counter()
    try:
        if tmp.exists():
            shutil.rmtree(tmp)   # an attempt on a worker that died
        info = run_into(task, tmp)
        files = read_files(tmp, skip=() if fetch_recording else (RECORDING,))
        recording = None
        if (tmp / RECORDING).exists() and not fetch_recording:
            keep = base / task["run_id"]
            keep.mkdir(parents=True, exist_ok=True)
            os.replace(tmp / RECORDING, keep / RECORDING)
            recording = {"host": socket.gethostname(), "path": str(keep / RECORDING),
                         "bytes": (keep / RECORDING).stat().st_size}
        shutil.rmtree(tmp)
        return {"run_id": task["run_id"], "status": "ok", "wall_s": info["wall_s"], "host": socket.gethostname(),
                "files": files, "recording": recording}
    except Exception as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        rec = failure(task["run_id"], exc, time.perf_counter() - t0)
        raise RunError(rec["error"], rec["traceback"]) from None


def version_problems(mine: str, workers: dict[str, object]) -> list[str]:
    """One line per worker whose flocktrack (a version string, or the exception its look-up raised) is not
    ``mine``."""
    out = []
    for addr, v in sorted(workers.items()):
        if isinstance(v, BaseException) or not isinstance(v, str):
            out.append(f"worker {addr} has no flocktrack installed (this client runs {mine})")
        elif v != mine:
            out.append(f"worker {addr} runs flocktrack {v}, this client {mine}")
    return out


class DaskExecutor:
    """The runs of a sweep on a Dask cluster (module doc); one client, and the cluster when it started one."""

    def __init__(self, *, scheduler: str | None, jobs: int, sweep: str, retries: int = 2, timeout: float = 10.0,
                 worker_dir: str | None = None, fetch_recordings: bool = False):
        distributed = require("distributed")
        self.scheduler, self.retries, self.sweep = scheduler, retries, sweep
        self.worker_dir, self.fetch = worker_dir, fetch_recordings
        self.cluster = None
        if scheduler:
            try:
                self.client = distributed.Client(scheduler, timeout=timeout, set_as_default=False)
            except OSError:
                raise ExecutorError(f"cannot reach the Dask scheduler at {scheduler} within {timeout:g} s "
                                    f"(is `dask scheduler` running there? --scheduler-timeout waits longer)") from None
        else:
            self.cluster = _local_cluster(distributed, jobs, retries)
            self.client = distributed.Client(self.cluster, set_as_default=False)
        self.address = self.client.scheduler.address
        try:
            self._check_workers(timeout)
        except BaseException:
            self.close()
            raise
        workers = self.client.scheduler_info()["workers"].values()
        self.n_workers = len(workers)
        self.slots = max(1, sum(w.get("nthreads", 1) for w in workers))
        # (a local cluster without bokeh serves only a page that asks for it: no link then)
        self.dashboard = (self.client.dashboard_link or None) if scheduler or has("bokeh") else None

    def _check_workers(self, timeout: float) -> None:
        from flocktrack import __version__

        try:
            self.client.wait_for_workers(1, timeout=timeout)
        except TimeoutError:
            raise ExecutorError(f"the Dask scheduler at {self.address} has no worker "
                                f"(waited {timeout:g} s)") from None
        versions = self.client.run(importlib.metadata.version, "flocktrack", on_error="return")
        bad = version_problems(__version__, versions)
        if bad:
            raise ExecutorError("; ".join(bad) + " — install the same flocktrack on every worker")

    def describe(self, n_tasks: int) -> str:
        where = "a local Dask cluster" if self.cluster is not None else f"the Dask cluster at {self.scheduler}"
        return f"{where} ({self.n_workers} workers, {self.slots} threads)"

    def info(self) -> dict:
        return {"kind": "dask", "scheduler": self.address, "workers": self.n_workers, "threads": self.slots,
                "retries": self.retries, "fetch_recordings": self.fetch, "worker_dir": self.worker_dir}

    def run(self, tasks: list[dict], on_result: Callable[[dict], None]) -> None:
        from distributed import as_completed

        futs = {self.client.submit(run_on_worker, t, sweep=self.sweep, worker_dir=self.worker_dir,
                                   fetch_recording=self.fetch, key=f"flocktrack-run-{t['run_id']}-{uuid.uuid4().hex[:8]}",
                                   pure=False, retries=self.retries): t for t in tasks}
        seen: set[str] = set()
        try:
            for fut in as_completed(futs, loop=self.client.loop):
                task = futs[fut]
                if task["run_id"] not in seen:   # the first result of a run is its result
                    seen.add(task["run_id"])
                    on_result(self._collect(fut, task))
                fut.release()
        except BaseException:   # Ctrl-C: drop what is queued; finished runs are written, the rest resumes
            self.client.cancel(list(futs))
            raise

    def _collect(self, fut, task: dict) -> dict:
        """A finished future's result, its run written to the sweep's disk; or the run's failure record."""
        if fut.status == "finished":
            res = fut.result()
            files = res.pop("files")
            if res.get("recording"):
                files["recording.json"] = (json.dumps(res["recording"], indent=2) + "\n").encode()
            try:
                install_run(Path(task["dir"]), files)
            except OSError as exc:
                return failure(task["run_id"], exc, res["wall_s"])
            return res
        exc = fut.exception()
        tries = f"{self.retries + 1} tries"
        if isinstance(exc, RunError):
            return {"run_id": task["run_id"], "status": "failed", "wall_s": 0.0, "error": f"{exc.error} ({tries})",
                    "traceback": exc.tb}
        what = type(exc).__name__
        if what == "KilledWorker":
            msg = f"the worker running it died each time it was tried (killed, out of memory): {exc}"
        else:
            msg = f"{what}: {exc}"
        return {"run_id": task["run_id"], "status": "failed", "wall_s": 0.0, "error": msg,
                "traceback": "".join(traceback.format_tb(fut.traceback()))}

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


#: Dask's defaults cost these runs about a fifth of their speed: glibc told to give memory back at every
#: 64 KiB freed (``MALLOC_TRIM_THRESHOLD_``, for workers that hold data between tasks; a run holds little)
#: and a statistical profiler sampling the running task every 10 ms. The cluster this module starts runs
#: without them; docs/sweeps.md says how to do the same for workers of one's own.
WORKER_CONFIG = {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                 "distributed.worker.profile.enabled": False}


def _local_cluster(distributed, jobs: int, retries: int):
    """``jobs`` single-threaded worker processes on this machine; the dashboard on a free port, or none when it
    cannot bind. A run may kill ``retries`` + 1 workers before it counts as failed. :data:`WORKER_CONFIG`
    makes the workers as fast as the local pool's processes."""
    import dask

    kw = {"n_workers": jobs, "threads_per_worker": 1, "processes": True, "silence_logs": logging.ERROR}
    with dask.config.set({**WORKER_CONFIG, "distributed.scheduler.allowed-failures": retries}):
        try:
            return distributed.LocalCluster(dashboard_address=":0", **kw)
        except OSError:
            return distributed.LocalCluster(dashboard_address=None, **kw)
