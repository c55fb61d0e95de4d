"""Options shared by the commands that run a procedure on a cell (simulated by default, or --real)."""

from __future__ import annotations

import sys
import time

from selfview.procedures.commands._common import FACTOR, SEED, add_cell_argument, load_cell_arg


#: Every command that builds the simulated cell builds the same one unless told otherwise: a perfect cell
#: with the nominal camera (``--profile realistic --sim-camera realistic``: a real cell's errors and a camera
#: to measure first), so that one command's figures hold for the next.
DEFAULT_PROFILE = "ideal"
DEFAULT_SIM_CAMERA = "ideal"


def add_session_arguments(p, *, seed_default: int = 0, camera_file: bool = False) -> None:
    """The cell options; --profile and --sim-camera default to ``DEFAULT_PROFILE`` and ``DEFAULT_SIM_CAMERA``
    for every command. ``camera_file``: ``--camera`` also takes a camera file (CAMERA.yaml, from ``selfview
    intrinsics``) and may be given twice; ``camera_arguments`` sorts the values."""
    add_cell_argument(p)
    g = p.add_argument_group("cell", "which devices; by default the simulated cell, every device on its real channel")
    g.add_argument("--real", action="store_true", help="use the lab's devices named by --robot, --gripper, --camera")
    g.add_argument("--robot", metavar="URL", help="VAL-II terminal: /dev/ttyS0, serial:///dev/ttyS0?baud=9600, socket://host:port")
    g.add_argument("--gripper", metavar="URL", help="valve terminal: modbus-tcp://host:502?unit=1 or modbus-rtu:///dev/ttyUSB0?baud=19200")
    if camera_file:
        g.add_argument("--camera", metavar="URL|CAMERA.yaml", action="append", default=None,
                       help="a camera file measured by 'selfview intrinsics' (its principal point and aspect replace the "
                            "nominal ones), and/or with --real the frame grabber's URL (v4l2:///dev/video0?input=1&std=pal, "
                            "frames:///dir/img_%%03d.png); may be given twice")
    else:
        g.add_argument("--camera", metavar="URL", help="frame grabber: v4l2:///dev/video0?input=1&std=pal, frames:///dir/img_%%03d.png")
    g.add_argument("--seed", type=SEED, default=seed_default, help="seed of the simulated cell (default %(default)s)")
    g.add_argument("--sim-camera", choices=("ideal", "realistic"), default=DEFAULT_SIM_CAMERA,
                   help="the simulated camera: ideal (the cell's nominal principal point and aspect) or realistic "
                        "(drawn from a real camera's ranges: centre up to 15 px off, aspect 0.97-1.07) "
                        "(default %(default)s)")
    g.add_argument("--time-scale", type=FACTOR, default=0.02,
                   help="simulated robot motions take this fraction of real time (default %(default)s)")
    g.add_argument("--profile", default=DEFAULT_PROFILE, metavar="NAME",
                   help="the simulated cell's imperfections: ideal (a perfect cell), realistic (a real CCIR cell's, "
                        "each at its published magnitude), paper-like (the paper's cell) (default %(default)s)")
    g.add_argument("--dry-run", action="store_true", help="print the steps, move nothing")


def camera_arguments(values) -> tuple[str | None, str | None]:
    """(grabber URL, camera file) from the values of an appending ``--camera``: a value with '://' or
    starting with /dev/ is a URL, any other a camera file. ``ConfigError`` for two of one kind."""
    from selfview.errors import ConfigError

    urls, files = [], []
    for v in values or []:
        (urls if ("://" in v or v.startswith("/dev/")) else files).append(v)
    if len(urls) > 1 or len(files) > 1:
        raise ConfigError(f"--camera given {len(values)} times: expected at most one grabber URL and one camera file")
    return (urls[0] if urls else None), (files[0] if files else None)


def progress_printer(quiet: bool = False):
    t0 = time.monotonic()

    def say(msg: str) -> None:
        if not quiet:
            print(f"[{time.monotonic() - t0:7.1f} s] {msg}", file=sys.stderr, flush=True)

    return say


def open_session(args, progress=None):
    """A CellSession (not yet opened) for the command's arguments."""
    from selfview.procedures.runs import CellSession

    cell = load_cell_arg(args)
    ask = None if not sys.stdin.isatty() else (lambda text: input(text + " "))
    if args.real:
        return cell, CellSession.real(cell, robot=args.robot, gripper=args.gripper, camera=args.camera,
                                      dry_run=args.dry_run, ask=ask, progress=progress)
    for nm in ("robot", "gripper", "camera"):
        if getattr(args, nm):
            from selfview.errors import ConfigError

            raise ConfigError(f"--{nm} is for a real cell: add --real (without it the simulated cell is used)")
    from selfview.mocks.imperfections import resolve

    resolve(args.profile)  # a clear error for an unknown profile before anything starts
    return cell, CellSession.simulated(cell, seed=args.seed, time_scale=args.time_scale, dry_run=args.dry_run,
                                       ask=ask, progress=progress, profile=args.profile,
                                       camera=getattr(args, "sim_camera", "ideal"))
