"""The robot's views of the plate for ``selfview.estimation.intrinsics.calibrate_intrinsics``: gripper poses over the
plate, tilted about different axes, lifted and turned, the fingers clear of the plate and the plate in view."""

from __future__ import annotations

import numpy as np

from selfview.errors import CalibrationError
from selfview.maths.geometry import R_from_rotvec, make_H, rot_axis, trans, transform_points

__all__ = ["CLEARANCE_MM", "LIFT_MM", "MAX_TILT_DEG", "plan_view_poses"]

#: Ranges of the planned views: lift of the fingertips off the plate [mm], tilt of the gripper about
#: axes in the plate [deg], turn about the approach axis [deg]; the fingertips stay this far [mm] above
#: the plate; the camera should see the plate this far from square-on [deg].
LIFT_MM = (15.0, 120.0)
MAX_TILT_DEG = 40.0
MAX_TURN_DEG = 90.0
#: With a direction to lean towards (the robot's base), the wrist may move at most this far from it [deg].
LEAN_TOLERANCE_DEG = 60.0
CLEARANCE_MM = 8.0
#: The camera sees the plate at most this far from square-on [deg] (the discs stay measurable).
MAX_CAMERA_TILT_DEG = 48.0


def _fingers_clear(W_H_G, gripper, gap) -> float:
    """Height [mm] of the lowest finger corner above the plate (W's z points into the plate)."""
    corners = []
    for lo, hi in gripper.finger_boxes_G(gap):
        for x in (lo[0], hi[0]):
            for y in (lo[1], hi[1]):
                for z in (lo[2], hi[2]):
                    corners.append((x, y, z))
    return float(-np.max(transform_points(W_H_G, np.array(corners))[:, 2]))


def plan_view_poses(cell, n: int = 12, *, state: str | None = None, C_H_G=None, lean_W=None) -> list[dict]:
    """``n`` gripper poses relative to the plate for the views of ``calibrate_intrinsics``.

    Each is the gripper tilted (at most ``MAX_TILT_DEG``) about an axis in the plate through the point
    under the TCP, lifted along its approach axis (``LIFT_MM``, more when the fingers need it to clear
    the plate by ``CLEARANCE_MM``) and turned about it (at most ``MAX_TURN_DEG``), chosen so that the
    plate's normal, in the gripper's (and so the camera's) frame, is tilted 25-40 deg in directions turning
    round from view to view (views that differ only by a turn about the approach axis or a lift see
    parallel planes, which cannot pin the principal point), at lifts spread over the range, the camera
    (mount ``C_H_G``, default the cell's guess) seeing the plate at most ``MAX_CAMERA_TILT_DEG`` from
    square-on with its centre in the picture. ``lean_W`` (2,): a direction in the plate (x, y of W) towards the robot's base;
    tilts then move the wrist within ``LEAN_TOLERANCE_DEG`` of it (a tilt away from the base takes the
    wrist out of a small arm's reach). Returns [{W_H_G (4, 4), lift_mm, tilt_deg, axis_deg, turn_deg,
    camera_tilt_deg, camera_azimuth_deg}]. Raises ``CalibrationError`` when no pose fits.
    """
    if n < 1:
        raise CalibrationError(f"view plan: expected at least one view, got {n}")
    C_H_G = cell.mount_guess_C_H_G if C_H_G is None else np.asarray(C_H_G, float)
    gap = cell.gripper.gap(state or cell.gripper.calibrate_in)
    cam = cell.camera.guess()
    lean = None if lean_W is None else np.asarray(lean_W, float)[:2] / np.linalg.norm(np.asarray(lean_W, float)[:2])
    cands = []
    for tilt in np.arange(0.0, MAX_TILT_DEG + 1e-9, 5.0):
        for axis in np.arange(0.0, 360.0, 22.5 if tilt else 360.0):
            a = np.radians(axis)
            Rt = rot_axis((np.cos(a), np.sin(a), 0.0), np.radians(tilt))
            if lean is not None and tilt > 0:
                wrist = -Rt[:2, 2]  # where the wrist moves, horizontally
                if wrist @ lean < np.cos(np.radians(LEAN_TOLERANCE_DEG)) * np.linalg.norm(wrist):
                    continue
            for turn in np.arange(-MAX_TURN_DEG, MAX_TURN_DEG + 1e-9, 22.5):
                W_H_C = Rt @ make_H(R_from_rotvec((0, 0, np.radians(turn))), (0, 0, 0)) @ np.linalg.inv(C_H_G)
                d = W_H_C[:3, 2]  # optical axis in W
                ctilt = float(np.degrees(np.arccos(np.clip(d[2], -1, 1))))
                caz = float(np.degrees(np.arctan2(d[1], d[0])) % 360.0)
                # the plate's normal in the gripper frame (rigidly tied to the camera): only its direction
                # tells views apart for the interior orientation; a turn alone does not change it
                nG = (np.linalg.inv(Rt @ make_H(R_from_rotvec((0, 0, np.radians(turn))), (0, 0, 0))))[:3, 2]
                naz = float(np.degrees(np.arctan2(nG[1], nG[0])) % 360.0)
                if ctilt <= MAX_CAMERA_TILT_DEG:
                    cands.append((tilt, axis, turn, ctilt, caz, naz))
    cands = np.array(cands)
    lifts = np.linspace(LIFT_MM[0] + 15.0, LIFT_MM[1], 4)
    out = []
    used: set[int] = set()
    for i in range(n):
        az = (360.0 * i / n + 45.0 * (i % 2)) % 360.0
        want_tilt = (35.0, 25.0, 40.0, 30.0)[i % 4]
        daz = np.abs((cands[:, 5] - az + 180.0) % 360.0 - 180.0)
        score = np.abs(cands[:, 0] - want_tilt) + 0.3 * daz
        for j in np.argsort(score, kind="stable"):  # ties in a fixed order on every numpy and CPU
            if int(j) in used:
                continue
            tilt, axis, turn, ctilt, caz, _ = cands[j]
            a = np.radians(axis)
            Rt = rot_axis((np.cos(a), np.sin(a), 0.0), np.radians(tilt))
            Rz = make_H(R_from_rotvec((0, 0, np.radians(turn))), (0, 0, 0))
            want = float(lifts[(i * 3) % len(lifts)])
            found = None
            for lift in sorted(np.arange(LIFT_MM[0], LIFT_MM[1] + 1e-9, 5.0), key=lambda v: abs(v - want)):
                W_H_G = Rt @ trans(0, 0, -lift) @ Rz
                if _fingers_clear(W_H_G, cell.gripper, gap) < CLEARANCE_MM:
                    continue
                C_H_W = C_H_G @ np.linalg.inv(W_H_G)
                if not cam.in_image(cam.project(transform_points(C_H_W, np.zeros((1, 3)))), margin=60)[0]:
                    continue
                found = lift
                break
            if found is None:
                continue
            lift = float(found)
            used.add(int(j))
            out.append({"W_H_G": W_H_G, "lift_mm": lift, "tilt_deg": float(tilt), "axis_deg": float(axis),
                        "turn_deg": float(turn), "camera_tilt_deg": float(ctilt), "camera_azimuth_deg": float(caz)})
            break
        else:
            raise CalibrationError(f"view plan: no pose for view {i + 1} keeps the fingers clear and the plate in view")
    return out

