"""The error traces and the other live series, as uPlot panels in a panel of their own docked left.

Each panel's data and lines come from :func:`dashboards.plots.uplot_panels`; a redraw sends each panel's
new data, and a panel whose set of lines changed is built anew. The NEES panel appears once an estimate
with a covariance has been scored, the suspicions panel once a resilient consensus reports whom it
discarded; each then stays.
"""

from __future__ import annotations

import numpy as np

from . import plots
from .state import RunInfo


class PlotPanel:
    """The "Plots" panel on ``server``'s GUI, for a run of ``info``; at most ``max_points`` rows of each
    series go to the browser (:func:`dashboards.plots.decimate`)."""

    #: the panels top to bottom
    ORDER = {k: 100 + i for i, k in enumerate(["errors", "tmsee", "disagreement", "nees", "suspicions", "lambda2",
                                               "rates"])}

    def __init__(self, server, info: RunInfo, *, max_points: int = 1500):
        self.server, self.info, self.max_points = server, info, max_points
        self.has_fusion = False           # once a fusion line is drawn it stays (the panel keeps its lines)
        self.has_nees = False             # once the NEES panel is shown it stays
        self.has_suspicion = False        # once the suspicions panel is shown it stays
        self.handles: dict = {}           #: panel key → its uPlot handle
        self.last_k: int | None = None    #: the last tick drawn (None: redraw at the next call)
        gui = server.gui
        panel = gui.add_panel()
        self.tab = panel.add_tab("Plots")
        panel.dock_left()
        panel.set_width(460)
        with self.tab:
            gui.add_markdown("live series (uPlot; drag to zoom, double-click to reset)", order=1)

    def render(self, series: dict[str, np.ndarray], selected: int | None, force: bool = False) -> bool:
        """Redraw from ``series`` (the error panel's highlighted line: sensor ``selected``) if its last tick
        is new, or with ``force``; False when there was nothing to draw."""
        if not len(series["k"]):
            return False
        last_k = int(series["k"][-1])
        if last_k == self.last_k and not force:
            return False
        self.last_k = last_k
        ser = plots.decimate(series, self.max_points)
        self.has_fusion = self.has_fusion or plots.has_values(series.get("fusion_err"))
        self.has_nees = self.has_nees or plots.has_values(series.get("nees"))
        self.has_suspicion = self.has_suspicion or plots.has_values(series.get("suspected"))
        specs = plots.uplot_panels(ser, self.info.n, selected, has_lower=self.info.tmsee_lower is not None,
                                   has_fusion=self.has_fusion, has_nees=self.has_nees,
                                   has_suspicion=self.has_suspicion)
        with self.server.atomic():
            for spec in specs:
                h = self.handles.get(spec.key)
                if h is None or [s.get("label", "") for s in h.series] != spec.labels:
                    if h is not None:
                        h.remove()
                    self.handles[spec.key] = self._add(spec)
                else:
                    h.data = tuple(np.asarray(a, float) for a in spec.data)
        return True

    def _add(self, spec: plots.PanelSpec):
        """A new uPlot panel for ``spec`` at its place (:attr:`ORDER`)."""
        with self.tab:
            return self.server.gui.add_uplot(data=tuple(np.asarray(a, float) for a in spec.data), series=spec.series,
                                             title=spec.title, scales=spec.scales, axes=spec.axes, aspect=2.5,
                                             order=self.ORDER[spec.key])
