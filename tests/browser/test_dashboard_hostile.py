"""Hostile tabs (dashboards/guard.py): tokenless and wrong-token websocket clients speaking the page's
protocol send random updates — random values of every type and size, to every widget id they were sent
and to ids they were not, with fields other than ``value`` — camera and pointer reports with garbage in
them, message types only a server sends, and frames that do not decode (hypothesis writes the script).
Afterwards nothing shared has changed, no control went out, every refusal was counted, the log holds a few
lines and no traceback, and an operator who connects after them gets whole controls and steers the run.

First against a DashboardUI in this process (many scripts, fast); then against a real run (a lockstep run of
the demo, one process per sensor over Zenoh, the dashboard its own process): the viewers attack, then an
operator pauses, steps and resumes it, the world acknowledges each on ``world/event``, and the run's
estimates are those of the same seed run without them."""

from __future__ import annotations

import io
import logging
import threading
import time
from pathlib import Path

import msgspec
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from dashboards.probe import Tab, operator_ui, wait

ROOT = Path(__file__).resolve().parents[2]
#: the most the dashboard may log about the hostile tabs of one test (its own lines included)
LOG_LIMIT = 24_000
WRONG = ("/", "/", "/operator/not-the-token", "/operator/")

# ---------------------------------------------------------------------------- what a hostile tab sends

VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.sampled_from([10**18, -10**18, 2**53 + 1]),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=40), st.just("x" * 10_000),
    st.binary(max_size=64), st.lists(st.integers(-5, 5), max_size=4),
    st.dictionaries(st.text(max_size=5), st.integers(-2**63, 2**64 - 1), max_size=3))   # msgpack's ints
PROPS = st.sampled_from(["value", "value", "value", "min", "max", "options", "update_cb", "sync_cb", "removed",
                         "nonexistent"])
SERVER_TYPES = st.sampled_from(["ShareUrlRequest", "ShareUrlDisconnect", "GetRenderResponseMessage",
                                "FileTransferStartUpload", "FileTransferPart", "GuiFormSubmitMessage",
                                "SetCameraLookAtMessage", "GuiButtonHoldMessage", "CommandTriggerMessage",
                                "NoSuchMessage"])
ACTION = st.one_of(
    st.tuples(st.just("update"), st.integers(0, 10**6), st.lists(st.tuples(PROPS, VALUES), min_size=1, max_size=3)),
    st.tuples(st.just("update_unseen"), st.text(max_size=40), VALUES),
    st.tuples(st.just("message"), SERVER_TYPES, st.dictionaries(st.text(max_size=12), VALUES, max_size=4)),
    st.tuples(st.just("camera"), st.sampled_from(["wxyz", "position", "fov", "look_at", "image_width"]), VALUES),
    st.tuples(st.just("pointer"), st.sampled_from(["event_type", "ray_origin", "screen_pos"]), VALUES),
    st.tuples(st.just("frame"), st.one_of(st.binary(max_size=200), VALUES.map(msgspec.msgpack.encode)), st.none()),
)
SCRIPT = st.lists(st.tuples(st.integers(0, len(WRONG) - 1), ACTION), min_size=1, max_size=40)


def _camera(field: str, value) -> dict:
    m = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [0.0, -30.0, 20.0], "fov": 1.0,
         "near": 0.01, "far": 1000.0, "image_height": 800, "image_width": 600, "look_at": [0.0, 0.0, 0.0],
         "up_direction": [0.0, 0.0, 1.0]}
    m[field] = value
    return m


def _pointer(field: str, value) -> dict:
    m = {"type": "ScenePointerMessage", "event_type": "click", "ray_origin": [0.0, 0.0, 10.0],
         "ray_direction": [0.0, 0.0, -1.0], "screen_pos": [[0.5, 0.5]], "modifier": None}
    m[field] = value
    return m


def _message(tab: Tab, action) -> dict | bytes:
    """One action of the script as what goes on the wire (bytes: a raw frame)."""
    kind, a, b = action
    if kind == "update":
        uuid = tab.uuids[a % len(tab.uuids)] if tab.uuids else "nothing-seen"
        return {"type": "GuiUpdateMessage", "uuid": uuid, "updates": dict(b)}
    if kind == "update_unseen":
        return {"type": "GuiUpdateMessage", "uuid": a, "updates": {"value": b}}
    if kind == "message":
        return {**b, "type": a}
    if kind == "camera":
        return _camera(a, b)
    if kind == "pointer":
        return _pointer(a, b)
    return a


