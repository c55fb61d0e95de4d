"""Off-line calibration from one picture of the gripper parked on the plate of discs (paper, section 3): Tsai's method
gives f, kappa and ``C_H_W``, the Plane Coincidence Constraint ``W_H_G``, and ``C_H_G = C_H_W W_H_G``."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field

import numpy as np

from selfview.files.calfile import Calibration
from selfview.maths.camera import CameraModel
from selfview.files.cell import POINT_NAMES, Cell
from selfview.files.io_safe import uint16_to_u8
from selfview.measurement.discs import DiscDetections
from selfview.measurement.plates import correct_plate_bias, detect_plate
from selfview.errors import CalibrationError, ImageError
from selfview.measurement.fingertips import FingertipResult
from selfview.measurement.fingers import find_fingertips
from selfview.maths.geometry import inv_H, make_H, rot_z
from selfview.estimation.pcc import PCCResult, measure_points_G, points_G_for_state, solve_pcc
from selfview.estimation.tsai import TsaiResult, calibrate_coplanar

__all__ = ["OfflineResult", "check_picture", "calibrate_offline", "predict_parked_C_H_G"]

#: A picture whose grey levels spread less than this is blank (lens cap, no light, no signal).
MIN_CONTRAST_GRAY = 20.0
#: Largest angle [deg] between the plate's normal and the mount guess's approach axis with the gripper parked on it.
MAX_PLANE_DISAGREEMENT_DEG = 25.0
#: Warn when the PCC residual exceeds this multiple of the picture's noise at the TCP (a corner off its place bends the
#: rectangle); the simulated cell gives at most 3.1, 4.9 with pictures 1.5 px out of focus.
PCC_NOISE_FACTOR = 6.0


@dataclass
class OfflineResult:
    """One off-line calibration's findings: ``calibration`` is saved, ``warnings`` what the picture could not tell."""

    calibration: Calibration
    tsai: TsaiResult
    discs: DiscDetections
    disc_uv_corrected: np.ndarray
    fingertips: FingertipResult
    pcc: PCCResult
    dims: dict | None
    timings_ms: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def disc_residuals_px(self) -> np.ndarray:
        """(N, 2) [px] each disc's model projection minus the bias-corrected, deskewed centre Tsai's fit used."""
        return -np.asarray(self.tsai.residuals_px, float)

    def summary(self) -> dict:
        """The figures a person or a script reads (plain types, units in the key names)."""
        cal = self.calibration
        return {
            "f": cal.camera.f, "kappa": cal.camera.kappa, "principal_point": [cal.camera.cx, cal.camera.cy],
            "C_H_W": cal.C_H_W.tolist(), "C_H_W_known": self.discs.origin_pinned, "C_H_G": cal.C_H_G.tolist(),
            "points_G": {nm: [float(v) for v in p] for nm, p in zip(POINT_NAMES, cal.points_G[cal.state])},
            "rms_px": float(self.tsai.rms_px), "max_px": float(self.tsai.max_px),
            "discs_used": int(len(self.discs.uv)),
            "corners_found": [nm for nm, ok in zip(POINT_NAMES, self.fingertips.found) if ok],
            "pcc_rms_mm": float(self.pcc.rms_mm), "state": cal.state,
            "timings_ms": {k: round(v, 2) for k, v in self.timings_ms.items()}, "warnings": list(self.warnings),
        }


def check_picture(image, width: int, height: int) -> np.ndarray:
    """The picture as a 2-D uint8 array (a uint16 one by ``uint16_gain``); ``ImageError`` naming what is wrong."""
    if image is None:
        raise ImageError("no picture (the grabber or the file gave nothing)")
    img = np.asarray(image)
    if img.ndim != 2:
        raise ImageError(f"picture has shape {img.shape}; expected a 2-D grey picture (no colour channels)")
    if img.shape != (height, width):
        raise ImageError(f"picture is {img.shape[1]}x{img.shape[0]} pixels; the cell's camera gives {width}x{height}")
    img = uint16_to_u8(img)  # a 10- to 16-bit camera's
    if img.dtype != np.uint8:
        raise ImageError(f"picture has {img.dtype} pixels; expected 8- or 16-bit grey")
    lo, hi = np.percentile(img[::4, ::4], [1, 99])
    if hi - lo < MIN_CONTRAST_GRAY:
        raise ImageError(f"picture is blank (grey levels {lo:.0f}..{hi:.0f}): check the light, the lens cap and the "
                         "video signal")
    return img


