"""Where a gripper's valve solenoids and reed switches sit in a Modbus device: the I/O map.

Pure configuration (no I/O, no pymodbus), shared by the driver and the simulated valve terminal. A valve
terminal such as a Festo CPX maps each solenoid to a bit of a 16-bit output word (a holding register) and
its inputs to bits of input registers; simple I/O modules use a coil per solenoid and a discrete input
per switch. Both fit here.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, fields

from selfview.errors import ConfigError

__all__ = ["Point", "IoMap", "KINDS", "from_reference", "to_reference", "JAW_STATES"]

#: Modbus tables: (short name, one-bit table?, writable?, Modicon reference digit).
KINDS: dict[str, tuple[str, bool, bool, int]] = {
    "coil": ("coil", True, True, 0),
    "discrete_input": ("di", True, False, 1),
    "input_register": ("ir", False, False, 3),
    "holding_register": ("hr", False, True, 4),
}
_SHORT = {v[0]: k for k, v in KINDS.items()} | {k: k for k in KINDS}
_BY_DIGIT = {v[3]: k for k, v in KINDS.items()}

#: The jaw states the driver reports; "open" and "closed" are also the cell's gripper state names.
JAW_STATES = ("open", "closed", "between")


@dataclass(frozen=True)
class Point:
    """One bit on the wire: a coil or discrete input, or bit ``bit`` of a 16-bit register.

    ``address`` is the 0-based wire address (the PDU's), ``bit`` 0..15 (0 = least significant) for
    registers and None for one-bit tables.
    """

    kind: str
    address: int
    bit: int | None = None

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ConfigError(f"I/O point kind {self.kind!r}: expected one of {', '.join(KINDS)}")
        if isinstance(self.address, bool) or not isinstance(self.address, int) or not 0 <= self.address <= 0xFFFF:
            raise ConfigError(f"I/O point {self.kind} address {self.address!r}: expected a whole number 0..65535")
        if self.is_bit_table:
            if self.bit is not None:
                raise ConfigError(f"I/O point {self.kind}:{self.address}: a {self.kind} has no bit number")
        elif isinstance(self.bit, bool) or not isinstance(self.bit, int) or not 0 <= self.bit <= 15:
            raise ConfigError(
                f"I/O point {self.kind}:{self.address}: a register point needs a bit 0..15, got {self.bit!r}"
            )

    @property
    def is_bit_table(self) -> bool:
        return KINDS[self.kind][1]

    @property
    def writable(self) -> bool:
        return KINDS[self.kind][2]

    @classmethod
    def parse(cls, text: "str | Point") -> "Point":
        """``coil:0`` / ``di:1`` / ``hr:0.3`` / ``ir:2.15`` (0-based wire addresses) or a Modicon
        reference such as ``40001.3``. Raises ConfigError naming the text.

        Manuals often count 1-based "Modicon references", with the table in the leading digit: ``00001``
        coil 0, ``10001`` discrete input 0, ``30001`` input register 0, ``40001`` holding register 0
        (six-digit forms ``400001`` likewise); they are converted with ``from_reference``."""
        if isinstance(text, Point):
            return text
        if not isinstance(text, str):
            raise ConfigError(
                f"I/O point {text!r}: expected text such as 'coil:0', 'hr:0.3' or '40001.3' "
                "(in YAML, quote a reference: a number would lose its leading zeros and bit digits)"
            )
        s = text.strip()
        m = re.fullmatch(r"([a-z_]+):([0-9]+)(?:\.([0-9]+))?", s)
        if m:
            kind = _SHORT.get(m.group(1))
            if kind is None:
                raise ConfigError(
                    f"I/O point {text!r}: unknown table {m.group(1)!r}; expected coil, di, ir or hr"
                )
            return cls(kind, int(m.group(2)), None if m.group(3) is None else int(m.group(3)))
        m = re.fullmatch(r"([0-9]{5,6})(?:\.([0-9]+))?", s)
        if m:
            return from_reference(m.group(1), None if m.group(2) is None else int(m.group(2)))
        raise ConfigError(
            f"I/O point {text!r}: expected 'coil:N', 'di:N', 'ir:N.B', 'hr:N.B' (0-based wire address, bit) "
            "or a 5/6-digit Modicon reference such as '40001.3'"
        )

    def __str__(self) -> str:
        short = KINDS[self.kind][0]
        return f"{short}:{self.address}" + ("" if self.bit is None else f".{self.bit}")


def from_reference(ref: str, bit: int | None = None) -> Point:
    """A 1-based Modicon reference (``40001``, ``400001``, ``10003``) -> the Point at its 0-based wire
    address. Raises ConfigError for a malformed reference or an unknown table digit."""
    if not isinstance(ref, str) or not re.fullmatch(r"[0-9]{5,6}", ref):
        raise ConfigError(f"Modicon reference {ref!r}: expected 5 or 6 digits such as '40001' or '400001'")
    kind = _BY_DIGIT.get(int(ref[0]))
    if kind is None:
        raise ConfigError(f"Modicon reference {ref!r}: leading digit {ref[0]} is not 0, 1, 3 or 4")
    number = int(ref[1:])
    if number < 1:
        raise ConfigError(f"Modicon reference {ref!r}: references count from 1 ({ref[0]}0001)")
    return Point(kind, number - 1, bit)


def to_reference(point: Point) -> str:
    """The 6-digit Modicon reference of a point (``hr:0.3`` -> ``'400001.3'``), for messages and manuals."""
    ref = f"{KINDS[point.kind][3]}{point.address + 1:05d}"
    return ref + ("" if point.bit is None else f".{point.bit}")


_SAFE = ("all-off", "open", "closed")
_REGISTER_WRITE = ("read-modify-write", "mask")
_STRAY = ("report", "switch-off")


@dataclass(frozen=True)
class IoMap:
    """The gripper's valve outputs and reed-switch inputs.

    - ``open_valve`` / ``close_valve``: the solenoid that drives the jaws open / closed. Give both for a
      double solenoid (bistable) valve; give one for a single solenoid with spring return, whose
      de-energised position is the other state.
    - ``open_sensor`` / ``closed_sensor``: the reed switches that read True when the jaws are fully
      open / fully closed (discrete inputs or register bits).
    - ``safe_state``: what ``safe()`` commands: ``all-off`` (de-energise every solenoid: a double valve
      holds its position, a single valve springs back), ``open`` or ``closed``.
    - ``register_write``: how a solenoid bit inside a holding register is written: ``read-modify-write``
      (FC3 then FC6; every device has them) or ``mask`` (FC22 Mask Write Register, atomic).
    - ``stray_coils``: what the driver does when a write's echo shows that the device switched *on* a coil
      this map does not own (a request corrupted on its way: Modbus TCP has no checksum of its own).
      ``report`` (default): the error names the coil and says to check it; the driver leaves it alone,
      since on a shared terminal it may be another valve's, held on by its owner. ``switch-off``: the
      terminal's other coils serve nothing that must stay energised (a terminal for this gripper alone),
      so the driver switches that coil off at once and reads it back. The fail-safe of such a terminal
      (its watchdog) is all coils off, which is what this restores.
    """

    open_valve: Point | None = Point("coil", 0)
    close_valve: Point | None = Point("coil", 1)
    open_sensor: Point = Point("discrete_input", 0)
    closed_sensor: Point = Point("discrete_input", 1)
    safe_state: str = "all-off"
    register_write: str = "read-modify-write"
    stray_coils: str = "report"

    def __post_init__(self):
        valves = [p for p in (self.open_valve, self.close_valve) if p is not None]
        if not valves:
            raise ConfigError("io map: needs open_valve, close_valve or both (single or double solenoid)")
        for name in ("open_valve", "close_valve"):
            p = getattr(self, name)
            if p is not None and not p.writable:
                raise ConfigError(f"io map {name}: {p} is a read-only table; a solenoid is a coil or an hr bit")
        for name in ("open_sensor", "closed_sensor"):
            if not isinstance(getattr(self, name), Point):
                raise ConfigError(f"io map {name}: expected a Point, got {getattr(self, name)!r}")
        if len(set(valves)) != len(valves):
            raise ConfigError(f"io map: open_valve and close_valve are the same point {valves[0]}")
        if self.open_sensor == self.closed_sensor:
            raise ConfigError(f"io map: open_sensor and closed_sensor are the same point {self.open_sensor}")
        if set(valves) & {self.open_sensor, self.closed_sensor}:
            raise ConfigError("io map: a sensor shares its point with a solenoid")
        if self.safe_state not in _SAFE:
            raise ConfigError(f"io map safe_state {self.safe_state!r}: expected one of {', '.join(_SAFE)}")
        if self.stray_coils not in _STRAY:
            raise ConfigError(f"io map stray_coils {self.stray_coils!r}: expected one of {', '.join(_STRAY)}")
        if self.register_write not in _REGISTER_WRITE:
            raise ConfigError(
                f"io map register_write {self.register_write!r}: expected one of {', '.join(_REGISTER_WRITE)}"
            )

    @property
    def solenoid(self) -> str:
        """'double' or 'single'."""
        return "double" if self.open_valve is not None and self.close_valve is not None else "single"

    @property
    def valves(self) -> dict[str, Point]:
        """{'open': point, 'close': point} for the solenoids present."""
        return {k: p for k, p in (("open", self.open_valve), ("close", self.close_valve)) if p is not None}

    def drive(self, state: str) -> dict[str, bool]:
        """Solenoid outputs {'open': bool, 'close': bool} (present ones only) that drive the jaws to
        ``state`` ('open' or 'closed'), or de-energise everything for 'all-off'."""
        if state == "all-off":
            return {k: False for k in self.valves}
        if state not in ("open", "closed"):
            raise ConfigError(f"jaw state {state!r}: expected 'open' or 'closed'")
        want = "open" if state == "open" else "close"
        return {k: k == want for k in self.valves}

    def direction(self, outputs: Mapping[str, bool]) -> str | None:
        """Where the valve drives the jaws for solenoid outputs {'open': bool, 'close': bool}:
        'open', 'closed', or None (a double valve with both or neither energised holds its position)."""
        o, c = bool(outputs.get("open", False)), bool(outputs.get("close", False))
        if self.solenoid == "double":
            if o == c:
                return None
            return "open" if o else "closed"
        if self.open_valve is not None:
            return "open" if o else "closed"
        return "closed" if c else "open"

    @classmethod
    def from_dict(cls, data: Mapping) -> "IoMap":
        """An IoMap from a mapping of text (a YAML section): points as ``Point.parse`` reads them, a
        missing or null valve for a single solenoid. Raises ConfigError naming unknown keys."""
        if not isinstance(data, Mapping):
            raise ConfigError(f"io map: expected a mapping, got {type(data).__name__}")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(map(str, data)) - names)
        if unknown:
            raise ConfigError(f"io map: unknown key(s) {', '.join(unknown)}; expected {', '.join(sorted(names))}")
        kw = {}
        for k, v in data.items():
            if k in ("safe_state", "register_write", "stray_coils"):
                kw[k] = v
            elif k in ("open_valve", "close_valve") and (v is None or str(v).strip().lower() in ("", "null", "~", "none")):
                kw[k] = None
            else:
                try:
                    kw[k] = Point.parse(v)
                except ConfigError as exc:
                    raise ConfigError(f"io map {k}: {exc}") from None
        return cls(**kw)

    def to_dict(self) -> dict:
        """The text form ``from_dict`` reads (for run records)."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = str(v) if isinstance(v, Point) else v
        return out
