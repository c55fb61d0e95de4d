"""The live feed (``selfview.procedures.livefeed``): the camera's current frame with the plate found in it, before a
view is taken, on the page; in headless Chromium the operator sees it and takes views by clicks."""

import json
import re
import threading
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from tests.procedures.test_cli_view import needs_chromium, start, wait_for
from tests.procedures.test_view_controls import DevTools, _close


class Frames:
    """A frame source (``FrameSource``) that serves ``frames`` in turn and counts its reads."""

    description = "test frames"
    frame_period_s = None

    def __init__(self, frames):
        self.frames = list(frames)
        self.reads = 0

    def open(self):
        pass

    def read(self, timeout_s):
        img = self.frames[self.reads % len(self.frames)]
        self.reads += 1
        return img, time.monotonic()

    def close(self):
        pass


@pytest.fixture(scope="module")
def cell_and_parked():
    from selfview.files.cell import default_cell_path, load_cell
    from selfview.mocks.render import render
    from selfview.mocks.world import SimWorld

    cell = load_cell(default_cell_path())
    w = SimWorld(cell, seed=3)
    w.park()
    return cell, render(w, seed=1).image


def _feed(cell, frames, view=None, plate=None, model=None, **kw):
    from selfview.drivers.frame_grabber_v4l2 import FrameGrabber
    from selfview.procedures.livefeed import LiveFeed
    from selfview.procedures.view import LiveView

    src = Frames(frames)
    grabber = FrameGrabber("test://", sources={"test": lambda url: src}, timeout_s=1.0).connect()
    view = view or LiveView("intrinsics")
    return LiveFeed(view, grabber, plate or cell.plate, model or cell.camera.guess(), **kw), view, src


