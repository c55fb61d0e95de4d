"""Transcript tests: the exact Modbus bytes each driver call sends, and how each reply is taken.

The device here is a raw socket on 127.0.0.1 playing a script of (expected request, reply) frames,
written out by hand from the Modbus specification (MBAP: transaction id, protocol 0, length, unit;
RTU: unit, PDU, CRC-16 low byte first). No pymodbus on this side.
"""

from __future__ import annotations

import socket
import threading
import time

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
    then the outputs read back until two readings agree."""
    return [
        (mbap(tid, "05 0000 0000"), mbap(tid, "05 0000 0000")),
        (mbap(tid + 1, "05 0001 0000"), mbap(tid + 1, "05 0001 0000")),
        (mbap(tid + 2, "01 0000 0002"), mbap(tid + 2, "01 01 00")),
        (mbap(tid + 3, "01 0000 0002"), mbap(tid + 3, "01 01 00")),
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
            (mbap(8, "01 0000 0002"), mbap(8, "01 01 02")),  # FC1: the valve still holds 'close' ...
            (mbap(9, "01 0000 0002"), mbap(9, "01 01 02")),  # ... read until two readings agree
        ]
    )
    # a stroke time far beyond what the transcript needs: a stalled machine cannot turn 'travelling' into a timeout
    g = PneumaticGripper(d.url, poll_s=None, confirm_poll_s=0.001, timeout_s=30.0)
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
            (mbap(7, "03 0000 0001"), mbap(7, "03 02 8002")),  # the outputs read back ...
            (mbap(8, "03 0000 0001"), mbap(8, "03 02 8002")),  # ... twice
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
            (mbap(6, "03 0007 0001"), mbap(6, "03 02 0004")),  # bit 2 (open) on, bit 3 (close) off
            (mbap(7, "03 0007 0001"), mbap(7, "03 02 0004")),
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
            (mbap(4, "01 0003 0001"), mbap(4, "01 01 00")),  # ... and read it back ...
            (mbap(5, "01 0003 0001"), mbap(5, "01 01 00")),  # ... until two readings agree
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
            (rtu("01 0000 0002"), rtu("01 01 01")),
            (rtu("01 0000 0002"), rtu("01 01 01")),
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
            (mbap(5, "02 0000 0002"), mbap(5, "02 01 01")),  # nothing commanded yet: two readings agree
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
    with PneumaticGripper(d.url, poll_s=None, request_timeout_s=0.2, retries=0) as g:
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


#: close_jaws() whose second write reaches the device with bit 4 of its address flipped: the device
#: switches coil 17 on and echoes that
CORRUPTED_CLOSE = CONNECT_OPEN + [
    (mbap(3, "05 0000 0000"), mbap(3, "05 0000 0000")),
    (mbap(4, "05 0001 FF00"), mbap(4, "05 0011 FF00")),
]


def test_write_echo_naming_another_coil_is_reported_on_a_shared_terminal(device):
    """Modbus TCP has no checksum. A write whose echo names another coil switched on: by
    default (a terminal shared with other valves) the driver leaves that coil alone and names it."""
    d = device(CORRUPTED_CLOSE + SAFE_AFTER_RECONNECT)
    with PneumaticGripper(d.url, poll_s=None) as g:
        with pytest.raises(ProtocolError, match="coil 17, which this gripper does not own, may have been switched on") as e:
            g.close_jaws()
        assert e.value.echoed == (17, True) and e.value.sent == (1, True)
        assert g.safe_report.confirmed
    d.check()


def test_write_echo_naming_another_coil_switches_it_off_on_a_dedicated_terminal(device):
    """With ``stray_coils: switch-off`` the coil the corrupted request switched on is switched off at
    once (on a new connection: the mismatch dropped the old one) and read back, then the safe state."""
    d = device(
        CORRUPTED_CLOSE
        + [
            (mbap(1, "01 0000 0002"), mbap(1, "01 01 00")),  # the new connection reads the outputs ...
            (mbap(2, "05 0011 0000"), mbap(2, "05 0011 0000")),  # ... coil 17 off ...
            (mbap(3, "01 0011 0001"), mbap(3, "01 01 00")),  # ... read back ...
            (mbap(4, "01 0011 0001"), mbap(4, "01 01 00")),  # ... twice
        ]
        + safe_on_link(5)
    )
    with PneumaticGripper(d.url, io_map=IoMap(stray_coils="switch-off"), poll_s=None) as g:
        with pytest.raises(ProtocolError, match="coil 17, not this gripper's, .* switched off again and read back off"):
            g.close_jaws()
        assert g.safe_report.confirmed
    d.check()


def test_reply_from_another_unit_is_ignored_until_timeout(device):
    # as on a shared RTU bus: a frame for another unit is not ours; the device counts as silent
    d = device(CONNECT_OPEN + [(mbap(3, "02 0000 0002"), mbap(3, "02 01 01", unit=9))] + SAFE_AFTER_RECONNECT)
    with PneumaticGripper(d.url, poll_s=None, request_timeout_s=0.2, retries=0) as g:
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
    """Single-bit errors in read replies. A reading with the target's switch on must be
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
            (mbap(11, "02 0000 0002"), mbap(11, "02 01 02")),  # confirmed by the switches
            (mbap(12, "01 0000 0002"), mbap(12, "01 01 00")),  # a flipped bit: outputs look reset ...
            (mbap(13, "01 0000 0002"), mbap(13, "01 01 02")),  # ... read again: 'close' held ...
            (mbap(14, "01 0000 0002"), mbap(14, "01 01 02")),  # ... and again: two agree
            # state(): the reading disagrees with the command (a flipped bit turned 'closed' into
            # 'between'), so it is read again
            (mbap(15, "02 0000 0002"), mbap(15, "02 01 00")),
            (mbap(16, "02 0000 0002"), mbap(16, "02 01 02")),
        ]
    )
    with PneumaticGripper(d.url, poll_s=None, confirm_poll_s=0.001, timeout_s=5.0) as g:
        assert g.close_jaws() == "closed"
        assert g.state() == "closed"
    d.check()


