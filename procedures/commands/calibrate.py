"""``selfview calibrate``: off-line calibration from one picture of the gripper parked on the plate.

With ``--image`` it calibrates a picture file; without it, it runs the ``calibrate`` procedure on the cell
(park, grab, calibrate, save, depart) — see ``selfview calibrate --help``.
"""

from __future__ import annotations

import sys

from selfview.procedures.commands._common import SECONDS, add_view_arguments, load_cell_arg, output_file, print_json
from selfview.procedures.commands._session import add_session_arguments, camera_arguments, open_session, progress_printer
from selfview.procedures.livefeed import live_feed
from selfview.procedures.view import watch, offline_state, viewing, with_progress


def read_picture(path) -> tuple:
    """(grey picture as a 2-D uint8 array, SHA-256 of the file) or ``ImageError`` naming the file; the
    picture's size is checked in its header before it is decoded (``selfview.files.io_safe.read_picture``)."""
    from selfview.files.io_safe import read_picture as checked_read

    return checked_read(path)


def register(sub):
    p = sub.add_parser(
        "calibrate",
        help="off-line calibration (f, kappa, C_H_W, C_H_G) from one picture of the gripper parked on the plate",
        description=(
            "Off-line calibration (the paper's section 3). Tsai's coplanar method on the plate's discs gives f, kappa "
            "and the plate pose C_H_W; the fingertip corners and the Plane Coincidence Constraint give the "
            "gripper-to-camera transform C_H_G, with no robot kinematics. The result is written atomically to "
            "--out; a previous file is kept in OUT.history/. On any failure nothing is written. With --image it "
            "calibrates a picture file; without, it runs the calibrate procedure on the cell (park, grab, "
            "calibrate, save, depart; the simulated cell, or --real --robot URL --gripper URL --camera URL). "
            "--camera CAMERA.yaml (from 'selfview intrinsics') replaces the cell's nominal principal point and "
            "aspect by the measured ones; without it, a picture that shows them wrong by more than the accuracy "
            "targets gives a warning."
        ),
    )
    add_session_arguments(p, camera_file=True)
    p.add_argument("--image", metavar="IMG", help="picture of the gripper parked on the plate (default: take it on the cell)")
    p.add_argument("--state", default=None, help="gripper state in the picture (default: the cell's calibrate_in)")
    p.add_argument("--out", default="calibration.yaml", metavar="CAL.yaml", help="calibration file to write")
    p.add_argument(
        "--mode",
        default="full",
        choices=("tsai", "full", "full+centre"),
        help="Tsai refinement: tsai (f, Tz, kappa), full (pose, f, kappa; default), full+centre (also the centre)",
    )
    p.add_argument("--points", default="measured", choices=("measured", "cell"),
                   help="gripper points from the picture (default, as the paper) or from the cell description")
    p.add_argument("--force", action="store_true",
                   help="write the calibration even when the camera file does not fit the picture")
    p.add_argument("--no-pictures", action="store_true",
                   help="do not keep the picture and its annotated copy beside --out (kept by default, named in the file)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--review", nargs="?", type=SECONDS, const=600.0, default=None, metavar="S",
                   help="with --view: show the calibration on the page and write it only when SAVE is clicked "
                        "(DISCARD, or no answer within S seconds, default 600: nothing written, exit 5)")
    add_view_arguments(p)
    p.set_defaults(func=run)
    return p


def camera_file_arg(path, cell):
    """(camera model, {path, sha256}, covariance of cx, cy, aspect (3, 3), and skew (4, 4) when the file
    has it) of a camera file, checked against the cell's picture size."""
    from selfview.files.camfile import load_camera_file

    cf = load_camera_file(path)
    cf.check_size(cell.camera.width, cell.camera.height, f"camera file {path}")
    return cf.camera, {"path": str(path), "sha256": cf.file_sha256}, cf.centre_covariance()


def _previous(out):
    """The calibration ``out`` holds now (the one this run replaces), or None (no file, or not a calibration)."""
    from selfview.files.calfile import load_calibration
    from selfview.errors import CellError

    try:
        return load_calibration(out)
    except (CellError, OSError):
        return None


def _review(view, timeout_s, cancel) -> None:
    """Wait for SAVE on the page; ``CalibrationError`` (nothing written) on DISCARD or no answer."""
    from selfview.errors import CalibrationError

    got = view.ask("check the calibration: SAVE writes it, DISCARD writes nothing",
                   [("save", "SAVE"), ("discard", "DISCARD")], timeout_s=timeout_s, cancel=cancel)
    if got is None or got[0] != "save":
        why = "discarded on the page" if got else f"not saved on the page within {timeout_s:g} s"
        raise CalibrationError(f"calibration {why}; nothing written")


def run(args) -> int:
    output_file(args.out, "--out")  # before anything moves: a name that cannot be written is refused now
    with viewing(args, "calibrate") as view:
        return _run(args, view)


