"""Modbus URLs: which transport and framing a gripper valve is reached by.

- ``modbus-tcp://HOST[:PORT]?unit=1`` - Modbus TCP (MBAP framing), port 502 by default.
- ``modbus-rtu:///dev/ttyUSB0?baud=19200&parity=E&stopbits=1&bytesize=8&unit=1`` - Modbus RTU on a
  serial line (defaults 19200 baud, even parity, 8 data bits, 1 stop bit: the Modbus standard's).
- ``modbus-rtu+socket://HOST:PORT?unit=1`` - RTU frames (with CRC, no MBAP header) over a TCP socket,
  as serial device servers and RTU-over-TCP gateways carry them.

``unit`` (the slave or device id, 1..247, 0 for a TCP device that ignores it; 255 is also common on
TCP) defaults to 1.
"""

from __future__ import annotations

from dataclasses import dataclass
from urllib.parse import parse_qsl, urlsplit

from selfview.errors import ConfigError
from selfview.files.io_safe import parse_number

__all__ = ["ModbusUrl", "parse_modbus_url"]

_SCHEMES = {"modbus-tcp": "tcp", "modbus-rtu": "rtu", "modbus-rtu+socket": "rtu-socket"}
_PARITY = {"N": "N", "E": "E", "O": "O", "NONE": "N", "EVEN": "E", "ODD": "O"}


@dataclass(frozen=True)
class ModbusUrl:
    """A parsed Modbus URL. ``transport`` is 'tcp', 'rtu' (serial) or 'rtu-socket'."""

    url: str
    transport: str
    host: str = ""
    port: int = 502
    device: str = ""
    unit: int = 1
    baud: int = 19200
    parity: str = "E"
    stopbits: int = 1
    bytesize: int = 8

    @property
    def framing(self) -> str:
        """'mbap' for Modbus TCP, 'rtu' for RTU frames (serial or over a socket)."""
        return "mbap" if self.transport == "tcp" else "rtu"

    def describe(self) -> str:
        if self.transport == "rtu":
            return f"{self.device} ({self.baud} baud {self.bytesize}{self.parity}{self.stopbits}, unit {self.unit})"
        return f"{self.host}:{self.port} ({'RTU over TCP' if self.transport == 'rtu-socket' else 'Modbus TCP'}, unit {self.unit})"


def _int(url: str, key: str, text: str, lo: int, hi: int) -> int:
    try:
        return parse_number(text, integer=True, lo=lo, hi=hi)
    except ValueError as exc:
        raise ConfigError(f"{url}: {key}={text}: {exc}") from None


def parse_modbus_url(url: str) -> ModbusUrl:
    """Parse a Modbus URL (see the module doc). Raises ConfigError naming the URL and the bad part."""
    if not isinstance(url, str) or "://" not in url:
        raise ConfigError(
            f"Modbus URL {url!r}: expected modbus-tcp://HOST:PORT?unit=N, modbus-rtu:///dev/ttyX?baud=N "
            "or modbus-rtu+socket://HOST:PORT?unit=N"
        )
    parts = urlsplit(url)
    transport = _SCHEMES.get(parts.scheme.lower())
    if transport is None:
        raise ConfigError(f"Modbus URL {url!r}: unknown scheme {parts.scheme!r}; expected {', '.join(_SCHEMES)}")
    params = dict(parse_qsl(parts.query, keep_blank_values=True))
    allowed = {"unit"} | ({"baud", "parity", "stopbits", "bytesize"} if transport == "rtu" else set())
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise ConfigError(f"{url}: unknown parameter(s) {', '.join(unknown)}; expected {', '.join(sorted(allowed))}")
    kw: dict = {"url": url, "transport": transport}
    kw["unit"] = _int(url, "unit", params.get("unit", "1"), 0, 255)
    if transport == "rtu":
        if parts.netloc or not parts.path:
            raise ConfigError(f"{url}: expected modbus-rtu:///dev/ttyX (three slashes, then the device path)")
        kw["device"] = parts.path
        kw["baud"] = _int(url, "baud", params.get("baud", "19200"), 50, 4_000_000)
        parity = _PARITY.get(params.get("parity", "E").upper())
        if parity is None:
            raise ConfigError(f"{url}: parity={params['parity']!r}; expected N, E or O")
        kw["parity"] = parity
        kw["stopbits"] = _int(url, "stopbits", params.get("stopbits", "1"), 1, 2)
        kw["bytesize"] = _int(url, "bytesize", params.get("bytesize", "8"), 7, 8)
    else:
        if parts.path not in ("", "/"):
            raise ConfigError(f"{url}: a {parts.scheme} URL has no path; expected {parts.scheme}://HOST:PORT")
        try:
            host, port = parts.hostname, parts.port
        except ValueError as exc:
            raise ConfigError(f"{url}: bad port ({exc})") from None
        if not host:
            raise ConfigError(f"{url}: missing host")
        if port is None and transport == "rtu-socket":
            raise ConfigError(f"{url}: RTU over TCP has no standard port; give HOST:PORT")
        if port == 0:
            raise ConfigError(f"{url}: port 0 is not a port to connect to")
        kw["host"] = host
        kw["port"] = 502 if port is None else port
    return ModbusUrl(**kw)
