"""Consistency checks: two halves of the views against each other; one picture against the assumed camera; the TCP's
uncertainty from the camera calibration and the PCC together."""

from __future__ import annotations

import numpy as np

from selfview.maths.camera import CameraModel
from selfview.errors import CalibrationError
from selfview.maths.geometry import R_from_rotvec, make_H
from selfview.estimation.intrinsics.fit import MIN_VIEWS_HALF, JointFit, named
from selfview.estimation.intrinsics.model import (POSE_STEP, STEP, JointProblem, central_differences, intrinsics_vector,
                                                  with_intrinsics)
from selfview.estimation.pcc import solve_pcc
from selfview.estimation.tsai import calibrate_coplanar
from selfview.maths.lm import levenberg_marquardt, wald_chi2


#: The halves of the cross-check agree when no parameter differs by more than this many combined sigmas.
AGREE_SIGMAS = 3.0


def halves_cross_check(fit: JointFit) -> dict:
    """Do two halves of the fit's views (alternate ones) give the same intrinsics within ``AGREE_SIGMAS`` combined
    sigmas? Each half to first order about ``fit`` (``ReducedSystem.fit_without``), with its own residual variance."""
    n = len(fit.views)
    if n < 2 * MIN_VIEWS_HALF:
        return {"done": False, "why": f"{n} views; the cross-check needs {2 * MIN_VIEWS_HALF} (two halves of "
                                      f"{MIN_VIEWS_HALF})"}
    ni, halves = len(fit.cov5), []
    for first in (1, 0):
        try:
            x, cov, _ = fit.reduced.fit_without(range(first, n, 2))  # the other half left out
        except CalibrationError as exc:
            return {"done": False, "why": f"a half could not be calibrated: {exc}"}
        halves.append((x[:ni], cov[:ni, :ni]))
    (xa, ca), (xb, cb) = halves
    comb = np.sqrt(np.diag(ca) + np.diag(cb))
    ratio = np.abs(xa - xb) / comb
    return {"done": True, "agree": bool(np.all(np.isfinite(ratio)) and np.all(ratio <= AGREE_SIGMAS)),
            "halves": [named(xa), named(xb)], "difference": named(xa - xb), "combined_sigma": named(comb),
            "ratio": named(ratio), "limit_sigmas": AGREE_SIGMAS}


#: Accuracy targets of the off-line calibration [mm]: TCP across and along the optical axis.
TARGET_ACROSS_MM = 0.02
TARGET_ALONG_MM = 0.08
#: Chi-square (3 dof) over which a picture's centre and aspect differ from the assumed (p = 1e-4 if right).
CAMERA_CHI2_LIMIT = 21.1
#: Most excess [px] of the disc residual with a camera file's intrinsics over that with the picture's own f and
#: kappa: under 0.02 px for the right camera, 0.3 px and more for another of the same size.
CAMERA_FILE_MAX_EXCESS_PX = 0.1
#: Least error [px] (u, v) of a found fingertip corner: the corner search's RMS error on rendered pictures (its
#: edges' scatter says 0.009 px; without it the TCP's sigma was 2.6-5.7 times too small).
CORNER_FLOOR_PX = (0.036, 0.062)


def _one_view(result, camera: CameraModel, ni: int = 5):
    """(model, x) of the one-view problem at the off-line result: f and kappa the picture's, the rest ``camera``'s
    (``ni`` 5: skew held, 6: free), and the pose."""
    ts = result.tsai
    H = ts.C_H_W
    model = JointProblem([result.discs.p_W], [result.disc_uv_corrected], [H[:3, :3]], ni=ni, skew=camera.skew)
    x = np.concatenate([intrinsics_vector(camera.with_(f=ts.camera.f, kappa=ts.camera.kappa), ni), np.zeros(3),
                        H[:3, 3]])
    return model, x


def _tcp_of(result):
    """``tcp(camera, C_H_W, uv=None)``: the TCP [mm, camera axes] by ``solve_pcc`` from the found fingertips (pixels
    ``uv`` (n, 2) when given)."""
    ft, cal = result.fingertips, result.calibration
    found = np.asarray(ft.found, bool)
    pG = cal.points_G[cal.state][found]

    def tcp(camera: CameraModel, C_H_W, uv=None) -> np.ndarray:
        return solve_pcc(ft.uv[found] if uv is None else uv, pG, C_H_W, camera).C_H_G[:3, 3]

    return tcp


