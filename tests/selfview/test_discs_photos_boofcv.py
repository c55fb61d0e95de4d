"""Disc detection and intrinsics on two more public sets of real photographs of one printed disc grid: BoofCV's.

An 8 x 10 grid of dark discs (15 mm at 25 mm pitch: a disc-to-pitch ratio of 0.6, a rectangular grid) on a
sheet clipped to a clipboard, by two cameras (CC BY 4.0, ``tests/data/boofcv-circles*``):

- ``stills``: six 640 x 480 colour JPEGs by a Sony DSC-HX5V indoors; the clipboard's metal clip beside the
  grid, a bent sheet, two steep views (00000, 00004) that plain ``cv2.findCirclesGrid`` does not assemble
  (its clustering mode does) and a hand's shadow over a quarter of the grid (00005).
- ``video``: ten frames of a 640 x 480 video by a wide-angle camera (OpenCV's k1 about -0.25) outdoors, the
  plate on a wooden bench among grass and gravel: a view with discs cut by the picture's edge (030, which
  OpenCV does not take), two that plain findCirclesGrid does not assemble (510, 555), and a small turned
  plate on end in the picture (435), whose foreshortened rows make a diagonal as short as a step (ours
  refused it as 'a lattice of 10 x 17' until the lattice's axes were taken from the lattice itself).

Measured (ours / findCirclesGrid / clustering discs; our centres against OpenCV's, median and max px):
stills 00000 80 / 0 / 80, 0.009, 0.04; 00001 80 / 80 / 80, 0.016, 0.19; 00002 80 / 80 / 80, 0.015, 0.27;
00003 80 / 80 / 80, 0.012, 0.06; 00004 80 / 0 / 80, 0.016, 0.10; 00005 80 / 80 / 80, 0.018, 0.22.
video 030 78 / 0 / 0; 075 80 / 80 / 80, 0.015, 0.16; 150 80 / 80 / 80, 0.017, 0.06; 210 80 / 80 / 80,
0.016, 0.15; 285 80 / 80 / 80, 0.022, 0.10; 360 80 / 80 / 80, 0.030, 1.53; 435 80 / 80 / 80, 0.032, 0.15;
510 80 / 0 / 80, 0.021, 0.13; 555 80 / 0 / 80, 0.017, 0.12; 615 80 / 80 / 80, 0.019, 0.07.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from selfview.estimation.intrinsics import detect_views, guess_camera
from selfview.files.cell import load_plate
from selfview.maths.camera import CameraModel
from selfview.measurement.discs import detect_discs
from selfview.procedures.cli import main
from tests.grid_photos import OPENCV_MODES, nearest, opencv_grid, opencv_intrinsics, same_indexing
from tests.photo_variants import plate_tilted, turned

DATA = Path(__file__).resolve().parents[1] / "data"
SETS = {
    "stills": (DATA / "boofcv-circles", [f"image0000{i}.jpg" for i in range(6)]),
    "video": (DATA / "boofcv-circles-video", [f"frame{i:03d}.jpg" for i in (30, 75, 150, 210, 285, 360, 435, 510, 555, 615)]),
}
#: Our centres against OpenCV's [px]: the median (measured 0.009-0.032 per picture; 0.03-0.07 before the ink-share
#: weight); any one of ours within this of one of OpenCV's is on that disc (neighbours lie 9-70 px apart here); the
#: largest measured, 1.53 px, is a disc beside the clip of a blurred frame (the hand's shadow's worst: 0.22).
MEDIAN_PX, SAME_DISC_PX = 0.1, 1.8

PICTURES = [pytest.param(s, n, id=f"{s}-{n}") for s in SETS for n in SETS[s][1]]
#: where both OpenCV (one mode or the other) and ours take the picture
BOTH = [pytest.param(s, n, id=f"{s}-{n}") for s in SETS for n in SETS[s][1]
        if (s, n) != ("video", "frame030.jpg")]


def _plate(which):
    return load_plate(SETS[which][0] / "plate.yaml")


def _load(which, name):
    img = cv2.imread(str(SETS[which][0] / name), cv2.IMREAD_GRAYSCALE)
    assert img is not None, f"missing test picture {which}/{name}"
    return img


@pytest.mark.parametrize("which, name", PICTURES)
def test_as_many_discs_as_the_better_of_opencvs_modes(which, name):
    img, plate = _load(which, name), _plate(which)
    theirs = max(len(g) if (g := opencv_grid(img, plate, mode)) is not None else 0 for mode in OPENCV_MODES)
    det = detect_discs(img, plate)
    assert len(det) >= theirs, (name, len(det), theirs, det.rejected)


@pytest.mark.parametrize("which, name", BOTH)
def test_centres_where_both_find_the_grid(which, name):
    img, plate = _load(which, name), _plate(which)
    grids = [g for g in (opencv_grid(img, plate, mode) for mode in OPENCV_MODES) if g is not None]
    assert grids, f"{name}: OpenCV found the grid in neither mode (the set's figures say it does)"
    det = detect_discs(img, plate)
    assert len(det) >= 70, (name, det.rejected)
    assert det.index_basis == {"cols": "all seen", "rows": "all seen"}
    idx, d = nearest(det.uv, grids[0])
    # one detection per disc, none on the clip, the board, the bench or the shadow's edge
    assert len(set(idx)) == len(idx)
    assert np.median(d) < MEDIAN_PX and d.max() < SAME_DISC_PX, (name, np.median(d), d.max())
    assert same_indexing(det.rc, idx, plate.cols)


def test_a_hands_shadow_over_the_grid_keeps_every_disc_where_opencv_puts_it():
    """Stills 00005: a hand's shadow over a quarter of the grid, its edge across discs, which the contrast
    threshold merges with the shadow (before: 71 of 80, 9 'not elliptical' or 'crowded', one centre 1.26 px off).
    Every disc now, each within issue 31's 0.3 px of OpenCV's (measured: 0.22 at most, median 0.018; weighted by the
    raw contrast 1 - I / I_paper instead of the share of the disc's ink, 1.20 px)."""
    img, plate = _load("stills", "image00005.jpg"), _plate("stills")
    det = detect_discs(img, plate)
    assert len(det) == plate.rows * plate.cols, det.rejected
    _, d = nearest(det.uv, opencv_grid(img, plate))
    assert d.max() < 0.3, np.round(d, 2)


@pytest.mark.parametrize("which, names", [("stills", ("image00000.jpg", "image00004.jpg")),
                                          ("video", ("frame510.jpg", "frame555.jpg"))])
def test_views_plain_findcirclesgrid_does_not_assemble(which, names):
    """The defect the sets have for OpenCV: views its plain mode does not assemble (its clustering mode does)."""
    plate = _plate(which)
    for name in names:
        img = _load(which, name)
        assert opencv_grid(img, plate) is None and opencv_grid(img, plate, "clustering") is not None
        assert len(detect_discs(img, plate)) == plate.rows * plate.cols


def test_discs_cut_by_the_picture_edge():
    """Video frame 030: the grid's left column runs off the picture, two of its discs cut by the edge.
    OpenCV takes nothing; ours takes the 78 whole discs, indexed on the plate's 8 x 10, and the two it leaves
    are the cut ones: the plate-to-picture homography of the 78 puts them within a disc of the edge."""
    img, plate = _load("video", "frame030.jpg"), _plate("video")
    assert all(opencv_grid(img, plate, mode) is None for mode in OPENCV_MODES)
    det = detect_discs(img, plate)
    assert len(det) == plate.rows * plate.cols - 2, det.rejected
    assert np.ptp(det.rc, axis=0).tolist() == [plate.rows - 1, plate.cols - 1]
    H, _ = cv2.findHomography(det.p_W[:, :2], det.uv)
    seen = {tuple(rc) for rc in det.rc.tolist()}
    lo = det.rc.min(axis=0)
    missing = [(r, c) for r in range(lo[0], lo[0] + plate.rows) for c in range(lo[1], lo[1] + plate.cols)
               if (r, c) not in seen]
    assert len(missing) == 2
    # the W points of the missing lattice places, from the found ones' (row, col) -> W map (affine)
    A = np.column_stack([det.rc, np.ones(len(det))])
    coef, *_ = np.linalg.lstsq(A, det.p_W[:, :2], rcond=None)
    p = cv2.perspectiveTransform((np.column_stack([missing, np.ones(2)]) @ coef).reshape(-1, 1, 2), H).reshape(-1, 2)
    r = np.sqrt(np.median(det.area_px) / np.pi)
    h, w = img.shape
    edge = np.minimum.reduce([p[:, 0], p[:, 1], w - 1 - p[:, 0], h - 1 - p[:, 1]])
    assert np.all(edge < 1.5 * r), (p, r)


def _run(which, capsys, extra=()):
    """The JSON of ``selfview intrinsics --plate --skip-unusable`` (with ``extra``) on a set, and its pictures."""
    folder, names = SETS[which]
    files = [str(folder / n) for n in names]
    code = main(["intrinsics", "--plate", str(folder / "plate.yaml"), "--images", *files, "--skip-unusable",
                 "--json", *extra])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out), names


