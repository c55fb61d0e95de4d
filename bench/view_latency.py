"""Benchmark of the live view (``--view``): how long a new frame takes to reach a real browser's page.

A ``LiveView`` publishes an annotated 1536 x 1152 frame every ``--period`` seconds while headless Chromium
shows the page for ``--seconds``; the time from each publication to the page's next request of its state
(after which it fetches the frame at once) is the page's update latency. Also the JPEG encoding and the
two requests' times. Prints one JSON object.

    python bench/view_latency.py [--seconds 6] [--period 0.13]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

if not __package__ and (Path(__file__).resolve().parents[1] / "pyproject.toml").is_file():
    # run as a file in a source tree: import the tree it lies in (installed, selfview is on the path)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from selfview.files.cell import default_cell_path, load_cell  # noqa: E402
from selfview.mocks.render import render  # noqa: E402
from selfview.mocks.world import SimWorld  # noqa: E402
from selfview.estimation.offline import calibrate_offline  # noqa: E402
from selfview.procedures.results import draw_offline  # noqa: E402
from selfview.procedures.view import LiveView  # noqa: E402


class TimedView(LiveView):
    """A LiveView that notes when the page asks for its state."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.asked: list[float] = []

    def state(self) -> dict:
        self.asked.append(time.monotonic())
        return super().state()


def ms(values) -> float | None:
    return round(1000 * statistics.median(values), 2) if values else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=6.0, help="how long the browser shows the page")
    ap.add_argument("--period", type=float, default=0.13, help="seconds between two frames")
    args = ap.parse_args(argv)
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    cell = load_cell(default_cell_path())
    w = SimWorld(cell, seed=0)
    w.park()
    img = render(w, seed=1).image
    annotated = draw_offline(img, calibrate_offline(img, cell))
    view = TimedView("bench").start()
    enc, published, stop = [], [], threading.Event()

    def publish():
        end = time.monotonic() + args.seconds + 3.0
        while not stop.is_set() and time.monotonic() < end:
            t = time.monotonic()
            view.frame(annotated)
            enc.append(time.monotonic() - t)
            published.append(time.monotonic())
            time.sleep(args.period)

    view.frame(annotated)
    th = threading.Thread(target=publish, daemon=True)
    th.start()
    req_state, req_frame = [], []
    for _ in range(20):
        t = time.monotonic()
        urllib.request.urlopen(view.url + "state.json", timeout=5).read()
        req_state.append(time.monotonic() - t)
        t = time.monotonic()
        size = len(urllib.request.urlopen(view.url + "frame.jpg", timeout=5).read())
        req_frame.append(time.monotonic() - t)
    latency = []
    if chromium:
        view.asked.clear()
        t0 = time.monotonic()
        with tempfile.TemporaryDirectory() as prof:
            # a browser that stays on the page (the debugging port keeps it open) until it is stopped
            b = subprocess.Popen([chromium, "--headless", "--no-sandbox", "--disable-gpu", f"--user-data-dir={prof}",
                                  "--remote-debugging-port=0", view.url],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            try:
                time.sleep(args.seconds)
            finally:
                b.terminate()
                try:
                    b.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    b.kill()
                    b.wait(timeout=10)
        asked = np.array([a for a in view.asked if a > t0])
        for p in published:
            later = asked[asked >= p]
            if p > t0 + 1.0 and len(later):  # after the page has loaded
                latency.append(float(later[0] - p))
    stop.set()
    th.join(timeout=5)
    view.close()
    print(json.dumps({
        "frame_px": [int(annotated.shape[1]), int(annotated.shape[0])], "jpeg_kB": round(size / 1024, 1),
        "jpeg_encode_ms": ms(enc), "state_request_ms": ms(req_state), "frame_request_ms": ms(req_frame),
        "browser": chromium is not None, "frames_seen": len(latency),
        "publish_to_page_ms": {"median": ms(latency), "max": round(1000 * max(latency), 1) if latency else None},
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
