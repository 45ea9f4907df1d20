"""A recording read by Foxglove's own TypeScript reader (``tests/mcap_check.js``: ``@mcap/core`` with CRCs
validated, every message decoded as Foxglove decodes it), for the tests."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from provision import mcap_reader, require

CHECK = Path(__file__).with_name("mcap_check.js")


def foxglove_read(path: str | Path, mode: str = "whole") -> dict:
    """What ``@mcap/core`` reads of ``path``: ``mode`` "whole" (indexed reader: a complete file) or "stream"
    (as far as the file goes: a cut one)."""
    modules = require(mcap_reader)
    node = shutil.which("node")
    if node is None:
        pytest.fail("node is not on PATH (it comes with npm)", pytrace=False)
    p = subprocess.run([node, str(CHECK), str(path), mode], capture_output=True, text=True, timeout=300,
                       env={**os.environ, "NODE_PATH": str(modules)})
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads(p.stdout)
