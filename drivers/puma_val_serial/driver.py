"""The PUMA 260 over VAL-II's terminal port: typed commands, checked replies, limits before sending.

The link is whatever ``serial.serial_for_url`` opens (a real port, a pty path, ``socket://``,
``spy://`` for a traffic dump, ``loop://``) or an already open serial-like object. Each command is one
line ended by CR; the reply ends with the prompt, a ``.`` at the start of a line followed by silence
(``dialect.prompt_silence_s``), or with a question (a line ending in ``?`` followed by silence) that the
method expecting it answers. Error lines ``*text*`` raise the typed ``ControllerError`` of the dialect's
table; garbage or a missing prompt raises ``ProtocolError`` and the driver resynchronises (CR, drain
to prompt and silence) before its next command; silence raises ``DeviceTimeout``.

Threads: one command is in flight at a time (``_cmd_lock``). Every line goes out whole in one write
under ``_write_lock``, so ``abort()`` from another thread can send ``ABORT`` while a motion waits for
its prompt; the waiting motion then reads the controller's answer and raises ``MotionAborted``.
Frames: poses are the tool point T in the robot base frame B, ``base_H_T``; mm and degrees.
"""

from __future__ import annotations

import re
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import serial

from selfview.drivers.puma_val_serial.dialect import ValDialect
from selfview.drivers.puma_val_serial.limits import ValLimits
from selfview.errors import ConfigError, DeviceError, DeviceTimeout, ProtocolError
from selfview.geometry import check_rigid, rotation_angle, trans

__all__ = ["PumaVAL", "Where"]

_PRINTABLE = set(range(0x20, 0x7F)) | {0x07, 0x09, 0x0A, 0x0D}  # BEL and TAB occur on real terminals


@dataclass(frozen=True)
class Where:
    """The robot's pose as ``WHERE`` reports it: ``pose`` (x, y, z mm, o, a, t deg) of the tool point,
    ``joints`` JT1..JT6 (deg), ``base_H_T`` (4, 4) the tool point in the base frame."""

    pose: tuple[float, ...]
    joints: tuple[float, ...]
    base_H_T: np.ndarray

    def to_dict(self) -> dict:
        return {
            "pose": dict(zip(("x", "y", "z", "o", "a", "t"), self.pose)),
            "joints": list(self.joints),
            "base_H_T": np.round(self.base_H_T, 6).tolist(),
        }


@dataclass
class _Segment:
    lines: list[str]
    end: str  # "prompt" or "question"
    question: str


def _norm(s: str) -> str:
    return " ".join(s.split()).upper()


