"""`docker compose up` for real: the demo in containers, built and run by the tests (docs/deploy.md).

A Docker engine (the running one, else a ``dockerd`` started here with no bridge network:
flocktrack/testbed/docker.py), the base image made without a registry (``flocktrack image``: mmdebstrap |
docker import), the project image built once by ``docker compose build`` from a file that
``flocktrack compose --network host`` generated, then:

* a lockstep run of the demo (4 sensors, 100 ticks): every service starts, summary.json and a complete
  recording land in the bind-mounted output directory, and the numbers equal the same scenario run with
  ``--transport inproc`` in the same image, bit for bit; ``docker compose down`` leaves nothing behind;
* a secure realtime run (TLS + mTLS + passwords + the router's ACL, each service mounting only its own
  credentials) in which one sensor's process is killed with SIGKILL: the compose restart policy restarts
  its container, the sensor rejoins and its estimates resume.

Every packet stays on 127.0.0.1 (host networking; the router and the dashboard listen on loopback).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from flocktrack.deploy import compose
from flocktrack.deploy import image
from flocktrack.launch.launcher import free_port
from flocktrack.record.reader import read_recording

import provision
from flocktrack.testbed.docker import Engine

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "scenarios" / "demo.toml"
BASE = "flocktrack-base:bookworm"
IMAGE = "flocktrack:compose-test"
SMALL = ["--set", "sensors.n=4"]


@pytest.fixture(scope="module")
def engine():
    dockerd = provision.require(provision.docker_engine)
    provision.require(provision.docker_compose)
    e = Engine.start(dockerd)
    try:
        yield e
    finally:
        e.stop()
    if e.owned:      # no dockerd of ours is left
        assert e.proc.poll() is not None and not Path(e.rundir).exists()


@pytest.fixture(scope="module")
def built(engine, tmp_path_factory):
    """The base image (made once per engine data root) and the project image, built by compose."""
    if engine.docker("image", "inspect", BASE, check=False).returncode != 0:
        image.build_base_image(BASE, env=engine.env, progress=lambda line: print(line, file=sys.__stderr__))
    d = tmp_path_factory.mktemp("build")
    _generate(d, "--mode", "lockstep")
    p = _compose(engine, d, "build", timeout=1200)
    assert engine.docker("image", "inspect", IMAGE, check=False).returncode == 0, p.stdout[-2000:]
    return IMAGE


def _generate(d: Path, *extra: str) -> dict:
    from flocktrack.cli import main

    argv = ["compose", str(DEMO), *SMALL, "--out", str(d), "--network", "host", "--base-image", BASE,
            "--image", IMAGE, "--router-port", str(free_port()), "--dashboard-port", str(free_port()),
            "--data", str(d / "data"), *extra]
    assert main(argv) == 0
    import yaml

    return yaml.safe_load((d / "docker-compose.yml").read_text())


def _compose(engine: Engine, d: Path, *args: str, project: str = "ft-build", timeout: float = 300, check: bool = True):
    p = subprocess.run([*provision.docker_compose(), "-p", project, *args],
                       cwd=d, env=engine.env, capture_output=True, text=True, timeout=timeout)
    if check and p.returncode != 0:
        raise AssertionError(f"docker compose {' '.join(args)} → {p.returncode}:\n{p.stdout[-2000:]}\n{p.stderr[-2000:]}")
    return p


class Project:
    """One compose project: up, wait for its services, inspect them, and always down."""

    def __init__(self, engine: Engine, d: Path):
        self.engine, self.d = engine, d
        self.name = f"ft-{uuid.uuid4().hex[:10]}"     # unique, also on an engine another session uses

    def compose(self, *args: str, **kw):
        return _compose(self.engine, self.d, *args, project=self.name, **kw)

    def __enter__(self):
        self.compose("up", "-d", "--no-build", timeout=600)
        return self

    def __exit__(self, *exc):
        p = self.compose("down", "-v", "--timeout", "10", check=False)
        if exc[0] is None:
            assert p.returncode == 0, p.stderr[-1000:]
            self.assert_gone()

    def container(self, service: str) -> str:
        cid = self.compose("ps", "-a", "-q", service).stdout.strip()
        assert cid, f"no container for {service}"
        return cid

    def inspect(self, service: str) -> dict:
        return json.loads(self.engine.docker("inspect", self.container(service)).stdout)[0]

    def wait(self, service: str, timeout: float) -> int:
        p = self.engine.docker("wait", self.container(service), timeout=timeout)
        return int(p.stdout.strip())

    def logs(self, service: str) -> str:
        """The service's whole log (slice it for a message)."""
        return self.compose("logs", "--no-color", service, check=False).stdout

    def assert_gone(self) -> None:
        """`docker compose down` left no container, network or volume of the project."""
        label = f"label=com.docker.compose.project={self.name}"
        for what in (["ps", "-a"], ["network", "ls"], ["volume", "ls"]):
            left = self.engine.docker(*what, "-q", "--filter", label).stdout.split()
            assert not left, (what, left)


