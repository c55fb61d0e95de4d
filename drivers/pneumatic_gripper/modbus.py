"""The Modbus master link: the one module of the project that imports pymodbus's client.

pymodbus renames arguments between minor releases (``unit`` > ``slave`` > ``device_id``) and changed
the coil bit order in 3.10; this adapter is written against 3.11 and tested on it and on the newest 3.x
(``.ci/constraints-*.txt``), and turns its results and exceptions into the project's (``ModbusLink``).
"""

from __future__ import annotations

import logging
import os
import socket
import struct
import threading
from collections.abc import Callable
from contextlib import contextmanager

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerType

from selfview.drivers.pneumatic_gripper.url import ModbusUrl, parse_modbus_url
from selfview.errors import ConfigError, DeviceError, DeviceTimeout, ProtocolError

__all__ = [
    "ModbusLink",
    "ModbusExceptionReply",
    "ConnectionFailed",
    "ConnectionLost",
    "WriteEchoMismatch",
    "EXCEPTION_NAMES",
]

# pymodbus logs every failure that it also raises, and with no logging configured Python prints those
# lines on stderr; the errors raised here say the same with the URL. Configured handlers still see them.
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

#: Request timeout and read retries by default: a terminal answers in milliseconds, but the PC asking may
#: be busy (image processing beside it) and a reply that comes late is not a faulty device.
DEFAULT_TIMEOUT_S = 1.0
DEFAULT_READ_RETRIES = 2
#: Longest request timeout accepted.
MAX_TIMEOUT_S = 600.0

#: Modbus exception codes (Modbus Application Protocol v1.1b3, section 7).
EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}


#: table -> (function code, name, pymodbus client method, reply field)
_READS = {
    "coil": (1, "coils", "read_coils", "bits"),
    "discrete_input": (2, "discrete inputs", "read_discrete_inputs", "bits"),
    "holding_register": (3, "holding registers", "read_holding_registers", "registers"),
    "input_register": (4, "input registers", "read_input_registers", "registers"),
}


#: The most values one read may ask for, per reply field (Modbus Application Protocol v1.1b3, 6.1-6.4).
_MAX_READ = {"bits": 2000, "registers": 125}


def _whole(what: str, name: str, v, lo: int, hi: int) -> int:
    """``v`` as an int in ``lo..hi``, else ``ConfigError`` naming the request and the value: checked
    before anything is sent (pymodbus would fail to encode it, which reads as a broken reply)."""
    if isinstance(v, bool) or not hasattr(v, "__index__") or not lo <= int(v) <= hi:
        raise ConfigError(f"Modbus {what}: {name} {v!r}: expected a whole number {lo}..{hi}; nothing was sent")
    return int(v)


class ModbusExceptionReply(DeviceError):
    """The device answered a request with a Modbus exception response."""

    def __init__(self, message: str, function: int, code: int):
        super().__init__(message)
        self.function = function
        self.code = code


class ConnectionFailed(DeviceError):
    """The transport could not be opened: connection refused, host unreachable, port missing or busy."""


class ConnectionLost(DeviceError):
    """The connection dropped; whatever the device did meanwhile is unknown."""


class WriteEchoMismatch(ProtocolError):
    """A write's reply echoes another address or value than the request's. Modbus TCP has no checksum of
    its own: either the request was corrupted on its way and the device executed what the echo says
    (``echoed``: (address, value)), or the reply was corrupted and the device executed ``sent``."""

    def __init__(self, message: str, table: str = "", sent: tuple = (), echoed: tuple = ()):
        super().__init__(message)
        self.table = table
        self.sent = sent
        self.echoed = echoed


class _NoReplyYet(Exception):
    """A read's reply did not come in time, and the read will be sent again (on the same connection)."""


#: bytes dropped before a request at most: far more than any late reply (an RTU frame is 256 bytes at
#: most); a line that keeps sending past it is left to the request, whose reply check refuses it
_DISCARD_MAX = 64 * 1024


