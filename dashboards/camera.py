"""Each browser tab's camera: framed on the flock and gliding after it until the tab's user moves it.

The dashboard commands a tab's camera (position, then look-at) and learns of the tab's camera only from the
poses the tab reports back, late at times and in pieces; a pose it did not command is the user's (drag,
wheel, keys), and the tab then stops following, so as not to fight them (:class:`ClientView`). The glide
runs on the live loop's thread and the reports arrive on Viser's threads: the views have their own lock.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from . import plots
from .state import Snapshot

log = logging.getLogger(__name__)


@dataclass
class ClientView:
    """The camera of one browser tab, as far as following the flock goes."""

    look_at: np.ndarray | None = None           #: the look-at point last commanded (None: never yet)
    distance: float = 0.0                       #: the camera distance last commanded
    direction: np.ndarray = field(default_factory=lambda: plots.VIEW_DIRECTION.copy())
    fit_now: bool = True                        #: jump (not glide) to the framing at the next update
    follow: bool = True                         #: glide after the flock (off once the tab's user moves it)
    zooming: bool = False
    #: (command number, point) of the camera positions / look-at points this process commanded, newest
    #: last, and those the page starts from (number 0). The page echoes them back, late at times and in any
    #: combination: a command is two messages (position, then look-at), Viser's send buffer replaces an
    #: unsent message by the next one of its kind (so a look-at may overtake a position), and the page's
    #: camera applies each alone (a position keeps the look-at, a look-at keeps the position). Whatever the
    #: user does moves the position, the look-at or both to a point that is in neither list.
    sent_pos: deque = field(default_factory=lambda: deque(maxlen=200))
    sent_look: deque = field(default_factory=lambda: deque(maxlen=400))
    seq: int = 0                                #: number of the last command
    sent_t: float = 0.0                         #: when it was sent (monotonic)
    #: the page's last report is an older pose than the last command: it was stale, or the page put its
    #: camera back (its initial-camera setup runs after the first frames) — send the command again
    resend: bool = False

    def remember(self, seq: int, pos=None, look=None) -> None:
        if pos is not None:
            self.sent_pos.append((seq, np.array(pos, float)))
        if look is not None:
            self.sent_look.append((seq, np.array(look, float)))

    def ours(self, pos: np.ndarray, look: np.ndarray, tol: float) -> int | None:
        """The oldest command number a reported pose is made of (None: the user made it)."""
        seqs = []
        for sent, x in ((self.sent_pos, pos), (self.sent_look, look)):
            seq = next((k for k, y in reversed(sent) if np.linalg.norm(x - y) < tol), None)
            if seq is None:
                return None
            seqs.append(seq)
        return min(seqs)


class TabCameras:
    """The cameras of the tabs on ``server``, each framed on the flock of the last drawn tick
    (:meth:`frame_on`) and following it while its "Follow the flock" is on. ``follow_box(cid, on)`` sets
    tab ``cid``'s checkbox when its user takes the camera over; ``safe`` wraps a GUI callback
    (:meth:`dashboards.guard.TabGuard.safe`)."""

    #: the glide's time constant (s): a moving flock is followed smoothly, a jump (replay seek) in ~1 s
    FOLLOW_TAU = 0.35
    #: zoom only when the flock's sphere stops fitting, or fills less than 1/ZOOM_SLACK of the view —
    #: the flock's breathing does not make the camera breathe, but a flock that gathers (the demo's
    #: contracts from 42 to 21 m across in its first 50 ticks: its sphere's fit distance × 1/1.5) is
    #: zoomed in on (1.6 left it a third of the canvas it should fill)
    ZOOM_SLACK = 1.3

    def __init__(self, server, follow_box: Callable[[int, bool], None], safe):
        self.server, self.follow_box, self.safe = server, follow_box, safe
        self.views: dict[int, ClientView] = {}
        self.framing: plots.Framing | None = None
        self._lock = threading.RLock()
        self._view_t = time.monotonic()

    def frame_on(self, snap: Snapshot, min_radius: float) -> None:
        """Frame the flock of ``snap`` (kept when the snapshot has none to frame)."""
        self.framing = plots.flock_framing(snap, min_radius=min_radius) or self.framing

    def add(self, client) -> None:
        """A new tab: it gets the framing at the next update, and its camera reports are watched for the
        user's own moves."""
        view = ClientView()
        # the page reports its default pose first, then the server's initial camera (applied after its first
        # frames, possibly after our first command): both are ours, not the user's
        ic = self.server.initial_camera
        view.remember(0, ic.position, ic.look_at)
        try:
            view.remember(0, client.camera.position, client.camera.look_at)
        except AssertionError:  # no camera report yet
            pass
        with self._lock:
            self.views[client.client_id] = view
        client.camera.on_update(self.safe(lambda cam, cid=client.client_id: self._on_camera(cid, cam), "camera"))

    def remove(self, cid: int) -> None:
        self.views.pop(cid, None)

    def _on_camera(self, cid: int, cam) -> None:
        """A camera report from a tab (Viser's thread pool). A pose this process did not command means the
        user moved the camera (drag, wheel, keys): stop following, so as not to fight them."""
        with self._lock:
            view = self.views.get(cid)
            if view is None or view.look_at is None or not view.follow:
                return
            P, L = np.asarray(cam.position, float), np.asarray(cam.look_at, float)
            tol = 1e-3 * max(view.distance, 1.0)
            seq = view.ours(P, L, tol)
            if seq is not None:
                view.resend = seq < view.seq
                return
        log.info("camera moved by the user in tab %s: no longer following the flock", cid)
        view.follow = False
        self.follow_box(cid, False)

    def set_follow(self, cid: int, on: bool) -> None:
        """Tab ``cid``'s "Follow the flock" checkbox. Turned on, the tab glides from where its camera is now,
        keeping its viewing direction (the user's orbit), to the flock."""
        client = self.server.get_clients().get(cid)
        with self._lock:
            view = self.views.get(cid)
            if view is None:
                return
            if on and not view.follow and client is not None:
                try:
                    P, L = np.array(client.camera.position, float), np.array(client.camera.look_at, float)
                except AssertionError:
                    P = L = np.zeros(3)
                dist = float(np.linalg.norm(L - P))
                if dist > 1e-9:
                    view.look_at, view.distance, view.direction = L, dist, (L - P) / dist
                    view.seq += 1
                    view.remember(view.seq, P, L)
            view.follow = bool(on)
        self.update(force=True)

    def reset(self, cid: int | None = None) -> None:
        """Tab ``cid`` (None: every tab) is framed on the flock at the next update, from the default
        direction, and follows it again."""
        with self._lock:
            for c, view in self.views.items():
                if cid is None or c == cid:
                    view.fit_now, view.follow = True, True
                    view.direction = plots.VIEW_DIRECTION.copy()

    def update(self, force: bool = False) -> None:
        """Move each following tab's camera toward the framing of the last drawn tick: look at the flock's
        centre from a distance that fits the flock and the target in the tab's view (its own field of view
        and aspect ratio), gliding with time constant ``FOLLOW_TAU``. The control panel is docked at the
        right edge and the plots at the left, so the canvas is exactly the visible part of the scene: the
        flock centred in the canvas is centred in what the user sees. Called after each scene redraw and
        from the loops (at most 20 times a second); it sends nothing once the camera is where it should be."""
        now = time.monotonic()
        if not force and now - self._view_t < 0.05:
            return
        fr = self.framing
        if fr is None:
            return
        with self._lock:
            a = 1.0 - math.exp(-min(max(now - self._view_t, 0.0), 0.25) / self.FOLLOW_TAU)
            self._view_t = now
            clients = self.server.get_clients()
            for cid, view in list(self.views.items()):
                client = clients.get(cid)
                if client is None or not (view.follow or view.fit_now):
                    continue
                try:
                    fov, aspect = float(client.camera.fov), float(client.camera.aspect)
                except (AssertionError, ZeroDivisionError):
                    continue                  # the tab has not reported its camera yet
                d_fit = plots.camera_distance(fr.radius, fov, aspect)
                if view.fit_now or view.look_at is None:
                    L, d = np.array(fr.centre, float), 1.1 * d_fit
                else:
                    L = view.look_at + a * (fr.centre - view.look_at)
                    d = view.distance
                    if not d_fit <= d <= self.ZOOM_SLACK * d_fit:
                        view.zooming = True
                    if view.zooming:
                        d += a * (1.1 * d_fit - d)
                        view.zooming = abs(d / (1.1 * d_fit) - 1.0) > 0.02
                    step = float(np.linalg.norm(L - view.look_at)) + abs(d - view.distance)
                    if step < 2e-3 * d and not (view.resend and now - view.sent_t > 0.5):
                        continue
                self._command(client, view, L, d)

    def _command(self, client, view: ClientView, L: np.ndarray, d: float) -> None:
        cam = client.camera
        P = L - view.direction * d
        prev_P, prev_L = np.array(cam.position, float), np.array(cam.look_at, float)
        view.seq += 1
        # Viser's position setter also sends the look-at moved along (it keeps the orientation): the tab
        # may report that one too (we hold the lock: its reports are looked at after this is recorded)
        view.remember(view.seq, P, prev_L + (P - prev_P))
        refit = view.fit_now
        view.look_at, view.distance, view.fit_now = L, d, False
        view.sent_t, view.resend = time.monotonic(), False
        with client.atomic():
            if 3 * d > cam.far:
                cam.far = 10 * d
            if 2 * d > cam.max_orbit_distance:
                cam.max_orbit_distance = 4 * d
            cam.position = P
            view.remember(view.seq, None, cam.look_at)   # what the setter sent (a report may have come between)
            view.remember(view.seq, None, L)
            cam.look_at = L
            if refit:
                cam.up_direction = (0.0, 0.0, 1.0)
