"""Tsai's coplanar calibration (selfview.estimation.tsai) and the Levenberg-Marquardt solver it runs on (selfview.maths.lm).

References: Willson's published run (``reference/tsai-willson/ccal.log``), NiftyCal's real dot grid
(``reference/niftycal-dots``), and seeded synthetic views of the reference cell's plate.
"""

from __future__ import annotations

import numpy as np
import pytest

from selfview.maths.camera import CameraModel
from selfview.errors import CalibrationError, CalibrationFileError, ConfigError
from selfview.maths.geometry import R_from_rotvec, R_from_rpy, make_H, pose_difference, rpy_from_R, transform_points
from selfview.maths.lm import levenberg_marquardt, numeric_jacobian
from selfview.estimation.tsai import (
    FREE_CENTRE_MODES, MODES, TsaiResult, _FullModel, _WillsonStages, calibrate_coplanar, load_willson_points,
    residual_stats,
)
from tests.selfview.test_camera_willson import willson_camera, willson_sections

TSAI_LOG = "Coplanar calibration (Tz, f, kappa1 optimization)"
FULL_LOG = "Coplanar calibration (full optimization)"
DPX = 0.023  # mm per pixel of Willson's Photometrics Star I


# --- scenes ------------------------------------------------------------------------------------------
def plate_points(rows=8, cols=8, pitch=9.0) -> np.ndarray:
    """(rows*cols, 3) disc centres of a grid centred on W's origin, z = 0 (the reference cell's plate)."""
    x = (np.arange(cols) - (cols - 1) / 2) * pitch
    y = (np.arange(rows) - (rows - 1) / 2) * pitch
    X, Y = np.meshgrid(x, y)
    return np.column_stack([X.ravel(), Y.ravel(), np.zeros(X.size)])


def view(tilt_deg, spin_deg=20.0, axis_deg=0.0, t=(3.0, 2.0, 120.0)) -> np.ndarray:
    """C_H_W of a camera looking at the plate from its -z side, tilted about an in-plane axis."""
    a = np.radians(axis_deg)
    R = R_from_rotvec(np.radians(tilt_deg) * np.array([np.cos(a), np.sin(a), 0.0])) @ R_from_rotvec(
        [0.0, 0.0, np.radians(spin_deg)]
    )
    return make_H(R, t)


def random_view(rng) -> np.ndarray:
    return view(
        rng.uniform(20, 50), rng.uniform(-180, 180), rng.uniform(0, 360),
        (rng.uniform(-8, 8), rng.uniform(-8, 8), rng.uniform(105, 140)),
    )


def picture(cam: CameraModel, C_H_W, p_W, noise_px=0.0, rng=None):
    """(p_W, uv) of the points that land in the picture, with Gaussian pixel noise."""
    uv = cam.project(transform_points(C_H_W, p_W))
    keep = cam.in_image(uv, margin=3.0)
    uv = uv[keep]
    if noise_px:
        uv = uv + rng.normal(scale=noise_px, size=uv.shape)
    return p_W[keep], uv


CAM = CameraModel(f=962.0, kappa=1.9e-7)  # the reference cell's camera (CONVENTIONS.md)


# --- Willson's published run -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def willson(willson_dir):
    d = willson_dir
    p_W, uv = load_willson_points(d / "cc_cd.dat")
    return p_W, uv, willson_sections((d / "ccal.log").read_text())


