"""Transcript tests: the exact Modbus bytes each driver call sends, and how each reply is taken.

The device here is a raw socket on 127.0.0.1 playing a script of (expected request, reply) frames,
written out by hand from the Modbus specification (MBAP: transaction id, protocol 0, length, unit;
RTU: unit, PDU, CRC-16 low byte first). No pymodbus on this side.
"""

from __future__ import annotations

import socket
import threading

import pytest

from selfview.drivers.pneumatic_gripper import (
    ConnectionFailed,
    ConnectionLost,
    GripperFault,
    IoMap,
    ModbusExceptionReply,
    PneumaticGripper,
    Point,
)
from selfview.errors import DeviceTimeout, ProtocolError

SILENT = object()  # script reply: say nothing
HANG_UP = object()  # script reply: close the connection


def mbap(tid: int, pdu: str, unit: int = 1) -> bytes:
    body = bytes.fromhex(pdu)
    return tid.to_bytes(2, "big") + b"\x00\x00" + (len(body) + 1).to_bytes(2, "big") + bytes([unit]) + body


def crc16(frame: bytes) -> bytes:
    crc = 0xFFFF
    for b in frame:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


def rtu(pdu: str, unit: int = 1) -> bytes:
    frame = bytes([unit]) + bytes.fromhex(pdu)
    return frame + crc16(frame)


class ScriptedDevice:
    """Accepts one connection at a time and plays ``script``: each request must equal the next expected
    frame; the reply is sent (or SILENT / HANG_UP). Records what it received in ``received``."""

    def __init__(self, script, framing: str = "mbap"):
        self.script = list(script)
        self.framing = framing
        self.received: list[bytes] = []
        self.mismatch: str | None = None
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.srv.settimeout(0.1)
        self.port = self.srv.getsockname()[1]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        scheme = "modbus-tcp" if self.framing == "mbap" else "modbus-rtu+socket"
        return f"{scheme}://127.0.0.1:{self.port}?unit=1"

    def _frame_len(self, buf: bytes) -> int | None:
        if self.framing == "mbap":
            return None if len(buf) < 6 else 6 + int.from_bytes(buf[4:6], "big")
        if len(buf) < 2:
            return None
        fc = buf[1]
        if fc in (1, 2, 3, 4, 5, 6):
            return 8
        if fc == 22:
            return 10
        if fc in (15, 16):
            return None if len(buf) < 7 else 9 + buf[6]
        return len(buf)

    def _serve(self):
        while not self._stop.is_set():
            try:
                conn, _ = self.srv.accept()
            except socket.timeout:
                continue
            conn.settimeout(0.05)
            buf = b""
            with conn:
                while not self._stop.is_set():
                    n = self._frame_len(buf)
                    if n is None or len(buf) < n:
                        try:
                            chunk = conn.recv(256)
                        except socket.timeout:
                            continue
                        if not chunk:
                            break
                        buf += chunk
                        continue
                    frame, buf = buf[:n], buf[n:]
                    self.received.append(frame)
                    if not self.script:
                        self.mismatch = self.mismatch or f"unexpected request {frame.hex(' ')}"
                        continue
                    expected, reply = self.script.pop(0)
                    if frame != expected:
                        self.mismatch = self.mismatch or f"expected {expected.hex(' ')}, got {frame.hex(' ')}"
                        self.script.clear()
                        break
                    if reply is HANG_UP:
                        break
                    if reply is not SILENT:
                        conn.sendall(reply)

    def close(self):
        self._stop.set()
        self._thread.join(2)
        self.srv.close()

    def check(self):
        assert self.mismatch is None, self.mismatch
        assert not self.script, f"{len(self.script)} scripted request(s) never came"


@pytest.fixture
def device(request):
    devices = []

    def make(script, framing="mbap"):
        d = ScriptedDevice(script, framing)
        devices.append(d)
        return d

    yield make
    for d in devices:
        d.close()


# Default io map: double solenoid on coils 0 (open) and 1 (close); switches on discrete inputs 0 and 1.
CONNECT_OPEN = [
    (mbap(1, "01 0000 0002"), mbap(1, "01 01 00")),  # FC1 read coils 0..1: both solenoids off
    (mbap(2, "02 0000 0002"), mbap(2, "02 01 01")),  # FC2 read inputs 0..1: open switch on
]