def _z(doc, which, names):
    """cv2.calibrateCamera on our discs of the set beside the command's ``doc``: the z of (f, cx, cy) in
    combined sigmas, ours and theirs."""
    plate = _plate(which)
    imgs = [_load(which, n) for n in names]
    dets, _, _ = detect_views(imgs, plate, None, skip_unusable=True)
    h, w = imgs[0].shape
    theirs, their_sd = opencv_intrinsics(dets, guess_camera(dets, w, h), (w, h))
    ours = np.array([doc["f"], *doc["principal_point"]])
    our_sd = np.array([doc["sigma"][k] for k in ("f", "cx", "cy")])
    return (ours - theirs) / np.hypot(our_sd, their_sd), ours, theirs


def test_stills_intrinsics_command_agrees_with_opencv(capsys):
    """``selfview intrinsics --plate`` with its defaults against cv2.calibrateCamera on the same discs. The
    sheet on its clipboard is bent (its bow's chi-square against 0 is 234, 3 dof) and a bow predicts
    each of the 6 views left out in turn better than the flat plate, but 6 of 6 is p = 0.016 by the sign
    test: 6 views cannot confirm a bent plate at the 1 % level, so the plate is taken flat and the bow's
    skew held at 0. Measured: f, cx, cy 0.25, -0.01, 0.03 combined sigmas from OpenCV (the bent plate,
    the default before: 0.3, 1.4, 0.8). (OpenCV on its own centres: f 454.34 +- 1.10, cx 318.35 +- 0.32,
    cy 238.69 +- 0.75 px.)"""
    doc, names = _run("stills", capsys)
    assert doc["views_used"] == len(names) and doc["width"] == 640 and doc["height"] == 480
    assert doc["plate_shape"]["model"] == "flat" and "6 of 6 views better" in doc["plate_shape"]["why"], doc["plate_shape"]
    assert doc["skew"] == 0.0
    z, ours, theirs = _z(doc, "stills", names)
    assert np.all(np.abs(z) < 2.0), (ours, theirs, z)