def test_tsai_mode_reproduces_willsons_coplanar_run(willson):
    p_W, uv, logs = willson
    log = logs[TSAI_LOG]
    res = calibrate_coplanar(p_W, uv, cx=258, cy=204, mode="tsai", width=576, height=384)
    assert res.mode == "tsai" and len(res.residuals_px) == 100
    assert res.camera.f == pytest.approx(log["f"] / DPX, rel=1e-4)
    assert res.camera.kappa == pytest.approx(log["kappa1"] * DPX**2, rel=1e-4)
    assert (res.camera.cx, res.camera.cy) == (258, 204)
    T = res.C_H_W[:3, 3]
    angles = np.degrees(rpy_from_R(res.C_H_W))  # (Rx, Ry, Rz) of R = Rz Ry Rx
    assert T == pytest.approx([log["Tx"], log["Ty"], log["Tz"]], rel=1e-4)
    assert angles == pytest.approx([log["Rx"], log["Ry"], log["Rz"]], rel=1e-4)
    # The linear stages (Tx, Ty, R) are not touched by the refinement: they agree to the printed digits.
    assert T[:2] == pytest.approx([log["Tx"], log["Ty"]], abs=5e-6)
    assert angles == pytest.approx([log["Rx"], log["Ry"], log["Rz"]], abs=5e-6)
    # error statistics of the distorted image plane, per-point distances in pixels
    assert res.mean_px == pytest.approx(log["distorted_mean"], rel=1e-4)
    assert res.max_px == pytest.approx(log["distorted_max"], rel=1e-4)
    assert res.sse_px2 == pytest.approx(log["distorted_sse"], rel=1e-4)


def test_full_centre_mode_on_willsons_data(willson):
    """Willson's full optimisation stopped on his ftol test in a flat valley: his published point is
    not a minimum of his own objective (our minimum of the distorted pixel error lies 0.65 % higher in
    f, the standard error of f from these data is about 5 %). So: the centre within 0.5 px, f within
    1 %, and a fit at least as good as his (his parameters evaluated on our objective do worse)."""
    p_W, uv, logs = willson
    log = logs[FULL_LOG]
    res = calibrate_coplanar(p_W, uv, cx=258, cy=204, mode="full+centre", width=576, height=384)
    assert res.camera.f * DPX == pytest.approx(log["f"], rel=0.01)
    assert np.hypot(res.camera.cx - log["Cx"], res.camera.cy - log["Cy"]) < 0.5
    assert res.camera.kappa == pytest.approx(log["kappa1"] * DPX**2, rel=0.01)
    assert res.sse_px2 <= log["distorted_sse"]
    # his parameters on our objective: the published distorted sse, which is higher than ours
    cam = CameraModel(f=log["f"] / DPX, kappa=log["kappa1"] * DPX**2, cx=log["Cx"], cy=log["Cy"])
    H = make_H(R_from_rpy(*np.radians([log["Rx"], log["Ry"], log["Rz"]])), [log["Tx"], log["Ty"], log["Tz"]])
    theirs = residual_stats(uv - cam.project(transform_points(H, p_W)))[3]
    assert theirs == pytest.approx(log["distorted_sse"], abs=1e-5)
    assert res.sse_px2 < theirs


def test_willson_mode_reproduces_willsons_full_optimisation(willson):
    """His chain (f/Tz/kappa, five parameters with late then early distortion removal, eight, ten) on
    his objective with his lmdif settings stops where his stopped, in the flat f-Tz valley of a plate
    6.3 m away. Where in the valley hangs on rounding (1e-12 on the pixels moves f by 0.05 %, 0.2 % at
    the 99th percentile, in his MINPACK as here), so f within 0.2 % and the centre within 0.5 px;
    Tz / f, which the valley keeps, and the error statistics far closer."""
    p_W, uv, logs = willson
    log = logs[FULL_LOG]
    res = calibrate_coplanar(p_W, uv, cx=258, cy=204, mode="willson", width=576, height=384)
    assert res.mode == "willson" and res.iterations > 0
    f_mm = res.camera.f * DPX
    assert f_mm == pytest.approx(log["f"], rel=2e-3)
    assert np.hypot(res.camera.cx - log["Cx"], res.camera.cy - log["Cy"]) < 0.5
    assert res.camera.kappa == pytest.approx(log["kappa1"] * DPX**2, rel=5e-3)
    T = res.C_H_W[:3, 3]
    assert T[:2] == pytest.approx([log["Tx"], log["Ty"]], rel=2e-3)
    assert T[2] / f_mm == pytest.approx(log["Tz"] / log["f"], rel=1e-4)
    assert np.degrees(rpy_from_R(res.C_H_W)) == pytest.approx([log["Rx"], log["Ry"], log["Rz"]], abs=0.01)
    assert res.mean_px == pytest.approx(log["distorted_mean"], rel=1e-3)
    assert res.max_px == pytest.approx(log["distorted_max"], rel=5e-3)
    assert res.sse_px2 == pytest.approx(log["distorted_sse"], rel=3e-4)
    # his objective, the undistorted image plane error, as his log prints it
    eu = np.linalg.norm(
        res.camera.undistort_pixels(uv) - res.camera.project_undistorted(transform_points(res.C_H_W, p_W)), axis=1
    )
    assert eu.mean() == pytest.approx(log["undistorted_mean"], rel=1e-3)
    assert np.sum(eu**2) == pytest.approx(log["undistorted_sse"], rel=3e-4)
    # where his optimiser stops is not the minimum of the distorted pixel error that full+centre finds
    best = calibrate_coplanar(p_W, uv, cx=258, cy=204, mode="full+centre", width=576, height=384)
    assert best.sse_px2 < res.sse_px2 - 1e-5


