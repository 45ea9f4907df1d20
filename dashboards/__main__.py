"""python -m dashboards — the live dashboard of a run, or a recording with a time slider.

Live (spawned by ``flocktrack run … --dashboard`` as ``dashboard/0``)::

    python -m dashboards --run RUN --connect tcp/127.0.0.1:7447 --port 8080 --scenario RUN_DIR/scenario.toml

Replay (``flocktrack replay FILE --dashboard``)::

    python -m dashboards --recording runs/demo/recording.mcap --port 8080

Static picture of a recording (no server; the last tick, or ``--tick K``)::

    python -m dashboards --recording runs/demo/recording.mcap --png docs/summary.png
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading

# one consumer thread: BLAS worker threads (λ₂ of a 100-node Laplacian) would only contend with the flock
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m dashboards", description=__doc__.split("\n")[0])
    ap.add_argument("--run", help="run name (key prefix ft/<run>/); live mode")
    ap.add_argument("--connect", default="tcp/127.0.0.1:7447", help="Zenoh router endpoint (live)")
    ap.add_argument("--scenario", help="the run's scenario TOML (live; design.json beside it is used if present)")
    ap.add_argument("--design", help="pre-run design JSON (TMSEE lower bound); default: beside the scenario")
    ap.add_argument("--recording", help="an MCAP recording to show with a time slider (replay mode)")
    ap.add_argument("--port", type=int, default=8080, help="HTTP/websocket port of the page")
    ap.add_argument("--host", default="127.0.0.1", help="interface to serve on (0.0.0.0 in containers)")
    ap.add_argument("--public-port", type=int, default=None,
                    help="live: the port users open, for the logged operator link (a container's published "
                         "host port; default: --port)")
    ap.add_argument("--config", default=None, help="Zenoh json5 config for this process")
    ap.add_argument("--plan", help="live: the run plan (plan.json): what to subscribe to (the dashboard node's reads)")
    ap.add_argument("--exit-on-end", action="store_true", help="live: exit one second after world/end")
    ap.add_argument("--operator-token-file", help="live: file holding the run's operator token (default: "
                                                  "$FLOCKTRACK_DASHBOARD_TOKEN, else a new token, its link logged)")
    ap.add_argument("--viewer-only", action="store_true", help="live: no operator at all (a read-only page)")
    ap.add_argument("--max-tabs", type=int, default=16,
                    help="live: browser tabs served at once; one more is refused with the reason (default 16)")
    ap.add_argument("--tls-cert", help="live: serve the page over HTTPS with this certificate (PEM) ...")
    ap.add_argument("--tls-key", help="... and its key (a secure run's: certs/dashboard-web.{pem,key})")
    ap.add_argument("--play", action="store_true", help="replay: start playing at once")
    ap.add_argument("--png", help="replay: write a static PNG of the recording and exit (no server)")
    ap.add_argument("--tick", type=int, default=None, help="--png: the tick to draw (default: the last)")
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = parser()
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    stop = threading.Event()

    def on_stop(*_):
        """Stop the loop and wake its poll. A dashboard writes nothing, so if it still has not stopped 10 s
        later it dumps every thread's stack to its log — the evidence — and exits anyway: a process asked to
        stop, stops."""
        from agent.bus import wake_all

        stop.set()
        wake_all()        # the loop's poll may sit in its queue (agent/bus.py wake_all)

        def watchdog():   # a daemon thread: a normal exit ends it first
            import faulthandler
            import time

            time.sleep(10.0)
            logging.getLogger("dashboards").error("did not stop within 10 s of the signal; threads:")
            faulthandler.dump_traceback(all_threads=True)
            sys.stderr.flush()
            os._exit(0)

        threading.Thread(target=watchdog, daemon=True).start()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_stop)

    from .live import replay_model_from_file, run_live, run_replay

    if args.recording:
        if args.png:
            import importlib.util

            from .plots import save_static_png

            if importlib.util.find_spec("matplotlib") is None:
                print("error: --png needs matplotlib, an optional dependency of flocktrack; install it with: "
                      "pip install 'flocktrack[figures]'", file=sys.stderr)
                return 2
            model = replay_model_from_file(args.recording)
            k = model.last if args.tick is None else args.tick
            save_static_png(args.png, model.series(k), model.snapshot(k), model.info.n,
                            title=f"{model.info.name} · {model.info.estimator}", link_range=model.info.link_range)
            print(f"wrote {args.png} (tick {model.seek(k)})")
            return 0
        return run_replay(args.recording, args.port, host=args.host, stop_event=stop, autoplay=args.play)
    if not (args.run and args.scenario):
        ap.error("live mode needs --run and --scenario (or give --recording)")
    if bool(args.tls_cert) != bool(args.tls_key):
        ap.error("--tls-cert and --tls-key go together")
    from agent.runner import observer_priority

    from .guard import Limits
    from .state import RunInfo

    observer_priority()          # the flock first (a live dashboard is an observer of the run)
    info = RunInfo.from_files(args.scenario, args.design)
    from .live import EVERYTHING, plan_reads

    try:
        reads = plan_reads(args.plan) if args.plan else EVERYTHING
    except (OSError, ValueError) as exc:
        ap.error(f"--plan: {exc}")
    return run_live(args.run, args.connect, args.port, info, host=args.host, config_file=args.config,
                    subscriptions=reads,
                    exit_on_end=args.exit_on_end, stop_event=stop, operator_token=operator_token(args),
                    tls=(args.tls_cert, args.tls_key) if args.tls_cert else None,
                    limits=Limits(max_tabs=max(1, args.max_tabs)))


def operator_token(args) -> str | None:
    """The run's operator token: from --operator-token-file, else $FLOCKTRACK_DASHBOARD_TOKEN, else a new one
    (its link is logged once, as Jupyter prints its token, with the port users open: --public-port, e.g. the
    host port compose publishes the container's on); --viewer-only: none (nobody can steer)."""
    from .operator import TOKEN_ENV, new_token, operator_url

    if args.viewer_only:
        return None
    if args.operator_token_file:
        with open(args.operator_token_file) as f:
            return f.read().strip() or None
    if os.environ.get(TOKEN_ENV):
        return os.environ[TOKEN_ENV]
    token = new_token()
    shown = "localhost" if args.host in ("127.0.0.1", "0.0.0.0", "::") else args.host
    logging.getLogger("dashboards").info("operator link (steers the run; keep it private): %s",
                                         operator_url(shown, args.public_port or args.port, token,
                                                      tls=bool(args.tls_cert)))
    return token


if __name__ == "__main__":
    sys.exit(main())
