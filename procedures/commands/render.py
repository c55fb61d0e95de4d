"""``selfview render``: one picture of the simulated wrist camera and its ground truth.

The simulated cell is built from the cell description and a seed, the gripper parked on the plate
(Plane Coincidence Constraint, eq. 5-7) with its jaws in the chosen state, the camera optionally
disturbed on its mount; the picture goes to a PNG and its ground truth to a JSON file.
"""

from __future__ import annotations

import json

from selfview.procedures.commands._common import SEED, add_cell_argument, load_cell_arg, output_file, print_json, write_image
from selfview.errors import ConfigError


def register(sub):
    p = sub.add_parser(
        "render",
        help="render the simulated wrist camera's picture of the parked gripper, with its ground truth",
        description=(
            "Build the simulated cell from CELL and --seed, park the gripper on the plate (or lift it "
            "over the table with --free) with its jaws in --state, apply each --disturb to the camera "
            "mount in order, and write the 8-bit grey picture (PNG) and its ground truth (JSON: f, kappa, "
            "principal_point, C_H_G, C_H_W, discs [[row, col, u, v, visible], ...], corners {name: "
            "[u, v, visible]}; mm and px). The same seed gives the same picture, byte for byte. Prints "
            "a one-line JSON summary."
        ),
    )
    add_cell_argument(p)
    p.add_argument("--out", required=True, metavar="IMG.png", help="where to write the picture (PNG)")
    p.add_argument("--seed", type=SEED, default=0, help="seed of the simulated cell and of the sensor noise (default 0)")
    p.add_argument("--state", default=None, metavar="STATE",
                   help="gripper state whose jaw gap to use, e.g. open or closed (default: the cell's calibrate_in)")
    p.add_argument("--disturb", action="append", default=[], metavar="SERIES",
                   help="disturb the camera mount as simulation.disturbances.SERIES says (cable, tilt); repeatable")
    p.add_argument("--free", action="store_true",
                   help="lift the gripper off the plate over the textured table instead of parking it")
    p.add_argument("--profile", default="ideal", metavar="NAME",
                   help="the simulated cell's imperfections: ideal, realistic, paper-like (default %(default)s)")
    p.add_argument("--truth", default=None, metavar="TRUTH.json", help="where to write the ground truth (JSON)")
    p.set_defaults(func=run)
    return p


def _json_text(obj: dict) -> str:
    """One JSON object, a top-level key per line (the values compact)."""
    rows = [f" {json.dumps(k)}: {json.dumps(v, allow_nan=False)}" for k, v in obj.items()]
    return "{\n" + ",\n".join(rows) + "\n}\n"


def run(args) -> int:

    from selfview.mocks.render import LIFTED_W_H_G, render
    from selfview.mocks.world import SimWorld

    cell = load_cell_arg(args)
    out = output_file(args.out, "--out", (".png",))
    truth_path = output_file(args.truth, "--truth") if args.truth is not None else None
    state = args.state or cell.gripper.calibrate_in
    gap = cell.gripper.gap(state)  # raises ConfigError naming the known states

    world = SimWorld(cell, seed=args.seed, imperfections=args.profile)
    if args.free:
        world.set_tcp(world.base_H_plate0 @ LIFTED_W_H_G)
    else:
        world.park()
    world.set_jaw(gap, state)
    for series in args.disturb:
        world.disturb(series)
    result = render(world, seed=args.seed)

    write_image(out, result.image)
    if truth_path is not None:
        from selfview.files.io_safe import atomic_write

        atomic_write(truth_path, _json_text(result.truth).encode("utf-8"), error=ConfigError, what="ground truth (--truth)")
    print_json(
        {
            "out": str(out),
            "truth": None if truth_path is None else str(truth_path),
            "seed": args.seed,
            "state": state,
            "parked": not args.free,
            "disturb": list(args.disturb),
            "visible_discs": int(result.disc_visible.sum()),
            "visible_corners": [n for n, v in result.truth["corners"].items() if v[2]],
        }
    )
    return 0
