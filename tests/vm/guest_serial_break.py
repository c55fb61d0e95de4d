"""A BREAK on the robot's line, inside the vm stage's guest (tests/vm/guest.sh runs this file by name).

The host's relay (``UartRelay`` in tests/vm/test_vm_stage.py) sends a telnet IAC BRK to qemu's chardev,
so the guest's 16550A receives a break and the kernel's 8250 driver and tty layer deliver it; a case asks
for one by recording a location (``HERE BRKMID``, ``BRKIDLE``, ``BRKMOVE``). The port starts with BRKINT
set (as ``stty sane`` or a getty leaves it); the driver must turn the break into a NUL it refuses. The
UART's own break count (/proc/tty/driver/serial) shows each break arrived. Runs only where
``SELFVIEW_VM_BREAK_RELAY=1`` says the line goes through that relay: never against a real controller.
"""

from __future__ import annotations

import os
import re
import termios
import time

import numpy as np
import pytest

from selfview.drivers.puma_val_serial import PumaVAL
from selfview.drivers.puma_val_serial.driver import parse_serial_url
from selfview.errors import ProtocolError

URL = os.environ.get("SELFVIEW_PUMA_URL", "")
pytestmark = pytest.mark.skipif(os.environ.get("SELFVIEW_VM_BREAK_RELAY") != "1" or not URL,
                                reason="runs in the vm stage's guest, behind the relay that injects BREAKs")
BREAK_FLAGS = termios.BRKINT | termios.IGNBRK | termios.PARMRK


def _breaks() -> int:
    """The breaks the UART of the robot's port has received so far."""
    index = re.fullmatch(r"/dev/ttyS(\d+)", parse_serial_url(URL)[0]).group(1)
    for line in open("/proc/tty/driver/serial").read().splitlines():
        if line.startswith(f"{index}:"):
            m = re.search(r"\bbrk:(\d+)", line)
            return int(m.group(1)) if m else 0
    raise AssertionError(f"ttyS{index} is not in /proc/tty/driver/serial")


def _wait_breaks(n: int, timeout_s: float = 15.0) -> int:
    deadline = time.monotonic() + timeout_s
    while _breaks() < n and time.monotonic() < deadline:
        time.sleep(0.05)
    return _breaks()


@pytest.fixture(scope="module")
def robot():
    path = parse_serial_url(URL)[0]
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        attrs = termios.tcgetattr(fd)
        attrs[0] |= termios.BRKINT  # with it the kernel would flush the reply received so far, silently
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
        r = PumaVAL(URL, timeout_s=5.0).connect()
    finally:
        os.close(fd)
    yield r
    r.close()


def test_serial_break_the_port_reads_a_break_as_a_nul(robot):
    flags = termios.tcgetattr(robot._ser.fileno())[0]  # noqa: SLF001
    assert not flags & BREAK_FLAGS, oct(flags)


def test_serial_break_in_the_middle_of_a_where_reply(robot):
    before = robot.where()
    robot.here("brkmid")
    n = _breaks()
    t0 = time.monotonic()
    with pytest.raises(ProtocolError, match=r"garbage in the reply to 'WHERE'.*BREAK on the line"):
        robot.where()
    assert time.monotonic() - t0 < robot.timeout_s
    assert _breaks() == n + 1
    assert robot.where().pose == before.pose  # resynchronised; the arm did not move


def test_serial_break_between_commands(robot):
    before = robot.where()
    robot.here("brkidle")
    n = _breaks()
    assert _wait_breaks(n + 1) == n + 1, "no BREAK reached the UART"
    time.sleep(0.2)
    assert robot.where().pose == before.pose  # a resync first (the host checks), then the right value


def test_serial_break_during_a_motion_wait(robot):
    robot.calibrate()
    robot.speed(3)  # JT1 turns 30 deg in about 5 s of the simulator's time: the break comes 0.4 s in
    start = robot.where()
    delta = -30.0 if start.joints[0] > 0 else 30.0
    robot.here("brkmove")
    n = _breaks()
    with pytest.raises(ProtocolError, match="BREAK on the line") as ei:
        robot.drive(1, delta, 3)
    assert "ABORT sent and confirmed" in str(ei.value), ei.value
    assert _breaks() == n + 1
    after = robot.where()
    moved = after.joints[0] - start.joints[0]
    assert 0.0 <= moved / delta < 0.9, (start.joints, after.joints)  # stopped on its way, never counted as done
    assert np.allclose(after.joints[1:], start.joints[1:], atol=0.01)
