"""Study: our disc detector beside ``cv2.findCirclesGrid`` (and its clustering mode) on real photographs.

The pictures are ViSP's photographs of a printed 6 x 6 disc grid (``tests/data/visp-circles``), as taken
and changed the ways real pictures differ: turned in the picture by 15..80 deg (on a canvas that holds the
whole photograph, the new corners the paper's grey), a lamp's shadow across the grid (a soft-edged band
at 45 % light), uneven light (a 2:1 ramp), glare (``hazed``: 100 grey levels over a fifth of the light).
The three detectors run interleaved on each picture, ``--repeat`` times, so that the machine's load falls
on all of them alike. Prints one JSON object: per picture the
discs each found (0 where OpenCV returns no grid), the median time of each, our centres against
OpenCV's where both found the grid, our median time over each OpenCV mode's (``time_ratio_ours_to``), and
the medians over the set (``median_time_ratio_ours_to_findCirclesGrid`` is issue 31's measure). A changed
picture's truth is known: each detector's centres in the unchanged photograph, turned as it was turned;
``moved_px`` is how far each detector's centres are from its own truth (the largest over the discs).
``--floor`` times instead what the detector would take if a stage cost nothing (``floor_study``).

    python bench/discs_vs_opencv.py [--repeat 5] [--quick] [--floor]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from selfview.files.cell import load_cell  # noqa: E402
from selfview.measurement.discs import detect_discs  # noqa: E402
from selfview.errors import ImageError  # noqa: E402

if str(Path(__file__).resolve().parents[1]) not in sys.path:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the picture changes live beside the tests
from tests.photo_variants import hazed, ramp, shadowed, turn_matrix, turned  # noqa: E402

SET = Path(__file__).resolve().parents[1] / "tests" / "data" / "visp-circles"
TURNS_DEG = (15, 30, 55, 80)


def pictures(quick: bool):
    names = sorted(p.name for p in SET.glob("*.*g"))
    if not names:
        raise SystemExit(f"discs_vs_opencv: no photographs in {SET.relative_to(SET.parents[2])}: run it from a "
                         "source checkout, which holds them")
    if quick:
        names = names[:2] + names[-2:]
    for name in names:
        img = cv2.imread(str(SET / name), cv2.IMREAD_GRAYSCALE)
        plate = load_cell(SET / ("cell-640x480.yaml" if name.endswith(".png") else "cell.yaml")).plate
        same = np.eye(2, 3)
        yield name, img, plate, None
        for d in (TURNS_DEG[2:3] if quick else TURNS_DEG):
            yield f"{name} turned {d}", turned(img, d), plate, turn_matrix(img.shape, d)[0]
        yield f"{name} shadow", shadowed(img), plate, same
        if not quick:
            yield f"{name} ramp", ramp(img), plate, same
            yield f"{name} glare", hazed(img), plate, same


def run_ours(img, plate):
    try:
        det = detect_discs(img, plate)
    except ImageError:
        return None
    return det.uv


def run_opencv(img, plate, clustering: bool):
    flags = cv2.CALIB_CB_SYMMETRIC_GRID | (cv2.CALIB_CB_CLUSTERING if clustering else 0)
    ok, c = cv2.findCirclesGrid(img, (plate.cols, plate.rows), flags=flags)
    return c.reshape(-1, 2).astype(float) if ok else None


def study(repeat: int, quick: bool) -> dict:
    runners = {
        "ours": run_ours,
        "findCirclesGrid": lambda i, p: run_opencv(i, p, False),
        "findCirclesGrid_clustering": lambda i, p: run_opencv(i, p, True),
    }
    rows = []
    plain = {}
    for name, img, plate, M in pictures(quick):
        times = {k: [] for k in runners}
        found = {}
        for _ in range(repeat):
            for k, fn in runners.items():  # interleaved: the load falls on all three alike
                t = time.perf_counter()
                found[k] = fn(img, plate)
                times[k].append((time.perf_counter() - t) * 1e3)
        row = {"picture": name, "discs_on_plate": plate.cols * plate.rows,
               "discs": {k: 0 if v is None else len(v) for k, v in found.items()},
               "ms": {k: round(float(np.median(v)), 2) for k, v in times.items()}}
        row["time_ratio_ours_to"] = {k: round(float(np.median(times["ours"]) / np.median(times[k])), 2)
                                     for k in runners if k != "ours"}
        if M is None:
            plain = found
        else:  # a changed photograph: its truth is each detector's own centres in the photograph, moved as it was
            row["moved_px"] = {}
            for k in runners:
                if found[k] is not None and plain[k] is not None:
                    d = np.linalg.norm(found[k][:, None] - (plain[k] @ M[:, :2].T + M[:, 2])[None], axis=2).min(1)
                    row["moved_px"][k] = round(float(d[d <= 3.0].max()), 3)
        ours = found["ours"]
        for k in ("findCirclesGrid", "findCirclesGrid_clustering"):
            ref = found[k]
            if ours is not None and ref is not None:
                d = np.linalg.norm(ref[:, None, :] - ours[None, :, :], axis=2).min(axis=1)
                both = d[d <= 3.0]  # the discs both found (OpenCV's others: ours has none within 3 px)
                if both.size == 0:  # two grids, no disc in common: no centre to compare
                    row[f"centres_vs_{k}_px"] = {"median": None, "max": None, "only_opencv": int(d.size)}
                    continue
                row[f"centres_vs_{k}_px"] = {"median": round(float(np.median(both)), 3), "max": round(float(both.max()), 3),
                                             "only_opencv": int(np.sum(d > 3.0))}
        rows.append(row)
    ratio = [r["time_ratio_ours_to"]["findCirclesGrid"] for r in rows]
    ratio_c = [r["time_ratio_ours_to"]["findCirclesGrid_clustering"] for r in rows]
    on_plates = sum(r["discs_on_plate"] for r in rows)
    centres = [r[k] for r in rows for k in r if k.startswith("centres_vs") and r[k]["max"] is not None]
    summary = {
        "pictures": len(rows),
        "share_of_discs_found": {k: round(sum(r["discs"][k] for r in rows) / on_plates, 3) for k in runners},
        "pictures_where_ours_finds_fewer_than_the_better_opencv": [
            r["picture"] for r in rows
            if r["discs"]["ours"] < max(r["discs"]["findCirclesGrid"], r["discs"]["findCirclesGrid_clustering"])],
        "median_time_ratio_ours_to_findCirclesGrid": round(float(np.median(ratio)), 2),
        "median_time_ratio_ours_to_clustering": round(float(np.median(ratio_c)), 2),
        "max_centre_difference_px": max((c["max"] for c in centres), default=None),
        "median_centre_difference_px": round(float(np.median([c["median"] for c in centres])), 3) if centres else None,
        "max_moved_px": {k: max((r["moved_px"][k] for r in rows if k in r.get("moved_px", {})), default=None)
                         for k in runners},
    }
    return {"repeat": repeat, "quick": quick, "opencv": cv2.__version__, "summary": summary, "pictures": rows}


def _box_centres(work, labels, stats, round_, reject, noise):
    """The refinement at no cost: each round blob's box centre, its area."""
    rows = stats[round_].tolist()
    return [np.array([x + (w - 1) / 2, y + (h - 1) / 2]) for x, y, w, h, _ in rows], [r[4] for r in rows]


