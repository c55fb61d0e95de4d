"""A simulated Modbus valve terminal with a pneumatic gripper on it.

A Modbus server (MBAP framing, or RTU frames over TCP; ``mocks/modbus_server.py``) bound to 127.0.0.1 on a
free port, in its own thread and event loop, started and stopped by the test or the CLI. Its data store is the
terminal's process image, laid out by the same ``IoMap`` the driver uses.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable

import numpy as np
from selfview.drivers.pneumatic_gripper.iomap import IoMap, Point
from selfview.errors import ConfigError, DeviceError
from selfview.mocks.modbus_server import EXCEPTION_CODES, ILLEGAL_ADDRESS, ILLEGAL_FUNCTION, ModbusServer

__all__ = ["ValveTerminal"]


def _check_settings(framing, travel_s, travel_sd_s, watchdog_s, unit, initial, tick_s) -> None:
    """The valve terminal's settings, each checked (``ConfigError`` naming it)."""
    if framing not in ("mbap", "rtu"):
        raise ConfigError(f"valve terminal framing {framing!r}: expected 'mbap' or 'rtu'")
    for name, v in (("travel_s", travel_s), ("travel_sd_s", travel_sd_s)):
        if not (isinstance(v, (int, float)) and v >= 0):
            raise ConfigError(f"valve terminal {name}={v!r}: expected a number of seconds >= 0")
    if watchdog_s is not None and not watchdog_s > 0:
        raise ConfigError(f"valve terminal watchdog_s={watchdog_s!r}: expected seconds > 0 or None")
    if not 0 <= int(unit) <= 255:
        raise ConfigError(f"valve terminal unit={unit!r}: expected 0..255")
    if initial not in ("open", "closed"):
        raise ConfigError(f"valve terminal initial={initial!r}: expected 'open' or 'closed'")
    if not 0 < tick_s <= 0.1:
        raise ConfigError(f"valve terminal tick_s={tick_s!r}: expected 0 < tick_s <= 0.1")


def _tables(io_map) -> dict[str, list]:
    """The terminal's process image: every Modbus table, at least the usual size and reaching every
    address of ``io_map``'s valves and sensors."""
    points = list(io_map.valves.values()) + [io_map.open_sensor, io_map.closed_sensor]

    def size(kind, n):
        return max([n] + [p.address + 1 for p in points if p.kind == kind])

    return {
        "coil": [False] * size("coil", 64),
        "discrete_input": [False] * size("discrete_input", 64),
        "holding_register": [0] * size("holding_register", 16),
        "input_register": [0] * size("input_register", 16),
    }


