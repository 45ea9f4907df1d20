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
# the tests are grouped by layer (tests/unit, runtime, deploy, browser); their shared helpers (provision.py,
# compose_schema.py, control_plan.py) sit in tests/ itself
sys.path.insert(1, str(ROOT / "tests"))
# the toy estimator lives in a plug-in package of its own (tests/plugin/); the contract tests import it
sys.path.insert(2, str(ROOT / "tests" / "plugin"))


@pytest.fixture
def scenario_path():
    return lambda name: SCENARIOS / name


@pytest.fixture(scope="session")
def bench_module():
    """``bench_module("bench_ab")``: a script of bench/ imported as a module (bench/ is not a package), once."""
    import importlib.util

    loaded = {}

    def load(name: str):
        if name not in loaded:
            spec = importlib.util.spec_from_file_location(name, ROOT / "bench" / f"{name}.py")
            mod = importlib.util.module_from_spec(spec)
            spec.loader.exec_module(mod)
            loaded[name] = mod
        return loaded[name]

    return load


_EXIT = {"status": 0}


def pytest_sessionfinish(session, exitstatus):
    _EXIT["status"] = int(exitstatus)


def pytest_unconfigure(config):
    """A test that fails before it undeclares a raw Zenoh subscriber leaves that subscriber's callback
    thread (zenoh-python's default indirect handler, a non-daemon "pyo3-closure" thread) alive, and the
    interpreter would wait for it at exit for ever — a red test turned into a hung suite. Once the report
    is written, leave with pytest's own status instead."""
    import threading

    stuck = [t.name for t in threading.enumerate() if t is not threading.main_thread() and not t.daemon]
    if stuck:
        sys.stdout.flush()
        sys.stderr.write(f"conftest: {len(stuck)} non-daemon threads left ({sorted(set(stuck))}); exiting\n")
        sys.stderr.flush()
        os._exit(_EXIT["status"])