def test_video_intrinsics_flat_plate_agrees_with_opencv(capsys):
    """The video frames with the plate taken flat: within 2 combined sigmas of cv2.calibrateCamera (k1
    -0.247), every frame used (frame 435, the plate on end, is indexed since the lattice's axes are its
    own). Measured: f 704.10 vs 705.87 px, cx 290.17 vs 291.13 px, cy 239.72 vs 238.41 px: -0.85, -0.63,
    0.68 combined sigmas."""
    doc, names = _run("video", capsys, ("--plate-model", "flat"))
    assert doc["views_used"] == len(names) and not doc.get("views_skipped")
    z, ours, theirs = _z(doc, "video", names)
    assert np.all(np.abs(z) < 2.0), (ours, theirs, z)


def test_video_intrinsics_defaults_agree_with_opencv(capsys):
    """With its defaults: the views measure a bow, but it does not predict the frames left out in turn better
    than the flat plate beyond chance (the sign test), so the plate is flat and the camera agrees with
    cv2.calibrateCamera as the flat plate does (before, a bow was taken and f, cx, cy lay -2.3, -1.8, 2.7
    combined sigmas off)."""
    doc, names = _run("video", capsys)
    assert doc["plate_shape"]["model"] == "flat", doc["plate_shape"]
    z, ours, theirs = _z(doc, "video", names)
    assert np.all(np.abs(z) < 2.0), (doc["plate_shape"]["model"], ours, theirs, z)