class ValveTerminal:
    """Simulated valve terminal serving Modbus on 127.0.0.1.

    ``world``: a SimWorld whose jaw gap follows the model (gaps from ``cell.gripper.states['open'|
    'closed']``), or None. ``io_map``: the same map the driver is given. ``framing``: 'mbap' (Modbus
    TCP) or 'rtu' (RTU frames over TCP). ``port`` 0 picks a free port. ``watchdog_s`` None disables
    the watchdog. ``initial`` is the jaw position without a world ('open' or 'closed').

    After the valve switches, the jaws travel between closed (position 0) and open (position 1) in
    ``travel_s`` (per stroke, jittered by ``travel_sd_s`` from the seeded generator); the reed switches
    are on at the ends. A master silent for longer than ``watchdog_s`` finds every output (coils, holding
    registers) reset to 0, as a real terminal's fail-safe does. Faults on demand: a stuck jaw, a broken
    or shorted reed switch, exception replies, a silent device, dropped connections. Time is the
    monotonic clock; the model advances on every request and on a tick of ``tick_s``.
    """

    def __init__(
        self,
        world=None,
        *,
        io_map: IoMap | None = None,
        seed: int = 0,
        travel_s: float = 0.1,
        travel_sd_s: float = 0.0,
        watchdog_s: float | None = 1.0,
        unit: int = 1,
        framing: str = "mbap",
        port: int = 0,
        tick_s: float = 0.005,
        initial: str = "open",
        clock: Callable[[], float] = time.monotonic,
    ):
        self.io_map = io_map if io_map is not None else IoMap()
        _check_settings(framing, travel_s, travel_sd_s, watchdog_s, unit, initial, tick_s)
        self.world = world
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)
        self.travel_s = float(travel_s)
        self.travel_sd_s = float(travel_sd_s)
        self.watchdog_s = None if watchdog_s is None else float(watchdog_s)
        self.unit = int(unit)
        self.framing = framing
        self.tick_s = float(tick_s)
        self.clock = clock
        self._want_port = int(port)
        self.port: int | None = None

        self.gaps: tuple[float, float] | None = None  # (closed, open) jaw gap in mm
        if world is not None:
            states = world.cell.gripper.states
            if "open" not in states or "closed" not in states:
                raise ConfigError(
                    f"valve terminal: the cell's gripper.states {sorted(states)} need 'open' and 'closed'"
                )
            self.gaps = (states["closed"], states["open"])
            initial = "closed" if world.jaw_state == "closed" else "open"

        self._image: dict[str, list] = _tables(self.io_map)
        self._lock = threading.RLock()
        self.position = 1.0 if initial == "open" else 0.0
        self._stroke_travel_s = self._draw_travel()
        self._direction: str | None = None
        self._t_model = self.clock()
        self._last_activity = self._t_model
        # faults
        self.stuck = False
        self.sensor_faults: dict[str, bool | None] = {"open": None, "closed": None}
        self.exception_code: int | None = None
        self.silent = False
        self._silent_left: int | None = None
        self._drop_next = False
        # statistics
        self.requests = 0
        self.watchdog_trips = 0
        self.connections_total = 0
        self.strokes: list[tuple[str, float, float]] = []  # (target, switch time, arrival time)
        self._stroke_start: float | None = None
        self._sync_sensors()
        self._sync_world()

        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server: ModbusServer | None = None
        self._stopping: asyncio.Event | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None

    # --- lifecycle ----------------------------------------------------------------------------
    @property
    def url(self) -> str:
        """The URL to give the driver (after ``start()``)."""
        if self.port is None:
            raise DeviceError("valve terminal: not started")
        scheme = "modbus-tcp" if self.framing == "mbap" else "modbus-rtu+socket"
        return f"{scheme}://127.0.0.1:{self.port}?unit={self.unit}"

    def start(self, timeout_s: float = 5.0) -> "ValveTerminal":
        """Start serving; returns once the port is bound. Raises DeviceError if it cannot bind."""
        if self._thread is not None:
            return self
        self._ready.clear()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run, name="valve-terminal", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            self.stop()
            raise DeviceError(f"valve terminal: server did not start within {timeout_s} s")
        if self._start_error is not None:
            err, self._start_error = self._start_error, None
            self._thread.join(timeout_s)
            self._thread = None
            raise DeviceError(f"valve terminal: cannot serve on 127.0.0.1:{self._want_port}: {err}") from err
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop serving and close every connection (safe to call twice)."""
        t, loop = self._thread, self._loop
        if t is None:
            return
        if loop is not None and self._stopping is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._stopping.set)
            except RuntimeError:  # the loop already ended
                pass
        t.join(timeout_s)
        if t.is_alive():
            raise DeviceError(f"valve terminal: server thread did not stop within {timeout_s} s")
        self._thread = None
        self.port = None

    def __enter__(self) -> "ValveTerminal":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._loop.run_until_complete(self._main())
        except BaseException as exc:  # reported to start(); nothing else is listening
            self._start_error = self._start_error or exc
            self._ready.set()
        finally:
            pending = [t for t in asyncio.all_tasks(self._loop) if not t.done()]
            for task in pending:
                task.cancel()
            if pending:
                self._loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            self._loop.close()

    async def _main(self) -> None:
        self._stopping = asyncio.Event()
        self._server = ModbusServer(self, unit=self.unit, framing=self.framing, port=self._want_port,
                                    on_request=self._on_request, on_connect=self._on_connect)
        self.port = await self._server.start()
        self._ready.set()
        try:
            while not self._stopping.is_set():
                self.advance()
                try:
                    await asyncio.wait_for(self._stopping.wait(), self.tick_s)
                except asyncio.TimeoutError:
                    pass
        finally:
            await self._server.close()

    # --- the server's hooks (event loop thread) -----------------------------------------------
    def _on_connect(self) -> None:
        with self._lock:
            self.connections_total += 1

    def _on_request(self, unit: int, pdu: bytes) -> str:
        with self._lock:
            self.requests += 1
            self._last_activity = self.clock()
            if self.silent:
                if self._silent_left is not None:
                    self._silent_left -= 1
                    self.silent = self._silent_left > 0
                return "silent"  # consumed, never answered
            if self._drop_next:
                self._drop_next = False
                return "drop"
        return "answer"

    # --- the process image the server reads and writes (modbus_server.ProcessImage) -------------
    def read(self, table: str, address: int, count: int) -> list | int:
        """``count`` values of ``table`` from ``address``, or a Modbus exception code."""
        with self._lock:
            self.advance()
            if self.exception_code is not None:
                return self.exception_code
            data = self._image.get(table)
            if data is None:
                return ILLEGAL_FUNCTION
            if address < 0 or count < 1 or address + count > len(data):
                return ILLEGAL_ADDRESS
            return list(data[address : address + count])

    def write(self, table: str, address: int, values) -> int | None:
        """Write ``values`` to ``table`` from ``address``: None, or a Modbus exception code."""
        with self._lock:
            self.advance()
            if self.exception_code is not None:
                return self.exception_code
            if table not in ("coil", "holding_register"):
                return ILLEGAL_FUNCTION
            data = self._image[table]
            values = list(values)
            if address < 0 or address + len(values) > len(data):
                return ILLEGAL_ADDRESS
            for i, v in enumerate(values):
                data[address + i] = bool(v) if table == "coil" else int(v) & 0xFFFF
            self._update_direction(self._t_model)
            self._sync_sensors()
            return None

    # --- the model ----------------------------------------------------------------------------
    def _draw_travel(self) -> float:
        if self.travel_sd_s == 0:
            return self.travel_s
        return max(0.0, float(self.rng.normal(self.travel_s, self.travel_sd_s)))

    def _bit(self, p: Point) -> bool:
        v = self._image[p.kind][p.address]
        return bool(v) if p.bit is None else bool((v >> p.bit) & 1)

    def _put(self, p: Point, on: bool) -> None:
        data = self._image[p.kind]
        if p.bit is None:
            data[p.address] = bool(on)
        else:
            data[p.address] = (data[p.address] | (1 << p.bit)) if on else (data[p.address] & ~(1 << p.bit))

    def _outputs(self) -> dict[str, bool]:
        return {k: self._bit(p) for k, p in self.io_map.valves.items()}

    def _update_direction(self, now: float) -> None:
        d = self.io_map.direction(self._outputs())
        if d != self._direction:
            self._direction = d
            if d is not None and self._target_position(d) != self.position:
                self._stroke_travel_s = self._draw_travel()
                self._stroke_start = now

    @staticmethod
    def _target_position(direction: str) -> float:
        return 1.0 if direction == "open" else 0.0

    def _move_until(self, now: float) -> None:
        """Move the jaws as the valve has driven them since the model's last update."""
        t_prev, self._t_model = self._t_model, max(self._t_model, now)
        d = self._direction
        if d is None or self.stuck:
            return
        target = self._target_position(d)
        remaining = abs(target - self.position)
        if remaining == 0:
            return
        travel = self._stroke_travel_s
        if travel == 0 or remaining * travel <= now - t_prev:
            self.position = target
            if self._stroke_start is not None:
                self.strokes.append((d, self._stroke_start, t_prev + remaining * travel))
                self._stroke_start = None
        else:
            step = (now - t_prev) / travel
            self.position += step if target > self.position else -step

    def advance(self) -> None:
        """Bring the model to now: jaw travel, watchdog, reed switches, the world's jaw gap."""
        with self._lock:
            now = self.clock()
            self._move_until(now)
            if (
                self.watchdog_s is not None
                and now - self._last_activity > self.watchdog_s
                and (any(self._image["coil"]) or any(self._image["holding_register"]))
            ):
                self._image["coil"][:] = [False] * len(self._image["coil"])
                self._image["holding_register"][:] = [0] * len(self._image["holding_register"])
                self.watchdog_trips += 1
            self._update_direction(now)
            self._sync_sensors()
            self._sync_world()

    def _sync_sensors(self) -> None:
        reads = {"open": self.position >= 1.0, "closed": self.position <= 0.0}
        for name, p in (("open", self.io_map.open_sensor), ("closed", self.io_map.closed_sensor)):
            fault = self.sensor_faults[name]
            self._put(p, reads[name] if fault is None else fault)

    def _sync_world(self) -> None:
        if self.world is None:
            return
        closed, opened = self.gaps
        gap = closed + self.position * (opened - closed)
        state = "open" if self.position >= 1.0 else "closed" if self.position <= 0.0 else None
        if gap != self.world.jaw_gap_mm or (state is not None and state != self.world.jaw_state):
            self.world.set_jaw(gap, state)

    # --- what a test reads --------------------------------------------------------------------
    @property
    def gap_mm(self) -> float | None:
        with self._lock:
            self.advance()
            return None if self.gaps is None else self.gaps[0] + self.position * (self.gaps[1] - self.gaps[0])

    @property
    def sensors(self) -> tuple[bool, bool]:
        """(open switch, closed switch) as a master would read them now."""
        with self._lock:
            self.advance()
            return self._bit(self.io_map.open_sensor), self._bit(self.io_map.closed_sensor)

    @property
    def valve_outputs(self) -> dict[str, bool]:
        with self._lock:
            self.advance()
            return self._outputs()

    def table(self, kind: str) -> list:
        """A copy of one table of the process image ('coil', 'discrete_input', ...)."""
        with self._lock:
            self.advance()
            return list(self._image[kind])

    @property
    def active_connections(self) -> int:
        return 0 if self._server is None else self._server.connections

    # --- faults on demand ---------------------------------------------------------------------
    def stick_jaw(self, stuck: bool = True) -> None:
        """Freeze the jaws where they are (True) or free them again."""
        with self._lock:
            self.advance()
            self.stuck = bool(stuck)

    def break_sensor(self, name: str, reads: bool | None = False) -> None:
        """Make reed switch 'open' or 'closed' read ``reads`` whatever the jaws do (False: a broken
        wire, True: a short); None repairs it."""
        if name not in self.sensor_faults:
            raise ConfigError(f"reed switch {name!r}: expected 'open' or 'closed'")
        with self._lock:
            self.sensor_faults[name] = None if reads is None else bool(reads)
            self.advance()

    def fail_requests(self, code: int | None = 4) -> None:
        """Answer every request with Modbus exception ``code`` (4: server device failure); None stops."""
        if code is not None and code not in EXCEPTION_CODES:
            raise ConfigError(f"Modbus exception code {code!r}: expected one of {list(EXCEPTION_CODES)}")
        with self._lock:
            self.exception_code = None if code is None else int(code)

    def set_silent(self, silent: bool = True, *, requests: int | None = None) -> None:
        """Take requests and never answer (a hung device, a broken transmit line); with ``requests``, only
        the next that many (a reply lost on a busy network), answering again after them."""
        with self._lock:
            self.silent = bool(silent)
            self._silent_left = requests if silent else None

    def drop_on_next_request(self) -> None:
        """Close every connection when the next request arrives, without answering it."""
        with self._lock:
            self._drop_next = True

    def drop_connections(self, timeout_s: float = 2.0) -> None:
        """Close every open connection now (the listener stays)."""
        loop = self._loop
        if loop is None or self._thread is None:
            return

        async def drop():
            if self._server is not None:
                self._server.drop_all()

        asyncio.run_coroutine_threadsafe(drop(), loop).result(timeout_s)