def _run(args, view) -> int:
    from selfview.api import assess_offline, calibration_change
    from selfview.files.calfile import save_calibration
    from selfview.procedures.results import draw_offline, keep_pictures
    from selfview.errors import ConfigError
    from selfview.estimation.offline import calibrate_offline
    from selfview.procedures.runs import refuse_unfitting_camera

    url, cam_path = camera_arguments(args.camera)
    args.camera = url
    if args.review is not None and view is None:
        raise ConfigError("--review asks on the page: give --view too")
    cell = load_cell_arg(args)
    camera = camera_file = cov3 = None
    if cam_path:
        camera, camera_file, cov3 = camera_file_arg(cam_path, cell)

    assessed, change = [], {}

    def before_save(img, res):
        fit = getattr(session, "camera_file_fit", None) if not args.image else refuse_unfitting_camera(
            res, camera, cam_path, args.force)
        assessed.append(assess_offline(res, cell, camera, cov3, cam_path, fit))  # records the sigma in the file
        previous = _previous(args.out)
        if previous is not None:
            change.update(calibration_change(previous, res.calibration))
        if not args.no_pictures:
            res.calibration.pictures = keep_pictures(args.out, img, lambda im: draw_offline(im, res))
        if view:
            offline_state(view, img, assessed[-1])
            if change:
                view.update(numbers=view.state()["numbers"] | {
                    "against the previous: TCP moved x y z [mm]": " ".join(f"{v:+.4f}" for v in change["tcp_moved_mm"]),
                    "against the previous: rotated [deg]": change["rotated_deg"],
                    "against the previous: f changed [px]": change["f_changed_px"]})
            if args.review is not None:
                _review(view, args.review, getattr(getattr(session, "engine", None), "cancel", None))

    if args.image:
        if args.real or url:
            raise ConfigError("--image calibrates a picture file; --real and a grabber URL are for the cell: give one of them")
        img, sha = read_picture(args.image)
        if view:
            view.doing(f"calibrating {args.image}")
            view.frame(img)
        res = calibrate_offline(img, cell, state=args.state, mode=args.mode, points=args.points, image_sha256=sha,
                                camera=camera, camera_file=camera_file)
        session = None
        before_save(img, res)  # refuses an unfitting camera file before anything is written
        kept = save_calibration(res.calibration, args.out)
        source = args.image
    else:
        say = with_progress(view, progress_printer())
        cell, session = open_session(args, say)
        with session, live_feed(view, session) as feed:
            watch(view, session, feed and feed.on_step)
            res = session.calibrate_camera(args.out, camera=camera, camera_file=camera_file, state=args.state,
                                           mode=args.mode, force=args.force, before_save=before_save)
        if res is None:  # dry run
            return 0
        kept = session.calibration_kept
        source = "the cell's picture"
    pc = assessed[-1]
    s = pc.to_dict()
    s["out"] = str(args.out)
    s["previous_kept_as"] = str(kept) if kept else None
    s["camera_file"] = camera_file
    s["pictures"] = dict(res.calibration.pictures)
    s["against_previous"] = change or None
    warnings = s["warnings"]
    if pc.camera_file_fit and not pc.camera_file_fit["fits"]:
        refusal = pc.camera_file_fit["refusal"]
        warnings[:] = [w.replace("; measure", "; written because of --force (measure") + ")" if w.startswith(refusal)
                       else w for w in warnings]
    for w in warnings:
        print(f"selfview calibrate: warning: {w}", file=sys.stderr)
    if args.json:
        print_json(s)
        return 0
    H = res.calibration.C_H_G
    sg = s["tcp_sigma_mm"]
    lines = [
        f"calibrated {source} ({s['discs_used']} discs, corners {', '.join(s['corners_found'])})"
        + (f" with the camera of {cam_path}" if cam_path else " with the cell's nominal camera"),
        f"  f = {s['f']:.2f} px   kappa = {s['kappa']:.4e} px^-2   residual rms {s['rms_px']:.3f} px, max {s['max_px']:.3f} px",
        f"  TCP in camera: x {H[0, 3]:+.3f}  y {H[1, 3]:+.3f}  z {H[2, 3]:+.3f} mm   PCC residual {s['pcc_rms_mm']:.3f} mm",
        f"  TCP 1-sigma:   x {sg[0]:.4f}  y {sg[1]:.4f}  z {sg[2]:.4f} mm (every part: "
        + ", ".join(f"{k} {max(v):.4f}" for k, v in s["tcp_sigma_parts_mm"].items()) + ")",
        "  C_H_G =",
        *(f"    [{' '.join(f'{v:+.6f}' for v in row)}]" for row in H),
        f"written to {args.out}" + (f" (previous kept as {kept})" if kept else ""),
    ]
    if s["pictures"]:
        lines.append(f"picture kept as {s['pictures']['picture']}, annotated as {s['pictures']['annotated']}")
    if change:
        lines.append("against the previous calibration: TCP moved "
                     + "  ".join(f"{a} {v:+.4f}" for a, v in zip("xyz", change["tcp_moved_mm"]))
                     + f" mm ({change['tcp_moved_norm_mm']:.4f} mm), rotated {change['rotated_deg']:.4f} deg, "
                     f"f {change['f_changed_px']:+.2f} px")
    lines.append(f"{'GO' if pc.go else 'NO-GO'}: {pc.reason}")
    print("\n".join(lines), file=sys.stdout)
    return 0
