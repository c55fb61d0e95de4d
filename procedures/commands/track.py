"""``selfview track``: on-line calibration from one new picture of the fingertips."""

from __future__ import annotations

import numpy as np

from selfview.procedures.commands._common import add_cell_argument, add_view_arguments, load_cell_arg, print_json
from selfview.procedures.view import viewing

from selfview.api import METHODS as METHOD_CHOICES


def register(sub):
    p = sub.add_parser(
        "track",
        help="on-line calibration from one picture: NP-U / NP-I / NP-R, or the update/recalibrate/alarm policy",
        description=(
            "Find the fingertip corners near where the calibration's C_H_G predicts them and estimate how far the "
            "camera moved on its mount. Methods: NP-U the paper's differential update (eq. 11-17), NP-I the exact "
            "iterative update, NP-R recalibration of the exterior orientation; 'auto' applies the cell's monitor "
            "policy (update below update_limit, recalibrate below alarm_limit, else alarm: exit code 6 and nothing "
            "written). E: the model-based estimate, the camera's motion fitted to all the edge samples of both "
            "fingers' silhouettes at once (hundreds of constraints instead of 4 corners; needs --measure model). "
            "With --apply the new C_H_G is written to the calibration file atomically, history kept."
        ),
    )
    add_cell_argument(p)
    p.add_argument("--calibration", required=True, metavar="CAL.yaml")
    p.add_argument("--image", required=True, metavar="IMG")
    p.add_argument("--method", default="4P-U", choices=METHOD_CHOICES, help="default %(default)s")
    p.add_argument("--state", default=None, help="gripper state in the picture (default: the calibration's)")
    p.add_argument("--measure", default="model", choices=("model", "corners"),
                   help="how the fingertips are measured: 'model' fits the whole silhouette of both fingers and says "
                        "when it has lost them (default); 'corners' the corner search alone")
    p.add_argument("--apply", action="store_true", help="write the new C_H_G to the calibration file")
    p.add_argument("--no-pictures", action="store_true",
                   help="do not keep the picture and its annotated copy beside the calibration file")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    add_view_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    with viewing(args, "track") as view:
        return _run(args, view)


def _run(args, view) -> int:
    from selfview.api import track
    from selfview.procedures.commands.calibrate import read_picture
    from selfview.procedures.results import draw_tracked, keep_pictures
    from selfview.files.calfile import load_calibration, save_calibration
    from selfview.errors import AlarmError
    from selfview.estimation.pcc import jaw_gap_of

    cell = load_cell_arg(args)
    cal = load_calibration(args.calibration)
    img, _ = read_picture(args.image)
    if view:
        view.doing(f"finding the fingertips in {args.image}")
        view.frame(img)
    tr = track(img, cal, args.method, cell=cell, state=args.state, measure=args.measure)
    out = tr.to_dict()
    ft = tr.fingertips
    found_names = tr.points_found
    pG = cal.points_G[args.state or cal.state]
    gap = jaw_gap_of(pG)
    new = None if tr.decision == "alarm" else np.asarray(tr.C_H_G_orthonormal, float)
    shown = new if new is not None else cal.C_H_G
    draw = lambda im: draw_tracked(im, cal.camera, shown, pG, ft, boxes=cell.gripper.finger_boxes_G(gap))  # noqa: E731
    if view:
        view.frame(draw(img))
        view.update(numbers={k: out[k] for k in ("method", "decision", "delta_deg", "d_mm", "rms_px")}
                    | {"points found": ", ".join(found_names), "TCP 1-sigma x y z [mm]": _sigma_text(tr.tcp_sigma_mm)})
        view.verdict(out["decision"] != "alarm", f"{out['decision']}: {out.get('reason') or out['method']}")
    if not args.no_pictures:
        out["pictures"] = keep_pictures(args.calibration, img, draw, "track-")
    if args.apply and new is not None:
        cal.C_H_G = new
        if "pictures" in out:
            cal.pictures = {f"track {k}": v for k, v in out["pictures"].items()}
        cal.updates.append({"by": "track", "method": out["method"], "decision": out["decision"],
                            "delta_deg": float(out["delta_deg"]), "d_mm": float(out["d_mm"])})
        save_calibration(cal, args.calibration, expected=cal)
        out["applied"] = True
    else:
        out["applied"] = False
    if args.json:
        print_json(out)
    else:
        H = np.asarray(out["C_H_G"])
        print(f"{out['method']}: {out['decision']}  delta {out['delta_deg']:.4f} deg  d {out['d_mm']:.4f} mm  "
              f"rms {out['rms_px']:.3f} px  points {', '.join(out['points_used'])}")
        print(f"  TCP in camera: x {H[0, 3]:+.3f}  y {H[1, 3]:+.3f}  z {H[2, 3]:+.3f} mm"
              + ("  (written to the calibration file)" if out["applied"] else ""))
        print(f"  TCP 1-sigma:   {_sigma_text(tr.tcp_sigma_mm)} mm (the estimate's and the calibration's)")
    if out["decision"] == "alarm":
        raise AlarmError(out.get("reason", "alarm"))
    return 0


def _sigma_text(sg) -> str:
    if sg is None:
        return "not known (no redundant point, or the model's estimate)"
    return "  ".join(f"{a} {v:.4f}" for a, v in zip("xyz", sg))
