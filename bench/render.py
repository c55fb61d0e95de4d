"""Benchmark of the simulated wrist camera: time to render one 768 x 576 frame, on one core.

Renders the reference cell's picture with the gripper parked on the plate (the off-line calibration
picture) and with the gripper lifted over the textured table, and prints one JSON object with the
median wall-clock and CPU time per frame of each, and the machine and library versions.

    python bench/render.py [--repeat 7] [--cell CELL.yaml] [--seed 0]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

if not __package__ and (Path(__file__).resolve().parents[1] / "pyproject.toml").is_file():
    # run as a file in a source tree: import the tree it lies in (installed, selfview is on the path)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from selfview.mocks.render import LIFTED_W_H_G, render  # noqa: E402
from selfview.mocks.world import SimWorld  # noqa: E402
from selfview.files.cell import default_cell_path, load_cell  # noqa: E402


def _time(world: SimWorld, repeat: int) -> dict:
    render(world, seed=0)  # warm-up: imports, the table texture
    wall, cpu = [], []
    for i in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        render(world, seed=i)
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return {
        "median_s": round(statistics.median(wall), 4),
        "min_s": round(min(wall), 4),
        "median_cpu_s": round(statistics.median(cpu), 4),
        "renders": repeat,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7, help="frames per scene (>= 5)")
    ap.add_argument("--cell", default=str(default_cell_path()), help="cell description")
    ap.add_argument("--seed", type=int, default=0, help="seed of the simulated cell")
    args = ap.parse_args(argv)
    if args.repeat < 5:
        ap.error("--repeat: expected at least 5 frames for a median")
    cv2.setNumThreads(1)  # one core: numpy's element-wise work is single-threaded already
    cell = load_cell(args.cell)

    parked = SimWorld(cell, seed=args.seed)
    parked.park()
    free = SimWorld(cell, seed=args.seed)
    free.set_tcp(free.base_H_plate0 @ LIFTED_W_H_G)

    out = {
        "benchmark": "render",
        "frame": [cell.camera.width, cell.camera.height],
        "target_s": 0.5,
        "parked": _time(parked, args.repeat),
        "free": _time(free, args.repeat),
        "cv2_threads": cv2.getNumThreads(),
        "machine": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "cv2": cv2.__version__,
            "cpu": platform.processor() or platform.machine(),
            "cores": os.cpu_count(),
            "load_1min": round(os.getloadavg()[0], 2),
        },
    }
    out["median_s"] = out["parked"]["median_s"]
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
