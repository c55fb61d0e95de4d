"""``selfview grasp``: servo the gripper to an object by its printed target, then grasp it."""

from __future__ import annotations

import argparse
import sys

from selfview.procedures.commands._common import add_view_arguments, numeric, print_json
from selfview.procedures.commands._session import add_session_arguments, open_session, progress_printer
from selfview.procedures.view import viewing, watch, with_progress


def register(sub):
    p = sub.add_parser(
        "grasp",
        help="visually guided grasping: servo the gripper to an object's grasp frame, then close the jaws",
        description=(
            "Position-based visual servoing in the gripper frame (the paper's application). From the pre-grasp "
            "pose (--start, a taught location; in simulation drawn per --seed near the object placed on the "
            "table), each picture measures the object's target and the fingertips: G_H_O = inv(C_H_G) C_H_O, "
            "C_H_G kept current by the on-line update (--offline: the calibration's, the fingertips watched "
            "for the alarm). The error to the stand-off goal (the object file's grasp frame backed off along "
            "its z) drives a capped straight motion of the tool; below 0.1 mm and 0.1 deg (the servo's stop_mm and "
            "stop_deg) a straight descent, pictures at the grasp pose measuring and correcting it (the target in view, "
            "the fingertips hidden by the block), and the jaws close. Fails (exit 5) when not converged after --max-iterations, when the "
            "target or the fingertips leave the picture, the error grows or a step would bring the fingertips "
            "to the table; exit 6 when the fingertips say the calibration is off beyond the alarm limit. The "
            "robot is stopped and the valve left safe on any failure or signal. --json: converged, held, "
            "iterations, true_error_mm (the grasp frame in the gripper frame, simulation) and each iteration's "
            "measured and true error; grasp_error_mm and at_grasp: what the pictures at the grasp pose measured."
        ),
    )
    add_session_arguments(p)
    p.add_argument("--object", metavar="OBJECT.yaml", help="the object file (default: the block shipped with selfview)")
    p.add_argument("--calibration", metavar="CAL.yaml",
                   help="calibration file (C_H_G, camera); required with --real; in simulation the cell is "
                        "calibrated off-line first when it is not given")
    p.add_argument("--start", default="pregrasp", metavar="LOCATION",
                   help="the taught pre-grasp location (default %(default)s); in simulation drawn per --seed")
    p.add_argument("--offline", action="store_true", help="servo with the calibration's C_H_G, no on-line update")
    p.add_argument("--intrinsics", action=argparse.BooleanOptionalAction, default=None,
                   help="without --calibration, in simulation: measure the camera first (the robot takes the views "
                        "of 'selfview intrinsics') and calibrate with it, as a lab does with a new camera (default: on "
                        "with --sim-camera realistic, whose principal point and aspect are not the nominal ones)")
    p.add_argument("--max-iterations", type=numeric(integer=True, lo=1, hi=1000, name="count"), default=20,
                   help="1 to 1000 (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_view_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    with viewing(args, "grasp") as view:
        return _run(args, view)


def _run(args, view) -> int:
    import tempfile

    import numpy as np

    from selfview.files.calfile import load_calibration
    from selfview.errors import CellError, ConfigError
    from selfview.measurement.objects import load_object
    from selfview.procedures.grasp import GraspResult, ServoSettings, draw_servo, run_grasp

    if (args.real or args.dry_run) and not args.calibration:
        raise ConfigError(f"{'--real' if args.real else '--dry-run'} needs --calibration CAL.yaml (the cell's calibration file)")
    if args.calibration and args.intrinsics is not None:  # the calibration file's camera is the one used
        flag = "--intrinsics" if args.intrinsics else "--no-intrinsics"
        raise argparse.ArgumentTypeError(f"{flag} is for a run without --calibration (the simulated cell's camera "
                                         "measured, or not, before calibrating); with --calibration the file's "
                                         "camera is used: give one of them")
    obj = load_object(args.object)
    settings = ServoSettings(online=not args.offline, max_iterations=int(args.max_iterations)).check()
    say = with_progress(view, progress_printer(quiet=args.json))
    cell, session = open_session(args, say)
    res = GraspResult()

    def shown(rec, img, pose):
        say(f"iteration {rec['iteration']}: error {np.linalg.norm(rec['error_mm']):.3f} mm {rec['error_deg']:.3f} deg "
            f"(fingertips: {rec['fingertips']}, {rec['processing_ms']:.0f} ms)")
        if view:
            mm = float(np.linalg.norm(rec["error_mm"]))
            view.frame(draw_servo(img, cal.camera, pose, np.asarray(cal.C_H_G), obj))
            view.point("grasp", {"frame": rec["iteration"], "delta_deg": rec["error_deg"], "d_mm": mm})
            first = res.iterations[0]  # the plot's scale: the first error; its dashed lines: where the servo stops
            view.series_limits(alarm_deg=max(first["error_deg"], settings.stop_deg),
                               alarm_mm=max(float(np.linalg.norm(first["error_mm"])), settings.stop_mm),
                               update_deg=settings.stop_deg, update_mm=settings.stop_mm,
                               names=["the first error", "stop at", "the first error"])
            view.update(numbers={"iteration": rec["iteration"], "error [mm]": mm, "error [deg]": rec["error_deg"],
                                 "fingertips": rec["fingertips"], "processing [ms]": rec["processing_ms"]})

    with tempfile.TemporaryDirectory(prefix="selfview-grasp-") as tmp, session:
        watch(view, session)
        if args.calibration:
            cal = load_calibration(args.calibration)
        else:
            camera = None
            if args.intrinsics if args.intrinsics is not None else args.sim_camera == "realistic":
                from selfview.procedures.intrinsics import measure_camera

                say("no --calibration: measuring the simulated cell's camera first")
                camera, _ = measure_camera(session, say, view)
            say("no --calibration: calibrating the simulated cell off-line first")
            session.calibrate_camera(f"{tmp}/calibration.yaml", camera=camera)
            cal = load_calibration(f"{tmp}/calibration.yaml")
        start = args.start
        if session.sim is not None:
            start = _simulated_start(session, obj, args.seed)
        try:
            if run_grasp(session, obj, cal, settings, start=start, result=res, on_iteration=shown) is None:
                return 0  # --dry-run: the plan was printed, nothing moved
        except CellError as exc:
            res.reason = f"{type(exc).__name__}: {exc}"
            _report(args, res, view)
            raise
    _report(args, res, view)
    if res.held is False:
        print(f"not held: {res.outcome['why']}", file=sys.stderr)
    return 0


def _simulated_start(session, obj, seed: int):
    """Put the object on the simulated table and draw the pre-grasp pose (one the arm can take)."""
    import numpy as np

    from selfview.maths.geometry import inv_H
    from selfview.mocks.objects import draw_start, place_object
    from selfview.mocks.puma260 import Unreachable

    world = session.sim.world
    place_object(world, obj, seed=seed)
    ctl = session.sim.robot_sim

    def reachable(H):
        try:
            ctl.kin.ik(H @ inv_H(ctl.tool))
            return True
        except Unreachable:
            return False

    return draw_start(world, np.random.default_rng([int(seed), 0x57A27]), reachable)


def _report(args, res, view) -> None:
    out = res.to_dict()
    if view:
        view.verdict(bool(res.converged and res.held is not False), res.reason)
    if args.json:
        print_json(out)
        return
    print(f"{'converged' if res.converged else 'NOT converged'} after {out['iterations']} iteration(s): {res.reason}")
    if res.grasp_error_mm is not None:
        g = res.grasp_error_mm
        print(f"  measured at the grasp pose ({len(res.at_grasp)} picture(s)): x {g[0]:+.3f}  y {g[1]:+.3f}  z {g[2]:+.3f} mm, "
              f"{res.grasp_error_deg:.3f} deg")
    elif res.grasp_note:
        print(f"  {res.grasp_note}")
    if res.true_error_mm is not None:
        t = res.true_error_mm
        print(f"  true TCP to grasp frame: x {t[0]:+.3f}  y {t[1]:+.3f}  z {t[2]:+.3f} mm, {res.true_error_deg:.3f} deg")
