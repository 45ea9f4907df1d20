"""Per-service credentials of a secure compose deployment (``flocktrack compose … --secure --keys DIR``).

A key set of ``flocktrack keys`` (:mod:`flocktrack.deploy.keys`) holds every identity's certificate, key and
password in one directory. A container must see only its own, so :func:`stage_keys` copies, for each
service's identity, just what that identity needs into ``OUT/compose/keys/<identity>/``, which the compose
file bind-mounts read-only into that service alone, at :data:`KEYS_MOUNT`:

=================  ============================================================================
file               content
=================  ============================================================================
``ca.pem``         the run's CA (to verify the router, or the clients for the router)
``certs/<id>.*``   the identity's certificate and private key (CN = identity)
``zenoh.json5``    its Zenoh config, paths inside the container: TLS + mTLS + user/password;
                   the router's adds the listen endpoint and the run's access-control list
``passwords.txt``  the router only: its user:password dictionary
``web.pem/.key``   the dashboard only: the page's HTTPS certificate of the run's CA
=================  ============================================================================

Private files are written 0600 and belong to the user who runs ``flocktrack compose``; the services run
as that user (``user:``), so they can read their own files and nothing else is mounted into them.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from flocktrack.deploy.keys import KeySet, acl, client_config, identities, load_keys, router_config, write_private

#: where a service finds its own credentials inside its container
KEYS_MOUNT = "/run/flocktrack/keys"


class KeysError(ValueError):
    """The key set does not fit the deployment; the message says how to make one that does."""


def check_keys(keys_dir: str | Path, plan, dial_host: str, scenario: str) -> KeySet:
    """The key set in ``keys_dir``, checked against the run plan: its ACL names the same run, it has
    credentials for every node, and the router's certificate is valid for the host name the services dial."""
    fix = f"make one with `flocktrack keys {scenario} --out {keys_dir}`"
    try:
        ks = load_keys(keys_dir)
    except FileNotFoundError:
        raise KeysError(f"--keys {keys_dir}: no keys.json there (not a key set); {fix}") from None
    except ValueError as exc:
        raise KeysError(str(exc)) from None
    if ks.run != plan.run:
        raise KeysError(f"--keys {keys_dir}: its access-control list is for run {ks.run!r}, the scenario's run is "
                        f"{plan.run!r}; {fix}")
    missing = ks.covers(plan)
    if missing:
        raise KeysError(f"--keys {keys_dir}: no credentials for {', '.join(missing[:5])}"
                        f"{' …' if len(missing) > 5 else ''}; {fix}")
    if dial_host not in ks.hosts:
        raise KeysError(f"--keys {keys_dir}: the router's certificate is not valid for {dial_host!r} (the services "
                        f"dial it so; it covers {', '.join(ks.hosts)}); {fix} --host {dial_host}")
    return ks


def stage_keys(ks: KeySet, out_dir: str | Path, endpoint: str, listen: str, plan) -> list[Path]:
    """Write ``out_dir/compose/keys/<identity>/`` for every service of the run plan (see the module
    docstring): configs that dial ``endpoint`` (the router's: listening on ``listen``). Returns the
    directories."""
    base = Path(out_dir) / "compose" / "keys"
    inside = Path(KEYS_MOUNT)
    dirs = []
    routers = [n.slug for n in plan.nodes if n.kind == "router"]
    for ident in identities(plan):
        d = base / ident
        if d.exists():
            shutil.rmtree(d)
        (d / "certs").mkdir(parents=True)
        d.chmod(0o700)
        shutil.copyfile(ks.ca, d / "ca.pem")
        pem, key = ks.cert(ident)
        shutil.copyfile(pem, d / "certs" / f"{ident}.pem")
        write_private(d / "certs" / f"{ident}.key", key.read_bytes())
        password = ks.password(ident)
        if ident in routers:
            write_private(d / "passwords.txt", (ks.dir / "passwords.txt").read_bytes())
            conf = router_config(inside, ident, password, [listen], acl_block=acl(ks.plan()))
        else:
            conf = client_config(inside, ident, password, endpoint)
        write_private(d / "zenoh.json5", f"// {ident} of run {ks.run} in its container (flocktrack compose --secure)\n"
                                          + json.dumps(conf, indent=2) + "\n")
        if ident.startswith("dashboard-"):
            web_pem, web_key = ks.web_cert()
            shutil.copyfile(web_pem, d / "web.pem")
            write_private(d / "web.key", web_key.read_bytes())
        dirs.append(d)
    return dirs