def test_stroke_with_outputs_reset_by_the_terminal_is_a_fault(device):
    """The terminal's watchdog resets the outputs during a stroke (the master was silent
    through a stalled exchange). A double valve then holds the jaws where they got to, so both switch
    readings confirm the target; the outputs read back say the valve no longer holds it: a GripperFault,
    then the safe state, never a success."""
    d = device(
        CONNECT_OPEN
        + [
            (mbap(3, "05 0000 0000"), mbap(3, "05 0000 0000")),
            (mbap(4, "05 0001 FF00"), mbap(4, "05 0001 FF00")),
            (mbap(5, "02 0000 0002"), mbap(5, "02 01 02")),
            (mbap(6, "02 0000 0002"), mbap(6, "02 01 02")),  # the switches confirm 'closed' ...
            (mbap(7, "01 0000 0002"), mbap(7, "01 01 00")),  # ... but the outputs are off ...
            (mbap(8, "01 0000 0002"), mbap(8, "01 01 00")),  # ... twice: reset by the terminal
        ]
        + safe_on_link(9)
    )
    with PneumaticGripper(d.url, poll_s=None, confirm_poll_s=0.001) as g:
        with pytest.raises(GripperFault, match="reset them during the stroke") as e:
            g.close_jaws()
        assert "safe state confirmed" in str(e.value)
        assert g.last_state is None and g.halted is not None
        with pytest.raises(ConnectionLost):  # the driver gave up: no jaw command until connect()
            g.open_jaws()
    d.check()


def test_poller_losing_the_link_during_a_stroke_fails_the_stroke(device, monkeypatch):
    """The poller's request fails while a jaw command waits between its switch readings. The
    driver gives up (safe state, once) before anything else can use the link, and the stroke fails:
    it never reconnects to report a jaw position the safe state is about to undo."""
    d = device(
        CONNECT_OPEN
        + [
            (mbap(3, "05 0000 0000"), mbap(3, "05 0000 0000")),
            (mbap(4, "05 0001 FF00"), mbap(4, "05 0001 FF00")),
            (mbap(5, "02 0000 0002"), mbap(5, "02 01 00")),  # travelling
            (mbap(6, "02 0000 0002"), HANG_UP),  # the poller's read: the link drops
        ]
        + SAFE_AFTER_RECONNECT  # the safe state, tried once, on a new connection
    )
    from selfview.drivers.pneumatic_gripper import gripper as mod

    # the stroke's deadline far away: the order (a 'travelling' reading, the wait, the poll) cannot depend on
    # the machine's speed (with 0.5 s, a stalled machine reached the deadline before the wait and its poll)
    g = PneumaticGripper(d.url, poll_s=None, confirm_poll_s=0.001, timeout_s=30.0)
    polled = []

    stroke_thread = threading.current_thread()

    class StrokeTime:  # the gripper module's clock, whose sleep is the stroke's wait between its readings
        def __getattr__(self, name):
            return getattr(time, name)

        @staticmethod
        def sleep(seconds):  # the poller's turn comes while the stroke waits
            if threading.current_thread() is not stroke_thread:  # another test's leftover thread, if any
                time.sleep(seconds)
            elif not polled:
                polled.append(True)
                g._poll_step()

    with g:
        # only the gripper module's sleep, in this thread: with time.sleep itself patched, any thread's sleep
        # (another test's leftover) could run the poll at a moment of its own; on a loaded machine the poll
        # then came before the stroke's wait and the stroke's own read met the dropped link
        monkeypatch.setattr(mod, "time", StrokeTime())
        with pytest.raises(ConnectionLost, match="gave up during the stroke"):
            g.close_jaws()
        assert g.halted is not None and g.safe_report.confirmed and not g.connected
        assert g.last_state is None
    d.check()


