"""The robot's ``serial://`` URL on a pseudo-terminal: the baud rate and flow control reach the port's
termios settings, and with ``xonxoff=1`` a controller's XON/XOFF bytes are flow control, not reply bytes.
A thread plays the controller on the pty's master side (echo, then the scripted reply)."""

from __future__ import annotations

import os
import select
import termios
import threading
import time
import tty

import pytest

from selfview.drivers.puma_val_serial import PumaVAL
from selfview.drivers.puma_val_serial.driver import parse_serial_url
from selfview.errors import ConfigError, ProtocolError
from tests.drivers.test_puma_transcript import JOINTS, where_reply

XON, XOFF = b"\x11", b"\x13"


class PtyController:
    """Echoes each typed byte and answers a CR with a prompt, WHERE with its reply; with ``flow`` it
    wraps every echo and reply in XOFF ... XON, as a controller with a full input buffer does."""

    def __init__(self, flow: bool = False):
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        os.close(slave)
        self.flow = flow
        self.lines: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _send(self, data: bytes) -> None:
        os.write(self.master, XOFF + data[:1] + XON + data[1:] if self.flow and data else data)

    def _serve(self) -> None:
        line = bytearray()
        deadline = time.monotonic() + 20.0
        while not self._stop.is_set() and time.monotonic() < deadline:
            r, _, _ = select.select([self.master], [], [], 0.05)
            if not r:
                continue
            try:
                data = os.read(self.master, 1024)
            except OSError:
                continue
            for b in data:
                if b == 0x0D:
                    self.lines.append(bytes(line))
                    reply = where_reply(JOINTS) if bytes(line).strip().upper() == b"WHERE" else b"\r\n."
                    line.clear()
                    self._send(reply)
                elif b == 0x15:
                    line.clear()
                elif b != 0x0A:
                    line.append(b)
                    self._send(bytes((b,)))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        os.close(self.master)


@pytest.fixture
def controller(request):
    c = PtyController(flow=getattr(request, "param", False))
    yield c
    c.close()


def test_the_documented_serial_url_opens_with_its_settings(controller):
    with PumaVAL(f"serial://{controller.path}?baud=9600&xonxoff=1&rtscts=1", timeout_s=2.0) as robot:
        assert robot.where().joints == pytest.approx(JOINTS, abs=0.005)
        iflag, _, cflag, _, ispeed, ospeed, _ = termios.tcgetattr(robot._ser.fd)
        assert ispeed == ospeed == termios.B9600
        assert iflag & termios.IXON and iflag & termios.IXOFF and cflag & termios.CRTSCTS
    with PumaVAL(f"serial://{controller.path}?baud=19200", timeout_s=2.0) as robot:
        iflag, _, cflag, _, ispeed, _, _ = termios.tcgetattr(robot._ser.fd)
        assert ispeed == termios.B19200 and not iflag & termios.IXON and not cflag & termios.CRTSCTS
        assert robot.baudrate == 19200


@pytest.mark.parametrize("controller", [True], indirect=True)
def test_xon_xoff_in_echoes_and_replies_is_flow_control_with_xonxoff_on(controller):
    with PumaVAL(f"serial://{controller.path}?baud=9600&xonxoff=1", timeout_s=2.0) as robot:
        for _ in range(3):
            assert robot.where().joints == pytest.approx(JOINTS, abs=0.005)
    assert controller.lines.count(b"WHERE") == 3


@pytest.mark.parametrize("controller", [True], indirect=True)
def test_without_xonxoff_the_same_bytes_are_garbage(controller):
    with PumaVAL(f"serial://{controller.path}?baud=9600", timeout_s=1.0) as robot:
        with pytest.raises(ProtocolError):
            robot.connect()
            robot.where()


@pytest.mark.parametrize(
    "url, message",
    [("serial://dev/ttyS0", "three slashes"), ("serial:///dev/ttyS0?baud=fast", "baud='fast'"),
     ("serial:///dev/ttyS0?parity=E", "unknown parameter 'parity'"), ("serial:///dev/ttyS0?xonxoff=yes", "expected 0 or 1")],
)
def test_bad_serial_urls_name_the_part(url, message):
    with pytest.raises(ConfigError, match=message):
        PumaVAL(url)


def test_other_urls_are_pyserials():
    assert parse_serial_url("socket://127.0.0.1:5000", 4800) == (
        "socket://127.0.0.1:5000", {"baudrate": 4800, "xonxoff": False, "rtscts": False})
    assert parse_serial_url("serial:///dev/ttyS0?baud=9600&rtscts=1")[0] == "/dev/ttyS0"


def test_the_cli_takes_the_documented_url(world_sim, capsys):
    from selfview.procedures.cli import main

    assert main(["robot", "--url", f"serial://{world_sim.url}?baud=9600&xonxoff=1", "where"]) == 0
    assert "JT1" in capsys.readouterr().out
    assert main(["robot", "--url", f"serial://{world_sim.url}?baud=nine", "where"]) == 3
    assert "baud='nine'" in capsys.readouterr().err


@pytest.fixture
def world_sim(cell):
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.world import SimWorld

    with ValController(SimWorld(cell, seed=1), time_scale=0.0) as c:
        c.start_pty()
        yield c
