"""The pneumatic parallel-jaw gripper behind a Modbus valve: switch the valve, confirm with reed switches.

The jaw state decides which fingertip points are valid (the gap differs per state), so the driver only
ever reports a state it has read from both reed switches. Its own safe-state rule (it does not rely on
the terminal's watchdog alone): after a failed jaw command, a failed ``safe()`` or a lost link, the
driver gives up (``PneumaticGripper._give_up``): silence, the safe state tried once, a report of what
it confirmed.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from selfview.drivers import signals
from selfview.drivers._ownership import DeviceLock
from selfview.drivers.pneumatic_gripper.iomap import IoMap, Point
from selfview.drivers.pneumatic_gripper.modbus import (DEFAULT_READ_RETRIES, DEFAULT_TIMEOUT_S, ConnectionLost, ModbusExceptionReply,
                                                    ModbusLink, WriteEchoMismatch)
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

    One program owns a valve terminal: ``connect()`` (which re-reads the valve outputs and both switches)
    takes its lock (``selfview.drivers._ownership``) and ``close()`` gives it back; a second driver meets
    ``DeviceBusy`` naming the holder. Until ``connect()``, ``last_state`` is None and jaw commands raise
    ``ConnectionLost``; ``safe()`` may always be called. A background poller reads the switches every
    ``poll_s`` (keeping the terminal's connection watchdog fed) on the open connection only: it never
    reconnects. ``disconnect()`` is an alias of ``close()``.
    """

    def __init__(
        self,
        url: str,
        *,
        io_map: IoMap | None = None,
        timeout_s: float = 0.5,
        request_timeout_s: float = DEFAULT_TIMEOUT_S,
        retries: int = DEFAULT_READ_RETRIES,
        poll_s: float | None = 0.1,
        confirm_poll_s: float = 0.005,
        clock: Callable[[], float] = time.monotonic,
        trace: Callable[[str, bytes], None] | None = None,
    ):
        self.io_map = io_map if io_map is not None else IoMap()
        if not isinstance(self.io_map, IoMap):
            raise ConfigError(f"io_map: expected an IoMap, got {type(io_map).__name__}")
        for name, v in (("timeout_s", timeout_s), ("confirm_poll_s", confirm_poll_s)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < float("inf"):
                raise ConfigError(f"gripper {name}={v!r}: expected a finite positive number of seconds (every wait ends)")
        if poll_s is not None and (isinstance(poll_s, bool) or not isinstance(poll_s, (int, float))
                                   or not 0 < poll_s < float("inf")):
            raise ConfigError(f"gripper poll_s={poll_s!r}: expected a finite positive number of seconds or None")
        self.timeout_s = float(timeout_s)
        self.poll_s = None if poll_s is None else float(poll_s)
        self.confirm_poll_s = float(confirm_poll_s)
        self.clock = clock
        self.link = ModbusLink(
            url, timeout_s=request_timeout_s, retries=retries, on_connect=self._on_connect, trace=trace
        )
        self.url = self.link.url.url
        u = self.link.url
        self._owner = (DeviceLock.for_path("valve terminal", u.device) if u.transport == "rtu"
                       else DeviceLock.for_host("valve terminal", u.host, u.port))
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
        self._gave_up = False  # the safe state was tried after giving up, since the last connect()
        self._halt_lock = threading.Lock()
        self._interrupted = threading.Event()  # a jaw wait ends at once (``interrupt()``), until connect()
        self.safe_report: SafeReport | None = None  # the latest attempt at the safe state

    # --- connection ---------------------------------------------------------------------------
    def connect(self, *, clear_stale: bool = False) -> "PneumaticGripper":
        """Connect (or reconnect after a loss or after the driver gave up), read the valve outputs and
        both switches, start the poller. Raises ConnectionFailed, DeviceTimeout, ModbusExceptionReply,
        GripperFault; ``StaleState`` if the previous program on this terminal died with the valve
        energised (nothing is sent; ``clear_stale`` once the operator has checked the gripper)."""
        first = not self._owner.held
        self._owner.acquire(clear_stale=clear_stale)  # DeviceBusy naming the program that holds the valve terminal
        self._explicit_connect = True
        try:
            if self.link.connected:
                self._read_outputs()
            else:
                self.link.connect()  # reads the outputs through _on_connect
            r = self._read_checked(None)
            r.state  # noqa: B018 - raises GripperFault when both switches stay on
        except BaseException:
            if first:  # a connect that failed leaves the terminal to others
                self.link.close()
                self._owner.release()
            raise
        finally:
            self._explicit_connect = False
        self._lost = None
        self._halted = None
        self._gave_up = False
        self._interrupted.clear()
        signals.watch(self)  # a termination signal makes the valve safe, whichever thread drives it
        if self.poll_s is not None and (self._poller is None or not self._poller.is_alive()):
            self._stop.clear()
            self._poller = threading.Thread(target=self._poll_loop, name=f"gripper-poll {self.url}", daemon=True)
            self._poller.start()
        return self

    def close(self) -> None:
        """Stop the poller and close the connection (safe to call twice). The valve keeps its outputs
        until the terminal's watchdog drops them; call ``safe()`` first to leave it safe."""
        signals.unwatch(self)
        self._stop.set()
        t, self._poller = self._poller, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=self.link.lock_timeout_s + (self.poll_s or 0) + 1.0)
        self.link.close()
        self._last = None
        self._owner.release()

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
        if self._interrupted.is_set():
            raise GripperFault(f"{self.url}: {what} refused: the driver was interrupted; call connect() to resume")
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
        (None if another thread is giving up already).

        1. The poller makes no request, and nothing reconnects on its own, until the caller calls
           ``connect()``;
        2. the io map's ``safe_state`` outputs are written (reconnecting once if the link dropped) and
           read back, then the connection is closed;
        3. ``safe_report`` (a ``SafeReport``) says what could be confirmed, and the message of the error
           raised to the caller ends with the report's sentence.
        """
        if not self._halt_lock.acquire(blocking=False):
            return None
        try:
            if self._gave_up and self.safe_report is not None:
                return self.safe_report  # tried once since connect(): reconnecting again would feed the watchdog
            # under the link's lock, so that no poll can slip in between the decision and the attempt
            try:
                with self.link._locked("give up"):
                    self._halted = reason
            except DeviceTimeout:
                self._halted = reason
            self._last = None
            report = self._try_safe(reason)
            self._gave_up = True
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
            outputs = self._read_outputs_agreed()
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
        for k, v in vars(exc).items():  # what the error carries besides its message (an echo's addresses)
            if not hasattr(new, k) or getattr(new, k) in ("", ()):
                setattr(new, k, v)
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
        driver give up (``_give_up``); the error says what it confirmed."""
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

    def _read_agreed(self, expect: str | None, reads: int = 4) -> JawReading:
        """A reading that either agrees with ``expect`` (the commanded direction; a reply corrupted into
        it is as likely as the truth) or is repeated by the next one: with no command to compare with
        (the valve holds the jaws where they are), two readings in a row must agree. ``ProtocolError``
        when none do in ``reads`` reads."""
        prev = None
        for _ in range(reads):
            r = self.read()
            both = r.open_sensor and r.closed_sensor
            if not both and expect is not None and r.state == expect:
                return r
            if prev is not None and (r.open_sensor, r.closed_sensor) == (prev.open_sensor, prev.closed_sensor):
                return r
            prev = r
        raise ProtocolError(f"{self.url}: reed switches: no two readings in a row agree in {reads} reads (line noise?)")

    def _expected(self) -> str | None:
        return None if self._commanded is None else self.io_map.direction(self._commanded)

    def state(self) -> str:
        """Read the switches now: 'open', 'closed' or 'between'. A reading that agrees with the commanded
        direction is believed; any other (both switches on, another state, or no direction commanded) is
        believed once the next reading repeats it. Raises GripperFault if both stay on, and the link's
        errors (ConnectionLost, DeviceTimeout, ModbusExceptionReply, ...)."""
        try:
            r = self._read_agreed(self._expected())
        except ProtocolError as exc:
            self._note_failure(exc)
            raise self._failed(exc, "reading the reed switches") from exc
        return r.state

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

    def _read_outputs_agreed(self, reads: int = 4) -> dict[str, bool]:
        """The solenoid outputs, read until two readings in a row agree (Modbus TCP has no checksum: one
        reply with a flipped bit cannot pass); ``ProtocolError`` when none agree in ``reads`` reads."""
        last = None
        for _ in range(reads):
            now = self._read_outputs()
            if now == last:
                return now
            last = now
        raise ProtocolError(f"{self.url}: valve outputs: no two readings in a row agree in {reads} reads (line noise?)")

    def outputs(self) -> dict[str, bool]:
        """Read the solenoid outputs now: {'open': bool, 'close': bool} for the solenoids present. Modbus
        TCP has no checksum, so the outputs are read until two readings in a row agree (at most 4 reads;
        ``ProtocolError`` if they never do)."""
        try:
            return self._read_outputs_agreed()
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
        on = [name for name, v in want.items() if v]
        if on:  # written ahead: a host that dies during or right after the write leaves this for the next one
            self._owner.note(f"the valve was energised ({', '.join(on)} on)")
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
        except WriteEchoMismatch as exc:
            if note:
                self._note_failure(exc)
            self.valve_outputs = None
            raise self._stray_write(exc) from exc
        except CellError as exc:
            if note:
                self._note_failure(exc)
            self.valve_outputs = None
            raise
        self._commanded = dict(want)
        self.valve_outputs = dict(want)
        if not on:  # every output off, as read back by the write: nothing is left to notice
            self._owner.note(None)

    def _stray_write(self, exc: WriteEchoMismatch) -> CellError:
        """The error for a write whose echo names another coil switched on: with ``stray_coils:
        switch-off`` that coil is switched off again (and read back) first; either way the error says
        which coil and what became of it."""
        address, value = exc.echoed
        own = {p.address for p in self.io_map.valves.values() if p.kind == "coil"}
        if exc.table != "coil" or value is not True or not isinstance(address, int) or address in own:
            return exc
        if self.io_map.stray_coils != "switch-off":
            return WriteEchoMismatch(
                f"{exc}; coil {address}, which this gripper does not own, may have been switched on by the corrupted "
                "request: check it (io map stray_coils: report)", exc.table, exc.sent, exc.echoed)
        try:
            self.link.write_coil(address, False)
            (now,) = self.link.read("coil", address, 1)
            (again,) = self.link.read("coil", address, 1)
            done = "switched off again and read back off" if not (now or again) else "still reads ON after switching it off"
        except CellError as exc2:
            done = f"NOT switched off ({type(exc2).__name__}: {exc2})"
        log.error("%s: a corrupted write switched on coil %d: %s", self.url, address, done)
        return WriteEchoMismatch(f"{exc}; coil {address}, not this gripper's, was switched on by the corrupted request: {done}",
                                 exc.table, exc.sent, exc.echoed)

    def _move(self, target: str) -> str:
        what = f"{'open' if target == 'open' else 'close'}_jaws"
        self._require_link(what)
        try:
            return self._move_confirmed(target)
        except CellError as exc:
            raise self._failed(exc, what) from exc

    def _move_confirmed(self, target: str) -> str:
        """Switch the valve to ``target`` and wait (``timeout_s``) until the switches confirm it.

        Confirmed by two consecutive readings of the target (its switch on, the other off): one reply with
        a flipped bit cannot confirm it; a reading with both on is read once more before it is believed.
        At the deadline, the other switch still on is a ``DeviceTimeout`` (the jaws never left: no air, a
        valve that did not switch, a stuck jaw); neither on a ``GripperFault`` (stuck between, or the
        target's switch broken); both on at any time a ``GripperFault`` too. Then the valve outputs are
        read back until two readings agree: a stroke the switches confirm while the terminal has reset its
        outputs (its watchdog tripped during a stalled exchange) is a ``GripperFault``, never a success.
        """
        want = self.io_map.drive(target)
        self._write_outputs(want)
        other = "closed" if target == "open" else "open"
        deadline = self.clock() + self.timeout_s
        seen_target = False
        while True:
            self._check_undisturbed(target)
            r = self._read_raw()
            if r.open_sensor and r.closed_sensor:
                r = self._read_raw()  # one flipped bit is not a broken switch: read once more
            state = r.state  # raises GripperFault when both switches are still on
            if state == target:
                if seen_target:  # two consecutive readings agree: a single corrupted reply cannot confirm
                    with self.link._locked("confirm the stroke"):
                        self._confirm_outputs(want, target)
                        self._check_undisturbed(target)
                    return state
                seen_target = True
                continue
            seen_target = False
            now = self.clock()
            if now >= deadline:
                break
            time.sleep(min(self.confirm_poll_s, deadline - now))  # interrupt() is seen at the next check
        if state == "between":
            raise GripperFault(
                f"{self.url}: jaws left '{other}' but the '{target}' reed switch did not come on within "
                f"{self.timeout_s} s: jaws stuck between, or that switch is broken"
            )
        raise DeviceTimeout(
            f"{self.url}: jaws still '{other}' {self.timeout_s} s after the valve was switched to '{target}': "
            "no air, valve not switching, or jaws stuck"
        )

    def _confirm_outputs(self, want: dict[str, bool], target: str) -> None:
        """The end of a stroke: the valve must still hold the commanded outputs. A terminal resets its
        outputs when its watchdog trips (the master silent through a stalled or dropped link) or when it
        restarts; the jaws of a double solenoid valve then stay where they are, so the reed switches alone
        would confirm a stroke the valve no longer holds (and a spring-return valve is about to undo)."""
        got = self._read_outputs_agreed()
        if got != want:
            raise GripperFault(
                f"{self.url}: jaws reached '{target}' but the valve outputs read back as {got}, not the commanded "
                f"{want}: the terminal reset them during the stroke (its watchdog, or a restart)"
            )

    def interrupt(self) -> None:
        """End a jaw wait in progress (in another thread) at once: it raises ``GripperFault`` and the driver
        gives up (the valve in its safe state); later jaw commands wait normally once ``connect()`` is called
        again. Safe to call from any thread, and from a signal's handler (it only sets a flag)."""
        self._interrupted.set()

    def _check_undisturbed(self, target: str) -> None:
        """Nothing else happened to the link during the stroke: the poller did not give up (it would make
        the valve safe right after this call returned), the link was not silently re-established (what
        the terminal did meanwhile is unknown), and the wait was not interrupted (``interrupt()``)."""
        if self._interrupted.is_set():
            raise GripperFault(f"{self.url}: '{target}' not confirmed: the wait was interrupted")
        if self._halted is not None:
            raise ConnectionLost(f"{self.url}: '{target}' not confirmed: the driver gave up during the stroke ({self._halted})")
        if self._lost is not None:
            raise ConnectionLost(f"{self.url}: '{target}' not confirmed: the link was lost during the stroke ({self._lost})")

    def open_jaws(self) -> str:
        """Open the jaws and wait for the open switch (``timeout_s``). Returns 'open'. On any failure
        the driver gives up (``_give_up``) and the error says what it confirmed."""
        return self._move("open")

    def close_jaws(self) -> str:
        """Close the jaws and wait for the closed switch (``timeout_s``). Returns 'closed'. On any
        failure the driver gives up (``_give_up``) and the error says what it confirmed."""
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
        gives up and the error (GripperFault, or the link's) carries the report.

        Safe by default (``all-off``) is every solenoid de-energised: a single solenoid valve (spring
        return) then moves the jaws to its spring position, a double solenoid (bistable) valve holds them
        where they are, so a held part stays held and an open gripper stays open. ``open`` / ``closed``
        energise one solenoid instead; the terminal's watchdog (if it has one) de-energises everything
        when the master goes silent, which the driver makes happen by going silent after giving up.
        """
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
            try:
                self._read_raw(reconnect=False)
            except CellError as exc:
                if not isinstance(exc, (GripperFault, ModbusExceptionReply)):
                    # the link failed: the driver gives up before it lets go of the link, so that a jaw
                    # command waiting for it cannot reconnect and report a stroke the safe state undoes
                    self._last = None
                    self._lost = f"{type(exc).__name__}: {exc}"
                    self._halted = f"the poller lost the link: {type(exc).__name__}: {exc}"
                raise

    def _poll_step(self) -> None:
        """One poll, and what follows a failure (the poller's loop body)."""
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

    def _poll_loop(self) -> None:
        while not self._stop.wait(self.poll_s):
            self._poll_step()
