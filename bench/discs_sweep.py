"""Study: the disc detector against ``cv2.findCirclesGrid`` on real photographs changed the ways pictures go wrong.

Every real disc-grid photograph in ``tests/data`` (ViSP's nine, BoofCV's stills and video frames) is changed
each of these ways: Gaussian blur (sigma 2 and 3.5 px), sensor noise (sigma 10 grey levels), JPEG at quality
20, over-exposure (light x 1.8, clipped), a dark picture (x 0.25), gamma 2.2, a 7 px motion blur, half size, and
glare (``tests.photo_variants.hazed``: 100 grey levels over a fifth of the light). Per change: the discs each
detector finds (OpenCV's grid in either of its modes, all or nothing), the pictures where ours finds fewer, and
how far each detector's centres move from its own in the unchanged photograph (the change keeps the geometry;
half size maps it). Prints one JSON object.

    python bench/discs_sweep.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))  # the picture changes live beside the tests

from selfview.bench.discs_vs_opencv import run_opencv, run_ours  # noqa: E402
from selfview.files.cell import load_cell, load_plate  # noqa: E402
from tests.photo_variants import hazed  # noqa: E402

DATA = ROOT / "tests" / "data"


def _u8(a) -> np.ndarray:
    return np.clip(a, 0, 255).astype(np.uint8)


#: name: (change of a grey uint8 picture, the change's map of pixel positions (N, 2) -> (N, 2)).
CHANGES = {
    "blur 2 px": (lambda g: cv2.GaussianBlur(g, (0, 0), 2.0), None),
    "blur 3.5 px": (lambda g: cv2.GaussianBlur(g, (0, 0), 3.5), None),
    "noise 10": (lambda g: _u8(g + np.random.default_rng(1).normal(0.0, 10.0, g.shape)), None),
    "jpeg 20": (lambda g: cv2.imdecode(cv2.imencode(".jpg", g, [cv2.IMWRITE_JPEG_QUALITY, 20])[1], 0), None),
    "over-exposed x1.8": (lambda g: _u8(g * 1.8), None),
    "dark x0.25": (lambda g: _u8(g * 0.25), None),
    "gamma 2.2": (lambda g: _u8(255.0 * (g / 255.0) ** 2.2), None),
    "motion 7 px": (lambda g: cv2.filter2D(g, -1, np.ones((1, 7), np.float32) / 7), None),
    "half size": (lambda g: cv2.resize(g, (g.shape[1] // 2, g.shape[0] // 2), interpolation=cv2.INTER_AREA),
                  lambda uv: (uv + 0.5) / 2 - 0.5),
    "glare": (hazed, None),
}


def photographs(quick: bool):
    """(name, grey picture, plate) of every real disc-grid photograph (``quick``: two of each set)."""
    sets = [(DATA / "visp-circles", "*.*g", None)]
    sets += [(DATA / f, "*.jpg", load_plate(DATA / f / "plate.yaml")) for f in ("boofcv-circles", "boofcv-circles-video")]
    for folder, pattern, plate in sets:
        files = sorted(folder.glob(pattern))
        for f in files[:2] if quick else files:
            p = plate or load_cell(folder / ("cell-640x480.yaml" if f.suffix == ".png" else "cell.yaml")).plate
            yield f"{folder.name}/{f.name}", cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), p


def _opencv(img, plate):
    """OpenCV's grid in either of its modes (findCirclesGrid's plain mode first), or None."""
    found = run_opencv(img, plate, False)
    return found if found is not None else run_opencv(img, plate, True)


def _moved(found, truth) -> float | None:
    """The largest distance [px] of ``found`` centres from their nearest ``truth`` (within 3 px), or None."""
    if found is None or truth is None:
        return None
    d = np.linalg.norm(found[:, None] - truth[None], axis=2).min(1)
    return float(d[d <= 3.0].max()) if np.any(d <= 3.0) else None


def study(quick: bool) -> dict:
    detectors = {"ours": run_ours, "opencv": _opencv}
    out = {k: {"discs_on_plates": 0, "found": dict.fromkeys(detectors, 0), "fewer": [],
               "max_moved_px": dict.fromkeys(detectors)} for k in CHANGES}
    for name, img, plate in photographs(quick):
        plain = {k: fn(img, plate) for k, fn in detectors.items()}
        for change, (fn, where) in CHANGES.items():
            pic, row = fn(img), out[change]
            found = {k: det(pic, plate) for k, det in detectors.items()}
            row["discs_on_plates"] += plate.rows * plate.cols
            for k, uv in found.items():
                row["found"][k] += 0 if uv is None else len(uv)
                truth = plain[k] if where is None or plain[k] is None else where(plain[k])
                m = _moved(uv, truth)
                if m is not None:
                    row["max_moved_px"][k] = round(max(m, row["max_moved_px"][k] or 0.0), 3)
            n = {k: 0 if uv is None else len(uv) for k, uv in found.items()}
            if n["ours"] < n["opencv"]:
                row["fewer"].append(f"{name}: {n['ours']} of OpenCV's {n['opencv']}")
    return {"opencv": cv2.__version__, "quick": quick, "changes": out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two photographs of each set")
    args = ap.parse_args(argv)
    print(json.dumps(study(args.quick), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
