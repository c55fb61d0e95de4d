"""A simulated VAL-II controller with a PUMA 260, serving its terminal dialogue on a pty or on TCP.

The dialogue follows the dialect's data (``selfview.drivers.puma_val_serial.dialect``), formatted by this
module's own code (never the driver's). Motions move the simulated world's TCP, so pressing the gripper
onto the plate parks it; faults come on demand (``ValController.inject``). The TCP server binds
127.0.0.1 only.
"""

from __future__ import annotations

import errno
import os
import select
import socket
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from selfview.drivers.puma_val_serial.dialect import ValDialect
from selfview.drivers.puma_val_serial.errors import ArmPowerOff
from selfview.mocks.puma260 import READY_DEG, ArmConfig, Puma260, Puma260Geometry, Unreachable, make_tool
from selfview.mocks.world import PLATE_BASE_POSE, SimWorld
from selfview.errors import ConfigError
from selfview.maths.geometry import R_from_rotvec, inv_H, make_H, rotation_angle, rotvec_from_R, trans

__all__ = ["ValController", "FAULTS", "trapezoid_time", "trapezoid_fraction", "TOOL_LENGTH_MM"]

#: Flange to TCP along the flange z (mm): force/torque sensor, gripper body and 60 mm fingers. With it
#: the taught locations above and on the plate (selfview.mocks.world.PLATE_BASE_POSE) are reachable.
TOOL_LENGTH_MM = 170.0
FAULTS = ("noise", "no_reply", "power_loss", "out_of_reach", "async_error", "stall")
_POLL_S = 0.02


# --- motion profile ---------------------------------------------------------------------------------
def trapezoid_time(dist: float, v_max: float, a_max: float) -> float:
    """Duration (s) of a rest-to-rest trapezoidal (or triangular) profile over ``dist``."""
    dist = abs(dist)
    if dist == 0:
        return 0.0
    if dist <= v_max * v_max / a_max:  # never reaches v_max
        return 2.0 * np.sqrt(dist / a_max)
    return dist / v_max + v_max / a_max


def trapezoid_fraction(t: float, dist: float, v_max: float, a_max: float) -> float:
    """Fraction (0..1) of ``dist`` covered after ``t`` seconds of that profile."""
    dist = abs(dist)
    T = trapezoid_time(dist, v_max, a_max)
    if dist == 0 or t >= T:
        return 1.0
    if t <= 0:
        return 0.0
    v = min(v_max, np.sqrt(dist * a_max))
    ta = v / a_max
    if t < ta:
        s = 0.5 * a_max * t * t
    elif t < T - ta:
        s = 0.5 * v * ta + v * (t - ta)
    else:
        s = dist - 0.5 * a_max * (T - t) ** 2
    return float(np.clip(s / dist, 0.0, 1.0))