def _discard_unasked(sock) -> None:
    """Drop the bytes waiting on an RTU-over-socket connection before a request (a reply that came too
    late for an earlier one): RTU frames carry no transaction id to tell them from the awaited reply. At
    most ``_DISCARD_MAX`` bytes: a peer that never stops sending cannot hold the request here."""
    if sock is None:
        return
    dropped = 0
    try:
        while dropped < _DISCARD_MAX:
            chunk = sock.recv(4096, socket.MSG_DONTWAIT)
            if not chunk:
                return
            dropped += len(chunk)
    except OSError:  # nothing more waiting (BlockingIOError), or a broken connection the request will report
        pass


class ModbusLink:
    """A Modbus master on one transport, safe to share between threads (one request at a time).

    Construction does no I/O; ``connect()`` opens the transport (done on demand by every request) and
    ``close()`` closes it, both safe to call twice. Addresses are 0-based wire addresses. ``on_connect``
    is called (inside the link's lock) after each successful (re)connection, before the request that
    caused it. ``trace(direction, frame)`` sees every frame sent ('>') and received ('<') as bytes.

    Errors: an exception reply from the device -> ``ModbusExceptionReply`` (with its code); a refused
    connection or a port that cannot open -> ``ConnectionFailed``; a connection that drops during a
    request -> ``ConnectionLost``; a device that stays silent -> ``DeviceTimeout``, after ``timeout_s``
    (a write) or ``timeout_s * (retries + 1)`` (a read); a garbled or mismatched reply ->
    ``ProtocolError``. After any of the last three the link closes its transport, so a late reply can
    never be taken for the answer to the next request; the next call connects again and calls
    ``on_connect``. On Modbus TCP a read whose reply is late is first sent again (``retries`` times, on
    the same connection: the MBAP transaction id tells a late reply from the awaited one), and so is an
    RTU read (serial or over a socket): RTU frames carry no transaction id, so whatever has arrived
    unasked is discarded before every RTU request is sent, and a late reply to an identical read is that
    read's answer. A write is never sent twice (it may have been carried out). The defaults fit a
    terminal answered by a busy PC: a reply within a second, two more tries.
    """

    def __init__(
        self,
        url: str | ModbusUrl,
        *,
        timeout_s: float = DEFAULT_TIMEOUT_S,
        retries: int = DEFAULT_READ_RETRIES,
        on_connect: Callable[[], None] | None = None,
        trace: Callable[[str, bytes], None] | None = None,
    ):
        self.url = url if isinstance(url, ModbusUrl) else parse_modbus_url(url)
        if isinstance(timeout_s, bool) or not isinstance(timeout_s, (int, float)) or not 0 < timeout_s <= MAX_TIMEOUT_S:
            raise ConfigError(f"Modbus request timeout_s={timeout_s!r}: expected a number of seconds > 0 and <= "
                              f"{MAX_TIMEOUT_S:g} (a device that stays silent longer is not answering)")
        if isinstance(retries, bool) or not isinstance(retries, int) or not 0 <= retries <= 5:
            raise ConfigError(f"Modbus retries={retries!r}: expected a whole number 0..5")
        self.timeout_s = float(timeout_s)
        self.retries = retries
        self.on_connect = on_connect
        self._trace = trace
        self._lock = threading.RLock()
        self._client: ModbusTcpClient | ModbusSerialClient | None = None
        self.connections = 0  # successful connections so far (reconnects show as > 1)

    # --- connection ---------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self._client is not None

    @property
    def lock_timeout_s(self) -> float:
        """How long a request waits for another thread's request (its worst case, plus a connect)."""
        return self.timeout_s * (self.retries + 3)

    def connect(self) -> None:
        """Open the transport if it is not open. Raises ConnectionFailed or DeviceTimeout."""
        with self._locked("connect"):
            self._ensure_connected()

    def close(self) -> None:
        """Close the transport (safe to call twice)."""
        with self._locked("close"):
            self._drop()

    def _packet_trace(self, sending: bool, data: bytes) -> bytes:
        if self._trace is not None:
            self._trace(">" if sending else "<", bytes(data))
        return data

    def _ensure_connected(self) -> None:
        if self._client is not None:
            return
        u = self.url
        trace = self._packet_trace if self._trace is not None else None
        if u.transport == "rtu":
            client = ModbusSerialClient(
                u.device,
                framer=FramerType.RTU,
                baudrate=u.baud,
                bytesize=u.bytesize,
                parity=u.parity,
                stopbits=u.stopbits,
                timeout=self.timeout_s,
                retries=0,  # this link retries reads itself, never writes
                trace_packet=trace,
            )
            if not client.connect():
                why = "does not exist" if not os.path.exists(u.device) else "cannot be opened (busy or no permission?)"
                raise ConnectionFailed(f"{u.url}: serial port {u.device} {why}")
        else:
            client = ModbusTcpClient(
                u.host,
                port=u.port,
                framer=FramerType.SOCKET if u.transport == "tcp" else FramerType.RTU,
                timeout=self.timeout_s,
                retries=0,  # this link retries reads itself, never writes
                trace_packet=trace,
            )
            # Open the socket here rather than in pymodbus, whose connect() only says "failed":
            # a refused connection and a silent host are different faults.
            try:
                sock = socket.create_connection((u.host, u.port), timeout=self.timeout_s)
            except ConnectionRefusedError as exc:
                raise ConnectionFailed(f"{u.url}: connection refused by {u.host}:{u.port} (is the device on?)") from exc
            except (socket.timeout, TimeoutError) as exc:
                raise DeviceTimeout(f"{u.url}: {u.host}:{u.port} did not accept a connection within {self.timeout_s} s") from exc
            except OSError as exc:
                raise ConnectionFailed(f"{u.url}: cannot connect to {u.host}:{u.port}: {exc}") from exc
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client.socket = sock
        self._client = client
        self.connections += 1
        if self.on_connect is not None:
            try:
                self.on_connect()
            except BaseException:
                self._drop()
                raise

    def _drop(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            try:
                client.close()
            except OSError:
                pass

    @contextmanager
    def _locked(self, what: str):
        if not self._lock.acquire(timeout=self.lock_timeout_s):
            raise DeviceTimeout(f"{self.url.url}: {what}: the link stayed busy for {self.lock_timeout_s:.2f} s")
        try:
            yield
        finally:
            self._lock.release()

    # --- requests -----------------------------------------------------------------------------
    def _request(self, what: str, function: int, call, *, reconnect: bool = True, idempotent: bool = False):
        """One request; a read (``idempotent``) whose reply does not come is sent again on the same
        connection, up to ``retries`` times (see the module doc). A write is sent once."""
        tries = self.retries + 1 if idempotent else 1
        with self._locked(what):
            for attempt in range(1, tries + 1):
                try:
                    return self._request_once(what, function, call, reconnect=reconnect, tries=tries,
                                              last=attempt == tries)
                except _NoReplyYet:
                    continue

    def _request_once(self, what: str, function: int, call, *, reconnect: bool, tries: int, last: bool):
        with self._locked(what):
            if not reconnect and self._client is None:
                raise ConnectionLost(f"{self.url.url}: {what}: not connected (this request does not reconnect)")
            self._ensure_connected()
            client = self._client
            if self.url.transport == "rtu-socket":
                _discard_unasked(client.socket)  # (the serial client does this itself before it sends)
            try:
                rsp = call(client, self.url.unit)
            except ModbusIOException as exc:
                if "no response" in str(exc).lower() and not last:
                    raise _NoReplyYet() from None
                self._drop()
                if "no response" in str(exc).lower():
                    raise DeviceTimeout(
                        f"{self.url.url}: {what}: no reply within {self.timeout_s} s x {tries} attempt(s)"
                    ) from exc
                raise ProtocolError(f"{self.url.url}: {what}: {exc}") from exc
            except (ConnectionException, OSError) as exc:
                self._drop()
                raise ConnectionLost(f"{self.url.url}: {what}: connection lost ({exc})") from exc
            except ModbusException as exc:
                self._drop()
                raise ProtocolError(f"{self.url.url}: {what}: {exc}") from exc
            except (struct.error, ValueError, IndexError) as exc:
                # a corrupted reply that pymodbus's decoder trips over (e.g. a flipped length byte)
                self._drop()
                raise ProtocolError(f"{self.url.url}: {what}: undecodable reply ({exc})") from exc
            if rsp is None:
                self._drop()
                raise ProtocolError(f"{self.url.url}: {what}: no decodable reply")
            if rsp.isError():
                fc = rsp.function_code & 0x7F
                code = int(getattr(rsp, "exception_code", 0))
                name = EXCEPTION_NAMES.get(code, "unknown exception")
                raise ModbusExceptionReply(
                    f"{self.url.url}: {what}: the device replied with Modbus exception {code} ({name}) "
                    f"to function {fc}",
                    fc,
                    code,
                )
            if rsp.function_code != function:
                self._drop()
                raise ProtocolError(
                    f"{self.url.url}: {what}: the reply is for function {rsp.function_code}, not {function}"
                )
            return rsp

    def read(self, kind: str, address: int, count: int = 1, *, reconnect: bool = True) -> list:
        """Read ``count`` values of one table from ``address``: coils (FC1) or discrete inputs (FC2) as
        bools, holding (FC3) or input (FC4) registers as ints 0..65535. ``reconnect=False``: raise
        ConnectionLost instead of opening a closed transport."""
        if kind not in _READS:
            raise ConfigError(f"Modbus read: unknown table {kind!r}; expected one of {', '.join(_READS)}")
        function, name, method, field = _READS[kind]
        address = _whole(f"read {name}", "address", address, 0, 0xFFFF)
        count = _whole(f"read {name}", "count", count, 1, min(_MAX_READ[field], 0x10000 - address))
        rsp = self._request(
            f"read {name} {address}+{count}",
            function,
            lambda c, u: getattr(c, method)(address, count=count, device_id=u),
            reconnect=reconnect,
            idempotent=True,
        )
        values = list(getattr(rsp, field))
        # bit replies are padded to whole bytes; register replies must match exactly
        if len(values) < count or (field == "registers" and len(values) != count):
            self.close()
            raise ProtocolError(f"{self.url.url}: asked {count} {name} at {address}, got {len(values)}")
        return [bool(v) for v in values[:count]] if field == "bits" else [int(v) for v in values]

    def _check_echo(self, what: str, rsp, expected: tuple, table: str) -> None:
        got = tuple(getattr(rsp, name, None) for name in ("address", "value"))
        if got != expected:
            self.close()
            raise WriteEchoMismatch(f"{self.url.url}: {what}: the reply echoes {got}, not {expected}", table, expected, got)

    def write_coil(self, address: int, value: bool) -> None:
        """FC5 Write Single Coil (the reply must echo address and value)."""
        address = _whole("write coil", "address", address, 0, 0xFFFF)
        if isinstance(value, str) or value not in (0, 1):  # True / False / 0 / 1: not whatever is truthy (NaN)
            raise ConfigError(f"Modbus write coil {address}: value {value!r}: expected True or False; nothing was sent")
        what = f"write coil {address}={int(bool(value))}"
        rsp = self._request(what, 5, lambda c, u: c.write_coil(address, bool(value), device_id=u))
        rsp.value = bool(rsp.bits[0]) if getattr(rsp, "bits", None) else None
        self._check_echo(what, rsp, (address, bool(value)), "coil")

    def write_register(self, address: int, value: int) -> None:
        """FC6 Write Single Register, value 0..65535 (the reply must echo address and value)."""
        address = _whole("write register", "address", address, 0, 0xFFFF)
        value = _whole("write register", "value", value, 0, 0xFFFF)
        what = f"write register {address}={int(value):#06x}"
        rsp = self._request(what, 6, lambda c, u: c.write_register(address, int(value), device_id=u))
        rsp.value = rsp.registers[0] if getattr(rsp, "registers", None) else None
        self._check_echo(what, rsp, (address, int(value)), "holding_register")

    def mask_write_register(self, address: int, and_mask: int, or_mask: int) -> None:
        """FC22 Mask Write Register: new = (old AND and_mask) OR (or_mask AND NOT and_mask)."""
        address = _whole("mask write register", "address", address, 0, 0xFFFF)
        and_mask = _whole("mask write register", "and_mask", and_mask, 0, 0xFFFF)
        or_mask = _whole("mask write register", "or_mask", or_mask, 0, 0xFFFF)
        what = f"mask write register {address} and={and_mask:#06x} or={or_mask:#06x}"
        rsp = self._request(
            what,
            22,
            lambda c, u: c.mask_write_register(address=address, and_mask=and_mask, or_mask=or_mask, device_id=u),
        )
        rsp.value = (getattr(rsp, "and_mask", None), getattr(rsp, "or_mask", None))
        self._check_echo(what, rsp, (address, (and_mask, or_mask)), "holding_register")
