"""A stall of the host that begins just as a silent read ends (the read returned nothing, the program was
stopped before it looked at the clock) and lasts past the reply's deadline: the complete reply that arrived
meanwhile is read and counts; it is no device fault (found by the fault campaign's host-stall family,
``selfview robot depart`` stopped with SIGSTOP: exit 4, "no prompt ... (received ...'\\r\\n')")."""

from __future__ import annotations

import time

from selfview.drivers.puma_val_serial import PumaVAL


class _StalledAfterSilence:
    """A serial-like port: after the host's CR, the controller's prompt arrives while the host is stopped
    right after a read that found the line silent."""

    timeout = 0.01

    def __init__(self, stall_s: float):
        self.stall_s, self.pending, self.stall_next, self.written = stall_s, b"", False, b""

    @property
    def in_waiting(self) -> int:
        return 0 if self.stall_next else len(self.pending)

    def write(self, data: bytes) -> int:
        self.written += data
        if data.endswith(b"\r"):
            self.pending += b"\r\n."  # the controller's answer: a new line and its prompt
            self.stall_next = True
        return len(data)

    def read(self, n: int = 1) -> bytes:
        if self.stall_next:  # the read found the line silent; the host is stopped before it goes on
            self.stall_next = False
            time.sleep(self.stall_s)
            return b""
        out, self.pending = self.pending[:n], self.pending[n:]
        if not out:
            time.sleep(self.timeout)
        return out


def test_a_reply_that_arrived_while_the_host_was_stopped_after_a_silent_read_counts():
    port = _StalledAfterSilence(stall_s=0.4)
    robot = PumaVAL(port, timeout_s=0.2)
    robot.connect()  # CR, then the prompt: read after the stall, past the 0.2 s deadline
    assert port.written.endswith(b"\r")
    robot.close()


def test_an_abort_confirmed_while_the_host_was_stopped_after_a_silent_read_counts_as_confirmed():
    port = _StalledAfterSilence(stall_s=0.4)
    robot = PumaVAL(port, timeout_s=0.2)
    robot.connect()
    res = robot.abort()  # ABORT, then the prompt arrives while the host is stopped past the 0.2 s budget
    assert port.written.rstrip(b"\r").endswith(b"ABORT")
    assert res.written and res.confirmed, res.detail
    robot.close()


class _TalksOnAfterAbort(_StalledAfterSilence):
    """A port whose controller answers CR with its prompt, but after ABORT never stops sending (line noise, a
    babbling controller): bytes are always waiting and no prompt ever ends them."""

    def __init__(self):
        super().__init__(stall_s=0.0)
        self.babbling = False

    @property
    def in_waiting(self) -> int:
        return 1 if self.babbling else len(self.pending)

    def write(self, data: bytes) -> int:
        if b"ABORT" in data:
            self.babbling = True
            self.written += data
            return len(data)
        return super().write(data)

    def read(self, n: int = 1) -> bytes:
        if self.babbling:
            time.sleep(0.001)
            return b"noise "
        self.stall_next = False
        return super().read(n)


def test_an_abort_on_a_line_that_never_stops_talking_returns_unconfirmed_within_its_bound():
    """The answer to ABORT is read for the driver's reply limit plus the overtime at most, however many bytes
    keep arriving (the read loop once looked at its deadline only after a silent read: it never returned, and
    neither did the motion's wait nor the cleanup's ABORT that called it)."""
    import threading

    robot = PumaVAL(_TalksOnAfterAbort(), timeout_s=0.2)
    robot.connect()
    box: dict = {}
    t = threading.Thread(target=lambda: box.setdefault("res", robot.abort()), daemon=True)
    t.start()
    t.join(10.0)
    assert not t.is_alive(), "abort() did not return on a line that keeps talking"
    res = box["res"]
    assert res.written and not res.confirmed and "no prompt within 0.2 s after ABORT" in res.detail, res