def predict_parked_C_H_G(C_H_W: np.ndarray, C_H_G_guess: np.ndarray) -> np.ndarray:
    """(4, 4) the parked gripper: the rough ``C_H_G_guess`` put into the plate's plane (eq. 5-7; its turn about z and
    in-plane position kept). Raises ``CalibrationError`` if the planes differ by over ``MAX_PLANE_DISAGREEMENT_DEG``."""
    W_H_Gg = inv_H(C_H_W) @ np.asarray(C_H_G_guess, float)
    tilt = np.degrees(np.arccos(np.clip(W_H_Gg[2, 2], -1.0, 1.0)))
    if tilt > MAX_PLANE_DISAGREEMENT_DEG:
        raise CalibrationError(f"the plate's plane is {tilt:.0f} deg from the gripper's contact plane of the mount "
                               "guess: the gripper is not parked on the plate, or the mount guess is wrong")
    W_H_G = rot_z(np.arctan2(W_H_Gg[1, 0], W_H_Gg[0, 0]))
    W_H_G[:2, 3] = W_H_Gg[:2, 3]
    return C_H_W @ W_H_G


def _parked_fingertips(img, camera: CameraModel, C_H_G_pred, cell: Cell, gap: float, search_px: float,
                       measurement: str) -> tuple[FingertipResult, str]:
    """The fingertips' corners and how measured ('corners' or 'model'); ``CalibrationError`` for fewer than 2."""
    how = {"corners": False, "model": True, "auto": "auto"}[measurement]
    ft = find_fingertips(img, camera, C_H_G_pred, cell.gripper, gap, search_px=search_px, model=how)
    measured_by = "corners" if ft.quality is None else "model"
    found = np.asarray(ft.found, bool)
    if found.sum() < 2:
        why = "; ".join(f"{nm}: {r}" for nm, r, ok in zip(POINT_NAMES, ft.reasons, found) if not ok)
        raise CalibrationError(f"only {int(found.sum())} fingertip corner(s) found, the PCC needs at least 2 ({why})")
    return ft, measured_by


def _gripper_points(ft: FingertipResult, camera: CameraModel, C_H_W, cell: Cell, state: str, points: str):
    """(dims or None, {state: (6, 3) points in G [mm]}): measured in the picture if asked and the inner four found."""
    found = np.asarray(ft.found, bool)
    if points == "measured" and found[:4].all():
        p_W, _ = camera.backproject_to_plane(ft.uv[found], C_H_W, 0.0)
        full = np.full((6, 3), np.nan)
        full[found] = p_W
        dims = measure_points_G(full, found)
        return dims, points_G_for_state(dims, state, cell.gripper)
    return None, {s: cell.gripper.points_G(s) for s in cell.gripper.states}


def _tsai_bias_corrected(det, nominal: CameraModel, cell: Cell, mode: str):
    """(``TsaiResult``, corrected pixels) of Tsai's fit refitted with the disc bias corrected at its first pose."""
    kw = dict(cx=nominal.cx, cy=nominal.cy, aspect=nominal.aspect, mode=mode, width=cell.camera.width,
              height=cell.camera.height)
    # Tsai's method has no skew: take it off the pixels (the same rays), give it back to the result
    ts = calibrate_coplanar(det.p_W, nominal.deskew_pixels(det.uv), **kw)
    # the image of a disc's centre is not the centroid of its ellipse
    uv_c = correct_plate_bias(det, ts.camera.with_(skew=nominal.skew), ts.C_H_W, cell.plate)
    return calibrate_coplanar(det.p_W, nominal.deskew_pixels(uv_c), **kw), uv_c


