"""The live view's controls, clicked in headless Chromium (over its DevTools protocol): STOP aborts the robot and
makes the valve safe, the alarm is acknowledged; only the page's own token changes anything, and never a GET."""

import base64
import json
import os
import re
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

import cv2
import pytest

from tests.procedures.test_cli_view import CHROMIUM, REPO, needs_chromium, start, wait_for


class DevTools:
    """A headless Chromium showing ``url``, driven over the DevTools protocol (a minimal WebSocket client)."""

    def __init__(self, url, tmp_path):
        profile = tmp_path / "chromium-cdp"
        self.proc = subprocess.Popen([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--window-size=1400,900",
                                      "--remote-debugging-port=0", f"--user-data-dir={profile}", url],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = profile / "DevToolsActivePort"
        for _ in range(300):
            if port_file.is_file() and port_file.read_text().strip():
                break
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            ws = next(t for t in json.loads(r.read()) if t["type"] == "page")["webSocketDebuggerUrl"]
        path = ws.split(f"127.0.0.1:{port}", 1)[1]
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=20)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade"
                          f"\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        assert b" 101 " in head.split(b"\r\n")[0], head
        self.n = 0

    def _read(self, n):
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            assert chunk, "DevTools closed the connection"
            buf += chunk
        return buf

    def call(self, method, **params):
        self.n += 1
        data = json.dumps({"id": self.n, "method": method, "params": params}).encode()
        mask = os.urandom(4)
        n = len(data)
        head = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + n.to_bytes(2, "big"))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))
        while True:  # events come between; the answer carries our id
            payload = b""
            while True:
                b0, b1 = self._read(2)
                ln = b1 & 0x7F
                ln = int.from_bytes(self._read(2 if ln == 126 else 8), "big") if ln >= 126 else ln
                payload += self._read(ln)
                if b0 & 0x80:
                    break
            msg = json.loads(payload)
            if msg.get("id") == self.n:
                assert "error" not in msg, msg
                return msg["result"]

    def js(self, expr):
        return self.call("Runtime.evaluate", expression=expr, returnByValue=True)["result"].get("value")

    def wait_js(self, expr, timeout_s=30.0):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if self.js(expr):
                return
            time.sleep(0.1)
        pytest.fail(f"never true on the page: {expr}")

    def click(self, element_id):
        """A mouse click (press and release) at the middle of the element, as a person's: on the element as shown
        (a hidden one has no place on the page, and a click there would be lost, not refused)."""
        self.wait_js(f"(()=>{{const e=document.getElementById('{element_id}');return e!==null&&!e.closest('[hidden]')"
                     "&&e.getBoundingClientRect().width>0})()")
        r = self.js(f"(()=>{{const r=document.getElementById('{element_id}').getBoundingClientRect();"
                    "return [r.x+r.width/2,r.y+r.height/2]})()")
        for kind in ("mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", type=kind, x=r[0], y=r[1], button="left", clickCount=1)

    def screenshot(self, path):
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))
        return cv2.imread(str(path))

    def close(self):
        self.sock.close()
        self.proc.kill()
        self.proc.wait(10)