def test_willsons_objective_matches_his_log_and_his_result_is_not_its_minimum(willson, willson_dir):
    """Of the error statistics his log prints, the undistorted sensor-plane error is the one his stages
    minimise: the 'willson' residuals at his published parameters give that block to every digit. Yet
    his point is not its minimum: refining all ten parameters further lowers it and raises f by ~1 %."""
    p_W, uv, logs = willson
    log = logs[FULL_LOG]
    cam, H = willson_camera(willson_dir / "cc_cpcc.dat")
    stages = _WillsonStages(p_W[:, :2], uv, cam.aspect)
    x = np.array([*rpy_from_R(H), *H[:3, 3], cam.kappa, cam.f, cam.cx, cam.cy])
    e, _ = stages.pose(x)
    assert [round(float(v), 6) for v in (e.mean(), e.max(), np.sum(e**2))] == [
        log["undistorted_mean"], log["undistorted_max"], log["undistorted_sse"]
    ]
    lm = levenberg_marquardt(lambda v: stages.pose(v)[0], x, "central", ftol=1e-12, xtol=1e-12, max_nfev=100)
    assert lm.cost < log["undistorted_sse"] - 2e-4
    assert lm.x[7] > 1.005 * cam.f


def test_willson_mode_where_the_data_determine_f(rng):
    """A near, tilted plate leaves no flat valley: his chain ends near the full+centre minimum (which
    one view of a plane places only to a few pixels in the centre)."""
    true = CAM.with_(cx=390.0, cy=281.0)
    H = view(35.0, spin_deg=30.0, axis_deg=60.0)
    p_W, uv = picture(true, H, plate_points(), 0.05, rng)
    res = calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, mode="willson")
    best = calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, mode="full+centre")
    assert res.camera.f == pytest.approx(best.camera.f, rel=1e-3)
    assert np.hypot(res.camera.cx - best.camera.cx, res.camera.cy - best.camera.cy) < 1.0
    assert res.sse_px2 >= best.sse_px2 and res.rms_px < 1.01 * best.rms_px
    assert res.camera.f == pytest.approx(962.0, rel=5e-3)
    assert pose_difference(res.C_H_W, H)[0] < 0.3


def test_full_mode_fits_better_than_tsai_mode(willson):
    p_W, uv, _ = willson
    fits = {m: calibrate_coplanar(p_W, uv, cx=258, cy=204, mode=m) for m in MODES}
    assert fits["full+centre"].sse_px2 < fits["full"].sse_px2 < fits["tsai"].sse_px2
    assert all(r.iterations > 0 for r in fits.values())


# --- NiftyCal's real dot grid ----------------------------------------------------------------------------
def niftycal_points(niftycal_dir, side):
    d = niftycal_dir
    model = {int(r[0]): r[1:] for r in np.loadtxt(d / "model.txt")}
    det = np.loadtxt(d / f"1479224185706804480_{side}.txt")
    p_W = np.array([model[int(i)] for i in det[:, 0]])
    uv = det[:, 1:3] * [1.0, 2.0]  # the detections are on the 1920 x 540 field: v scaled by 2
    return p_W, uv