@pytest.mark.parametrize("name, deg", [("frame510.jpg", 15), ("frame555.jpg", 45), ("frame435.jpg", 60),
                                       ("frame150.jpg", 90)])
def test_a_foreshortened_plate_turned_in_the_picture(name, deg):
    """Video frames turned in the picture: where the plate is foreshortened a diagonal of the lattice can be
    as short as a step (frame 510 turned 15 deg, 555 turned 15-60 deg were refused as 'a lattice of 17 x 10'
    before the lattice's axes were its own); every disc is found and indexed as in the frame itself, up to a
    symmetry of the plate and with no shift."""
    img, plate = _load("video", name), _plate("video")
    straight = detect_discs(img, plate)
    pic = turned(img, deg)
    det = detect_discs(pic, plate)
    assert len(det) == len(straight) == plate.rows * plate.cols and det.origin_pinned
    h, w = img.shape
    M = cv2.getRotationMatrix2D((w / 2, h / 2), deg, 1.0)
    M[:, 2] += ((pic.shape[1] - w) / 2, (pic.shape[0] - h) / 2)
    k, d = nearest(det.uv, straight.uv @ M[:, :2].T + M[:, 2])
    assert d.max() < 0.5 and len(set(k)) == len(k)
    assert _same_as(det.rc, straight.rc[k], plate)


@pytest.mark.parametrize("name", ["frame285.jpg", "frame435.jpg"])
def test_a_defocused_frame_keeps_the_discs_by_the_sheets_edge(name):
    """Video frames blurred by a Gaussian of sigma 2 px (discs 7-9 px across, the outer rows a few pixels from the
    sheet's edge, a dark bench beyond): every disc, as OpenCV finds, each where it is in the frame (measured: at
    most 0.12 and 0.15 px, median 0.04-0.05). Before, 77 and 71 of 80: the paper's level, smoothed across the
    sheet's edge, was taken darker there, and the outer discs' contrast with it, under the threshold."""
    img, plate = _load("video", name), _plate("video")
    det = detect_discs(cv2.GaussianBlur(img, (0, 0), 2.0), plate)
    assert len(det) == plate.rows * plate.cols, det.rejected
    _, moved = nearest(det.uv, detect_discs(img, plate).uv)
    assert moved.max() < 0.3 and np.median(moved) < 0.1, np.round(np.sort(moved)[-5:], 3)


@pytest.mark.parametrize("name, least", [("frame210.jpg", 80), ("frame285.jpg", 75), ("frame510.jpg", 79)])
def test_a_badly_defocused_frame_is_measured_with_its_spread_ink(name, least):
    """Video frames blurred by a Gaussian of sigma 3.5 px (discs 7-9 px across, 14-16 px apart: each disc's ink
    spread until its contrast lies about the 0.3 darkness threshold; frame 285: 0.22-0.33), measured again with half
    the paper's level taken off (``DEFOCUS_PEDESTAL``): 80, 75 and 79 discs (OpenCV 80 each), each indexed as in the
    frame and within 0.6 px of where it is there (measured: at most 0.52, 0.32, 0.52 px). Before, 36, none and 48:
    the glare pedestal, from the picture's darkest percentile (the bench beside the sheet), was none."""
    img, plate = _load("video", name), _plate("video")
    det = detect_discs(cv2.GaussianBlur(img, (0, 0), 3.5), plate)
    assert len(det) >= least and det.pedestal > 0 and det.origin_pinned, (len(det), det.rejected)
    sharp = detect_discs(img, plate)
    k, moved = nearest(det.uv, sharp.uv)
    assert np.array_equal(det.rc, sharp.rc[k]) and moved.max() < 0.6, np.round(np.sort(moved)[-5:], 3)