def _close(browser, p) -> None:
    """The browser closed, and the command killed if it still runs (the test failed before it ended)."""
    if browser is not None:
        browser.close()
    if p.poll() is None:
        p.kill()
        p.communicate(timeout=10)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    d = tmp_path_factory.mktemp("controls")
    r = subprocess.run([sys.executable, "-m", "selfview.procedures.cli", "calibrate", "--out", "cal.yaml", "--no-pictures"],
                       cwd=d, env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return d


@needs_chromium
def test_stop_on_the_page_aborts_the_robot_and_makes_the_valve_safe(calibrated, tmp_path):
    p, url = start(["monitor", "--calibration", "cal.yaml", "--frames", "2000", "--view"], calibrated)
    b = None
    try:
        wait_for(url, lambda s: (s["series"] or {}).get("points") and len(s["series"]["points"]) >= 4)
        b = DevTools(url, tmp_path)
        b.wait_js("document.querySelectorAll('#log tr').length>=4 && document.querySelectorAll('#plot .tick').length>=4")
        shot = b.screenshot(tmp_path / "monitor-running.png")
        # the red STOP button at the top right, the frame large
        stop_px = shot[5:40, 1300:1395].reshape(-1, 3).mean(axis=0)
        assert stop_px[2] > 180 and stop_px[1] < 80, stop_px
        assert b.js("document.getElementById('frame').getBoundingClientRect().width") > 840  # was at most 760
        assert b.js("document.getElementById('alarmbox').offsetHeight") == 0  # no alarm: no alarm bar
        # the chart's limit labels do not overlap
        boxes = b.js("[...document.querySelectorAll('#plot .limit')].map(t=>{const r=t.getBBox();return [r.y,r.height]})")
        ys = sorted(boxes)
        assert len(ys) == 3 and all(b2[0] >= a[0] + a[1] - 0.5 for a, b2 in zip(ys, ys[1:])), ys
        b.click("stop")
        out, err = p.communicate(timeout=60)
    finally:
        _close(b, p)
    assert p.returncode in (130, 143), err[-2000:]
    assert "view: STOP pressed on the page" in err
    assert "ABORT sent and confirmed" in err and "valve set to its safe state" in err
    frames = [int(m) for m in re.findall(r"^frame +(\d+):", out, re.M)]
    assert 4 <= max(frames) < 2000  # stopped mid-run


@needs_chromium
def test_the_alarm_is_acknowledged_by_a_click(calibrated, tmp_path):
    p, url = start(["monitor", "--calibration", "cal.yaml", "--frames", "60", "--drift", "1.0", "--view",
                    "--view-linger", "60"], calibrated)
    b = None
    try:
        s = wait_for(url, lambda s: s["alarm"] is not None, timeout_s=120)
        assert s["alarm"]["acknowledged"] is False and s["verdict"]["go"] is False
        assert s["log"][-1]["decision"] == "alarm" and len(s["log"]) == s["log"][-1]["frame"]
        b = DevTools(url, tmp_path)
        b.wait_js("document.getElementById('alarmbox').offsetHeight>0")
        b.screenshot(tmp_path / "alarm.png")
        b.click("ack")
        s = wait_for(url, lambda s: s["alarm"]["acknowledged"])
        b.wait_js("document.getElementById('alarmtext').textContent.startsWith('ALARM acknowledged at')")
        assert b.js("document.getElementById('ack').offsetHeight") == 0  # the button is gone
    finally:
        if b is not None:
            b.close()
        if p.poll() is None:
            p.kill()
        _, err = p.communicate(timeout=10)
    assert "view: alarm acknowledged on the page" in err


def test_only_the_pages_token_changes_anything_and_never_a_get():
    from selfview.procedures.view import LiveView

    view = LiveView("test").start()
    try:
        page = urllib.request.urlopen(view.url, timeout=5).read().decode()
        token = re.search(r'const TOKEN="([^"]+)"', page).group(1)
        assert token == view.token and token not in json.dumps(view.state())

        def post(body, **headers):
            req = urllib.request.Request(view.url + "action", data=json.dumps(body).encode(), method="POST",
                                         headers={"Content-Type": "application/json", **headers})
            try:
                with urllib.request.urlopen(req, timeout=5) as r:
                    return r.status, json.loads(r.read())
            except urllib.error.HTTPError as exc:
                return exc.code, None

        view.alarm("camera moved 12 deg")
        assert post({"action": "acknowledge"})[0] == 403  # no token
        assert post({"action": "acknowledge"}, **{"X-Selfview-Token": "x" * len(token)})[0] == 403
        assert post({"action": "acknowledge"}, **{"X-Selfview-Token": token, "Host": "evil.example:80"})[0] == 403
        assert post({"action": "reboot"}, **{"X-Selfview-Token": token})[0] == 400
        for path in ("action", "action?action=acknowledge", "stop"):
            with pytest.raises(urllib.error.HTTPError) as e:
                urllib.request.urlopen(view.url + path, timeout=5)
            assert e.value.code == 404
        assert view.state()["alarm"]["acknowledged"] is False  # nothing above changed it
        code, said = post({"action": "acknowledge"}, **{"X-Selfview-Token": token})
        assert code == 200 and said["said"] == "alarm acknowledged" and view.state()["alarm"]["acknowledged"]
    finally:
        view.close()


@needs_chromium
def test_intrinsics_page_has_a_row_per_view_and_coverage_bars(tmp_path):
    from tests.procedures.test_cli_view import browser

    p, url = start(["intrinsics", "--view", "--view-linger", "30", "--json"], tmp_path)
    try:
        s = wait_for(url, lambda s: s["done"], timeout_s=240)
        dom, shot = browser(url, tmp_path, "intrinsics")
    finally:
        if p.poll() is None:
            p.kill()
        p.communicate(timeout=10)
    used = [v for v in s["views"] if v["used"] == "yes"]
    assert len(used) == s["numbers"]["views used"] >= 4
    assert all(v["discs"] >= 5 and v["rms [px]"] < 0.1 for v in used)
    assert set(s["bars"]) == {"x", "y", "size", "tilt"}
    assert all(0 <= b["fraction"] <= 1 for b in s["bars"].values())
    assert s["bars"]["tilt"]["value"] == pytest.approx(max(v["tilt [deg]"] for v in used))
    assert s["bars"]["x"]["value"] > 0.3  # the discs of 12 planned views spread over the picture
    assert len(re.findall(r'<div class="barin" style="width:\d+%"', dom)) == 4 and "<th>tilt [deg]</th>" in dom and "<td>view 12</td>" in dom
    assert shot is not None


@needs_chromium
def test_views_are_rejected_recalibrated_and_saved_by_clicks(tmp_path):
    """intrinsics --review: the page lists the views; a view marked and CALIBRATE measures again without it;
    SAVE writes the camera file; nothing is written before."""
    p, url = start(["intrinsics", "--view", "--review", "120", "--out", "cam.yaml", "--json"], tmp_path)
    b = None
    try:
        s = wait_for(url, lambda s: s["ask"] is not None, timeout_s=240)
        assert s["numbers"]["views used"] == 12 and not (tmp_path / "cam.yaml").exists()
        b = DevTools(url, tmp_path)
        b.wait_js("document.getElementById('reject-view-3')!==null && document.getElementById('ask-calibrate')!==null")
        b.click("reject-view-3")
        assert b.js("document.getElementById('reject-view-3').checked") is True
        b.screenshot(tmp_path / "review.png")
        b.click("ask-calibrate")
        s = wait_for(url, lambda s: s["ask"] is not None and s["numbers"]["views used"] == 11, timeout_s=120)
        assert {"view": "view 3", "used": "no: rejected on the page"}.items() <= next(
            v for v in s["views"] if v["view"] == "view 3").items()
        assert not (tmp_path / "cam.yaml").exists()
        # the page shows the new question once it has drawn the new state (until then the first question's buttons
        # stay in the page, hidden since the click: a click on them would be lost)
        b.wait_js("!document.getElementById('askbox').hidden && document.getElementById('ask-save')!==null"
                  " && document.getElementById('views').textContent.includes('no: rejected on the page')"
                  " && document.getElementById('reject-view-3').checked")
        b.click("ask-save")
        out, err = p.communicate(timeout=60)
    finally:
        _close(b, p)
    assert p.returncode == 0, err[-2000:]
    res = json.loads(out)
    assert res["views_used"] == 11 and res["views_rejected"] == ["view 3"] and res["out"] == "cam.yaml"
    assert (tmp_path / "cam.yaml").is_file()


@needs_chromium
@pytest.mark.parametrize("button, code", [("ask-discard", 5), ("ask-save", 0)])
def test_a_calibration_is_saved_or_discarded_by_a_click(tmp_path, button, code):
    from selfview.files.cell import default_cell_path, load_cell
    from selfview.mocks.render import render
    from selfview.mocks.world import SimWorld

    w = SimWorld(load_cell(default_cell_path()), seed=3)
    w.park()
    cv2.imwrite(str(tmp_path / "parked.png"), render(w, seed=1).image)
    p, url = start(["calibrate", "--image", "parked.png", "--out", "cal.yaml", "--no-pictures", "--view",
                    "--review", "60"], tmp_path)
    b = None
    try:
        s = wait_for(url, lambda s: s["ask"] is not None)
        assert s["verdict"]["go"] and "TCP 1-sigma x y z [mm]" in s["numbers"] and not (tmp_path / "cal.yaml").exists()
        b = DevTools(url, tmp_path)
        b.wait_js(f"document.getElementById('{button}')!==null")
        b.click(button)
        out, err = p.communicate(timeout=60)
    finally:
        _close(b, p)
    assert p.returncode == code, err[-2000:]
    assert (tmp_path / "cal.yaml").exists() == (code == 0)
    if code:
        assert "calibration discarded on the page; nothing written" in err
    else:
        assert "written to cal.yaml" in out