# --- links --------------------------------------------------------------------------------------------
class _PtyLink:
    """The controller's side of a pseudo-terminal; a client opens ``path`` like a serial device."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR/LF translation: clients see exactly the bytes we send
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)

    def read(self, timeout: float) -> bytes | None:
        r, _, _ = select.select([self.master], [], [], timeout)
        if not r:
            return b""
        try:
            return os.read(self.master, 4096)
        except BlockingIOError:
            return b""
        except OSError as exc:  # EIO while no client holds the slave open
            if exc.errno != errno.EIO:
                raise
            time.sleep(timeout)
            return b""

    def write(self, data: bytes, deadline: float, stop: threading.Event | None = None) -> bool:
        view = memoryview(data)
        while view:
            if stop is not None and stop.is_set():
                return False
            try:
                n = os.write(self.master, view)
                view = view[n:]
            except BlockingIOError:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False  # nobody reads the terminal: drop the rest
                select.select([], [self.master], [], min(left, _POLL_S))
        return True

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class _TcpLink:
    """One accepted TCP connection."""

    def __init__(self, conn: socket.socket):
        self.conn = conn
        conn.setblocking(False)

    def read(self, timeout: float) -> bytes | None:
        r, _, _ = select.select([self.conn], [], [], timeout)
        if not r:
            return b""
        try:
            data = self.conn.recv(4096)
        except BlockingIOError:
            return b""
        except OSError:
            return None
        return data if data else None  # b"" from recv: the client closed

    def write(self, data: bytes, deadline: float, stop: threading.Event | None = None) -> bool:
        view = memoryview(data)
        while view:
            if stop is not None and stop.is_set():
                return False
            try:
                view = view[self.conn.send(view) :]
            except BlockingIOError:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                select.select([], [self.conn], [], min(left, _POLL_S))
            except OSError:
                return False
        return True

    def close(self) -> None:
        try:
            self.conn.close()
        except OSError:
            pass


class _Disconnected(Exception):
    pass


class _Input:
    """Bytes from the host split into lines: CR ends a line, LF is ignored, CTRL-U (``cancel``) erases
    the line typed so far. ``echoed`` counts the bytes of the first line already echoed; ``fresh``
    is set when an echoed line was erased (the terminal then starts a new line)."""

    def __init__(self, cancel: bytes = b"\x15"):
        self.buf = bytearray()
        self.cancel = cancel[0]
        self.echoed = 0
        self.fresh = False

    def feed(self, data: bytes) -> None:
        for b in data:
            if b == 0x0A:
                continue
            if b == self.cancel:
                cut = self.buf.rfind(b"\r") + 1
                if cut == 0 and self.echoed:
                    self.fresh = True
                    self.echoed = 0
                del self.buf[cut:]
            else:
                self.buf.append(b)

    def pending_echo(self) -> bytes:
        """The bytes of the first line typed since the last echo (not its CR)."""
        end = self.buf.find(b"\r")
        upto = len(self.buf) if end < 0 else end
        out = bytes(self.buf[self.echoed : upto])
        self.echoed = upto
        return out

    def pop(self) -> bytes | None:
        i = self.buf.find(b"\r")
        if i < 0:
            return None
        line = bytes(self.buf[:i])
        del self.buf[: i + 1]
        self.echoed = 0
        return line


@dataclass
class _Motion:
    """A planned motion: joint-interpolated (q0 -> q1) or straight (H0 -> H1), ``T`` seconds long."""

    T: float
    frac: Callable[[float], float]
    q0: np.ndarray
    q1: np.ndarray | None = None
    H0: np.ndarray | None = None
    H1: np.ndarray | None = None


class ValController:
    """The simulated controller. ``world`` (optional) is moved with the robot; ``seed`` fixes every fault;
    ``time_scale`` multiplies motion and calibration times (0: instant); ``pace_baud`` sends replies one
    byte at a time at that baud rate (8N1, 10 bits a byte); ``echo`` overrides the dialect's echo.

    The controller keeps arm power, calibration, SPEED, named locations (tool-point poses in the base
    frame B) and the joints; ``WHERE`` comes from the PUMA 260 forward kinematics
    (``selfview.mocks.puma260``) with a TOOL of ``tool_length_mm`` along the flange z, Cartesian targets
    go through inverse kinematics in the configuration 'front, above, noflip'. Motions take the time of
    a trapezoidal profile at SPEED % (times ``time_scale``), can be stopped by ``ABORT``, and move the
    world's TCP at every tick (``SimWorld.set_tcp``): pressing too far is a collision. A motion goes on
    to its target when the client leaves (on a pty and on TCP alike, as the real controller's does).
    Every loop is bounded: reads, writes and paced output check the stop event; threads are daemons
    joined by ``stop()`` before it closes the links.
    """

    accel_time_s = 0.25  # time to reach top speed (joint and Cartesian)
    cart_speed_mm_s = 500.0  # straight-line tool speed at SPEED 100
    cart_rot_deg_s = 180.0
    calibrate_s = 3.0
    question_timeout_s = 60.0  # an unanswered question is taken as 'no'
    tick_s = 0.01  # how often a motion updates the joints and the world (real seconds)
    contact_step = 0.01  # fraction of a motion between two contact checks against the world

    def __init__(
        self,
        world: SimWorld | None = None,
        *,
        seed: int = 0,
        time_scale: float = 1.0,
        pace_baud: int | None = None,
        echo: bool | None = None,
        dialect: ValDialect | None = None,
        geometry: Puma260Geometry | None = None,
        config: ArmConfig | None = None,
        tool_length_mm: float = TOOL_LENGTH_MM,
        speed_pct: float = 50.0,
        arm_power: bool = True,
        calibrated: bool = False,
        taught: dict | None = None,
    ):
        if not (np.isfinite(time_scale) and time_scale >= 0):
            raise ConfigError(f"time_scale: expected a number >= 0, got {time_scale!r}")
        if pace_baud is not None and not (isinstance(pace_baud, int) and pace_baud > 0):
            raise ConfigError(f"pace_baud: expected a positive whole number or None, got {pace_baud!r}")
        self.world = world
        self.dialect = dialect or ValDialect()
        self.echo = self.dialect.echo if echo is None else bool(echo)
        self.time_scale = float(time_scale)
        self.pace_baud = pace_baud
        self.kin = Puma260(geometry or Puma260Geometry(), config or ArmConfig())
        self.tool = make_tool(tool_length_mm)
        self.rng = np.random.default_rng(seed)
        self._state = threading.RLock()  # guards the robot state below
        self._exec = threading.Lock()  # one command executes at a time, whichever link it came from
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._links: list = []
        self._faults: dict[str, dict] = {}
        self.moving = threading.Event()
        self.received: list[str] = []  # every line the controller received, in order
        self.program_running = False  # a VAL program runs: the prompt is the dialect's program prompt
        self._stalled = False  # the 'stall' fault: output is dropped
        self.url: str | None = None
        self.arm_power = bool(arm_power)
        self.calibrated = bool(calibrated)
        self.speed_pct = float(speed_pct)
        self._joints = np.array(READY_DEG, dtype=float)
        self._locations: dict[str, np.ndarray] = {}
        if world is not None:
            with world.lock:
                try:
                    self._joints = self.kin.ik(world.base_H_G @ inv_H(self.tool))
                except Unreachable:
                    world.set_tcp(self.base_H_T)
        if taught is None:
            taught = {
                "above": PLATE_BASE_POSE @ trans(0.0, 0.0, -60.0),
                "plate": PLATE_BASE_POSE @ trans(0.0, 0.0, 4.0),  # 4 mm into the foam: parks the gripper
            }
        for name, pose in taught.items():
            H = np.asarray(pose, dtype=float)
            self._locations[self.dialect.validate_name(name).upper()] = H if H.shape == (4, 4) else self.dialect.pose_to_H(H)

    # --- state (thread-safe snapshots) ------------------------------------------------------------
    @property
    def joints(self) -> np.ndarray:
        with self._state:
            return self._joints.copy()

    @property
    def base_H_T(self) -> np.ndarray:
        """The tool point's pose in the base frame now, (4, 4)."""
        return self.kin.fk(self.joints) @ self.tool

    def locations(self) -> dict[str, np.ndarray]:
        with self._state:
            return {k: v.copy() for k, v in self._locations.items()}

    def power_on(self) -> None:
        """The operator presses ARM POWER."""
        with self._state:
            self.arm_power = True

    def inject(self, fault: str, **params) -> None:
        """Arm a fault for the next occasion.

        'noise' (count=3, mode='flip'|'drop'|'mixed'): corrupt the next reply; 'no_reply': swallow the
        next line; 'power_loss' (at=None: a seeded fraction 0.3..0.7): lose arm power during the next
        motion; 'out_of_reach': refuse the next motion target; 'async_error' (text=arm power off): print
        an error line unasked as soon as the controller is idle; 'stall' (after_s=0.0): from ``after_s``
        (simulated) into the next motion on, nothing reaches the host (the reply line is cut; the
        controller goes on reading and executing) until ``resume()``.
        """
        if fault not in FAULTS:
            raise ConfigError(f"fault {fault!r}: expected one of {', '.join(FAULTS)}")
        if fault == "noise":
            params.setdefault("count", 3)
            params.setdefault("mode", "flip")
            if params["mode"] not in ("flip", "drop", "mixed") or int(params["count"]) < 1:
                raise ConfigError(f"noise: expected count >= 1 and mode flip|drop|mixed, got {params}")
        if fault == "power_loss":
            at = params.get("at")
            params["at"] = float(self.rng.uniform(0.3, 0.7)) if at is None else float(at)
        with self._state:
            self._faults[fault] = params

    def resume(self) -> None:
        """End a 'stall': replies reach the host again."""
        with self._state:
            self._stalled = False

    def _take_fault(self, fault: str) -> dict | None:
        with self._state:
            return self._faults.pop(fault, None)

    # --- serving --------------------------------------------------------------------------------------
    def start_pty(self) -> str:
        """Serve on a new pseudo-terminal; returns the slave device path for the client to open."""
        link = _PtyLink()
        self._links.append(link)
        self.url = link.path
        self._spawn(self._serve, link, name="val-pty")
        return link.path

    def start_tcp(self, port: int = 0) -> int:
        """Serve on TCP 127.0.0.1:``port`` (0: any free port), one client at a time; returns the port."""
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            srv.bind(("127.0.0.1", int(port)))
        except OSError as exc:
            srv.close()
            raise ConfigError(f"port {port}: cannot listen on 127.0.0.1 ({exc.strerror})") from exc
        srv.listen(1)
        srv.settimeout(_POLL_S * 5)
        self._links.append(srv)
        p = srv.getsockname()[1]
        self.url = f"socket://127.0.0.1:{p}"
        self._spawn(self._accept_loop, srv, name="val-tcp")
        return p

    def _spawn(self, fn, arg, name):
        t = threading.Thread(target=fn, args=(arg,), name=name, daemon=True)
        self._threads.append(t)
        t.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop serving: end the loops (paced output included), join every thread, then close the links,
        so that nothing writes to a descriptor once it is closed (and perhaps reused). Safe to call twice;
        ``RuntimeError`` (the links left open) if a thread outlives ``timeout_s``."""
        self._stop.set()
        deadline = time.monotonic() + timeout_s
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
        alive = [t.name for t in self._threads if t.is_alive()]
        if alive:
            raise RuntimeError(f"simulated controller: thread(s) {', '.join(alive)} still running {timeout_s:g} s "
                               "after stop(); their links are left open")
        for link in self._links:
            link.close()
        self._links.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()

    def _accept_loop(self, srv: socket.socket) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = srv.accept()
            except (socket.timeout, BlockingIOError):
                continue
            except OSError:
                return
            link = _TcpLink(conn)
            try:
                self._serve(link)
            finally:
                link.close()

    def _serve(self, link) -> None:
        # Characters are echoed as they are typed (echo on), CR ends and executes a line (a stray LF is
        # ignored), CTRL-U erases the line typed so far. Type-ahead during a motion is read (ABORT stops
        # it) and echoed once the controller is idle again.
        inp = _Input(self.dialect.cancel_line.encode("ascii"))
        try:
            while not self._stop.is_set():
                self._echo_typed(link, inp)
                line = inp.pop()
                if line is None:
                    data = link.read(_POLL_S)
                    if data is None:
                        return
                    inp.feed(data)
                    if not data:
                        self._idle(link)
                    continue
                while not self._exec.acquire(timeout=_POLL_S):  # another link's command is running
                    if self._stop.is_set():
                        return
                try:
                    self._handle(link, inp, line)
                finally:
                    self._exec.release()
        except _Disconnected:
            return

    def _echo_typed(self, link, inp: _Input) -> None:
        """Echo what was typed since the last echo, as a terminal does (nothing with echo off)."""
        fresh, inp.fresh = inp.fresh, False
        typed = inp.pending_echo()
        if not self.echo:
            return
        out = (self._eol().encode("ascii") if fresh else b"") + typed
        if out:
            self._send_bytes(link, out)

    # --- output ---------------------------------------------------------------------------------------
    def _send(self, link, text: str) -> None:
        self._send_bytes(link, text.encode("ascii", errors="replace"))

    def _send_bytes(self, link, raw: bytes) -> None:
        if self._stalled:
            return
        data = bytearray(raw)
        noise = self._faults.get("noise")
        if noise is not None:
            data = self._corrupt(data, noise)
        deadline = time.monotonic() + 5.0 + (len(data) * 10.0 / self.pace_baud if self.pace_baud else 0.0)
        if not self.pace_baud:
            if not link.write(bytes(data), deadline, self._stop):
                raise _Disconnected()
            return
        byte_s = 10.0 / self.pace_baud
        t = time.monotonic()
        for b in data:  # one byte per character time, on an absolute schedule (no drift); stop() ends it
            t += byte_s
            delay = t - time.monotonic()
            if delay > 0 and self._stop.wait(delay):
                raise _Disconnected()
            if not link.write(bytes((b,)), deadline, self._stop):
                raise _Disconnected()

    def _corrupt(self, data: bytearray, noise: dict) -> bytearray:
        n = int(noise["count"])
        end = len(data) - (1 if data.endswith(self.dialect.prompt.encode()) else 0)
        idx = [i for i in range(end) if data[i] not in b"\r\n"]
        if len(idx) < n:
            return data  # too short to carry the noise: keep it armed for the next reply
        self._take_fault("noise")
        hit = sorted(self.rng.choice(idx, size=n, replace=False), reverse=True)
        for i in hit:
            mode = noise["mode"] if noise["mode"] != "mixed" else ("flip", "drop")[int(self.rng.integers(2))]
            if mode == "flip":
                data[i] ^= 0x80  # what a framing error on a noisy line looks like
            else:
                del data[i]
        return data

    def _eol(self) -> str:
        return self.dialect.controller_eol

    def _lines(self, *lines: str) -> str:
        return "".join(ln + self._eol() for ln in lines)

    def _prompt(self) -> str:
        with self._state:
            running = self.program_running
        return self.dialect.program_prompt if running else self.dialect.prompt

    def _error(self, cls: str, **values) -> str:
        return f"*{self.dialect.error_text(cls, **values)}*"

    def _ask(self, link, inp: _Input, text: str) -> str | None:
        """Print a question and wait for the answer line (None: no answer in time); echo it."""
        self._send(link, text + " ")
        deadline = time.monotonic() + self.question_timeout_s
        while not self._stop.is_set() and time.monotonic() < deadline:
            self._echo_typed(link, inp)
            raw = inp.pop()
            if raw is not None:
                line = raw.decode("ascii", errors="replace")
                self.received.append(line)
                self._send(link, self._eol())
                return line if raw.isascii() else "\ufffd"
            data = link.read(_POLL_S)
            if data is None:
                raise _Disconnected()
            inp.feed(data)
        self._send(link, self._eol())
        return None

    def _idle(self, link) -> None:
        f = self._take_fault("async_error")
        if f is not None:
            text = f.get("text") or self.dialect.error_text("ArmPowerOff")
            if isinstance(self.dialect.error_for(text), ArmPowerOff):
                with self._state:
                    self.arm_power = False
            self._send(link, self._eol() + f"*{text}*" + self._eol() + self._prompt())

    # --- commands -------------------------------------------------------------------------------------
    def _handle(self, link, inp: _Input, raw: bytes) -> None:
        # A line with a byte >= 0x80 or a control character is answered *Unrecognized command* and the
        # controller goes on. Replies are lines ending CR LF, the prompt is '.' at the start of a line
        # ('*' while program_running), errors are *text* lines from the dialect's table; CAL asks
        # "Are you sure (Y/N)?", POINT and HERE show the location and ask "Change?", STATUS prints the
        # monitor speed. A line is read as VAL-II reads its syntax (``ValDialect.parse_command``): a
        # number or a motion's location may stand in parentheses (``DO DEPART (50)``, ``DO MOVE (a)``) or
        # not; a parenthesis left open or an argument missing (a line cut short by a line end that noise
        # put inside it: ``DO DEPART (5``) is *Unrecognized command* and nothing runs.
        line = raw.decode("ascii", errors="replace")
        self.received.append(line)
        if self._take_fault("no_reply") is not None:
            return
        head = self._eol()  # the characters were echoed as they came; the line end now
        prompt = self._prompt()
        if not line.strip():
            self._send(link, self._eol() + prompt)
            return
        # a byte >= 0x80 or a control character: the controller cannot read the line, says so, goes on
        parsed = self.dialect.parse_command(line) if all(0x20 <= b < 0x7F for b in raw) else None
        if parsed is None:
            self._send(link, head + self._lines(self._error("CommandRejected")) + prompt)
            return
        kind, f = parsed
        handler = getattr(self, f"_cmd_{kind}")
        out = handler(link, inp, head, **f)
        if out is not None:
            self._send(link, out + self._prompt())

    # --- reply formatting (the simulator's own code, from the dialect's data) ------------------------------
    def _row(self, cells) -> str:
        """Cells right-aligned in the dialect's field width (or two blanks apart without one)."""
        w = self.dialect.field_width
        return "".join(c.rjust(w) for c in cells) if w else "  ".join(cells)

    def _num(self, v: float) -> str:
        txt = "%.*f" % (self.dialect.decimals, float(v))
        return txt[1:] if txt.startswith("-") and not any(ch in "123456789" for ch in txt) else txt

    def _values_row(self, header, columns, values) -> str:
        by = {c.upper(): v for c, v in zip(columns, values)}
        return self._row([self._num(by.get(h.upper(), 0.0)) for h in header])

    def _pose_lines(self, H) -> list[str]:
        d = self.dialect
        return [self._row(d.pose_header), self._values_row(d.pose_header, d.pose_columns, d.H_to_pose(H))]

    def _cmd_where(self, link, inp, head):
        d = self.dialect
        q = self.joints  # one reading: the pose is computed from the very joint angles printed beside it
        rows = {
            "pose_header": self._row(d.pose_header),
            "pose": self._values_row(d.pose_header, d.pose_columns, d.H_to_pose(self.kin.fk(q) @ self.tool)),
            "joint_header": self._row(d.joint_header),
            "joints": self._values_row(d.joint_header, d.joint_columns, q),
        }
        return head + self._lines(*(rows[k] for k in d.where_lines))

    def _cmd_status(self, link, inp, head):
        with self._state:
            speed, power, cal, running = self.speed_pct, self.arm_power, self.calibrated, self.program_running
        return head + self._lines(
            f"Program: {'running' if running else 'none'}",
            f"Monitor speed: {speed:g}",
            f"Arm power: {'on' if power else 'off'}",
            f"Calibrated: {'yes' if cal else 'no'}",
        )

    def _cmd_calibrate(self, link, inp, head):
        self._send(link, head)
        answer = self._ask(link, inp, self.dialect.confirm_question)
        if answer is not None and answer.strip().upper().startswith(self.dialect.yes.upper()):
            self._sleep(self.calibrate_s)
            with self._state:
                self.calibrated = True
        return ""

    def _cmd_speed(self, link, inp, head, pct):
        if not 0 < pct <= 100:
            return head + self._lines(self._error("InvalidArgument"))
        with self._state:
            self.speed_pct = float(pct)
        return head

    def _cmd_define(self, link, inp, head, name, x, y, z, o, a, t):
        with self._state:
            self._locations[name.upper()] = self.dialect.pose_to_H((x, y, z, o, a, t))
        return head

    def _cmd_here(self, link, inp, head, name):
        with self._state:
            self._locations[name.upper()] = self.base_H_T
        if not self.dialect.here_asks_change:
            return head
        return self._change_dialogue(link, inp, head, name)

    def _cmd_point(self, link, inp, head, name):
        if name.upper() not in self._locations:
            return head + self._lines(self._error("UndefinedLocation"))
        return self._change_dialogue(link, inp, head, name)

    def _change_dialogue(self, link, inp, head, name):
        """Show a location and ask ``Change?`` until an empty answer; values 'x,y,z,o,a,t' (blank: keep)."""
        first = head
        for _ in range(100):
            with self._state:
                H = self._locations[name.upper()]
            self._send(link, first + self._lines(*self._pose_lines(H)))
            first = ""
            answer = self._ask(link, inp, self.dialect.change_question)
            if answer is None or not answer.strip():
                break
            old = list(self.dialect.H_to_pose(H))
            parts = answer.split(",")
            try:
                new = [float(p) if p.strip() else v for p, v in zip(parts + [""] * 6, old)]
            except ValueError:
                self._send(link, self._lines(self._error("InvalidArgument")))
                continue
            with self._state:
                self._locations[name.upper()] = self.dialect.pose_to_H(new[:6])
        return ""

    def _cmd_abort(self, link, inp, head):
        return head  # nothing is moving

    def _location(self, name) -> np.ndarray | None:
        with self._state:
            H = self._locations.get(name.upper())
            return None if H is None else H.copy()

    def _cmd_move(self, link, inp, head, name):
        return self._motion_to(link, inp, head, self._location(name), straight=False)

    def _cmd_moves(self, link, inp, head, name):
        return self._motion_to(link, inp, head, self._location(name), straight=True)

    def _cmd_appro(self, link, inp, head, name, d):
        H = self._location(name)
        return self._motion_to(link, inp, head, None if H is None else H @ trans(0.0, 0.0, -d), straight=False)

    def _cmd_depart(self, link, inp, head, d):
        return self._motion_to(link, inp, head, self.base_H_T @ trans(0.0, 0.0, -d), straight=False)

    def _cmd_ready(self, link, inp, head):
        refusal = self._refuse()
        if refusal:
            return head + self._lines(refusal)
        return self._run(link, inp, head, self._joint_motion(np.array(READY_DEG)))

    def _cmd_drive(self, link, inp, head, joint, deg, speed):
        j = int(joint)
        if j != joint or not 1 <= j <= 6 or not 0 < speed <= 100:
            return head + self._lines(self._error("InvalidArgument"))
        refusal = self._refuse()
        if refusal:
            return head + self._lines(refusal)
        q1 = self.joints
        q1[j - 1] += deg
        if self.kin.within_limits(q1) is not None:
            return head + self._lines(self._error("JointLimit", joint=j))
        return self._run(link, inp, head, self._joint_motion(q1, speed_factor=speed / 100.0))

    def _refuse(self) -> str | None:
        """The error line that refuses any motion now (power, calibration, injected fault), or None."""
        with self._state:
            if not self.arm_power:
                return self._error("ArmPowerOff")
            if not self.calibrated:
                return self._error("NotCalibrated")
        if self._take_fault("out_of_reach") is not None:
            return self._error("OutOfReach")
        return None

    def _motion_to(self, link, inp, head, H, *, straight: bool):
        if H is None:
            return head + self._lines(self._error("UndefinedLocation"))
        refusal = self._refuse()
        if refusal:
            return head + self._lines(refusal)
        try:
            q1 = self.kin.ik(H @ inv_H(self.tool), self.joints)
        except Unreachable:
            return head + self._lines(self._error("OutOfReach"))
        if straight:
            return self._run(link, inp, head, self._straight_motion(H))
        return self._run(link, inp, head, self._joint_motion(q1))

    # --- motion -------------------------------------------------------------------------------------
    def _joint_motion(self, q1, speed_factor: float = 1.0) -> _Motion:
        q0 = self.joints
        dq = np.abs(np.asarray(q1) - q0)
        top = np.asarray(self.kin.geometry.joint_speed_deg_s)
        v = top * self.speed_pct / 100.0 * speed_factor
        a = top / self.accel_time_s
        times = [trapezoid_time(d, vj, aj) for d, vj, aj in zip(dq, v, a)]
        k = int(np.argmax(times))
        return _Motion(T=times[k], frac=lambda t: trapezoid_fraction(t, dq[k], v[k], a[k]), q0=q0, q1=np.asarray(q1, float))

    def _straight_motion(self, H1) -> _Motion:
        H0 = self.base_H_T
        s = self.speed_pct / 100.0
        dist = float(np.linalg.norm(H1[:3, 3] - H0[:3, 3]))
        ang = float(np.degrees(rotation_angle(H0[:3, :3].T @ H1[:3, :3])))
        lin = (dist, self.cart_speed_mm_s * s, self.cart_speed_mm_s / self.accel_time_s)
        rot = (ang, self.cart_rot_deg_s * s, self.cart_rot_deg_s / self.accel_time_s)
        prof = max(lin, rot, key=lambda p: trapezoid_time(*p))
        return _Motion(T=trapezoid_time(*prof), frac=lambda t: trapezoid_fraction(t, *prof), q0=self.joints, H0=H0, H1=H1)

    def _joints_at(self, m: _Motion, s: float, q_prev) -> np.ndarray:
        if m.q1 is not None:
            return m.q0 + s * (m.q1 - m.q0)
        R = m.H0[:3, :3] @ R_from_rotvec(s * rotvec_from_R(m.H0[:3, :3].T @ m.H1[:3, :3]))
        H = make_H(R, m.H0[:3, 3] + s * (m.H1[:3, 3] - m.H0[:3, 3]))
        return self.kin.ik(H @ inv_H(self.tool), q_prev)

    def _true_tool(self, q, noise: bool = True) -> np.ndarray:
        """Where the tool really is at the joint reading ``q`` (base frame): the controller's own model
        here; a subclass with kinematic errors answers differently (``noise``: encoder noise on the
        reading, off where a motion is checked for collisions)."""
        return self.kin.fk(q) @ self.tool

    def _set_joints(self, q) -> str:
        with self._state:
            self._joints = np.asarray(q, dtype=float).copy()
        if self.world is None:
            return "free"
        return self.world.set_tcp(self._true_tool(q))

    def _first_contact(self, m: _Motion, s0: float, s1: float, q_prev) -> tuple[float, np.ndarray] | None:
        """The first point in (s0, s1] where the tool collides, checked every ``contact_step`` of the
        motion (a tick of real time can span much of a fast-forwarded motion); None if nothing is hit."""
        if self.world is None or s1 <= s0:
            return None
        n = int(np.ceil((s1 - s0) / self.contact_step))
        q = q_prev
        for s in np.linspace(s0, s1, n + 1)[1:]:
            q = self._joints_at(m, s, q)
            if self.world.contact(self._true_tool(q, noise=False)) == "collision":
                return float(s), q
        return None

    def _sleep(self, sim_s: float) -> None:
        self._stop.wait(sim_s * self.time_scale)

    def _poll_abort(self, link, inp: _Input) -> bool:
        data = link.read(0.0)
        if data is None:
            raise _Disconnected()
        inp.feed(data)
        abort = " ".join(self.dialect.command("abort").split()).upper()
        kept, hit = bytearray(), False
        while True:
            line = inp.pop()
            if line is None:
                break
            text = line.decode("ascii", errors="replace")
            if not hit and " ".join(text.split()).upper() == abort:
                hit = True
                self.received.append(text)
            else:
                kept += line + b"\r"
        inp.buf[:0] = kept  # type-ahead stays queued (and unechoed) for after the motion
        inp.echoed = 0
        return hit

    def _run(self, link, inp: _Input, head: str, m: _Motion) -> str:
        """Execute a motion in (scaled) real time; the reply lines after the echo."""
        self._send(link, head)
        loss = self._take_fault("power_loss")
        stall = self._take_fault("stall")
        t0 = time.monotonic()
        status, q, s_done = "done", self.joints, 0.0
        lost = False  # the client went away: the arm goes on to its target, as a real controller's does
        self.moving.set()
        try:
            while True:
                t_sim = (time.monotonic() - t0) / self.time_scale if self.time_scale > 0 else m.T
                s = m.frac(min(t_sim, m.T))
                if stall is not None and t_sim >= float(stall.get("after_s", 0.0)):
                    with self._state:
                        self._stalled = True
                if loss is not None and s >= loss["at"]:
                    s, status = loss["at"], "power"
                try:
                    hit = self._first_contact(m, s_done, s, q)
                    q = hit[1] if hit else self._joints_at(m, s, q)
                except Unreachable:
                    status = "reach"
                    break
                s_done = s
                if self._set_joints(q) == "collision":
                    status = "collision"
                if status != "done" or t_sim >= m.T:
                    break
                try:
                    aborted = not lost and self._poll_abort(link, inp)
                except _Disconnected:
                    lost, aborted = True, False
                if aborted or self._stop.is_set():
                    status = "aborted"
                    break
                remaining = (m.T - t_sim) * self.time_scale
                time.sleep(min(self.tick_s, max(remaining, 0.0)))
        finally:
            self.moving.clear()
        if lost:
            raise _Disconnected()
        if status == "done":
            return ""
        if status == "aborted":
            echo = self.dialect.command("abort") if self.echo else None
            return self._lines(*([echo] if echo else []), self._error("MotionAborted"))
        if status in ("power", "collision"):
            with self._state:
                self.arm_power = False  # both stop the arm with its brakes on
            return self._lines(self._error("ArmPowerOff" if status == "power" else "Collision"))
        return self._lines(self._error("OutOfReach"))
