"""``selfview robot``: command the PUMA 260 over VAL-II (a real controller's terminal port or the simulator).

Every motion (move, moves, appro, depart, drive, ready) goes through the engine: its plan is checked
against the limits first, and on any error, Ctrl-C or termination signal (SIGTERM, SIGHUP, SIGQUIT) the
engine writes ABORT (confirmed or reported as not) before the command ends (exit 128+N for signal N:
130 for Ctrl-C, 143 for SIGTERM). APPRO and DEPART take distances >= 0 only."""

from __future__ import annotations

import argparse

from selfview.procedures.commands._common import BAUD, SECONDS, number, numeric, print_json
from selfview.errors import ConfigError

_ACTIONS = {
    "where": "print the pose (X Y Z O A T) and the joints",
    "ready": "move to READY (arm straight up)",
    "calibrate": "CAL (answers 'Are you sure' with Y)",
    "speed": "set the monitor SPEED in percent",
    "move": "joint-interpolated motion to NAME or to X Y Z O A T",
    "moves": "straight-line motion to NAME or to X Y Z O A T",
    "appro": "approach NAME (or X Y Z O A T) at a distance D mm along its tool z",
    "depart": "back off D mm along the tool z",
    "drive": "turn joint J by DEG at SPEED percent",
    "abort": "stop the current motion",
    "here": "record the current pose as location NAME",
    "define": "define location NAME = X Y Z O A T",
    "point": "show location NAME",
}


#: What each motion is called when it is done.
_DONE = {"ready": "READY", "move": "MOVE", "moves": "MOVES (straight line)", "appro": "APPRO", "depart": "DEPART",
         "drive": "DRIVE"}


def _number(text: str, what: str) -> float:
    """A coordinate, angle, distance or speed typed on the command line: ASCII digits, finite, within
    +-10,000 (a wider number is a typing error, not a pose); exit 2 otherwise."""
    return number(text, what, lo=-1e4, hi=1e4)


def _target(values: list[str], what: str):
    """A location name or six numbers (x, y, z mm, o, a, t deg)."""
    if len(values) == 1:
        return values[0]
    if len(values) == 6:
        return tuple(_number(v, f"{what} {k}") for v, k in zip(values, "XYZOAT"))
    raise ConfigError(f"{what}: expected a location name or six numbers X Y Z O A T, got {' '.join(values)!r}")


def register(sub):
    p = sub.add_parser(
        "robot",
        help="command the PUMA 260 over VAL-II (where, move, calibrate, ...)",
        description=(
            "Drive a VAL-II controller through its terminal port. --url is a device path (/dev/ttyS0, a pty), "
            "socket://HOST:PORT, or spy://PATH?file=dump.txt for a traffic dump. Poses are the tool point in the "
            "robot base frame: X Y Z in mm, O A T in degrees (VAL's Euler angles). Limits (workspace box, joint "
            "limits, maximum speed) are checked before anything is sent."
        ),
    )
    p.add_argument("--url", required=True, help="the controller's terminal port (path or URL)")
    p.add_argument("--timeout", type=SECONDS, default=2.0, metavar="S", help="reply timeout of non-motion commands (default 2 s)")
    p.add_argument("--baud", type=BAUD, default=9600, help="baud rate of a real serial port (default 9600)")
    p.add_argument("--dialect", default=None, metavar="DIALECT.yaml", help="controller dialect (echo, prompt, error texts, ...)")
    p.add_argument("--limits", default=None, metavar="LIMITS.yaml", help="client-side limits (workspace_mm, max_speed_pct, ...)")
    p.add_argument("--kinematics", default=None, metavar="KIN.yaml",
                   help="the arm's link lengths and TOOL (tool_mm), to check WHERE's pose against its joints")
    p.add_argument("--max-speed", type=numeric(lo=0, lo_open=True, hi=100, name="percent"), default=None, metavar="PCT", help="override the limits' maximum speed")
    actions = p.add_subparsers(dest="action", metavar="ACTION")
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    a = {name: actions.add_parser(name, help=h, description=h, parents=[common]) for name, h in _ACTIONS.items()}
    a["speed"].add_argument("pct", help="percent (0 < pct <= the maximum speed)")
    for name in ("move", "moves"):
        a[name].add_argument("target", nargs="+", metavar="NAME | X Y Z O A T")
    a["appro"].add_argument("target", nargs="+", metavar="NAME | X Y Z O A T")
    a["appro"].add_argument("distance", metavar="D", help="mm back from NAME along its tool z (>= 0)")
    a["depart"].add_argument("distance", metavar="D", help="mm back along the tool z (>= 0)")
    a["drive"].add_argument("joint", type=numeric(integer=True, lo=1, hi=6, name="joint"), metavar="J", help="joint 1..6")
    a["drive"].add_argument("deg", metavar="DEG")
    a["drive"].add_argument("speed", metavar="SPEED", help="percent")
    for name in ("here", "point", "define"):
        a[name].add_argument("name", metavar="NAME")
    a["define"].add_argument("pose", nargs=6, metavar="V", help="X Y Z O A T")
    p.set_defaults(func=lambda args: run(args) if args.action else (p.print_help(), 2)[1])
    return p


