"""The PUMA 260 over VAL-II's terminal port: typed commands, checked replies, limits before sending.

A command runs only after its echo matched in full; a reply is trusted only when its bytes, the
kinematics of what ``WHERE`` prints and the arm's arrival agree; every target is checked against the
limits before it is sent; ``ABORT`` goes out first when anything in a motion's wait fails. Poses are the
tool point T in the robot base frame B, ``base_H_T``; mm and degrees.
"""

from __future__ import annotations

import os
import re
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from urllib.parse import urlsplit

import numpy as np
import serial

try:
    import termios
except ImportError:  # not a POSIX system: its ports have no terminal settings to make
    termios = None

from selfview.drivers.puma_val_serial.dialect import OAT_CONVENTIONS, ValDialect
from selfview.drivers.puma_val_serial.errors import ControllerError, MotionAborted, ProgramRunning
from selfview.drivers.puma_val_serial.kinematics import PumaKinematics
from selfview.drivers.puma_val_serial.limits import ValLimits
from selfview.drivers.robot_protocol import AbortResult, Where
from selfview.errors import CellError, ConfigError, DeviceError, DeviceTimeout, ProtocolError
from selfview.files.io_safe import parse_number
from selfview.drivers import signals
from selfview.drivers._ownership import DeviceLock
from selfview.maths.geometry import check_rigid, rotation_angle, trans

__all__ = ["PumaVAL", "Where", "AbortResult", "parse_serial_url"]

_PRINTABLE = set(range(0x20, 0x7F)) | {0x07, 0x09, 0x0A, 0x0D}  # BEL and TAB occur on real terminals
_BREAK_HINT = ("; a NUL byte is what a BREAK on the line reads as (the controller power-cycled, a cable was "
               "plugged in, or line noise)")


#: After a fault, how long the line must stay quiet after a prompt for the driver to take it as its own.
_RESYNC_QUIET_S = 0.2

#: How many times a location is read at most, looking for two replies in a row that agree.
LOCATION_READS = 4


def _noted(exc: BaseException, note: str) -> BaseException:
    """``exc`` with ``note`` appended to its message (the driver's own error types), else ``exc``."""
    if type(exc) in (DeviceTimeout, ProtocolError, DeviceError, ProgramRunning):
        new = type(exc)(f"{exc}; {note}")
        new.__cause__ = exc
        return new
    return exc


@dataclass
class _Segment:
    lines: list[str]
    end: str  # "prompt" or "question"
    question: str


_SERIAL_FLAGS = ("xonxoff", "rtscts")


def parse_serial_url(url: str, baudrate: int = 9600) -> tuple[str, dict]:
    """``serial://PATH?baud=N&xonxoff=0|1&rtscts=0|1`` -> (PATH, serial settings); any other URL or path
    is pyserial's and comes back as it is, with ``baudrate`` and flow control off. Raises ConfigError
    naming the part that is wrong."""
    settings = {"baudrate": baudrate, "xonxoff": False, "rtscts": False}
    if not url.lower().startswith("serial:"):
        return url, settings
    rest = url[len("serial:"):]
    path, _, query = rest.partition("?")
    if not path.startswith("///"):
        raise ConfigError(f"robot URL {url!r}: expected serial:///dev/ttyX (three slashes, then the device path)")
    path = path[2:]
    for item in filter(None, query.split("&")):
        key, eq, value = item.partition("=")
        if key == "baud":
            try:
                settings["baudrate"] = parse_number(value, integer=True, lo=50, hi=4_000_000)
            except ValueError:
                raise ConfigError(f"robot URL {url!r}: baud={value!r}; expected a baud rate such as 9600") from None
        elif key in _SERIAL_FLAGS:
            if value not in ("0", "1"):
                raise ConfigError(f"robot URL {url!r}: {key}={value!r}; expected 0 or 1")
            settings[key] = value == "1"
        else:
            raise ConfigError(f"robot URL {url!r}: unknown parameter {key!r}; a serial URL takes baud, xonxoff, rtscts")
    return path, settings


def _break_reads_as_nul(ser) -> None:
    """On a terminal port, make a BREAK read as one NUL byte (BRKINT, IGNBRK and PARMRK off). With BRKINT
    the kernel would silently discard what the port had received and had queued to send (an ABORT too);
    with IGNBRK a break that cost characters would pass unseen. A NUL is never part of a VAL reply, so the
    reader refuses it. Ports that are not terminals (socket://, loop://) are left alone."""
    if termios is None:
        return
    try:
        fd = ser.fileno()
        attrs = termios.tcgetattr(fd) if os.isatty(fd) else None
    except (AttributeError, TypeError, ValueError, OSError, termios.error, serial.SerialException):
        return
    if attrs is None or not attrs[0] & (termios.BRKINT | termios.IGNBRK | termios.PARMRK):
        return
    attrs[0] &= ~(termios.BRKINT | termios.IGNBRK | termios.PARMRK)
    try:
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
    except termios.error as exc:
        raise DeviceError(f"robot port: cannot make a BREAK read as a NUL byte (BRKINT off): {exc}") from exc


def _garbage(command: str, buf) -> str:
    """What a reply with bytes that are not text is called (a NUL named as a BREAK)."""
    bad = [i for i, b in enumerate(buf) if b not in _PRINTABLE]
    return (f"garbage in the reply to {command!r}: {len(bad)} byte(s) that are not text, first at offset {bad[0]}: "
            f"{bytes(buf[max(0, bad[0] - 20) : bad[0] + 20])!r}" + (_BREAK_HINT if 0 in buf else ""))


def _numbers(target) -> np.ndarray | None:
    """``target`` as a float array, or None for a name or what is no array of numbers."""
    try:
        return None if isinstance(target, str) else np.asarray(target, dtype=float)
    except (TypeError, ValueError):
        return None