def _all_round(labels, stats, reject, smooth):
    """The ellipse tests at no cost: every blob of 20 px or more, clear of the border, under 5 % of the picture."""
    H, W = labels.shape
    x, y, w, h, area = stats[1:].T
    ok = (area >= 20) & (area <= 0.05 * H * W) & (x > 0) & (y > 0) & (x + w < W) & (y + h < H)
    return list(np.flatnonzero(ok) + 1), stats


FREE_STAGES = {"as_is": {},
               "refinement_free": {"_measure_discs": _box_centres},
               "refinement_and_ellipse_tests_free": {"_measure_discs": _box_centres, "_round_blobs": _all_round}}


def floor_study(repeat: int, quick: bool) -> dict:
    """Our detector's time with a stage made free (``FREE_STAGES``: the per-disc refinement, a blob's box centre
    instead; and the per-blob ellipse tests, every blob of a disc's size taken), beside findCirclesGrid, interleaved
    per picture: how much of our time each stage is, and the time per disc (``per_disc_budget_us``) the per-disc
    stages may take together for the detector to match findCirclesGrid's median time. A study of where the time
    goes, not a detector: the free stages' centres are not measured."""
    from selfview.measurement import discs

    saved = {name: getattr(discs, name) for v in FREE_STAGES.values() for name in v}
    times = {k: [] for k in (*FREE_STAGES, "findCirclesGrid")}
    on_plate = []  # discs on each picture's plate
    try:
        for _, img, plate, _ in pictures(quick):
            t_pic = {k: [] for k in times}
            for _ in range(repeat):
                for k, stages in FREE_STAGES.items():
                    for name, fn in saved.items():
                        setattr(discs, name, stages.get(name, fn))
                    t = time.perf_counter()
                    run_ours(img, plate)
                    t_pic[k].append((time.perf_counter() - t) * 1e3)
                t = time.perf_counter()
                run_opencv(img, plate, False)
                t_pic["findCirclesGrid"].append((time.perf_counter() - t) * 1e3)
            for k in times:
                times[k].append(float(np.median(t_pic[k])))
            on_plate.append(plate.rows * plate.cols)
    finally:
        for name, fn in saved.items():
            setattr(discs, name, fn)
    cv = np.array(times["findCirclesGrid"])
    ms = {k: round(float(np.median(v)), 2) for k, v in times.items()}
    free = np.array(times["refinement_and_ellipse_tests_free"])
    return {"repeat": repeat, "quick": quick, "opencv": cv2.__version__, "pictures": len(cv), "median_ms": ms,
            "median_time_ratio_to_findCirclesGrid": {k: round(float(np.median(np.array(v) / cv)), 2)
                                                     for k, v in times.items() if k != "findCirclesGrid"},
            "per_disc_budget_us": round(float(np.median((cv - free) / np.array(on_plate))) * 1e3, 1),
            "per_disc_now_us": round(float(np.median((np.array(times["as_is"]) - free) / np.array(on_plate))) * 1e3, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="runs of each detector per picture (interleaved)")
    ap.add_argument("--quick", action="store_true", help="4 photographs, one turn each, no ramp")
    ap.add_argument("--floor", action="store_true", help="our time with the per-disc stages made free (floor_study)")
    args = ap.parse_args(argv)
    if args.repeat < 1:
        print("discs_vs_opencv: --repeat must be at least 1", file=sys.stderr)
        return 2
    run = floor_study if args.floor else study
    print(json.dumps(run(args.repeat, args.quick), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