# README: a Tsai-model fit with the centre fixed at (959.5, 539.5) gives f near 1667 px, kappa near
# 1.0e-7 px^-2, residual near 0.8 px; NiftyCal's own values (centre free): left 1676.49, right 1660.21.
@pytest.mark.parametrize("side,niftycal_f", [("left", 1676.49), ("right", 1660.21)])
def test_niftycal_dot_grid(niftycal_dir, side, niftycal_f):
    p_W, uv = niftycal_points(niftycal_dir, side)
    res = calibrate_coplanar(p_W, uv, cx=959.5, cy=539.5, width=1920, height=1080)
    assert res.camera.f == pytest.approx(1667.0, rel=0.01)
    assert res.camera.f == pytest.approx(niftycal_f, rel=0.01)
    assert 0.5e-7 < res.camera.kappa < 2.0e-7
    assert res.rms_px < 1.3
    assert res.camera.width == 1920 and res.camera.height == 1080


# --- synthetic round trips ---------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(8))
def test_round_trip_with_noise(seed):
    rng = np.random.default_rng(1000 + seed)
    H = random_view(rng)
    noise = 0.05
    p_W, uv = picture(CAM, H, plate_points(), noise, rng)
    res = calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5)
    assert isinstance(res, TsaiResult) and res.mode == "full"
    assert res.camera.f == pytest.approx(962.0, rel=3e-3)
    assert res.camera.kappa == pytest.approx(1.9e-7, rel=0.05)
    ang, dist = pose_difference(res.C_H_W, H)
    assert ang < 0.05 and dist < 0.3
    # the reported residual is the noise, less what 8 parameters absorb
    n = len(uv)
    expected_rms = noise * np.sqrt(2.0 * (2 * n - 8) / (2 * n))
    assert res.rms_px == pytest.approx(expected_rms, rel=0.3)


def test_residuals_are_observed_minus_model_and_statistics_match(rng):
    H = view(35.0)
    p_W, uv = picture(CAM, H, plate_points(), 0.1, rng)
    for mode in MODES:
        res = calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, mode=mode)
        model = res.camera.project(transform_points(res.C_H_W, p_W))
        assert np.abs(res.residuals_px - (uv - model)).max() < 1e-8
        d = np.hypot(*res.residuals_px.T)
        assert res.errors_px == pytest.approx(d)
        assert res.rms_px == pytest.approx(np.sqrt(np.mean(d**2)))
        assert res.mean_px == pytest.approx(d.mean())
        assert res.max_px == pytest.approx(d.max())
        assert res.sse_px2 == pytest.approx(np.sum(d**2))
        out = res.to_dict()
        assert out["n_points"] == len(uv) and out["mode"] == mode and np.shape(out["C_H_W"]) == (4, 4)


@pytest.mark.parametrize("mode", MODES)
def test_exact_data_is_recovered_exactly(mode):
    true = CAM.with_(cx=390.0, cy=281.0) if mode in FREE_CENTRE_MODES else CAM
    H = view(30.0, spin_deg=-65.0, axis_deg=40.0)
    p_W, uv = picture(true, H, plate_points(), 0.0)
    res = calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, mode=mode)
    # tsai, willson: Willson's loose ftol; tsai: pose from the linear stage
    tol = {"tsai": 2e-4, "willson": 2e-6}.get(mode, 1e-7)
    assert res.camera.f == pytest.approx(962.0, rel=tol)
    ang, dist = pose_difference(res.C_H_W, H)
    if mode == "tsai":
        # the pose is the linear stage's, which ignores distortion
        assert ang < 1e-3 and dist < 0.05 and res.rms_px < 0.05
    elif mode == "willson":
        assert res.camera.kappa == pytest.approx(1.9e-7, rel=1e-5)
        assert ang < 1e-4 and dist < 5e-4 and res.rms_px < 2e-5
        assert (res.camera.cx, res.camera.cy) == pytest.approx((390.0, 281.0), abs=2e-3)
    else:
        assert res.camera.kappa == pytest.approx(1.9e-7, rel=1e-6)
        # the rotation as matrices (an angle through arccos resolves no better than ~1e-6 deg): entries to
        # 1e-9, i.e. the rotation to about 1e-9 rad (1e-7 mm at the plate's 100 mm)
        assert np.abs(res.C_H_W[:3, :3] - H[:3, :3]).max() < 1e-9
        assert dist < 1e-6 and res.rms_px < 1e-7
    if mode == "full+centre":
        assert (res.camera.cx, res.camera.cy) == pytest.approx((390.0, 281.0), abs=1e-5)


