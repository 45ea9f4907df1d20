"""run.json's ``unrecorded_messages``: what the run's processes say they sent on a recorded key against what the
recording holds (flocktrack/engine/run.py ``unrecorded``)."""

from __future__ import annotations

import json

from agent.recording import Recording
from flocktrack.engine.run import unrecorded


def test_a_message_sent_but_not_recorded_is_counted_by_key_and_addressed_copies_are_not(tmp_path):
    (tmp_path / "agent-0.json").write_text(json.dumps({"sent_by_key": {
        "agent/0/state": 3, "agent/0/xchg": 2, "agent/0/to/1/xchg": 7}}))
    (tmp_path / "world-0.json").write_text(json.dumps({"sent_by_key": {"world/tick": 3}}))
    (tmp_path / "recorder-0.json").write_text(json.dumps({"received": 9}))    # no sent_by_key: nothing to say
    (tmp_path / "broken.json").write_text("{")                                # unreadable: skipped
    rows = [("world/tick", None, 0)] * 3 + [("agent/0/state", None, 0)] * 2 + [("agent/0/xchg", None, 0)] * 2
    assert unrecorded(tmp_path, Recording({}, rows)) == {"agent/0/state": 1}
    assert unrecorded(tmp_path, Recording({}, rows + [("agent/0/state", None, 0)])) == {}
