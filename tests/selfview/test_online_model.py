"""The model's own estimate 'E' through ``online.estimate``, like the point methods."""

import numpy as np
import pytest

from selfview.maths.camera import CameraModel
from selfview.errors import ConfigError
from selfview.maths.geometry import pose_difference, rot_x, trans
from selfview.estimation.online import MODEL_METHOD, estimate


def test_E_is_the_fitted_pose_and_the_camera_motion_it_implies():
    cam = CameraModel(f=950.0, kappa=0.0, cx=383.5, cy=287.5, aspect=1.0, width=768, height=576)
    C_H_G = trans(0.0, 1.0, 110.0) @ rot_x(np.radians(30.0))
    moved = trans(0.8, -0.2, 0.1) @ rot_x(np.radians(0.3)) @ C_H_G
    nan6 = np.full((6, 2), np.nan)
    est = estimate(MODEL_METHOD, C_H_G, np.zeros((6, 3)), nan6, np.zeros(6, bool), cam, model_C_H_G=moved,
                   model_rms_px=0.12)
    assert est.method == "E" and np.allclose(est.C_H_G_orth, moved) and est.points_used == ()
    M = moved @ np.linalg.inv(C_H_G)
    assert est.d_mm == pytest.approx(np.linalg.norm(M[:3, 3]))
    assert est.delta_deg == pytest.approx(pose_difference(moved, C_H_G)[0]) and est.delta_deg == pytest.approx(0.3)
    assert est.rms_px == 0.12
    with pytest.raises(ConfigError, match="model's own estimate"):
        estimate(MODEL_METHOD, C_H_G, np.zeros((6, 3)), nan6, np.zeros(6, bool), cam)


def test_the_monitor_takes_E_like_the_other_update_methods(cell):
    from selfview.estimation.policy import Monitor

    cam = CameraModel(f=950.0, kappa=0.0, cx=383.5, cy=287.5, aspect=1.0, width=768, height=576)
    C_H_G = trans(0.0, 1.0, 110.0) @ rot_x(np.radians(30.0))
    pG = cell.gripper.points_G()
    uv = cam.project((C_H_G @ np.c_[pG, np.ones(6)].T).T[:, :3])
    found = np.ones(6, bool)
    mon = Monitor(C_H_G, cam, pG, cell.monitor, update_method="E")
    small = trans(0.05, 0.0, 0.0) @ C_H_G
    d = mon.step(uv, found, model_C_H_G=small, model_rms_px=0.1)
    assert d.action == "update" and d.method == "E" and np.allclose(mon.C_H_G, small)
    d = mon.step(uv, found)  # no model pose: no estimate, an alarm naming why
    assert d.action == "alarm" and "model's own estimate" in d.reason


def test_E_refuses_a_current_transform_that_is_no_transform():
    cam = CameraModel(f=950.0, kappa=0.0, cx=383.5, cy=287.5, aspect=1.0, width=768, height=576)
    moved = trans(0.8, -0.2, 0.1)
    nan6 = np.full((6, 2), np.nan)
    for bad in (np.eye(3), np.full((4, 4), np.nan)):
        with pytest.raises(ValueError, match=r"C_H_G: expected a finite \(4, 4\) transform"):
            estimate(MODEL_METHOD, bad, np.zeros((6, 3)), nan6, np.zeros(6, bool), cam, model_C_H_G=moved)