def _estimates(path: Path, n: int) -> dict[int, list[int]]:
    """Each sensor's estimated ticks in the recording (read once)."""
    est: dict[int, list[int]] = {i: [] for i in range(n)}
    for key, m, _ in read_recording(path).messages:
        if key.startswith("agent/") and key.endswith("/estimate") and m.src in est:
            est[m.src].append(m.k)
    return {i: sorted(ks) for i, ks in est.items()}


def test_compose_up_lockstep_equals_inproc_and_down_leaves_nothing(engine, built, tmp_path):
    doc = _generate(tmp_path, "--mode", "lockstep", "--set", "run.ticks=100")
    services = list(doc["services"])
    assert all(s["network_mode"] == "host" for s in doc["services"].values())
    data = tmp_path / "data"
    with Project(engine, tmp_path) as proj:
        assert proj.wait("world-0", 300) == 0, proj.logs("world-0")[-3000:]
        assert proj.wait("recorder-0", 120) == 0, proj.logs("recorder-0")[-3000:]
        for name in services:   # every service started; the run's members exited cleanly
            state = proj.inspect(name)["State"]
            assert not state["StartedAt"].startswith("0001"), name
            if name.startswith("agent-") or name == "target-0":
                assert state["Status"] == "exited" and state["ExitCode"] == 0, (name, proj.logs(name)[-3000:])
        assert proj.inspect("router-0")["State"]["Running"] and proj.inspect("dashboard-0")["State"]["Running"]

    summary = json.loads((data / "summary.json").read_text())
    rec = read_recording(data / "recording.mcap")
    assert rec.complete and summary["ticks_seen"] == 100 and summary["n_sensors"] == 4
    # the same scenario (the resolved file the containers read), in-process, in the same image
    out = tmp_path / "inproc"
    out.mkdir()
    engine.docker("run", "--rm", "--network", "host", "--user", f"{os.getuid()}:{os.getgid()}",
                  "-v", f"{tmp_path}:/w", built, "flocktrack", "run", "/w/compose/scenario.toml",
                  "--transport", "inproc", "--mode", "lockstep", "--quiet", "--out", "/w/inproc", timeout=300)
    assert (data / "metrics.csv").read_bytes() == (out / "metrics.csv").read_bytes()
    ref = json.loads((out / "summary.json").read_text())
    for k in ("final_rmse", "mean_estimate_rmse", "max_error", "disagreement_mean", "ticks_seen"):
        assert summary[k] == ref[k], k


