"""``selfview calibrate``: off-line calibration from one picture of the gripper parked on the plate.

With ``--image`` it calibrates a picture file; without it, it runs the ``calibrate`` procedure on the cell
(park, grab, calibrate, save, depart) — see ``selfview calibrate --help``.
"""

from __future__ import annotations

import sys

from selfview.procedures.commands._common import add_cell_argument, load_cell_arg, print_json


def read_picture(path) -> tuple:
    """(grey picture as a 2-D uint8 array, SHA-256 of the file) or ``ImageError`` naming the file; the
    picture's size is checked in its header before it is decoded (``selfview.io_safe.read_picture``)."""
    from selfview.io_safe import read_picture as checked_read

    return checked_read(path)


def register(sub):
    p = sub.add_parser(
        "calibrate",
        help="off-line calibration (f, kappa, C_H_W, C_H_G) from one picture of the gripper parked on the plate",
        description=(
            "Off-line calibration (the paper's section 3). Tsai's coplanar method on the plate's discs gives f, kappa "
            "and the plate pose C_H_W; the fingertip corners and the Plane Coincidence Constraint give the "
            "gripper-to-camera transform C_H_G, with no robot kinematics. The result is written atomically to "
            "--out; a previous file is kept in OUT.history/. On any failure nothing is written."
        ),
    )
    add_cell_argument(p)
    p.add_argument("--image", required=True, metavar="IMG", help="picture of the gripper parked on the plate")
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
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from selfview.calfile import save_calibration
    from selfview.offline import calibrate_offline

    cell = load_cell_arg(args)
    img, sha = read_picture(args.image)
    res = calibrate_offline(img, cell, state=args.state, mode=args.mode, points=args.points, image_sha256=sha)
    kept = save_calibration(res.calibration, args.out)
    s = res.summary()
    s["out"] = str(args.out)
    s["previous_kept_as"] = str(kept) if kept else None
    if args.json:
        print_json(s)
        return 0
    H = res.calibration.C_H_G
    lines = [
        f"calibrated {args.image} ({s['discs_used']} discs, corners {', '.join(s['corners_found'])})",
        f"  f = {s['f']:.2f} px   kappa = {s['kappa']:.4e} px^-2   residual rms {s['rms_px']:.3f} px, max {s['max_px']:.3f} px",
        f"  TCP in camera: x {H[0, 3]:+.3f}  y {H[1, 3]:+.3f}  z {H[2, 3]:+.3f} mm   PCC residual {s['pcc_rms_mm']:.3f} mm",
        "  C_H_G =",
        *(f"    [{' '.join(f'{v:+.6f}' for v in row)}]" for row in H),
        f"written to {args.out}" + (f" (previous kept as {kept})" if kept else ""),
    ]
    print("\n".join(lines), file=sys.stdout)
    return 0