@pytest.mark.parametrize("name", ["frame285.jpg", "frame360.jpg"])
def test_an_over_exposed_frame_keeps_its_discs(name):
    """Video frames at 1.8 times the light, clipped (the paper white, the discs grey and faint): every disc, each
    indexed as in the frame and within 0.3 px of where it is there (measured: at most 0.28 and 0.21 px), measured
    again with half the paper's level taken off (``DEFOCUS_PEDESTAL``). Before, 74 and 69: the glare pedestal, from
    the picture's darkest percentile (the bench beside the sheet), was none."""
    img, plate = _load("video", name), _plate("video")
    det = detect_discs(np.clip(img * 1.8, 0, 255).astype(np.uint8), plate)
    assert len(det) == plate.rows * plate.cols and det.pedestal > 0, (len(det), det.rejected)
    sharp = detect_discs(img, plate)
    k, moved = nearest(det.uv, sharp.uv)
    assert np.array_equal(det.rc, sharp.rc[k]) and moved.max() < 0.3, np.round(np.sort(moved)[-5:], 3)


@pytest.mark.parametrize("name", ["image00002.jpg", "image00005.jpg"])
def test_sensor_noise_over_a_real_photograph_keeps_its_discs(name):
    """White sensor noise of sigma 10 grey levels over stills whose paper lies at 100-160 (6-10 % of it; the hand's
    shadow over 00005): every disc, each where it is in the photograph (measured: at most 0.12 and 0.20 px, median
    0.03). Before, 75 and 74 discs: rings noisier than the fixed 0.12 tolerance were 'occluded'; and noise specks
    in the hand's shadow, joined to a disc or cutting its ring, left it out (with the tolerance alone widened to
    the noise, they moved it by 0.9 px)."""
    img, plate = _load("stills", name), _plate("stills")
    noisy = np.clip(img + np.random.default_rng(1).normal(0.0, 10.0, img.shape), 0, 255).astype(np.uint8)
    det = detect_discs(noisy, plate)
    assert len(det) == plate.rows * plate.cols, det.rejected
    _, moved = nearest(det.uv, detect_discs(img, plate).uv)
    assert moved.max() < 0.3 and np.median(moved) < 0.05, np.round(np.sort(moved)[-5:], 3)


@pytest.mark.parametrize("name, axis, deg", [("image00001.jpg", "y", 60), ("image00002.jpg", "y", 60),
                                             ("image00003.jpg", "x", 60)])
def test_a_plate_seen_60_deg_off_square_on(name, axis, deg):
    """The stills' plate as a camera 60 deg off square-on would see it (the photo warped through the plate):
    the discs found are indexed as in the photo itself, up to a symmetry of the plate and with no shift,
    with the origin pinned. Before, the far columns' steps were carried over from the walk's start (a third
    too long there): 00001 kept 74 discs with two one row off, 00002 67 with some off, both axes 'all
    seen', no warning. (00002 keeps 73 of 80: the sheet's shaded corner is not found in the warped picture.)"""
    img, plate = _load("stills", name), _plate("stills")
    straight = detect_discs(img, plate)
    pic, H = plate_tilted(img, straight.p_W, straight.uv, 455.0, axis, deg)
    h, w = pic.shape
    cam = CameraModel(f=455.0, cx=(w - 1) / 2, cy=(h - 1) / 2, width=w, height=h)
    det = detect_discs(pic, plate, camera=cam)
    assert len(det) >= (73 if name == "image00002.jpg" else plate.rows * plate.cols), det.rejected
    assert det.origin_pinned
    k, d = nearest(det.uv, cv2.perspectiveTransform(straight.uv.reshape(-1, 1, 2), H).reshape(-1, 2))
    assert d.max() < 1.0 and len(set(k)) == len(k)
    assert _same_as(det.rc, straight.rc[k], plate)


def _same_as(rc, ref, plate) -> bool:
    """Whether indices ``rc`` are ``ref`` up to a symmetry of the (rectangular) plate, with no shift."""
    r, c = ref[:, 0], ref[:, 1]
    R, C = plate.rows - 1, plate.cols - 1
    return any(np.array_equal(rc, np.column_stack(x)) for x in ((r, c), (R - r, c), (r, C - c), (R - r, C - c)))