def _norm(s: str) -> str:
    return " ".join(s.split()).upper()


def _record_lock(port: str) -> DeviceLock | None:
    """The lock that records what this driver is in the middle of, keyed on the controller's port (a
    device path or socket://HOST:PORT); None for other URLs (a spy or loop, no record)."""
    if "://" not in port:
        return DeviceLock.for_path("robot", port)
    parts = urlsplit(port)
    if parts.scheme.lower() == "socket":
        try:
            host, p = parts.hostname, parts.port
        except ValueError:  # a port out of range: connect() names it
            return None
        if host and p:
            return DeviceLock.for_host("robot", host, p)
    return None


_OVERTIME_S = 1.0  # past a reply's deadline, bytes already waiting are read for at most this long before it is judged


class _Deadline:
    """A reply's deadline as every reader of the line keeps it: at the deadline the line is read once more
    before it is judged (the host may have been stopped right after a silent read, the reply arriving
    meanwhile), and on while bytes come, for at most ``_OVERTIME_S``: a line that never stops talking
    cannot hold a reader past that."""

    def __init__(self, deadline: float):
        self.deadline = deadline
        self._overtime_end: float | None = None

    def passed(self, chunk: bytes) -> bool:
        """Whether the reader must give up now, after a read that returned ``chunk``."""
        now = time.monotonic()
        if now < self.deadline:
            return False
        if self._overtime_end is None:
            self._overtime_end = now + _OVERTIME_S
            return False
        return not (chunk and now < self._overtime_end)