def test_plate_origin_far_from_the_picture_and_on_the_optical_axis(rng):
    """Tsai's linear stage divides by Ty: the grid's centre in mid-picture (Ty ~ 0) and a corner origin
    far from it give the same camera and the same plate pose, moved by the origin's offset."""
    H = view(32.0, t=(0.0, 0.0, 118.0))  # the grid's centre on the optical axis: Tx = Ty = 0
    p_W, uv = picture(CAM, H, plate_points(), 0.05, rng)
    a = calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5)
    shift = np.array([31.5 + 50.0, 31.5 + 20.0, 0.0])
    b = calibrate_coplanar(p_W + shift, uv, cx=383.5, cy=287.5)
    assert a.camera.f == pytest.approx(b.camera.f, rel=1e-9)
    assert np.abs(a.C_H_W - b.C_H_W @ make_H(np.eye(3), shift)).max() < 1e-6
    assert pose_difference(a.C_H_W, H)[0] < 0.05


def test_guesses_start_the_refinement_but_do_not_change_the_minimum(rng):
    H = view(40.0, spin_deg=100.0)
    p_W, uv = picture(CAM, H, plate_points(), 0.05, rng)
    ref = calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5)
    for kw in ({"kappa_guess": 1.9e-7}, {"f_guess": 900.0}, {"f_guess": 1100.0, "kappa_guess": 1e-7}):
        res = calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, **kw)
        assert res.camera.f == pytest.approx(ref.camera.f, rel=1e-7)
        assert res.camera.kappa == pytest.approx(ref.camera.kappa, rel=1e-5)


def test_aspect_ratio_is_applied(rng):
    true = CAM.with_(aspect=0.95)
    H = view(35.0, spin_deg=10.0)
    p_W, uv = picture(true, H, plate_points(), 0.02, rng)
    res = calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, aspect=0.95)
    assert res.camera.aspect == 0.95
    assert res.camera.f == pytest.approx(962.0, rel=2e-3)
    # one planar view absorbs most of a wrong aspect in the pose, but not in f and not all of it
    wrong = calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, aspect=1.0)
    assert abs(wrong.camera.f / 962.0 - 1.0) > 0.05 and wrong.rms_px > 2 * res.rms_px


# --- degenerate input ----------------------------------------------------------------------------------
def _good():
    return picture(CAM, view(32.0), plate_points(), 0.0)


def _degenerate(case, rng):
    p_W, uv = _good()
    if case == "too few":
        return p_W[:4], uv[:4], "at least 5 points"
    if case == "collinear":
        row = np.abs(p_W[:, 1] - p_W[0, 1]) < 1e-9
        return p_W[row], uv[row], "collinear plate points"
    if case == "non-coplanar":
        q = p_W.copy()
        q[5, 2] = 2.0
        return q, uv, "non-coplanar points in a coplanar call"
    if case == "nan":
        u = uv.copy()
        u[7, 1] = np.nan
        return p_W, u, "non-finite"
    if case == "shapes":
        return p_W, uv[:-1], r"plate points but \d+ image points"
    if case == "shape (N, 2) plate":
        return p_W[:, :2], uv, r"p_W must have shape \(N, 3\)"
    if case == "edge-on":
        return (*picture(CAM, view(87.0, t=(0, 0, 60.0)), plate_points(), 0.05, rng), "edge-on")
    if case == "exactly edge-on":
        P = plate_points()
        return P, np.column_stack([300 + P[:, 0], 287.5 + 0 * P[:, 1]]), "edge-on"
    if case == "square-on":
        return (*picture(CAM, view(0.0), plate_points(), 0.05, rng), "f cannot be separated from Tz")
    if case == "square-on, exact, no distortion":
        return (*picture(CAM.with_(kappa=0.0), view(0.0), plate_points(), 0.0), "f cannot be separated from Tz")
    if case == "too far":
        return (*picture(CAM, view(30.0, t=(0, 0, 4000.0)), plate_points(), 0.05, rng), "f cannot be separated")
    if case == "mirrored":
        return p_W * [-1, 1, 1], uv, "mirrored"
    raise AssertionError(case)


