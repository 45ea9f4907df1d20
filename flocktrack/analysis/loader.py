"""``load``: a run directory (or its recording) as a :class:`Run` of pandas tables.

The recording is read through :func:`agent.recording.read_recording`, the one reader; the scenario comes
from the recording's own metadata, so a recording alone is enough. Input that is not a flocktrack recording
raises :class:`LoadError`, one line naming the file and what is wrong. A recording cut short (its writer
killed) gives the tables of what it holds, with :attr:`Run.complete` False and :attr:`Run.lost_ticks` the
ticks the scenario has beyond those read, and a :class:`TruncatedRecordingWarning` that says so.
"""

from __future__ import annotations

import json
import os
import tomllib
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agent.recording import Recording, read_recording
from agent.scenario import Scenario, ScenarioError, parse_scenario

from flocktrack.extras import require

if TYPE_CHECKING:
    import pandas as pd

#: the first bytes of every MCAP file
MCAP_MAGIC = b"\x89MCAP0\r\n"
RECORDING = "recording.mcap"


class LoadError(ValueError):
    """What was given is not a flocktrack recording (or holds none); the message names the file and why."""


class TruncatedRecordingWarning(UserWarning):
    """The recording was cut short (its writer killed before it closed the file); the tables hold what it kept."""


@dataclass(frozen=True, eq=False)
class Run:
    """A recorded run as tables (pandas DataFrames; simulated time t = k·T in every one):

    * ``ticks`` — a row per tick: the target's true state, the tick's scores (``metrics.csv``'s columns),
      the number of links and of alive sensors;
    * ``estimates`` — a row per tick per sensor: its estimate by component, its error, its P where reported;
    * ``links`` — a row per tick per directed link (src → dst: dst hears src);
    * ``events`` — the world's and the launcher's events, the control requests, the run's end;
    * ``faults`` — the fault schedule and the faults injected live, with the ticks each started and healed.

    ``scenario`` is the parsed scenario of the recording, ``summary`` the run's ``summary.json`` (empty when
    there is none beside the recording, or it is another run's). ``complete`` is False for a recording cut
    short; ``lost_ticks`` then counts the scenario's ticks it does not hold.
    """

    path: Path
    scenario: Scenario
    summary: dict[str, Any]
    ticks: pd.DataFrame = field(repr=False)
    estimates: pd.DataFrame = field(repr=False)
    links: pd.DataFrame = field(repr=False)
    events: pd.DataFrame = field(repr=False)
    faults: pd.DataFrame = field(repr=False)
    complete: bool = True
    lost_ticks: int = 0
    rejected: int = 0   #: messages the tables read that failed validation (left out)

    def tables(self) -> dict[str, pd.DataFrame]:
        """The five tables by name, in the order ``flocktrack export`` writes them."""
        from flocktrack.analysis.tables import TABLES

        return {name: getattr(self, name) for name in TABLES}

    def __repr__(self) -> str:
        state = "complete" if self.complete else f"cut short, {self.lost_ticks} ticks lost"
        return (f"Run({self.scenario.run.name!r}: {len(self.ticks)} ticks, {self.scenario.sensors.n} sensors, "
                f"{self.scenario.estimator.name}, {state}; {self.path})")


def load(run_dir_or_mcap: str | os.PathLike) -> Run:
    """The run at ``run_dir_or_mcap`` — a run directory (its ``recording.mcap``) or a recording file — as a
    :class:`Run`. Raises :class:`LoadError` for a missing path, a directory without a recording, a file that
    is not MCAP, an MCAP file that is not a flocktrack recording; ModuleNotFoundError naming the extra
    (``pip install 'flocktrack[analysis]'``) without pandas. Warns (:class:`TruncatedRecordingWarning`) of a
    recording cut short."""
    require("pandas")
    from flocktrack.analysis.tables import build, needed

    path = recording_path(run_dir_or_mcap)
    rec = read_recording(path, decode=needed)
    sc = _scenario(rec, path)
    tables = build(rec, sc, json.loads(rec.metadata.get("design") or "{}"))
    lost = 0 if rec.complete else max(0, sc.run.ticks - len(tables["ticks"]))
    if not rec.complete:
        warnings.warn(truncated_line(path, sc.run.ticks, lost), TruncatedRecordingWarning, stacklevel=2)
    return Run(path=path, scenario=sc, summary=_summary(path, sc), complete=rec.complete, lost_ticks=lost,
               rejected=rec.rejected, **tables)


def truncated_line(path: Path, ticks: int, lost: int) -> str:
    """The one line about a recording cut short."""
    return (f"{path}: the recording was cut short (its writer stopped before closing it): {lost} of the scenario's "
            f"{ticks} ticks are lost; `flocktrack recover {path}` rewrites what is left as a complete file")


def recording_path(given: str | os.PathLike) -> Path:
    """The MCAP file ``given`` names (a run directory: its ``recording.mcap``), checked to be MCAP."""
    p = Path(given)
    if not p.exists():
        raise LoadError(f"{p}: no such file or directory")
    if p.is_dir():
        if not (p / RECORDING).is_file():
            raise LoadError(f"{p}: a directory without a {RECORDING} (an in-process run records with "
                            f"`flocktrack run … --transport inproc --record`)")
        p = p / RECORDING
    try:
        with open(p, "rb") as f:
            head = f.read(len(MCAP_MAGIC))
    except OSError as exc:
        raise LoadError(f"{p}: cannot read it ({exc.strerror or exc})") from None
    if head != MCAP_MAGIC:
        raise LoadError(f"{p}: not an MCAP file (a flocktrack recording is the recording.mcap of a run directory)")
    return p


def _scenario(rec: Recording, path: Path) -> Scenario:
    """The scenario the recording's metadata holds."""
    text = rec.metadata.get("scenario")
    if text is None:
        raise LoadError(f"{path}: an MCAP file, but not a flocktrack recording (no flocktrack metadata with a scenario)")
    try:
        return parse_scenario(tomllib.loads(text), rec.metadata.get("scenario_path") or str(path))
    except (tomllib.TOMLDecodeError, ScenarioError) as exc:
        raise LoadError(f"{path}: the scenario in its metadata does not parse: {exc}") from None


def _summary(path: Path, sc: Scenario) -> dict[str, Any]:
    """``summary.json`` beside the recording, if it is this run's (the same scenario, seed, estimator, ticks)."""
    from flocktrack.record.metrics import summary_identity

    f = path.parent / "summary.json"
    try:
        s = json.loads(f.read_text())
    except (OSError, ValueError):
        return {}
    same = isinstance(s, dict) and all(s.get(k) == v for k, v in summary_identity(sc).items())
    return s if same else {}
