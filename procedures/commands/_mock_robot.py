"""``selfview mock robot``: the simulated VAL-II controller with a PUMA 260, on a pty or TCP, until stopped."""

from __future__ import annotations

import sys

from selfview.procedures.commands._common import BAUD, FACTOR, PORT, SECONDS, SEED, add_cell_argument, load_cell_arg, serve_until


def register(kinds):
    p = kinds.add_parser(
        "robot",
        help="simulated VAL-II controller with a PUMA 260 (pty or TCP)",
        description=(
            "A simulated VAL-II controller speaking the terminal dialogue on a pseudo-terminal (open the printed "
            "device path like /dev/ttyS0) or on TCP 127.0.0.1 (socket://127.0.0.1:PORT). It moves the simulated "
            "cell's gripper; the taught locations 'above' and 'plate' lie over and on the calibration plate. "
            "Prints the URL as the first line, then serves until Ctrl-C or --duration."
        ),
    )
    p.add_argument("--link", choices=("pty", "tcp"), default="pty", help="pseudo-terminal (default) or TCP")
    p.add_argument("--port", type=PORT, default=0, help="TCP port (default: a free one)")
    p.add_argument("--duration", type=SECONDS, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--seed", type=SEED, default=0, help="seed of the simulated world and of the faults")
    p.add_argument("--time-scale", type=FACTOR, default=1.0, metavar="K", help="motion time factor (default 1: real time)")
    p.add_argument("--pace", action="store_true", help="send reply bytes at --baud (8N1), like a real line")
    p.add_argument("--baud", type=BAUD, default=9600, help="pacing baud rate (default 9600)")
    p.add_argument("--no-echo", action="store_true", help="do not echo command lines")
    p.add_argument("--calibrated", action="store_true", help="start calibrated (no CAL needed)")
    p.add_argument("--dialect", default=None, metavar="DIALECT.yaml", help="controller dialect")
    add_cell_argument(p)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from selfview.drivers.puma_val_serial import load_dialect
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.world import SimWorld

    world = SimWorld(load_cell_arg(args), seed=args.seed)
    sim = ValController(
        world,
        seed=args.seed,
        time_scale=args.time_scale,
        pace_baud=args.baud if args.pace else None,
        echo=False if args.no_echo else None,
        dialect=load_dialect(args.dialect) if args.dialect else None,
        calibrated=args.calibrated,
    )
    try:
        if args.link == "pty":
            url = sim.start_pty()
        else:
            sim.start_tcp(args.port)
            url = sim.url
        serve_until(url, args.duration)
    finally:
        sim.stop()
    print(f"selfview mock robot: received {len(sim.received)} lines; parked={world.parked}", file=sys.stderr)
    return 0
