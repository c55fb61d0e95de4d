"""``selfview intrinsics``: measure the camera (f, kappa, principal point, aspect) from several views of the plate.

With ``--images`` it calibrates picture files; without, the robot takes the views on the cell (simulated
by default, or ``--real``): from above the plate it moves through a planned set of poses (checked against
the limits before the first motion), grabs a picture at each and goes back above the plate.
"""

from __future__ import annotations

import datetime as _dt
import sys
from pathlib import Path

from selfview.estimation.intrinsics.plate import PLATE_MODELS
from selfview.procedures.commands._common import COUNT, SECONDS, add_view_arguments, print_json
from selfview.procedures.commands._session import add_session_arguments, open_session, progress_printer
from selfview.procedures.livefeed import live_feed
from selfview.procedures.view import ViewProgress, intrinsics_state, viewing, watch, with_progress


def register(sub):
    p = sub.add_parser(
        "intrinsics",
        help="measure the camera (f, kappa, principal point, aspect, with uncertainties) from several views of the plate",
        description=(
            "Joint calibration of f, kappa, the principal point, the aspect and every view's plate pose from "
            "several pictures of the plate (the off-line calibration's bias-corrected disc centres), with the "
            "uncertainty from the covariance scaled by the residual. It says whether the views pin the centre "
            "(sigma < 0.3 px) and the aspect (sigma < 0.05 %), and if not how many more views of which kind "
            "would; it cross-checks two halves of the views. --out writes a camera file (atomically, the "
            "previous one kept in OUT.history/) for 'selfview calibrate --camera'; it is only written when the "
            "stop rule is met (or with --force). Without --images the robot takes the views."
        ),
    )
    add_session_arguments(p)
    p.add_argument("--images", nargs="+", metavar="IMG", help="pictures of the plate from different poses (no devices)")
    p.add_argument("--plate", metavar="PLATE.yaml",
                   help="with --images: a file whose 'plate:' section describes the plate (discs, chessboard or charuco); "
                        "without --cell the starting camera comes from the pictures")
    p.add_argument("--plate-model", choices=("auto",) + PLATE_MODELS, default="auto",
                   help="what of the printed plate's shape is fitted with the camera; auto: a bent plate only when the views pin it and views left out confirm it (default %(default)s)")
    p.add_argument("--views", type=COUNT, default=12, help="views the robot takes on the cell (default %(default)s)")
    p.add_argument("--skip-unusable", action="store_true",
                   help="skip a picture without the plate (listed in the output) instead of refusing the set")
    p.add_argument("--out", metavar="CAMERA.yaml", help="write the camera file here")
    p.add_argument("--force", action="store_true", help="write --out even when the stop rule is not met")
    p.add_argument("--save-views", metavar="DIR", help="on the cell: write the pictures taken into DIR")
    p.add_argument("--review", nargs="?", type=SECONDS, const=600.0, default=None, metavar="S",
                   help="with --view: before anything is written, the page lists the views; reject any, CALIBRATE "
                        "again without them, and SAVE (waits S seconds for the operator, default 600)")
    p.add_argument("--operator-views", nargs="?", type=SECONDS, const=600.0, default=None, metavar="S",
                   help="with --view, on the cell: the robot goes above the plate and makes no planned views; the "
                        "operator moves the arm (pendant, hand guiding, manual://), watches the live picture with the "
                        "plate found in it and the coverage it would add, and takes each view with TAKE THIS VIEW, "
                        "then MEASURE (waits S seconds for each click, default 600; --views is not used)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_view_arguments(p)
    p.set_defaults(func=run)
    return p


def _check_args(args) -> None:
    from selfview.errors import ConfigError

    if args.plate and not args.images:
        raise ConfigError("--plate describes the plate of --images; on the cell the cell file's plate is used")
    if args.images and args.real:
        raise ConfigError("--images calibrates picture files; --real takes the views on the cell: give one of them")
    if args.review is not None and args.view is None:
        raise ConfigError("--review asks on the page: give --view too")
    if args.operator_views is not None and (args.view is None or args.images):
        raise ConfigError("--operator-views takes the views on the cell with the page's TAKE THIS VIEW: give --view "
                          "and no --images")
    if args.views < 1:
        raise ConfigError(f"--views: expected a positive number of views, got {args.views}")
    if args.out:
        out = Path(args.out)
        if out.exists() and out.is_dir():
            raise ConfigError(f"--out {out}: is a folder; expected a camera file name")


def _text(res, source: str, written, out) -> list[str]:
    """The result as lines for the terminal."""
    xc = res.cross_check
    c = res.camera
    sg = res.sigma
    ps = res.projection_sigma_px
    lines = [
        f"camera from {res.views_used} views ({source}), residual rms {res.rms_px:.3f} px",
        f"  f      = {c.f:.3f} +- {sg['f']:.3f} px",
        f"  kappa  = {c.kappa:.4e} +- {sg['kappa']:.1e} px^-2",
        f"  centre = ({c.cx:.2f}, {c.cy:.2f}) +- ({sg['cx']:.2f}, {sg['cy']:.2f}) px",
        f"  aspect = {c.aspect:.5f} +- {sg['aspect']:.5f}",
        *([f"  skew   = {c.skew:.2e} +- {sg['skew']:.1e} (the grabber's shear: "
           f"{c.skew * c.height:+.2f} px from the top line to the bottom one)"] if "skew" in sg
          else [f"  {res.skew_fit.get('note', 'skew not fitted')}"]),
        f"  projection uncertainty: centre {ps['centre']:.3f} px, corners "
        + ", ".join(f"{ps[k]:.3f}" for k in ("top_left", "top_right", "bottom_left", "bottom_right")) + " px",
        "  stop rule: " + ("met" if res.stop_rule["met"] else "NOT met: " + res.stop_rule.get("advice", "")),
        "  cross-check: " + (("halves agree" if xc["agree"] else "halves DISAGREE") if xc.get("done") else xc["why"]),
    ]
    if written:
        lines.append(f"written to {written}")
    elif out:
        lines.append(f"{out} not written: the stop rule is not met (take the views advised, or --force)")
    return lines


def _picture_files(args):
    """--images with --plate or --cell: (plate, starting camera or None, cell file hash or None, pictures,
    their names, [{name, sha256}])."""
    from selfview.files.cell import default_cell_path, load_cell, load_plate
    from selfview.procedures.commands.calibrate import read_picture

    camera = cell_sha = None
    if args.plate is None or args.cell:
        cell = load_cell(args.cell or default_cell_path())
        camera, cell_sha = cell.camera.guess(), cell.sha256
    plate = load_plate(args.plate) if args.plate else cell.plate
    images, names, pictures = [], [], []
    for path in args.images:
        img, sha = read_picture(path)
        images.append(img)
        names.append(str(path))
        pictures.append({"name": Path(path).name, "sha256": sha})
    return plate, camera, cell_sha, images, names, pictures


def run(args) -> int:
    with viewing(args, "intrinsics") as view:
        return _run(args, view)


def _measure(args, view, say, images, names, plate, camera):
    """(the camera measured from the views, the views the operator rejected). With --review the page lists
    the views and waits: CALIBRATE measures again without the views marked, SAVE goes on with the last
    measurement. ``ConfigError`` when nobody answers in time (nothing written)."""
    from selfview.errors import ConfigError
    from selfview.procedures.intrinsics import measure_intrinsics

    rejected: list[str] = []
    while True:
        keep = [i for i, nm in enumerate(names) if nm not in rejected]
        say(f"measuring the camera from {len(keep)} views" + (f" ({len(rejected)} rejected)" if rejected else ""))
        res = measure_intrinsics([images[i] for i in keep], plate, camera, [names[i] for i in keep],
                                 skip_unusable=args.skip_unusable or not args.images, plate_model=args.plate_model)
        if not (view and args.review):
            return res, rejected
        intrinsics_state(view, res, plate, rejected)
        got = view.ask("check the views: mark any to reject and CALIBRATE again, or SAVE this camera",
                       [("calibrate", "CALIBRATE"), ("save", "SAVE")], select_views=True, timeout_s=args.review)
        if got is None:
            raise ConfigError(f"--review: no answer on the page within {args.review:g} s; nothing written")
        if got[0] == "save":
            return res, rejected
        rejected = [nm for nm in names if nm in set(got[1]["reject"])]


def _take_on_page(view, feed, progress, timeout_s: float, cancel):
    """``CellSession.operator_views``'s ``take``: the page offers TAKE THIS VIEW and MEASURE (MEASURE only
    ends the views once there are enough for a measurement) beside the live feed; ``ConfigError`` when
    nobody clicks within ``timeout_s`` (or the run is stopping: ``cancel`` set)."""
    from selfview.errors import ConfigError
    from selfview.estimation.intrinsics import MIN_VIEWS

    def take(n: int) -> str:
        progress.flush()
        if feed is not None:
            feed.resume()
        note = ""
        while True:
            view.doing(f"waiting for the operator: {n} view(s) taken")
            got = view.ask(f"{n} view(s) taken{note}: move the arm until the live picture shows the plate where the "
                           "coverage needs it, then TAKE THIS VIEW; MEASURE when done",
                           [("take", "TAKE THIS VIEW"), ("done", "MEASURE")], timeout_s=timeout_s, cancel=cancel)
            if got is None:
                raise ConfigError(f"--operator-views: no click on the page within {timeout_s:g} s; nothing measured")
            if got[0] == "take" or n >= MIN_VIEWS:
                return got[0]
            note = f" (MEASURE needs at least {MIN_VIEWS})"

    return take


def _run(args, view) -> int:
    from selfview import __version__
    from selfview.files.camfile import CameraFile, save_camera_file
    from selfview.procedures.intrinsics import intrinsics_warnings
    from selfview.procedures.commands._common import write_image

    _check_args(args)
    say = with_progress(view, progress_printer())
    if args.images:
        plate, camera, cell_sha, images, names, pictures = _picture_files(args)
        source = "pictures"
    else:
        cell, session = open_session(args, say)
        with session:
            by_operator = args.operator_views is not None
            progress = ViewProgress(say, None if by_operator else args.views, session.engine, cell, view)
            with live_feed(view, session, progress) as feed:
                watch(view, session, progress, feed and feed.on_step)
                if by_operator:
                    got = session.operator_views(_take_on_page(view, feed, progress, args.operator_views, session.engine.cancel))
                else:
                    got = session.intrinsics_views(args.views)
        if got is None:  # dry run
            return 0
        images, poses = got
        import hashlib

        import numpy as np

        names = [f"view {i + 1}" for i in range(len(images))]
        pictures = [{"name": nm, "sha256": hashlib.sha256(np.ascontiguousarray(img).tobytes()).hexdigest()}
                    for nm, img in zip(names, images)]
        if args.save_views:
            folder = Path(args.save_views)
            folder.mkdir(parents=True, exist_ok=True)
            for i, img in enumerate(images):
                write_image(folder / f"view_{i + 1:02d}.png", img, "--save-views")
        source = "cell (real)" if args.real else f"simulated cell (seed {args.seed}, camera {args.sim_camera})"
        plate, camera, cell_sha = cell.plate, cell.camera.guess(), cell.sha256
    res, rejected = _measure(args, view, say, images, names, plate, camera)
    s = res.summary()
    s["source"] = source
    warnings = intrinsics_warnings(res)
    s["warnings"] = warnings
    if rejected:
        s["views_rejected"] = rejected
    if view:
        intrinsics_state(view, res, plate, rejected)
    if not args.images and getattr(session, "sim", None) is not None:
        t = session.sim.world.camera
        s["truth"] = {"f": t.f, "kappa": t.kappa, "principal_point": [t.cx, t.cy], "aspect": t.aspect}
    for w in warnings:
        print(f"selfview intrinsics: warning: {w}", file=sys.stderr)
    written = None
    if args.out:
        if res.stop_rule["met"] or args.force:
            cf = CameraFile(
                res.camera, res.sigma, res.covariance,
                figures={k: s[k] for k in ("rms_px", "views_used", "projection_sigma_px", "stop_rule", "cross_check",
                                          "skew_fit")},
                provenance={"pictures": pictures, "source": source, "cell_sha256": cell_sha,
                            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                            "software": f"selfview {__version__}"},
            )
            kept = save_camera_file(cf, args.out)
            written = str(args.out)
            s["previous_kept_as"] = str(kept) if kept else None
        else:
            s["out"] = None
    s["out"] = written
    if args.json:
        print_json(s)
    else:
        lines = _text(res, source, written, args.out)
        print("\n".join(lines))
    if args.out and not written:
        return 5
    return 0
