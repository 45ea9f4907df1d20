"""Who may steer a run from the dashboard (dashboards/operator.py), at the protocol level: websocket clients
written by hand (the page's own wire format, msgpack over Viser's websocket), one with the run's operator
token in its path, one with a wrong one, one with none. Only the first gets controls, and the others cannot
press them even by sending the operator's button id themselves. (The browser-level test is in
tests/browser/test_dashboard_browser.py; the launcher's token file and printed link are checked here too.)"""

import os
import stat
import time

import pytest

from dashboards.probe import connect as _connect
from dashboards.probe import operator_ui as _operator_ui
from dashboards.probe import press as _press
from dashboards.probe import report_camera as _report_camera
from dashboards.probe import wait as _wait
from dashboards.operator import Operators, operator_url, write_token
from dashboards.state import RunInfo
from flocktrack.launch.launcher import free_port


def test_a_crafted_client_without_the_token_gets_no_controls_and_cannot_press_them():
    with _operator_ui(5) as (ui, sent, socks):
        viewer = _connect(ui.port, "/")
        wrong = _connect(ui.port, "/operator/not-the-token")
        socks += [viewer, wrong]
        assert _wait(lambda: len(ui.server.get_clients()) == 2)
        assert ui.operators.panels == {}                          # no tab is an operator yet
        op = _connect(ui.port, "/operator/the-token")
        socks.append(op)
        assert _wait(lambda: len(ui.operators.panels) == 1)
        (cid, panel), = ui.operators.panels.items()
        assert cid in ui.server.get_clients()
        uuid = panel.b_burst._impl.uuid                           # the operator tab's "Inject outlier burst"
        for ws in (viewer, wrong):                                # others pressing it: nothing happens
            _press(ws, uuid)
        time.sleep(1.5)
        assert sent == []
        _press(op, uuid)                                          # the operator pressing it: sent
        assert _wait(lambda: sent == [("outlier_burst", {"agent": -1, "ticks": 20, "magnitude": 5.0})]), sent
        op.close()
        assert _wait(lambda: ui.operators.panels == {})           # its controls go with its tab
        assert ui.operators.counters == {"viewer_tabs": 1, "wrong_tokens": 1, "operator_tabs": 1}


def test_a_viewer_inspecting_another_sensor_changes_only_its_own_tab():
    """Each tab has its own inspector (its own "Sensor" dropdown, overlays and text): a viewer inspecting
    sensor 3 changes its own tab — not the operator's fields, not the sensor the shared page highlights —
    and it cannot write the operator's widgets nor anyone else's; only the operator's own choice there, or
    its own click in the scene, moves its "Sensor id" and "Link a" (so a viewer cannot make the operator's
    next Kill hit another sensor)."""
    with _operator_ui(6) as (ui, sent, socks):
        viewer = _connect(ui.port, "/")
        op = _connect(ui.port, "/operator/the-token")
        socks += [viewer, op]
        assert _wait(lambda: len(ui.operators.panels) == 1 and len(ui.tabs) == 2)
        (op_id, panel), = ui.operators.panels.items()
        viewer_id = next(c for c in ui.tabs if c != op_id)

        def fields() -> tuple[int, int]:
            return panel.g_kill_id.value, panel.g_link_a.value

        assert fields() == (0, 0)
        _press(viewer, ui.tabs[viewer_id].widgets["node"]._impl.uuid, "3")     # the viewer inspects sensor 3
        assert _wait(lambda: ui.tabs[viewer_id].selected == 3)
        time.sleep(1.0)
        assert fields() == (0, 0) and ui.selected == 0 and ui.tabs[op_id].selected == 0   # its own tab only
        ui.select(4, viewer_id)                                        # (a viewer's click in its scene)
        assert ui.tabs[viewer_id].selected == 4 and fields() == (0, 0) and ui.selected == 0
        refused = ui.guard.tabs[viewer_id].counters["invalid_updates"]
        _press(viewer, panel.g_kill_id._impl.uuid, 5)                  # nor can it write the operator's fields
        _press(viewer, ui.tabs[op_id].widgets["node"]._impl.uuid, "5")  # or the operator's inspector
        assert _wait(lambda: ui.guard.tabs[viewer_id].counters["invalid_updates"] == refused + 2)
        assert fields() == (0, 0) and ui.tabs[op_id].selected == 0
        _press(op, ui.tabs[op_id].widgets["node"]._impl.uuid, "2")     # the operator's own choice moves them
        assert _wait(lambda: fields() == (2, 2)), fields()
        assert ui.selected == 2                                        # ... and the shared highlight
        ui.select(5, op_id)                                            # and so does its click in the scene
        assert fields() == (5, 5)
        _press(viewer, ui.tabs[viewer_id].widgets["node"]._impl.uuid, "1")  # a viewer's choice after it: not
        assert _wait(lambda: ui.tabs[viewer_id].selected == 1)
        time.sleep(1.0)
        assert fields() == (5, 5) and ui.selected == 5 and sent == []


