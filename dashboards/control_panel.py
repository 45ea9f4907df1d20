"""The shared part of the control panel docked right: the status line at its top, the replay's slider and
playback buttons, the legend at its bottom.

Each tab adds its own folders between them at the places of :data:`LAYOUT`: its view and inspector
(dashboards/tabs.py) and, an operator's, run control, faults, the plan-fault form and the display
(dashboards/operator.py).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from .state import ReplayModel, RunInfo

#: where each part of the control panel goes, top to bottom: the shared parts (status, replay, the
#: legend) and each tab's own (dashboards/tabs.py: view, inspect; an operator's, dashboards/operator.py:
#: run control, faults, the plan-fault form, display)
LAYOUT = {"status": 1.0, "note": 1.5, "replay": 2.0, "run": 2.5, "view": 3.0, "inspect": 4.0, "faults": 5.0,
          "plan": 6.0, "display": 7.0, "legend": 8.0}

LEGEND = ("colour: own error, green (low) → red (≥ scale); grey = dead  \n"
          "● sensor  ◆ its estimate  red ball = target (trail)  purple = fusion  \n"
          "orange = selected sensor's links, blue = its covariance ellipse")


class ControlPanel:
    """The theme, the docked control panel and its status line on ``gui`` (the server's) at the places of
    ``layout``; live, a note that the controls are on the operator's link. :meth:`add_legend` closes it."""

    def __init__(self, gui, layout: dict[str, float], info: RunInfo, *, live: bool):
        self.gui, self.layout, self.info, self.live = gui, layout, info, live
        gui.configure_theme(control_width="large", show_share_button=False, show_logo=False,
                            brand_color=(40, 90, 160))
        # docked, not floating over the scene: the canvas is then exactly the part of the scene the user
        # sees, and a camera centred on the flock shows it clear of the panel (a floating panel hid the
        # flock, which sits in the canvas's middle, behind it)
        gui.main_panel.dock_right()
        self.g_status = gui.add_markdown("waiting for the first tick …", order=layout["status"])
        if live:
            gui.add_markdown("*read-only; the run and fault controls are on the run's operator link "
                             "(`flocktrack run` prints it)*", order=layout["note"])

    def add_legend(self) -> None:
        self.gui.add_markdown(LEGEND, order=self.layout["legend"])

    def render_status(self, st: dict) -> None:
        """The status line from a summary (:meth:`dashboards.state.DashboardState.summary`)."""
        def f(v, fmt="{:.3g}"):
            return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else fmt.format(v)

        info = self.info
        mode = "replay" if not self.live else ("**paused**" if st.get("paused") else "running")
        if st.get("ended"):
            mode = "ended" if self.live else mode
        lines = [f"**{info.name}** · {info.n} sensors · {info.estimator} · {mode}",
                 f"tick **{f(st.get('k'), '{}')}** (world at {f(st.get('latest_tick'), '{}')}) · "
                 f"t = {f(st.get('t'), '{:.2f}')} s",
                 f"RMSE {f(st.get('rmse'))} · λ₂ {f(st.get('lambda2'))} · links {f(st.get('links'), '{:.0f}')}",
                 f"{f(st.get('msg_rate'), '{:.0f}')} msg/s · dropped {f(st.get('drop_rate'), '{:.1f}')}/s "
                 f"(bus {st.get('bus_dropped', 0)}, missing {st.get('missing', 0)})"]
        if st.get("speed") is not None:
            lines.append(f"speed ×{f(st.get('speed'))}")
        if st.get("last_event"):
            lines.append(f"last event: `{st['last_event']}`")
        text = "  \n".join(lines)
        if text != self.g_status.content:
            self.g_status.content = text


class Playback:
    """Replay: the tick slider, play / pause / first / last, and the playback speed, on ``gui`` at
    ``order`` (shared: a replay has nothing to steer, and every tab watches the same recording). ``k`` is
    the tick shown, ``playing`` whether it advances; ``on_seek()`` is called when ``k`` changes; ``safe``
    wraps the callbacks (:meth:`dashboards.guard.TabGuard.safe`)."""

    def __init__(self, gui, replay: ReplayModel | None, order: float, *, safe, on_seek: Callable[[], None]):
        self.replay, self.on_seek = replay, on_seek
        self.k = replay.first if replay else 0
        self.playing = False
        with gui.add_folder("Replay", order=order):
            self.g_slider = gui.add_slider("Tick", replay.first if replay else 0, max(replay.last if replay else 1, 1),
                                           1, replay.first if replay else 0)
            bg = gui.add_button_group("Playback", ("Play", "Pause", "First", "Last"))
            self.g_speed = gui.add_slider("Playback ×", 0.1, 10.0, 0.1, 1.0)
        self.g_slider.on_update(safe(lambda _e: self.seek(int(self.g_slider.value)), "seek"))
        bg.on_click(safe(lambda e: self.press(e.target.value), "playback"))

    def seek(self, k: int) -> None:
        self.k = k
        self.on_seek()

    def press(self, v: str) -> None:
        """A playback button: "Play", "Pause", "First" or "Last"."""
        if v == "Play":
            self.playing = True
        elif v == "Pause":
            self.playing = False
        elif v in ("First", "Last") and self.replay:
            self.playing = False
            self.g_slider.value = self.replay.first if v == "First" else self.replay.last

    def attach(self, model: ReplayModel) -> None:
        """The recording is loaded: the slider spans its ticks, from its first."""
        self.replay = model
        self.g_slider.min = model.first
        self.g_slider.max = max(model.last, model.first + 1)
        self.g_slider.value = model.first
        self.k = model.first
