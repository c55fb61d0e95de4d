"""``selfview camera``: Tsai's coplanar calibration from point correspondences (Willson's format)."""

from __future__ import annotations

import numpy as np

from selfview.procedures.commands._common import numeric, print_json
from selfview.maths.geometry import rpy_from_R
from selfview.estimation.tsai import FREE_CENTRE_MODES, MODES, calibrate_coplanar, load_willson_points


def register(sub):
    p = sub.add_parser(
        "camera",
        help="Tsai coplanar calibration from correspondences 'xw yw zw u v'",
        description=(
            "Calibrate f, kappa and C_H_W by Tsai's coplanar method (Willson's implementation) from plate "
            "points and their pixels, one correspondence per line 'xw yw zw u v' (mm, mm, mm, px, px; "
            "zw = 0; '#' starts a comment). The principal point is given, not calibrated, unless "
            "--mode full+centre or willson."
        ),
    )
    p.add_argument("--points", required=True, metavar="FILE", help="correspondences, one 'xw yw zw u v' per line")
    p.add_argument(
        "--principal-point", required=True, nargs=2, type=numeric(lo=-1e5, hi=1e5, name="px"), metavar=("CX", "CY"),
        help="principal point in pixels (the start value with --mode full+centre or willson)",
    )
    p.add_argument("--aspect", type=numeric(lo=0.5, hi=2.0, name="aspect"), default=1.0, help="horizontal factor: X^ = A (u - cx) (default 1)")
    p.add_argument(
        "--mode", choices=MODES, default="full",
        help=(
            "tsai: f, Tz, kappa as Tsai published; full (default): pose, f, kappa; full+centre: also cx, cy; "
            "willson: Willson's full optimisation (centre free) as his v3.0b3 runs it, stopping where his "
            "optimiser stops rather than at the minimum"
        ),
    )
    p.add_argument(
        "--size", nargs=2, type=numeric(integer=True, lo=1, hi=16384, name="px"), default=(768, 576), metavar=("W", "H"),
        help="picture size in pixels, recorded with the camera (default 768 576)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the summary")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    p_W, uv = load_willson_points(args.points)
    cx, cy = args.principal_point
    res = calibrate_coplanar(
        p_W, uv, cx=cx, cy=cy, aspect=args.aspect, mode=args.mode, width=args.size[0], height=args.size[1]
    )
    if args.json:
        print_json(res.to_dict())
        return 0
    cam, H = res.camera, res.C_H_W
    rx, ry, rz = np.degrees(rpy_from_R(H))
    lines = [
        f"Tsai coplanar calibration ({res.mode}) from {len(uv)} points of {args.points}",
        f"  f            = {cam.f:.4f} px",
        f"  kappa        = {cam.kappa:.6e} px^-2",
        f"  principal pt = ({cam.cx:.3f}, {cam.cy:.3f}) px{'' if res.mode in FREE_CENTRE_MODES else ' (fixed)'}",
        f"  aspect       = {cam.aspect:g}",
        f"  T            = ({H[0, 3]:.4f}, {H[1, 3]:.4f}, {H[2, 3]:.4f}) mm",
        f"  R = Rz Ry Rx, (Rx, Ry, Rz) = ({rx:.6f}, {ry:.6f}, {rz:.6f}) deg",
        "  C_H_W =",
        *(f"    [{' '.join(f'{v:12.6f}' for v in row)}]" for row in H),
        f"  distorted image error: rms {res.rms_px:.6f}, mean {res.mean_px:.6f}, max {res.max_px:.6f} px, "
        f"sse {res.sse_px2:.6f} px^2",
    ]
    print("\n".join(lines))
    return 0