def camera_file_fit(result, camera: CameraModel, source: str = "the camera file") -> dict:
    """Does ``camera`` (from a camera file) fit an off-line calibration's picture (``OfflineResult``), the plate's pose
    alone fitted? {rms_px, own_rms_px (f and kappa the picture's), excess_px, limit_px, fits, refusal (naming
    ``source``; None when it fits)}."""
    model, x = _one_view(result, camera, ni=6)
    x[:6] = intrinsics_vector(camera, 6)
    own = float(result.tsai.rms_px)
    try:
        res = levenberg_marquardt(lambda y: model.residuals(np.r_[x[:6], y]), x[6:],
                                  lambda y: model.jacobian(np.r_[x[:6], y])[:, 6:])
        rms = float(np.sqrt(np.mean(np.square(res.residuals.reshape(2, -1)).sum(0))))
    except CalibrationError:
        rms = float("inf")
    excess = rms - own
    fits = bool(excess <= CAMERA_FILE_MAX_EXCESS_PX)
    refusal = None if fits else (
        f"{source} does not fit this picture: the plate's disc residual with its camera (f {camera.f:.1f} px) is "
        f"{rms:.3f} px against {own:.3f} px with the picture's own f ({result.tsai.camera.f:.1f} px) and kappa, more "
        f"than {CAMERA_FILE_MAX_EXCESS_PX} px over: it was measured on another camera or lens setting")
    return {"rms_px": rms, "own_rms_px": own, "excess_px": excess, "limit_px": CAMERA_FILE_MAX_EXCESS_PX,
            "fits": fits, "refusal": refusal}


def camera_check(result, cell, camera: CameraModel | None = None) -> dict:
    """Does an off-line calibration's picture show the assumed camera's (default the cell's) centre or aspect wrong
    (chi-square over ``CAMERA_CHI2_LIMIT``) and costly (the TCP's move when recalibrated with its own)? {significant,
    chi2, centre_offset_px, aspect, aspect_sigma, centre_sigma_px, tcp_shift_mm [3], costly, warning (or None)}.
    """
    cam0 = camera or cell.camera.guess()
    model, x0 = _one_view(result, cam0)
    out = {"significant": False, "costly": False, "warning": None}
    try:
        res = levenberg_marquardt(model.residuals, x0, model.jacobian, normal=True)
    except (CalibrationError, np.linalg.LinAlgError) as exc:
        out["why"] = f"the one-view fit failed: {exc}"
        return out
    d = res.x[2:5] - np.array([cam0.cx, cam0.cy, cam0.aspect])
    C3 = res.covariance(normal=True)[2:5, 2:5]
    chi2 = wald_chi2(d, C3) if res.converged and np.all(np.isfinite(C3)) else np.nan
    if not np.isfinite(chi2):  # not converged, or a singular covariance
        out["why"] = "one picture does not determine the centre and the aspect"
        return out
    sig = np.sqrt(np.diag(C3))
    out.update(chi2=chi2, centre_offset_px=[float(d[0]), float(d[1])], centre_sigma_px=[float(sig[0]), float(sig[1])],
               aspect=float(res.x[4]), aspect_sigma=float(sig[2]), assumed_aspect=float(cam0.aspect),
               significant=bool(chi2 > CAMERA_CHI2_LIMIT))
    if not out["significant"]:
        return out
    try:
        own = cam0.with_(cx=float(res.x[2]), cy=float(res.x[3]), aspect=float(res.x[4]))
        ts = calibrate_coplanar(result.discs.p_W, own.deskew_pixels(result.disc_uv_corrected), cx=own.cx, cy=own.cy,
                                aspect=own.aspect, mode="full", width=cam0.width, height=cam0.height)
        shift = _tcp_of(result)(ts.camera.with_(skew=cam0.skew), ts.C_H_W) - result.calibration.C_H_G[:3, 3]
    except CalibrationError as exc:
        out["why"] = f"recalibrating with the picture's own centre failed: {exc}"
        return out
    across, along = float(np.hypot(shift[0], shift[1])), float(abs(shift[2]))
    out.update(tcp_shift_mm=[float(v) for v in shift],
               costly=bool(across > TARGET_ACROSS_MM or along > TARGET_ALONG_MM))
    if out["costly"]:
        out["warning"] = (
            f"the picture shows the camera's principal point {np.hypot(d[0], d[1]):.1f} px from the assumed "
            f"({cam0.cx:.1f}, {cam0.cy:.1f}) (offset {d[0]:+.1f}, {d[1]:+.1f} px, +- {sig[0]:.1f}, {sig[1]:.1f}) "
            f"and its aspect {res.x[4]:.4f} +- {sig[2]:.4f} instead of {cam0.aspect:.4f}; that moves the TCP by "
            f"{across:.3f} mm across and {along:.3f} mm along the optical axis (targets {TARGET_ACROSS_MM} and "
            f"{TARGET_ALONG_MM} mm): measure the camera with 'selfview intrinsics' and calibrate with "
            "--camera CAMERA.yaml"
        )
    return out


