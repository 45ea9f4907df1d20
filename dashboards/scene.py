"""The shared 3-D scene every tab sees: the ground grid, the range circles, the links, the suspicions (red:
from a sensor to the neighbour whose payloads it discarded this tick), the target's trail, the sensors and
their estimates, the target and the fusion estimate.

A redraw is a handful of batched messages (one point cloud for all sensors, one line-segment set for all
links, …) made from a snapshot by :func:`dashboards.plots.scene_arrays`. What a tab selects is drawn on
that tab's own scene (dashboards/tabs.py), not here.
"""

from __future__ import annotations

import math

import numpy as np

from . import plots
from .state import RunInfo, Snapshot
from .tabs import DisplaySettings, set_segments, show


def set_cloud(h, pts: np.ndarray, colors, visible: bool = True) -> None:
    """Draw ``pts`` in ``colors`` with the point-cloud handle ``h`` (hidden when ``visible`` is off or there
    are none)."""
    if not visible or len(pts) == 0:
        show(h, False)
        return
    h.points = pts
    h.colors = np.asarray(colors, np.uint8)
    show(h, True)


class FlockScene:
    """The shared scene's objects on ``server``, sized from the run's link range; the server's initial
    camera looks at the origin until the first tick frames the flock (dashboards/camera.py)."""

    def __init__(self, server, info: RunInfo):
        self.server, self.info = server, info
        s = server.scene
        s.set_up_direction("+z")
        # no shadow maps: a flat flock needs none, and every redraw (≤ 10/s) would render the scene twice
        # (measured: software-rendered Chromium went from 6 to ~20 frames/s)
        s.configure_default_lights(True, cast_shadow=False)
        r = info.link_range if math.isfinite(info.link_range) else 10.0
        self.extent = max(2.5 * r, 25.0)
        server.initial_camera.position = tuple(-1.4 * self.extent * plots.VIEW_DIRECTION)
        server.initial_camera.look_at = (0.0, 0.0, 0.0)
        self.world = s.add_frame("/world", show_axes=False)
        cell = 10 ** math.floor(math.log10(max(r, 1.0)))
        # the ground grid as plain line segments: Viser's shader grid covers the whole view and cost more
        # than the rest of the scene together in a software-rendered browser (measured: 9 → 22 frames/s)
        s.configure_environment_map(None)
        self.grid = s.add_line_segments("/world/grid", plots.grid_segments(10 * self.extent, cell), (222, 222, 222),
                                        thickness=1.0, thickness_units="screen")
        z = np.zeros((1, 3), np.float32)
        zs = np.zeros((1, 2, 3), np.float32)
        self.h_circles = s.add_line_segments("/world/ranges", zs, (160, 185, 215), thickness=1.0,
                                             thickness_units="screen", visible=False)
        self.h_links = s.add_line_segments("/world/links", zs, (70, 110, 170), thickness=2.0,
                                           thickness_units="screen", visible=False)
        self.h_suspicions = s.add_line_segments("/world/suspicions", zs, (225, 25, 35), thickness=3.5,
                                                thickness_units="screen", visible=False)
        self.h_trail = s.add_line_segments("/world/trail", zs, (215, 40, 40), thickness=2.5,
                                           thickness_units="screen", visible=False)
        size = max(0.06 * r, 0.3)
        self.h_sensors = s.add_point_cloud("/world/sensors", z, (0, 0, 0), point_size=1.4 * size,
                                           point_shape="circle", precision="float32", visible=False)
        self.h_est = s.add_point_cloud("/world/estimates", z, (0, 0, 0), point_size=0.7 * size,
                                       point_shape="diamond", precision="float32", visible=False)
        self.h_target = s.add_icosphere("/world/target", radius=0.45 * size, color=(215, 30, 40), visible=False,
                                        cast_shadow=False, receive_shadow=False)
        self.h_fusion = s.add_icosphere("/world/fusion", radius=0.4 * size, color=(148, 103, 189), visible=False,
                                        cast_shadow=False, receive_shadow=False)
        self.marker_size = size
        #: the suspicions are drawn this much above the links they lie on (no depth fight with them)
        self.lift = np.array([0.0, 0.0, 0.1 * size], np.float32)

    def draw(self, snap: Snapshot, display: DisplaySettings, err_rows: np.ndarray | None = None) -> plots.SceneArrays:
        """Redraw from ``snap`` what ``display`` shows, coloured by own error on ``display``'s scale (0: the
        scale of ``err_rows``, the recent errors, else of the snapshot's)."""
        d = display
        scale = d.err_scale if d.err_scale > 0 else \
            plots.auto_error_scale(err_rows if err_rows is not None else snap.errors)
        sa = plots.scene_arrays(snap, error_scale=scale, link_range=self.info.link_range, show_circles=d.circles)
        with self.server.atomic():
            set_cloud(self.h_sensors, sa.sensor_points, sa.sensor_colors)
            set_cloud(self.h_est, sa.estimate_points, sa.estimate_colors, d.estimates)
            set_segments(self.h_links, sa.links, d.links)
            set_segments(self.h_suspicions, sa.suspicions + self.lift)
            set_segments(self.h_circles, sa.circles, d.circles)
            set_segments(self.h_trail, sa.trail, d.trail)
            if sa.target is not None:
                self.h_target.position = tuple(sa.target)
                self.h_target.visible = True
            if sa.fusion is not None:
                self.h_fusion.position = tuple(sa.fusion)
                self.h_fusion.visible = True
            else:
                self.h_fusion.visible = False
        return sa

    def nearest(self, snap: Snapshot | None, origin, direction) -> int | None:
        """The sensor of ``snap`` nearest to where a click's ray (``origin``, ``direction``) meets the
        ground, if it is near enough to mean it (None: nothing there, or no ray)."""
        if snap is None or origin is None or direction is None:
            return None
        o, dvec = np.asarray(origin, float), np.asarray(direction, float)
        o = o - np.asarray(self.world.position, float)  # into the /world frame
        if abs(dvec[2]) < 1e-9:
            return None
        t = -o[2] / dvec[2]
        if t <= 0:
            return None
        p = o + t * dvec
        d = np.linalg.norm(snap.positions[:, :2] - p[None, :2], axis=1)
        d[~np.isfinite(d)] = np.inf
        i = int(np.argmin(d))
        near = max(3 * self.marker_size, 0.15 * self.info.link_range if math.isfinite(self.info.link_range) else 3)
        return i if d[i] <= near else None