class Attack:
    """Tokenless and wrong-token tabs (:data:`WRONG`) on the dashboard at ``port``; a tab the server closed
    (a malformed frame, too many messages) is opened again, as a script would."""

    def __init__(self, port: int):
        self.port = port
        self.tabs = [Tab(port, path) for path in WRONG]
        self.sent = self.reopened = 0

    def run(self, script) -> None:
        for who, action in script:
            tab = self._open(who)
            m = _message(tab, action)
            ok = tab.send_raw(m) if isinstance(m, bytes) else tab.send(m)
            self.sent += ok

    def every_value_to_every_widget(self, value) -> None:
        """The first report's attack: ``value`` written into every widget every tab has seen."""
        for i, tab in enumerate(self.tabs):
            for uuid in list(tab.uuids):
                self._open(i).press(uuid, value)

    def _open(self, who: int) -> Tab:
        tab = self.tabs[who]
        if tab.closed.is_set():
            tab = self.tabs[who] = Tab(self.port, WRONG[who])
            self.reopened += 1
            wait(lambda: tab.uuids or tab.closed.is_set(), 10)
        return tab

    def close(self) -> None:
        for tab in self.tabs:
            tab.close()


class LogTap(logging.Handler):
    """Every line logged in this process while it is attached (formatted as the dashboard's log is)."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.buf = io.StringIO()
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))

    def emit(self, record) -> None:
        self.buf.write(self.format(record) + "\n")

    @property
    def text(self) -> str:
        return self.buf.getvalue()


# ---------------------------------------------------------------------------- in this process

def test_hostile_tabs_change_nothing_shared_and_a_later_operator_still_steers(capfd):
    from dashboards.tabs import DisplaySettings

    tap = LogTap()
    logging.getLogger().addHandler(tap)
    try:
        with operator_ui(8) as (ui, sent, socks):
            attack = Attack(ui.port)
            socks.append(attack)
            assert wait(lambda: all(t.uuids for t in attack.tabs) and len(ui.tabs) == len(WRONG))
            attack.every_value_to_every_widget(10**18)       # the first report: a huge sensor id, everywhere

            @settings(max_examples=25, deadline=None, database=None, derandomize=True,
                  suppress_health_check=list(HealthCheck))
            @given(script=SCRIPT)
            def hostile(script) -> None:
                attack.run(script)

            hostile()
            time.sleep(1.0)                                  # (what is still in flight lands)
            assert sent == [] and ui.operators.panels == {}
            assert ui.selected == 0 and ui.display == DisplaySettings(circles=True)
            for panel in ui.tabs.values():                  # each viewer's own choice stays a sensor it can see
                assert 0 <= panel.selected < 8
            g = ui.guard.stats()
            assert g.get("total_invalid_updates", 0) > 0, g
            assert g.get("total_malformed_frames", 0) + g.get("total_unknown_messages", 0) > 0, g
            assert ui.operators.counters["wrong_tokens"] >= 2
            op = Tab(ui.port, "/operator/the-token")
            socks.append(op)
            assert wait(lambda: len(ui.operators.panels) == 1)
            (cid, panel), = ui.operators.panels.items()
            assert panel.g_kill_id.value == 0 and panel.g_link_a.value == 0   # a whole panel, clamped
            run = panel.b_run._impl.uuid
            for i, verb in enumerate(("Pause", "Step", "Resume")):   # (each callback runs in Viser's pool)
                op.press(run, verb)
                assert wait(lambda i=i: len(sent) == i + 1), sent
            assert sent == [("pause", {}), ("step", {"n": 1}), ("resume", {})]
            assert ui.guard.tabs[cid].counters.get("invalid_updates", 0) == 0
    finally:
        logging.getLogger().removeHandler(tap)
    err = capfd.readouterr().err
    logged = tap.text + err
    assert "Traceback" not in logged and "never retrieved" not in logged, logged[-3000:]
    assert len(logged) < LOG_LIMIT, (len(logged), logged[-3000:])
    assert "x" * 100 not in logged                           # no payload echoed


def test_a_tab_past_the_cap_is_refused_and_a_flooding_tab_is_closed():
    from dashboards.guard import Limits

    with operator_ui(4, limits=Limits(max_tabs=2, close_after=50)) as (ui, sent, socks):
        a, b = Tab(ui.port), Tab(ui.port)
        socks += [a, b]
        assert wait(lambda: len(ui.tabs) == 2)
        c = Tab(ui.port)
        socks.append(c)
        assert wait(c.closed.is_set) and ui.guard.counters["refused_tabs"] == 1
        assert c.ws.close_code == 1013 and "at most 2 tabs" in c.ws.close_reason
        assert wait(lambda: a.uuids)
        node = ui.tabs[min(ui.tabs)].widgets["node"]._impl.uuid
        while a.press(node, "1") and not a.closed.is_set():  # far beyond 30 updates a second
            pass
        assert wait(a.closed.is_set)
        assert ui.guard.counters["closed_for_rate"] == 1 and a.ws.close_code == 1008
        assert not b.closed.is_set() and sent == []


# ---------------------------------------------------------------------------- against a real run

RUN_TICKS = 400
TOKEN = "hostile-test-operator"


def _run(tmp: Path, driver=None):
    """The demo in lockstep (seed fixed by the scenario), one process per sensor over Zenoh; with
    ``driver`` the dashboard too, and ``driver(launcher)`` started in its own thread on the first poll."""
    from agent.scenario import parse_scenario, scenario_data
    from flocktrack.launch.launcher import free_port
    from flocktrack.engine.run import run_zenoh_to_dir

    data = scenario_data(str(ROOT / "scenarios" / "demo.toml"), [],
                         **{"run.ticks": RUN_TICKS, "run.mode": "lockstep"})
    sc = parse_scenario(data, "demo.toml")
    port = free_port() if driver else None
    started: list = []

    def on_poll(launcher) -> None:
        if driver and not started:
            started.append(threading.Thread(target=driver, args=(launcher, port), daemon=True))
            started[0].start()

    run_zenoh_to_dir(sc, data, tmp, dashboard_port=port, dashboard_token=TOKEN if driver else None, quiet=True,
                     on_poll=on_poll, timeout_s=600)
    if started:
        started[0].join(60)
    return tmp


def _estimates(out: Path) -> list:
    from flocktrack.record.reader import read_recording

    return sorted((m.k, key, tuple(map(float, m.x))) for key, m, _ in read_recording(out / "recording.mcap").messages
                  if key.endswith("/estimate") and key.startswith("agent/"))


class Steering:
    """The driver of the attacked run: hostile viewers, then an operator that pauses, steps and resumes,
    each acknowledged by the world on ``world/event`` (seen through our own Zenoh client)."""

    def __init__(self, script):
        self.script, self.acks, self.notes, self.error = script, [], {}, None

    def __call__(self, launcher, port: int) -> None:
        from agent.bus import ZenohBus

        bus = None
        try:
            assert wait(lambda: _serving(port), 120), "the dashboard never served"
            bus = ZenohBus(launcher.run, connect=launcher.endpoint)
            bus.subscribe("world/event", lambda key, m: self.acks.append(m.verb))
            attack = Attack(port)
            # every viewer has its own panels (the dashboard has taken it in), then the attack begins
            assert wait(lambda: all(t.find("GuiFolderMessage", label="Inspect") for t in attack.tabs), 60), \
                "the viewers were sent no panels of their own"
            attack.every_value_to_every_widget(10**18)
            attack.run(self.script)
            self.notes["attack_sent"], self.notes["reopened"] = attack.sent, attack.reopened
            op = Tab(port, f"/operator/{TOKEN}")
            assert wait(lambda: op.shown("GuiFolderMessage", label="Run control"), 60), "no run control"
            run = op.find("GuiButtonGroupMessage", option="Pause")
            for verb in ("Pause", "Step", "Resume"):
                op.press(run, verb)
                end = time.monotonic() + 60
                while verb.lower() not in self.acks and time.monotonic() < end:
                    bus.poll(0.1)
                assert verb.lower() in self.acks, (verb, self.acks)
            attack.close()
            op.close()
        except BaseException as exc:
            self.error = exc
        finally:
            if bus is not None:
                bus.close()


def _serving(port: int) -> bool:
    import socket

    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.fixture(scope="module")
def quiet_run(tmp_path_factory):
    """The same run with no dashboard at all: what the estimates must be."""
    return _estimates(_run(tmp_path_factory.mktemp("quiet")))


def _scripts(n: int) -> list:
    """``n`` of hypothesis's hostile scripts, one after the other (a real run is too long to be one example:
    hypothesis writes the scripts, the run plays them all)."""
    out: list = []

    @settings(max_examples=n, deadline=None, database=None, phases=[Phase.generate], derandomize=True,
              suppress_health_check=list(HealthCheck))
    @given(script=SCRIPT)
    def collect(script) -> None:
        out.extend(script)

    collect()
    return out


@pytest.mark.slow
def test_hostile_viewers_of_a_real_run_leave_its_estimates_and_its_operator_alone(quiet_run, tmp_path):
    """The first report, on a real run: viewers write a huge integer into every widget they were sent, then
    play hypothesis's hostile scripts; a new operator then pauses, steps and resumes the run — the world
    acknowledges each — and the run's estimates are those of the same run without a dashboard."""
    import json

    steer = Steering(_scripts(30))
    out = _run(tmp_path / "attacked", steer)
    if steer.error is not None:
        raise steer.error
    assert [v for v in steer.acks if v in ("pause", "step", "resume")] == ["pause", "step", "resume"]
    assert _estimates(out) == quiet_run                     # the viewers changed nothing of the run
    log = (out / "logs" / "dashboard-0.log").read_text()
    assert "Traceback" not in log and len(log) < LOG_LIMIT, (len(log), log[-3000:])
    role = json.loads((out / "stats" / "dashboard-0.json").read_text())["role"]
    assert role["operator_tabs"] >= 1 and role["wrong_tokens"] >= 1 and "refused_controls" not in role
    assert role["guard"]["total_invalid_updates"] > 0, role["guard"]
