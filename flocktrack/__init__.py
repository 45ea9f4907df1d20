"""flocktrack: distributed robust target tracking by a flock of mobile sensors.

Every sensor, the target, the world (clock and link table) and the fusion solver are message-driven
roles (``agent/``, ``topology/``) exchanging msgpack messages over Zenoh, one OS process each, or on an
in-process bus. This package is the runtime around them: the ``flocktrack`` command (:mod:`flocktrack.cli`),
the launcher, the recorder, metrics, sweeps, compose files and secure deployments; :func:`load` gives a
recorded run as pandas tables (:mod:`flocktrack.analysis`).
"""

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version

try:
    __version__ = _version("flocktrack")   # one source of truth: the installed distribution's metadata
except PackageNotFoundError:                # imported from a source tree that was never installed
    __version__ = "0+unknown"



def __getattr__(name: str):
    """``flocktrack.load`` (:func:`flocktrack.analysis.load`: a recorded run as pandas tables), imported on first
    use so that ``import flocktrack`` stays cheap."""
    if name == "load":
        from flocktrack.analysis import load

        return load
    raise AttributeError(f"module 'flocktrack' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), "load"])
