import numpy as np
import pytest

from selfview.files.cell import POINT_NAMES
from selfview.errors import CalibrationError
from selfview.maths.geometry import H_from_rotvec, inv_H, pose_difference, rot_z, transform_points
from selfview.estimation.pcc import measure_points_G, points_G_for_state, solve_pcc


def scene(cell, rng, gap=56.0):
    cam = cell.camera.guess().with_(f=962.0, kappa=1.9e-7)
    C_H_G = cell.mount_guess_C_H_G @ H_from_rotvec(rng.normal(scale=0.02, size=3), rng.normal(scale=2, size=3))
    W_H_G = rot_z(rng.uniform(-np.pi, np.pi))
    W_H_G[:2, 3] = rng.uniform(-3, 3, 2)
    C_H_W = C_H_G @ inv_H(W_H_G)
    pG = cell.gripper.points_G(gap=gap)
    uv = cam.project(transform_points(C_H_G, pG))
    return cam, C_H_G, C_H_W, W_H_G, pG, uv


def test_exact_points_give_the_exact_transform(cell, rng):
    for _ in range(20):
        cam, C_H_G, C_H_W, W_H_G, pG, uv = scene(cell, rng)
        for idx in ([0, 1, 2, 3], [0, 3], [0, 1, 2, 3, 4, 5]):
            r = solve_pcc(uv[idx], pG[idx], C_H_W, cam, [POINT_NAMES[i] for i in idx])
            assert np.allclose(r.C_H_G, C_H_G, atol=1e-9)
            assert np.allclose(r.W_H_G, W_H_G, atol=1e-9)
            assert r.rms_mm < 1e-9 and r.q_norm == pytest.approx(1.0)


def test_noise_is_reported_in_the_residual(cell, rng):
    cam, C_H_G, C_H_W, W_H_G, pG, uv = scene(cell, rng)
    noisy = uv + rng.normal(scale=0.3, size=uv.shape)
    r = solve_pcc(noisy, pG, C_H_W, cam)
    assert 0.005 < r.rms_mm < 0.2
    ang, dist = pose_difference(r.C_H_G, C_H_G)
    assert ang < 0.2 and dist < 0.2
    # the residuals are what eq. 10 leaves: back-projected minus modelled
    model = transform_points(r.W_H_G, pG)[:, :2]
    assert np.allclose(r.residuals_mm, r.p_W[:, :2] - model)


def test_gripper_dimensions_measured_from_the_picture(cell, rng):
    cam, C_H_G, C_H_W, W_H_G, pG, uv = scene(cell, rng, gap=55.3)
    p_W, _ = cam.backproject_to_plane(uv, C_H_W, 0.0)
    dims = measure_points_G(p_W, np.ones(6, bool))
    assert dims["gap"] == pytest.approx(55.3) and dims["width"] == pytest.approx(12.0)
    assert dims["thickness_A"] == pytest.approx(8.0) and dims["thickness_B"] == pytest.approx(8.0)
    per_state = points_G_for_state(dims, "open", cell.gripper)
    assert np.allclose(per_state["open"], cell.gripper.points_G(gap=55.3))
    assert np.allclose(per_state["closed"], cell.gripper.points_G(gap=55.3 - 36.0))
    # measured coordinates give the same transform as the true ones
    r = solve_pcc(uv, per_state["open"], C_H_W, cam)
    assert np.allclose(r.C_H_G, C_H_G, atol=1e-9)
    with pytest.raises(CalibrationError, match="A-inner-back"):
        measure_points_G(p_W, np.array([1, 0, 1, 1, 1, 1], bool))


def test_degenerate_input_raises(cell, rng):
    cam, C_H_G, C_H_W, W_H_G, pG, uv = scene(cell, rng)
    with pytest.raises(CalibrationError, match="at least 2"):
        solve_pcc(uv[:1], pG[:1], C_H_W, cam)
    with pytest.raises(CalibrationError, match="coincide"):
        solve_pcc(uv[:2], np.zeros((2, 3)), C_H_W, cam)
    with pytest.raises(CalibrationError, match="NaN"):
        solve_pcc(np.where(np.arange(12).reshape(6, 2) == 3, np.nan, uv), pG, C_H_W, cam)
    behind = C_H_W.copy()
    behind[:3, 3] = -C_H_W[:3, 3]
    with pytest.raises(CalibrationError, match="behind"):
        solve_pcc(uv, pG, behind, cam)


def test_wrong_shapes_and_a_non_finite_plate_pose_are_named(cell, rng):
    cam, C_H_G, C_H_W, W_H_G, pG, uv = scene(cell, rng)
    with pytest.raises(ValueError, match=r"uv: expected shape \(N, 2\), got \(6, 3\)"):
        solve_pcc(np.c_[uv, np.ones(6)], pG, C_H_W, cam)  # reshaped, these would be 9 points
    with pytest.raises(ValueError, match=r"points_G: expected shape \(N, 3\)"):
        solve_pcc(uv, pG[:, :2], C_H_W, cam)
    with pytest.raises(ValueError, match=r"C_H_W: expected a \(4, 4\) transform"):
        solve_pcc(uv, pG, C_H_W[:3], cam)
    with pytest.raises(CalibrationError, match="C_H_W contains NaN"):
        solve_pcc(uv, pG, np.where(np.eye(4) == 1, np.nan, C_H_W), cam)
    with pytest.raises(ValueError, match=r"expected p_W \(6, 3\) and found \(6,\)"):
        measure_points_G(np.zeros((4, 3)), np.ones(4, bool))