@pytest.mark.parametrize(
    "case",
    ["too few", "collinear", "non-coplanar", "nan", "shapes", "shape (N, 2) plate", "edge-on", "exactly edge-on",
     "square-on", "square-on, exact, no distortion", "too far", "mirrored"],
)
def test_degenerate_input_raises_naming_the_cause(case, rng):
    p_W, uv, why = _degenerate(case, rng)
    with pytest.raises(CalibrationError, match=why):
        calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5)


@pytest.mark.parametrize("mode", FREE_CENTRE_MODES)
@pytest.mark.parametrize("seed", range(3))
def test_free_centre_without_distortion_is_refused(seed, mode):
    """One view of a plane through a distortion-free lens cannot give f and the principal point."""
    rng = np.random.default_rng(seed)
    p_W, uv = picture(CAM.with_(kappa=0.0), view(30.0, axis_deg=30.0), plate_points(), 0.1, rng)
    with pytest.raises(CalibrationError, match="cannot separate the principal point, f and the tilt"):
        calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, mode=mode)
    # with the centre fixed the same picture calibrates
    assert calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5).camera.f == pytest.approx(962.0, rel=5e-3)


@pytest.mark.parametrize("free_centre", [False, True])
def test_full_model_jacobian_is_the_derivative_of_its_residuals(free_centre, rng):
    H = view(35.0, spin_deg=50.0)
    p_W, uv = picture(CAM.with_(aspect=0.9), H, plate_points(), 0.05, rng)
    R0 = R_from_rotvec([0.01, -0.02, 0.015]) @ H[:3, :3]
    model = _FullModel(p_W, uv, R0, 380.0, 290.0, 0.9, free_centre)
    x = np.array([0.02, -0.01, 0.03, 3.5, 1.5, 121.0, 950.0, 2.5e-7, 381.0, 289.0][: 10 if free_centre else 8])
    J = model.jacobian(x)
    Jn = numeric_jacobian(model.residuals, x, scale=np.abs(x))
    assert np.all(np.abs(J - Jn).max(axis=0) <= 1e-6 * np.abs(Jn).max(axis=0))


def test_bad_arguments_raise_config_errors():
    p_W, uv = _good()
    with pytest.raises(ConfigError, match="mode"):
        calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, mode="bundle")
    with pytest.raises(ConfigError, match="aspect"):
        calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, aspect=0.0)
    with pytest.raises(ConfigError, match="cx"):
        calibrate_coplanar(p_W, uv, cx=float("nan"), cy=287.5)
    with pytest.raises(ConfigError, match="f_guess"):
        calibrate_coplanar(p_W, uv, cx=383.5, cy=287.5, f_guess=-5.0)


# --- the points file -------------------------------------------------------------------------------------
def test_load_willson_points_reads_comments_and_blank_lines(tmp_path):
    f = tmp_path / "pts.dat"
    f.write_text("# xw yw zw u v\n\n1 2 0 3.5 4.5  # first\n 1e1 -2 0.0 5 6\n")
    p_W, uv = load_willson_points(f)
    assert p_W.tolist() == [[1, 2, 0], [10, -2, 0]] and uv.tolist() == [[3.5, 4.5], [5, 6]]


