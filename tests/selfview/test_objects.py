"""Objects to grasp: the object file, the target's detection and the object's pose from a picture."""

import cv2
import numpy as np
import pytest

from selfview.errors import CalibrationError, ConfigError, ImageError
from selfview.maths.geometry import H_from_rotvec, rotation_angle, transform_points
from selfview.measurement.plates import charuco_biased
from selfview.measurement.objects import TargetDetection, TargetSpec, detect_target, load_object, object_pose, parse_object, target_board


def _block(**changes):
    o = {"name": "b", "block": [54.0, 44.0, 30.0],
         "target": {"pattern": "charuco", "squares": [4, 4], "square": 10.0, "marker": 7.0, "dictionary": "DICT_4X4_50"},
         "grasp": {"xyz": [0, 0, 25], "rpy_deg": [0, 0, 180]}, "approach_mm": 30}
    o.update(changes)
    return {"object": o}


def test_the_shipped_block_reads_and_its_grasp_frame_lies_inside_the_block():
    obj = load_object()
    assert obj.target.size == (40.0, 40.0)
    g = obj.O_H_Gstar[:3, 3]
    assert 0 < g[2] < obj.block[2]  # below the top face (z into the block), above the table
    assert obj.O_H_Gpre[2, 3] == pytest.approx(g[2] - obj.approach_mm)
    assert obj.jaw_clearance_mm(56.0) == pytest.approx(1.0)


@pytest.mark.parametrize("changes, says", [
    ({"block": [54, 44]}, "object.block"),
    ({"target": {"pattern": "charuco", "squares": [4, 4], "square": 10.0, "marker": 12.0}}, "smaller than"),
    ({"target": {"pattern": "charuco", "squares": [8, 8], "square": 10.0, "marker": 7.0}}, "does not fit"),
    ({"target": {"pattern": "discs", "squares": [4, 4], "square": 10.0, "marker": 7.0}}, "only 'charuco'"),
    ({"target": {"squares": [4, 4], "square": 10.0, "marker": 7.0, "dictionary": "DICT_9X9"}}, "dictionary"),
    ({"grasp": {"xyz": [0, 0]}}, "grasp.xyz"),
    ({"colour": "red"}, "unknown key"),
    ({"approach_mm": -3}, "approach_mm"),
])
def test_a_bad_object_file_is_refused_naming_what_is_wrong(changes, says):
    with pytest.raises(ConfigError, match=says):
        parse_object(_block(**changes), "obj.yaml")


def test_a_missing_object_file_is_a_file_error(tmp_path):
    with pytest.raises(ConfigError, match=r"nope\.yaml: cannot read the object file \(no such file\)"):
        load_object(tmp_path / "nope.yaml")


def _board_picture(target, size=(300, 300), at=(100, 100)):
    img = np.full((576, 768), 200, np.uint8)
    board = target_board(target).generateImage(size, marginSize=0)
    img[at[1]:at[1] + size[1], at[0]:at[0] + size[0]] = board // 2 + 40
    return img


def test_a_target_seen_twice_is_refused():
    t = load_object().target
    img = _board_picture(t, at=(20, 100))
    img[100:400, 420:720] = _board_picture(t, at=(20, 100))[100:400, 20:320]
    with pytest.raises(CalibrationError, match="seen twice"):
        detect_target(img, t)


def test_a_picture_without_the_target_is_refused():
    """A picture of something else (a textured table) is not seen; a blank one is a blank picture (an ImageError)."""
    table = np.random.default_rng(3).integers(60, 200, (576, 768)).astype(np.uint8)
    with pytest.raises(CalibrationError, match="target not seen"):
        detect_target(cv2.GaussianBlur(table, (0, 0), 2.0), load_object().target)
    with pytest.raises(ImageError, match="blank target picture"):
        detect_target(np.full((576, 768), 120, np.uint8), load_object().target)


@pytest.mark.skipif(charuco_biased(),
                    reason="OpenCV before 4.12 places ChArUco corners about 0.5 px off (warned at run time)")
