"""``selfview devices``: check that each configured device answers and print what it reports."""

from __future__ import annotations

from selfview.procedures.commands._common import print_json
from selfview.procedures.commands._session import add_session_arguments, open_session


def register(sub):
    p = sub.add_parser(
        "devices",
        help="check that the robot, the gripper valve and the camera answer; print what they report",
        description="Connects to each configured device (the simulated cell unless --real), asks it for its "
        "state (robot pose and joints, gripper switches and valve outputs, one camera frame) and disconnects.",
    )
    add_session_arguments(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    cell, session = open_session(args)
    with session:
        if args.dry_run:
            print("devices:", vars(session.urls))
            return 0
        info = session.describe_devices()
    if args.json:
        print_json(info)
        return 0
    r, g, c = info["robot"], info["gripper"], info["camera"]
    print(f"robot    {r['url']}: at x y z o a t = {' '.join(f'{v:.2f}' for v in r['pose_xyzoat'])}; "
          f"joints {' '.join(f'{v:.2f}' for v in r['joints_deg'])} deg")
    print(f"gripper  {g['url']}: jaws {g['state']}; valve outputs {g['outputs']}")
    print(f"camera   {c['url']}: {c['size'][0]}x{c['size'][1]} frame, mean grey {c['mean_grey']:.1f} ({c['source']})")
    return 0
