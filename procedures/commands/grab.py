"""``selfview grab``: take one (averaged) picture from the frame grabber and write it to a file."""

from __future__ import annotations

import argparse

from selfview.files.io_safe import PICTURE_EXTENSIONS
from selfview.procedures.commands._common import COUNT, SECONDS, SEED, add_cell_argument, load_cell_arg, output_file, print_json, write_image
from selfview.errors import ConfigError


def register(sub):
    p = sub.add_parser(
        "grab",
        help="grab a picture from the camera (V4L2 grabber, recording or sim://) into a file",
        description=(
            "Take one checked grey picture and write it (PNG, or any format OpenCV writes by the extension). URLs: "
            "v4l2:///dev/video0?input=1&std=pal&width=768&height=576&format=GREY, frames:///dir/img_%%03d.png, "
            "file:///dir/run.avi, sim:// (the simulated cell built from --cell and --seed, gripper parked on the plate)."
        ),
    )
    p.add_argument("--camera", metavar="URL",
                   help="the camera (required): v4l2:///dev/video0?input=1&std=pal, frames:///dir/img_%%03d.png, "
                        "file:///run.avi, sim://")
    p.add_argument("--url", dest="camera", help=argparse.SUPPRESS)  # the earlier name, still read
    p.add_argument("--out", required=True, metavar="IMG.png", help="picture file to write")
    p.add_argument("--average", type=COUNT, default=1, metavar="N", help="average N frames (default 1)")
    p.add_argument("--field", action="store_true", help="one field only (every other row, for a moving scene)")
    p.add_argument("--timeout", type=SECONDS, default=2.0, metavar="S", help="frame timeout (default 2 s)")
    p.add_argument("--seed", type=SEED, default=0, help="sim://: seed of the simulated world")
    add_cell_argument(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=run)
    return p


def run(args) -> int:

    from selfview.drivers.frame_grabber_v4l2 import FrameGrabber, parse_grabber_url

    if not args.camera:
        raise ConfigError("--camera URL is required: the frame source (sim:// for the simulated camera)")
    out = output_file(args.out, "--out", PICTURE_EXTENSIONS)
    attachment = None
    if parse_grabber_url(args.camera).scheme == "sim":
        from selfview.mocks.sim_camera import attach_world
        from selfview.mocks.world import SimWorld

        world = SimWorld(load_cell_arg(args), seed=args.seed)
        world.park()
        attachment = attach_world(world)
    try:
        with FrameGrabber(args.camera, timeout_s=args.timeout) as grabber:
            frame = grabber.grab(average=args.average, field=args.field)
    finally:
        if attachment is not None:
            attachment.detach()
    write_image(out, frame.image)
    info = {
        "url": args.camera,
        "out": str(out),
        "width": int(frame.image.shape[1]),
        "height": int(frame.image.shape[0]),
        "average": frame.count,
        "field": frame.field,
        "index": frame.index,
        "mean_grey": round(float(frame.image.mean()), 2),
    }
    if args.json:
        print_json(info)
    else:
        print(f"{out}: {info['width']}x{info['height']}, mean grey {info['mean_grey']}")
    return 0
