"""One call per task for lab scripts and ``selfview calibrate`` / ``track``: ``calibrate_picture`` (off-line, with
uncertainty and verdict) and ``track`` (on-line), each from one picture, taking files or loaded objects."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from selfview.files.calfile import Calibration, load_calibration, save_calibration
from selfview.maths.camera import CameraModel
from selfview.files.cell import POINT_NAMES, Cell, default_cell_path, load_cell
from selfview.files.io_safe import read_picture
from selfview.errors import CalibrationError, ConfigError
from selfview.maths.geometry import hat, pose_difference
from selfview.estimation.online import METHODS as ONLINE_METHODS, MODEL_METHOD

if TYPE_CHECKING:  # the command line reads METHODS without loading the measurement
    from selfview.measurement.fingertips import FingertipResult
    from selfview.estimation.offline import OfflineResult

__all__ = ["PictureCalibration", "TrackResult", "assess_offline", "calibrate_picture", "calibration_change", "track",
           "tcp_sigma_after", "RMS_LIMIT_PX"]

#: A disc residual RMS [px] above this says the picture is out of focus or badly lit.
RMS_LIMIT_PX = 0.5
#: ``track``'s methods: an on-line method, the model's own estimate 'E', or the policy 'auto'
METHODS = (*ONLINE_METHODS, MODEL_METHOD, "auto")


def _cell(cell) -> Cell:
    return cell if isinstance(cell, Cell) else load_cell(default_cell_path() if cell is None else cell)


def _picture(image) -> tuple[np.ndarray, str | None]:
    """(grey uint8 picture, SHA-256 of its file or None for an array)."""
    return read_picture(image) if isinstance(image, (str, Path)) else (np.asarray(image), None)


@dataclass
class PictureCalibration:
    """An off-line calibration: ``calibration`` what ``save`` writes; ``offline`` every intermediate; ``C_H_G`` (4, 4)
    gripper -> camera [mm]; ``tcp_sigma_mm`` the TCP's 1-sigma along camera x, y, z [mm] of all ``sigma_parts_mm``;
    ``verdict`` 'go'/'no-go', ``reason``, ``warnings``; ``camera_check``, ``camera_file_fit`` the checks behind them."""

    calibration: Calibration
    offline: OfflineResult
    tcp_sigma_mm: list
    sigma_parts_mm: dict
    verdict: str
    reason: str
    warnings: list = field(default_factory=list)
    camera_check: dict = field(default_factory=dict)
    camera_file_fit: dict | None = None

    @property
    def C_H_G(self) -> np.ndarray:
        return self.calibration.C_H_G

    @property
    def go(self) -> bool:
        return self.verdict == "go"

    def save(self, path, *, force: bool = False) -> Path | None:
        """Write to ``path`` atomically, returning the history copy of the previous file; ``CalibrationError`` when
        the camera file does not fit the picture, unless ``force``."""
        fit = self.camera_file_fit
        if fit and not fit["fits"] and not force:
            raise CalibrationError(f"{fit['refusal']}; nothing written")
        return save_calibration(self.calibration, path)

    def to_dict(self) -> dict:
        """JSON-ready figures: ``OfflineResult.summary`` and the sigma, verdict, warnings."""
        return {**self.offline.summary(), "tcp_sigma_mm": list(self.tcp_sigma_mm),
                "tcp_sigma_parts_mm": dict(self.sigma_parts_mm), "verdict": self.verdict, "reason": self.reason,
                "warnings": list(self.warnings),
                "camera_check": {k: v for k, v in self.camera_check.items() if k != "warning"},
                "camera_file_fit": self.camera_file_fit}


def calibration_change(previous: Calibration, new: Calibration) -> dict:
    """From ``previous`` to ``new``: TCP move [mm, camera axes], rotation [deg], f [px], kappa; same picture, state."""
    d = np.asarray(new.C_H_G, float)[:3, 3] - np.asarray(previous.C_H_G, float)[:3, 3]
    deg, mm = pose_difference(new.C_H_G, previous.C_H_G)
    return {"previous_created": previous.created, "tcp_moved_mm": [float(v) for v in d], "tcp_moved_norm_mm": mm,
            "rotated_deg": deg, "f_changed_px": float(new.camera.f - previous.camera.f),
            "kappa_changed": float(new.camera.kappa - previous.camera.kappa),
            "same_picture": bool(new.image_sha256 and new.image_sha256 == previous.image_sha256),
            "same_state": new.state == previous.state}


def assess_offline(res: OfflineResult, cell: Cell, camera: CameraModel | None = None, camera_cov3=None,
                   camera_name: str | None = None, fit: dict | None = None) -> PictureCalibration:
    """Uncertainty and verdict of off-line calibration ``res`` (sigma recorded in its residuals for ``track``).
    ``camera`` the camera used (None: the cell's), ``camera_cov3`` its file's centre and aspect (skew) covariance,
    ``fit`` its ``camera_file_fit`` (None: computed). No-go: the camera file does not fit, a corner is missing, disc
    rms > ``RMS_LIMIT_PX``, or the TCP's sigma over ``TARGET_ACROSS_MM`` across or ``TARGET_ALONG_MM`` along."""
    from selfview.estimation.intrinsics import (TARGET_ACROSS_MM, TARGET_ALONG_MM, camera_check, camera_file_fit,
                                                tcp_sigma)

    if camera is not None and fit is None:
        fit = camera_file_fit(res, camera, f"the camera file {camera_name}" if camera_name else "the camera")
    chk = camera_check(res, cell, camera)
    sig = tcp_sigma(res, cell, camera_cov3, camera_error=chk)
    sg = sig["tcp_sigma_mm"]
    res.calibration.residuals["tcp_sigma_mm"] = [float(v) for v in sg]
    warnings = list(res.warnings)  # what the picture cannot tell (the plate's origin, a PCC residual over noise)
    if fit and not fit["fits"]:
        warnings.append(f"{fit['refusal']}; measure this camera with 'selfview intrinsics'")
    if chk.get("warning"):
        w = chk["warning"]
        if camera is not None:
            w = f"the picture disagrees with the camera file {camera_name or ''}: {w}".replace(" :", ":")
        warnings.append(w)
    s = res.summary()
    missing = [nm for nm in POINT_NAMES if nm not in s["corners_found"]]
    across = math.hypot(sg[0], sg[1])
    if fit and not fit["fits"]:
        go, why = False, fit["refusal"]
    elif missing:
        go, why = False, (f"{len(missing)} fingertip corner(s) not found ({', '.join(missing)}): C_H_G rests on "
                          "fewer points")
    elif s["rms_px"] > RMS_LIMIT_PX:
        go, why = False, f"disc residual rms {s['rms_px']:.3f} px above {RMS_LIMIT_PX} px: check focus and light"
    elif across > TARGET_ACROSS_MM or sg[2] > TARGET_ALONG_MM:
        worst = max(sig["parts"], key=lambda k: max(sig["parts"][k]))
        go, why = False, (f"the TCP's 1-sigma is {across:.3f} mm across and {sg[2]:.3f} mm along the optical axis, "
                          f"over the targets {TARGET_ACROSS_MM} and {TARGET_ALONG_MM} mm (largest part: {worst})")
        if worst == "camera_model":
            why += "; measure the camera with 'selfview intrinsics' and calibrate with --camera CAMERA.yaml"
    else:
        go, why = True, (f"all 6 corners, {s['discs_used']} discs, residual rms {s['rms_px']:.3f} px (max "
                         f"{s['max_px']:.3f} px), TCP 1-sigma {across:.4f} mm across, {sg[2]:.4f} mm along")
    return PictureCalibration(calibration=res.calibration, offline=res, tcp_sigma_mm=sg, sigma_parts_mm=sig["parts"],
                              verdict="go" if go else "no-go", reason=why, warnings=warnings, camera_check=chk,
                              camera_file_fit=fit)


def calibrate_picture(image, cell=None, camera=None, *, state: str | None = None, mode: str = "full",
                      points: str = "measured") -> PictureCalibration:
    """Off-line calibration of one picture of the gripper parked on the plate; nothing written (``save`` the result).
    ``image`` a file or (H, W) uint8 array; ``cell`` a file or ``Cell`` (None: the reference); ``camera`` a ``selfview
    intrinsics`` file or ``CameraModel`` (None: the cell's); the rest as ``calibrate_offline``. Raises ``ImageError``,
    ``ConfigError`` / ``CalibrationFileError`` (cell or camera file), ``CalibrationError`` (too few discs, corners)."""
    from selfview.estimation.offline import calibrate_offline

    c = _cell(cell)
    img, sha = _picture(image)
    cam = cov3 = camera_file = name = None
    if isinstance(camera, CameraModel):
        cam = camera
    elif camera is not None:
        from selfview.files.camfile import load_camera_file

        cf = load_camera_file(camera)
        cf.check_size(c.camera.width, c.camera.height, f"camera file {camera}")
        cam, cov3, name = cf.camera, cf.centre_covariance(), str(camera)
        camera_file = {"path": name, "sha256": cf.file_sha256}
    res = calibrate_offline(img, c, state=state, mode=mode, points=points, image_sha256=sha, camera=cam,
                            camera_file=camera_file)
    return assess_offline(res, c, cam, cov3, name)


@dataclass
class TrackResult:
    """One on-line estimate: ``C_H_G`` (4, 4) [mm] (NP-U: eq. 13's, not orthonormal; after an alarm the calibration's);
    ``C_H_G_orthonormal`` the one to use; ``decision`` update/recalibrate/alarm, ``reason``; ``delta_deg``, ``d_mm``
    the camera's move; ``rms_px``; ``tcp_sigma_mm`` the TCP's 1-sigma in camera axes [mm] (with the calibration's),
    None for 3 points or method E; ``points_used``, ``points_found`` names; ``quality``; ``fingertips``."""

    C_H_G: np.ndarray
    method: str
    decision: str
    reason: str
    delta_deg: float
    d_mm: float
    rms_px: float
    tcp_sigma_mm: list | None
    points_used: list
    points_found: list
    quality: dict | None
    fingertips: FingertipResult = field(repr=False)
    C_H_G_orthonormal: np.ndarray | None = None

    def __post_init__(self):
        if self.C_H_G_orthonormal is None:
            self.C_H_G_orthonormal = np.asarray(self.C_H_G, float)

    @property
    def verdict(self) -> str:
        return "no-go" if self.decision == "alarm" else "go"

    def to_dict(self) -> dict:
        return {"method": self.method, "C_H_G": np.asarray(self.C_H_G).tolist(), "delta_deg": self.delta_deg,
               "d_mm": self.d_mm, "decision": self.decision, "reason": self.reason, "verdict": self.verdict,
               "points_used": list(self.points_used), "rms_px": self.rms_px, "tcp_sigma_mm": self.tcp_sigma_mm,
               "points_found": list(self.points_found), "quality": self.quality,
               "C_H_G_orthonormal": np.asarray(self.C_H_G_orthonormal).tolist()}


def tcp_sigma_after(est, H, cal: Calibration) -> list | None:
    """TCP 1-sigma [mm] at ``H`` (4, 4) from motion ``est``'s covariance (rotation [rad], shift [mm]) and ``cal``'s."""
    if est is None or not np.all(np.isfinite(est.covariance)):
        return None
    p = np.asarray(H, float)[:3, 3]
    J = np.hstack([-hat(p), np.eye(3)])
    var = np.diag(J @ est.covariance @ J.T)
    own = cal.residuals.get("tcp_sigma_mm")
    if own is not None:
        var = var + np.square(np.asarray(own, float))
    return [float(v) for v in np.sqrt(np.clip(var, 0, None))]


def track(image, calibration, method: str = "auto", *, cell=None, state: str | None = None,
          measure: str = "model") -> TrackResult:
    """Where the camera moved on its mount, from one picture of the fingertips; nothing written, an alarm is a result.
    ``image``, ``cell`` as ``calibrate_picture``; ``calibration`` a file or ``Calibration``; ``method`` NP-U/NP-I/NP-R,
    E (the fingers' model, ``measure='model'``) or 'auto' (the cell's policy); ``state`` default the calibration's;
    ``measure`` 'model' or 'corners'. Raises ``ImageError``, ``ConfigError`` (unknown method, state, measure),
    ``CalibrationError`` (fingertips not found)."""
    from selfview.measurement.fingers import find_fingertips
    from selfview.estimation.offline import check_picture
    from selfview.estimation.online import estimate
    from selfview.estimation.pcc import jaw_gap_of
    from selfview.estimation.policy import Monitor

    if method not in METHODS:
        raise ConfigError(f"method {method!r}: expected one of {', '.join(METHODS)}")
    if measure not in ("model", "corners"):
        raise ConfigError(f"measure {measure!r}: expected 'model' or 'corners'")
    c = _cell(cell)
    cal = calibration if isinstance(calibration, Calibration) else load_calibration(calibration)
    state = state or cal.state
    if state not in cal.points_G:
        raise ConfigError(f"state {state!r}: the calibration has points for {', '.join(cal.points_G)}")
    img, _ = _picture(image)
    img = check_picture(img, cal.camera.width, cal.camera.height)
    pG = cal.points_G[state]
    ft = find_fingertips(img, cal.camera, cal.C_H_G, c.gripper, jaw_gap_of(pG), model=measure == "model")
    found = [nm for nm, ok in zip(POINT_NAMES, ft.found) if ok]
    n = len(found)
    if ft.lost is not None or (method == "auto" and n < 3):
        raise CalibrationError(f"fingertips not found: {ft.lost or f'{n} point(s) found, 3 needed'}")
    common = dict(points_found=found, quality=ft.quality, fingertips=ft)
    if method == "auto":
        mon = Monitor(cal.C_H_G, cal.camera, pG, c.monitor, max_missed_frames=1)  # one picture: no next frame
        d = mon.step(ft.uv, ft.found, lost=ft.lost)
        H = np.asarray(d.C_H_G, float)
        return TrackResult(H, d.method or "auto", d.action, d.reason, d.delta_deg, d.d_mm, d.rms_px,
                           None if d.action == "alarm" else tcp_sigma_after(d.estimate, H, cal),
                           list(d.points_used or []), **common)
    if method == MODEL_METHOD and ft.C_H_G is None:
        raise ConfigError("method E is the model's own estimate: it needs --measure model (measure='model' in Python)")
    est = estimate(method, cal.C_H_G, pG, ft.uv, ft.found, cal.camera, model_C_H_G=ft.C_H_G,
                   model_rms_px=float(ft.quality.get("rms_px", float("nan"))) if ft.quality else float("nan"))
    decision = "recalibrate" if method.endswith("R") else "update"
    reason = "the fingers' model fitted to the picture" if method == MODEL_METHOD else method
    sigma = None if method == MODEL_METHOD else tcp_sigma_after(est, est.C_H_G_orth, cal)
    return TrackResult(est.C_H_G, method, decision, reason, est.delta_deg, est.d_mm, est.rms_px, sigma,
                       list(est.points_used), C_H_G_orthonormal=est.C_H_G_orth, **common)