def _residuals(mode: str, ts, det, ft: FingertipResult, pcc, dims, measured_by: str, camera_file, noise_mm: float,
               warnings: list[str]) -> dict:
    """The calibration file's ``residuals``: Tsai's, the points used, the PCC's, the picture's noise, the warnings."""
    found = np.asarray(ft.found, bool)
    return {
        "tsai_mode": mode, "rms_px": float(ts.rms_px), "max_px": float(ts.max_px), "discs_used": int(len(det.uv)),
        "corners_found": [nm for nm, ok in zip(POINT_NAMES, found) if ok],
        "corner_edge_rms_px": {nm: float(ft.edge_rms_px[i]) for i, nm in enumerate(POINT_NAMES) if found[i]},
        "pcc_rms_mm": float(pcc.rms_mm), "pcc_q_norm": float(pcc.q_norm), "pcc_noise_mm": float(noise_mm),
        "points_from": "picture" if dims is not None else "cell", "corners_measured_by": measured_by,
        "plate_origin": "pinned" if det.origin_pinned else "ambiguous", "disc_pedestal_grey": float(det.pedestal),
        **({"warnings": warnings} if warnings else {}),
        **({"camera_file": dict(camera_file)} if camera_file else {}),
    }


def _check_offline_args(cell: Cell, camera: CameraModel | None, points: str, measurement: str) -> CameraModel:
    """``calibrate_offline``'s options checked; the starting camera (``camera``, else the cell's nominal)."""
    cs = cell.camera
    if camera is not None:
        camera.check_size(cs.width, cs.height)
    if points not in ("measured", "cell"):
        raise CalibrationError(f"points: expected 'measured' or 'cell', got {points!r}")
    if measurement not in ("auto", "corners", "model"):
        raise CalibrationError(f"measurement: expected 'auto', 'corners' or 'model', got {measurement!r}")
    return cs.guess() if camera is None else camera


def _mount_guess(cell: Cell, C_H_G_guess) -> np.ndarray:
    """``C_H_G_guess``, else the cell's mount guess; ``ValueError`` unless a finite (4, 4) transform."""
    guess = cell.mount_guess_C_H_G if C_H_G_guess is None else np.asarray(C_H_G_guess, float)
    if guess.shape != (4, 4) or not np.all(np.isfinite(guess)):
        raise ValueError(f"C_H_G_guess: expected a finite (4, 4) transform, got shape {guess.shape}")
    return guess