def test_the_object_pose_through_the_camera_model_matches_the_truth(cell):
    from selfview.mocks.objects import place_object
    from selfview.mocks.render import render
    from selfview.mocks.world import SimWorld

    world = SimWorld(cell, seed=2)
    obj = load_object()
    o = place_object(world, obj, seed=5)
    world.set_tcp(o.base_H_O @ obj.O_H_Gpre @ H_from_rotvec([0.05, -0.04, 0.1], [5.0, -60.0, -90.0]))
    assert world.camera.kappa != 0  # kappa is in the model the corners are undistorted with
    pose = object_pose(render(world, seed=3).image, world.camera, obj)
    C_H_O = world.C_H_O
    assert np.linalg.norm(pose.C_H_O[:3, 3] - C_H_O[:3, 3]) < 0.1
    assert np.degrees(rotation_angle(pose.C_H_O[:3, :3].T @ C_H_O[:3, :3])) < 0.2
    assert pose.corners >= 6 and pose.rms_px < 0.3 and pose.rms_px_other > 3 * pose.rms_px
    assert np.all(pose.sigma_mm > 0) and np.all(pose.sigma_mm < 0.5) and np.all(pose.sigma_deg < 0.5)
    # without kappa the same corners give another pose: the model's distortion is applied
    flat = object_pose(None, world.camera.with_(kappa=0.0), obj, detection=pose.detection)
    assert np.linalg.norm(flat.C_H_O[:3, 3] - pose.C_H_O[:3, 3]) > 0.01


def _target_seen(obj, cam, C_H_O):
    """(p_O (N, 3), exact pixels (N, 2), ids (N,)) of every corner of the object's target at ``C_H_O``."""
    p_O = target_board(obj.target).getChessboardCorners().astype(float) - np.array([20.0, 20.0, 0.0])
    return p_O, cam.project(transform_points(C_H_O, p_O)), np.arange(len(p_O))


def test_a_far_frontal_target_is_ambiguous_and_refused(cell):
    obj = load_object()
    cam = cell.camera.guess()
    C_H_O = H_from_rotvec([np.radians(1.0), 0.0, 0.0], [0.0, 0.0, 2500.0])  # 40 mm seen from 2.5 m, face on
    p_O, uv, ids = _target_seen(obj, cam, C_H_O)
    uv = uv + np.random.default_rng(1).normal(0, 0.1, (len(p_O), 2))
    with pytest.raises(CalibrationError, match="ambiguous"):
        object_pose(None, cam, obj, detection=TargetDetection(uv, p_O, ids, 8))


def test_a_target_of_an_unknown_dictionary_is_a_config_error():
    t = TargetSpec((4, 4), 10.0, 7.0, "DICT_9X9_1")
    with pytest.raises(ConfigError, match="target.dictionary: 'DICT_9X9_1' is not an OpenCV predefined dictionary"):
        target_board(t)


def test_a_given_detection_that_cannot_fix_a_pose_is_refused_naming_why(cell):
    obj = load_object()
    cam = cell.camera.guess()
    p_O, uv, ids = _target_seen(obj, cam, H_from_rotvec([np.radians(30.0), 0.0, 0.0], [0.0, 0.0, 200.0]))
    with pytest.raises(CalibrationError, match=r"target pose: 5 corner\(s\), at least 6 needed"):
        object_pose(None, cam, obj, detection=TargetDetection(uv[:5], p_O[:5], ids[:5], 8))
    row = np.flatnonzero(np.isclose(p_O[:, 1], p_O[0, 1]))  # one row of corners: on one line
    line = np.r_[row, row]  # enough corners, all on that line
    with pytest.raises(CalibrationError, match="on one line"):
        object_pose(None, cam, obj, detection=TargetDetection(uv[line], p_O[line], ids[line], 8))
    bad = uv.copy()
    bad[2] = np.nan
    with pytest.raises(CalibrationError, match="not finite"):
        object_pose(None, cam, obj, detection=TargetDetection(bad, p_O, ids, 8))
    with pytest.raises(ValueError, match=r"expected uv \(N, 2\) and p_O \(N, 3\)"):
        object_pose(None, cam, obj, detection=TargetDetection(uv, p_O[:, :2], ids, 8))


def test_a_target_picture_is_read_as_every_picture_is():
    """The target's picture goes through the one grey conversion (``as_gray``): no picture, or a blank one, is an
    ``ImageError`` naming it; a colour or 12-bit camera's picture (pixels 0..4095) gives the grey picture's corners."""
    t = load_object().target
    for bad, why in ((np.zeros((10,), np.uint8), r"target picture: expected a grey or BGR image, got .* \(10,\)"),
                     (np.zeros((0, 0), np.uint8), r"target picture: expected a grey or BGR image, got .* \(0, 0\)"),
                     (np.zeros((576, 768), np.float32), "blank target picture"),
                     (np.zeros((576, 768, 2), np.uint8), r"expected a grey or BGR image, got .* \(576, 768, 2\)"),
                     (None, r"target picture: expected a grey or BGR image, got an array of shape \(\)")):
        with pytest.raises(ImageError, match=why):
            detect_target(bad, t)
    grey = _board_picture(t)
    ids = detect_target(grey, t).ids
    assert len(ids) > 0
    for same in (np.repeat(grey[..., None], 3, axis=2), np.rint(grey * (4095 / 255)).astype(np.uint16)):
        assert np.array_equal(detect_target(same, t).ids, ids)
