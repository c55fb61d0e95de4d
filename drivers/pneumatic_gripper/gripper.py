"""The pneumatic parallel-jaw gripper behind a Modbus valve: switch the valve, confirm with reed switches.

The jaw state decides which fingertip points are valid (the gap differs per state), so the driver only
ever reports a state it has read from both reed switches:

- ``open_jaws()`` / ``close_jaws()`` switch the valve and wait until the matching switch confirms within
  ``timeout_s``; if the other switch is still on then, ``DeviceTimeout`` (the jaws never left: no air, a
  valve that did not switch, a stuck jaw); if neither is on, ``GripperFault`` (stuck between, or the
  target's switch is broken); both on at any time is a ``GripperFault`` too.
- ``state()`` reads both switches now.
- A motion is confirmed by two consecutive readings of the target (its switch on, the other off): one
  reply with a flipped bit cannot confirm it. A reading with both switches on, or one that disagrees
  with the commanded direction in ``state()``, is read once more before it is believed.
- A background poller reads the switches every ``poll_s`` (keeping the terminal's connection watchdog
  fed) on the open connection only: it never reconnects.

The driver's own safe-state rule (it does not rely on the terminal's watchdog alone): after a failed jaw
command, a failed ``safe()`` or a lost link (seen by a call or by the poller), the driver *gives up*:

1. it stops feeding the terminal's watchdog: the poller makes no request, and nothing reconnects on its
   own, until the caller calls ``connect()``;
2. it tries the safe state once: it writes the io map's ``safe_state`` outputs (reconnecting once if the
   link dropped) and reads them back, then closes the connection;
3. it reports what it could confirm: ``safe_report`` (a ``SafeReport``), and the message of the error
   raised to the caller ends with the report's sentence.

Until ``connect()`` (which re-reads the valve outputs and both switches), ``last_state`` is None and jaw
commands raise ``ConnectionLost``. ``safe()`` may always be called; it returns a ``SafeReport`` and raises
when it cannot confirm the safe outputs.

What "safe" means (the io map's ``safe_state``; default ``all-off``): every solenoid de-energised. A single
solenoid valve (spring return) then moves the jaws to its spring position (the state opposite to its
solenoid); a double solenoid (bistable) valve holds the jaws where they are, so a held part stays held and
an open gripper stays open. ``open`` / ``closed`` energise one solenoid instead; the terminal's watchdog
(if it has one) de-energises everything when the master goes silent, which the driver makes happen by
going silent after giving up.

The connection's ``close()`` is the STYLE's ``close()``; the jaws move with ``open_jaws()`` /
``close_jaws()`` (``disconnect()`` is an alias of ``close()``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from selfview.drivers.pneumatic_gripper.iomap import IoMap, Point
from selfview.drivers.pneumatic_gripper.modbus import ConnectionLost, ModbusExceptionReply, ModbusLink
from selfview.errors import CellError, ConfigError, DeviceError, DeviceTimeout, ProtocolError

__all__ = ["PneumaticGripper", "GripperFault", "JawReading", "SafeReport"]

log = logging.getLogger(__name__)


class GripperFault(DeviceError):
    """The reed switches contradict each other or the jaws stopped between them."""


@dataclass(frozen=True)
class JawReading:
    """Both reed switches as read at ``time`` (the driver's monotonic clock, seconds)."""

    open_sensor: bool
    closed_sensor: bool
    time: float

    @property
    def state(self) -> str:
        """'open', 'closed' or 'between' (neither switch on). Raises GripperFault if both are on."""
        if self.open_sensor and self.closed_sensor:
            raise GripperFault("both reed switches (open and closed) are on: a switch is broken or mis-wired")
        if self.open_sensor:
            return "open"
        if self.closed_sensor:
            return "closed"
        return "between"


@dataclass(frozen=True)
class SafeReport:
    """What the driver could confirm when it tried the safe state.

    ``reason`` why it was tried; ``wanted`` the safe outputs; ``written`` whether every write was
    acknowledged; ``outputs`` the solenoid outputs read back afterwards (None: not read); ``confirmed``
    the read-back equals ``wanted``; ``error`` what failed (None: nothing).
    """

    reason: str
    wanted: dict[str, bool]
    written: bool
    outputs: dict[str, bool] | None
    confirmed: bool
    error: str | None = None

    def sentence(self) -> str:
        want = ", ".join(f"{k} {'on' if v else 'off'}" for k, v in self.wanted.items())
        if self.confirmed:
            return f"safe state confirmed: valve outputs read back as {want}"
        if self.written:
            return f"safe state NOT confirmed: outputs written ({want}) but read back as {self.outputs} ({self.error})"
        return (
            f"safe state NOT confirmed: could not write {want} ({self.error}); the driver stopped feeding the "
            "terminal's watchdog"
        )


#: Most values one read may ask for (Modbus Application Protocol: 2000 bits, 125 registers).
_MAX_READ = {"coil": 2000, "discrete_input": 2000, "holding_register": 125, "input_register": 125}


def _span_reads(points: list[Point]) -> list[tuple[str, int, int]]:
    """[(kind, first address, count)]: as few reads as cover every point, within Modbus's limits."""
    spans: list[tuple[str, int, int]] = []
    for p in sorted(set(points), key=lambda p: (p.kind, p.address)):
        if spans and spans[-1][0] == p.kind and p.address - spans[-1][1] < _MAX_READ[p.kind]:
            kind, lo, _ = spans[-1]
            spans[-1] = (kind, lo, p.address - lo + 1)
        else:
            spans.append((p.kind, p.address, 1))
    return spans


class PneumaticGripper:
    """Driver of a pneumatic gripper on a Modbus valve (terminal).

    ``url``: a Modbus URL (``selfview.drivers.pneumatic_gripper.url``). ``io_map``: where the solenoids and reed
    switches are (default: double solenoid on coils 0 (open) and 1 (close), switches on discrete inputs
    0 (open) and 1 (closed)). ``timeout_s``: how long a jaw motion may take to confirm.
    ``request_timeout_s`` / ``retries``: per Modbus request. ``poll_s``: background poll period
    (None: no poller, and the terminal's watchdog is then the caller's business). ``confirm_poll_s``:
    how often the switches are read while a motion is confirmed. Construction does no I/O.
    """

    def __init__(
        self,
        url: str,
        *,
        io_map: IoMap | None = None,
        timeout_s: float = 0.5,
        request_timeout_s: float = 0.25,
        retries: int = 0,
        poll_s: float | None = 0.1,
        confirm_poll_s: float = 0.005,
        clock: Callable[[], float] = time.monotonic,
        trace: Callable[[str, bytes], None] | None = None,
    ):
        self.io_map = io_map if io_map is not None else IoMap()
        if not isinstance(self.io_map, IoMap):
            raise ConfigError(f"io_map: expected an IoMap, got {type(io_map).__name__}")
        for name, v in (("timeout_s", timeout_s), ("confirm_poll_s", confirm_poll_s)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ConfigError(f"gripper {name}={v!r}: expected a positive number of seconds")
        if poll_s is not None and (isinstance(poll_s, bool) or not isinstance(poll_s, (int, float)) or not poll_s > 0):
            raise ConfigError(f"gripper poll_s={poll_s!r}: expected a positive number of seconds or None")
        self.timeout_s = float(timeout_s)
        self.poll_s = None if poll_s is None else float(poll_s)
        self.confirm_poll_s = float(confirm_poll_s)
        self.clock = clock
        self.link = ModbusLink(
            url, timeout_s=request_timeout_s, retries=retries, on_connect=self._on_connect, trace=trace
        )
        self.url = self.link.url.url
        self._explicit_connect = False
        self._lost: str | None = None  # why the state became unknown, until connect() is called again
        self._last: JawReading | None = None
        self._commanded: dict[str, bool] | None = None  # what this driver last wrote
        self.valve_outputs: dict[str, bool] | None = None  # as last read from (or written to) the device
        self.outputs_reset = False  # the device's outputs differed from what was commanded at a reconnect
        self.poll_error: BaseException | None = None
        self.polls = 0
        self._stop = threading.Event()
        self._poller: threading.Thread | None = None
        self._halted: str | None = None  # why the driver gave up (safe-state rule), until connect()
        self._halt_lock = threading.Lock()
        self.safe_report: SafeReport | None = None  # the latest attempt at the safe state

    # --- connection ---------------------------------------------------------------------------
    def connect(self) -> "PneumaticGripper":
        """Connect (or reconnect after a loss or after the driver gave up), read the valve outputs and
        both switches, start the poller. Raises ConnectionFailed, DeviceTimeout, ModbusExceptionReply,
        GripperFault."""
        self._explicit_connect = True
        try:
            if self.link.connected:
                self._read_outputs()
            else:
                self.link.connect()  # reads the outputs through _on_connect
            r = self._read_checked(None)
            r.state  # noqa: B018 - raises GripperFault when both switches stay on
        finally:
            self._explicit_connect = False
        self._lost = None
        self._halted = None
        if self.poll_s is not None and (self._poller is None or not self._poller.is_alive()):
            self._stop.clear()
            self._poller = threading.Thread(target=self._poll_loop, name=f"gripper-poll {self.url}", daemon=True)
            self._poller.start()
        return self

    def close(self) -> None:
        """Stop the poller and close the connection (safe to call twice). The valve keeps its outputs
        until the terminal's watchdog drops them; call ``safe()`` first to leave it safe."""
        self._stop.set()
        t, self._poller = self._poller, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=self.link.lock_timeout_s + (self.poll_s or 0) + 1.0)
        self.link.close()
        self._last = None

    disconnect = close

    def __enter__(self) -> "PneumaticGripper":
        return self.connect()

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def connected(self) -> bool:
        return self.link.connected

    @property
    def halted(self) -> str | None:
        """Why the driver gave up (its safe-state rule), or None; cleared by ``connect()``."""
        return self._halted

    def _on_connect(self) -> None:
        # A reconnect that connect() did not ask for: what happened meanwhile is unknown.
        if not self._explicit_connect and self.link.connections > 1:
            self._lost = self._lost or "the connection was re-established after a loss"
        self._read_outputs()

    def _note_failure(self, exc: BaseException) -> None:
        self._last = None
        if not isinstance(exc, ModbusExceptionReply):
            self._lost = f"{type(exc).__name__}: {exc}"

    def _require_link(self, what: str) -> None:
        if self._halted is not None:
            raise ConnectionLost(
                f"{self.url}: {what} refused: the driver gave up ({self._halted}) and left the valve in its safe "
                "state as far as it could; call connect() to re-read the valve and resume"
            )
        if self._lost is not None:
            raise ConnectionLost(
                f"{self.url}: {what} refused: the gripper state is unknown since the connection was lost "
                f"({self._lost}); call connect() to re-establish it and re-read the valve"
            )

    # --- the safe-state rule --------------------------------------------------------------------
    def _give_up(self, reason: str) -> SafeReport | None:
        """Stop feeding the watchdog, try the safe state once, close the link; returns the report
        (None if another thread is giving up already)."""
        if not self._halt_lock.acquire(blocking=False):
            return None
        try:
            # under the link's lock, so that no poll can slip in between the decision and the attempt
            try:
                with self.link._locked("give up"):
                    self._halted = reason
            except DeviceTimeout:
                self._halted = reason
            self._last = None
            report = self._try_safe(reason)
            self.link.close()  # silence: a terminal watching its master sees none
            return report
        finally:
            self._halt_lock.release()

    def _try_safe(self, reason: str) -> SafeReport:
        want = self.io_map.drive(self.io_map.safe_state)
        written, outputs, error = False, None, None
        try:
            self._write_outputs(want, note=False)
            written = True
            outputs = self._read_outputs()
        except CellError as exc:
            error = f"{type(exc).__name__}: {exc}"
        except OSError as exc:  # never let the attempt itself escape
            error = f"{type(exc).__name__}: {exc}"
        confirmed = outputs is not None and outputs == want
        if written and outputs is not None and not confirmed:
            error = error or "the terminal did not keep the written outputs"
        report = SafeReport(reason, dict(want), written, outputs, confirmed, error)
        self.safe_report = report
        (log.info if confirmed else log.error)("%s: gave up (%s): %s", self.url, reason, report.sentence())
        return report

    def _failed(self, exc: CellError, what: str) -> CellError:
        """The error to raise after ``exc`` made the driver give up: same type, the report appended."""
        report = self._give_up(f"{what} failed: {type(exc).__name__}: {exc}")
        if report is None:
            return exc
        msg = f"{exc}; {report.sentence()}"
        try:
            if isinstance(exc, ModbusExceptionReply):
                new = ModbusExceptionReply(msg, exc.function, exc.code)
            else:
                new = type(exc)(msg)
        except Exception:  # an exception type with another constructor: keep it as it is
            return exc
        new.safe_report = report
        new.__cause__ = exc
        return new

    # --- reading ------------------------------------------------------------------------------
    def _read_points(self, points: list[Point], *, reconnect: bool = True) -> list[bool]:
        values: dict[Point, bool] = {}
        for kind, lo, n in _span_reads(points):
            read = self.link.read(kind, lo, n, reconnect=reconnect)
            for p in points:
                if p.kind == kind and lo <= p.address < lo + n:
                    v = read[p.address - lo]
                    values[p] = bool(v) if p.bit is None else bool((v >> p.bit) & 1)
        return [values[p] for p in points]

    def _read_raw(self, *, reconnect: bool = True) -> JawReading:
        o, c = self._read_points([self.io_map.open_sensor, self.io_map.closed_sensor], reconnect=reconnect)
        r = JawReading(o, c, self.clock())
        self._last = r
        return r

    def read(self) -> JawReading:
        """Read both reed switches now (one request per table they sit in). A link failure makes the
        driver give up (see the module's safe-state rule); the error says what it confirmed."""
        try:
            return self._read_raw()
        except CellError as exc:
            self._note_failure(exc)
            if isinstance(exc, ModbusExceptionReply):
                raise
            raise self._failed(exc, "reading the reed switches") from exc

    def _read_checked(self, expect: str | None) -> JawReading:
        """A reading, read once more when it contradicts itself (both switches on) or disagrees with
        ``expect`` (the commanded direction); the second reading is the one believed."""
        r = self.read()
        if (r.open_sensor and r.closed_sensor) or (expect is not None and r.state != expect):
            r = self.read()
        return r

    def _expected(self) -> str | None:
        return None if self._commanded is None else self.io_map.direction(self._commanded)

    def state(self) -> str:
        """Read the switches now: 'open', 'closed' or 'between'. A reading that disagrees with the
        commanded direction, or has both switches on, is read again. Raises GripperFault if both
        stay on, and the link's errors (ConnectionLost, DeviceTimeout, ModbusExceptionReply, ...)."""
        return self._read_checked(self._expected()).state

    @property
    def last_state(self) -> str | None:
        """The state of the latest successful read (poller or call), or None when unknown: never read,
        a read failed since, the connection was lost, the driver gave up, or the switches contradicted
        each other."""
        r = self._last
        if r is None or self._lost is not None or self._halted is not None:
            return None
        try:
            return r.state
        except GripperFault:
            return None

    @property
    def last_reading(self) -> JawReading | None:
        return self._last

    def _read_outputs(self, *, reconnect: bool = True) -> dict[str, bool]:
        valves = self.io_map.valves
        vals = self._read_points(list(valves.values()), reconnect=reconnect)
        out = dict(zip(valves, vals))
        if self._commanded is not None and out != self._commanded:
            self.outputs_reset = True
            log.warning("%s: valve outputs are %s, last commanded %s (reset by the terminal?)", self.url, out, self._commanded)
        self.valve_outputs = out
        return out

    def outputs(self) -> dict[str, bool]:
        """Read the solenoid outputs now: {'open': bool, 'close': bool} for the solenoids present. Modbus
        TCP has no checksum, so the outputs are read until two readings in a row agree (at most 4 reads;
        ``ProtocolError`` if they never do)."""
        try:
            last = None
            for _ in range(4):
                now = self._read_outputs()
                if now == last:
                    return now
                last = now
            raise ProtocolError(f"{self.url}: valve outputs: no two readings in a row agree in 4 reads (line noise?)")
        except CellError as exc:
            self._note_failure(exc)
            if isinstance(exc, ModbusExceptionReply):
                raise
            raise self._failed(exc, "reading the valve outputs") from exc

    # --- writing ------------------------------------------------------------------------------
    def _write_outputs(self, want: dict[str, bool], *, note: bool = True) -> None:
        valves = self.io_map.valves
        coils_off, coils_on = [], []
        registers: dict[int, list[tuple[int, bool]]] = {}
        for name, value in want.items():
            p = valves[name]
            if p.kind == "coil":
                (coils_on if value else coils_off).append(p.address)
            else:
                registers.setdefault(p.address, []).append((p.bit, value))
        try:
            # break before make: a double valve never sees both solenoids energised by this driver
            for a in coils_off:
                self.link.write_coil(a, False)
            for address, bits in registers.items():
                touched = sum(1 << b for b, _ in bits)
                set_bits = sum(1 << b for b, v in bits if v)
                if self.io_map.register_write == "mask":
                    self.link.mask_write_register(address, 0xFFFF & ~touched, set_bits)
                else:
                    (old,) = self.link.read("holding_register", address, 1)
                    self.link.write_register(address, (old & ~touched & 0xFFFF) | set_bits)
            for a in coils_on:
                self.link.write_coil(a, True)
        except CellError as exc:
            if note:
                self._note_failure(exc)
            self.valve_outputs = None
            raise
        self._commanded = dict(want)
        self.valve_outputs = dict(want)

    def _move(self, target: str) -> str:
        what = f"{'open' if target == 'open' else 'close'}_jaws"
        self._require_link(what)
        try:
            return self._move_confirmed(target)
        except CellError as exc:
            raise self._failed(exc, what) from exc

    def _move_confirmed(self, target: str) -> str:
        self._write_outputs(self.io_map.drive(target))
        other = "closed" if target == "open" else "open"
        deadline = self.clock() + self.timeout_s
        seen_target = False
        while True:
            r = self._read_raw()
            if r.open_sensor and r.closed_sensor:
                r = self._read_raw()  # one flipped bit is not a broken switch: read once more
            state = r.state  # raises GripperFault when both switches are still on
            if state == target:
                if seen_target:  # two consecutive readings agree: a single corrupted reply cannot confirm
                    return state
                seen_target = True
                continue
            seen_target = False
            now = self.clock()
            if now >= deadline:
                break
            time.sleep(min(self.confirm_poll_s, deadline - now))
        if state == "between":
            raise GripperFault(
                f"{self.url}: jaws left '{other}' but the '{target}' reed switch did not come on within "
                f"{self.timeout_s} s: jaws stuck between, or that switch is broken"
            )
        raise DeviceTimeout(
            f"{self.url}: jaws still '{other}' {self.timeout_s} s after the valve was switched to '{target}': "
            "no air, valve not switching, or jaws stuck"
        )

    def open_jaws(self) -> str:
        """Open the jaws and wait for the open switch (``timeout_s``). Returns 'open'. On any failure
        the driver gives up (the module's safe-state rule) and the error says what it confirmed."""
        return self._move("open")

    def close_jaws(self) -> str:
        """Close the jaws and wait for the closed switch (``timeout_s``). Returns 'closed'. On any
        failure the driver gives up (the module's safe-state rule) and the error says what it confirmed."""
        return self._move("closed")

    def move(self, state: str) -> str:
        """Move to the cell's gripper state 'open' or 'closed' (the names in cell.yaml)."""
        if state == "open":
            return self.open_jaws()
        if state == "closed":
            return self.close_jaws()
        raise ConfigError(f"gripper state {state!r}: expected 'open' or 'closed'")

    def safe(self) -> SafeReport:
        """Command the io map's ``safe_state`` (de-energise, open or close) and read the outputs back;
        does not wait for the switches. Tried even after a connection loss or after the driver gave up
        (it reconnects once). Returns the report when the outputs are confirmed; otherwise the driver
        gives up and the error (GripperFault, or the link's) carries the report."""
        report = self._try_safe("safe() called")
        if report.confirmed:
            return report
        self._halted = self._halted or f"safe() could not confirm the safe state ({report.error})"
        self._last = None
        self.link.close()
        err = GripperFault(f"{self.url}: {report.sentence()}")
        err.safe_report = report
        raise err

    # --- poller -------------------------------------------------------------------------------
    def _poll_once(self) -> None:
        with self.link._locked("poll"):
            if self._halted is not None or self._lost is not None:
                return  # the safe-state rule: after a failure nothing feeds the watchdog until connect()
            self._read_raw(reconnect=False)

    def _poll_loop(self) -> None:
        while not self._stop.wait(self.poll_s):
            try:
                self._poll_once()
                self.poll_error = None
            except GripperFault as exc:  # the switches contradict each other: the link is fine
                self.poll_error = exc
            except CellError as exc:
                self.poll_error = exc
                self._note_failure(exc)
                if not isinstance(exc, ModbusExceptionReply):
                    self._give_up(f"the poller lost the link: {type(exc).__name__}: {exc}")
            except Exception as exc:  # a bug must not kill the poller silently
                log.exception("%s: gripper poller", self.url)
                self.poll_error = exc
            self.polls += 1
