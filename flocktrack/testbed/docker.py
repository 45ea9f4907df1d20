"""A Docker engine for the container tests: the one already running, else a ``dockerd`` the tests start
and stop themselves.

The engine a test starts has no bridge network and touches no firewall (``--bridge=none
--iptables=false``): the tests run every container with host networking, so every packet stays on
127.0.0.1. Its images live in a data root that survives the run (``/var/tmp/flocktrack-dockerd/slotN``,
a cache: the base image and the dependency layer are built once per machine), one slot per concurrent
test session (an exclusive file lock), so two sessions never share a daemon they could stop under each
other. Its socket, pid file and state are in a directory of its own, removed at :meth:`Engine.stop`,
which stops the daemon (and its containerd) by pid — also when a test failed.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

CACHE = Path("/var/tmp/flocktrack-dockerd")
SLOTS = 4


class Engine:
    def __init__(self, host: str, proc: subprocess.Popen | None = None, rundir: Path | None = None, lock=None):
        self.host = host                    # DOCKER_HOST
        self.proc = proc                    # the dockerd this session started (None: one already running)
        self.rundir = rundir
        self._lock = lock
        self.env = dict(os.environ, DOCKER_HOST=host)

    @property
    def owned(self) -> bool:
        return self.proc is not None

    def docker(self, *args: str, timeout: float = 120, check: bool = True) -> subprocess.CompletedProcess:
        p = subprocess.run(["docker", *args], capture_output=True, text=True, env=self.env, timeout=timeout)
        if check and p.returncode != 0:
            raise AssertionError(f"docker {' '.join(args)} → {p.returncode}: {p.stderr.strip()[-800:]}")
        return p

    def responds(self) -> bool:
        try:
            return self.docker("version", "--format", "{{.Server.Version}}", timeout=10, check=False).returncode == 0
        except subprocess.TimeoutExpired:
            return False

    @classmethod
    def start(cls, dockerd: str | Path, timeout: float = 90) -> Engine:
        """The running engine ($DOCKER_HOST or /var/run/docker.sock) if it answers, else a new dockerd."""
        for host in filter(None, (os.environ.get("DOCKER_HOST"), "unix:///var/run/docker.sock")):
            if host.startswith("unix://") and not Path(host[7:]).exists():
                continue
            e = cls(host)
            if e.responds():
                return e
        CACHE.mkdir(parents=True, exist_ok=True)
        for slot in range(SLOTS):
            lock = open(CACHE / f"slot{slot}.lock", "w")
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                lock.close()
                continue
            break
        else:
            raise RuntimeError(f"all {SLOTS} dockerd slots under {CACHE} are in use")
        rundir = Path(tempfile.mkdtemp(prefix="ftd-", dir="/tmp"))   # short: the sockets' paths live here
        host = f"unix://{rundir}/docker.sock"
        log = open(rundir / "dockerd.log", "wb")
        proc = subprocess.Popen(
            [str(dockerd), "--bridge=none", "--iptables=false", "--ip6tables=false", "--ip-masq=false",
             "--data-root", str(CACHE / f"slot{slot}"), "--exec-root", str(rundir / "exec"),
             "--pidfile", str(rundir / "dockerd.pid"), "-H", host],
            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        e = cls(host, proc, rundir, lock)
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if proc.poll() is not None:
                e.stop()
                raise RuntimeError(f"dockerd exited with {proc.returncode}: {(rundir / 'dockerd.log').read_text()[-1500:]}")
            if e.responds():
                return e
            time.sleep(0.5)
        e.stop()
        raise RuntimeError(f"dockerd did not answer within {timeout} s")

    def stop(self) -> None:
        """Stop the dockerd this session started (SIGTERM, then SIGKILL of its whole process group)."""
        if self.proc is None:
            return
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                pass
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)     # its containerd and shims, whatever is left
        except ProcessLookupError:
            pass
        self.proc.wait()
        if self._lock is not None:
            self._lock.close()
        if self.rundir is not None:
            for m in _mounts_under(self.rundir):      # dockerd's netns bind mounts outlive it
                subprocess.run(["umount", "-l", m], capture_output=True)
            shutil.rmtree(self.rundir, ignore_errors=True)


def _mounts_under(path: Path) -> list[str]:
    """Mount points at or below ``path``, deepest first (from /proc/self/mountinfo)."""
    prefix = str(path).rstrip("/") + "/"
    points = []
    for line in Path("/proc/self/mountinfo").read_text().splitlines():
        mp = line.split()[4].replace("\\040", " ")
        if mp.startswith(prefix) or mp == prefix[:-1]:
            points.append(mp)
    return sorted(points, key=len, reverse=True)
