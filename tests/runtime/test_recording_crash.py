"""What a crash leaves of a recording: ``kill -9`` of a run's launcher (its children, the recorder among them,
die with it) mid-run leaves an MCAP file that ``flocktrack metrics`` reads, missing at most the last second
(the recorder closes a chunk once it is FLUSH_S old), and ``flocktrack recover`` rewrites it as a complete
file that a strict MCAP reader (summary, index, footer) opens."""

import json
import signal
import subprocess
import sys
import time

import pytest

from flocktrack.cli import main
from flocktrack.record.writer import FLUSH_S
from flocktrack.record.reader import read_recording

from conftest import ROOT
from mcap_js import foxglove_read


@pytest.mark.slow
def test_kill_9_of_the_launcher_leaves_a_readable_recording_short_of_at_most_a_second(tmp_path, capsys):
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "flocktrack", "run", "scenarios/gu_hu_normal.toml", "--mode",
                             "realtime", "--ticks", "100000", "--quiet", "--out", str(out)], cwd=ROOT,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rec_file = out / "recording.mcap"
    end = time.monotonic() + 120
    while time.monotonic() < end and not (rec_file.exists() and rec_file.stat().st_size > 300_000):
        time.sleep(0.2)
    assert rec_file.exists(), "the run never got going"
    time.sleep(2.0)                       # a steady stream: a tick every T = 0.04 s
    t_kill = time.time_ns()
    proc.send_signal(signal.SIGKILL)
    proc.wait(30)
    time.sleep(2.0)                       # its children are gone with it (PR_SET_PDEATHSIG)

    rec = read_recording(rec_file)
    assert not rec.complete and len(rec.messages) > 100
    last = max(rec.wall)                  # when the last message was recorded
    lost_s = (t_kill - last) / 1e9
    assert lost_s < 1.0, f"the last recorded message is {lost_s:.2f} s older than the kill (FLUSH_S = {FLUSH_S})"
    ticks = sorted(m.k for k, m, _t in rec.messages if k == "world/tick")
    assert ticks == list(range(len(ticks)))          # what is there has no hole
    # a realtime run too is recorded on the simulated clock: k·T
    assert rec.simulated and all(t == round(m.k * 0.04 * 1e9) for _k, m, t in rec.messages)
    # Foxglove's own reader reads the cut file as far as it goes, every message and view decoding
    cut = foxglove_read(rec_file, "stream")
    assert not cut["complete"] and cut["decodeErrors"] == 0, cut["firstError"]
    assert {"foxglove.SceneUpdate", "foxglove.FrameTransforms"} <= set(cut["schemas"])
    assert cut["perTopic"]["world/tick"] >= len(ticks) - 10

    # flocktrack metrics reads the truncated file as it is ...
    assert main(["metrics", str(rec_file), "--out", str(tmp_path / "m1")]) == 0
    # ... and flocktrack recover makes a complete file of it
    assert main(["recover", str(rec_file)]) == 0
    assert "had no summary (a crash)" in capsys.readouterr().out
    fixed = out / "recording.recovered.mcap"
    from mcap.reader import make_reader

    with open(fixed, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        ours = {c.id for c in summary.channels.values() if summary.schemas[c.schema_id].name.startswith("flocktrack.")
                and not summary.schemas[c.schema_id].name.startswith("flocktrack.view.")}
        assert sum(summary.statistics.channel_message_counts[c] for c in ours) == len(rec.messages)
        assert sum(1 for _ in reader.iter_messages()) == summary.statistics.message_count
    whole = foxglove_read(fixed, "whole")            # ... that Foxglove's reader opens whole, CRCs checked
    assert whole["complete"] and whole["readError"] is None and whole["decodeErrors"] == 0, whole["firstError"]
    assert {"foxglove.SceneUpdate", "foxglove.FrameTransforms"} <= set(whole["schemas"])   # (no event: no log)
    again = read_recording(fixed)
    assert again.complete and again.metadata == rec.metadata
    assert [(k, t) for k, _m, t in again.messages] == [(k, t) for k, _m, t in rec.messages]
    assert main(["metrics", str(fixed), "--out", str(tmp_path / "m2")]) == 0
    s1, s2 = (json.loads((tmp_path / d / "summary.json").read_text()) for d in ("m1", "m2"))
    assert s1 == s2 and s1["ticks_seen"] >= 20


def test_an_output_directory_that_cannot_be_written_is_said_at_start(tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert main(["run", str(ROOT / "scenarios" / "demo.toml"), "--ticks", "3", "--out", str(blocker / "run")]) == 2
    assert f"cannot write the results to {blocker / 'run'}" in capsys.readouterr().err


def test_a_long_recording_keeps_half_a_kilobyte_per_chunk_and_every_index(tmp_path):
    """The recorder's memory grows with the number of chunks only by the chunk index the MCAP summary
    needs (packed to its bytes: the soak's recorder grew 8 % in 10 minutes before), and the file keeps
    the per-channel message indexes Foxglove's indexed reader requires."""
    import tracemalloc

    import numpy as np
    from mcap.reader import make_reader

    from agent.wire import Estimate
    from flocktrack.record.writer import McapRecorder

    path = tmp_path / "long.mcap"
    rec = McapRecorder(path, {"scenario": ""})
    keys = [f"agent/{i}/estimate" for i in range(40)]

    def chunk(k: int) -> None:          # one chunk of 40 channels, as the demo's half-second chunks have
        for i, key in enumerate(keys):
            rec.write(key, Estimate(src=i, k=k, x=np.zeros(4), x_next=np.zeros(4)))
        rec.flush()

    for k in range(20):
        chunk(k)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    for k in range(20, 620):
        chunk(k)
    per_chunk = (tracemalloc.get_traced_memory()[0] - before) / 600
    tracemalloc.stop()
    rec.finish()
    assert per_chunk < 800, per_chunk            # (a record object with its offsets dict: ~2.8 KB)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert len(summary.chunk_indexes) == 620
        assert all(len(ci.message_index_offsets) == 40 for ci in summary.chunk_indexes)
        assert sum(1 for _ in reader.iter_messages(topics=["agent/7/estimate"])) == 620
    assert len(read_recording(path).messages) == 620 * 40
