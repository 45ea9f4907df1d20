"""A standalone Zenoh router process: ``python -m flocktrack.launch.router [--config FILE] [--listen EP[,EP]]``.

``flocktrack run`` opens its router inside the launcher process (``launch.open_router``); a deployment
of separate containers or hosts needs the router as a process of its own, and this is it — the same
``eclipse-zenoh`` the agents use, so no separately installed ``zenohd`` is needed. It opens
``zenoh.open(config)`` in router mode (config: a json5 file, or the name of one the package ships in
``broker_cfg/``, e.g. ``compose_router.json5``; ``--listen`` overrides the file's listen endpoints), prints one ``listening on …`` line, and serves
until SIGTERM or SIGINT, then closes the session and exits 0 (exit 1 if the router cannot open,
e.g. the port is taken).
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m flocktrack.launch.router", description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=None, help="Zenoh json5 config file, or the name of one in the package's "
                                                   "broker_cfg/ (router mode is forced)")
    ap.add_argument("--listen", default=None,
                    help="listen endpoint(s), comma-separated, e.g. tcp/0.0.0.0:7447 (default: the config's)")
    args = ap.parse_args(argv)

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())

    import zenoh

    from flocktrack.launch.health import zenoh_config  # = agent.bus.zenoh_config, without importing numpy
    from flocktrack.resources import MissingDataError, config_file

    zenoh.init_log_from_env_or("error")
    try:
        path = str(config_file(args.config)) if args.config else None
    except (FileNotFoundError, MissingDataError) as exc:
        print(f"error: --config: {exc}", file=sys.stderr)
        return 1
    try:
        conf = zenoh_config(listen=args.listen, mode="router", config_file=path)
        session = zenoh.open(conf)
    except Exception as exc:  # zenoh.ZError: bad config, port in use, …
        print(f"error: cannot open the Zenoh router: {exc}", file=sys.stderr)
        return 1
    try:
        where = args.listen or _config_listen(conf)
        print(f"flocktrack router {session.zid()} listening on {where}", flush=True)
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
    print("flocktrack router stopped", flush=True)
    return 0


def _config_listen(conf) -> str:
    try:
        return conf.get_json("listen/endpoints")
    except Exception:
        return "(the config's endpoints)"


if __name__ == "__main__":
    sys.exit(main())