def safe_on_link(tid: int) -> list:
    """The driver's safe-state attempt on an open link (default io map, safe = all-off): both coils off,
    then the outputs read back."""
    return [
        (mbap(tid, "05 0000 0000"), mbap(tid, "05 0000 0000")),
        (mbap(tid + 1, "05 0001 0000"), mbap(tid + 1, "05 0001 0000")),
        (mbap(tid + 2, "01 0000 0002"), mbap(tid + 2, "01 01 00")),
    ]


#: The safe-state attempt after the link dropped: one new connection (transaction ids from 1 again),
#: which reads the outputs first, then the attempt.
SAFE_AFTER_RECONNECT = [(mbap(1, "01 0000 0002"), mbap(1, "01 01 00"))] + safe_on_link(2)


def test_connect_reads_outputs_then_switches(device):
    d = device(CONNECT_OPEN)
    g = PneumaticGripper(d.url, poll_s=None)
    with g:
        assert g.valve_outputs == {"open": False, "close": False}
        assert g.last_state == "open"
    d.check()


def test_close_jaws_breaks_before_make_and_confirms(device):
    d = device(
        CONNECT_OPEN
        + [
            (mbap(3, "05 0000 0000"), mbap(3, "05 0000 0000")),  # FC5 coil 0 (open) off
            (mbap(4, "05 0001 FF00"), mbap(4, "05 0001 FF00")),  # FC5 coil 1 (close) on
            (mbap(5, "02 0000 0002"), mbap(5, "02 01 00")),  # travelling: neither switch
            (mbap(6, "02 0000 0002"), mbap(6, "02 01 02")),  # closed switch on ...
            (mbap(7, "02 0000 0002"), mbap(7, "02 01 02")),  # ... and again: confirmed
        ]
    )
    g = PneumaticGripper(d.url, poll_s=None, confirm_poll_s=0.001)
    with g:
        assert g.close_jaws() == "closed"
        assert g.valve_outputs == {"open": False, "close": True}
    d.check()


def test_holding_register_bits_read_modify_write(device):
    # Festo-style: solenoids are bits 0 (open) and 1 (close) of output word 40001 (wire address 0);
    # switches are bits 4 (open) and 5 (closed) of input word 30003 (wire address 2).
    m = IoMap(open_valve=Point.parse("40001.0"), close_valve=Point.parse("40001.1"),
              open_sensor=Point.parse("30003.4"), closed_sensor=Point.parse("30003.5"))
    d = device(
        [
            (mbap(1, "03 0000 0001"), mbap(1, "03 02 8000")),  # bit 15 belongs to another valve
            (mbap(2, "04 0002 0001"), mbap(2, "04 02 0010")),  # open switch
            (mbap(3, "03 0000 0001"), mbap(3, "03 02 8000")),  # read-modify-write: read ...
            (mbap(4, "06 0000 8002"), mbap(4, "06 0000 8002")),  # ... and write, bit 15 kept
            (mbap(5, "04 0002 0001"), mbap(5, "04 02 0020")),  # closed switch
            (mbap(6, "04 0002 0001"), mbap(6, "04 02 0020")),  # twice
        ]
    )
    with PneumaticGripper(d.url, io_map=m, poll_s=None) as g:
        assert g.close_jaws() == "closed"
    d.check()


def test_mask_write_open_transcript(device):
    m = IoMap(open_valve=Point.parse("hr:7.2"), close_valve=Point.parse("hr:7.3"), open_sensor=Point.parse("di:10"),
              closed_sensor=Point.parse("di:12"), register_write="mask")
    d = device(
        [
            (mbap(1, "03 0007 0001"), mbap(1, "03 02 0008")),
            (mbap(2, "02 000A 0003"), mbap(2, "02 01 04")),
            (mbap(3, "16 0007 FFF3 0004"), mbap(3, "16 0007 FFF3 0004")),
            (mbap(4, "02 000A 0003"), mbap(4, "02 01 01")),
            (mbap(5, "02 000A 0003"), mbap(5, "02 01 01")),
        ]
    )
    with PneumaticGripper(d.url, io_map=m, poll_s=None) as g:
        assert g.last_state == "closed"
        assert g.open_jaws() == "open"
    d.check()