class PumaVAL:
    """Driver of a PUMA 260 on a VAL-II controller's terminal port.

    ``url_or_port``: a pyserial URL or device path, or an open serial-like object (read, write,
    in_waiting, timeout). ``timeout_s``: the wait for a non-motion reply; motions wait as long as
    ``limits`` estimates from distance and speed. Constructing does no I/O.
    """

    def __init__(
        self,
        url_or_port,
        *,
        dialect: ValDialect | None = None,
        limits: ValLimits | None = None,
        timeout_s: float = 2.0,
        baudrate: int = 9600,
    ):
        if isinstance(url_or_port, str):
            if not url_or_port.strip():
                raise ConfigError("robot URL: expected a device path or URL such as socket://127.0.0.1:5000, got ''")
        elif not all(hasattr(url_or_port, a) for a in ("read", "write", "in_waiting")):
            raise ConfigError(f"robot port: expected a URL, a path or a serial-like object, got {url_or_port!r}")
        if not (isinstance(timeout_s, (int, float)) and np.isfinite(timeout_s) and timeout_s > 0):
            raise ConfigError(f"timeout_s: expected a positive number of seconds, got {timeout_s!r}")
        if not (isinstance(baudrate, int) and baudrate > 0):
            raise ConfigError(f"baudrate: expected a positive whole number, got {baudrate!r}")
        self.url = url_or_port if isinstance(url_or_port, str) else None
        self._given = None if isinstance(url_or_port, str) else url_or_port
        self.dialect = dialect or ValDialect()
        self.limits = limits or ValLimits()
        self.timeout_s = float(timeout_s)
        self.baudrate = baudrate
        self._ser = None
        self._cmd_lock = threading.Lock()
        self._write_lock = threading.Lock()
        self._need_resync = False
        self._motion_active = False
        self._abort_sent = threading.Event()
        self._motion_done = threading.Event()
        self._motion_done.set()
        self._speed_pct: float | None = None
        self._locations: dict[str, np.ndarray] = {}
        self.last_rx_bytes = 0  # bytes received for the last command (benchmarks)

    def __repr__(self) -> str:
        return f"PumaVAL({self.url or self._given!r}, {'open' if self._ser else 'closed'})"

    # --- link -----------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self._ser is not None

    def connect(self) -> "PumaVAL":
        """Open the link and synchronise with the controller (CR, wait for the prompt). Idempotent.

        Raises ``DeviceError`` if the port cannot be opened, ``ConfigError`` for an unknown URL scheme,
        ``DeviceTimeout`` if no prompt comes within ``timeout_s``.
        """
        with self._locked("connect"):
            if self._ser is not None:
                return self
            if self._given is not None:
                ser = self._given
            else:
                try:
                    ser = serial.serial_for_url(
                        self.url,
                        baudrate=self.baudrate,
                        timeout=self.dialect.prompt_silence_s,
                        write_timeout=self.timeout_s,
                    )
                except ValueError as exc:
                    raise ConfigError(f"robot URL {self.url!r}: {exc}") from exc
                except (serial.SerialException, OSError) as exc:
                    raise DeviceError(f"robot URL {self.url!r}: cannot open ({exc})") from exc
            try:
                ser.timeout = self.dialect.prompt_silence_s
                self._ser = ser
                self._resync()
            except BaseException:
                self._ser = None
                if self._given is None:
                    ser.close()
                raise
        return self

    def close(self) -> None:
        """Close the link (a port given open is left open). Safe to call twice."""
        with self._write_lock:
            ser, self._ser = self._ser, None
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

    def _write_line(self, text: str, *, motion: bool = False) -> None:
        """Write one whole line in one call, under the write lock."""
        data = self.dialect.encode_line(text)
        with self._write_lock:
            ser = self._port()
            if motion:
                self._abort_sent.clear()
                self._motion_done.clear()
            try:
                ser.write(data)
            except serial.SerialTimeoutException as exc:
                self._need_resync = True
                raise DeviceTimeout(f"writing {text!r}: the link took no data within {self.timeout_s:g} s") from exc
            except (serial.SerialException, OSError) as exc:
                self._need_resync = True
                raise DeviceError(f"writing {text!r}: {exc}") from exc
            if motion:
                self._motion_active = True

    def _read(self):
        ser = self._port()
        try:
            return ser.read(max(1, ser.in_waiting))
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            # TypeError/AttributeError: pyserial's posix port after a close() from another thread
            self._need_resync = True
            raise DeviceError(f"robot link failed while reading: {exc}") from exc

    def _terminator(self, buf: bytearray) -> str | None:
        cut = max(buf.rfind(b"\r"), buf.rfind(b"\n"))
        tail = bytes(buf[cut + 1 :])
        if tail == self.dialect.prompt.encode():
            return "prompt"
        if tail.rstrip().endswith(b"?"):
            return "question"
        return None

    def _read_segment(self, deadline: float, command: str, budget_s: float, *, strict: bool = True) -> _Segment:
        """Read until a prompt or a question followed by silence, or raise at ``deadline``."""
        buf = bytearray()
        while True:
            chunk = self._read()
            if chunk:
                buf += chunk
                self.last_rx_bytes += len(chunk)
            else:
                end = self._terminator(buf)
                if end is not None:
                    return self._split(buf, end, command, strict)
            if time.monotonic() >= deadline:
                self._need_resync = True
                shown = bytes(buf[-80:])
                if not buf:
                    raise DeviceTimeout(f"no reply to {command!r} within {budget_s:.2f} s")
                cut = max(buf.rfind(b"\r"), buf.rfind(b"\n"))
                if buf[cut + 1 :].strip():
                    raise ProtocolError(f"reply to {command!r} ended in {shown!r} without the prompt")
                raise DeviceTimeout(f"no prompt after {command!r} within {budget_s:.2f} s (received ...{shown!r})")

    def _split(self, buf: bytearray, end: str, command: str, strict: bool) -> _Segment:
        bad = [i for i, b in enumerate(buf) if b not in _PRINTABLE]
        if bad and strict:
            self._need_resync = True
            raise ProtocolError(
                f"garbage in the reply to {command!r}: {len(bad)} byte(s) that are not text, "
                f"first at offset {bad[0]}: {bytes(buf[max(0, bad[0] - 20) : bad[0] + 20])!r}"
            )
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

    def _resync(self) -> None:
        """Bring the dialogue back to an idle prompt: drain, send CR, read to a prompt and silence."""
        self._drain()
        deadline = time.monotonic() + self.timeout_s
        self._need_resync = True
        self._write_line("")
        for _ in range(4):  # a pending question (Y/N, Change?) takes the empty line as its answer
            seg = self._read_segment(deadline, "<resync: CR>", self.timeout_s, strict=False)
            if seg.end == "prompt":
                self._need_resync = False
                return
            self._write_line("")
        raise ProtocolError("resynchronising: the controller kept asking questions instead of prompting")

    def _prepare(self) -> None:
        """Before a command: resynchronise after a fault, or report what arrived unasked."""
        if self._need_resync:
            self._resync()
            return
        stray = self._classify(self._drain(), None, set(), raise_errors=False)
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
        deadline = time.monotonic() + budget
        echoes = {_norm(command)}
        try:
            self._write_line(command, motion=motion)
            lines: list[str] = []
            for _ in range(16):
                seg = self._read_segment(deadline, command, budget)
                lines += seg.lines
                if seg.end == "prompt":
                    return self._checked(lambda: self._classify(lines, command, echoes)[0])
                answer = next((a for q, a in answers if self.dialect.is_question(seg.question, q)), None)
                if answer is None:
                    self._need_resync = True
                    raise ProtocolError(f"unexpected question {seg.question!r} after {command!r}")
                if answer:
                    echoes.add(_norm(answer))
                self._write_line(answer)
            self._need_resync = True
            raise ProtocolError(f"{command!r}: the controller asked more than 16 questions")
        finally:
            if motion:
                with self._write_lock:
                    self._motion_active = False
                self._motion_done.set()

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

    # --- parsing ------------------------------------------------------------------------------------
    def _parse_where(self, content: list[str]) -> Where:
        d = self.dialect
        if len(content) != 4:
            raise ProtocolError(f"WHERE: expected 4 lines (pose header, values, joint header, values), got {content!r}")
        d.parse_header(content[0], d.pose_header)
        pose = d.parse_values(content[1])
        d.parse_header(content[2], d.joint_header)
        joints = d.parse_values(content[3])
        return Where(pose=pose, joints=joints, base_H_T=d.pose_to_H(pose))

    def _parse_location(self, content: list[str], command: str) -> tuple[float, ...]:
        d = self.dialect
        if len(content) != 2:
            raise ProtocolError(f"{command!r}: expected a pose header and its values, got {content!r}")
        d.parse_header(content[0], d.pose_header)
        return d.parse_values(content[1])

    # --- targets and limits ---------------------------------------------------------------------------
    def _as_H(self, target, what: str) -> np.ndarray:
        try:
            a = None if isinstance(target, str) else np.asarray(target, dtype=float)
        except (TypeError, ValueError):
            a = None
        if a is not None and a.shape == (4, 4):
            return check_rigid(a, what)
        if a is not None and a.shape == (6,) and np.all(np.isfinite(a)):
            return self.dialect.pose_to_H(a)
        raise ConfigError(f"{what}: expected a location name, 6 numbers (x, y, z, o, a, t) or a 4x4 transform, got {target!r}")

    def _resolve(self, target, what: str) -> tuple[str, np.ndarray]:
        """(location name, base_H_T) of a target; a pose is first defined as the scratch location."""
        if isinstance(target, str):
            name = self.dialect.validate_name(target)
            H = self._locations.get(name.upper())
            if H is None:
                H = self.dialect.pose_to_H(self.location(name))
            return name, H
        H = self._as_H(target, what)
        self.limits.check_position(H[:3, 3], what)
        name = self.dialect.scratch_location
        self.define(name, H)
        return name, H

    def _motion_timeout(self, from_H: np.ndarray, to_H: np.ndarray) -> float:
        dist = float(np.linalg.norm(to_H[:3, 3] - from_H[:3, 3]))
        ang = float(np.degrees(rotation_angle(from_H[:3, :3].T @ to_H[:3, :3])))
        return self.limits.cartesian_timeout_s(dist, ang, self._speed_pct) + self.timeout_s

    def _motion(self, command: str, timeout_s: float) -> None:
        self._expect_nothing(self._exchange(command, timeout_s=timeout_s, motion=True), command)

    # --- commands -----------------------------------------------------------------------------------------
    def calibrate(self) -> None:
        """``CAL``, answering its ``Are you sure (Y/N)?`` with yes; waits for the calibration to end."""
        cmd = self.dialect.command("calibrate")
        content = self._exchange(
            cmd, timeout_s=self.limits.calibrate_s + self.timeout_s, answers=[(self.dialect.confirm_question, self.dialect.yes)]
        )
        self._expect_nothing(content, cmd)

    def speed(self, pct: float) -> None:
        """``SPEED pct``: the monitor speed in percent; ``LimitError`` above ``limits.max_speed_pct``."""
        pct = self.limits.check_speed(pct, "SPEED")
        cmd = self.dialect.command("speed", pct=pct)
        self._expect_nothing(self._exchange(cmd), cmd)
        self._speed_pct = pct

    def where(self) -> Where:
        """``WHERE``: the tool point's pose (x, y, z, o, a, t), ``base_H_T`` and the six joints."""
        content = self._exchange(self.dialect.command("where"))
        return self._checked(lambda: self._parse_where(content))

    def here(self, name: str) -> tuple[float, ...]:
        """``HERE name``: record the current pose as a location; returns it (x, y, z, o, a, t)."""
        cmd = self.dialect.command("here", name=name)
        content = self._exchange(cmd, answers=[(self.dialect.change_question, "")])
        if content:
            pose = self._checked(lambda: self._parse_location(content, cmd))
        else:
            pose = self.location(name)
        self._locations[name.upper()] = self.dialect.pose_to_H(pose)
        return pose

    def location(self, name: str) -> tuple[float, ...]:
        """``POINT name`` answered with an empty line: the stored pose (x, y, z, o, a, t), unchanged."""
        cmd = self.dialect.command("point", name=name)
        content = self._exchange(cmd, answers=[(self.dialect.change_question, "")])
        pose = self._checked(lambda: self._parse_location(content, cmd))
        self._locations[name.upper()] = self.dialect.pose_to_H(pose)
        return pose

    def define(self, name: str, pose) -> None:
        """``DO SET name = TRANS(...)`` from a pose (x, y, z, o, a, t) or a (4, 4) ``base_H_T``.

        ``LimitError`` if the point lies outside the workspace box (nothing sent).
        """
        self.dialect.validate_name(name)
        H = self._as_H(pose, f"location {name}")
        self.limits.check_position(H[:3, 3], f"location {name}")
        x, y, z, o, a, t = self.dialect.H_to_pose(H)
        cmd = self.dialect.command("define", name=name, x=x, y=y, z=z, o=o, a=a, t=t)
        self._expect_nothing(self._exchange(cmd), cmd)
        self._locations[name.upper()] = H

    def move(self, target) -> None:
        """``DO MOVE``: joint-interpolated motion to a location name, a pose or a (4, 4) transform."""
        name, H = self._resolve(target, "MOVE target")
        self.limits.check_position(H[:3, 3], f"MOVE {name}")
        here = self.where().base_H_T
        self._motion(self.dialect.command("move", name=name), self._motion_timeout(here, H))

    def moves(self, target) -> None:
        """``DO MOVES``: straight-line motion to a location name, a pose or a (4, 4) transform."""
        name, H = self._resolve(target, "MOVES target")
        self.limits.check_position(H[:3, 3], f"MOVES {name}")
        here = self.where().base_H_T
        self._motion(self.dialect.command("moves", name=name), self._motion_timeout(here, H))

    def appro(self, target, distance_mm: float) -> None:
        """``DO APPRO name, d``: to the location backed off ``distance_mm`` along its tool z."""
        d = float(distance_mm)
        if not np.isfinite(d):
            raise ConfigError(f"APPRO distance: expected a finite number of mm, got {distance_mm!r}")
        name, H = self._resolve(target, "APPRO target")
        goal = H @ trans(0.0, 0.0, -d)
        self.limits.check_position(goal[:3, 3], f"APPRO {name}, {d:g}")
        here = self.where().base_H_T
        self._motion(self.dialect.command("appro", name=name, d=d), self._motion_timeout(here, goal))

    def depart(self, distance_mm: float) -> None:
        """``DO DEPART d``: back the tool off ``distance_mm`` along its own z (away from what it approached)."""
        d = float(distance_mm)
        if not np.isfinite(d):
            raise ConfigError(f"DEPART distance: expected a finite number of mm, got {distance_mm!r}")
        here = self.where().base_H_T
        goal = here @ trans(0.0, 0.0, -d)
        self.limits.check_position(goal[:3, 3], f"DEPART {d:g}")
        self._motion(self.dialect.command("depart", d=d), self._motion_timeout(here, goal))

    def drive(self, joint: int, delta_deg: float, speed_pct: float) -> None:
        """``DO DRIVE j, deg, speed``: turn one joint by ``delta_deg`` at ``speed_pct`` % of the monitor speed.

        ``LimitError`` if the joint would leave its limits or the speed is too high (nothing sent).
        """
        if isinstance(joint, bool) or not isinstance(joint, (int, np.integer)) or not 1 <= joint <= 6:
            raise ConfigError(f"DRIVE joint: expected 1..6, got {joint!r}")
        delta = float(delta_deg)
        if not np.isfinite(delta):
            raise ConfigError(f"DRIVE angle: expected a finite number of degrees, got {delta_deg!r}")
        sp = self.limits.check_speed(speed_pct, "DRIVE")
        now = self.where().joints
        self.limits.check_joint(int(joint), now[joint - 1] + delta, f"DRIVE {joint}, {delta:g}")
        dq = np.zeros(6)
        dq[joint - 1] = delta
        timeout = self.limits.joint_timeout_s(dq, self._speed_pct, drive_pct=sp) + self.timeout_s
        self._motion(self.dialect.command("drive", joint=int(joint), deg=delta, speed=sp), timeout)

    def ready(self) -> None:
        """``DO READY``: to VAL's READY position (arm straight up)."""
        now = np.asarray(self.where().joints)
        timeout = self.limits.joint_timeout_s(np.asarray(self.limits.ready_joints_deg) - now, self._speed_pct) + self.timeout_s
        self._motion(self.dialect.command("ready"), timeout)

    def abort(self) -> None:
        """``ABORT``: stop a motion that another thread is waiting on, or send ABORT to an idle controller.

        Never waits for the command lock while a motion is in flight: the line goes out under the write
        lock, and the waiting motion raises ``MotionAborted``. ``DeviceTimeout`` if the motion does not
        end within ``timeout_s``.
        """
        cmd = self.dialect.command("abort")
        deadline = time.monotonic() + self.timeout_s
        while True:
            with self._write_lock:
                in_motion = self._motion_active
                if in_motion:
                    self._abort_sent.set()
                    try:
                        self._port().write(self.dialect.encode_line(cmd))
                    except (serial.SerialException, OSError) as exc:
                        raise DeviceError(f"writing {cmd!r}: {exc}") from exc
            if in_motion:
                if not self._motion_done.wait(timeout=max(0.0, deadline - time.monotonic())):
                    raise DeviceTimeout(f"ABORT: the motion did not end within {self.timeout_s:g} s")
                return
            if self._cmd_lock.acquire(timeout=0.01):
                try:
                    self._expect_nothing(self._exchange_locked(cmd), cmd)
                finally:
                    self._cmd_lock.release()
                return
            if time.monotonic() >= deadline:
                raise DeviceTimeout(f"ABORT: another command held the line for {self.timeout_s:g} s")
