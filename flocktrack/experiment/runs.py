"""One run of a sweep, wherever it executes: run a task into a directory, turn an exception into a failure
record, and put a finished run in place atomically.

A task is ``{"run_id", "dir", "data", "source", "transport"}``: the resolved scenario mapping and where its
run directory goes on the sweep's disk. ``transport`` ``inproc`` runs the in-process engine in this process
(:func:`flocktrack.engine.run.run_inproc_to_dir`); ``zenoh`` runs the lockstep run over Zenoh
(:func:`flocktrack.engine.run.run_zenoh_to_dir`: a process per node around its own router, on a free port the
kernel picks, so runs side by side on one host do not collide) in a child process of its own — the launcher
installs signal handlers and supervises its children, which it can do only from a main thread, and a Dask
worker runs tasks in a thread.

``python -m flocktrack.experiment.runs < TASK.json`` is that child: it runs the task over Zenoh into the
directory named by the task's ``tmp`` and exits non-zero when the run did not end well.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
import traceback
from pathlib import Path

from agent.scenario import ScenarioError, parse_scenario

TRANSPORTS = ("inproc", "zenoh")
RECORDING = "recording.mcap"


def failure(run_id: str, exc: BaseException, wall_s: float) -> dict:
    """The failure record of a run that raised (the scenario's own message for a scenario error)."""
    msg = str(exc) if isinstance(exc, ScenarioError) else f"{type(exc).__name__}: {exc}"
    return {"run_id": run_id, "status": "failed", "error": msg, "wall_s": wall_s,
            "traceback": traceback.format_exc(limit=6)}


def run_into(task: dict, out: Path) -> dict:
    """Run the task into ``out`` (a fresh directory); its run info (``run.json``). Raises when the run fails."""
    if task.get("transport", "inproc") == "zenoh":
        return _run_zenoh_child(task, out)
    from flocktrack.engine.run import run_inproc_to_dir

    sc = parse_scenario(task["data"], task["source"])
    _, info = run_inproc_to_dir(sc, task["data"], out)
    return info


def _run_zenoh_child(task: dict, out: Path) -> dict:
    from flocktrack.launch.forkserver import die_with_parent

    parse_scenario(task["data"], task["source"])      # a bad scenario fails here, with its own message
    out.mkdir(parents=True, exist_ok=True)
    child = {"data": task["data"], "source": task["source"], "tmp": str(out)}
    proc = subprocess.run([sys.executable, "-m", "flocktrack.experiment.runs"], input=json.dumps(child),
                          capture_output=True, text=True, preexec_fn=die_with_parent)
    if proc.returncode != 0:
        tail = "\n".join((proc.stdout + proc.stderr).strip().splitlines()[-20:])
        raise RuntimeError(f"the Zenoh run exited with {proc.returncode}:\n{tail}")
    return json.loads((out / "run.json").read_text())


def replace_dir(tmp: Path, final: Path) -> None:
    """Put a complete run directory in place: ``runs/.<id>.tmp`` → ``runs/<id>`` (a finished run is whole)."""
    if final.exists():
        shutil.rmtree(final)
    os.replace(tmp, final)


def execute_run(task: dict) -> dict:
    """One run on the sweep's own disk (the local executor): run into ``runs/.<id>.tmp``, rename when complete.
    Returns ``{"run_id", "status", "wall_s"}`` or a failure record — a failing cell never aborts a sweep."""
    final = Path(task["dir"])
    tmp = final.parent / f".{final.name}.tmp"
    t0 = time.perf_counter()
    try:
        if tmp.exists():
            shutil.rmtree(tmp)
        info = run_into(task, tmp)
        replace_dir(tmp, final)
        return {"run_id": task["run_id"], "status": "ok", "wall_s": info["wall_s"]}
    except Exception as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        return failure(task["run_id"], exc, time.perf_counter() - t0)


def install_run(final: Path, files: dict[str, bytes]) -> None:
    """Write a run that came back as data (``{relative path: bytes}``) to ``final``, atomically like
    :func:`execute_run` (a ``.tmp`` sibling, then a rename)."""
    tmp = final.parent / f".{final.name}.tmp"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    for rel, blob in files.items():
        if Path(rel).is_absolute() or ".." in Path(rel).parts:
            raise ValueError(f"a run file outside its directory: {rel!r}")
        (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp / rel).write_bytes(blob)
    replace_dir(tmp, final)


def read_files(run_dir: Path, *, skip: tuple[str, ...] = ()) -> dict[str, bytes]:
    """Every file under ``run_dir`` as ``{relative path: bytes}``, but those named in ``skip``."""
    return {str(p.relative_to(run_dir)): p.read_bytes() for p in sorted(run_dir.rglob("*"))
            if p.is_file() and str(p.relative_to(run_dir)) not in skip}


def main() -> int:
    """The Zenoh child (module doc): the task on stdin, the run in its ``tmp``; exit 0 when it ended well."""
    from flocktrack.engine.run import run_zenoh_to_dir

    task = json.loads(sys.stdin.read())
    sc = parse_scenario(task["data"], task["source"])
    _, info = run_zenoh_to_dir(sc, task["data"], Path(task["tmp"]), quiet=True)
    if info.get("rc") != 0 or not info.get("recording_complete", True):
        print(f"the run ended with rc={info.get('rc')} (recording complete: {info.get('recording_complete')})",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
