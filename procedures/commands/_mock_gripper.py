"""``selfview mock gripper``: the simulated valve terminal, serving Modbus on 127.0.0.1 until stopped."""

from __future__ import annotations

import sys
import time

from procedures.commands.gripper import add_io_map_argument, load_io_map_arg


def _positive(text: str) -> float:
    v = float(text)
    if not v > 0:
        raise ValueError(text)
    return v


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
    p.add_argument("--port", type=int, default=0, help="TCP port (default: a free one)")
    p.add_argument("--duration", type=_positive, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--seed", type=int, default=0, help="seed of the travel-time jitter")
    p.add_argument("--travel", type=float, default=0.1, metavar="S", help="jaw travel time (default 0.1 s)")
    p.add_argument("--travel-sd", type=float, default=0.0, metavar="S", help="travel time jitter, sd (default 0)")
    p.add_argument("--watchdog", type=_positive, default=1.0, metavar="S", help="connection watchdog (default 1 s)")
    p.add_argument("--no-watchdog", action="store_true", help="never drop the outputs")
    p.add_argument("--unit", type=int, default=1, help="Modbus unit (device id), default 1")
    p.add_argument("--rtu", action="store_true", help="RTU frames over TCP (prints modbus-rtu+socket://...)")
    add_io_map_argument(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from mocks.valve_terminal import ValveTerminal

    if not 0 <= args.port <= 65535:
        raise SystemExit(f"selfview mock gripper: --port {args.port} out of 0..65535")
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
        print(terminal.url, flush=True)
        end = None if args.duration is None else time.monotonic() + args.duration
        while end is None or time.monotonic() < end:
            time.sleep(0.2 if end is None else max(0.0, min(0.2, end - time.monotonic())))
    except KeyboardInterrupt:
        pass
    finally:
        terminal.stop()
    print(
        f"selfview mock gripper: served {terminal.requests} requests on {terminal.connections_total} connection(s), "
        f"{len(terminal.strokes)} strokes, {terminal.watchdog_trips} watchdog trip(s)",
        file=sys.stderr,
    )
    return 0
