"""The example notebook runs: ``examples/quickstart.ipynb`` executed top to bottom by a real kernel, in a
temporary copy (its runs and tables land there), within a time limit, without an error."""

import os
import shutil
import sys
import time
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

from conftest import ROOT

NOTEBOOK = ROOT / "examples" / "quickstart.ipynb"
TIMEOUT_S = 300          #: the whole notebook (a cell: CELL_TIMEOUT_S); it takes ~15 s on 2 busy cores
CELL_TIMEOUT_S = 120


@pytest.mark.timeout(TIMEOUT_S)
def test_the_quickstart_notebook_runs_without_an_error(tmp_path, monkeypatch):
    copy = tmp_path / NOTEBOOK.name
    shutil.copyfile(NOTEBOOK, copy)
    # the kernel spec starts `python`: this interpreter's, whatever the PATH the tests were started with
    monkeypatch.setenv("PATH", f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    nb = nbformat.read(copy, as_version=4)
    t0 = time.monotonic()
    NotebookClient(nb, timeout=CELL_TIMEOUT_S, kernel_name="python3",
                   resources={"metadata": {"path": str(tmp_path)}}).execute()   # raises CellExecutionError
    print(f"the notebook ran in {time.monotonic() - t0:.1f} s")
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors, errors
    assert (tmp_path / "runs" / "quickstart" / "byzantine" / "recording.mcap").is_file()
    assert (tmp_path / "runs" / "quickstart" / "byzantine-tables" / "ticks.parquet").is_file()
