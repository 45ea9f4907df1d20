"""The run's Python processes started from a pre-imported template instead of a fresh interpreter each.

A sensor process spends ~0.4 s of CPU importing numpy, SciPy, Zenoh and the roles before it does anything;
a flock of N pays it N times on the launcher's critical path (start-up), and a restarted sensor
pays it again before it can rejoin. The standard library's *forkserver* (``multiprocessing``) does what is
needed: one server process imports :data:`PRELOAD` once; every child is a ``fork()`` of it — the imports
already done, copy-on-write — that then runs ``python -m MODULE ARGS`` in-process (:func:`_child_main`,
with ``runpy``, as the interpreter would). The server never opens a Zenoh session (fork after a Tokio
runtime has started is unsafe), so each child opens its own, as a fresh process does.

:class:`ForkedProcess` is the part of :class:`subprocess.Popen` the launcher uses (``pid``, ``stdout``,
``poll``, ``wait``, ``send_signal``, ``kill``, ``returncode``): the child's stdout and stderr are one pipe,
passed to it at the fork (``multiprocessing.reduction.DupFd``), read line by line by the launcher as
before; the exit code is the one ``python -m`` would give (``SystemExit``'s code, 1 on an uncaught
exception, −signal when killed). A child asks the kernel to SIGKILL it when the server dies, and the server
exits when its launcher does, so a ``kill -9`` of the launcher still takes every process with it.

``FLOCKTRACK_FORKSERVER=0`` turns it off (every child a fresh interpreter, as before); children that are
not ``python -m`` of this interpreter (a mesh host's, wrapped in ``ip netns exec``) always are.
"""

from __future__ import annotations

import ctypes
import gc
import io
import multiprocessing
import os
import runpy
import signal
import subprocess
import sys
import traceback
from functools import cache
from multiprocessing import reduction

#: imported once by the server, before any fork (what every role's process imports at start; reading the
#: scenario imports every estimator the registry finds: agent/estimators/preload.py)
PRELOAD = ["numpy", "scipy.linalg", "msgpack", "zenoh", "agent.bus", "agent.wire", "agent.scenario", "agent.assemble",
           "agent.runner", "agent.estimators.preload", "topology.world", "flocktrack.record.recorder"]


def die_with_parent() -> None:
    """Ask the kernel to SIGKILL this process when its parent dies (in a child, between fork and exec — or
    before ``python -m`` runs, in a forked one)."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def enabled() -> bool:
    return os.environ.get("FLOCKTRACK_FORKSERVER", "1") != "0"


def forkable(argv: list[str]) -> bool:
    """Is ``argv`` ``python -m MODULE …`` of this interpreter (what the server can run)?"""
    return enabled() and len(argv) >= 3 and argv[0] == sys.executable and argv[1] == "-m"


@cache
def _context():
    ctx = multiprocessing.get_context("forkserver")
    ctx.set_forkserver_preload(PRELOAD)
    return ctx


def start_server() -> None:
    """Start the server now (its imports, once) rather than at the first child."""
    from multiprocessing import forkserver

    _context()
    forkserver.ensure_running()


class _Fd:
    """A file descriptor that travels to the forked child (it is duplicated into it at the fork)."""

    def __init__(self, fd: int):
        self.fd = fd

    def __reduce__(self):
        return _Fd._arrived, (reduction.DupFd(self.fd),)

    @staticmethod
    def _arrived(dup) -> "_Fd":
        return _Fd(dup.detach())


def _child_main(argv: list[str], env: dict[str, str], cwd: str, out: _Fd) -> None:
    """In the forked child: stdout/stderr to ``out``, stdin from /dev/null, the launcher's environment and
    directory, then ``python -m argv[0] argv[1:]``; exits with its code."""
    null = os.open(os.devnull, os.O_RDONLY)
    os.dup2(null, 0)
    os.dup2(out.fd, 1)
    os.dup2(out.fd, 2)
    # nothing else of the server's: among its descriptors is the write end of the pipe by which the server
    # learns that its launcher is gone — held by a child, the server (and with it the child) would outlive
    # a killed launcher
    os.closerange(3, os.sysconf("SC_OPEN_MAX"))
    sys.stdout = io.TextIOWrapper(io.FileIO(1, "w", closefd=False), encoding="utf-8", line_buffering=True,
                                  write_through=True)
    sys.stderr = io.TextIOWrapper(io.FileIO(2, "w", closefd=False), encoding="utf-8", errors="backslashreplace",
                                  line_buffering=True, write_through=True)
    # the template's objects are never garbage: keep the cyclic collector off them — it would scan them at
    # every full collection and, writing their headers, copy every page of the template into each child
    # (all children at once, as their allocations run alike: a burst of missed round deadlines)
    gc.freeze()
    os.environ.clear()
    os.environ.update(env)
    os.chdir(cwd)
    die_with_parent()
    code = 0
    sys.argv = list(argv)
    try:
        runpy.run_module(argv[0], run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        if exc.code is None:
            code = 0
        elif isinstance(exc.code, int):
            code = exc.code
        else:
            print(exc.code, file=sys.stderr)
            code = 1
    except BaseException:  # noqa: B036 - what the interpreter does with an uncaught exception: print, exit 1
        traceback.print_exc()
        code = 1
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


class ForkedProcess:
    """``python -m …`` forked from the server (module doc); the subset of :class:`subprocess.Popen` the
    launcher uses."""

    def __init__(self, argv: list[str], env: dict[str, str], cwd: str):
        self.args = list(argv)
        r, w = os.pipe()
        try:
            self._p = _context().Process(target=_child_main, args=(argv[2:], dict(env), cwd, _Fd(w)), daemon=True)
            self._p.start()
        finally:
            os.close(w)
        self.pid: int = self._p.pid
        self.stdout = os.fdopen(r, "rb")
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self._p.exitcode
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        self._p.join(timeout)
        if self.poll() is None:
            raise subprocess.TimeoutExpired(self.args, timeout)
        return self.returncode  # type: ignore[return-value]

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)
