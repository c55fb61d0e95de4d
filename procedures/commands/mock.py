"""``selfview mock robot|gripper``: start a simulated device on its real channel and serve until stopped."""

from __future__ import annotations


def register(sub):
    p = sub.add_parser(
        "mock",
        help="start a simulated device (VAL-II controller on a pty or TCP, Modbus valve terminal)",
        description=(
            "Start a simulated device that speaks the real wire protocol. The first line of stdout is the "
            "URL to give the driver (a pty path or socket://127.0.0.1:P, or modbus-tcp://127.0.0.1:P?unit=1); "
            "it then serves until stopped with Ctrl-C or until --duration runs out."
        ),
    )
    kinds = p.add_subparsers(dest="device", metavar="DEVICE")
    from selfview.procedures.commands import _mock_gripper, _mock_robot

    _mock_robot.register(kinds)
    _mock_gripper.register(kinds)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])
    return p
