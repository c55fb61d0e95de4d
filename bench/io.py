"""Benchmark of the I/O drivers on loopback; prints one JSON object.

- gripper: open/close-to-confirmed latency against the simulated valve terminal, minus the stroke's
  simulated travel time (what the driver and Modbus add), and the Modbus request round trip (one FC2
  read), for Modbus TCP and RTU frames over TCP;
- pictures: the checked reader (``selfview.files.io_safe.read_picture``: header size check, then OpenCV's
  decoder) against ``cv2.imread`` on a 768 x 576 PNG, and the time to refuse a 0.3 MB PNG whose header
  says 30000 x 30000 (refused from the header; OpenCV would decode 900 Mpx);
- frames per second from ``sim://`` (cached render: the world at rest; and a world that changes every
  frame, so each frame is rendered) and from ``frames://`` (768 x 576 PNG sequence).

Run: ``python bench/io.py [--strokes N] [--requests N] [--frames N]``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

if not __package__ and (Path(__file__).resolve().parents[1] / "pyproject.toml").is_file():
    # run as a file in a source tree: import the tree it lies in (installed, selfview is on the path)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from selfview.drivers.frame_grabber_v4l2 import FrameGrabber  # noqa: E402
from selfview.drivers.pneumatic_gripper import PneumaticGripper  # noqa: E402
from selfview.mocks.sim_camera import attach_world  # noqa: E402
from selfview.mocks.valve_terminal import ValveTerminal  # noqa: E402
from selfview.mocks.world import SimWorld  # noqa: E402
from selfview import __version__  # noqa: E402
from selfview.files.cell import default_cell_path, load_cell  # noqa: E402


def stats(values_s: list[float]) -> dict:
    a = np.asarray(values_s) * 1000.0
    return {
        "n": int(a.size),
        "mean_ms": round(float(a.mean()), 3),
        "median_ms": round(float(np.median(a)), 3),
        "p95_ms": round(float(np.percentile(a, 95)), 3),
        "max_ms": round(float(a.max()), 3),
    }


def bench_gripper(framing: str, strokes: int, requests: int, travel_s: float) -> dict:
    with ValveTerminal(travel_s=travel_s, framing=framing, watchdog_s=1.0) as t:
        scheme = t.url.split(":")[0]
        with PneumaticGripper(t.url, poll_s=0.1, confirm_poll_s=0.002) as g:
            latency, overhead = [], []
            for k in range(strokes):
                n = len(t.strokes)
                t0 = time.monotonic()
                (g.close_jaws if k % 2 == 0 else g.open_jaws)()
                dt = time.monotonic() - t0
                _, switched, arrived = t.strokes[n]
                latency.append(dt)
                overhead.append(dt - (arrived - switched))
            rtt = []
            for _ in range(requests):
                t0 = time.monotonic()
                g.read()
                rtt.append(time.monotonic() - t0)
    return {
        "url_scheme": scheme,
        "travel_s": travel_s,
        "confirm_poll_s": 0.002,
        "open_close_to_confirmed": stats(latency),
        "minus_travel": stats(overhead),
        "request_round_trip": stats(rtt),
    }


def bench_sim(frames: int) -> dict:
    cell = load_cell(default_cell_path())
    world = SimWorld(cell, seed=1)
    world.park()
    out = {}
    with attach_world(world), FrameGrabber("sim://?fps=1000&seed=1", timeout_s=5.0) as g:
        g.grab()  # the first render fills the cache
        t0 = time.monotonic()
        for _ in range(frames):
            g.grab()
        out["fps_world_at_rest"] = round(frames / (time.monotonic() - t0), 2)
        n = max(3, frames // 10)
        gaps = cell.gripper.states
        t0 = time.monotonic()
        for k in range(n):
            world.set_jaw(gaps["open"] - (k % 2) * 0.5)  # every frame a new scene: a full render
            g.grab()
        out["fps_world_changing"] = round(n / (time.monotonic() - t0), 2)
        out["renders"] = g.source.renders
    return out


def bench_frames(frames: int) -> dict:
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as d:
        img = np.clip(rng.normal(128, 30, (576, 768)), 0, 255).astype(np.uint8)
        for i in range(frames):
            cv2.imwrite(f"{d}/img_{i:04d}.png", np.roll(img, i, axis=1))
        with FrameGrabber(f"frames://{d}/img_%04d.png", width=768, height=576) as g:
            t0 = time.monotonic()
            for _ in range(frames):
                g.grab()
            dt = time.monotonic() - t0
    return {"fps": round(frames / dt, 2), "frames": frames, "size": [768, 576]}


def bench_pictures(repeats: int) -> dict:
    import struct
    import zlib

    from selfview.files.io_safe import read_picture
    from selfview.errors import ImageError

    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "x.png"
        cv2.imwrite(str(p), np.clip(rng.normal(128, 30, (576, 768)), 0, 255).astype(np.uint8))
        out = {}
        for name, fn in (("checked_ms", lambda: read_picture(p)), ("cv2_imread_ms", lambda: cv2.imread(str(p), 0))):
            t = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                fn()
                t.append(time.perf_counter() - t0)
            out[name] = round(1000 * float(np.median(t)), 3)

        def chunk(kind, data):
            return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

        bomb = Path(d) / "bomb.png"
        ihdr = struct.pack(">IIBBBBB", 30000, 30000, 8, 0, 0, 0, 0)
        bomb.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 30_000_000))
                         + chunk(b"IEND", b""))
        t0 = time.perf_counter()
        try:
            read_picture(bomb)
            refused = False
        except ImageError:
            refused = True
        out["bomb_png_bytes"] = bomb.stat().st_size
        out["bomb_30000x30000_refused"] = refused
        out["bomb_refusal_ms"] = round(1000 * (time.perf_counter() - t0), 3)
    out["size"] = [768, 576]
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--strokes", type=int, default=20)
    p.add_argument("--requests", type=int, default=500)
    p.add_argument("--frames", type=int, default=50)
    p.add_argument("--travel", type=float, default=0.05, help="simulated jaw travel time, s")
    a = p.parse_args(argv)
    result = {
        "benchmark": "io",
        "selfview": __version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "gripper_modbus_tcp": bench_gripper("mbap", a.strokes, a.requests, a.travel),
        "gripper_rtu_over_tcp": bench_gripper("rtu", a.strokes, a.requests, a.travel),
        "sim": bench_sim(a.frames),
        "frames": bench_frames(a.frames),
        "pictures": bench_pictures(a.frames),
    }
    json.dump(result, sys.stdout)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
