"""The plate seam: chessboard and ChArUco plates through ``detect_plate`` on real photographs and in the
simulated cell (drawn by the renderer, the fingers over the board), against OpenCV's calibration, and the
bad inputs."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from selfview.maths.camera import CameraModel
from selfview.files.cell import default_cell_path, load_plate, parse_cell, parse_plate
from selfview.errors import ConfigError, ImageError
from selfview.maths.geometry import transform_points
from selfview.mocks.render import render
from selfview.mocks.world import SimWorld
from selfview.estimation.offline import calibrate_offline
from selfview.measurement.plates import (board_edges_W, board_ink, charuco_biased, detect_plate, make_charuco_board,
                                        plate_image_bias)
from selfview.procedures.cli import main
from selfview.procedures.intrinsics import measure_intrinsics

PHOTOS = Path(__file__).resolve().parents[1] / "data" / "charuco-basler"
CHESS_PHOTOS = Path(__file__).resolve().parents[1] / "data" / "opencv-chessboard"
CHARUCO = {"pattern": "charuco", "squares": [10, 10], "square": 8.0, "marker": 6.0, "dictionary": "DICT_4X4_50"}
CHESSBOARD = {"pattern": "chessboard", "squares": [9, 8], "square": 9.0}


def cell_with(plate: dict):
    raw = yaml.safe_load(default_cell_path().read_text())
    raw["plate"] = dict(plate)
    return parse_cell(raw)


def board_picture(plate, H_img_W, size=(640, 480), px_per_mm=8.0):
    """A picture of the board (light paper, dark print) through the homography ``H_img_W`` from W (x, y) [mm]
    to pixels: the print sampled on a fine grid (``board_ink``), warped and averaged down."""
    w, h = size
    up = 4
    ys, xs = np.mgrid[0 : h * up, 0 : w * up]
    uv = np.column_stack([(xs.ravel() + 0.5) / up - 0.5, (ys.ravel() + 0.5) / up - 0.5, np.ones(xs.size)])
    p = uv @ np.linalg.inv(H_img_W).T
    ink = board_ink(plate, p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]).reshape(h * up, w * up)
    img = np.where(ink, 30.0, 220.0)
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA).astype(np.uint8)


def homography(turn_deg=20.0, scale=9.0, tilt=2e-4):
    a = np.radians(turn_deg)
    return np.array([[scale * np.cos(a), -scale * np.sin(a), 320.0],
                     [scale * np.sin(a), scale * np.cos(a), 240.0],
                     [tilt, tilt / 2, 1.0]])


# --- real photographs --------------------------------------------------------------------------------
def _cv2_k1(obj, img, size, K0):
    flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3)
    out = cv2.calibrateCameraExtended([o.astype(np.float32) for o in obj], [u.astype(np.float32).reshape(-1, 1, 2) for u in img],
                                      size, K0, np.zeros(5), flags=flags)
    K, sd = out[1], np.ravel(out[5])
    return {"f": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "aspect": K[1, 1] / K[0, 0]}, \
        {"f": sd[1], "cx": sd[2], "cy": sd[3], "aspect": K[1, 1] / K[0, 0] * np.hypot(sd[0] / K[0, 0], sd[1] / K[1, 1])}


@pytest.fixture(scope="module")
def charuco_photos():
    files = sorted(PHOTOS.glob("basler-*.jpg"))
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    plate = load_plate(PHOTOS / "plate.yaml")
    return plate, images, [f.name for f in files]


def test_charuco_photographs_are_indexed_as_opencv_numbers_them(charuco_photos):
    plate, images, _ = charuco_photos
    from selfview.measurement.plates import charuco_board

    for img in images:
        det = detect_plate(img, plate)
        corners, ids, _, _ = cv2.aruco.CharucoDetector(charuco_board(plate)).detectBoard(img)
        ref = dict(zip(np.ravel(ids), corners.reshape(-1, 2)))
        assert len(det) == len(ref) == 28
        for (r, c), uv, p in zip(det.rc, det.uv, det.p_W):
            k = r * plate.cols + c
            assert np.allclose(uv, ref[k])
            obj = charuco_board(plate).getChessboardCorners()[k]
            assert np.allclose(p[:2], obj[:2] - np.array(plate.squares) * plate.pitch / 2)


def test_charuco_photographs_intrinsics_agree_with_opencv(charuco_photos):
    """Ours (Tsai's kappa) against cv2.calibrateCamera (one radial term k1) on OpenCV's ChArUco corners of
    the same photographs: the difference, less the shift the two radial models alone make on the same
    corners, within 3 combined sigmas; at least as many views used. Both on the plate as specified (ours
    with ``plate_model='flat'``, as cv2 takes it). Measured (12 views, 648 x 486): f 1903.3 +- 2.6 vs
    1903.2 +- 2.6 px, centre (309.5, 227.6) vs (310.0, 227.6) +- (4.0, 2.6) px, all within 0.1 combined
    sigma; the radial models' own shift is -0.12 px in f, +0.07 px in cx."""
    plate, images, names = charuco_photos
    out, res = _agreement(plate, images, names)
    assert res.views_used == len(images) == 12
    for k, (ours, theirs, shift, z) in out.items():
        assert abs(z) < 3, (k, ours, theirs, shift, z)
    assert res.rms_px < 0.15  # measured 0.107 px (flat plate; 0.045 px with the default bow+dots model)


def _agreement(plate, images, names):
    """Ours (flat plate) and cv2.calibrateCamera (k1) on the same corners: per parameter (ours, cv2, the
    radial models' own shift, (cv2 - ours - shift) / combined sigma), and our result."""
    res = measure_intrinsics(images, plate, None, names, plate_model="flat")
    dets = [detect_plate(img, plate) for img in images]
    size = (images[0].shape[1], images[0].shape[0])
    c = res.camera
    K0 = np.array([[c.f, 0, c.cx], [0, c.f, c.cy], [0, 0, 1.0]])
    theirs, sd = _cv2_k1([d.p_W for d in dets], [d.uv for d in dets], size, K0)
    ideal = [c.project(transform_points(v.C_H_W, d.p_W)) for d, v in zip(dets, res.views)]
    on_ours, _ = _cv2_k1([d.p_W for d in dets], ideal, size, K0)
    out = {}
    for k in ("f", "cx", "cy", "aspect"):
        shift = on_ours[k] - getattr(c, k)
        out[k] = (getattr(c, k), theirs[k], shift, (theirs[k] - getattr(c, k) - shift) / np.hypot(res.sigma[k], sd[k]))
    return out, res


def test_chessboard_photographs_intrinsics_agree_with_opencv():
    """OpenCV's own sample chessboard photographs (13 views, 640 x 480, strong barrel distortion): ours
    against cv2.calibrateCamera (k1) on the same corners, within 3 combined sigmas beyond the radial models'
    own shift. Measured: f 532.65 +- 0.55 vs 530.15 +- 0.62 px with a model shift of -2.61 px, cx 341.79 vs
    343.74 px with +2.20 px, cy 233.14 vs 233.18 px with +0.26 px; all within 0.3 combined sigma."""
    plate = load_plate(CHESS_PHOTOS / "plate.yaml")
    files = sorted(CHESS_PHOTOS.glob("left*.jpg"))
    images = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
    out, res = _agreement(plate, images, [f.name for f in files])
    assert res.views_used == len(files) == 13
    for k, (ours, theirs, shift, z) in out.items():
        assert abs(z) < 3, (k, ours, theirs, shift, z)
    assert abs(out["f"][2]) > 1.0  # the radial models do differ here: the shift is part of the comparison


def test_intrinsics_command_with_a_plate_file(charuco_photos, capsys, tmp_path):
    files = sorted(str(f) for f in PHOTOS.glob("basler-*.jpg"))
    code = main(["intrinsics", "--plate", str(PHOTOS / "plate.yaml"), "--images", *files, "--plate-model", "flat", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert out["views_used"] == 12 and out["width"] == 648 and out["height"] == 486
    assert {"f", "kappa", "principal_point", "aspect", "sigma", "rms_px", "stop_rule", "cross_check"} <= set(out)
    # a plate file without its plate section
    bad = tmp_path / "plate.yaml"
    bad.write_text("camera: {width: 10}\n")
    assert main(["intrinsics", "--plate", str(bad), "--images", *files]) == 3
    assert "'plate:' section" in capsys.readouterr().err


# --- the simulated cell ------------------------------------------------------------------------------
@pytest.mark.skipif(charuco_biased(),
                    reason="OpenCV before 4.12 places ChArUco corners about 0.5 px off (warned at run time)")
def test_offline_C_H_G_with_a_charuco_plate_under_the_gripper():
    """The ideal cell with a ChArUco plate: the fingers hide part of it, the ids index the rest; C_H_G as
    accurate as with discs (0.02 mm across, 0.08 mm along the optical axis)."""
    cell = cell_with(CHARUCO)
    for seed in range(3):
        w = SimWorld(cell, seed=seed)
        w.park()
        r = render(w, seed=seed)
        res = calibrate_offline(r.image, cell)
        det = res.discs
        assert 20 <= len(det) < 81  # a partial view
        truth = r.disc_uv[det.rc[:, 0] * cell.plate.cols + det.rc[:, 1]]
        assert np.median(np.linalg.norm(det.uv - truth, axis=1)) < 0.1
        d = res.calibration.C_H_G[:3, 3] - w.C_H_G[:3, 3]
        assert np.hypot(d[0], d[1]) < 0.02 and abs(d[2]) < 0.08, (seed, d)


def test_a_corner_has_no_perspective_bias():
    plate = parse_plate(CHARUCO)
    cam = CameraModel(f=900.0, kappa=0.0, cx=320, cy=240, aspect=1.0, width=640, height=480)
    H = np.eye(4)
    H[:3, :3] = cv2.Rodrigues(np.array([0.4, 0.1, 0.0]))[0]
    H[2, 3] = 150.0
    assert np.all(plate_image_bias(plate, cam, H, plate.disc_centres_W()) == 0)
    discs = cell_with({"rows": 8, "cols": 8, "pitch": 9.0, "disc_diameter": 4.5, "size": [110, 110]}).plate
    assert np.abs(plate_image_bias(discs, cam, H, discs.disc_centres_W())).max() > 0.01


@pytest.mark.parametrize("turn", [20.0, 200.0, -70.0])
def test_chessboard_is_indexed_the_same_whichever_way_it_is_turned(turn):
    plate = parse_plate({"pattern": "chessboard", "squares": [7, 6], "square": 8.0})
    H = homography(turn, scale=7.0)
    det = detect_plate(board_picture(plate, H), plate)
    assert len(det) == 30 and det.index_basis["x"] == "board"
    p = np.column_stack([det.p_W[:, :2], np.ones(len(det))]) @ H.T
    assert np.abs(p[:, :2] / p[:, 2:] - det.uv).max() < 0.3


# --- bad input ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("plate, msg", [
    ({"pattern": "dots"}, "expected one of discs, chessboard, charuco"),
    ({**CHARUCO, "dictionary": "DICT_9X9_50"}, "not an OpenCV predefined dictionary"),
    ({**CHARUCO, "squares": [20, 20]}, "holds 50 markers"),
    ({**CHARUCO, "marker": 9.0}, "expected less than the square"),
    ({**CHESSBOARD, "squares": [9]}, "plate.squares"),
    ({**CHESSBOARD, "size": [20, 20]}, "smaller than the board"),
    ({**CHESSBOARD, "rows": 8}, "rows"),
])
def test_bad_plate_sections_are_refused(plate, msg):
    with pytest.raises(ConfigError, match=msg):
        parse_plate(plate)


def test_a_symmetric_chessboard_is_refused():
    plate = parse_plate({"pattern": "chessboard", "squares": [8, 6], "square": 8.0})
    with pytest.raises(ImageError, match="orientation in the picture is ambiguous"):
        detect_plate(board_picture(plate, homography(10.0, scale=7.0)), plate)


def test_charuco_board_of_another_layout_or_dictionary_is_named():
    plate = parse_plate(CHARUCO)
    img = board_picture(plate, homography(10.0, scale=4.0))
    assert len(detect_plate(img, plate)) == 81
    other = parse_plate({**CHARUCO, "dictionary": "DICT_5X5_50"})
    with pytest.raises(ImageError, match="no DICT_5X5_50 marker found"):
        detect_plate(img, other)
    big = parse_plate({**CHARUCO, "squares": [6, 6]})  # ids 0..17 of the same dictionary: the picture's go to 49
    far = board_picture(parse_plate({**CHARUCO, "squares": [10, 10]}), homography(10.0, scale=4.0))
    cut = far.copy()
    cut[:, :330] = 220  # only the markers with high ids remain
    with pytest.raises(ImageError, match="are not this board's|ChArUco corner"):
        detect_plate(cut, big)


def test_too_few_corners_are_refused():
    plate = parse_plate(CHARUCO)
    img = board_picture(plate, homography(10.0, scale=4.0))
    img[:, 260:] = 220
    img[:200, :] = 220
    with pytest.raises(ImageError, match=r"only \d+ ChArUco corner\(s\) seen"):
        detect_plate(img, plate, min_points=12)
    with pytest.raises(ValueError, match="min_points: expected a whole number"):
        detect_plate(img, plate, min_points=0)


def test_a_board_drawing_of_a_disc_plate_or_a_board_of_an_unknown_dictionary_is_refused():
    discs = cell_with({"rows": 8, "cols": 8, "pitch": 9.0, "disc_diameter": 4.5, "size": [110, 110]}).plate
    with pytest.raises(ConfigError, match="'discs' is not a board"):
        board_ink(discs, np.zeros(3), np.zeros(3))
    with pytest.raises(ConfigError, match="'discs' is not a board"):
        board_edges_W(discs)
    with pytest.raises(ConfigError, match="plate.dictionary: 'DICT_NONE' is not an OpenCV predefined dictionary"):
        make_charuco_board((5, 5), 10.0, 7.0, "DICT_NONE")
