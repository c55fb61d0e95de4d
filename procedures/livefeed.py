"""The live feed: the camera's current frame on the page, with the plate found in it drawn, between the views a
command takes (``--view``), as ROS camera_calibration shows the detection before a view is taken.

A thread grabs through the session's own ``FrameGrabber`` (the same handle and lock the engine's grab steps
use; no second camera handle) at a bounded rate, finds the plate with ``detect_plate`` (discs, chessboard or
ChArUco alike), draws it, and publishes the frame (``/live.jpg``, for the page's token only) with what it
found: "n of N found" or why the plate was not found, and the coverage bars as they are and as they would
be with this view taken. It pauses while the engine grabs a view, so a view waits at most for one live
frame in flight; a grab error is shown on the page and the feed goes on (the command never hears of it).
A recording (``frames://``, ``file://``) gets no live feed: its frames would be used up.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time

from selfview.errors import CalibrationError, ImageError

__all__ = ["LIVE_RATE_HZ", "LiveFeed", "live_feed"]

log = logging.getLogger("selfview.view")

#: Live frames per second at most; a frame that takes longer (a simulated camera renders it) waits twice as
#: long before the next, so the feed takes at most a third of the time.
LIVE_RATE_HZ = 3.0

#: Before each planned view the engine waits at most this long for a live frame shown since the last view, so
#: the operator has seen the plate at the view's pose (or on the way to it) before it is taken, whatever the
#: machine's load (a simulated frame renders in about 0.2-2 s).
LIVE_FRAME_WAIT_S = 5.0

#: Fewer plate points than this is "plate not found" (a pose of the view needs at least 4).
LIVE_MIN_POINTS = 4


class LiveFeed:
    """The live feed of ``camera`` (a connected ``FrameGrabber``) on ``view`` (``LiveView``), the plate found with
    the cell's ``plate`` and starting camera ``model``. ``taken()``: the plate found in each view taken so far
    (``ViewProgress.taken``), for the coverage. ``cancel``: an event that ends the feed (the engine's). Use
    ``on_step`` as an ``Engine.on_step`` hook (``view.watch``); ``start`` and ``close``. ``until_grab``: the feed
    ends at the first grab step (a command that takes one picture: ``park``, ``calibrate``); ``taken`` None: no
    coverage (views are for ``intrinsics``)."""

    def __init__(self, view, camera, plate, model, *, taken=None, rate_hz: float = LIVE_RATE_HZ, cancel=None,
                 until_grab: bool = False):
        from selfview.errors import ConfigError

        if not 0 < rate_hz <= 25:
            raise ConfigError(f"live feed rate {rate_hz!r}: expected 0 < frames per second <= 25")
        self.view, self.camera, self.plate, self.model = view, camera, plate, model
        self.taken = taken
        self.until_grab = bool(until_grab)
        self.period_s = 1.0 / float(rate_hz)
        self.cancel = cancel
        self.frames = 0  # live frames shown
        self.errors = 0  # grabs that failed
        self._paused_until = 0.0  # the engine is grabbing a view: no live grab starts before (time.monotonic)
        self._frames_at_view = 0  # live frames shown when the last view was taken
        self._last_kind = None  # the engine's previous step
        self._stop = threading.Event()
        self._wake = threading.Event()  # ends the feed's wait between frames (a view waits for a frame, or the end)
        self._publishing = threading.Lock()  # a frame is published only while the feed has not been stopped
        self._thread: threading.Thread | None = None
        self._poses: list = []  # the taken views' poses (from the starting camera), computed once each

    # --- the engine's hook ----------------------------------------------------------------------
    def on_step(self, n, step) -> None:
        try:
            self._on_step(step)
        finally:
            self._last_kind = step.kind

    def _on_step(self, step) -> None:
        """``Engine.on_step``: a grab step pauses the feed until the next step starts (or ``resume``), at most
        the grab's own time limit (the grabber's timeout for each frame it averages); so does the settling
        wait before it (at most its seconds, up to 2 s, and half a second more)."""
        if step.kind == "wait":  # the settling before a picture: the picture's grab comes next
            self.frame_before_view()
            self._paused_until = time.monotonic() + min(float(step.params.get("seconds", 0.0)), 2.0) + 0.5
        elif step.kind == "grab" and self.until_grab:
            with self._publishing:  # a live frame in flight is not shown after this
                self._stop.set()
                self._wake.set()
                self.view.live_state(on=False, text="live feed ended: the picture is taken")
        elif step.kind == "grab":
            if self._last_kind != "wait":  # (after a settling wait, the frame came before it)
                self.frame_before_view()
            frames = int(step.params.get("average", 1)) + 1
            self._paused_until = time.monotonic() + frames * float(getattr(self.camera, "timeout_s", 1.0))
        else:
            self.resume()

    def frame_before_view(self) -> None:
        """A view is about to be taken: wait (at most ``LIVE_FRAME_WAIT_S``, and not once the feed or the run is
        ending) until a live frame has been shown since the last view, so that one always comes before it."""
        if self._thread is not None and self._thread.is_alive():
            end = time.monotonic() + LIVE_FRAME_WAIT_S
            self._wake.set()  # no pause between frames now
            while self.frames <= self._frames_at_view and not self._stopping() and time.monotonic() < end:
                time.sleep(0.01)
        self._frames_at_view = self.frames

    def resume(self) -> None:
        """The view is taken: the feed goes on."""
        self._paused_until = 0.0

    # --- running --------------------------------------------------------------------------------
    def start(self) -> "LiveFeed":
        url = getattr(self.camera, "url", None)
        if getattr(url, "scheme", None) in ("frames", "file"):
            self.view.live_state(on=False, text=f"no live feed: the camera is a recording ({url.url}); "
                                                "a live feed would use up its frames")
            return self
        self.view.live_state(on=True, text="live feed: waiting for the first frame")
        self._thread = threading.Thread(target=self._run, name="selfview-live", daemon=True)
        self._thread.start()
        return self

    def _stopping(self) -> bool:
        return self._stop.is_set() or (self.cancel is not None and self.cancel.is_set())

    def _run(self) -> None:
        delay = 0.0
        while True:
            self._wake.wait(delay)
            self._wake.clear()
            if self._stopping():
                return
            if time.monotonic() < self._paused_until:
                delay = 0.05
                continue
            t0 = time.monotonic()
            try:
                self.once()
            except Exception as exc:  # shown on the page; the command goes on
                self.errors += 1
                with self._publishing:
                    if not self._stopping():
                        log.info("live feed: %s", exc)
                        self.view.live_state(error=f"{type(exc).__name__}: {exc}",
                                             text=f"live feed: the grab failed ({exc}); trying again")
            took = time.monotonic() - t0
            delay = max(self.period_s - took, 2.0 * took, 0.05)

    def once(self) -> dict:
        """Grab one frame, find the plate, publish it; returns what was published (the state's ``live``).
        Raises what the grab raises (``DeviceError``, ``DeviceTimeout``, ``ImageError``)."""
        from selfview.procedures.results import draw_plate_points

        frame = self.camera.grab()
        of = self.plate.rows * self.plate.cols
        det, why = self._detect(frame.image)
        found = det is not None
        text = (f"LIVE: {len(det.uv)} of {of} plate points found" if found else f"LIVE: plate not found ({why})")
        info = {"found": len(det.uv) if found else 0, "of": of, "text": text, "error": None,
                "at": time.strftime("%H:%M:%S"), "frame": int(frame.index),
                "coverage": self._coverage(det) if self.taken is not None else {}}
        drawn = draw_plate_points(frame.image, det, text, found=found)
        with self._publishing:
            if not self._stop.is_set():
                self.view.live_frame(drawn, info)
                self.frames += 1
        return info

    def _detect(self, image):
        from selfview.measurement.plates import detect_plate

        try:
            return detect_plate(image, self.plate, camera=self.model, min_points=LIVE_MIN_POINTS), ""
        except ImageError as exc:
            return None, str(exc)

    def _coverage(self, det) -> dict:
        """{bar: {now, if_taken, goal}}: the coverage bars (``view.coverage_bars``) of the views taken, and with
        this one; poses from the starting camera (the measured camera's bars come after the measurement)."""
        import numpy as np

        from selfview.procedures.view import coverage_bars

        taken = list(self.taken())
        for d in taken[len(self._poses):]:
            self._poses.append(self._pose(d))
        pairs = [(d.uv, H) for d, H in zip(taken, self._poses) if H is not None]
        w, h = self.model.width, self.model.height
        now = coverage_bars(np.vstack([u for u, _ in pairs]) if pairs else np.zeros((0, 2)), w, h, [H for _, H in pairs])
        H = self._pose(det) if det is not None else None
        more = pairs + ([(det.uv, H)] if H is not None else [])
        after = coverage_bars(np.vstack([u for u, _ in more]) if more else np.zeros((0, 2)), w, h, [H for _, H in more])
        return {k: {"now": (now.get(k) or {}).get("value", 0.0), "if_taken": (after.get(k) or {}).get("value", 0.0),
                    "goal": g["goal"]} for k, g in after.items()} if after else {}

    def _pose(self, det):
        import cv2

        from selfview.estimation.intrinsics import initial_pose

        try:
            return initial_pose(det.p_W, det.uv, self.model)
        except (CalibrationError, cv2.error):
            return None

    def close(self, why: str = "the views are taken") -> None:
        """Stop the feed (waits at most one grab's timeout for the frame in flight) and hide it on the page."""
        ended = self._stop.is_set()
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=float(getattr(self.camera, "timeout_s", 1.0)) + 2.0)
            self._thread = None
        if not ended:
            self.view.live_state(on=False, text=f"live feed ended: {why}")


@contextlib.contextmanager
def live_feed(view, session, progress=None):
    """A started ``LiveFeed`` of ``session``'s camera for ``view`` (None without a view or in a dry run),
    closed at the end; ``progress``: the command's ``ViewProgress`` (the views taken, for the coverage), None:
    a command that takes one picture (the feed ends at its grab)."""
    if view is None or session.dry_run or session.devices is None or session.devices.camera is None:
        yield None
        return
    feed = LiveFeed(view, session.devices.camera, session.cell.plate, session.cell.camera.guess(),
                    taken=(lambda: progress.taken) if progress is not None else None, cancel=session.engine.cancel,
                    until_grab=progress is None)
    feed.start()
    try:
        yield feed
    finally:
        feed.close()