def test_state_with_nothing_commanded_needs_two_agreeing_readings(device):
    """With no direction commanded (the valve holds the jaws), a reply with a flipped bit is
    not believed alone: the state is the one two readings in a row agree on."""
    d = device(
        CONNECT_OPEN
        + [
            (mbap(3, "02 0000 0002"), mbap(3, "02 01 00")),  # a flipped bit: 'between' ...
            (mbap(4, "02 0000 0002"), mbap(4, "02 01 01")),  # ... not repeated: 'open' ...
            (mbap(5, "02 0000 0002"), mbap(5, "02 01 01")),  # ... repeated: believed
        ]
    )
    with PneumaticGripper(d.url, poll_s=None) as g:
        assert g.state() == "open"
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


def test_a_register_write_whose_echo_differs_is_a_protocol_error(device):
    """FC6's reply must echo the register and value sent: an echo with a bit flipped (a corrupted
    request, or a reply to another one) is a protocol error naming both, and the link is dropped."""
    from selfview.drivers.pneumatic_gripper.modbus import ModbusLink, WriteEchoMismatch

    d = device([(mbap(1, "06 0000 8002"), mbap(1, "06 0000 8003"))])  # the value's bit 0 flipped
    link = ModbusLink(d.url, timeout_s=0.5)
    with pytest.raises(WriteEchoMismatch, match=r"echoes \(0, 32771\), not \(0, 32770\)") as e:
        link.write_register(0, 0x8002)
    assert isinstance(e.value, ProtocolError) and e.value.sent == (0, 0x8002) and e.value.echoed == (0, 0x8003)
    assert not link.connected
    d.check()


def test_a_request_the_protocol_cannot_carry_is_refused_before_it_is_sent(device):
    """An address, count, value or mask outside what a Modbus frame carries is a ``ConfigError`` naming it,
    and nothing goes on the wire: the link stays up, the next request is answered (tid 1)."""
    from selfview.drivers.pneumatic_gripper.modbus import ModbusLink
    from selfview.errors import ConfigError

    d = device([(mbap(1, "01 0000 0002"), mbap(1, "01 01 01"))])
    link = ModbusLink(d.url, timeout_s=0.5)
    link.connect()
    bad = [
        (lambda: link.read("coil", -1), "address -1"),
        (lambda: link.read("coil", 70000), "address 70000"),
        (lambda: link.read("coil", 1.5), "address 1.5"),
        (lambda: link.read("coil", True), "address True"),
        (lambda: link.read("coil", 0, 0), "count 0"),
        (lambda: link.read("coil", 0, 2001), "count 2001"),
        (lambda: link.read("holding_register", 0, 126), "count 126"),
        (lambda: link.read("coil", 0xFFFF, 2), "count 2"),  # past the last address
        (lambda: link.write_coil(70000, True), "address 70000"),
        (lambda: link.write_coil(0, float("nan")), "value nan"),
        (lambda: link.write_register(0, 1.7), "value 1.7"),
        (lambda: link.write_register(0, 0x10000), "value 65536"),
        (lambda: link.mask_write_register(0, -1, 0), "and_mask -1"),
        (lambda: link.mask_write_register(0, 0xFFFF, 0x1FFFF), "or_mask 131071"),
    ]
    for call, named in bad:
        with pytest.raises(ConfigError, match=f"{named}.*nothing was sent"):
            call()
    assert link.connected and d.received == []
    assert link.read("coil", 0, 2) == [True, False]
    link.close()
    d.check()


def test_dropping_unasked_bytes_before_an_rtu_request_ends_on_a_peer_that_never_stops_sending():
    """Before an RTU-over-socket request the bytes already waiting are dropped, but at most a bound's worth:
    a peer that keeps sending (a babbling line) cannot hold the request there (the loop once read until the
    line fell silent, and never returned)."""
    from selfview.drivers.pneumatic_gripper import modbus

    class Babbling:
        def __init__(self):
            self.given = 0

        def recv(self, n, flags=0):
            self.given += n
            return b"\x55" * n

    peer = Babbling()
    t = threading.Thread(target=modbus._discard_unasked, args=(peer,), daemon=True)
    t.start()
    t.join(10.0)
    assert not t.is_alive(), "the drop loop did not end on a peer that never stops sending"
    assert modbus._DISCARD_MAX <= peer.given < modbus._DISCARD_MAX + 4096
