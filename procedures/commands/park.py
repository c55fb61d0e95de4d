"""``selfview park``: park the gripper on the plate and save the picture."""

from __future__ import annotations

from selfview.procedures.commands._common import add_view_arguments, print_json, write_image
from selfview.procedures.commands._session import add_session_arguments, open_session, progress_printer
from selfview.procedures.livefeed import live_feed
from selfview.procedures.view import watch, viewing, with_progress


def register(sub):
    p = sub.add_parser(
        "park",
        help="park the gripper on the plate (approach, open, press, settle) and grab a picture",
        description=(
            "Approach above the plate's taught location, open the gripper and wait for its switch, descend in a "
            "straight line until the fingertips press the plate (the foam lets it tilt into coincidence with the "
            "fingertip plane), settle, grab a picture. The robot stays parked."
        ),
    )
    add_session_arguments(p)
    p.add_argument("--out", metavar="IMG.png", help="write the picture here")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_view_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    if args.out is not None:
        from selfview.files.io_safe import PICTURE_EXTENSIONS
        from selfview.procedures.commands._common import output_file

        output_file(args.out, "--out", PICTURE_EXTENSIONS)  # before anything moves
    with viewing(args, "park") as view:
        return _run(args, view)


def _run(args, view) -> int:
    say = with_progress(view, progress_printer())
    cell, session = open_session(args, say)
    with session, live_feed(view, session) as feed:
        watch(view, session, feed and feed.on_step)
        img = session.park()
    if img is None:  # dry run
        return 0
    if view:
        view.frame(img)
        view.update(numbers={"picture": f"{img.shape[1]}x{img.shape[0]}", "mean grey": float(img.mean())})
        view.verdict(True, "parked on the plate; the picture is the one a calibration would use")
    if args.out is not None:
        write_image(args.out, img)
    if args.json:
        print_json({"picture": args.out, "size": [int(img.shape[1]), int(img.shape[0])], "mean_grey": float(img.mean())})
    else:
        print(f"parked; picture {img.shape[1]}x{img.shape[0]}" + (f" written to {args.out}" if args.out else ""))
    return 0
