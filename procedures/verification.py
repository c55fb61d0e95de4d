"""Checking a calibration on the cell, as ``selfview verify`` and a lab script run it: the gripper parks at
several places and turns on the plate, each picture is calibrated on its own, and the spread of ``C_H_G``
is set against the calibration's own sigma and a target.

    with session:  # a procedures.runs.CellSession
        results = park_and_calibrate(session, cell, PLACES[:5], state)
    summary = verify_summary(results, PLACES[:5], target_mm=0.25)
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: Where the parks go, relative to the taught plate location: in-plane shift x, y [mm] along the gripper's
#: axes and turn about the approach axis [deg]. The fingers lie along G's x (+-28..36 mm) and are 12 mm
#: deep along y, so the shifts along y stay small to keep the plate's centre between the fingertips.
PLACES = ((0.0, 0.0, 0.0), (10.0, 0.0, 12.0), (-10.0, 0.0, -12.0), (5.0, -1.5, 25.0), (-5.0, 1.5, -25.0),
          (16.0, 0.0, -6.0), (-16.0, 0.0, 6.0), (0.0, 2.0, 18.0))

#: What every park shares, so what their agreement cannot show.
BLIND = ("the plate's print scale (a scale error moves every park's C_H_G the same way, mostly along the optical "
         "axis: measure the plate's pitch), the camera file or nominal camera (principal point, aspect, skew), "
         "the fingers' real dimensions, and anything that did not change between the parks")


def centre_in_hull(points_G, shift_xy, turn_deg) -> bool:
    """Whether the plate's centre (the taught park's TCP) lies inside the convex hull of the fingertip points
    (x, y in G) after the gripper moved by ``shift_xy`` and turned by ``turn_deg`` in the plate's plane."""
    import cv2

    q = np.radians(turn_deg)
    R = np.array([[np.cos(q), -np.sin(q)], [np.sin(q), np.cos(q)]])
    c = -R.T @ np.asarray(shift_xy, float)  # the old origin in the new G
    hull = cv2.convexHull(np.ascontiguousarray(np.asarray(points_G, np.float32)[:, :2]))
    return cv2.pointPolygonTest(hull, (float(c[0]), float(c[1])), True) > 1.0  # at least 1 mm inside


def spread(Hs) -> dict:
    """Spread of a set of C_H_G: per-axis sample sd of the TCP [mm], the rotations' RMS angle from their
    mean [deg], and the mean transform."""
    from selfview.maths.geometry import make_H, orthonormalize, rotation_angle

    Hs = np.asarray(Hs, float)
    if Hs.ndim != 3 or Hs.shape[1:] != (4, 4) or len(Hs) < 2 or not np.isfinite(Hs).all():
        raise ValueError(f"spread: expected at least 2 finite (4, 4) transforms, got an array of shape {Hs.shape}")
    t = Hs[:, :3, 3]
    R = orthonormalize(Hs[:, :3, :3].mean(axis=0))
    ang = np.array([np.degrees(rotation_angle(R.T @ H[:3, :3])) for H in Hs])
    return {"spread_mm": t.std(axis=0, ddof=1).tolist(), "range_mm": np.ptp(t, axis=0).tolist(),
            "spread_deg": float(np.sqrt(np.mean(ang**2))), "mean": make_H(R, t.mean(axis=0))}


def park_and_calibrate(session, cell, places, state: str, *, camera=None, camera_file=None, camera_cov3=None,
                       camera_name=None, on_result=None):
    """Park at each of ``places`` ((shift x, y [mm], turn [deg]) from the taught plate location), grab and
    calibrate each picture on its own (``calibrate_offline``, assessed by ``selfview.api.assess_offline``: the
    honest sigma, the camera model's error the picture shows included), through the session's engine (the
    plan checked first; the robot departs at the end). ``on_result(k, picture, result)`` after each park.
    Returns the ``PictureCalibration`` list, or None on a dry run."""
    from selfview.api import assess_offline
    from selfview.maths.geometry import rot_z, trans
    from selfview.estimation.offline import calibrate_offline
    from selfview.procedures.engine import Step
    from selfview.procedures.runs import depart_plan, park_plan

    from selfview.errors import ConfigError

    if not places:
        raise ConfigError("verify: no places to park at; give at least one (shift x, y [mm], turn [deg])")
    s = session.settings
    if session.dry_run:
        targets = [f"{s.plate} shifted {dx:+.0f} {dy:+.0f} mm, turned {t:+.0f} deg" for dx, dy, t in places]
    else:
        robot = session.devices.robot
        plate_H = robot.pose_to_H(robot.location(s.plate))
        targets = [plate_H @ trans(dx, dy, 0.0) @ rot_z(np.radians(t)) for dx, dy, t in places]
    plan = [Step("speed", {"pct": s.speed_pct})]
    for k, target in enumerate(targets):
        plan += park_plan(dataclasses.replace(s, plate=target), state)
        plan += [Step("grab", {"average": s.average}, name=f"park{k + 1}", note=f"park {k + 1} of {len(targets)}")]
        plan += depart_plan(s)

    def body(e):
        results = []
        per_park = len(plan[1:]) // len(targets)
        e.execute(plan[0])
        for k in range(len(targets)):
            for st in plan[1 + k * per_park: 1 + (k + 1) * per_park]:
                e.execute(st)
                if st.name == f"park{k + 1}":
                    img = e.results[st.name]
                    res = e.execute(Step("compute", {"fn": lambda e, img=img: calibrate_offline(
                        img, cell, state=state, camera=camera, camera_file=camera_file)},
                        note=f"calibrate park {k + 1}"))
                    results.append(assess_offline(res, cell, camera, camera_cov3, camera_name))
                    if on_result is not None:
                        on_result(k, img, results[-1])
        return results

    return session.engine.run(body, plan)