def test_compose_up_secure_killed_sensor_is_restarted_and_rejoins(engine, built, tmp_path):
    from flocktrack.cli import main

    keys = tmp_path / "keys"
    assert main(["keys", str(DEMO), *SMALL, "--out", str(keys)]) == 0
    doc = _generate(tmp_path, "--mode", "realtime", "--set", "run.ticks=300", "--set", "run.speed=0.5",
                    "--secure", "--keys", str(keys))
    svcs = doc["services"]
    # each service mounts only its own credentials
    for name, ident in [("router-0", "router-0"), ("world-0", "world-0"), ("agent-2", "agent-2"), ("dashboard-0", "dashboard-0")]:
        mounts = [v for v in svcs[name]["volumes"] if "/keys/" in v]
        assert mounts == [f"./compose/keys/{ident}:{compose.KEYS_MOUNT}:ro"], (name, mounts)
    data = tmp_path / "data"
    ep = doc["x-flocktrack"]["endpoint"]
    assert ep.startswith("tls/127.0.0.1:")
    with Project(engine, tmp_path) as proj:
        for name, ident in [("agent-1", "agent-1"), ("recorder-0", "recorder-0")]:
            binds = [m["Source"] for m in proj.inspect(name)["Mounts"] if m["Destination"] == compose.KEYS_MOUNT]
            assert binds == [str(tmp_path / "compose" / "keys" / ident)], (name, binds)
        # the run is well under way: ~100 ticks in the recording (it grows ~8 kB a tick; its size is watched,
        # not parsed over and over — that would take a core from the run it watches) ...
        _wait_size(data / "recording.mcap", 600_000, 240, proj)
        # ... sensor 1's process dies (SIGKILL, as a crash: `docker kill` would be a manual stop, which
        # Docker's restart policy does not undo) ...
        top = engine.docker("top", proj.container("agent-1"), "-eo", "pid,args").stdout.splitlines()[1:]
        pids = [int(ln.split()[0]) for ln in top if ln.split(None, 1)[1].startswith("python -m agent sensor")]
        assert len(pids) == 1, top
        os.kill(pids[0], signal.SIGKILL)
        # ... a client without the run's credentials is refused by the router (TLS, mTLS, password, ACL)
        probe = subprocess.run([sys.executable, "-m", "flocktrack.launch.health", "--quiet", "--timeout", "3", "--run", "demo",
                                "--connect", ep, "--member", "world/0"], capture_output=True, text=True, timeout=60)
        assert probe.returncode == 1, probe.stderr
        assert proj.wait("world-0", 300) == 0, proj.logs("world-0")[-3000:]
        assert proj.wait("recorder-0", 120) == 0, proj.logs("recorder-0")[-3000:]
        # ... the restart policy restarted its container once, and it rejoined the running flock
        assert proj.inspect("agent-1")["RestartCount"] == 1, proj.logs("agent-1")[-3000:]
        assert "agent/1: rejoining the flock at tick" in proj.logs("agent-1")
    est = _estimates(data / "recording.mcap", 4)
    longest = {i: max(((b - a, a, b) for a, b in zip(ks, ks[1:])), default=(0, 0, 0)) for i, ks in est.items()}
    # sensor 1 was down (a restart takes seconds) — longer than any gap the others had (a loaded machine
    # makes the whole flock skip a few ticks now and then) ...
    gap, _, back = longest[1]
    assert gap >= 8 and all(gap > longest[i][0] for i in (0, 2, 3)), longest
    # ... and estimated again, with the flock, till the end
    after = {i: len([k for k in ks if k >= back]) for i, ks in est.items()}
    assert back < 250 and est[1][-1] >= 280 and after[1] >= 0.8 * min(after[i] for i in (0, 2, 3)), (longest, after)
    assert all(len(est[i]) >= 0.7 * 300 for i in (0, 2, 3)), {i: len(ks) for i, ks in est.items()}
    summary = json.loads((data / "summary.json").read_text())
    assert summary["ticks_seen"] >= 280


def _wait_size(path: Path, size: int, timeout: float, proj: Project) -> None:
    """Until the recording being written has ``size`` bytes."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if path.exists() and path.stat().st_size >= size:
            return
        time.sleep(0.5)
    raise AssertionError(f"the recording did not reach {size} bytes in {timeout} s: {proj.logs('world')[-3000:]}")


def test_base_image_command_lines():
    argv = image.mmdebstrap_argv("bookworm", Path("/etc/ssl/certs/ca-certificates.crt"))
    assert argv[:2] == ["mmdebstrap", "--variant=minbase"] and argv[-2:] == ["bookworm", "-"]
    assert "python3-venv" in argv[2] and any(a.startswith("--customize-hook=cp ") for a in argv)
    assert "--customize-hook" not in " ".join(image.mmdebstrap_argv("bookworm", None))
    imp = image.import_argv("x:y")
    assert imp[:2] == ["docker", "import"] and imp[-2:] == ["-", "x:y"]
    assert "ENV PIP_CERT=/etc/ssl/certs/ca-certificates.crt" in imp