def test_the_feed_shows_the_plate_found_and_a_grab_error_without_ending(cell_and_parked):
    cell, parked = cell_and_parked
    blank = np.full_like(parked, 128)
    black = np.zeros_like(parked)
    feed, view, src = _feed(cell, [parked, blank, black, parked], taken=lambda: [])
    info = feed.once()
    live = view.state()["live"]
    assert live["on"] and live["seq"] == 1 and live["found"] == info["found"]
    assert 40 <= live["found"] < 64 and live["of"] == 64  # the fingers hide some discs
    assert live["text"] == f"LIVE: {live['found']} of 64 plate points found"
    frame = cv2.imdecode(np.frombuffer(view._live_jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert frame.shape == (2 * parked.shape[0], 2 * parked.shape[1], 3)
    green = (frame[:, :, 1] > 150) & (frame[:, :, 0] < 80) & (frame[:, :, 2] < 80)
    assert green.sum() > 2000  # the points found are drawn
    # no view taken yet: the coverage now is empty, with this view taken it is this view's
    cov = live["coverage"]
    assert set(cov) == {"x", "y", "size", "tilt"} and cov["x"]["now"] == 0 and cov["x"]["if_taken"] > 0.2
    assert feed.once()["found"] == 0
    assert view.state()["live"]["text"].startswith("LIVE: plate not found (")
    with pytest.raises(Exception, match="black frame"):
        feed.once()  # the thread catches this and shows it (below)
    assert view.state()["live"]["seq"] == 2  # the frame with an error is not shown as live

    # the thread: a grab error is shown and the feed goes on
    feed, view, src = _feed(cell, [black, parked], rate_hz=25)
    feed.start()
    try:
        end = time.monotonic() + 20
        seen_error = False
        while time.monotonic() < end:
            live = view.state()["live"]
            seen_error |= "black frame" in (live.get("error") or "")
            if seen_error and live["seq"] >= 2 and live["error"] is None:
                break
            time.sleep(0.01)
        assert seen_error and live["seq"] >= 2 and live["found"] > 40, live
        assert feed.errors >= 1 and feed.frames >= 2
    finally:
        feed.close()
    assert view.state()["live"]["on"] is False and feed._thread is None


def test_no_live_grab_while_the_engine_grabs_a_view(cell_and_parked):
    from selfview.procedures.engine import Step

    cell, parked = cell_and_parked
    feed, view, src = _feed(cell, [parked], rate_hz=25)
    feed.start()
    try:
        wait = time.monotonic() + 20
        while src.reads < 2 and time.monotonic() < wait:
            time.sleep(0.01)
        feed.on_step(7, Step("grab", {"average": 1}, name="view1"))
        time.sleep(0.3)  # a live grab in flight ends
        n = src.reads
        time.sleep(0.5)
        assert src.reads == n  # paused
        feed.on_step(8, Step("wait", {"seconds": 0.1}))
        wait = time.monotonic() + 20
        while src.reads == n and time.monotonic() < wait:
            time.sleep(0.01)
        assert src.reads > n  # going on after the view
    finally:
        feed.close()


def test_a_recording_gets_no_live_feed(cell_and_parked, tmp_path):
    from selfview.drivers.frame_grabber_v4l2 import FrameGrabber
    from selfview.procedures.livefeed import LiveFeed
    from selfview.procedures.view import LiveView

    cell, parked = cell_and_parked
    cv2.imwrite(str(tmp_path / "img_000.png"), parked)
    view = LiveView("intrinsics")
    grabber = FrameGrabber(f"frames://{tmp_path}/img_%03d.png").connect()
    feed = LiveFeed(view, grabber, cell.plate, cell.camera.guess()).start()
    assert feed._thread is None and grabber.source.frames_read == 0
    live = view.state()["live"]
    assert live["on"] is False and "recording" in live["text"]
    grabber.close()


def test_the_live_picture_needs_the_pages_token_and_a_get_changes_nothing(cell_and_parked):
    from selfview.procedures.view import LiveView

    cell, parked = cell_and_parked
    view = LiveView("intrinsics").start()
    try:
        page = urllib.request.urlopen(view.url, timeout=5).read().decode()
        token = re.search(r'const TOKEN="([^"]+)"', page).group(1)

        def get(path, **headers):
            try:
                with urllib.request.urlopen(urllib.request.Request(view.url + path, headers=headers), timeout=5) as r:
                    return r.status, r.read()
            except urllib.error.HTTPError as exc:
                return exc.code, None

        assert get("live.jpg", **{"X-Selfview-Token": token})[0] == 404  # no live frame yet
        view.live_frame(parked, {"found": 0, "of": 64, "text": "LIVE"})
        before = view.state()["live"]
        assert get("live.jpg")[0] == 403  # no token
        assert get(f"live.jpg?token={token}")[0] == 403  # the token goes in the header, never in an address
        assert get("live.jpg", **{"X-Selfview-Token": "x" * len(token)})[0] == 403
        assert get("live.jpg", **{"X-Selfview-Token": token, "Host": "evil.example:80"})[0] == 403
        code, body = get("live.jpg", **{"X-Selfview-Token": token})
        assert code == 200 and cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_GRAYSCALE).shape == parked.shape
        # taking a view is a POST with the token, offered only while the run asks for it
        req = urllib.request.Request(view.url + "action", data=json.dumps({"action": "take"}).encode(), method="POST",
                                     headers={"X-Selfview-Token": token, "Content-Type": "application/json"})
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(req, timeout=5)
        assert e.value.code == 400
        got = {}
        t = threading.Thread(target=lambda: got.update(a=view.ask("take?", [("take", "TAKE THIS VIEW")], timeout_s=10)))
        t.start()
        wait_end = time.monotonic() + 10
        while view.state()["ask"] is None and time.monotonic() < wait_end:
            time.sleep(0.01)
        assert get("action?action=take")[0] == 404 and get("take")[0] == 404  # never a GET
        assert view.state()["ask"] is not None and view.state()["live"] == before
        with urllib.request.urlopen(req, timeout=5) as r:
            assert json.loads(r.read())["said"] == "take requested"
        t.join(10)
        assert got["a"] == ("take", {"reject": []})
    finally:
        view.close()


def test_intrinsics_shows_the_live_plate_between_the_planned_views(tmp_path):
    """A planned run: live frames with the plate found come while views are still to be taken, then the feed
    ends; the run's result is a camera as without it."""
    # the simulated arm at a tenth of real time (0.02 by default): its moves between views last long enough for
    # several live frames on a loaded machine (three a second at most; one at a load of 10 was measured)
    p, url = start(["intrinsics", "--views", "6", "--view", "--view-linger", "1", "--time-scale", "0.1", "--json"],
                   tmp_path)
    seen = []
    try:
        end = time.monotonic() + 120
        while time.monotonic() < end:
            s = json.loads(urllib.request.urlopen(url + "state.json", timeout=5).read())
            live = s["live"] or {}
            seen.append((live.get("seq", 0), live.get("found", 0), (s["coverage"] or {}).get("views taken", 0),
                         live.get("on")))
            if s["done"]:
                break
            time.sleep(0.05)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate(timeout=10)
    assert p.returncode == 0, err[-2000:]
    before = {seq for seq, found, taken, on in seen if on and found >= 12 and taken < 6}
    assert before, seen  # live frames with the plate found while views are still to be taken
    # a live frame is shown before each view (the engine waits for one), however slow the machine: the feed's
    # count when it ended covers the six views
    assert seen[-1][0] >= 6, seen
    assert seen[-1][3] is False  # the feed ended with the views
    assert json.loads(out)["views_used"] == 6


@needs_chromium
def test_the_operator_sees_the_live_plate_and_takes_views_by_clicks(tmp_path):
    """--operator-views: the page shows the camera now with the plate found in it and the coverage it would
    add; TAKE THIS VIEW takes a view (the count grows); STOP ends the run."""
    p, url = start(["intrinsics", "--view", "--operator-views", "120", "--json"], tmp_path)
    b = None
    try:
        wait_for(url, lambda s: s["ask"] is not None and (s["live"] or {}).get("found", 0) >= 12, timeout_s=120)
        b = DevTools(url, tmp_path)
        b.wait_js("document.getElementById('live').naturalWidth===1536 && document.getElementById('ask-take')!==null")
        first = b.js("document.getElementById('live').src")
        assert first.startswith("blob:")  # fetched with the token, never an address holding it
        b.wait_js(f"document.getElementById('live').src!=={json.dumps(first)} && "
                  "document.getElementById('live').naturalWidth===1536")  # the frame changes
        caption = b.js("document.getElementById('livecaption').textContent")
        assert re.match(r"LIVE: \d+ of 64 plate points found at \d\d:\d\d:\d\d$", caption), caption
        assert b.js("document.querySelectorAll('#livecov .barnext').length") == 4
        shot = b.screenshot(tmp_path / "live.png")
        r = b.js("(()=>{const r=document.getElementById('live').getBoundingClientRect();return [r.x,r.y,r.width,r.height]})()")
        x, y, w, h = (int(v) for v in r)
        assert w > 840
        region = shot[y:y + h, x:x + w]
        green = (region[:, :, 1] > 150) & (region[:, :, 0] < 90) & (region[:, :, 2] < 90)
        assert green.mean() > 0.002  # the plate points found, drawn in green on the grey picture
        for n in (1, 2):
            b.click("ask-take")
            s = wait_for(url, lambda s: (s["coverage"] or {}).get("views taken") == n and s["ask"] is not None)
            assert s["coverage"]["discs in this view"] >= 12
            b.wait_js("document.getElementById('ask-take')!==null && document.getElementById('askbox').offsetHeight>0")
        assert "2 view(s) taken" in b.js("document.getElementById('asktext').textContent")
        b.click("stop")
        out, err = p.communicate(timeout=60)
    finally:
        _close(b, p)
    assert p.returncode in (130, 143), err[-2000:]
    assert "view 2: taken on the page" in err and "ABORT sent and confirmed" in err


def test_a_robot_without_poses_is_told_to_let_the_operator_take_the_views():
    from selfview.drivers.manual_robot import ManualRobot
    from selfview.errors import ConfigError
    from selfview.files.cell import default_cell_path, load_cell
    from selfview.procedures.runs import CellSession

    asked = []
    with CellSession.simulated(load_cell(default_cell_path()), seed=0) as s:
        val = s.devices.robot
        s.devices.robot = ManualRobot(ask=lambda q: asked.append(q) or "")
        try:
            with pytest.raises(ConfigError, match="knows no pose.*--operator-views"):
                s.intrinsics_views(4)
        finally:
            s.devices.robot = val
    assert asked == []  # refused before the operator was asked anything


def test_views_the_operator_takes_measure_the_camera():
    """``CellSession.operator_views``: the robot goes above the plate and waits; the operator moves the arm
    (here through the driver, as a pendant would) and says 'take' for each view, then 'done'."""
    from selfview.files.cell import default_cell_path, load_cell
    from selfview.procedures.intrinsics import measure_intrinsics
    from selfview.procedures.runs import CellSession
    from selfview.procedures.viewplan import plan_view_poses

    cell = load_cell(default_cell_path())
    with CellSession.simulated(cell, seed=0) as s:
        robot = s.devices.robot
        plate_H = robot.pose_to_H(robot.location(s.settings.plate))
        lean = (np.linalg.inv(plate_H) @ np.array([0.0, 0.0, 0.0, 1.0]))[:2]
        poses = plan_view_poses(cell, 4, lean_W=lean)

        def take(n):
            if n == len(poses):
                return "done"
            robot.moves(plate_H @ poses[n]["W_H_G"])  # the operator's pendant
            return "take"

        images, taken = s.operator_views(take)
        steps = [r.step for r in s.engine.records]
        truth = s.sim.world.camera
    assert len(images) == 4 and taken == [{"taken_by": "operator"}] * 4
    assert sum(st.startswith("grab") for st in steps) == 4 and not any(st.startswith("moves") for st in steps)
    res = measure_intrinsics(images, cell.plate, cell.camera.guess())
    assert res.views_used == 4 and abs(res.camera.f - truth.f) < 1.0


def test_park_shows_the_live_feed_until_its_picture_is_grabbed(tmp_path):
    p, url = start(["park", "--view", "--view-linger", "5"], tmp_path)
    try:
        s = wait_for(url, lambda s: s["done"], timeout_s=120)
    finally:
        if p.poll() is None:
            p.kill()
        p.communicate(timeout=10)
    assert s["live"]["on"] is False and s["live"]["text"] == "live feed ended: the picture is taken"
    assert s["live"].get("coverage", {}) == {}  # no views, no coverage


def test_the_live_feed_finds_a_charuco_board_in_photographs():
    """The plate seam: a ChArUco board (real photographs) is found and counted by its corners."""
    from pathlib import Path

    from selfview.estimation.intrinsics import guess_camera
    from selfview.files.cell import load_cell, default_cell_path, load_plate
    from selfview.measurement.plates import detect_plate

    photos = Path(__file__).resolve().parents[1] / "data" / "charuco-basler"
    plate = load_plate(photos / "plate.yaml")
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in sorted(photos.glob("basler-*.jpg"))[:2]]
    h, w = images[0].shape
    model = guess_camera([detect_plate(images[0], plate)], w, h)
    feed, view, src = _feed(load_cell(default_cell_path()), images, plate=plate, model=model, taken=lambda: [])
    for img in images:
        info = feed.once()
        assert info["of"] == plate.rows * plate.cols and info["found"] == len(detect_plate(img, plate, camera=model).uv)
        assert info["found"] >= 12 and info["text"] == f"LIVE: {info['found']} of {plate.rows * plate.cols} plate points found"
        assert info["coverage"]["x"]["if_taken"] > 0.1


def test_a_live_frame_comes_before_each_view_however_slow_the_feed(cell_and_parked):
    """The engine's settling step before a view waits until a live frame was shown since the last view: with a
    feed of one frame every 10 s, each view still gets its own frame (the feed's own pause would give none within the wait's 5 s)."""
    from types import SimpleNamespace

    cell, parked = cell_and_parked
    feed, view, src = _feed(cell, [parked], rate_hz=0.1, taken=lambda: [])
    feed.start()
    try:
        t0 = time.monotonic()
        while feed.frames < 1 and time.monotonic() - t0 < 30:
            time.sleep(0.01)
        for k in (1, 2, 3):
            feed.on_step(0, SimpleNamespace(kind="move", params={}))
            feed.on_step(0, SimpleNamespace(kind="wait", params={"seconds": 0.0}))
            assert feed.frames >= k  # a frame since the last view
            feed.on_step(0, SimpleNamespace(kind="grab", params={"average": 1}))
    finally:
        feed.close()
