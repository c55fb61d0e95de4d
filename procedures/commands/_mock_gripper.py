"""``selfview mock gripper``: the simulated valve terminal, serving Modbus on 127.0.0.1 until stopped."""

from __future__ import annotations

import sys

from selfview.procedures.commands._common import PORT, SECONDS, SECONDS_OR_ZERO, SEED, numeric, serve_until
from selfview.procedures.commands.gripper import add_io_map_argument, load_io_map_arg


def register(kinds):
    p = kinds.add_parser(
        "gripper",
        help="simulated Modbus valve terminal with a pneumatic gripper",
        description=(
            "A simulated valve terminal (a real Modbus TCP server on 127.0.0.1) driving a pneumatic gripper: the "
            "jaws travel in --travel seconds after the valve switches and the reed switches follow; outputs drop "
            "to 0 when the master is silent for --watchdog seconds. Prints modbus-tcp://127.0.0.1:PORT?unit=1 as "
            "the first line, then serves until Ctrl-C or --duration."
        ),
    )
    p.add_argument("--port", type=PORT, default=0, help="TCP port (default: a free one)")
    p.add_argument("--duration", type=SECONDS, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--seed", type=SEED, default=0, help="seed of the travel-time jitter")
    p.add_argument("--travel", type=SECONDS_OR_ZERO, default=0.1, metavar="S", help="jaw travel time (default 0.1 s)")
    p.add_argument("--travel-sd", type=SECONDS_OR_ZERO, default=0.0, metavar="S", help="travel time jitter, sd (default 0)")
    p.add_argument("--watchdog", type=SECONDS, default=1.0, metavar="S", help="connection watchdog (default 1 s)")
    p.add_argument("--no-watchdog", action="store_true", help="never drop the outputs")
    p.add_argument("--unit", type=numeric(integer=True, lo=0, hi=255, name="unit"), default=1, help="Modbus unit (device id), default 1")
    p.add_argument("--rtu", action="store_true", help="RTU frames over TCP (prints modbus-rtu+socket://...)")
    add_io_map_argument(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from selfview.mocks.valve_terminal import ValveTerminal

    terminal = ValveTerminal(
        None,
        io_map=load_io_map_arg(args),
        seed=args.seed,
        travel_s=args.travel,
        travel_sd_s=args.travel_sd,
        watchdog_s=None if args.no_watchdog else args.watchdog,
        unit=args.unit,
        framing="rtu" if args.rtu else "mbap",
        port=args.port,
    )
    terminal.start()
    try:
        serve_until(terminal.url, args.duration)
    finally:
        terminal.stop()
    print(
        f"selfview mock gripper: served {terminal.requests} requests on {terminal.connections_total} connection(s), "
        f"{len(terminal.strokes)} strokes, {terminal.watchdog_trips} watchdog trip(s)",
        file=sys.stderr,
    )
    return 0
