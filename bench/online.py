"""Benchmark: one on-line solve (4P-U, 4P-I, 4P-R) against OpenCV's solvePnP on the same four points.

Prints one JSON object: the median time of one call of each solver [us] (batches of the solvers taken
in turn) and its ratio to 4P-U, the TCP error of each against the simulator's truth, a yardstick of
this machine's speed (one trivial numpy operation on a small array), and the median time of the whole
per-frame step (find the fingertip corners in a 768x576 picture + 4P-I) when the fingertip finder
exists and finds the four inner corners (null otherwise, with the reason). One run, one core: BLAS and
OpenCV threads are limited to one and the process is pinned to one CPU.

The scene: the reference cell simulated (seed 3), the camera disturbed by one draw of the paper's
'cable' series (a typical one: the TCP moves 1.4 mm), the four inner corners projected exactly and
given 0.05 px of noise. OpenCV gets them already undistorted and normalised (identity camera matrix, no distortion: its
distortion model is not the paper's kappa); our solvers take the distorted pixels and undistort them.

    python bench/online.py [--repeat 300] [--number 20]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import timeit  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mocks.world import SimWorld  # noqa: E402
from selfview.cell import default_cell_path, load_cell  # noqa: E402
from selfview.geometry import make_H, transform_points  # noqa: E402
from selfview.online import differential_update, iterative_update, recalibrate  # noqa: E402

TARGET_SOLVE_US = 50.0
TARGET_STEP_MS = 5.0


def median_us(fn, repeat: int, number: int) -> float:
    """Median time of one call of ``fn`` [us] over ``repeat`` batches of ``number`` calls."""
    fn()  # warm up
    return statistics.median(timeit.repeat(fn, number=number, repeat=repeat)) / number * 1e6


def interleaved_median_us(fns: dict, repeat: int, number: int) -> dict:
    """``median_us`` of several functions, their batches taken in turn, so that a change of the
    machine's load during the run weighs on all of them alike and their ratios stay meaningful."""
    timers = {k: timeit.Timer(fn) for k, fn in fns.items()}
    for fn in fns.values():
        fn()  # warm up
    times = {k: [] for k in fns}
    for _ in range(repeat):
        for k, t in timers.items():
            times[k].append(t.timeit(number))
    return {k: statistics.median(v) / number * 1e6 for k, v in times.items()}


def per_frame_step(cell, world, C_H_G_before):
    """(median [ms] of find_fingertips + 4P-I on a rendered 768x576 picture or None, median [ms] of
    find_fingertips alone or None, a note)."""
    try:
        from selfview.fingertips import find_fingertips
    except ImportError as exc:
        return None, None, f"selfview.fingertips not available ({exc})"
    from mocks.render import render
    from selfview.errors import CalibrationError
    from selfview.online import estimate

    image = render(world, seed=1).image
    gap = world.jaw_gap_mm
    p_G6 = cell.gripper.points_G(gap=gap)

    def find():
        return find_fingertips(image, world.camera, C_H_G_before, cell.gripper, gap)

    def step():
        fr = find()
        return estimate("4P-I", C_H_G_before, p_G6, fr.uv, fr.found, world.camera)

    find_ms = median_us(find, repeat=5, number=1) / 1000.0
    try:
        est = step()
    except CalibrationError as exc:
        return None, find_ms, f"the finder's corners do not allow 4P-I in the benchmark picture: {exc}"
    ms = median_us(step, repeat=5, number=1) / 1000.0
    err = float(np.linalg.norm(est.C_H_G[:3, 3] - world.C_H_G[:3, 3]))
    return ms, find_ms, f"4P-I TCP error from the rendered picture {err:.4f} mm"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=300, help="batches per solver (median over them)")
    ap.add_argument("--number", type=int, default=20, help="calls per batch")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

    cell = load_cell(default_cell_path())
    world = SimWorld(cell, seed=3)
    C_H_G_before = world.C_H_G
    dist = world.disturb("cable")
    truth = world.C_H_G
    cam = world.camera
    P = world.points_G()[:4]
    rng = np.random.default_rng(0)
    uv = cam.project(transform_points(truth, P)) + rng.normal(scale=0.05, size=(4, 2))
    # OpenCV's input: the same observations undistorted by our model and normalised by f
    img = (cam.undistort_pixels(uv) / cam.f).reshape(-1, 1, 2)
    obj = P.reshape(-1, 1, 3)
    K = np.eye(3)

    def cv_pose(flag):
        ok, rv, tv = cv2.solvePnP(obj, img, K, None, flags=flag)
        return make_H(cv2.Rodrigues(rv)[0], tv.ravel())

    solvers = {
        "4P-U": lambda: differential_update(C_H_G_before, P, uv, cam).C_H_G,
        "4P-I": lambda: iterative_update(C_H_G_before, P, uv, cam).C_H_G,
        "4P-R": lambda: recalibrate(C_H_G_before, P, uv, cam).C_H_G,
        "cv2.solvePnP ITERATIVE": lambda: cv_pose(cv2.SOLVEPNP_ITERATIVE),
        "cv2.solvePnP IPPE": lambda: cv_pose(cv2.SOLVEPNP_IPPE),
    }
    times = interleaved_median_us(solvers, args.repeat, args.number)
    errors = {k: float(np.linalg.norm(fn()[:3, 3] - truth[:3, 3])) for k, fn in solvers.items()}
    small = np.ones(8)
    numpy_op_us = median_us(lambda: small * 2.0, args.repeat, 200)
    step_ms, find_ms, step_note = per_frame_step(cell, world, C_H_G_before)
    out = {
        "benchmark": "online solve",
        "scene": {
            "series": "cable",
            "tcp_shift_mm": float(np.linalg.norm(dist.tcp_shift_C)),
            "angle_deg": float(dist.angle_deg),
            "noise_px": 0.05,
            "points": 4,
        },
        "median_us": {k: round(v, 2) for k, v in times.items()},
        "ratio_to_4P-U": {k: round(v / times["4P-U"], 3) for k, v in times.items()},
        "tcp_error_mm": {k: round(v, 6) for k, v in errors.items()},
        "target_solve_us": TARGET_SOLVE_US,
        "4P-U_within_target": times["4P-U"] <= TARGET_SOLVE_US,
        "numpy_op_us": round(numpy_op_us, 3),
        "per_frame_step_ms": None if step_ms is None else round(step_ms, 3),
        "find_fingertips_ms": None if find_ms is None else round(find_ms, 3),
        "per_frame_step_note": step_note,
        "target_step_ms": TARGET_STEP_MS,
        "repeat": args.repeat,
        "number": args.number,
        "versions": {"numpy": np.__version__, "opencv": cv2.__version__, "python": sys.version.split()[0]},
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