def test_single_solenoid_safe_state(device):
    # spring-return valve: coil 3 energised closes, de-energised opens; safe = all-off
    m = IoMap(open_valve=None, close_valve=Point("coil", 3))
    d = device(
        [
            (mbap(1, "01 0003 0001"), mbap(1, "01 01 01")),
            (mbap(2, "02 0000 0002"), mbap(2, "02 01 02")),
            (mbap(3, "05 0003 0000"), mbap(3, "05 0003 0000")),  # safe(): de-energise ...
            (mbap(4, "01 0003 0001"), mbap(4, "01 01 00")),  # ... and read it back
        ]
    )
    with PneumaticGripper(d.url, io_map=m, poll_s=None) as g:
        assert m.solenoid == "single" and g.valve_outputs == {"close": True}
        g.safe()
        assert g.valve_outputs == {"close": False}
    d.check()


def test_rtu_frames_over_socket(device):
    d = device(
        [
            (rtu("01 0000 0002"), rtu("01 01 00")),
            (rtu("02 0000 0002"), rtu("02 01 02")),
            (rtu("05 0001 0000"), rtu("05 0001 0000")),  # open: close coil off first
            (rtu("05 0000 FF00"), rtu("05 0000 FF00")),
            (rtu("02 0000 0002"), rtu("02 01 01")),
            (rtu("02 0000 0002"), rtu("02 01 01")),
        ],
        framing="rtu",
    )
    assert rtu("01 0000 0002") == bytes.fromhex("01 01 0000 0002 BDCB")  # the CRC every Modbus manual shows
    with PneumaticGripper(d.url, poll_s=None) as g:
        assert g.open_jaws() == "open"
    d.check()


def test_exception_reply_is_typed_and_keeps_the_link(device):
    d = device(
        CONNECT_OPEN
        + [
            (mbap(3, "02 0000 0002"), mbap(3, "82 04")),  # server device failure
            (mbap(4, "02 0000 0002"), mbap(4, "02 01 01")),
        ]
    )
    with PneumaticGripper(d.url, poll_s=None) as g:
        with pytest.raises(ModbusExceptionReply) as e:
            g.state()
        assert e.value.code == 4 and e.value.function == 2 and "server device failure" in str(e.value)
        assert g.last_state is None  # not read
        assert g.state() == "open"  # the device answered: the link is fine
    d.check()


def test_silent_device_times_out_within_its_timeout(device):
    d = device(CONNECT_OPEN + [(mbap(3, "02 0000 0002"), SILENT)] + SAFE_AFTER_RECONNECT)
    with PneumaticGripper(d.url, poll_s=None, request_timeout_s=0.2) as g:
        with pytest.raises(DeviceTimeout):
            g.state()  # one attempt (not pymodbus's default 4): a repeated request would break the script
        assert g.last_state is None and not g.connected  # silent after the safe attempt
        assert g.safe_report.confirmed
        with pytest.raises(ConnectionLost):  # state unknown: no jaw command until connect()
            g.close_jaws()
    d.check()


def test_connection_dropped_mid_request(device):
    d = device(CONNECT_OPEN + [(mbap(3, "02 0000 0002"), HANG_UP)] + SAFE_AFTER_RECONNECT)
    with PneumaticGripper(d.url, poll_s=None) as g:
        with pytest.raises(ConnectionLost):
            g.state()
        assert g.last_state is None
    d.check()


def test_reply_for_another_function_is_a_protocol_error(device):
    d = device(CONNECT_OPEN + [(mbap(3, "02 0000 0002"), mbap(3, "03 02 0001"))] + SAFE_AFTER_RECONNECT)
    with PneumaticGripper(d.url, poll_s=None) as g:
        with pytest.raises(ProtocolError, match="function 3, not 2"):
            g.state()
        assert g.last_state is None and not g.connected  # dropped: a late reply cannot pass for the next
    d.check()


def test_wrong_write_echo_is_a_protocol_error(device):
    d = device(
        CONNECT_OPEN
        + [
            (mbap(3, "05 0001 0000"), mbap(3, "05 0001 0000")),
            (mbap(4, "05 0000 FF00"), mbap(4, "05 0000 0000")),  # the device did not take the write
        ]
        + SAFE_AFTER_RECONNECT
    )
    with PneumaticGripper(d.url, poll_s=None) as g:
        with pytest.raises(ProtocolError, match="echoes"):
            g.open_jaws()
        assert g.valve_outputs == {"open": False, "close": False}  # unknown, then the safe state read back
    d.check()


