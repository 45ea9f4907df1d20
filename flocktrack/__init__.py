"""flocktrack: distributed robust target tracking by a flock of mobile sensors.

Every sensor, the target, the world (clock and link table) and the fusion solver are message-driven
roles (``agent/``, ``topology/``) exchanging msgpack messages over Zenoh, one OS process each, or on an
in-process bus. This package is the runtime around them: the ``flocktrack`` command (:mod:`flocktrack.cli`),
the launcher, the recorder, metrics, sweeps, compose files and secure deployments.
"""

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version

try:
    __version__ = _version("flocktrack")   # one source of truth: the installed distribution's metadata
except PackageNotFoundError:                # imported from a source tree that was never installed
    __version__ = "0+unknown"
