"""``flocktrack image``: a base image for the Dockerfile on a machine that cannot reach an image registry.

The generated Dockerfile builds ``FROM ${BASE_IMAGE}`` (``python:3.11-slim`` from Docker Hub by default).
Where no registry is reachable, this command makes an equivalent base locally from Debian's packages::

    mmdebstrap --variant=minbase --include=python3,python3-venv,python3-pip,ca-certificates SUITE - \\
      | docker import --change 'ENV PIP_CERT=…' - NAME

(~25–50 s, ~240 MB), and the compose file points at it with ``flocktrack compose … --base-image NAME``.
The host's CA bundle is copied into the image (``--ca``, default ``/etc/ssl/certs/ca-certificates.crt``)
and pip is told to use it: where package traffic passes a proxy only the host trusts, ``pip install``
inside the build needs it. Needs root (or mmdebstrap's unshare mode), ``mmdebstrap`` and ``docker``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

DEFAULT_NAME = "flocktrack-base:bookworm"
DEFAULT_SUITE = "bookworm"
PACKAGES = ["python3", "python3-venv", "python3-pip", "ca-certificates"]
HOST_CA = Path("/etc/ssl/certs/ca-certificates.crt")
IMAGE_CA = "/etc/ssl/certs/ca-certificates.crt"


class ImageError(RuntimeError):
    """The base image could not be made; the message says what is missing and how to get it."""


def mmdebstrap_argv(suite: str = DEFAULT_SUITE, ca: Path | None = HOST_CA, mirror: str | None = None) -> list[str]:
    """The mmdebstrap command writing the root file system as a tar stream to stdout."""
    argv = ["mmdebstrap", "--variant=minbase", f"--include={','.join(PACKAGES)}"]
    if ca is not None:
        # after ca-certificates has written its bundle: replace it by the host's (which may hold a proxy's CA)
        argv.append(f"--customize-hook=cp {ca} \"$1{IMAGE_CA}\"")
    argv += [suite, "-"]
    if mirror:
        argv.append(mirror)
    return argv


def import_argv(name: str, docker: str = "docker") -> list[str]:
    """``docker import`` of the tar stream on stdin, with pip pointed at the bundle and a python3 command."""
    return [docker, "import", "--change", f"ENV PIP_CERT={IMAGE_CA}", "--change", 'CMD ["python3"]', "-", name]


def build_base_image(name: str = DEFAULT_NAME, suite: str = DEFAULT_SUITE, ca: Path | None = HOST_CA,
                     mirror: str | None = None, *, env: dict | None = None, progress=print) -> dict:
    """Make the base image ``name``; returns ``{"image", "seconds", "bytes"}``. ``progress`` gets one line
    per stage of mmdebstrap (its ``I:`` lines)."""
    for tool, pkg in (("mmdebstrap", "mmdebstrap"), ("docker", "docker.io")):
        if not shutil.which(tool):
            raise ImageError(f"{tool} not found: install it (`apt-get install -y {pkg}`)")
    if ca is not None and not Path(ca).is_file():
        raise ImageError(f"--ca {ca}: no such file (give the CA bundle pip must trust, or --no-ca)")
    t0 = time.monotonic()
    strap = subprocess.Popen(mmdebstrap_argv(suite, ca, mirror), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             env=env)
    imp = subprocess.Popen(import_argv(name), stdin=strap.stdout, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           env=env)
    strap.stdout.close()          # the importer holds the pipe now
    tail: list[str] = []
    for raw in strap.stderr:
        line = raw.decode(errors="replace").rstrip()
        tail = (tail + [line])[-20:]
        if line.startswith("I: ") and progress:
            progress(f"[image] {line[3:]}")
    out, err = imp.communicate()
    if strap.wait() != 0:
        raise ImageError("mmdebstrap failed (is this root, or is unshare allowed?):\n" + "\n".join(tail))
    if imp.returncode != 0:
        raise ImageError(f"docker import failed: {err.decode(errors='replace').strip()} (is dockerd running?)")
    size = subprocess.run(["docker", "image", "inspect", "-f", "{{.Size}}", name], capture_output=True, text=True,
                          env=env)
    return {"image": name, "seconds": round(time.monotonic() - t0, 1),
            "bytes": int(size.stdout.strip()) if size.returncode == 0 and size.stdout.strip().isdigit() else None}


def cmd_image(args) -> int:
    try:
        r = build_base_image(args.name, args.suite, None if args.no_ca else Path(args.ca), args.mirror,
                             env=dict(os.environ))
    except ImageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    mb = f", {r['bytes'] / 1e6:.0f} MB" if r["bytes"] else ""
    print(f"built {r['image']} in {r['seconds']} s{mb}; use it with: "
          f"flocktrack compose SCENARIO --base-image {r['image']}")
    return 0


def register(subparsers) -> None:
    """Add ``flocktrack image`` to the CLI."""
    p = subparsers.add_parser("image", help="make the Dockerfile's base image locally (no registry needed)",
                              description=__doc__.split("\n\n")[0])
    p.add_argument("--name", default=DEFAULT_NAME, help=f"image name (default {DEFAULT_NAME})")
    p.add_argument("--suite", default=DEFAULT_SUITE, help=f"Debian suite (default {DEFAULT_SUITE}: python 3.11)")
    p.add_argument("--mirror", help="Debian mirror URL (default: mmdebstrap's)")
    p.add_argument("--ca", default=str(HOST_CA), help=f"CA bundle copied into the image for pip (default {HOST_CA})")
    p.add_argument("--no-ca", action="store_true", help="keep Debian's own CA bundle")
    p.set_defaults(fn=cmd_image)
