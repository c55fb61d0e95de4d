"""On-line calibration from one picture of the fingertips, as ``selfview track`` and a lab script run it.

    from selfview.calfile import load_calibration
    from selfview.procedures.tracking import track_picture
    res = track_picture(picture, load_calibration("cal.yaml"), cell, method="4P-I")
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from selfview.errors import CalibrationError, ConfigError

if TYPE_CHECKING:  # the command line reads METHOD_CHOICES without loading the measurement
    from selfview.calfile import Calibration
    from selfview.cell import Cell
    from selfview.fingertips import FingertipResult

#: what ``track_picture`` takes as ``method``: an on-line method, the model's own estimate, or the policy
METHOD_CHOICES = ("3P-U", "4P-U", "5P-U", "3P-I", "4P-I", "5P-I", "4P-R", "5P-R", "E", "auto")


@dataclass
class TrackResult:
    """``summary`` the JSON-ready figures (method, C_H_G, delta_deg, d_mm, decision, reason, points_used,
    rms_px, points_found, quality); ``C_H_G`` (4, 4) the new transform (None: an alarm, nothing to apply);
    ``fingertips`` the measurement; ``points_G`` (6, 3) and ``gap_mm`` of the state in the picture."""

    summary: dict
    C_H_G: np.ndarray | None
    fingertips: FingertipResult
    points_G: np.ndarray
    gap_mm: float


def track_picture(image, cal: Calibration, cell: Cell, *, method: str = "4P-U", state: str | None = None,
                  measure: str = "model") -> TrackResult:
    """How far the camera moved on its mount, from one picture: the fingertips measured near where
    ``cal.C_H_G`` predicts them (``measure`` 'model' or 'corners'), then ``method`` (``METHOD_CHOICES``;
    'auto' the cell's monitor policy). Raises ``ConfigError`` (an unknown state or method; E without the
    model), ``CalibrationError`` (fingertips not found), ``ImageError`` (a picture of the wrong size)."""
    from selfview.cell import POINT_NAMES
    from selfview.fingers import find_fingertips
    from selfview.offline import check_picture
    from selfview.online import estimate
    from selfview.pcc import jaw_gap_of
    from selfview.policy import Monitor

    if method not in METHOD_CHOICES:
        raise ConfigError(f"method {method!r}: expected one of {', '.join(METHOD_CHOICES)}")
    state = state or cal.state
    if state not in cal.points_G:
        raise ConfigError(f"--state {state!r}: the calibration has points for {', '.join(cal.points_G)}")
    img = check_picture(image, cal.camera.width, cal.camera.height)
    pG = cal.points_G[state]
    gap = jaw_gap_of(pG)
    ft = find_fingertips(img, cal.camera, cal.C_H_G, cell.gripper, gap, model=measure == "model")
    found_names = [nm for nm, ok in zip(POINT_NAMES, ft.found) if ok]
    if method == "auto":
        if ft.lost is not None or int(np.sum(ft.found)) < 3:
            n = int(np.sum(ft.found))
            raise CalibrationError(f"fingertips not found: {ft.lost or f'{n} point(s) found, 3 needed'}")
        mon = Monitor(cal.C_H_G, cal.camera, pG, cell.monitor, max_missed_frames=1)  # one picture: no next frame
        d = mon.step(ft.uv, ft.found, lost=ft.lost)
        out = {
            "method": d.method or "auto",
            "C_H_G": np.asarray(d.C_H_G).tolist(),
            "delta_deg": d.delta_deg,
            "d_mm": d.d_mm,
            "decision": d.action,
            "reason": d.reason,
            "points_used": list(d.points_used or []),
            "rms_px": d.rms_px,
            "points_found": found_names,
            "quality": ft.quality,
        }
        new = None if d.action == "alarm" else np.asarray(d.C_H_G, float)
    else:
        if ft.lost is not None:
            raise CalibrationError(f"fingertips not found: {ft.lost}")
        if method == "E" and ft.C_H_G is None:
            raise ConfigError("--method E is the model's own estimate: it needs --measure model")
        est = estimate(method, cal.C_H_G, pG, ft.uv, ft.found, cal.camera, model_C_H_G=ft.C_H_G,
                       model_rms_px=float((ft.quality or {}).get("rms_px", float("nan"))))
        decision = "recalibrate" if method.endswith("R") else "update"
        out = {
            "method": method,
            "C_H_G": est.C_H_G.tolist(),
            "C_H_G_orthonormal": est.C_H_G_orth.tolist(),
            "delta_deg": est.delta_deg,
            "d_mm": est.d_mm,
            "decision": decision,
            "points_used": list(est.points_used),
            "rms_px": est.rms_px,
            "points_found": found_names,
            "quality": ft.quality,
        }
        new = est.C_H_G_orth
    return TrackResult(out, new, ft, pG, gap)
