"""``selfview gripper``: open or close the pneumatic gripper, or read its reed switches."""

from __future__ import annotations

import time
from pathlib import Path

from selfview.procedures.commands._common import positive_seconds, print_json
from selfview.errors import ConfigError


def add_io_map_argument(p) -> None:
    p.add_argument(
        "--io-map",
        default=None,
        metavar="MAP.yaml",
        help="where the solenoids and reed switches are (keys open_valve, close_valve, open_sensor, "
        "closed_sensor, safe_state, register_write, stray_coils; points as coil:0, di:1, hr:0.3 or 40001.3). "
        "Default: coils 0 (open) and 1 (close), discrete inputs 0 (open) and 1 (closed)",
    )


def load_io_map_arg(args):
    from selfview.drivers.pneumatic_gripper import IoMap

    if args.io_map is None:
        return IoMap()
    from selfview.io_safe import load_yaml

    path = Path(args.io_map)
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the io map ({exc.strerror or exc})") from exc
    # every value as text: a YAML number would turn 40001.10 into 40001.1 and 00001 into 1
    data = load_yaml(blob, str(path), error=ConfigError, text_only=True, what="io map")
    try:
        return IoMap.from_dict(data or {})
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def _finite_seconds(text: str) -> float:
    """argparse type: a finite number of seconds > 0 (a wait that never ends would leave the valve energised)."""
    v = positive_seconds(text)
    if v == float("inf"):
        raise ValueError(text)
    return v


_finite_seconds.__name__ = "finite number of seconds"


def register(sub):
    p = sub.add_parser(
        "gripper",
        help="open or close the pneumatic gripper, or read its reed switches (Modbus)",
        description=(
            "Check the gripper valve by hand: 'open' and 'close' switch the valve and wait until the matching reed "
            "switch confirms (--timeout); 'state' reads both switches; 'safe' commands the io map's safe state. "
            "URLs: modbus-tcp://HOST:PORT?unit=1, modbus-rtu:///dev/ttyUSB0?baud=19200&parity=E, "
            "modbus-rtu+socket://HOST:PORT?unit=1 (RTU frames over TCP)."
        ),
    )
    p.add_argument("--url", required=True, help="Modbus URL of the valve (terminal)")
    p.add_argument("--timeout", type=_finite_seconds, default=0.5, metavar="S",
                   help="jaw motion timeout, a finite number of seconds (default 0.5 s)")
    p.add_argument("--request-timeout", type=float, default=0.25, metavar="S", help="per request (default 0.25 s)")
    p.add_argument("--retries", type=int, default=0, help="Modbus retries per request (default 0)")
    add_io_map_argument(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("action", choices=("open", "close", "state", "safe"))
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from selfview.drivers.pneumatic_gripper import PneumaticGripper

    gripper = PneumaticGripper(
        args.url,
        io_map=load_io_map_arg(args),
        timeout_s=args.timeout,
        request_timeout_s=args.request_timeout,
        retries=args.retries,
        poll_s=None,
    )
    with gripper:
        t0 = time.monotonic()
        if args.action == "open":
            gripper.open_jaws()
        elif args.action == "close":
            gripper.close_jaws()
        elif args.action == "safe":
            gripper.safe()
        elapsed = time.monotonic() - t0
        reading = gripper.read()
        outputs = gripper.outputs()
    state = reading.state
    if args.json:
        print_json(
            {
                "url": gripper.url,
                "action": args.action,
                "state": state,
                "open_sensor": reading.open_sensor,
                "closed_sensor": reading.closed_sensor,
                "valve_outputs": outputs,
                "elapsed_s": round(elapsed, 4),
            }
        )
    else:
        print(state)
    return 0
