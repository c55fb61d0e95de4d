"""A small Modbus server for the simulated devices: Modbus TCP (MBAP) or RTU frames over TCP, on 127.0.0.1.

Written from the Modbus Application Protocol v1.1b3 and the serial line guide (CRC-16, RTU framing), so that
the simulated valve terminal depends on no Modbus library's server API (pymodbus's server data store changes
between its releases, and pymodbus 4 removes it) and the driver's client is tested against a server it shares
no code with. The CRC-16 here is the server's own; the tests check its frames with a CRC written separately. It
serves one unit; a request for another unit gets exception 11 (gateway target failed to respond), as a
gateway would say. Requests of one connection are answered in order, in the caller's event loop.
"""

from __future__ import annotations

import asyncio
import struct
from collections.abc import Callable
from typing import Protocol

__all__ = ["ModbusServer", "ProcessImage", "crc16", "ILLEGAL_FUNCTION", "ILLEGAL_ADDRESS", "ILLEGAL_VALUE",
           "DEVICE_FAILURE", "GATEWAY_NO_RESPONSE", "EXCEPTION_CODES"]

ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE, GATEWAY_NO_RESPONSE = 1, 2, 3, 4, 11
#: The exception codes of the protocol (section 7).
EXCEPTION_CODES = (1, 2, 3, 4, 5, 6, 8, 10, 11)

#: function code -> (table, bits?); the tables are 'coil', 'discrete_input', 'holding_register', 'input_register'
_READS = {1: ("coil", True), 2: ("discrete_input", True), 3: ("holding_register", False), 4: ("input_register", False)}
_MAX_READ = {True: 2000, False: 125}
#: Silence after a partial RTU frame that ends it (the 3.5-character gap of a serial line, generously).
_SILENCE_S = 0.2


class ProcessImage(Protocol):
    """What the server reads and writes: each call returns the values / None, or an exception code (int)."""

    def read(self, table: str, address: int, count: int) -> list | int: ...

    def write(self, table: str, address: int, values: list) -> int | None: ...


def crc16(frame: bytes) -> bytes:
    """Modbus RTU CRC-16 (polynomial 0xA001 reflected, initial 0xFFFF), low byte first."""
    crc = 0xFFFF
    for b in frame:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return struct.pack("<H", crc)


