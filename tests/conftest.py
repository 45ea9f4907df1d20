import os
import sys
from pathlib import Path

# tiny matrices: threaded BLAS only adds contention on 2 cores (inherited by every process a test starts)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


@pytest.fixture
def scenario_path():
    return lambda name: SCENARIOS / name
