"""The live view (``--view``): the page a person sees during a run on the simulated cell, in a real browser."""

import json
import os
import re
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[2]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="no chromium on this machine (Debian: apt-get install chromium)")


def start(argv, cwd):
    """The command in a child process with --view; (process, page URL) once the URL is printed."""
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.Popen([sys.executable, "-m", "selfview.procedures.cli", *argv], cwd=cwd, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for _ in range(200):
        line = p.stderr.readline()
        m = re.match(r"view: (http://127\.0\.0\.1:\d+/)$", line.strip())
        if m:
            return p, m.group(1)
        if not line and p.poll() is not None:
            break
    p.kill()
    pytest.fail(f"no 'view: URL' line on stderr: {p.stderr.read()}")


def state(url):
    with urllib.request.urlopen(url + "state.json", timeout=5) as r:
        return json.loads(r.read())


def wait_for(url, test, timeout_s=60.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        s = state(url)
        if test(s):
            return s
        time.sleep(0.1)
    pytest.fail(f"the page's state never got there: {s}")


def stop(p):
    if p.poll() is None:
        p.kill()
    p.communicate(timeout=10)


def browser(url, tmp_path, name):
    """(rendered DOM, screenshot as a BGR picture) from headless Chromium."""
    common = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=2500",
              f"--user-data-dir={tmp_path / 'chromium'}"]
    dom = subprocess.run(common + ["--dump-dom", url], capture_output=True, text=True, timeout=60).stdout
    assert "\"doing\">page error" not in dom, dom[:3000]
    shot = tmp_path / f"{name}.png"
    subprocess.run(common + ["--window-size=1400,900", f"--screenshot={shot}", url], capture_output=True, timeout=60)
    return dom, cv2.imread(str(shot))


def test_calibrate_view_serves_the_annotated_frame_and_a_verdict(tmp_path):
    p, url = start(["calibrate", "--out", "cal.yaml", "--view", "--view-linger", "20"], tmp_path)
    try:
        s = wait_for(url, lambda s: s["done"])
        assert s["command"] == "calibrate"
        assert s["verdict"]["go"] is True and "6 corners" in s["verdict"]["why"]
        assert s["numbers"]["TCP z [mm]"] == pytest.approx(112.6, abs=1.0)
        assert len(s["residuals"]) >= 40 and all(r["|r| [mm]"] < 0.05 for r in s["residuals"])
        with urllib.request.urlopen(url + "frame.jpg", timeout=5) as r:
            frame = cv2.imdecode(np.frombuffer(r.read(), np.uint8), cv2.IMREAD_COLOR)
        assert frame.shape == (1152, 1536, 3)  # the picture at twice its size
        b, g, r_ = (frame[..., k].astype(int) for k in range(3))
        assert np.count_nonzero((g - r_ > 80) & (g - b > 80)) > 500  # the green disc marks and grid indices
    finally:
        stop(p)
    assert p.returncode in (0, -9)


@needs_chromium
def test_calibrate_page_in_a_browser(tmp_path):
    p, url = start(["calibrate", "--out", "cal.yaml", "--view", "--view-linger", "30"], tmp_path)
    try:
        wait_for(url, lambda s: s["done"])
        dom, shot = browser(url, tmp_path, "calibrate")
    finally:
        stop(p)
    assert re.search(r'<div id="verdict" class="go">GO: all 6 corners, \d+ discs', dom), dom[:2000]
    assert re.search(r"<td>TCP z \[mm\]</td><td>112\.\d{4}</td>", dom)
    assert 'src="frame.jpg?' in dom and "<th>|r| [mm]</th>" in dom
    assert shot is not None
    banner = shot[5:40, 5:1000].reshape(-1, 3).mean(axis=0)  # BGR of the verdict banner: green
    assert banner[1] > 100 and banner[1] > banner[2] + 40
    picture = shot[100:600, 20:760]
    assert picture.std() > 20  # the frame is shown, not an empty box


@needs_chromium
def test_monitor_page_updates_as_frames_arrive(tmp_path):
    code = subprocess.run([sys.executable, "-m", "selfview.procedures.cli", "calibrate", "--out", "cal.yaml",
                           "--no-pictures"], cwd=tmp_path, env=dict(os.environ, PYTHONPATH=str(REPO)),
                          capture_output=True, timeout=120).returncode
    assert code == 0
    p, url = start(["monitor", "--calibration", "cal.yaml", "--frames", "15", "--drift", "0.02", "--view",
                    "--view-linger", "20"], tmp_path)
    try:
        wait_for(url, lambda s: (s["series"] or {}).get("points") and len(s["series"]["points"]) >= 3)
        dom1, _ = browser(url, tmp_path, "monitor1")
        wait_for(url, lambda s: len(s["series"]["points"]) >= 8 or s["done"])
        dom2, shot = browser(url, tmp_path, "monitor2")
        final = wait_for(url, lambda s: s["done"], timeout_s=120)
    finally:
        stop(p)
    frames = [int(re.search(r"<td>frame</td><td>(\d+)</td>", d).group(1)) for d in (dom1, dom2)]
    assert frames[1] > frames[0] >= 1
    assert "alarm limit" in dom2 and "<polyline" in dom2
    assert final["series"]["limits"]["alarm_deg"] > final["series"]["limits"]["update_deg"] > 0
    assert len(final["series"]["points"]) == 15 and final["frame_seq"] >= 15
    assert shot is not None and shot[100:600, 20:760].std() > 20


@pytest.fixture(scope="module")
def pictures(tmp_path_factory):
    from selfview.files.cell import default_cell_path, load_cell
    from selfview.mocks.render import render
    from selfview.mocks.world import SimWorld

    d = tmp_path_factory.mktemp("viewpics")
    w = SimWorld(load_cell(default_cell_path()), seed=3)
    w.park()
    cv2.imwrite(str(d / "parked.png"), render(w, seed=1).image)
    w.disturb("cable")
    cv2.imwrite(str(d / "moved.png"), render(w, seed=2).image)
    cv2.imwrite(str(d / "blank.png"), np.full((576, 768), 128, np.uint8))
    return d


def test_track_view_shows_the_decision_and_a_failed_calibration_says_no_go(pictures, tmp_path):
    d = pictures
    p, url = start(["calibrate", "--image", str(d / "blank.png"), "--out", "bad.yaml", "--view", "--view-linger", "20"],
                   tmp_path)
    try:
        s = wait_for(url, lambda s: s["done"])
    finally:
        stop(p)
    assert s["verdict"]["go"] is False and "ImageError" in s["verdict"]["why"] and s["doing"].startswith("stopped:")
    assert not (tmp_path / "bad.yaml").exists()
    env = dict(os.environ, PYTHONPATH=str(REPO))
    assert subprocess.run([sys.executable, "-m", "selfview.procedures.cli", "calibrate", "--image", str(d / "parked.png"),
                           "--out", "cal.yaml", "--no-pictures"], cwd=tmp_path, env=env, timeout=120).returncode == 0
    p, url = start(["track", "--calibration", "cal.yaml", "--image", str(d / "moved.png"), "--method", "auto",
                    "--view", "--view-linger", "20"], tmp_path)
    try:
        s = wait_for(url, lambda s: s["done"])
    finally:
        stop(p)
    assert s["verdict"]["go"] is True and s["numbers"]["decision"] in ("update", "recalibrate")
    assert s["numbers"]["d_mm"] > 0 and s["frame_seq"] >= 2 and "B-outer-front" in s["numbers"]["points found"]


def test_park_view_serves_the_parked_picture(tmp_path):
    p, url = start(["park", "--out", "parked.png", "--view", "--view-linger", "20"], tmp_path)
    try:
        s = wait_for(url, lambda s: s["done"])
        with urllib.request.urlopen(url + "frame.jpg", timeout=5) as r:
            frame = cv2.imdecode(np.frombuffer(r.read(), np.uint8), cv2.IMREAD_GRAYSCALE)
    finally:
        stop(p)
    assert s["command"] == "park" and s["verdict"]["go"] is True and s["numbers"]["picture"] == "768x576"
    parked = cv2.imread(str(tmp_path / "parked.png"), cv2.IMREAD_GRAYSCALE)
    assert frame.shape == parked.shape and np.abs(frame.astype(int) - parked).mean() < 3  # the same picture, as JPEG
    assert "moves(" in s["doing"] or "grab" in s["doing"]
