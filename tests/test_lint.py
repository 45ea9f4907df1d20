"""Lint is part of the test command (so `.ci/run`, which runs exactly the README's test command, lints):
ruff with the rules of pyproject.toml (pyflakes, bugbear, pep8-naming with the papers' notation allowed),
and every ``# noqa`` says why."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ["agent", "topology", "dashboards", "flocktrack", "tests", "bench"]


def test_ruff_passes():
    p = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise",
                        *SOURCES], cwd=ROOT, capture_output=True, text=True)
    assert p.returncode == 0, p.stdout + p.stderr


def test_every_noqa_says_why():
    """``# noqa: CODE - reason`` (or ``— reason``): a suppression nobody can explain is a bug to fix."""
    bare = []
    for d in SOURCES:
        for path in (ROOT / d).rglob("*.py"):
            for n, line in enumerate(path.read_text().splitlines(), 1):
                m = re.search(r"#\s*noqa\b(?!`)(.*)$", line)
                if m and not re.match(r":\s*[A-Z0-9]+(\s*,\s*[A-Z0-9]+)*\s+[-—]\s*\S", m.group(1)):
                    bare.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not bare, "\n".join(bare)
