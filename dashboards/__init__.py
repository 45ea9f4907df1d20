"""The flocktrack dashboard: a Viser web page showing the flock, the estimates, the links and the error
traces of a run, live (a read-only subscriber to ``ft/<run>/**`` that writes only ``control/**``) or from a
recording (time slider).

* :mod:`dashboards.state` — a pure model of what is shown, fed message by message (testable alone);
* :mod:`dashboards.plots` — data → figures (batched scene arrays, uPlot panels, a static PNG);
* :mod:`dashboards.nees` — the NEES of the node estimates and the χ² band of its mean;
* :mod:`dashboards.live`  — the live loop (bus → state → page) and the replay's;
* :mod:`dashboards.ui`    — the page: the Viser server and its panels (:mod:`~dashboards.scene`,
  :mod:`~dashboards.camera`, :mod:`~dashboards.plot_panel`, :mod:`~dashboards.control_panel`, each tab's
  :mod:`~dashboards.tabs` and :mod:`~dashboards.operator`);
* :mod:`dashboards.probe` — headless tabs for load-testing a dashboard (``python -m dashboards.probe``);
* ``python -m dashboards`` — the process the launcher spawns (``--run/--connect``) or the replay
  (``--recording``).

Floors: imports only :mod:`agent` (never ``flocktrack`` or ``topology``).
"""