def calibrate_offline(image, cell: Cell, *, state: str | None = None, mode: str = "full",
                      C_H_G_guess: np.ndarray | None = None, points: str = "measured", search_px: float = 60.0,
                      image_sha256: str | None = None, camera: CameraModel | None = None,
                      camera_file: dict | None = None, measurement: str = "auto") -> OfflineResult:
    """Off-line calibration of one picture ``image`` (H, W) uint8 of the gripper parked in ``state`` (default
    ``calibrate_in``). ``mode`` Tsai's refinement; ``points`` 'measured' (the paper's way) or 'cell': where the G
    coordinates come from. ``camera`` a measured camera whose principal point, aspect and skew replace the nominal ones,
    ``camera_file`` {path, sha256} its file, recorded in the residuals. ``measurement``: 'corners' the corner search,
    'model' the fingers' silhouette fit, 'auto' the model only where the search misses a corner.
    Raises ``ImageError`` (unusable picture), ``ConfigError`` (a camera for another picture size), ``CalibrationError``
    (too few discs or corners, degenerate) or ``ValueError`` (a bad ``C_H_G_guess``)."""
    t0 = time.perf_counter()
    timings = {}
    nominal = _check_offline_args(cell, camera, points, measurement)
    img = check_picture(image, cell.camera.width, cell.camera.height)
    state = state or cell.gripper.calibrate_in
    gap = cell.gripper.gap(state)

    det = detect_plate(img, cell.plate, camera=nominal)
    timings["discs"] = (time.perf_counter() - t0) * 1e3

    t = time.perf_counter()
    ts, uv_c = _tsai_bias_corrected(det, nominal, cell, mode)
    camera: CameraModel = ts.camera.with_(skew=nominal.skew)
    timings["tsai"] = (time.perf_counter() - t) * 1e3

    t = time.perf_counter()
    guess = _mount_guess(cell, C_H_G_guess)
    ft, measured_by = _parked_fingertips(img, camera, predict_parked_C_H_G(ts.C_H_W, guess), cell, gap, search_px,
                                         measurement)
    timings["fingertips"] = (time.perf_counter() - t) * 1e3
    found = np.asarray(ft.found, bool)

    t = time.perf_counter()
    dims, per_state = _gripper_points(ft, camera, ts.C_H_W, cell, state, points)
    pG = per_state[state]
    names = [nm for nm, ok in zip(POINT_NAMES, found) if ok]
    pcc = solve_pcc(ft.uv[found], pG[found], ts.C_H_W, camera, names)
    timings["pcc"] = (time.perf_counter() - t) * 1e3
    timings["total"] = (time.perf_counter() - t0) * 1e3

    noise_mm = _picture_noise_mm(ft, found, camera, pcc.C_H_G)
    warnings = _warnings(det, pcc, noise_mm, ft)
    sha = image_sha256 or hashlib.sha256(np.ascontiguousarray(img).tobytes()).hexdigest()
    residuals = _residuals(mode, ts, det, ft, pcc, dims, measured_by, camera_file, noise_mm, warnings)
    cal = Calibration(camera=camera, C_H_W=ts.C_H_W, C_H_G=make_H(pcc.C_H_G[:3, :3], pcc.C_H_G[:3, 3]),
                      points_G=per_state, state=state, residuals=residuals, image_sha256=sha, cell_sha256=cell.sha256)
    return OfflineResult(calibration=cal, tsai=ts, discs=det, disc_uv_corrected=uv_c, fingertips=ft, pcc=pcc, dims=dims,
                         timings_ms=timings, warnings=warnings)


def _picture_noise_mm(ft: FingertipResult, found: np.ndarray, camera: CameraModel, C_H_G: np.ndarray) -> float:
    """The picture's noise at the TCP's depth [mm]: the corners' median edge scatter [px], at least 0.02 px."""
    rms_px = float(np.median(np.asarray(ft.edge_rms_px, float)[found])) if found.any() else np.nan
    rms_px = max(rms_px if np.isfinite(rms_px) else 0.0, 0.02)
    return rms_px * float(C_H_G[2, 3]) / float(camera.f)


def _warnings(det: DiscDetections, pcc: PCCResult, noise_mm: float, ft: FingertipResult) -> list[str]:
    """What the picture could not tell: the plate's origin, a PCC residual far above ``noise_mm``, a corner left out."""
    out = []
    if not det.origin_pinned:
        out.append("the plate's origin is not pinned by the picture, so C_H_W is not known (it may be off by whole "
                    "pitches; C_H_G does not depend on it): " + "; ".join(det.ambiguous.values()))
    if pcc.rms_mm > PCC_NOISE_FACTOR * noise_mm:
        out.append(f"the PCC residual {pcc.rms_mm:.3f} mm is {pcc.rms_mm / noise_mm:.0f} times what the picture's "
                   f"noise gives ({noise_mm:.4f} mm): a fingertip corner is measured off its place (on a printed disc, "
                   "a mark or a shadow's edge?), or the gripper points used are not this gripper's; park the gripper "
                   "elsewhere on the plate and calibrate again")
    # also when the model measured the corners: its nominal boxes miss a real finger's faces by tenths of a pixel
    out += [f"the fingertip corner {nm} was left out of the corner search: {r}"
            + ("; the fingers' model measured the corners instead" if ft.found[POINT_NAMES.index(nm)] else "")
            for nm, r in ft.left_out.items()]
    return out