def verify_summary(results, places, target_mm: float, truth: dict | None = None) -> dict:
    """The JSON-ready verdict of ``park_and_calibrate``'s results: per park the TCP and residual, the spread
    (``spread``), the calibrations' own 1-sigma (each park's, the camera model's error its picture shows
    included), go when every axis' spread and the camera model's shared part are within ``target_mm``, the
    reason, what the spread cannot see (``BLIND``) and, with the simulator's ``truth``, the error against it."""
    from selfview.errors import ConfigError
    from selfview.maths.geometry import rotation_angle

    if len(results) < 2 or len(results) != len(places):
        raise ConfigError(f"verify: {len(results)} result(s) for {len(places)} place(s); a spread needs one result "
                          "per place and at least 2 places")
    if not (np.isfinite(target_mm) and target_mm > 0):
        raise ConfigError(f"verify: target {target_mm!r} mm: expected a finite length > 0")
    Hs = [r.C_H_G for r in results]
    sp = spread(Hs)
    sigmas = np.array([r.tcp_sigma_mm for r in results])
    sigma = np.sqrt(np.mean(sigmas**2, axis=0))
    # what every park shares (the camera model's error): the spread cannot see it, the sigma must
    shared = np.array([r.sigma_parts_mm.get("camera_model", [0.0] * 3) for r in results])
    shared = np.sqrt(np.mean(shared**2, axis=0))
    worst = float(np.max(sp["spread_mm"]))
    ratio = np.asarray(sp["spread_mm"]) / np.maximum(sigma, 1e-9)
    go = worst <= target_mm and float(shared.max()) <= target_mm
    axes = "xyz"
    k = int(np.argmax(sp["spread_mm"]))
    reason = (f"the TCP's spread over {len(results)} parks is at most {worst:.4f} mm (along {axes[k]}), "
              + ("within" if worst <= target_mm else "over") + f" the target {target_mm:g} mm")
    if shared.max() > target_mm:
        reason += (f"; but the pictures show the camera's centre or aspect wrong by enough to move every park's TCP "
                   f"by {shared.max():.3f} mm along {axes[int(np.argmax(shared))]}, which the spread cannot see: "
                   "measure the camera with 'selfview intrinsics' and verify with --camera CAMERA.yaml")
    if np.any(ratio > 3):
        reason += (f"; along {axes[int(np.argmax(ratio))]} the spread is {ratio.max():.1f} times the calibration's "
                   "own sigma: the picture-to-picture error is larger than the sigma says")
    out = {
        "parks": [{"shift_mm": [dx, dy], "turn_deg": t, "tcp_mm": H[:3, 3].tolist(),
                   "rms_px": float(r.offline.tsai.rms_px), "tcp_sigma_mm": list(r.tcp_sigma_mm),
                   "corners_found": int(np.count_nonzero(r.offline.fingertips.found))}
                  for (dx, dy, t), H, r in zip(places, Hs, results)],
        "spread_mm": sp["spread_mm"],
        "range_mm": sp["range_mm"],
        "spread_deg": sp["spread_deg"],
        "sigma_mm": sigma.tolist(),
        "camera_model_sigma_mm": shared.tolist(),
        "spread_over_sigma": ratio.tolist(),
        "target_mm": target_mm,
        "verdict": "go" if go else "no-go",
        "reason": reason,
        "cannot_see": BLIND,
        "C_H_G_mean": sp["mean"].tolist(),
    }
    if truth is not None:
        Ht = np.asarray(truth["C_H_G"], float)
        out["truth_error_mm"] = (sp["mean"][:3, 3] - Ht[:3, 3]).tolist()
        out["truth_error_deg"] = float(np.degrees(rotation_angle(sp["mean"][:3, :3].T @ Ht[:3, :3])))
        out["truth_error_per_park_mm"] = [float(np.linalg.norm(H[:3, 3] - Ht[:3, 3])) for H in Hs]
    return out
