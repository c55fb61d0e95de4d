"""``selfview gripper``: open or close the pneumatic gripper, or read its reed switches."""

from __future__ import annotations

import time
from pathlib import Path

from selfview.procedures.commands._common import SECONDS, numeric, print_json
from selfview.drivers.pneumatic_gripper.modbus import DEFAULT_READ_RETRIES, DEFAULT_TIMEOUT_S
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
    from selfview.files.io_safe import load_yaml_file

    path = Path(args.io_map)
    # every value as text: a YAML number would turn 40001.10 into 40001.1 and 00001 into 1
    data = load_yaml_file(path, error=ConfigError, text_only=True, what="io map")
    try:
        return IoMap.from_dict(data or {})
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


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
    p.add_argument("--timeout", type=SECONDS, default=0.5, metavar="S",
                   help="jaw motion timeout, a finite number of seconds (default 0.5 s)")
    p.add_argument("--request-timeout", type=SECONDS, default=DEFAULT_TIMEOUT_S, metavar="S",
                   help="per request (default %(default)s s)")
    p.add_argument("--retries", type=numeric(integer=True, lo=0, hi=5, name="retries"), default=DEFAULT_READ_RETRIES,
                   help="Modbus retries of a read (writes are sent once; default %(default)s)")
    add_io_map_argument(p)
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("action", choices=("open", "close", "state", "safe"))
    p.set_defaults(func=run)
    return p


def _switch(gripper, action: str) -> None:
    """Switch the valve through the engine, the safety path every command that drives a device shares: on
    Ctrl-C, SIGTERM, SIGHUP or SIGQUIT the jaw wait ends, the valve is put in its safe state and the
    command says so (exit 128+N); a failed stroke likewise leaves the valve safe (exit 4)."""
    import sys

    from selfview.procedures.engine import CellDevices, Engine, Step

    step = (Step("compute", {"fn": lambda e: gripper.safe()}, note="the safe state") if action == "safe"
            else Step("gripper", {"state": "open" if action == "open" else "closed"}))
    engine = Engine(CellDevices(gripper=gripper), progress=lambda msg: print(f"selfview gripper: {msg}", file=sys.stderr))
    engine.run(lambda e: e.execute(step), [step])


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
        if args.action != "state":
            _switch(gripper, args.action)
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
