"""``selfview monitor``: keep C_H_G true while the robot works (update, recalibrate or alarm per frame)."""

from __future__ import annotations

import json
import sys

from selfview.procedures.commands._common import COUNT, add_view_arguments, numeric
from selfview.procedures.commands._session import add_session_arguments, open_session, progress_printer
from selfview.procedures.view import decision_state, tracked_frames, viewing, watch, with_progress


def register(sub):
    p = sub.add_parser(
        "monitor",
        help="grab frames as the robot works, track the fingertips, update / recalibrate / raise the alarm",
        description=(
            "The on-line calibration (section 4). For each frame: find the fingertip corners near where the current "
            "C_H_G predicts them, estimate the camera's motion (default 4P-U), and by the cell's monitor limits "
            "apply the update, recalibrate (4P-R / 5P-R), or raise the alarm and stop the robot. Every decision is "
            "printed with delta, d and the residual. The fingertips are measured by fitting both fingers' whole "
            "silhouette; a frame where that fit is not believed (its quality is printed with --json), where fewer "
            "than 3 fingertips show, where no picture came, or whose picture is black, blank or bit-identical to the "
            "previous one (a stuck grabber: a camera's noise never repeats) is a missed frame: C_H_G unchanged, "
            "the fingertips searched for again, and the alarm only after the cell's monitor.max_missed_frames (default 3) missed "
            "frames in a row. Poses alternating between two values frame after frame (a loose mount, or two "
            "cameras on one input) raise the alarm. With --drift (simulation) the camera creeps on its mount by "
            "that many degrees per frame, to watch the policy at work."
        ),
    )
    add_session_arguments(p)
    p.add_argument("--calibration", required=True, metavar="CAL.yaml", help="calibration file to start from")
    p.add_argument("--frames", type=COUNT, default=20, help="frames to judge (default %(default)s)")
    p.add_argument("--method", default="4P-U", choices=("3P-U", "4P-U", "5P-U", "3P-I", "4P-I", "5P-I"),
                   help="update method (default %(default)s)")
    p.add_argument("--drift", type=numeric(lo=-180, hi=180, name="degrees"), default=0.0, metavar="DEG",
                   help="simulation: rotate the camera by DEG per frame about the cable axis")
    p.add_argument("--apply", action="store_true", help="write the final C_H_G to the calibration file (history kept)")
    p.add_argument("--json", action="store_true", help="print one JSON line per decision on stdout")
    add_view_arguments(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    with viewing(args, "monitor") as view:
        return _run(args, view)


def _run(args, view) -> int:
    from selfview.errors import ConfigError

    if args.frames < 1:
        raise ConfigError(f"--frames: expected at least 1, got {args.frames}")
    if args.drift and args.real:
        raise ConfigError("--drift moves the simulated camera; it has no meaning with --real")
    say = with_progress(view, progress_printer())
    cell, session = open_session(args, say)
    on_frame = tracked_frames(view, args.calibration, cell) if view else None

    def show(rec):
        if view:
            decision_state(view, rec, cell.monitor)
        if args.json:
            print(json.dumps({k: v for k, v in rec.items() if k != "estimate"}, default=str), flush=True)
        else:
            def num(key):
                v = rec.get(key)
                return "  -  " if v is None else f"{v:.3f}"

            sg = rec.get("tcp_sigma_mm")
            print(f"frame {rec['frame']:3d}: {rec['action']:<11s} delta {num('delta_deg')} deg, d {num('d_mm')} mm, "
                  f"rms {num('rms_px')} px" + (f", TCP 1-sigma z {sg[2]:.4f} mm" if sg else "") + f" - {rec['reason']}"
                  + (f" [fingertips {rec['fingertips']}]" if rec.get("fingertips") else ""), flush=True)

    from selfview.files.calfile import load_calibration, save_calibration

    started = load_calibration(args.calibration)  # the version a final --apply may replace
    with session:
        watch(view, session)
        disturb = None
        if args.drift:
            w = session.sim.world
            axis = cell.simulation.disturbances["cable"]
            disturb = lambda k: w.disturb_by_angle(axis.axis_C, args.drift, axis.pivot_C, series="drift")  # noqa: E731
        records = session.monitor(args.calibration, frames=args.frames, method=args.method, disturb=disturb,
                                  on_decision=show, on_frame=on_frame)
    if args.apply:
        cal = started
        last = records[-1]
        import numpy as np

        cal.C_H_G = np.asarray(last["C_H_G"], float)
        cal.updates.append({"by": "monitor", "frames": args.frames, "method": args.method})
        save_calibration(cal, args.calibration, expected=started)
        print(f"C_H_G written to {args.calibration} (previous kept in its .history)", file=sys.stderr)
    return 0