def tcp_sigma(result, cell, camera_cov3: np.ndarray | None = None, camera_error: dict | None = None) -> dict:
    """1-sigma [mm, camera axes] of an off-line calibration's TCP by central differences. Parts: ``picture`` (disc
    noise), ``camera_file`` (``camera_cov3`` (3, 3) of cx, cy, aspect, or (4, 4) with the skew; None: exact),
    ``corners`` (at least ``CORNER_FLOOR_PX``), ``camera_model`` (``camera_error``'s ``tcp_shift_mm`` when significant).
    Returns {tcp_sigma_mm [3], parts}; ``ValueError`` for a ``camera_cov3`` of another shape.
    """
    cal = result.calibration
    cam = cal.camera
    model, x = _one_view(result, cam, ni=6)
    r = model.residuals(x)
    J = model.jacobian(x)
    p_idx = np.r_[0:2, 6:12]
    Jp, Jt = J[:, p_idx], J[:, 2:6]
    s2 = float(r @ r) / max(len(r) - len(p_idx), 1)
    Ninv = np.linalg.inv(Jp.T @ Jp)
    dp_dt = -Ninv @ Jp.T @ Jt
    R0 = result.tsai.C_H_W[:3, :3]
    ft = result.fingertips
    found = np.asarray(ft.found, bool)
    pcc = _tcp_of(result)

    def tcp(xv, uv=None):
        return pcc(with_intrinsics(cam, xv[:6]), make_H(R_from_rotvec(xv[6:9]) @ R0, xv[9:12]), uv)

    G = central_differences(tcp, x, np.r_[STEP[0] * x[0], STEP[1:], POSE_STEP])  # (3, 12)
    Gp = G[:, p_idx]
    parts = {"picture": Gp @ (s2 * Ninv) @ Gp.T}
    if camera_cov3 is not None:
        C = np.asarray(camera_cov3, float)
        if C.shape not in ((3, 3), (4, 4)):
            raise ValueError(f"tcp_sigma: camera_cov3: expected (3, 3) or (4, 4), got {C.shape}")
        Gt = (G[:, 2:6] + Gp @ dp_dt)[:, : len(C)]
        parts["camera_file"] = Gt @ C @ Gt.T
    uv = ft.uv[found]
    n_edge = ft.n_edge_points[found] if ft.n_edge_points is not None else np.full(len(uv), 20)
    sc = np.nan_to_num(ft.edge_rms_px[found], nan=0.1) / np.sqrt(np.maximum(np.asarray(n_edge, float), 2) / 2)
    Gc = central_differences(lambda u: tcp(x, u.reshape(-1, 2)), uv.ravel(), np.full(uv.size, 1e-3))  # (3, 2n)
    parts["corners"] = np.zeros((3, 3))
    for j, g in enumerate(Gc.T):  # u, v of each corner in turn
        parts["corners"] += np.outer(g, g) * max(sc[j // 2], CORNER_FLOOR_PX[j % 2]) ** 2
    if (camera_error or {}).get("significant") and camera_error.get("tcp_shift_mm") is not None:
        shift = camera_error["tcp_shift_mm"]
        parts["camera_model"] = np.outer(shift, shift)

    def sd(c):
        return [float(v) for v in np.sqrt(np.clip(np.diag(c), 0, None))]

    return {"tcp_sigma_mm": sd(sum(parts.values())), "parts": {k: sd(c) for k, c in parts.items()}}