class PumaVAL:
    """Driver of a PUMA 260 on a VAL-II controller's terminal port.

    ``url_or_port``: a pyserial URL or device path, or an open serial-like object (read, write,
    in_waiting, timeout). ``timeout_s``: the wait for a non-motion reply; motions wait as long as
    ``limits`` estimates from distance and speed. ``kinematics``: the arm and its TOOL, to check WHERE.
    Constructing does no I/O.

    The link is whatever ``serial.serial_for_url`` opens (a real port, a pty path, ``socket://``,
    ``spy://`` for a traffic dump, ``loop://``); ``serial:///dev/ttyS0?baud=9600&xonxoff=1&rtscts=1``
    names a serial port with its baud rate and flow control (``parse_serial_url``); with ``xonxoff=1``
    the kernel's terminal driver acts on the controller's XON/XOFF bytes and they never reach the reply
    parser. The port is opened exclusively: a second program opening it is refused.

    Replies end with the prompt, a ``.`` at the start of a line followed by silence
    (``dialect.prompt_silence_s``), or with a question that the method expecting it answers; ``*`` at
    the start of a line is VAL's prompt while a program runs (``ProgramRunning``). Error lines ``*text*``
    raise the typed ``ControllerError`` of the dialect's table; garbage or a missing prompt raises
    ``ProtocolError`` and the driver resynchronises (CR, drain to prompt and silence) before its next
    command; silence raises ``DeviceTimeout``. A BREAK reads as one NUL byte: it is refused at once (a
    waiting motion is stopped), and one that arrived between commands is followed by a resynchronisation.

    Checks beyond the bytes: ``WHERE``'s pose must equal the forward kinematics of its joint angles up
    to the print rounding (``PumaKinematics.where_fit``; read again on a mismatch). A named target is read
    from the controller (``POINT``) before its limit check, never taken from a cache. ``SPEED`` is read
    back (``STATUS``) after it is set and before every motion. APPRO and DEPART distances must be >= 0.

    Threads: one command is in flight at a time (``_cmd_lock``); bytes go out under ``_write_lock``, so
    ``abort()`` from another thread can write ``ABORT`` while a motion waits; the waiting motion then
    reads the controller's answer and raises ``MotionAborted``.
    """

    def __init__(
        self,
        url_or_port,
        *,
        dialect: ValDialect | None = None,
        limits: ValLimits | None = None,
        kinematics: PumaKinematics | None = None,
        timeout_s: float = 2.0,
        baudrate: int = 9600,
    ):
        if isinstance(url_or_port, str):
            if not url_or_port.strip():
                raise ConfigError("robot URL: expected a device path or URL such as socket://127.0.0.1:5000, got ''")
        elif not all(hasattr(url_or_port, a) for a in ("read", "write", "in_waiting")):
            raise ConfigError(f"robot port: expected a URL, a path or a serial-like object, got {url_or_port!r}")
        if isinstance(timeout_s, bool) or not (isinstance(timeout_s, (int, float)) and np.isfinite(timeout_s) and timeout_s > 0):
            raise ConfigError(f"timeout_s: expected a positive number of seconds, got {timeout_s!r}")
        if isinstance(baudrate, bool) or not (isinstance(baudrate, int) and baudrate > 0):
            raise ConfigError(f"baudrate: expected a positive whole number, got {baudrate!r}")
        self.url = url_or_port if isinstance(url_or_port, str) else None
        self._given = None if isinstance(url_or_port, str) else url_or_port
        self.dialect = dialect or ValDialect()
        self.limits = limits or ValLimits()
        self.kinematics = kinematics or PumaKinematics()
        self.timeout_s = float(timeout_s)
        self._port_name, self._link = parse_serial_url(self.url, baudrate) if self.url else (None, {})
        self.baudrate = self._link.get("baudrate", baudrate)
        self._ser = None
        self._owner = _record_lock(self._port_name) if self.url else None  # what a dead holder was doing
        self._cmd_lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._need_resync = False
        self._motion_active = False
        self._abort_sent = threading.Event()
        self._motion_done = threading.Event()
        self._motion_done.set()
        self._motion_outcome: tuple[bool, str] = (True, "no motion")
        self._speed_pct: float | None = None
        self.last_rx_bytes = 0  # bytes received for the last command (benchmarks)

    #: a ``Robot`` (drivers/robot.py) that reports and reaches numeric poses
    knows_poses = True

    def pose_to_H(self, pose) -> np.ndarray:
        """(4, 4) ``base_H_T`` of a pose (x, y, z mm, o, a, t deg) in the dialect's O/A/T convention;
        ``ConfigError`` for anything but six finite numbers."""
        a = _numbers(pose)
        if a is None or a.shape != (6,) or not np.all(np.isfinite(a)):
            raise ConfigError(f"pose: expected 6 finite numbers (x, y, z mm, o, a, t deg), got {pose!r}")
        return self.dialect.pose_to_H(a)

    def __repr__(self) -> str:
        return f"PumaVAL({self.url or self._given!r}, {'open' if self._ser else 'closed'})"

    # --- link -----------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self._ser is not None

    def connect(self, *, sync: bool = True, clear_stale: bool = False) -> "PumaVAL":
        """Open the link and synchronise with the controller (CR, wait for the prompt). Idempotent.

        ``sync=False`` only opens the link (to ABORT a controller that may be busy). Raises
        ``DeviceError`` if the port cannot be opened, ``ConfigError`` for an unknown URL scheme,
        ``DeviceTimeout`` if no prompt comes within ``timeout_s``, ``StaleState`` if the previous program
        on this controller died during a motion (nothing is sent; ``clear_stale`` once the operator has
        checked the arm).
        """
        with self._locked("connect"):
            if self._ser is not None:
                return self
            if self._given is not None:
                ser = self._given
            else:
                try:
                    ser = serial.serial_for_url(
                        self._port_name,
                        **self._link,
                        timeout=self.dialect.prompt_silence_s,
                        write_timeout=self.timeout_s,
                        exclusive=True,
                    )
                except ValueError as exc:
                    raise ConfigError(f"robot URL {self.url!r}: {exc}") from exc
                except (serial.SerialException, OSError) as exc:
                    held = "lock" in str(exc).lower() or getattr(exc, "errno", None) in (11, 16)
                    raise DeviceError(f"robot URL {self.url!r}: cannot open ({exc})" + (
                        "; another program holds the port: stop it first (one program drives the arm)" if held else "")) from exc
            try:
                if self._owner is not None:
                    self._owner.acquire(clear_stale=clear_stale)
                ser.timeout = self.dialect.prompt_silence_s
                _break_reads_as_nul(ser)
                self._ser = ser
                signals.watch(self)  # a termination signal ABORTs the arm, whichever thread drives it
                if sync:
                    self._resync()
                else:
                    self._need_resync = True
            except BaseException:
                self._ser = None
                if self._given is None:
                    ser.close()
                if self._owner is not None:
                    self._owner.release()
                raise
        return self

    def close(self) -> None:
        """Close the link (a port given open is left open). Safe to call twice."""
        with self._write_lock:
            ser, self._ser = self._ser, None
        signals.unwatch(self)
        if self._owner is not None:
            self._owner.release()
        if ser is not None and self._given is None:
            try:
                ser.close()
            except (serial.SerialException, OSError):
                pass

    def __enter__(self) -> "PumaVAL":
        return self.connect()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- low level --------------------------------------------------------------------------------
    @contextmanager
    def _locked(self, what: str):
        """Hold the command lock (one command in flight); ``DeviceTimeout`` if it stays taken."""
        if not self._cmd_lock.acquire(timeout=self.timeout_s):
            raise DeviceTimeout(f"{what}: another command is still in flight after {self.timeout_s:g} s")
        try:
            yield
        finally:
            self._cmd_lock.release()

    def _port(self):
        if self._ser is None:
            raise DeviceError(f"robot link {self.url or self._given!r} is not open; call connect() first")
        return self._ser

    def _write_raw(self, data: bytes, what: str, *, motion: bool = False) -> None:
        """Write ``data`` in one call under the write lock; ``motion``: this write starts a motion."""
        with self._write_lock:
            ser = self._port()
            if motion:
                self._mark_motion(what)
            try:
                ser.write(data)
            except serial.SerialTimeoutException as exc:
                self._need_resync = True
                raise DeviceTimeout(f"writing {what!r}: the link took no data within {self.timeout_s:g} s") from exc
            except (serial.SerialException, OSError) as exc:
                self._need_resync = True
                raise DeviceError(f"writing {what!r}: {exc}") from exc

    def _mark_motion(self, what: str) -> None:
        """A motion may be running from now on (called under the write lock): its stop is owed."""
        if self._owner is not None:  # a program that dies now leaves this for the next one to see
            self._owner.note(f"a motion was running ({what})")
        self._abort_sent.clear()
        self._motion_done.clear()
        self._motion_outcome = (False, "the motion is running")
        self._motion_active = True

    def _read_echo(self, n: int, deadline: float) -> bytes:
        """The next ``n`` bytes (the echo of a typed line), and whatever else has arrived with them."""
        buf = bytearray()
        while len(buf) < n:
            chunk = self._read()
            buf += chunk
            if not chunk and time.monotonic() >= deadline:
                break
        if self._port().in_waiting:
            buf += self._read()
        return bytes(buf)

    def _send_line(self, text: str, deadline: float, *, motion: bool = False) -> None:
        """Type ``text`` and execute it: with echo, the line goes out without its line end, its echo is
        compared in full, and only a faithful echo is followed by the line end (else CTRL-U erases it,
        ``dialect.cancel_line``, and ``ProtocolError``). With a dialect without echo nothing can be
        verified before it runs."""
        d = self.dialect
        data = d.encode_line(text)
        body, eol = data[: len(data) - len(d.host_eol)], d.host_eol.encode("ascii")
        if body and d.echo:
            self._write_raw(body, text)
            echo = self._read_echo(len(body), deadline)
            if echo != body:  # the whole line, byte for byte: 'SPEED 02' is not 'SPEED 20'
                self._need_resync = True
                if b"\r" in echo or b"\n" in echo:
                    # noise made a line end inside the typed line: the controller executed what came before
                    # it. The default templates make every such prefix a syntax error ('DO APPRO p1, (5'),
                    # but a dialect's own templates may not ('DO APPRO p1, 5' of 'DO APPRO p1, 50'): never
                    # "nothing ran": a motion gets the stop written first, by the caller's fault path, as
                    # any motion whose end is in doubt.
                    if motion:
                        with self._write_lock:
                            self._mark_motion(text)
                    raise ProtocolError(f"the echo of {text!r} came back as {echo!r}: a line end reached the controller "
                                        "inside the line, so it may have run the part before it")
                try:
                    self._write_raw(d.cancel_line.encode("ascii"), "<cancel line>")
                except CellError:
                    pass
                raise ProtocolError(
                    f"the echo of {text!r} came back as {echo!r}: the line was erased before its line end; nothing ran"
                    + (_BREAK_HINT if 0 in echo else "")
                )
            self._write_raw(eol, text, motion=motion)
        else:
            self._write_raw(body + eol, text, motion=motion)

    def _read(self):
        ser = self._port()
        try:
            return ser.read(max(1, ser.in_waiting))
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            # TypeError/AttributeError: pyserial's posix port after a close() from another thread
            self._need_resync = True
            raise DeviceError(f"robot link failed while reading: {exc}") from exc

    def _terminator(self, buf: bytearray) -> str | None:
        """How ``buf`` ends: 'prompt' or 'program' (a prompt character alone at the start of a line),
        'question' (a line ending in '?'), or None."""
        cut = max(buf.rfind(b"\r"), buf.rfind(b"\n"))
        if cut < 0:
            return None  # a prompt counts only at the start of a line, after the command's own output
        tail = bytes(buf[cut + 1 :])
        if tail == self.dialect.prompt.encode():
            return "prompt"
        if tail == self.dialect.program_prompt.encode():
            return "program"
        if tail.rstrip().endswith(b"?"):
            return "question"
        return None

    def _read_segment(self, deadline: float, command: str, budget_s: float, *, strict: bool = True) -> _Segment:
        """Read until a prompt or a question followed by silence, or raise at ``deadline``. Bytes read at
        the deadline are judged first (after the silence that ends a reply): a reply that arrived complete
        while this host was stalled (suspended, swapped out) counts, and the stall is no device fault."""
        buf = bytearray()
        limit = _Deadline(deadline)
        while True:
            chunk = self._read()
            if chunk:
                buf += chunk
                self.last_rx_bytes += len(chunk)
                if strict and 0 in chunk:  # a BREAK: refused at once (a motion waiting for its prompt is stopped)
                    self._need_resync = True
                    raise ProtocolError(_garbage(command, buf))
            else:
                end = self._terminator(buf)
                if end == "program":
                    self._need_resync = True
                    raise ProgramRunning(
                        f"after {command!r} the controller prompts {self.dialect.program_prompt!r}: a VAL program is "
                        "running; stop it on the controller before commanding the arm from the terminal"
                    )
                if end is not None:
                    return self._split(buf, end, command, strict)
            if limit.passed(chunk):
                self._need_resync = True
                shown = bytes(buf[-80:])
                if not buf:
                    raise DeviceTimeout(f"no reply to {command!r} within {budget_s:.2f} s")
                cut = max(buf.rfind(b"\r"), buf.rfind(b"\n"))
                if buf[cut + 1 :].strip():
                    raise ProtocolError(f"reply to {command!r} ended in {shown!r} without the prompt")
                raise DeviceTimeout(f"no prompt after {command!r} within {budget_s:.2f} s (received ...{shown!r})")

    def _split(self, buf: bytearray, end: str, command: str, strict: bool) -> _Segment:
        if strict and any(b not in _PRINTABLE for b in buf):
            self._need_resync = True
            raise ProtocolError(_garbage(command, buf))
        text = buf.decode("ascii", errors="replace")
        parts = re.split(r"\r\n|\r|\n", text)
        lines = [p for p in parts[:-1] if p.strip()]
        return _Segment(lines=lines, end=end, question=parts[-1].strip() if end == "question" else "")

    def _drain(self) -> list[str]:
        """Read what the controller sent unasked (until silence); the lines of it."""
        ser = self._port()
        if not ser.in_waiting:
            return []
        buf = bytearray()
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            chunk = self._read()
            if not chunk:
                break
            buf += chunk
        else:
            self._need_resync = True
            raise ProtocolError(f"the controller kept talking for {self.timeout_s:g} s unasked: ...{bytes(buf[-60:])!r}")
        text = buf.decode("ascii", errors="replace")
        return [p for p in re.split(r"\r\n|\r|\n", text) if p.strip()]

    def _resync(self, quiet_s: float = 0.0) -> None:
        """Bring the dialogue back to an idle prompt: drain, send CR, read to a prompt and silence. With
        ``quiet_s`` (after a fault, when the rest of an earlier reply may still be on its way) a prompt
        counts only if nothing follows it for that long: else it was the earlier reply's, read on."""
        self._drain()
        deadline = time.monotonic() + self.timeout_s
        self._need_resync = True
        self._send_line("", deadline)
        for _ in range(4):  # a pending question (Y/N, Change?) takes the empty line as its answer
            seg = self._read_segment(deadline, "<resync: CR>", self.timeout_s, strict=False)
            if seg.end == "prompt":
                quiet_until = time.monotonic() + quiet_s
                while quiet_s and time.monotonic() < quiet_until and not self._port().in_waiting:
                    time.sleep(0.01)
                if not (quiet_s and self._port().in_waiting):
                    self._need_resync = False
                    return
                continue
            self._send_line("", deadline)
        raise ProtocolError("resynchronising: the controller kept asking questions or talking instead of prompting")

    def _prepare(self) -> None:
        """Before a command: resynchronise after a fault, or report what arrived unasked."""
        if self._need_resync:
            self._resync(_RESYNC_QUIET_S)
            return
        lines = self._drain()
        if any("\x00" in ln for ln in lines):  # a BREAK since the last reply: back to a known prompt first
            self._resync(_RESYNC_QUIET_S)
            return
        stray = self._classify(lines, None, set(), raise_errors=False)
        if stray[1]:
            raise self.dialect.error_for(stray[1][0], None)

    def _classify(self, lines, command, echoes, *, raise_errors=True):
        """(content lines, error texts) of a reply: echoes, prompts and blank lines dropped."""
        p = self.dialect.prompt
        if self._abort_sent.is_set():
            echoes = echoes | {_norm(self.dialect.command("abort"))}
        content, errors = [], []
        for ln in lines:
            s = ln.strip()
            body = s[1:].strip() if s.startswith(p) else s  # a prompt with the next echo on its line
            if not body or _norm(body) in echoes:
                continue
            et = self.dialect.error_text_of(body)
            if et is not None:
                errors.append(et)
            else:
                content.append(ln)
        if errors and raise_errors:
            raise self.dialect.error_for(errors[0], command)
        return content, errors

    def _exchange_locked(self, command: str, *, timeout_s: float | None = None, answers=(), motion=False) -> list[str]:
        budget = self.timeout_s if timeout_s is None else float(timeout_s)
        self._prepare()
        self.last_rx_bytes = 0
        echo_deadline = time.monotonic() + self.timeout_s
        echoes = {_norm(command)} if command else set()
        self._send_line(command, echo_deadline, motion=motion)
        deadline = time.monotonic() + budget
        shown = command or "<CR>"
        lines: list[str] = []
        for _ in range(16):
            seg = self._read_segment(deadline, shown, budget)
            lines += seg.lines
            if seg.end == "prompt":
                return self._checked(lambda: self._classify(lines, command, echoes)[0])
            answer = next((a for q, a in answers if self.dialect.is_question(seg.question, q)), None)
            if answer is None:
                self._need_resync = True
                raise ProtocolError(f"unexpected question {seg.question!r} after {shown!r}")
            if answer:
                echoes.add(_norm(answer))
            self._send_line(answer, time.monotonic() + self.timeout_s)
        self._need_resync = True
        raise ProtocolError(f"{shown!r}: the controller asked more than 16 questions")

    def _exchange(self, command: str, **kw) -> list[str]:
        with self._locked(command):
            return self._exchange_locked(command, **kw)

    def _checked(self, parse):
        """Run a reply parser; a ``ProtocolError`` also schedules a resynchronisation."""
        try:
            return parse()
        except ProtocolError:
            self._need_resync = True
            raise

    def _expect_nothing(self, content: list[str], command: str) -> None:
        if content:
            self._need_resync = True
            raise ProtocolError(f"unexpected reply to {command!r}: {content[:3]!r}")

    # --- stopping --------------------------------------------------------------------------------------
    def _write_abort(self) -> str | None:
        """Write CTRL-U and ABORT now, whatever state the dialogue is in; None, or why it could not."""
        d = self.dialect
        data = (d.cancel_line + d.command("abort") + d.host_eol).encode("ascii")
        with self._write_lock:
            self._abort_sent.set()
            ser = self._ser
            if ser is None:
                return "the link is closed"
            try:
                ser.write(data)
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                return f"writing ABORT failed: {exc}"
        return None

    def _confirm_abort(self, budget_s: float) -> tuple[bool, str]:
        """Read the controller's answer to ABORT (the command lock held): (confirmed, how)."""
        limit = _Deadline(time.monotonic() + budget_s)
        buf = bytearray()
        try:
            while True:
                chunk = self._read()
                buf += chunk
                if not chunk and self._terminator(buf) == "prompt":
                    text = buf.decode("ascii", errors="replace")
                    errors = [self.dialect.error_text_of(ln) for ln in re.split(r"\r\n|\r|\n", text)]
                    errors = [e for e in errors if e]
                    if any(isinstance(self.dialect.error_for(e), MotionAborted) for e in errors):
                        return True, "the controller answered *Motion aborted*"
                    return True, "the controller answered with its prompt" + (f" after *{errors[0]}*" if errors else "")
                if limit.passed(chunk):  # a line that keeps talking ends the wait too
                    return False, f"no prompt within {budget_s:g} s after ABORT (received {bytes(buf[-60:])!r})"
        except CellError as exc:
            return False, f"reading the answer to ABORT failed: {exc}"
        finally:
            self._need_resync = True

    def _stop_after_fault(self) -> AbortResult:
        """A motion's wait failed: ABORT first, unconditionally, then confirm (the command lock held)."""
        why = self._write_abort()
        if why is not None:
            return AbortResult(False, False, why)
        ok, how = self._confirm_abort(self.timeout_s)
        return AbortResult(True, ok, how)

    def abort_now(self) -> str | None:
        """Write ABORT at once and return (None, or why it could not be written): what a signal's handler
        does first; the motion's wait, wherever it runs, reads the controller's answer."""
        return self._write_abort()

    def wait_motion_end(self, timeout_s: float) -> bool:
        """Wait (at most ``timeout_s``) until no motion's wait is in progress; whether none is."""
        return self._motion_done.wait(timeout_s)

    def abort(self) -> AbortResult:
        """Stop the arm: write ``ABORT`` at once (after a CTRL-U that erases any half-typed line, never
        after a resynchronisation), then confirm it by reading the controller's answer.

        Works from any thread: a motion waiting in another thread reads the controller's answer (and
        raises ``MotionAborted``); otherwise this reads it. Never raises for a failed stop: the
        ``AbortResult`` says whether ABORT went out and whether the controller confirmed it.
        """
        why = self._write_abort()
        if why is not None:
            return AbortResult(False, False, why)
        with self._write_lock:
            in_motion = self._motion_active
        if in_motion:
            if not self._motion_done.wait(timeout=self.timeout_s * 2):
                return AbortResult(True, False, f"the motion's wait did not end within {self.timeout_s * 2:g} s")
            ok, how = self._motion_outcome
            return AbortResult(True, ok, how)
        if not self._cmd_lock.acquire(timeout=self.timeout_s):
            return AbortResult(True, False, f"another command held the line for {self.timeout_s:g} s")
        try:
            ok, how = self._confirm_abort(self.timeout_s)
        finally:
            self._cmd_lock.release()
        return AbortResult(True, ok, how)

    # --- WHERE and its cross-check -------------------------------------------------------------------
    def _where_fit(self, pose, joints, euler=None):
        """WHERE's pose against the kinematics of its joints (under ``euler``), at WHERE's print precision."""
        return self.kinematics.where_fit(pose, joints, euler or self.dialect.euler, self.dialect.decimals)

    def _where_locked(self, attempts: int = 3) -> Where:
        d = self.dialect
        cmd = d.command("where")
        last = None
        for _ in range(attempts):
            content = self._exchange_locked(cmd)
            pose, joints = self._checked(lambda: d.parse_where(content))
            fit = self._where_fit(pose, joints)
            if fit.consistent:
                return Where(pose=pose, joints=joints, base_H_T=d.pose_to_H(pose))
            last = (pose, joints, fit)
        pose, joints, fit = last
        for name, conv in OAT_CONVENTIONS.items():  # is it the O/A/T convention?
            if conv != d.euler and self._where_fit(pose, joints, conv).consistent:
                raise ConfigError(
                    f"WHERE: the controller's O/A/T {pose[3:]} fit the joint angles {joints} under the {name!r} "
                    f"convention, not the dialect's (off by {fit.deg:.2f} deg): set 'euler: {name}' in the dialect file"
                )
        self._need_resync = True
        raise ProtocolError(
            f"WHERE: the pose {pose} lies {fit.mm:.3f} mm / {fit.deg:.3f} deg from the kinematics of its own joint angles "
            f"{joints} in {attempts} readings, {fit.ratio:.1f} times what printing both to {d.decimals} decimals can "
            f"explain (up to {fit.bound_mm:.3f} mm / {fit.bound_deg:.3f} deg here): a corrupted reply, or a TOOL / O/A/T "
            "convention other than the driver's (kinematics.tool_mm, dialect.euler)"
        )

    # --- targets and limits ---------------------------------------------------------------------------
    def _as_H(self, target, what: str) -> np.ndarray:
        a = _numbers(target)
        if a is not None and a.shape == (4, 4):
            return check_rigid(a, what)
        if a is not None and a.shape == (6,) and np.all(np.isfinite(a)):
            return self.dialect.pose_to_H(a)
        raise ConfigError(f"{what}: expected a location name, 6 numbers (x, y, z, o, a, t) or a 4x4 transform, got {target!r}")

    def _resolve_locked(self, target, what: str) -> tuple[str, np.ndarray]:
        """(location name, base_H_T) of a target, read from the controller now (a stale copy never
        passes the limit check); a pose is first defined as the scratch location."""
        if isinstance(target, str):
            name = self.dialect.validate_name(target)
            return name, self.dialect.pose_to_H(self._location_locked(name))
        H = self._as_H(target, what)
        self.limits.check_position(H[:3, 3], what)
        name = self.dialect.scratch_location
        self._define_locked(name, H)
        return name, H

    def _speed_locked(self) -> float:
        """The monitor speed read from the controller now, before a motion. ``ProtocolError`` if it is not
        the speed this driver last set or read (another program changed it), ``LimitError`` above the
        limits' maximum; nothing is sent then."""
        got = self._read_speed_locked()
        known, self._speed_pct = self._speed_pct, got
        if known is not None and abs(got - known) > 0.5 * 10.0 ** -self.dialect.command_decimals:
            raise ProtocolError(f"the controller's SPEED is {got:g}, not the {known:g} this driver set or read: "
                                "another program changed it; nothing was moved (set the speed again)")
        self.limits.check_speed(got, "the controller's SPEED")
        return got

    def _read_speed_locked(self) -> float:
        cmd = self.dialect.command("status")
        content = self._exchange_locked(cmd)
        return self._checked(lambda: self.dialect.speed_of_status(content))

    def _motion_timeout(self, from_H: np.ndarray, to_H: np.ndarray, joints=None) -> float:
        """The wait for a motion from ``from_H`` to ``to_H``: straight (``joints`` None) or joint-interpolated
        from the joint angles ``joints`` (then timed by the joints that reach ``to_H``, when found): the
        expected duration at the speed read back (``ValLimits``) plus a margin of a few seconds."""
        speed = self._speed_locked()
        if joints is not None:
            goal_q = self.kinematics.joints_reaching(to_H, joints)
            if goal_q is not None:
                return self.limits.joint_timeout_s(goal_q - np.asarray(joints, float), speed)
        dist = float(np.linalg.norm(to_H[:3, 3] - from_H[:3, 3]))
        ang = float(np.degrees(rotation_angle(from_H[:3, :3].T @ to_H[:3, :3])))
        return self.limits.cartesian_timeout_s(dist, ang, speed)

    def _arrived_at(self, goal_H: np.ndarray):
        lim = self.limits

        def check(w: Where) -> str | None:
            mm = float(np.linalg.norm(w.base_H_T[:3, 3] - goal_H[:3, 3]))
            deg = float(np.degrees(rotation_angle(w.base_H_T[:3, :3].T @ goal_H[:3, :3])))
            if mm > lim.arrival_tol_mm or deg > lim.arrival_tol_deg:
                return f"{mm:.2f} mm / {deg:.2f} deg from its target"
            return None

        return check

    def _arrived_at_joints(self, goal_q) -> Callable:
        tol = self.limits.arrival_tol_joint_deg

        def check(w: Where) -> str | None:
            err = np.abs(np.asarray(w.joints) - np.asarray(goal_q))
            if err.max() > tol:
                return f"JT{int(np.argmax(err)) + 1} {err.max():.2f} deg from its target"
            return None

        return check

    def _motion_locked(self, command: str, timeout_s: float, arrived) -> None:
        """Execute a motion and make sure it is over: its prompt, a prompt for an empty line (a busy
        controller gives none, so one noise ``.`` cannot end a motion), a WHERE at the target. On any
        failure of the wait (timeout, garbage, a failed check, an interrupt): ABORT, confirmed."""
        t_end = time.monotonic() + timeout_s
        try:
            self._expect_nothing(self._exchange_locked(command, timeout_s=timeout_s, motion=True), command)
            rest = max(t_end - time.monotonic(), 0.0) + self.timeout_s
            self._expect_nothing(self._exchange_locked("", timeout_s=rest), f"<CR after {command}>")
            miss = arrived(self._where_locked())
            if miss is not None:
                raise ProtocolError(f"{command!r}: the controller prompted, but WHERE puts the arm {miss}")
            self._motion_outcome = (True, "the motion had ended at its target")
        except MotionAborted:
            self._motion_outcome = (True, "the controller answered *Motion aborted*")
            raise
        except ControllerError as exc:  # the controller stopped (or refused) the motion itself
            self._motion_outcome = (True, f"the controller stopped the motion: *{exc.text}*")
            raise
        except BaseException as exc:
            with self._write_lock:
                started = self._motion_active
            if not started:  # the line was never executed (a corrupted echo, a failed write)
                self._motion_outcome = (True, "the motion never started")
                raise
            res = self._stop_after_fault()
            self._motion_outcome = (res.confirmed, res.detail)
            raise _noted(exc, str(res)) from exc.__cause__
        finally:
            with self._write_lock:
                self._motion_active = False
            if self._owner is not None:
                ended, how = self._motion_outcome
                self._owner.note(None if ended else f"a motion's stop was not confirmed ({command}: {how})")
            self._motion_done.set()

    # --- commands -----------------------------------------------------------------------------------------
    def calibrate(self) -> None:
        """``CAL``, answering its ``Are you sure (Y/N)?`` with yes; waits for the calibration to end.

        CAL turns every joint a little: refused (``LimitError``) if the tool point is outside the workspace."""
        cmd = self.dialect.command("calibrate")
        with self._locked(cmd):
            here = self._where_locked()
            self.limits.check_position(here.base_H_T[:3, 3], "CAL (from the current position)")
            content = self._exchange_locked(
                cmd, timeout_s=self.limits.calibrate_s + self.timeout_s, answers=[(self.dialect.confirm_question, self.dialect.yes)]
            )
            self._expect_nothing(content, cmd)

    def speed(self, pct: float) -> None:
        """``SPEED pct``: the monitor speed in percent, read back (``STATUS``); ``LimitError`` above
        ``limits.max_speed_pct`` (nothing sent), ``ProtocolError`` if the controller holds another speed."""
        pct = self.limits.check_speed(pct, "SPEED")
        cmd = self.dialect.command("speed", pct=pct)
        with self._locked(cmd):
            self._speed_pct = None
            self._expect_nothing(self._exchange_locked(cmd), cmd)
            got = self._read_speed_locked()
            self._speed_pct = got
            if abs(got - pct) > 0.5 * 10.0 ** -self.dialect.command_decimals:
                self._need_resync = True
                raise ProtocolError(f"{cmd!r}: the controller reads back SPEED {got:g}, not {pct:g}")

    def speed_now(self) -> float:
        """The monitor speed read from the controller (``STATUS``)."""
        with self._locked("STATUS"):
            self._speed_pct = self._read_speed_locked()
            return self._speed_pct

    def where(self) -> Where:
        """``WHERE``: the tool point's pose (x, y, z, o, a, t), ``base_H_T`` and the six joints, checked
        against the kinematics of those joints (read again on a mismatch; ``ProtocolError`` after three,
        ``ConfigError`` naming the O/A/T convention that would fit)."""
        with self._locked("WHERE"):
            return self._where_locked()

    def here(self, name: str) -> tuple[float, ...]:
        """``HERE name``: record the current pose as a location; returns it (x, y, z, o, a, t)."""
        cmd = self.dialect.command("here", name=name)
        with self._locked(cmd):
            content = self._exchange_locked(cmd, answers=[(self.dialect.change_question, "")])
            if content:
                return self._checked(lambda: self.dialect.parse_location(content))
            return self._location_locked(name)

    def _location_locked(self, name: str) -> tuple[float, ...]:
        """``POINT name`` until two replies in a row agree (at most ``LOCATION_READS``): a serial line has no
        checksum, and a location prints no joint angles to check it against, so one corrupted digit would
        otherwise pass every later check (the limit check included)."""
        cmd = self.dialect.command("point", name=name)
        last = None
        for _ in range(LOCATION_READS):
            content = self._exchange_locked(cmd, answers=[(self.dialect.change_question, "")])
            pose = self._checked(lambda: self.dialect.parse_location(content))
            if last is not None and pose == last:
                return pose
            last = pose
        raise ProtocolError(f"{cmd}: no two replies in a row agree in {LOCATION_READS} reads (line noise?); "
                            f"nothing was moved")

    def location(self, name: str) -> tuple[float, ...]:
        """``POINT name`` answered with an empty line: the stored pose (x, y, z, o, a, t), unchanged."""
        with self._locked("POINT"):
            return self._location_locked(name)

    def _define_locked(self, name: str, H) -> None:
        x, y, z, o, a, t = self.dialect.H_to_pose(H)
        cmd = self.dialect.command("define", name=name, x=x, y=y, z=z, o=o, a=a, t=t)
        self._expect_nothing(self._exchange_locked(cmd), cmd)

    def define(self, name: str, pose) -> None:
        """``DO SET name = (TRANS(...))`` from a pose (x, y, z, o, a, t) or a (4, 4) ``base_H_T``.

        ``LimitError`` if the point lies outside the workspace box (nothing sent).
        """
        self.dialect.validate_name(name)
        H = self._as_H(pose, f"location {name}")
        self.limits.check_position(H[:3, 3], f"location {name}")
        with self._locked("DO SET"):
            self._define_locked(name, H)

    def _to_target(self, kind: str, target, distance_mm: float | None = None) -> None:
        what = f"{kind.upper()} target"
        if distance_mm is not None:
            d = self._distance(distance_mm, kind)
        with self._locked(kind.upper()):
            name, H = self._resolve_locked(target, what)
            goal = H if distance_mm is None else H @ trans(0.0, 0.0, -d)
            label = f"{kind.upper()} {name}" + ("" if distance_mm is None else f", {d:g}")
            self.limits.check_position(goal[:3, 3], label)
            w = self._where_locked()
            joints = None if kind == "moves" else w.joints  # MOVE and APPRO interpolate the joints
            fields = {"name": name} if distance_mm is None else {"name": name, "d": d}
            self._motion_locked(self.dialect.command(kind, **fields), self._motion_timeout(w.base_H_T, goal, joints),
                                self._arrived_at(goal))

    def _distance(self, distance_mm, kind: str) -> float:
        try:
            d = float(distance_mm)
        except (TypeError, ValueError):
            raise ConfigError(f"{kind.upper()} distance: expected a number of mm, got {distance_mm!r}") from None
        if not np.isfinite(d):
            raise ConfigError(f"{kind.upper()} distance: expected a finite number of mm, got {distance_mm!r}")
        return self.limits.check_distance(d, kind.upper())

    def move(self, target) -> None:
        """``DO MOVE``: joint-interpolated motion to a location name, a pose or a (4, 4) transform."""
        self._to_target("move", target)

    def moves(self, target) -> None:
        """``DO MOVES``: straight-line motion to a location name, a pose or a (4, 4) transform."""
        self._to_target("moves", target)

    def appro(self, target, distance_mm: float) -> None:
        """``DO APPRO name, d``: to the location backed off ``distance_mm`` along its tool z."""
        self._to_target("appro", target, distance_mm)

    def depart(self, distance_mm: float) -> None:
        """``DO DEPART d``: back the tool off ``distance_mm`` along its own z (away from what it approached)."""
        d = self._distance(distance_mm, "depart")
        with self._locked("DEPART"):
            w = self._where_locked()
            goal = w.base_H_T @ trans(0.0, 0.0, -d)
            self.limits.check_position(goal[:3, 3], f"DEPART {d:g}")
            self._motion_locked(self.dialect.command("depart", d=d), self._motion_timeout(w.base_H_T, goal, w.joints),
                                self._arrived_at(goal))

    def drive(self, joint: int, delta_deg: float, speed_pct: float) -> None:
        """``DO DRIVE j, deg, speed``: turn one joint by ``delta_deg`` at ``speed_pct`` % of the monitor speed.

        ``LimitError`` if the joint would leave its limits, the tool the workspace, or the speed is too
        high (nothing sent).
        """
        if isinstance(joint, bool) or not isinstance(joint, (int, np.integer)) or not 1 <= joint <= 6:
            raise ConfigError(f"DRIVE joint: expected 1..6, got {joint!r}")
        try:
            delta = float(delta_deg)
        except (TypeError, ValueError):
            delta = float("nan")
        if not np.isfinite(delta):
            raise ConfigError(f"DRIVE angle: expected a finite number of degrees, got {delta_deg!r}")
        sp = self.limits.check_speed(speed_pct, "DRIVE")
        with self._locked("DRIVE"):
            now = np.asarray(self._where_locked().joints)
            what = f"DRIVE {joint}, {delta:g}"
            self.limits.check_joint(int(joint), now[joint - 1] + delta, what)
            goal = now.copy()
            goal[joint - 1] += delta
            self.limits.check_position(self.kinematics.tool(goal)[:3, 3], what)
            dq = goal - now
            timeout = self.limits.joint_timeout_s(dq, self._speed_locked(), drive_pct=sp)
            self._motion_locked(self.dialect.command("drive", joint=int(joint), deg=delta, speed=sp), timeout,
                                self._arrived_at_joints(goal))

    def ready_pose(self) -> np.ndarray:
        """base_H_T (4, 4) at VAL's READY position (the arm straight up), from the driver's kinematics."""
        return self.kinematics.tool(self.limits.ready_joints_deg)

    def ready(self) -> None:
        """``DO READY``: to VAL's READY position (arm straight up); ``LimitError`` if READY's tool point
        lies outside the workspace (nothing sent)."""
        goal = np.asarray(self.limits.ready_joints_deg, dtype=float)
        self.limits.check_position(self.ready_pose()[:3, 3], "READY")
        with self._locked("READY"):
            now = np.asarray(self._where_locked().joints)
            timeout = self.limits.joint_timeout_s(goal - now, self._speed_locked())
            self._motion_locked(self.dialect.command("ready"), timeout, self._arrived_at_joints(goal))
