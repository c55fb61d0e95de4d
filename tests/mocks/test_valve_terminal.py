"""The simulated valve terminal against clients not written here: raw Modbus frames written by hand
(MBAP and RTU), and pyModbusTCP's client."""

from __future__ import annotations

import socket
import time

import pytest

from selfview.drivers.pneumatic_gripper import IoMap, Point
from selfview.mocks.valve_terminal import ValveTerminal
from selfview.errors import ConfigError, DeviceError
from tests.drivers.test_gripper_transcript import crc16  # Modbus CRC-16, written from the specification


class RawClient:
    """A Modbus master in a few lines: one request frame out, one reply frame back."""

    def __init__(self, port: int, framing: str = "mbap", unit: int = 1):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=1.0)
        self.framing, self.unit, self.tid = framing, unit, 0

    def _recv_exact(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            if not chunk:
                raise ConnectionError("closed by the terminal")
            out += chunk
        return out

    def ask(self, pdu_hex: str, unit: int | None = None) -> bytes:
        """Send a PDU, return the reply PDU (function code first)."""
        unit = self.unit if unit is None else unit
        pdu = bytes.fromhex(pdu_hex)
        if self.framing == "mbap":
            self.tid += 1
            self.sock.sendall(self.tid.to_bytes(2, "big") + b"\0\0" + (len(pdu) + 1).to_bytes(2, "big") + bytes([unit]) + pdu)
            head = self._recv_exact(7)
            assert head[:2] == self.tid.to_bytes(2, "big") and head[2:4] == b"\0\0" and head[6] == unit
            return self._recv_exact(int.from_bytes(head[4:6], "big") - 1)
        frame = bytes([unit]) + pdu
        self.sock.sendall(frame + crc16(frame))
        head = self._recv_exact(3)
        fc = head[1]
        rest = 2 if fc & 0x80 else head[2] + 2 if fc in (1, 2, 3, 4) else 5 if fc in (5, 6, 15, 16) else 7
        reply = head + self._recv_exact(rest)
        assert reply[-2:] == crc16(reply[:-2]), "bad CRC from the terminal"
        assert reply[0] == unit
        return reply[1:-2]

    def close(self):
        self.sock.close()


@pytest.fixture
def terminal():
    with ValveTerminal(travel_s=0.03, watchdog_s=None) as t:
        yield t


def ask_until(c: RawClient, pdu: str, reply: str, timeout_s: float = 2.0) -> bytes:
    """Repeat a request until the reply is ``reply`` (or the timeout passes); returns the last reply."""
    end = time.monotonic() + timeout_s
    got = c.ask(pdu)
    while got != bytes.fromhex(reply) and time.monotonic() < end:
        time.sleep(0.005)
        got = c.ask(pdu)
    return got


@pytest.mark.parametrize("framing", ["mbap", "rtu"])
def test_raw_frames_drive_the_gripper(framing):
    with ValveTerminal(travel_s=0.2, watchdog_s=None, framing=framing) as t:
        c = RawClient(t.port, framing)
        try:
            assert c.ask("02 0000 0002") == bytes.fromhex("02 01 01")  # open switch on
            assert c.ask("01 0000 0008") == bytes.fromhex("01 01 00")
            assert c.ask("05 0001 FF00") == bytes.fromhex("05 0001 FF00")  # energise 'close'
            assert c.ask("01 0000 0002") == bytes.fromhex("01 01 02")
            assert c.ask("02 0000 0002") == bytes.fromhex("02 01 00")  # travelling: neither switch
            assert ask_until(c, "02 0000 0002", "02 01 02") == bytes.fromhex("02 01 02")  # closed
            assert t.position == 0.0 and t.strokes[-1][0] == "closed"
            # FC15: open on, close off in one request (coil 0 = bit 0 of the first byte)
            assert c.ask("0F 0000 0002 01 01") == bytes.fromhex("0F 0000 0002")
            assert ask_until(c, "02 0000 0002", "02 01 01") == bytes.fromhex("02 01 01")
        finally:
            c.close()


def test_register_map_with_fc3_fc4_fc6_fc16_fc22():
    m = IoMap(open_valve=Point.parse("40002.0"), close_valve=Point.parse("40002.1"),
              open_sensor=Point.parse("30001.8"), closed_sensor=Point.parse("30001.9"))
    with ValveTerminal(io_map=m, travel_s=0.0, watchdog_s=None) as t:
        c = RawClient(t.port)
        try:
            assert c.ask("04 0000 0001") == bytes.fromhex("04 02 0100")  # bit 8: open
            assert c.ask("06 0001 0002") == bytes.fromhex("06 0001 0002")  # close solenoid
            assert ask_until(c, "04 0000 0001", "04 02 0200") == bytes.fromhex("04 02 0200")  # bit 9: closed
            assert c.ask("16 0001 FFFC 0001") == bytes.fromhex("16 0001 FFFC 0001")  # mask write: open
            assert c.ask("03 0000 0002") == bytes.fromhex("03 04 0000 0001")
            assert c.ask("10 0000 0002 04 1234 0002") == bytes.fromhex("10 0000 0002")  # FC16, close again
            assert ask_until(c, "04 0000 0001", "04 02 0200") == bytes.fromhex("04 02 0200")
            assert t.table("holding_register")[:2] == [0x1234, 0x0002]
        finally:
            c.close()


def test_exception_replies(terminal):
    c = RawClient(terminal.port)
    try:
        assert c.ask("01 0040 0001") == bytes.fromhex("81 02")  # beyond the 64 coils: illegal address
        assert c.ask("02 003F 0002") == bytes.fromhex("82 02")
        assert c.ask("05 0000 FF00", unit=7) == bytes.fromhex("85 0B")  # no such unit: gateway no response
        assert terminal.valve_outputs == {"open": False, "close": False}
        terminal.fail_requests(4)
        assert c.ask("02 0000 0002") == bytes.fromhex("82 04")
        assert c.ask("05 0001 FF00") == bytes.fromhex("85 04")
        terminal.fail_requests(None)
        assert terminal.valve_outputs == {"open": False, "close": False}  # refused writes did nothing
        assert c.ask("02 0000 0002") == bytes.fromhex("02 01 01")
    finally:
        c.close()


def test_silent_and_dropped(terminal):
    c = RawClient(terminal.port)
    try:
        terminal.set_silent()
        c.sock.settimeout(0.3)
        with pytest.raises(socket.timeout):
            c.ask("02 0000 0002")
        terminal.set_silent(False)
        c.sock.settimeout(1.0)
        assert c.ask("02 0000 0002") == bytes.fromhex("02 01 01")
        terminal.drop_connections()
        with pytest.raises((ConnectionError, OSError)):
            c.ask("02 0000 0002")
    finally:
        c.close()
    c = RawClient(terminal.port)  # the listener stays
    try:
        terminal.drop_on_next_request()
        with pytest.raises((ConnectionError, OSError)):
            c.ask("05 0001 FF00")
        assert terminal.valve_outputs["close"] is False  # the request was dropped, not executed
    finally:
        c.close()


class StepClock:
    """A clock the test moves by hand: the terminal's model time (watchdog, travel) without sleeps."""

    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_watchdog_drops_outputs_when_the_master_is_silent():
    clock = StepClock()
    with ValveTerminal(travel_s=0.0, watchdog_s=0.3, clock=clock) as t:
        c = RawClient(t.port)
        try:
            c.ask("05 0001 FF00")
            for _ in range(12):  # a master that keeps talking (every 0.25 s < 0.3 s) keeps its outputs
                clock.now += 0.25
                t.advance()
                c.ask("02 0000 0002")
            assert t.watchdog_trips == 0 and t.valve_outputs["close"]
            clock.now += 0.29
            t.advance()
            assert t.watchdog_trips == 0  # not yet: silent for 0.29 s
            clock.now += 0.02
            t.advance()
            assert t.watchdog_trips == 1  # silent for 0.31 s
            assert c.ask("01 0000 0002") == bytes.fromhex("01 01 00")
            assert c.ask("02 0000 0002") == bytes.fromhex("02 01 02")  # a double valve holds: still closed
        finally:
            c.close()


def test_stuck_jaw_and_broken_switch(terminal):
    c = RawClient(terminal.port)
    try:
        terminal.stick_jaw()
        c.ask("05 0001 FF00")
        time.sleep(0.1)  # three travel times
        assert terminal.position == 1.0 and c.ask("02 0000 0002") == bytes.fromhex("02 01 01")
        terminal.stick_jaw(False)
        assert ask_until(c, "02 0000 0002", "02 01 02") == bytes.fromhex("02 01 02")
        terminal.break_sensor("closed", reads=False)
        assert c.ask("02 0000 0002") == bytes.fromhex("02 01 00")
        terminal.break_sensor("open", reads=True)
        assert c.ask("02 0000 0002") == bytes.fromhex("02 01 01")
        with pytest.raises(ConfigError):
            terminal.break_sensor("middle")
    finally:
        c.close()


def test_pymodbustcp_client():
    client_mod = pytest.importorskip("pyModbusTCP.client", reason="test extra pyModbusTCP not installed")
    with ValveTerminal(travel_s=0.0, watchdog_s=None) as t:
        c = client_mod.ModbusClient(host="127.0.0.1", port=t.port, unit_id=1, timeout=1.0)
        try:
            assert c.read_discrete_inputs(0, 2) == [True, False]
            assert c.write_multiple_coils(0, [False, True])
            end = time.monotonic() + 2.0
            while c.read_discrete_inputs(0, 2) != [False, True] and time.monotonic() < end:
                time.sleep(0.005)
            assert c.read_discrete_inputs(0, 2) == [False, True]
            assert c.read_coils(0, 2) == [False, True]
            assert c.read_coils(100, 1) is None and c.last_except == 2  # illegal data address
        finally:
            c.close()


def test_start_stop_and_port_in_use():
    t = ValveTerminal(watchdog_s=None).start()
    port = t.port
    assert t.url == f"modbus-tcp://127.0.0.1:{port}?unit=1"
    with pytest.raises(DeviceError, match="cannot serve"):
        ValveTerminal(port=port).start()
    t.stop()
    t.stop()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", port), timeout=1.0)
    with pytest.raises(DeviceError, match="not started"):
        t.url


def test_bad_settings_are_refused():
    with pytest.raises(ConfigError):
        ValveTerminal(framing="ascii")
    with pytest.raises(ConfigError):
        ValveTerminal(travel_s=-1)
    with pytest.raises(ConfigError):
        ValveTerminal().fail_requests(99)


def test_world_follows_the_jaws(cell):
    from selfview.mocks.world import SimWorld

    world = SimWorld(cell, seed=0)
    with ValveTerminal(world, travel_s=0.3, watchdog_s=None) as t:
        c = RawClient(t.port)
        try:
            c.ask("05 0001 FF00")
            seen = set()
            end = time.monotonic() + 2.0
            while world.jaw_state != "closed" and time.monotonic() < end:
                seen.add(round(world.jaw_gap_mm, 3))
                time.sleep(0.005)
            assert world.jaw_gap_mm == cell.gripper.states["closed"]
            assert any(cell.gripper.states["closed"] < g < cell.gripper.states["open"] for g in seen)
        finally:
            c.close()


def test_rtu_noise_is_skipped_and_the_next_frame_answered():
    """A corrupted RTU frame gets no reply (a slave stays silent on a bad CRC); the stream re-synchronises
    on the next good frame, and a partial frame followed by silence is dropped."""
    with ValveTerminal(travel_s=0.0, watchdog_s=None, framing="rtu") as t:
        c = RawClient(t.port, "rtu")
        try:
            bad = bytes.fromhex("01 05 0001 FF00")
            c.sock.sendall(bad + bytes([crc16(bad)[0] ^ 0x5A, crc16(bad)[1]]))  # CRC wrong: not executed
            c.sock.sendall(b"\x01\x0f\x00")  # a torn frame, then silence
            time.sleep(0.4)
            assert c.ask("01 0000 0002") == bytes.fromhex("01 01 00")
            assert t.valve_outputs == {"open": False, "close": False}
            assert c.ask("2B 0E01 00") == bytes.fromhex("AB 01")  # a function it lacks: illegal function
        finally:
            c.close()


def test_mbap_header_that_is_not_modbus_ends_the_connection(terminal):
    c = RawClient(terminal.port)
    try:
        c.sock.sendall(b"\x00\x01\x00\x07\x00\x06\x01\x01\x00\x00\x00\x02")  # protocol id 7
        c.sock.settimeout(1.0)
        assert c.sock.recv(16) == b""
        assert terminal.valve_outputs == {"open": False, "close": False}
    finally:
        c.close()


@pytest.mark.parametrize("unit", [-1, 256, 1.0, True])
def test_the_server_refuses_a_unit_that_is_not_a_modbus_address(unit):
    from selfview.mocks.modbus_server import ModbusServer

    with pytest.raises(ValueError, match="unit"):
        ModbusServer(ValveTerminal(), unit=unit)


def test_the_servers_crc_is_the_specifications():
    """The server's own CRC-16 against the one written from the specification, and the serial line guide's
    worked example (Read Exception Status to unit 2: frame 02 07, CRC 41 12 sent low byte first)."""
    from selfview.mocks.modbus_server import crc16 as server_crc16

    assert crc16(bytes.fromhex("0207")) == bytes.fromhex("4112") == server_crc16(bytes.fromhex("0207"))
    for frame in (b"", bytes.fromhex("01 05 0001 FF00"), bytes(range(256))):
        assert server_crc16(frame) == crc16(frame)