def _bits_to_bytes(bits) -> bytes:
    out = bytearray((len(bits) + 7) // 8)
    for i, b in enumerate(bits):
        if b:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def _exception(fc: int, code: int) -> bytes:
    return bytes([(fc | 0x80) & 0xFF, code])


def execute(image: ProcessImage, pdu: bytes) -> bytes:
    """Run one request PDU (function code first) against ``image``; returns the reply PDU."""
    if not pdu:
        return b""
    fc, body = pdu[0], pdu[1:]
    if fc in _READS:
        table, bits = _READS[fc]
        if len(body) != 4:
            return _exception(fc, ILLEGAL_VALUE)
        address, count = struct.unpack(">HH", body)
        if not 1 <= count <= _MAX_READ[bits]:
            return _exception(fc, ILLEGAL_VALUE)
        values = image.read(table, address, count)
        if isinstance(values, int):
            return _exception(fc, values)
        data = _bits_to_bytes(values) if bits else b"".join(struct.pack(">H", int(v) & 0xFFFF) for v in values)
        return bytes([fc, len(data)]) + data
    if fc in (5, 6, 22):
        if len(body) != (6 if fc == 22 else 4):
            return _exception(fc, ILLEGAL_VALUE)
        address, value = struct.unpack(">HH", body[:4])
        if fc == 5:
            if value not in (0x0000, 0xFF00):
                return _exception(fc, ILLEGAL_VALUE)
            rc = image.write("coil", address, [value == 0xFF00])
        elif fc == 6:
            rc = image.write("holding_register", address, [value])
        else:
            and_mask, or_mask = value, struct.unpack(">H", body[4:])[0]
            current = image.read("holding_register", address, 1)
            if isinstance(current, int):
                return _exception(fc, current)
            rc = image.write("holding_register", address, [(current[0] & and_mask) | (or_mask & ~and_mask & 0xFFFF)])
        return _exception(fc, rc) if rc else pdu
    if fc in (15, 16):
        if len(body) < 5:
            return _exception(fc, ILLEGAL_VALUE)
        address, count, nbytes = struct.unpack(">HHB", body[:5])
        data = body[5:]
        bits = fc == 15
        ok_count = 1 <= count <= (0x7B0 if bits else 123)
        want = (count + 7) // 8 if bits else 2 * count
        if not ok_count or nbytes != want or len(data) != nbytes:
            return _exception(fc, ILLEGAL_VALUE)
        if bits:
            values = [bool((data[i // 8] >> (i % 8)) & 1) for i in range(count)]
            rc = image.write("coil", address, values)
        else:
            rc = image.write("holding_register", address, list(struct.unpack(f">{count}H", data)))
        return _exception(fc, rc) if rc else bytes([fc]) + body[:4]
    return _exception(fc, ILLEGAL_FUNCTION)


def _rtu_length(buf: bytes) -> int | None:
    """The length of the RTU request frame at the start of ``buf`` (None: not known yet)."""
    if len(buf) < 2:
        return None
    fc = buf[1]
    if fc in (1, 2, 3, 4, 5, 6):
        return 8
    if fc == 22:
        return 10
    if fc in (15, 16):
        return 9 + buf[6] if len(buf) >= 7 else None
    # an unknown function: the shortest prefix whose CRC checks (a real slave would time the silence)
    for n in range(4, min(len(buf), 256) + 1):
        if crc16(buf[: n - 2]) == buf[n - 2 : n]:
            return n
    return None if len(buf) < 256 else -1


class ModbusServer:
    """Serves ``image`` for ``unit`` on 127.0.0.1:``port`` (0: a free port) in the running event loop.

    ``framing``: 'mbap' (Modbus TCP) or 'rtu' (RTU frames over TCP). ``on_request(unit, pdu)`` is called for
    each well-framed request before it runs and returns 'answer', 'silent' (taken, never answered) or 'drop'
    (every connection closed, the request not run). ``on_connect()`` is called for each new connection.
    """

    def __init__(self, image: ProcessImage, *, unit: int, framing: str = "mbap", port: int = 0,
                 on_request: Callable[[int, bytes], str] | None = None, on_connect: Callable[[], None] | None = None):
        if framing not in ("mbap", "rtu"):
            raise ValueError(f"framing {framing!r}: expected 'mbap' or 'rtu'")
        if isinstance(unit, bool) or not isinstance(unit, int) or not 0 <= unit <= 255:
            raise ValueError(f"Modbus unit {unit!r}: expected a whole number 0..255")
        self.image, self.unit, self.framing, self._want_port = image, int(unit), framing, int(port)
        self.on_request = on_request or (lambda unit, pdu: "answer")
        self.on_connect = on_connect or (lambda: None)
        self.port: int | None = None
        self._server: asyncio.base_events.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    @property
    def connections(self) -> int:
        return len(self._writers)

    async def start(self) -> int:
        self._server = await asyncio.start_server(self._serve, "127.0.0.1", self._want_port)
        self.port = self._server.sockets[0].getsockname()[1]
        return self.port

    def drop_all(self) -> None:
        """Close every open connection now (the listener stays)."""
        for w in list(self._writers):
            w.close()

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            self.drop_all()
            await self._server.wait_closed()
            self._server = None

    def _reply(self, unit: int, pdu: bytes) -> bytes | None:
        """The reply PDU for a request, or None when the request is not to be answered."""
        what = self.on_request(unit, pdu)
        if what == "drop":
            self.drop_all()
            return None
        if what == "silent":
            return None
        if what != "answer":
            raise ValueError(f"on_request returned {what!r}: expected 'answer', 'silent' or 'drop'")
        if unit != self.unit:
            return _exception(pdu[0], GATEWAY_NO_RESPONSE)
        return execute(self.image, pdu)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        self.on_connect()
        try:
            if self.framing == "mbap":
                await self._serve_mbap(reader, writer)
            else:
                await self._serve_rtu(reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError, OSError):
            pass
        finally:
            self._writers.discard(writer)
            writer.close()

    async def _serve_mbap(self, reader, writer) -> None:
        while True:
            head = await reader.readexactly(7)
            tid, pid, length, unit = struct.unpack(">HHHB", head)
            if pid != 0 or not 2 <= length <= 254:
                return  # not Modbus TCP: the stream cannot be re-synchronised, so the connection ends
            pdu = await reader.readexactly(length - 1)
            reply = self._reply(unit, pdu)
            if reply is None or writer.is_closing():
                continue
            writer.write(struct.pack(">HHHB", tid, 0, len(reply) + 1, unit) + reply)
            await writer.drain()

    async def _serve_rtu(self, reader, writer) -> None:
        buf = b""
        while True:
            n = _rtu_length(buf)
            if n is None or (n > 0 and len(buf) < n):
                try:  # silence ends an RTU frame: what came before it and is no whole frame is noise
                    chunk = await asyncio.wait_for(reader.read(256), None if not buf else _SILENCE_S)
                except asyncio.TimeoutError:
                    buf = b""
                    continue
                if not chunk:
                    return
                buf += chunk
                continue
            if n < 0 or crc16(buf[: n - 2]) != buf[n - 2 : n]:
                buf = buf[1:]  # a corrupted frame: a slave stays silent; look for the next frame
                continue
            frame, buf = buf[:n], buf[n:]
            reply = self._reply(frame[0], frame[1:-2])
            if reply is None or writer.is_closing():
                continue
            out = bytes([frame[0]]) + reply
            writer.write(out + crc16(out))
            await writer.drain()
