"""``selfview devices``: check each device on its own and print one row per device."""

from __future__ import annotations

import sys

from selfview.procedures.commands._common import load_cell_arg, print_json
from selfview.procedures.commands._session import add_session_arguments


def register(sub):
    p = sub.add_parser(
        "devices",
        help="check that the robot, the gripper valve and the camera answer; one row each",
        description="Connects to each configured device on its own (the simulated cell unless --real), asks it for "
        "its state (robot pose and joints, gripper switches and valve outputs, one camera frame) and disconnects. "
        "One row per device: answered, failed (and why) or not tried (no URL). Exit status 0 only when every "
        "device answered, else 4.",
    )
    add_session_arguments(p)
    p.add_argument("--json", action="store_true", help="print the table as one JSON object on stdout")
    p.add_argument("--reset", action="store_true",
                   help="after a program died holding a device (killed, a crash, a power cut of the host) and the other "
                        "commands refuse: ABORT the robot, put the valve in its safe state and clear the record, "
                        "then check as usual (check the cell first)")
    p.set_defaults(func=run)
    return p


def _robot(url, cell, timeout_s):
    from selfview.drivers.robot import open_robot

    with open_robot(url, cell, timeout_s=timeout_s) as robot:
        if not robot.knows_poses:
            return "the operator's arm (manual://): it reports no pose", {"manual": True}
        w = robot.where()
        pose, joints = list(w.pose), list(w.joints)
    return (f"at x y z o a t = {' '.join(f'{v:.2f}' for v in pose)}; joints {' '.join(f'{v:.2f}' for v in joints)} deg",
            {"pose_xyzoat": pose, "joints_deg": joints})


def _gripper(url, cell, timeout_s):
    from selfview.drivers.pneumatic_gripper import PneumaticGripper

    g = PneumaticGripper(url)
    try:
        g.connect()
        state, outputs = g.state(), g.outputs()
    finally:
        g.close()
    return f"jaws {state}; valve outputs {outputs}", {"state": state, "outputs": outputs}


def _camera(url, cell, timeout_s):
    from selfview.drivers.frame_grabber_v4l2 import FrameGrabber

    cs = cell.camera
    with FrameGrabber(url, width=cs.width, height=cs.height, timeout_s=timeout_s) as cam:
        img = cam.grab().image
        source = getattr(cam.source, "description", "")
    size = [int(img.shape[1]), int(img.shape[0])]
    return (f"{size[0]}x{size[1]} frame, mean grey {img.mean():.1f}" + (f" ({source})" if source else ""),
            {"size": size, "mean_grey": float(img.mean()), "source": source})


PROBES = (("robot", _robot), ("gripper", _gripper), ("camera", _camera))


def reset_devices(urls: dict, timeout_s: float = 2.0) -> list[str]:
    """The operator has checked the cell after a program died holding a device: ABORT the robot, make
    the valve safe, and clear the records that made the other commands refuse. What was done, one line
    per device; the devices' errors are raised. The operator's arm (``manual://``) has no controller to
    ABORT or record to clear: its line says so."""
    from selfview.drivers.pneumatic_gripper import PneumaticGripper
    from selfview.drivers.puma_val_serial import PumaVAL
    from selfview.drivers.robot import robot_scheme

    done = []
    if urls.get("robot") and robot_scheme(urls["robot"]) == "manual":
        done.append("robot: the operator's arm (manual://) has no controller to ABORT; stop it by hand")
    elif urls.get("robot"):
        robot = PumaVAL(urls["robot"], timeout_s=timeout_s)
        robot.connect(sync=False, clear_stale=True)
        try:
            done.append(f"robot: {robot.abort()}")
        finally:
            robot.close()
    if urls.get("gripper"):
        g = PneumaticGripper(urls["gripper"], poll_s=None)
        g.connect(clear_stale=True)
        try:
            done.append(f"gripper: {g.safe().sentence()}")
        finally:
            g.close()
    return done


def check_devices(urls: dict, cell, timeout_s: float = 2.0) -> list[dict]:
    """One row per device: {device, url, status: answered | failed | not tried, detail, and what it reported}.
    A device's failure never keeps the next one from being tried."""
    from selfview.errors import CellError

    rows = []
    for name, probe in PROBES:
        url = urls.get(name)
        row = {"device": name, "url": url}
        if not url:
            row.update(status="not tried", detail=f"no URL (give --{name} URL)")
        else:
            try:
                detail, info = probe(url, cell, timeout_s)
                row.update(status="answered", detail=detail, **info)
            except (CellError, OSError) as exc:
                row.update(status="failed", detail=f"{type(exc).__name__}: {exc}")
        rows.append(row)
    return rows


def run(args) -> int:
    from selfview.errors import ConfigError

    cell = load_cell_arg(args)
    urls = {"robot": args.robot, "gripper": args.gripper, "camera": args.camera}
    sim = None
    if not args.real:
        given = [nm for nm, u in urls.items() if u]
        if given:
            raise ConfigError(f"--{given[0]} is for a real cell: add --real (without it the simulated cell is used)")
        from selfview.mocks.imperfections import resolve
        from selfview.procedures.simcell import SimulatedCell

        resolve(args.profile)
        sim = SimulatedCell(cell, seed=args.seed, time_scale=args.time_scale, profile=args.profile,
                            camera=args.sim_camera)
        if args.dry_run:
            print("devices: the simulated cell's robot (a pseudo-terminal), gripper (Modbus TCP on 127.0.0.1), "
                  "camera (sim://)")
            return 0
        sim.start()
        urls = vars(sim.urls)
    elif args.dry_run:
        print("devices:", urls)
        return 0
    try:
        if args.reset:
            for line in reset_devices(urls):
                print(f"reset {line}", file=sys.stderr)
        rows = check_devices(urls, cell)
    finally:
        if sim is not None:
            sim.stop()
    ok = all(r["status"] == "answered" for r in rows)
    if args.json:
        print_json({"devices": rows, "all_answered": ok})
    else:
        for r in rows:
            print(f"{r['device']:<8s} {r['status']:<9s} {r['url'] or '-'}: {r['detail']}")
        if not ok:
            print("not every device answered: check the failed ones' cable, power and URL")
    return 0 if ok else 4