def test_a_replay_or_tokenless_page_has_no_operator():
    ops = Operators(None)
    assert not ops.is_operator("/operator/") and not ops.is_operator("/operator/x")
    assert ops.counters["wrong_tokens"] == 2
    ops = Operators("tok")
    assert ops.is_operator("/operator/tok") and not ops.is_operator("/operator/tok2")
    assert not ops.is_operator("/tok") and not ops.is_operator(None)
    assert not ops.allowed(7) and ops.refused == 1
    assert ops.counters == {"operator_tabs": 1, "wrong_tokens": 1, "viewer_tabs": 2, "refused_controls": 1}


def test_token_file_is_private_and_the_link_carries_the_token(tmp_path):
    p = tmp_path / "dashboard_token"
    write_token(p, "abc")
    assert p.read_text() == "abc\n" and stat.S_IMODE(os.stat(p).st_mode) == 0o600
    write_token(p, "def")   # a re-run overwrites it, still private
    assert p.read_text() == "def\n" and stat.S_IMODE(os.stat(p).st_mode) == 0o600
    assert operator_url("localhost", 8080, "abc") == "http://localhost:8080/?websocket=ws://localhost:8080/operator/abc"


@pytest.mark.parametrize("token", [None, "given-token"])
def test_the_launcher_hands_its_dashboard_the_token_file_or_makes_it_read_only(tmp_path, token):
    from pathlib import Path

    from agent.scenario import load_scenario
    from flocktrack.launch.commands import LaunchOptions, RunInputs
    from flocktrack.launch.launcher import Launcher
    from flocktrack.plan import build_plan

    plan = build_plan(load_scenario(Path(__file__).parents[2] / "scenarios" / "demo.toml"), dashboard=True)
    launcher = Launcher(plan, LaunchOptions(tmp_path, RunInputs(Path("s.toml")), port=7447, dashboard_port=8080,
                                            dashboard_token=token))
    argv = next(c.argv for c in launcher.child_plan() if c.name == "dashboard/0")
    if token is None:
        assert "--viewer-only" in argv and "--operator-token-file" not in argv
    else:
        f = Path(argv[argv.index("--operator-token-file") + 1])
        assert f == tmp_path / "dashboard_token" and f.read_text().strip() == token
        assert token not in " ".join(argv)                       # never on a command line (ps shows those)


def test_a_secure_runs_page_is_https_with_the_runs_ca_and_the_token_still_decides(tmp_path):
    """--secure: the page and its websocket over TLS (dashboards/tls.py) with the key set's dashboard-web
    certificate; a client trusting the run's CA gets the page, plain HTTP gets nothing, and the operator
    token in a wss:// path still makes the only operator."""
    import ssl
    import urllib.error
    import urllib.request

    import viser
    from websockets.sync.client import connect

    from dashboards.ui import DashboardUI
    from flocktrack.deploy.keys import make_keys

    from pathlib import Path

    from agent.scenario import load_scenario
    from flocktrack.plan import build_plan

    ks = make_keys(tmp_path / "keys", build_plan(load_scenario(Path(__file__).parents[2] / "scenarios" / "demo.toml"),
                                                 run="auth", dashboard=True))
    pem, key = ks.web_cert()
    assert pem.is_file() and stat.S_IMODE(os.stat(key).st_mode) == 0o600
    ui = DashboardUI(RunInfo(n=2, link_range=12.0, name="auth"), port=free_port(), live=True,
                     send_control=lambda v, a: None, operator_token="tok", tls=(str(pem), str(key)))
    try:
        ctx = ssl.create_default_context(cafile=str(ks.ca))
        with urllib.request.urlopen(f"https://localhost:{ui.port}/", context=ctx, timeout=30) as r:
            assert r.status == 200 and b"<html" in r.read().lower()
        with pytest.raises(OSError):   # no plain HTTP on the public port ...
            urllib.request.urlopen(f"http://localhost:{ui.port}/", timeout=10).read()
        with pytest.raises(urllib.error.URLError) as e:   # ... and a client must trust the run's CA
            urllib.request.urlopen(f"https://localhost:{ui.port}/", context=ssl.create_default_context(),
                                   timeout=10)
        assert isinstance(e.value.reason, ssl.SSLCertVerificationError), e.value
        ws = connect(f"wss://localhost:{ui.port}/operator/tok", ssl=ctx, subprotocols=[f"viser-v{viser.__version__}"],
                     max_size=None, open_timeout=30)
        _report_camera(ws)
        assert _wait(lambda: len(ui.operators.panels) == 1)
        ws.close()
    finally:
        ui.stop()
