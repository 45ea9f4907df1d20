"""Who may press the dashboard's buttons: viewers see the run, operators steer it.

The page is read-only for everyone (flock, estimates, plots, the inspect and view panels, the replay
slider). The controls that write ``control/**`` — run control (pause, resume, step, speed), faults
(kill / restart a sensor, links, loss, partition, outlier bursts) and the plan-fault form — are built
per browser tab, on that tab's own GUI (``client.gui``), and only for a tab that connected with the
run's operator token (Jupyter's model: a token made per run, printed once, kept 0600 in the run
directory). A tab without it never receives those widgets, so it has nothing to press; and Viser hands a
widget's events only to the tab it belongs to, so a crafted websocket client cannot press another
tab's buttons either. Every control callback checks its tab once more (:meth:`Operators.allowed`).

The token travels in the websocket's path: Viser's page connects its websocket to the page's own URL
without the query string, or to the one in its ``?websocket=`` parameter, so the operator link is
``http://HOST:PORT/?websocket=ws://HOST:PORT/operator/<token>`` (:func:`operator_url`), and the server
reads the path of the tab's websocket handshake (:func:`websocket_path`).
"""

from __future__ import annotations

import hmac
import logging
import os
import math
import secrets
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

from agent import wire
from agent.ports import Ports

log = logging.getLogger(__name__)

TOKEN_ENV = "FLOCKTRACK_DASHBOARD_TOKEN"

#: the dashboard writes only the control plane; it reads what the run's other nodes write (the run plan fills
#: its reads in: every node's writes but the addressed copies)
PORTS = Ports(writes=("control/**",))
PATH_PREFIX = "/operator/"


def new_token() -> str:
    return secrets.token_urlsafe(18)


def operator_url(host: str, port: int, token: str, tls: bool = False) -> str:
    """The link that opens the page as an operator (print it once; it is the password)."""
    s = "s" if tls else ""
    return f"http{s}://{host}:{port}/?websocket=ws{s}://{host}:{port}{PATH_PREFIX}{token}"


