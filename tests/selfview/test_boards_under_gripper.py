"""A lab's board under the parked gripper (issue 29): a chessboard the fingers cut, found along its lattice and
placed on the plate, never at a silent wrong origin; a ChArUco board on the realistic simulated cell, whose
print lies all round the fingertips, calibrated off-line."""

import numpy as np
import pytest
import yaml

from selfview.estimation.offline import calibrate_offline
from selfview.files.cell import default_cell_path, parse_cell
from selfview.maths.geometry import transform_points
from selfview.measurement.plates import detect_plate
from selfview.mocks.render import render
from selfview.mocks.world import SimWorld

from tests.selfview.test_plates import board_picture, homography

CHESSBOARD = {"pattern": "chessboard", "squares": [9, 8], "square": 8.0}
CHARUCO = {"pattern": "charuco", "squares": [10, 10], "square": 8.0, "marker": 6.0, "dictionary": "DICT_4X4_50"}


def parked(plate: dict, seed: int, profile="ideal", camera="ideal"):
    raw = yaml.safe_load(default_cell_path().read_text())
    raw["plate"] = dict(plate)
    cell = parse_cell(raw)
    world = SimWorld(cell, seed=seed, imperfections=profile, camera=camera)
    world.set_jaw(cell.gripper.gap(cell.gripper.calibrate_in), cell.gripper.calibrate_in)
    world.park()
    return cell, world, render(world, seed=seed * 1000 + 1).image


def corner_errors_px(world, det) -> np.ndarray:
    """Each detected corner against the truth's image of the plate point its index names."""
    truth = world.camera.project(transform_points(np.array(world.truth()["C_H_W"]), det.p_W))
    return np.linalg.norm(det.uv - truth, axis=1)


def test_a_chessboard_the_fingers_cut_is_found_along_its_lattice_and_placed():
    """Ideal cell, seed 1: OpenCV's partial grid skips rows (main refused the picture: 'not a grid of alternating
    squares'). Grown along the lattice: 49 of the 56 corners, each where the truth puts the point its index
    names (measured: within 0.06 px), the board's far edge seen, the placement unique."""
    cell, world, img = parked(CHESSBOARD, 1)
    det = detect_plate(img, cell.plate)
    err = corner_errors_px(world, det)
    assert len(det.uv) >= 40 and err.max() < 0.5, (len(det.uv), err.max())
    assert det.origin_pinned and "high end seen" in det.index_basis.values(), (det.index_basis, det.ambiguous)


def test_a_whole_chessboard_keeps_no_corner_a_finger_hides():
    """Realistic cell, seed 3: OpenCV reports the whole board, one corner under a finger 11 px off (main kept it);
    a corner whose four squares do not alternate is dropped (measured: 50 kept, within 0.33 px)."""
    cell, world, img = parked(CHESSBOARD, 3, "realistic")
    det = detect_plate(img, cell.plate)
    err = corner_errors_px(world, det)
    assert 40 <= len(det.uv) < 56 and err.max() < 0.6, (len(det.uv), err.max())


def test_a_chessboard_seen_without_its_border_is_placed_but_said_ambiguous():
    """Only the board's middle in the picture (squares 80 px wide, no border): several placements fit the
    corners, so the origin is not pinned and each axis names why; the corners are still a lattice of the
    board's pitch (what the plane needs)."""
    cell = parse_cell({**yaml.safe_load(default_cell_path().read_text()), "plate": dict(CHESSBOARD)})
    img = board_picture(cell.plate, homography(turn_deg=12.0, scale=10.0, tilt=0.0), size=(480, 360))
    det = detect_plate(img, cell.plate)
    assert not det.origin_pinned and set(det.ambiguous) == {"x", "y"}, (det.index_basis, det.ambiguous)
    assert "places" in det.ambiguous["x"] and det.index_basis["x"] == "centred"
    d = np.diff(det.p_W[:, 0])
    assert np.allclose(d[d > 0], cell.plate.pitch)


def test_offline_calibration_over_a_chessboard_under_the_gripper():
    """Ideal cell, seed 0: a square's edge beside finger A's tip took two corners 4 and 10 px off in the corner
    search (main: C_H_G 0.275 mm off across the optical axis); they are dropped as off the fingers' shape
    (measured: 0.001 mm across, 0.11 mm along). The warning names a corner left out with its own reason, not
    the 'not found there' of a corner the search missed (measured: B-inner-back, 8.1 px off the shape)."""
    cell, world, img = parked(CHESSBOARD, 0)
    res = calibrate_offline(img, cell, camera=world.camera)
    e = np.abs(res.calibration.C_H_G[:3, 3] - np.array(world.truth()["C_H_G"])[:3, 3])
    assert np.hypot(e[0], e[1]) < 0.02 and e[2] < 0.2, e
    assert any("left out of the corner search: off the fingers' shape: " in m for m in res.warnings), res.warnings


def test_offline_calibration_over_a_charuco_plate_on_the_realistic_cell():
    """Realistic cell and camera, seed 0: the corner search's alignment locked 40-70 px off onto the print and
    the silhouette fit, right but not believed (residual 0.63 px over its 0.6: nominal boxes, real fingers),
    gave no corner (main: 'only 0 fingertip corner(s) found'). From the fit's pose the corners are searched
    again within a few px (measured: 5 corners, 0.05 mm across, 0.15 mm along with OpenCV 5.1, 0.31 along with
    OpenCV 4.10; the bar is the disc plate's on the same cell: 0.05-0.1 mm across and 0.1-0.4 mm along)."""
    cell, world, img = parked(CHARUCO, 0, "realistic", "realistic")
    res = calibrate_offline(img, cell, camera=world.camera)
    e = np.abs(res.calibration.C_H_G[:3, 3] - np.array(world.truth()["C_H_G"])[:3, 3])
    assert len(res.summary()["corners_found"]) >= 4
    assert np.hypot(e[0], e[1]) < 0.1 and e[2] < 0.4, e
