"""The example notebooks are committed without outputs: no cell output, no execution count (a test runs them:
tests/runtime/test_notebook.py)."""

import json

from conftest import ROOT


def test_the_committed_notebooks_carry_no_outputs():
    notebooks = sorted((ROOT / "examples").glob("*.ipynb"))
    assert notebooks, "examples/ holds the quickstart notebook"
    for path in notebooks:
        for i, cell in enumerate(json.loads(path.read_text())["cells"]):
            if cell["cell_type"] == "code":
                assert cell["outputs"] == [] and cell["execution_count"] is None, f"{path.name} cell {i} has outputs"