def make_robot(args):
    """The driver the arguments describe (not connected)."""
    from selfview.drivers.robot import open_robot

    return open_robot(args.url, None, dialect=args.dialect, limits=args.limits,
                      kinematics=getattr(args, "kinematics", None), max_speed=args.max_speed, timeout_s=args.timeout,
                      baudrate=args.baud)


def _motion_step(args):
    """The engine step of a motion action."""
    from selfview.procedures.engine import Step

    act = args.action
    if act == "ready":
        return Step("ready")
    if act in ("move", "moves"):
        return Step(act, {"target": _target(args.target, act.upper())})
    if act == "appro":
        return Step("appro", {"target": _target(args.target, "APPRO"), "distance_mm": _number(args.distance, "APPRO distance")})
    if act == "depart":
        return Step("depart", {"distance_mm": _number(args.distance, "DEPART distance")})
    return Step("drive", {"joint": args.joint, "deg": _number(args.deg, "DRIVE angle"),
                          "speed": _number(args.speed, "DRIVE speed")})


def _run_motion(robot, step) -> None:
    """One motion through the engine: plan checked first; ABORT and a report on any error or Ctrl-C."""
    import sys

    from selfview.procedures.engine import CellDevices, Engine

    engine = Engine(CellDevices(robot=robot), progress=lambda msg: print(f"selfview robot: {msg}", file=sys.stderr))
    engine.run(lambda e: e.execute(step), [step])


def run(args) -> int:
    robot = make_robot(args)
    act = args.action
    out: dict = {"command": act, "url": args.url}
    step = _motion_step(args) if act in ("move", "moves", "appro", "depart", "drive", "ready") else None
    if act == "abort":  # the controller may be busy: no resynchronising CR, ABORT first
        robot.connect(sync=False)
        try:
            res = robot.abort()
        finally:
            robot.close()
        out["abort"] = {"written": res.written, "confirmed": res.confirmed, "detail": res.detail}
        if args.json:
            print_json(out)
        else:
            print(str(res))
        return 0 if res.confirmed else 4
    with robot:
        if step is not None:
            _run_motion(robot, step)
        elif act == "speed":
            robot.speed(_number(args.pct, "SPEED"))
            out["speed_pct"] = float(args.pct)
        elif act == "calibrate":
            robot.calibrate()
        elif act == "here":
            out["location"] = {"name": args.name, "pose": list(robot.here(args.name))}
        elif act == "point":
            out["location"] = {"name": args.name, "pose": list(robot.location(args.name))}
        elif act == "define":
            robot.define(args.name, tuple(_number(v, f"{args.name} {k}") for v, k in zip(args.pose, "XYZOAT")))
        if act not in ("speed", "define"):
            w = robot.where()
            out["where"] = w.to_dict()
        else:
            w = None
    if step is not None:
        out["done"] = step.describe()
    if args.json:
        print_json(out)
        return 0
    d = robot.dialect
    if "location" in out:
        print(f"{out['location']['name']}:")
        print(d.format_header(d.pose_header))
        print(d.format_values(out["location"]["pose"]))
    if step is not None:
        desc = step.describe()
        print(f"{_DONE[act]} done" + (f" ({desc})" if desc != act else "") + "; the arm is now at:")
    elif act == "calibrate":
        print("CAL done: the arm is calibrated; it is now at:")
    if w is not None:
        print(d.format_header(d.pose_header))
        print(d.format_values(w.pose))
        print(d.format_header(d.joint_header))
        print(d.format_values(w.joints))
    elif act == "speed":
        print(f"SPEED {out['speed_pct']:g}")
    else:
        print("ok")
    return 0