def write_token(path: Path, token: str) -> None:
    """The token in a file only its owner may read (created 0600, never world-readable in between)."""
    path.unlink(missing_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")


def websocket_path(server, client_id: int) -> str | None:
    """The request path of a tab's websocket handshake (None if unknown). Viser keeps the connection of
    each tab (``websockets`` ``ServerConnection``, whose ``request`` is the handshake) but offers no public
    accessor: a change there makes every tab a viewer (safe), and tests/browser/test_dashboard_auth.py fails."""
    try:
        conn = server._websock_server._live_connections[client_id]
        return str(conn.request.path)
    except (AttributeError, KeyError):
        return None


class OperatorPanel(SimpleNamespace):
    """One operator tab's control widgets (its own GUI), as attributes: ``client_id``, ``g_kill_id``, …"""


class Operators:
    """The operator tabs of one dashboard and the checks on them.

    ``token`` None: no tab is an operator (a viewer-only page)."""

    def __init__(self, token: str | None):
        self.token = token
        self.panels: dict[int | None, OperatorPanel] = {}
        #: tabs by kind (operator_tabs, viewer_tabs, wrong_tokens: an operator path with another token) and
        #: refused_controls (control callbacks from tabs that are not operators: there should be none);
        #: the dashboard's stats file (stats/dashboard_0.json) carries them
        self.counters: Counter = Counter()
        self._warned = -math.inf

    @property
    def refused(self) -> int:
        return self.counters["refused_controls"]

    def is_operator(self, path: str | None) -> bool:
        """Does a tab whose websocket path is ``path`` hold the token? (Counted; a wrong token is logged.)"""
        if not path or not path.startswith(PATH_PREFIX):
            self.counters["viewer_tabs"] += 1
            return False
        if self.token and hmac.compare_digest(path[len(PATH_PREFIX):].split("?")[0].encode(), self.token.encode()):
            self.counters["operator_tabs"] += 1
            return True
        self.counters["wrong_tokens"] += 1
        now = time.monotonic()
        if now - self._warned >= 10.0:           # (a script reconnecting is a new tab each time)
            self._warned = now
            log.warning("a tab came with a wrong operator token: read-only (%d so far)",
                        self.counters["wrong_tokens"])
        return False

    def allowed(self, client_id: int | None) -> bool:
        ok = client_id in self.panels
        if not ok:
            self.counters["refused_controls"] += 1
            log.warning("control refused: tab %s is not an operator", client_id)
        return ok


def build_panel(gui, client_id: int | None, ui, orders: dict[str, float]) -> OperatorPanel:
    """The operator widgets on ``gui`` (a tab's own, or the server's in tests): run control at
    ``orders["run"]``, faults at ``orders["faults"]``, the plan-fault form at ``orders["plan"]`` and the
    shared display at ``orders["display"]``. Every initial value is clamped into its widget's range,
    whatever the shared state holds; if a widget still fails, the folders built so far are removed and the
    error raised (the caller tells the tab: never a half-built operator)."""
    p = OperatorPanel(client_id=client_id, folders=[])
    ctl = ui.guard.safe(_checked(ui, client_id), "control")
    try:
        _run_control(gui, p, ui, ctl, orders["run"])
        _faults(gui, p, ui, ctl, orders["faults"])
        _plan_fault(gui, p, ui, ctl, orders["plan"])
        p.display = _display(gui, p, ui, orders["display"])
    except Exception:
        for folder in p.folders:
            folder.remove()
        raise
    return p


def _checked(ui, client_id: int | None) -> Callable[..., None]:
    def control(verb: str, **args) -> None:
        if ui.operators.allowed(client_id):
            ui.control(verb, **args)
    return control


def _folder(gui, p: OperatorPanel, *args, **kwargs):
    """A folder of the panel's, hidden until the whole panel is built and the tab is an operator (a button
    the tab could see before would be refused), and removed with the rest if the panel fails to build."""
    f = gui.add_folder(*args, visible=False, **kwargs)
    p.folders.append(f)
    return f


def show_panel(p: OperatorPanel) -> None:
    """Show the operator's folders: call it once the tab is registered as an operator."""
    for folder in p.folders:
        folder.visible = True


def _display(gui, p: OperatorPanel, ui, order: float) -> dict:
    """The shared display's settings (dashboards/tabs.py build_display): an operator's to change."""
    from .tabs import build_display

    folder, widgets = build_display(gui, ui, order, visible=False)
    p.folders.append(folder)
    return widgets


def _run_control(gui, p: OperatorPanel, ui, control, order: float) -> None:
    """Pause / resume / step n ticks, and the realtime factor (control/pause, resume, step, speed)."""
    with _folder(gui, p, "Run control", order=order):
        gui.add_markdown("**operator**: this tab steers the run")
        p.b_run = bg = gui.add_button_group("Run", ("Pause", "Resume", "Step"))
        p.g_step_n = gui.add_number("Step ticks", 1, min=1, max=10_000, step=1)
        p.g_speed = gui.add_slider("Speed ×", 0.05, 4.0, 0.05, min(4.0, max(0.05, round(ui.info.speed, 2))),
                                   hint="realtime factor (control/speed)")

    @bg.on_click
    def _(event) -> None:
        v = event.target.value
        if v == "Step":
            control("step", n=int(p.g_step_n.value))
        else:
            control(v.lower())

    @p.g_speed.on_update
    def _(event) -> None:
        if event.client is not None:
            control("speed", factor=float(p.g_speed.value))


def _faults(gui, p: OperatorPanel, ui, control, order: float) -> None:
    """Kill / restart a sensor, drop / heal a link, link loss, partition / heal the flock, and an outlier
    burst (control/kill, restart, link_drop, link_heal, link_loss, partition, heal, outlier_burst)."""
    from .tabs import clamp_index

    n = ui.info.n
    top = max(n - 1, 0)
    sel = clamp_index(ui.selected, n)
    with _folder(gui, p, "Faults (control/**)", order=order):
        p.g_kill_id = gui.add_number("Sensor id", sel, min=0, max=top, step=1)
        kb = gui.add_button_group("Process", ("Kill sensor", "Restart sensor"))
        p.g_link_a = gui.add_number("Link a", sel, min=0, max=top, step=1)
        p.g_link_b = gui.add_number("Link b", 1 if n > 1 else 0, min=0, max=top, step=1)
        lb = gui.add_button_group("Link", ("Drop link", "Heal link"))
        p.g_loss = gui.add_slider("Link loss p", 0.0, 1.0, 0.05, 0.0)
        b_loss = gui.add_button("Set link loss")
        pb = gui.add_button_group("Flock", ("Partition", "Heal all"))
        p.g_burst_agent = gui.add_number("Outlier sensor (−1 = all)", -1, min=-1, max=top, step=1)
        p.g_burst_ticks = gui.add_number("Outlier ticks", 20, min=1, max=100_000, step=1)
        p.g_burst_mag = gui.add_number("Outlier magnitude", 5.0, min=0.0, max=1e6, step=0.5)
        p.b_burst = gui.add_button("Inject outlier burst")

    kb.on_click(lambda e: control("kill" if e.target.value == "Kill sensor" else "restart",
                                  agent=int(p.g_kill_id.value)))
    lb.on_click(lambda e: control("link_drop" if e.target.value == "Drop link" else "link_heal",
                                  a=int(p.g_link_a.value), b=int(p.g_link_b.value)))
    b_loss.on_click(lambda _e: control("link_loss", p=float(p.g_loss.value)))
    pb.on_click(lambda e: control("partition", groups=ui.partition_groups()) if e.target.value == "Partition"
                else control("heal"))
    p.b_burst.on_click(lambda _e: control("outlier_burst", agent=int(p.g_burst_agent.value),
                                          ticks=int(p.g_burst_ticks.value), magnitude=float(p.g_burst_mag.value)))


def _plan_fault(gui, p: OperatorPanel, ui, control, order: float) -> None:
    """Folded: the "Plan fault" form (control/inject, see :func:`inject_from_form`) and healing one live
    fault by its id (control/heal_fault)."""
    from agent.wire import FAULT_KINDS

    with _folder(gui, p, "Plan fault (control/inject)", expand_by_default=False, order=order):
        p.g_inj_kind = gui.add_dropdown("Kind", FAULT_KINDS, initial_value="delay")
        p.g_inj_targets = gui.add_text("Targets", "agents:0")
        p.g_inj_params = gui.add_text("Parameters", "delay_ms=80 jitter_ms=20 direction=in")
        p.g_inj_ticks = gui.add_number("Ticks (0 = until healed)", 100, min=0, max=10**7, step=1)
        b_inj = gui.add_button("Inject")
        p.g_inj_id = gui.add_number("Live fault id", 1000, min=1000, max=10**6, step=1)
        b_heal_one = gui.add_button("Heal this fault")

    b_inj.on_click(lambda _e: inject_from_form(p, control))
    b_heal_one.on_click(lambda _e: control("heal_fault", id=int(p.g_inj_id.value)))


def inject_from_form(p: OperatorPanel, control: Callable[..., None]) -> bool:
    """The "Plan fault" form → control/inject (the world validates it and answers on world/event with
    the fault's id, or "rejected" and the reason). Words that are not name=value are flagged in place."""
    try:
        args = wire.control_args(p.g_inj_params.value)
    except ValueError as exc:
        p.g_inj_params.value = f"{p.g_inj_params.value.split('  ←')[0]}  ← {exc}"
        return False
    args.update(kind=p.g_inj_kind.value, targets=p.g_inj_targets.value.strip())
    if int(p.g_inj_ticks.value) > 0:
        args["ticks"] = int(p.g_inj_ticks.value)
    control("inject", **args)
    return True
