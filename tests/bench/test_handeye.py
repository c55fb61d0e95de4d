"""Classical hand/eye calibration (AX = XB): Tsai-Lenz and Park-Martin on seeded synthetic stations."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from selfview.errors import CalibrationError, ConfigError
from selfview.maths.geometry import R_from_rotvec, inv_H, make_H, pose_difference, rot_z, transform_points
from selfview.bench.handeye import METHODS, calibrate_handeye, plate_pose, relative_motions


def random_H(rng, angle_scale=1.0, t_scale=100.0, t0=(0.0, 0.0, 0.0)) -> np.ndarray:
    return make_H(R_from_rotvec(rng.normal(size=3) * angle_scale), rng.normal(size=3) * t_scale + np.asarray(t0))


def stations(rng, X, n, noise_deg=0.0, noise_mm=0.0):
    """Flange poses and plate poses consistent with F_H_C = X and a fixed plate; camera-side noise."""
    base_H_W = random_H(rng, 1.0, 50.0, (400.0, 0.0, 0.0))
    F, C = [], []
    for _ in range(n):
        bF = random_H(rng, 0.4, 80.0, (300.0, 0.0, 300.0))
        C_H_W = inv_H(X) @ inv_H(bF) @ base_H_W
        if noise_deg or noise_mm:
            C_H_W = make_H(R_from_rotvec(rng.normal(size=3) * np.radians(noise_deg)), rng.normal(size=3) * noise_mm) @ C_H_W
        F.append(bF)
        C.append(C_H_W)
    return F, C, base_H_W


# a camera looking back at its gripper: X within a degree of a half turn (the reference cell's mount)
HALF_TURN = make_H(R_from_rotvec(np.array([0.0, 0.2588, 0.9659]) * np.radians(179.5)), (0.0, -58.0, -263.0))


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("X_kind", ["general", "half turn", "exact half turn"])
def test_exact_stations_give_X_exactly(method, X_kind, rng):
    X = {"general": random_H(rng), "half turn": HALF_TURN,
         "exact half turn": make_H(np.diag([-1.0, -1.0, 1.0]), (5.0, 60.0, -250.0))}[X_kind]
    F, C, base_H_W = stations(rng, X, 6)
    r = calibrate_handeye(F, C, method)
    np.testing.assert_allclose(r.F_H_C, X, atol=1e-8)
    np.testing.assert_allclose(r.C_H_F, inv_H(X), atol=1e-8)
    np.testing.assert_allclose(r.base_H_W, base_H_W, atol=1e-8)
    assert r.rotation_residual_deg < 1e-7 and r.translation_residual_mm < 1e-7 and r.plate_spread_mm < 1e-7
    assert (r.n_poses, r.n_motions) == (6, 15)


@pytest.mark.parametrize("method, flag", [("tsai-lenz", "CALIB_HAND_EYE_TSAI"), ("park-martin", "CALIB_HAND_EYE_PARK")])
def test_noisy_stations_agree_with_opencv(method, flag, rng):
    X = random_H(rng)
    F, C, _ = stations(rng, X, 12, noise_deg=0.01, noise_mm=0.02)
    r = calibrate_handeye(F, C, method)
    R, t = cv2.calibrateHandEye([f[:3, :3] for f in F], [f[:3, 3] for f in F],
                                [c[:3, :3] for c in C], [c[:3, 3] for c in C], method=getattr(cv2, flag))
    ours, cv = pose_difference(r.F_H_C, X), pose_difference(make_H(R, t.ravel()), X)
    assert ours[0] < 0.02 and ours[1] < 0.3  # deg, mm: the noise propagated
    # two implementations of one estimator, compared as rotation matrices (entry differences ~ the angle in
    # rad; an angle through arccos resolves nothing below ~1e-6 deg) and translations [mm]. Park-Martin:
    # the same closed form, so far below anything physical: 1e-9 rad, 1e-6 mm. Tsai-Lenz: OpenCV solves
    # its linear systems otherwise (an unconstrained least squares, then orthonormalised), which moves the
    # result within the station noise (0.01 deg = 1.7e-4 rad, 0.02 mm, propagated: up to ~0.1 mm)
    tol_R, tol_t = (1e-9, 1e-6) if method == "park-martin" else (np.radians(0.01), 0.1)
    dR = np.abs(r.F_H_C[:3, :3] - R).max()
    dt = np.linalg.norm(r.F_H_C[:3, 3] - t.ravel())
    assert dR < tol_R and dt < tol_t, (dR, dt, ours, cv)
    assert 0 < r.rotation_residual_deg < 0.1 and 0 < r.plate_spread_mm < 1.0


def test_C_H_G_goes_through_the_tool(rng):
    X = random_H(rng)
    F, C, _ = stations(rng, X, 4)
    F_H_G = make_H(np.eye(3), (0.0, 0.0, 170.0))
    r = calibrate_handeye(F, C)
    np.testing.assert_allclose(r.C_H_G(F_H_G), inv_H(X) @ F_H_G, atol=1e-7)
    d = r.to_dict()
    assert d["method"] == "tsai-lenz" and np.shape(d["F_H_C"]) == (4, 4)


def test_relative_motions_satisfy_AX_XB(rng):
    X = random_H(rng)
    F, C, _ = stations(rng, X, 5)
    A, B = relative_motions(F, C)
    assert A.shape == B.shape == (10, 4, 4)
    for a, b in zip(A, B):
        np.testing.assert_allclose(a @ X, X @ b, atol=1e-8)


def test_two_stations_are_one_motion_too_few(rng):
    F, C, _ = stations(rng, random_H(rng), 2)
    with pytest.raises(CalibrationError, match="at least 2 motions"):
        calibrate_handeye(F, C)


def test_parallel_rotation_axes_are_refused(rng):
    X = random_H(rng)
    base_H_W = random_H(rng, 1.0, 50.0, (400.0, 0.0, 0.0))
    F = [make_H(np.eye(3), (300.0, 0.0, 300.0)) @ rot_z(np.radians(a)) @ make_H(np.eye(3), rng.normal(size=3) * 20)
         for a in (0.0, 20.0, 45.0, 70.0)]
    C = [inv_H(X) @ inv_H(f) @ base_H_W for f in F]
    for m in METHODS:
        with pytest.raises(CalibrationError, match="parallel"):
            calibrate_handeye(F, C, m)


def test_pure_translations_are_refused(rng):
    X = random_H(rng)
    base_H_W = random_H(rng, 1.0, 50.0, (400.0, 0.0, 0.0))
    F = [make_H(np.eye(3), rng.normal(size=3) * 50) for _ in range(4)]
    C = [inv_H(X) @ inv_H(f) @ base_H_W for f in F]
    with pytest.raises(CalibrationError, match="turn the flange"):
        calibrate_handeye(F, C)


def test_shuffled_pictures_are_refused(rng):
    F, C, _ = stations(rng, random_H(rng), 6)
    with pytest.raises(CalibrationError, match="not paired in order"):
        calibrate_handeye(F, C[::-1])


def test_bad_input_names_what_is_wrong(rng):
    F, C, _ = stations(rng, random_H(rng), 4)
    with pytest.raises(ConfigError, match="4 robot poses for 3 camera poses"):
        calibrate_handeye(F, C[:3])
    bad = [H.copy() for H in C]
    bad[2][:3, :3] *= 2.0
    with pytest.raises(ConfigError, match=r"C_H_W\[2\]: not a rigid transform"):
        calibrate_handeye(F, bad)
    with pytest.raises(ConfigError, match="hand/eye method 'daniilidis'"):
        calibrate_handeye(F, C, "daniilidis")


def test_plate_pose_with_a_fixed_camera(cell):
    from selfview.measurement.discs import DiscDetections
    from tests.alt_render import disc_centroids

    cam = cell.camera.guess().with_(f=962.0, kappa=1.9e-7)
    C_H_W = make_H(R_from_rotvec([0.5, -0.2, 0.1]) @ np.diag([1.0, -1.0, -1.0]) @ np.diag([1.0, -1.0, -1.0]),
                   (5.0, -8.0, 230.0))
    p_W = cell.plate.disc_centres_W()
    # the centroid of each disc's image, not its centre's: by the independent renderer's own projection and
    # an area integral, not by the boundary polygon that plate_pose's bias correction uses
    uv = disc_centroids(cam, C_H_W, cell.plate)
    rc = np.array([(i // cell.plate.cols, i % cell.plate.cols) for i in range(len(p_W))])
    det = DiscDetections(uv=uv, rc=rc, p_W=p_W, area_px=np.full(len(p_W), 80.0), n_blobs=len(p_W), rejected={})
    rot, tr = pose_difference(plate_pose(det, cam, cell.plate), C_H_W)
    assert rot < 1e-4 and tr < 1e-3
    # without the bias correction the pose would be off by far more
    centres = cam.project(transform_points(C_H_W, p_W))
    assert np.abs(uv - centres).max() > 0.02