@pytest.mark.parametrize(
    "text,why",
    [
        ("1 2 0 3 4\n1 2 0 3\n", "line 2: expected 5 numbers"),
        ("1 2 0 3 4\n\n1 2 zero 3 4\n", "line 3: not a number"),
        ("1 2 0 3 nan\n", "line 1: non-finite"),
        ("# nothing\n", "no points"),
    ],
)
def test_load_willson_points_names_the_bad_line(tmp_path, text, why):
    f = tmp_path / "pts.dat"
    f.write_text(text)
    with pytest.raises(CalibrationFileError, match=why):
        load_willson_points(f)


def test_load_willson_points_missing_file(tmp_path):
    with pytest.raises(CalibrationFileError, match="no such points file"):
        load_willson_points(tmp_path / "absent.dat")


# --- the Levenberg-Marquardt solver ---------------------------------------------------------------------------
def _rosenbrock(x):
    return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


def _rosenbrock_jac(x):
    return np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])


@pytest.mark.parametrize("jac", [_rosenbrock_jac, "central", "forward"])
def test_lm_solves_rosenbrock(jac):
    res = levenberg_marquardt(_rosenbrock, [-1.2, 1.0], jac)
    assert res.converged and res.x == pytest.approx([1.0, 1.0], abs=1e-7)
    assert res.cost < 1e-14 and res.iterations > 5


def test_lm_linear_least_squares_and_covariance(rng):
    A = rng.normal(size=(50, 3)) * [1.0, 1e3, 1e-4]  # badly scaled columns
    x_true = np.array([2.0, -1e-3, 5e3])
    b = A @ x_true + rng.normal(scale=0.01, size=50)
    res = levenberg_marquardt(lambda x: A @ x - b, np.zeros(3), lambda x: A)
    ref, *_ = np.linalg.lstsq(A, b, rcond=None)
    assert res.x == pytest.approx(ref, rel=1e-9)
    s2 = float(np.sum((A @ ref - b) ** 2)) / (50 - 3)
    assert res.covariance() == pytest.approx(s2 * np.linalg.inv(A.T @ A), rel=1e-6)


def test_lm_rejects_steps_into_non_finite_regions():
    # minimum at x = 3, but the residual is undefined beyond x = 3.5: big first steps land there
    def fun(x):
        return np.array([np.nan]) if x[0] > 3.5 else np.array([np.exp(x[0] - 3.0) - 1.0, 0.1 * (x[0] - 3.0)])

    res = levenberg_marquardt(fun, [-30.0], "central", factor=1000.0)
    assert res.converged and res.x[0] == pytest.approx(3.0, abs=1e-8)


def test_lm_input_errors_and_budget():
    with pytest.raises(CalibrationError, match="not finite at the start"):
        levenberg_marquardt(lambda x: np.array([np.nan, 1.0]), [0.0])
    with pytest.raises(ValueError, match="cannot determine"):
        levenberg_marquardt(lambda x: np.array([x[0]]), [0.0, 1.0])
    with pytest.raises(ValueError, match="Jacobian of shape"):
        levenberg_marquardt(_rosenbrock, [0.0, 0.0], lambda x: np.zeros((3, 2)))
    res = levenberg_marquardt(_rosenbrock, [-1.2, 1.0], _rosenbrock_jac, max_nfev=3)
    assert not res.converged and "gave up" in res.message


def test_numeric_jacobian_schemes():
    def fun(x):
        return np.array([np.sin(x[0]) * x[1], x[1] ** 3, np.exp(x[0])])

    x = np.array([0.3, 2.0])
    exact = np.array([[np.cos(0.3) * 2.0, np.sin(0.3)], [0.0, 12.0], [np.exp(0.3), 0.0]])
    assert numeric_jacobian(fun, x) == pytest.approx(exact, abs=1e-9)
    assert numeric_jacobian(fun, x, method="forward") == pytest.approx(exact, abs=1e-6)
    # a parameter at 0 steps by rel_step * scale
    J0 = numeric_jacobian(lambda v: np.array([v[0] ** 2]), np.array([0.0]), method="forward", scale=[1e-3])
    assert J0[0, 0] == pytest.approx(np.sqrt(np.finfo(float).eps) * 1e-3, rel=1e-6)
    with pytest.raises(ValueError, match="method"):
        numeric_jacobian(fun, x, method="backward")
