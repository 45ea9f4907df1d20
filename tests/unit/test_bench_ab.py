"""The two-builds comparison (bench/bench_ab.py): a build named by a git revision is checked out beside the
repository and its processes import it, not this checkout; the ratios and their summary over the pairs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ab(bench_module):
    return bench_module("bench_ab")


def test_ratios_and_their_summary_per_role(ab):
    r = ab.ratios({"total": 20.0, "agent": 10.0, "world": 0.0}, {"total": 18.0, "agent": 9.5, "router": 3.0})
    assert r == pytest.approx({"total": 0.9, "agent": 0.95})      # (world: A spent nothing; router: only in B)
    pairs = [{"b_over_a": {"total": 0.9, "agent": 0.95}}, {"b_over_a": {"total": 1.1, "agent": 0.85}},
             {"b_over_a": {"total": 1.0}}]
    s = ab.summarize(pairs)
    assert set(s) == {"total"}                                     # only the roles every pair measured
    assert s["total"] == pytest.approx({"median": 1.0, "min": 0.9, "max": 1.1})


def test_a_revision_is_checked_out_and_imported_by_its_processes(ab, tmp_path):
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    assert ab.build(str(tmp_path), []) == tmp_path.resolve()       # a directory is taken as it is
    keep: list[Path] = []
    tree = ab.build("HEAD", keep)
    try:
        assert keep == [tree] and (tree / "agent" / "runner.py").is_file() and tree != ROOT
        env = ab.env_of(tree, ["FLOCKTRACK_X=1"])
        out = subprocess.run([sys.executable, "-c", "import agent, os; print(agent.__file__, os.environ['FLOCKTRACK_X'])"],
                             env=env, cwd=tree, capture_output=True, text=True, check=True).stdout.split()
        assert Path(out[0]).resolve().is_relative_to(tree.resolve()) and out[1] == "1"
    finally:
        ab.drop(tree)
    assert not tree.parent.exists()
    assert str(tree) not in subprocess.run(["git", "-C", str(ROOT), "worktree", "list"], capture_output=True,
                                           text=True).stdout
