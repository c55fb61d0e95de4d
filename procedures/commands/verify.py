"""``selfview verify``: the calibration checked on the cell, in millimetres.

The gripper parks at several places and turns on the plate (the plate's centre inside the fingertips'
contact hull each time), each picture is calibrated on its own, and the spread of ``C_H_G`` across the
parks is compared with the calibration's own sigma and with a target the user sets.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from selfview.procedures.commands._common import numeric, print_json
from selfview.procedures.commands._session import add_session_arguments, camera_arguments, open_session, progress_printer
from selfview.procedures.commands._common import add_view_arguments
from selfview.procedures.view import offline_state, viewing, watch, with_progress

#: Where the parks go, relative to the taught plate location: in-plane shift x, y [mm] along the gripper's
#: axes and turn about the approach axis [deg]. The fingers lie along G's x (+-28..36 mm) and are 12 mm
#: deep along y, so the shifts along y stay small to keep the plate's centre between the fingertips.
PLACES = ((0.0, 0.0, 0.0), (10.0, 0.0, 12.0), (-10.0, 0.0, -12.0), (5.0, -1.5, 25.0), (-5.0, 1.5, -25.0),
          (16.0, 0.0, -6.0), (-16.0, 0.0, 6.0), (0.0, 2.0, 18.0))

#: What every park shares, so what their agreement cannot show.
BLIND = ("the plate's print scale (a scale error moves every park's C_H_G the same way, mostly along the optical "
         "axis: measure the plate's pitch), the camera file or nominal camera (principal point, aspect, skew), "
         "the fingers' real dimensions, and anything that did not change between the parks")


def register(sub):
    p = sub.add_parser(
        "verify",
        help="park at several places and turns on the plate, calibrate each, report the spread of C_H_G in mm",
        description=(
            "Checks a calibration on the cell: the gripper parks at --parks places and turns on the plate (the "
            "plate's centre inside the fingertips' contact hull each time), each picture is calibrated on its own, "
            "and the spread of C_H_G (the TCP in camera axes in mm, the rotation in degrees) is set against the "
            "calibration's own 1-sigma and against --target-mm: go when every axis' spread is within the target. "
            "What every park shares (the plate's print scale, the camera file, the fingers' dimensions) moves all "
            "of them alike, so the spread cannot see it. On the simulated cell the error against the truth is "
            "reported too. Nothing is written; the robot departs from the plate at the end."
        ),
    )
    add_session_arguments(p, camera_file=True, profile_default="realistic")
    p.add_argument("--parks", type=numeric(integer=True, lo=3, hi=len(PLACES), name="parks"), default=5, help=f"how many parks, 3 to {len(PLACES)} (default %(default)s)")
    p.add_argument("--target-mm", type=numeric(lo=0, lo_open=True, hi=1000, name="mm"), default=0.25, metavar="MM",
                   help="the largest spread of the TCP along any camera axis that counts as go (default %(default)s)")
    p.add_argument("--state", default=None, help="gripper state (default: the cell's calibrate_in)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_view_arguments(p)
    p.set_defaults(func=run)
    return p


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
    from selfview.geometry import make_H, orthonormalize, rotation_angle

    Hs = np.asarray(Hs, float)
    t = Hs[:, :3, 3]
    R = orthonormalize(Hs[:, :3, :3].mean(axis=0))
    ang = np.array([np.degrees(rotation_angle(R.T @ H[:3, :3])) for H in Hs])
    return {"spread_mm": t.std(axis=0, ddof=1).tolist(), "range_mm": np.ptp(t, axis=0).tolist(),
            "spread_deg": float(np.sqrt(np.mean(ang**2))), "mean": make_H(R, t.mean(axis=0))}


def run(args) -> int:
    with viewing(args, "verify") as view:
        return _run(args, view)


def _run(args, view) -> int:
    from selfview.errors import ConfigError
    from selfview.geometry import rot_z, rotation_angle, trans
    from selfview.intrinsics import tcp_sigma
    from selfview.offline import calibrate_offline
    from selfview.procedures.commands.calibrate import camera_file_arg
    from selfview.procedures.engine import Step
    from selfview.procedures.runs import depart_plan, park_plan

    if not 3 <= args.parks <= len(PLACES):
        raise ConfigError(f"--parks {args.parks}: expected 3 to {len(PLACES)}")
    if not args.target_mm > 0:
        raise ConfigError(f"--target-mm {args.target_mm}: expected a length > 0 in mm")
    url, cam_path = camera_arguments(args.camera)
    args.camera = url
    say = with_progress(view, progress_printer())
    cell, session = open_session(args, say)
    camera = camera_file = cov3 = None
    if cam_path:
        camera, camera_file, cov3 = camera_file_arg(cam_path, cell)
    state = args.state or cell.gripper.calibrate_in
    pG = cell.gripper.points_G(state)
    places = PLACES[: args.parks]
    for dx, dy, turn in places:
        if not centre_in_hull(pG, (dx, dy), turn):
            raise ConfigError(f"park at {dx:+.0f} {dy:+.0f} mm, {turn:+.0f} deg: the plate's centre would leave the "
                              "fingertips' contact hull (a narrower gripper than the reference cell's): give fewer --parks")
    with session:
        watch(view, session)
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
                        results.append(res)
                        if view:
                            offline_state(view, img, res)
                            view.update(numbers={"park": f"{k + 1} of {len(targets)}",
                                                 **{f"park {i + 1} TCP x y z [mm]": " ".join(f"{v:+.4f}" for v in
                                                    r.calibration.C_H_G[:3, 3]) for i, r in enumerate(results)}})
            return results

        results = session.engine.run(body, plan)
        truth = session.devices.truth() if (results and session.devices.truth) else None
    if results is None:  # dry run
        return 0
    Hs = [r.calibration.C_H_G for r in results]
    sp = spread(Hs)
    sigmas = np.array([tcp_sigma(r, cell, cov3)["tcp_sigma_mm"] for r in results])
    sigma = np.sqrt(np.mean(sigmas**2, axis=0))
    worst = float(np.max(sp["spread_mm"]))
    ratio = np.asarray(sp["spread_mm"]) / np.maximum(sigma, 1e-9)
    go = worst <= args.target_mm
    axes = "xyz"
    k = int(np.argmax(sp["spread_mm"]))
    reason = (f"the TCP's spread over {len(results)} parks is at most {worst:.4f} mm (along {axes[k]}), "
              + ("within" if go else "over") + f" the target {args.target_mm:g} mm")
    if np.any(ratio > 3):
        reason += (f"; along {axes[int(np.argmax(ratio))]} the spread is {ratio.max():.1f} times the calibration's "
                   "own sigma: the picture-to-picture error is larger than the sigma says")
    out = {
        "parks": [{"shift_mm": [dx, dy], "turn_deg": t, "tcp_mm": H[:3, 3].tolist(), "rms_px": float(r.tsai.rms_px),
                   "corners_found": int(np.count_nonzero(r.fingertips.found))}
                  for (dx, dy, t), H, r in zip(places, Hs, results)],
        "spread_mm": sp["spread_mm"],
        "range_mm": sp["range_mm"],
        "spread_deg": sp["spread_deg"],
        "sigma_mm": sigma.tolist(),
        "spread_over_sigma": ratio.tolist(),
        "target_mm": args.target_mm,
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
    if view:
        view.update(numbers={"spread x y z [mm]": " ".join(f"{v:.4f}" for v in out["spread_mm"]),
                             "spread rotation [deg]": out["spread_deg"],
                             "own 1-sigma x y z [mm]": " ".join(f"{v:.4f}" for v in out["sigma_mm"]),
                             **({"error against the truth x y z [mm]": " ".join(f"{v:+.4f}" for v in out["truth_error_mm"])}
                                if "truth_error_mm" in out else {}),
                             "cannot see": BLIND})
        view.verdict(go, reason)
    if args.json:
        print_json(out)
    else:
        print(f"verify: {len(results)} parks on the plate, each calibrated on its own")
        for i, pk in enumerate(out["parks"]):
            t = pk["tcp_mm"]
            print(f"  park {i + 1}: shift {pk['shift_mm'][0]:+5.1f} {pk['shift_mm'][1]:+5.1f} mm, turn {pk['turn_deg']:+5.1f} deg"
                  f"  TCP x {t[0]:+.4f}  y {t[1]:+.4f}  z {t[2]:+.4f} mm  (rms {pk['rms_px']:.3f} px)")
        f3 = lambda v: "  ".join(f"{a} {x:.4f}" for a, x in zip(axes, v))  # noqa: E731
        print(f"  spread (sd):   {f3(out['spread_mm'])} mm;  rotation {out['spread_deg']:.4f} deg")
        print(f"  own 1-sigma:   {f3(out['sigma_mm'])} mm")
        if truth is not None:
            print(f"  against the simulator's truth: {f3(out['truth_error_mm'])} mm, {out['truth_error_deg']:.4f} deg")
        print(f"{'GO' if go else 'NO-GO'}: {reason}")
        print(f"  what the spread cannot see (every park shares it): {BLIND}")
    return 0 if go else 5
