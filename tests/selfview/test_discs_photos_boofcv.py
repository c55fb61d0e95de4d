"""Disc detection and intrinsics on a second public set of real photographs: BoofCV's regular circle grid.

Six 640 x 480 colour JPEGs by a Sony DSC-HX5V of an 8 x 10 grid of dark discs (15 mm at 25 mm pitch) on a
sheet clipped to a clipboard (``tests/data/boofcv-circles``, CC BY 4.0). Its defects beside ViSP's set:
another camera and disc-to-pitch ratio (0.6), a rectangular grid, the clipboard's metal clip beside the
grid, a bent sheet, two views (00000, 00004) that plain ``cv2.findCirclesGrid`` does not assemble (its
clustering mode does), and a hand's shadow over a quarter of the grid (00005).

Measured (ours / findCirclesGrid / clustering discs; our centres against OpenCV's, median and max px):
00000 80 / 0 / 80, 0.047, 0.22; 00001 80 / 80 / 80, 0.042, 0.71; 00002 80 / 80 / 80, 0.055, 0.48;
00003 80 / 80 / 80, 0.038, 0.11; 00004 80 / 0 / 80, 0.036, 0.18; 00005 71 / 80 / 80, 0.068, 1.26.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from selfview.estimation.intrinsics import detect_views, guess_camera
from selfview.files.cell import load_plate
from selfview.measurement.discs import detect_discs
from selfview.procedures.cli import main
from tests.grid_photos import OPENCV_MODES, nearest, opencv_grid, opencv_intrinsics, same_indexing

SET = Path(__file__).resolve().parents[1] / "data" / "boofcv-circles"
PICTURES = [f"image0000{i}.jpg" for i in range(6)]
PLATE = SET / "plate.yaml"
#: Our centres against OpenCV's [px]: the median as for ViSP's set; any one of ours within this of one of
#: OpenCV's is on that disc (the discs lie 35-60 px apart here); the largest measured, 1.26 px, is a disc
#: half in the hand's shadow, 0.71 px one at the sheet's near edge.
MEDIAN_PX, SAME_DISC_PX = 0.3, 1.5

SHADOW = pytest.mark.xfail(
    strict=True,
    reason="a hand's shadow over a quarter of the grid: OpenCV (both modes) finds all 80 discs, ours 71; "
    "the 9 in or at the edge of the shadow are rejected as 'not elliptical' (merged with the shadow) or "
    "'crowded' (measured; the detector is not tuned to this set)",
)


def _load(name):
    img = cv2.imread(str(SET / name), cv2.IMREAD_GRAYSCALE)
    assert img is not None, f"missing test picture {name}"
    return img


def _best_opencv(img, plate):
    """The grid of whichever of OpenCV's modes finds it (both give the same centres), or None."""
    grids = [g for g in (opencv_grid(img, plate, mode) for mode in OPENCV_MODES) if g is not None]
    return grids[0] if grids else None


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=SHADOW) if n == "image00005.jpg" else n for n in PICTURES]
)
def test_as_many_discs_as_the_better_of_opencvs_modes(name):
    img, plate = _load(name), load_plate(PLATE)
    theirs = max(len(g) if (g := opencv_grid(img, plate, mode)) is not None else 0 for mode in OPENCV_MODES)
    assert theirs == plate.rows * plate.cols, f"{name}: OpenCV found {theirs} (the set's figures say 80)"
    det = detect_discs(img, plate)
    assert len(det) >= theirs, (name, len(det), theirs, det.rejected)


@pytest.mark.parametrize("name", PICTURES)
def test_centres_where_both_find_the_grid(name):
    img, plate = _load(name), load_plate(PLATE)
    ref = _best_opencv(img, plate)
    det = detect_discs(img, plate)
    assert len(det) >= 70, (name, det.rejected)
    assert det.index_basis == {"cols": "all seen", "rows": "all seen"}
    idx, d = nearest(det.uv, ref)
    # one detection per disc, none on the clip, the board or the shadow's edge
    assert len(set(idx)) == len(idx)
    assert np.median(d) < MEDIAN_PX and d.max() < SAME_DISC_PX, (name, np.median(d), d.max())
    assert same_indexing(det.rc, idx, plate.cols)


def test_plain_findcirclesgrid_misses_two_views_ours_does_not():
    """The defect the set has for OpenCV: two steep views its plain mode does not assemble."""
    plate = load_plate(PLATE)
    for name in ("image00000.jpg", "image00004.jpg"):
        img = _load(name)
        assert opencv_grid(img, plate) is None and opencv_grid(img, plate, "clustering") is not None
        assert len(detect_discs(img, plate)) == plate.rows * plate.cols


def test_intrinsics_command_agrees_with_opencv(capsys):
    """``selfview intrinsics --plate`` with its defaults against cv2.calibrateCamera on the same discs.
    Measured: f 455.52 +- 0.97 vs 455.04 +- 1.14 px, cx 319.12 +- 0.29 vs 318.49 +- 0.33 px, cy 238.68 +-
    0.63 vs 237.87 +- 0.79 px: 0.3, 1.4 and 0.8 combined sigmas. The sheet on its clipboard is bent: the
    default plate model takes the bow (13 sigmas from flat, 9 by the views left out in turn). (OpenCV on its
    own centres: f 454.34 +- 1.10, cx 318.35 +- 0.32, cy 238.69 +- 0.75 px.)"""
    files = [SET / n for n in PICTURES]
    code = main(["intrinsics", "--plate", str(PLATE), "--images", *map(str, files), "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    doc = json.loads(out)
    assert doc["views_used"] == len(files) and doc["width"] == 640 and doc["height"] == 480
    assert doc["plate_shape"]["model"] == "bow+dots", doc["plate_shape"]
    plate = load_plate(PLATE)
    imgs = [_load(n) for n in PICTURES]
    dets, _, _ = detect_views(imgs, plate, None)
    theirs, their_sd = opencv_intrinsics(dets, guess_camera(dets, 640, 480), (640, 480))
    ours = np.array([doc["f"], *doc["principal_point"]])
    our_sd = np.array([doc["sigma"][k] for k in ("f", "cx", "cy")])
    z = (ours - theirs) / np.hypot(our_sd, their_sd)
    assert np.all(np.abs(z) < 2.0), (ours, theirs, z)