def test_reply_from_another_unit_is_ignored_until_timeout(device):
    # as on a shared RTU bus: a frame for another unit is not ours; the device counts as silent
    d = device(CONNECT_OPEN + [(mbap(3, "02 0000 0002"), mbap(3, "02 01 01", unit=9))] + SAFE_AFTER_RECONNECT)
    with PneumaticGripper(d.url, poll_s=None, request_timeout_s=0.2) as g:
        with pytest.raises(DeviceTimeout):
            g.state()
        assert g.last_state is None
    d.check()


def test_both_switches_on_is_a_fault(device):
    d = device(
        CONNECT_OPEN
        + [
            (mbap(3, "05 0000 0000"), mbap(3, "05 0000 0000")),
            (mbap(4, "05 0001 FF00"), mbap(4, "05 0001 FF00")),
            (mbap(5, "02 0000 0002"), mbap(5, "02 01 03")),
            (mbap(6, "02 0000 0002"), mbap(6, "02 01 03")),  # read again: still both
        ]
        + safe_on_link(7)
    )
    with PneumaticGripper(d.url, poll_s=None) as g:
        with pytest.raises(GripperFault, match="both reed switches"):
            g.close_jaws()
        assert g.safe_report.confirmed
    d.check()


def test_one_flipped_bit_neither_confirms_nor_faults(device):
    """Issue 18 #9: single-bit errors in read replies. A reading with the target's switch on must be
    confirmed by the next one; a reading with both on is read again before it is believed."""
    d = device(
        CONNECT_OPEN
        + [
            (mbap(3, "05 0000 0000"), mbap(3, "05 0000 0000")),
            (mbap(4, "05 0001 FF00"), mbap(4, "05 0001 FF00")),
            (mbap(5, "02 0000 0002"), mbap(5, "02 01 00")),  # travelling
            (mbap(6, "02 0000 0002"), mbap(6, "02 01 02")),  # a flipped bit: "closed" ...
            (mbap(7, "02 0000 0002"), mbap(7, "02 01 00")),  # ... not confirmed: still travelling
            (mbap(8, "02 0000 0002"), mbap(8, "02 01 03")),  # a flipped bit: both on ...
            (mbap(9, "02 0000 0002"), mbap(9, "02 01 00")),  # ... read again: travelling
            (mbap(10, "02 0000 0002"), mbap(10, "02 01 02")),  # arrived
            (mbap(11, "02 0000 0002"), mbap(11, "02 01 02")),  # confirmed
            # state(): the reading disagrees with the command (a flipped bit turned 'closed' into
            # 'between'), so it is read again
            (mbap(12, "02 0000 0002"), mbap(12, "02 01 00")),
            (mbap(13, "02 0000 0002"), mbap(13, "02 01 02")),
        ]
    )
    with PneumaticGripper(d.url, poll_s=None, confirm_poll_s=0.001, timeout_s=5.0) as g:
        assert g.close_jaws() == "closed"
        assert g.state() == "closed"
    d.check()


def test_refused_connection_is_typed():
    # the port stays bound (so no other program can take it) but does not listen: connections are refused
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        with pytest.raises(ConnectionFailed, match="refused"):
            PneumaticGripper(f"modbus-tcp://127.0.0.1:{port}?unit=1", poll_s=None).connect()


def test_rtu_serial_client_path(device):
    """The modbus-rtu:///dev/tty... path (pymodbus's serial client on pyserial) on real RTU frames: pyserial
    opens its socket:// URL like a port (a pseudo-terminal would not take pymodbus's inter-byte timeout)."""
    from selfview.drivers.pneumatic_gripper import ModbusLink, ModbusUrl

    d = device([(rtu("01 0000 0002"), rtu("01 01 02")), (rtu("02 0000 0002"), rtu("02 01 02"))], framing="rtu")
    link = ModbusLink(ModbusUrl(url="test", transport="rtu", device=f"socket://127.0.0.1:{d.port}", baud=115200))
    try:
        assert link.read("coil", 0, 2) == [False, True]
        assert link.read("discrete_input", 0, 2) == [False, True]
    finally:
        link.close()
    d.check()


def test_missing_serial_port_is_typed():
    with pytest.raises(ConnectionFailed, match="does not exist"):
        PneumaticGripper("modbus-rtu:///dev/ttyUSB-selfview-missing", poll_s=None).connect()
