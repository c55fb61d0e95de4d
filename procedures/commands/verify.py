"""``selfview verify``: the calibration checked on the cell, in millimetres.

The gripper parks at several places and turns on the plate (the plate's centre inside the fingertips'
contact hull each time), each picture is calibrated on its own, and the spread of ``C_H_G`` across the
parks is compared with the calibration's own sigma and with a target the user sets.
"""

from __future__ import annotations

from selfview.procedures.commands._common import add_view_arguments, numeric, print_json
from selfview.procedures.commands._session import add_session_arguments, camera_arguments, open_session, progress_printer
from selfview.procedures.verification import BLIND, PLACES, centre_in_hull
from selfview.procedures.view import offline_state, viewing, watch, with_progress


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
    add_session_arguments(p, camera_file=True)
    p.add_argument("--parks", type=numeric(integer=True, lo=3, hi=len(PLACES), name="parks"), default=5, help=f"how many parks, 3 to {len(PLACES)} (default %(default)s)")
    p.add_argument("--target-mm", type=numeric(lo=0, lo_open=True, hi=1000, name="mm"), default=0.25, metavar="MM",
                   help="the largest spread of the TCP along any camera axis that counts as go (default %(default)s)")
    p.add_argument("--state", default=None, help="gripper state (default: the cell's calibrate_in)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_view_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    with viewing(args, "verify") as view:
        return _run(args, view)


def _run(args, view) -> int:
    from selfview.errors import ConfigError
    from selfview.procedures.commands.calibrate import camera_file_arg
    from selfview.procedures.verification import park_and_calibrate, verify_summary

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
    seen = []

    def shown(k, img, res):
        seen.append(res)
        if view:
            offline_state(view, img, res)
            view.update(numbers={"park": f"{k + 1} of {len(places)}",
                                 **{f"park {i + 1} TCP x y z [mm]": " ".join(f"{v:+.4f}" for v in
                                    r.C_H_G[:3, 3]) for i, r in enumerate(seen)}})

    with session:
        watch(view, session)
        results = park_and_calibrate(session, cell, places, state, camera=camera, camera_file=camera_file,
                                     camera_cov3=cov3, camera_name=cam_path, on_result=shown)
        truth = session.devices.truth() if (results and session.devices.truth) else None
    if results is None:  # dry run
        return 0
    out = verify_summary(results, places, args.target_mm, truth)
    go, reason, axes = out["verdict"] == "go", out["reason"], "xyz"
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
