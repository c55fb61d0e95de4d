"""The VAL-II terminal dialect as data: what to send, how replies look, what the error texts mean.

The real controller's details (echo, line endings, the prompts, the WHERE layout, the wording of error
lines, the O/A/T Euler convention, the command syntax) are not documented precisely, so they live here
as a ``ValDialect`` that a YAML file can adjust (``load_dialect``) without code changes. The driver
formats and parses through it; the simulator (``mocks/val_controller.py``) reads the same data but
formats its replies with its own code, so a bug in the driver's formatting cannot hide in both.
"""

from __future__ import annotations

import itertools
import logging
import re
import string
from dataclasses import asdict, dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from selfview.drivers.puma_val_serial._config import check_keys, read_yaml
from selfview.drivers.puma_val_serial.errors import ERROR_CLASSES, ControllerError
from selfview.errors import ConfigError, ProtocolError
from selfview.maths.geometry import VAL_OAT, EulerConvention, H_from_xyzoat, xyzoat_from_H

_log = logging.getLogger(__name__)

__all__ = ["ValDialect", "DEFAULT_COMMANDS", "PREFIX_SAFE_KINDS", "DEFAULT_ERRORS", "OAT_CONVENTIONS", "load_dialect"]

#: O/A/T conventions by name. The default is the convention of Unimation's VAL, which VAL-II keeps
#: (the sources, best first):
#: - Unimation, *User's Guide to VAL* (1977-1980), on location data: "With all three angles zero, the
#:   hand points in the negative Y direction with the fingers in a horizontal plane"; O is a rotation
#:   about the vertical, A tilts the approach direction up or down, T turns the hand about its approach
#:   direction. A vertical tool therefore has A = +-90. VAL's READY position (the arm straight up, tool
#:   up) prints O = 90, A = -90, T = 0 in this convention, the values seen on PUMA controllers at READY.
#: - VAL-II kept VAL's location syntax (``TRANS(x, y, z, o, a, t)``, ``WHERE``'s ``X Y Z O A T``); its
#:   reference manual (Unimation, *User's Guide to VAL II*, 1986) was not available to check the signs.
#: - Adept's V+, VAL-II's successor, changed to plain ZYZ (yaw, pitch, roll) with the tool pointing up
#:   at (0, 0, 0) and down at (0, 180, 0): the ``vplus`` entry.
#: As an ``EulerConvention``: ``R = Rz(O) Rx(A) Ry(-T) R0`` with ``R0`` the hand at zero (approach -Y,
#: fingers' closing axis along +X, both horizontal). A real arm's first WHERE names a wrong choice: the
#: driver checks WHERE's pose against the kinematics of its own joint angles and says which convention
#: fits (``PumaVAL.where``).
OAT_CONVENTIONS: dict[str, EulerConvention] = {
    # VAL (Unimation 1977): all zero = approach along -Y, fingers horizontal; R = Rz(O) Rx(A) Ry(-T) R0
    "val": EulerConvention(
        sequence="zxy",
        signs=(1.0, 1.0, -1.0),
        tool=((0.0, 1.0, 0.0), (0.0, 0.0, -1.0), (-1.0, 0.0, 0.0)),
    ),
    # Adept V+ (VAL-II's successor): ZYZ, the tool up at (0, 0, 0), down at (0, 180, 0)
    "vplus": VAL_OAT,
}

#: Command line templates; ``{name}`` is a location name, every other field a number.
#:
#: **No proper prefix of a line that moves the arm (or sets the speed, or defines a location) is itself a
#: valid line.** Noise on the host-to-controller wire can put a line end inside a typed line, and the
#: controller then executes the part before it: ``DO APPRO plate, 5`` of ``DO APPRO plate, 50`` is a real,
#: different motion, and ``DO MOVE p`` of ``DO MOVE p1`` is one too when a location ``p`` exists. So the
#: last argument of each such line is a parenthesised expression (VAL-II reads a real or location
#: expression in parentheses as its value): any prefix that reaches into it leaves a parenthesis open,
#: which is a syntax error, and any shorter prefix lacks a required argument. Per line (``|`` marks where
#: a cut can fall):
#:
#: - ``SPEED (20)``: ``SPEED`` alone lacks its value; ``SPEED (2`` is unbalanced.
#: - ``DO SET svtgt = (TRANS(350, 20, 100, 0, 90, 0))``: ``DO SET svtgt`` lacks ``=`` and its value,
#:   ``DO SET svtgt = (TRANS`` is unbalanced, and no prefix reads as ``= T`` (a location named ``T``).
#: - ``DO MOVE (above)``, ``DO MOVES (above)``: ``DO MOVE (abo`` is unbalanced (not the location ``abo``),
#:   ``DO MOVE`` lacks its location.
#: - ``DO APPRO plate, (50)``: ``DO APPRO plate, (5`` is unbalanced; ``DO APPRO plat`` and
#:   ``DO APPRO plate`` lack the distance (required).
#: - ``DO DEPART (50)``: ``DO DEPART (5`` is unbalanced, ``DO DEPART`` lacks the distance.
#: - ``DO DRIVE 2, (-10.5), (20)``: ``DO DRIVE 2, (-10.5), (2`` is unbalanced; shorter ones lack the
#:   speed (required).
#: - ``DO READY`` has no argument: its prefixes are ``DO`` and parts of the word ``READY``.
#:
#: ``HERE name`` and ``POINT name`` move nothing: a prefix of the first records the current pose under a
#: shorter name, one of the second shows a location and is answered "no change".
#:
#: **To be checked on a real VAL-II controller** before relying on this (the simulator,
#: ``mocks/val_controller.py``, follows these assumptions): (1) a parenthesised real expression is
#: accepted wherever a number is (``SPEED (20)``, ``DO DEPART (50)``) and a parenthesised location
#: wherever a location is (``DO MOVE (above)``, ``DO SET a = (TRANS(...))``); (2) an unbalanced
#: parenthesis is a syntax error and nothing runs; (3) APPRO's distance and DRIVE's speed are required,
#: not optional (else ``DO APPRO plate`` would run as APPRO with no offset); (4) ``DO`` alone, and ``DO``
#: with an abbreviated keyword such as ``DO READ``, runs nothing (neither repeats the last DO instruction).
#: Where (1) fails, a YAML dialect can put back the bare forms (``commands:``), at the price of issue 32's
#: prefix motions; ``ValDialect.valid_prefixes`` lists what a template leaves open.
DEFAULT_COMMANDS: dict[str, str] = {
    "where": "WHERE",
    "calibrate": "CAL",
    "speed": "SPEED ({pct})",
    "here": "HERE {name}",
    "point": "POINT {name}",
    "define": "DO SET {name} = (TRANS({x}, {y}, {z}, {o}, {a}, {t}))",
    "move": "DO MOVE ({name})",
    "moves": "DO MOVES ({name})",
    "appro": "DO APPRO {name}, ({d})",
    "depart": "DO DEPART ({d})",
    "drive": "DO DRIVE {joint}, ({deg}), ({speed})",
    "ready": "DO READY",
    "abort": "ABORT",
    "status": "STATUS",
}

#: The command kinds that move the arm, set its speed or define a location: no proper prefix of their
#: lines may be a valid line (``ValDialect.valid_prefixes``).
PREFIX_SAFE_KINDS = ("speed", "define", "move", "moves", "appro", "depart", "drive", "ready")

#: (controller text, error class) pairs. ``{joint}`` stands for a number. The simulator prints the
#: first text listed for a class; the driver accepts every text (case-insensitive, anywhere in the line).
DEFAULT_ERRORS: tuple[tuple[str, str], ...] = (
    ("Arm power off", "ArmPowerOff"),
    ("Location out of reach", "OutOfReach"),
    ("Robot not calibrated", "NotCalibrated"),
    ("Undefined location", "UndefinedLocation"),
    ("Collision detected", "Collision"),
    ("Motion aborted", "MotionAborted"),
    ("Joint {joint} limit stop", "JointLimit"),
    ("Illegal value", "InvalidArgument"),
    ("Unrecognized command", "CommandRejected"),
)

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_PAREN_LEVELS = 3  # how deep a value's parentheses may nest: '50', '(50)', '((50))', '(((50)))'


def _optional_parens(inner: str, tag: str) -> str:
    """``inner`` inside 0 to ``_PAREN_LEVELS`` pairs of parentheses, balanced by construction (each
    closing parenthesis is conditional on its opening one): an unbalanced text never matches."""
    names = [f"{tag}_{k}" for k in range(_PAREN_LEVELS)]
    return "".join(rf"(?P<{n}>\(\s*)?" for n in names) + inner + "".join(rf"(?({n})\s*\))" for n in reversed(names))


def _template_regex(tpl: str, name_pattern: str) -> re.Pattern:
    """A regex for a command template that reads a line as a VAL-II controller would: any case, blanks
    optional around punctuation and required between words, fields as groups. A number is a real
    expression: a number, or one in (nested) parentheses. Parentheses of the template that follow a
    blank or punctuation group (``DO MOVE ({name})``, ``= (TRANS(...))``) may be given or left out,
    as a controller's expression syntax allows; those right after a word are a function's
    (``TRANS(``) and required. Every parenthesis given must be closed: a truncated line is rejected."""
    atoms: list[tuple[str, str]] = []  # (kind, text): 'w' a word character, 'p' punctuation, 's' blank, 'f' field
    for lit, fld, _, _ in string.Formatter().parse(tpl):
        for m in re.finditer(r"\s+|\w|[^\w\s]", lit):
            t = m.group()
            atoms.append(("s", t) if t.isspace() else ("w" if re.fullmatch(r"\w", t) else "p", t))
        if fld:
            atoms.append(("f", fld))
    groups = itertools.count()

    def close_of(i: int) -> int:
        depth = 0
        for j in range(i, len(atoms)):
            depth += {"(": 1, ")": -1}.get(atoms[j][1], 0) if atoms[j][0] == "p" else 0
            if depth == 0:
                return j
        raise ConfigError(f"command template {tpl!r}: a parenthesis is not closed")

    def seq(lo: int, hi: int) -> str:
        rx, prev, i = "", "p", lo  # prev: what came last, 'w' word-like or 'p' punctuation
        while i < hi:
            kind, t = atoms[i]
            if kind == "s":
                nk, nt = atoms[i + 1] if i + 1 < hi else ("p", "")
                if prev == "w" and nk in ("w", "f"):
                    rx += r"\s+"
                elif prev == "w" and nt == "(":  # '(' optional: a blank, or the parenthesis itself
                    rx += r"(?:\s+|(?=\())"
                else:
                    rx += r"\s*"
                prev = "s"
                i += 1
                continue
            if kind == "p" and t == "(":
                j = close_of(i)
                inner = seq(i + 1, j)
                if prev == "w":  # a function's parentheses, TRANS(...)
                    rx += r"\(\s*" + inner + r"\s*\)"
                else:
                    rx += r"\s*" + _optional_parens(inner, f"g{next(groups)}")
                prev, i = "p", j + 1
                continue
            if kind == "p":
                rx += r"\s*" + re.escape(t)
                prev = "p"
            else:
                if prev == "p":
                    rx += r"\s*"
                if kind == "f":
                    pat = name_pattern if t == "name" else _optional_parens(_NUMBER, f"n{next(groups)}")
                    rx += f"(?P<{t}>{pat})"
                else:
                    rx += re.escape(t)
                prev = "w"
            i += 1
        return rx

    return re.compile(r"\s*" + seq(0, len(atoms)) + r"\s*", re.IGNORECASE)


def _euler_from(v: Any) -> EulerConvention:
    if isinstance(v, EulerConvention):
        return v
    check_keys(v, EulerConvention, "dialect.euler")
    kw = {}
    for k, val in v.items():
        kw[k] = val if k == "sequence" else tuple(tuple(r) if isinstance(r, (list, tuple)) else float(r) for r in val)
    return EulerConvention(**kw)


@dataclass(frozen=True)
class ValDialect:
    """One controller's terminal dialect. Defaults: VAL-II on a PUMA 260 as reconstructed from public
    drivers and transcripts.

    ``prompt`` is the monitor's prompt, ``program_prompt`` the one VAL prints while a program runs
    (``*``): a driver that meets it says so (``ProgramRunning``) instead of timing out.
    ``prompt_silence_s`` is how long the line must stay quiet after a prompt (or a question) before it
    counts as one: numbers contain ``.`` too, so a prompt is a ``.`` at the start of a line followed by
    silence. ``field_width`` (characters per value in WHERE-style lines, right-aligned; None: values
    separated by blanks) and ``decimals`` let the driver notice dropped characters.

    The WHERE layout: ``where_lines`` the reply's lines in order (``pose_header``, ``pose``,
    ``joint_header``, ``joints``); ``pose_header`` / ``joint_header`` every column the controller prints
    (more than six allowed); ``pose_columns`` / ``joint_columns`` the six the driver reads, by name.

    ``echo``: the controller echoes each character as it is typed (a full-duplex terminal). The driver
    then sends a command without its line end, compares the echo in full, and only then sends the
    line end that executes it; on a difference it sends ``cancel_line`` (VAL-II's CTRL-U, which erases
    the line typed so far) and nothing runs. ``status_speed`` finds the monitor speed in the reply to
    ``STATUS`` (the speed is read back after ``SPEED``).
    """

    name: str = "VAL-II PUMA 260"
    echo: bool = True
    host_eol: str = "\r"
    controller_eol: str = "\r\n"
    prompt: str = "."
    program_prompt: str = "*"
    prompt_silence_s: float = 0.01
    cancel_line: str = "\x15"
    status_speed: str = r"monitor\s+speed\s*[:=]?\s*(?P<pct>\d+(?:\.\d+)?)"
    confirm_question: str = "Are you sure (Y/N)?"
    change_question: str = "Change?"
    yes: str = "Y"
    here_asks_change: bool = True
    pose_header: tuple[str, ...] = ("X", "Y", "Z", "O", "A", "T")
    joint_header: tuple[str, ...] = ("JT1", "JT2", "JT3", "JT4", "JT5", "JT6")
    pose_columns: tuple[str, ...] = ("X", "Y", "Z", "O", "A", "T")
    joint_columns: tuple[str, ...] = ("JT1", "JT2", "JT3", "JT4", "JT5", "JT6")
    where_lines: tuple[str, ...] = ("pose_header", "pose", "joint_header", "joints")
    field_width: int | None = 9
    decimals: int = 2
    command_decimals: int = 3
    name_pattern: str = r"[A-Za-z][A-Za-z0-9_]{0,14}"
    scratch_location: str = "svtgt"
    euler: EulerConvention = OAT_CONVENTIONS["val"]
    errors: tuple[tuple[str, str], ...] = DEFAULT_ERRORS
    commands: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_COMMANDS))

    def __post_init__(self):
        for nm in ("host_eol", "controller_eol"):
            if getattr(self, nm) not in ("\r", "\n", "\r\n"):
                raise ConfigError(f"dialect.{nm}: expected CR, LF or CR LF, got {getattr(self, nm)!r}")
        for nm in ("prompt", "program_prompt"):
            v = getattr(self, nm)
            if len(v) != 1 or not v.isprintable() or v.isspace():
                raise ConfigError(f"dialect.{nm}: expected one printable character, got {v!r}")
        if self.prompt == self.program_prompt:
            raise ConfigError("dialect.program_prompt: must differ from the prompt")
        if len(self.cancel_line) != 1 or self.cancel_line.isprintable() or self.cancel_line in "\r\n":
            raise ConfigError(f"dialect.cancel_line: expected one control character (CTRL-U is '\\x15'), got {self.cancel_line!r}")
        try:
            if "pct" not in re.compile(self.status_speed).groupindex:
                raise ConfigError(f"dialect.status_speed: needs a group (?P<pct>...), got {self.status_speed!r}")
        except re.error as exc:
            raise ConfigError(f"dialect.status_speed: not a regular expression ({exc})") from exc
        if not (0.0 < self.prompt_silence_s <= 1.0):
            raise ConfigError(f"dialect.prompt_silence_s: expected 0 < s <= 1, got {self.prompt_silence_s!r}")
        for nm in ("confirm_question", "change_question"):
            if not getattr(self, nm).rstrip().endswith("?"):
                raise ConfigError(f"dialect.{nm}: a question must end in '?', got {getattr(self, nm)!r}")
        for cols, hdr in (("pose_columns", "pose_header"), ("joint_columns", "joint_header")):
            c, h = getattr(self, cols), getattr(self, hdr)
            if len(c) != 6 or len({n.upper() for n in c}) != 6:
                raise ConfigError(f"dialect.{cols}: expected six distinct names, got {list(c)}")
            missing = [n for n in c if n.upper() not in [x.upper() for x in h]]
            if missing or len({x.upper() for x in h}) != len(h):
                raise ConfigError(f"dialect.{hdr}: expected distinct names including {list(c)}, got {list(h)}")
        if sorted(self.where_lines) != sorted(("pose_header", "pose", "joint_header", "joints")) or \
                self.where_lines.index("pose_header") > self.where_lines.index("pose") or \
                self.where_lines.index("joint_header") > self.where_lines.index("joints"):
            raise ConfigError(f"dialect.where_lines: expected pose_header, pose, joint_header, joints (each header before its values), got {list(self.where_lines)}")
        if self.field_width is not None and not (isinstance(self.field_width, int) and self.field_width >= self.decimals + 3):
            raise ConfigError(f"dialect.field_width: expected a whole number >= decimals + 3 or null, got {self.field_width!r}")
        if not (0 <= self.decimals <= 6 and 0 <= self.command_decimals <= 6):
            raise ConfigError("dialect.decimals / command_decimals: expected 0..6")
        try:
            re.compile(self.name_pattern)
        except re.error as exc:
            raise ConfigError(f"dialect.name_pattern: not a regular expression ({exc})") from exc
        self.validate_name(self.scratch_location)
        for text, cls in self.errors:
            if cls not in ERROR_CLASSES:
                raise ConfigError(f"dialect.errors: {text!r} maps to unknown class {cls!r}; expected one of {', '.join(ERROR_CLASSES)}")
        unknown = set(self.commands) - set(DEFAULT_COMMANDS)
        missing = set(DEFAULT_COMMANDS) - set(self.commands)
        if unknown or missing:
            raise ConfigError(
                f"dialect.commands: unknown {sorted(unknown)} / missing {sorted(missing)}; "
                f"expected exactly {', '.join(DEFAULT_COMMANDS)}"
            )
        for kind, tpl in self.commands.items():
            want = {f for _, f, _, _ in string.Formatter().parse(DEFAULT_COMMANDS[kind]) if f}
            got = {f for _, f, _, _ in string.Formatter().parse(tpl) if f}
            if want != got:
                raise ConfigError(f"dialect.commands.{kind}: {tpl!r} must use the fields {sorted(want)}, got {sorted(got)}")

    # --- configuration -------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, data: dict) -> "ValDialect":
        """A dialect from a mapping of field names (``commands`` is merged over the defaults)."""
        kw = dict(check_keys(data, cls, "dialect"))
        if "euler" in kw:
            if isinstance(kw["euler"], str):
                if kw["euler"] not in OAT_CONVENTIONS:
                    raise ConfigError(f"dialect.euler: {kw['euler']!r} is not one of {', '.join(OAT_CONVENTIONS)} (or give sequence, signs, ...)")
                kw["euler"] = OAT_CONVENTIONS[kw["euler"]]
            else:
                kw["euler"] = _euler_from(kw["euler"])
        if "commands" in kw:
            if not isinstance(kw["commands"], dict):
                raise ConfigError(f"dialect.commands: expected a mapping, got {kw['commands']!r}")
            kw["commands"] = {**DEFAULT_COMMANDS, **{str(k): str(v) for k, v in kw["commands"].items()}}
        for k in ("pose_header", "joint_header", "pose_columns", "joint_columns", "where_lines"):
            if k in kw:
                kw[k] = tuple(str(v) for v in kw[k])
        if "errors" in kw:
            try:
                kw["errors"] = tuple((str(t), str(c)) for t, c in kw["errors"])
            except (TypeError, ValueError):
                raise ConfigError(f"dialect.errors: expected a list of [text, class] pairs, got {kw['errors']!r}") from None
        try:
            return cls(**kw)
        except TypeError as exc:
            raise ConfigError(f"dialect: {exc}") from exc

    def to_dict(self) -> dict:
        d = asdict(self)
        d["euler"] = asdict(self.euler)
        return d

    # --- lines and names -----------------------------------------------------------------------
    def validate_name(self, name: str) -> str:
        """``name`` if it is a valid location name, else ``ConfigError``."""
        if not isinstance(name, str) or not re.fullmatch(self.name_pattern, name):
            raise ConfigError(f"location name {name!r}: expected {self.name_pattern} (a letter, then letters or digits)")
        return name

    def encode_line(self, text: str) -> bytes:
        """One host line as bytes, ended by ``host_eol``."""
        if any(c in text for c in "\r\n") or not text.isascii():
            raise ConfigError(f"command line {text!r}: expected printable ASCII without line breaks")
        return (text + self.host_eol).encode("ascii")

    def number(self, v: float, decimals: int | None = None) -> str:
        """A number as the host writes it (``command_decimals``, trailing zeros dropped) or, with
        ``decimals``, as the controller prints it; never '-0'."""
        d = self.command_decimals if decimals is None else decimals
        v = float(v)
        if not np.isfinite(v):
            raise ConfigError(f"value {v!r}: expected a finite number")
        s = f"{v:.{d}f}"
        if decimals is None and "." in s:  # a command: no trailing zeros (fewer bytes at 9600 baud)
            s = s.rstrip("0").rstrip(".")
        return s[1:] if s.startswith("-") and float(s) == 0 else s

    def command(self, kind: str, **values) -> str:
        """The command line of ``kind`` (a key of ``commands``) with its fields filled in."""
        out = {}
        for k, v in values.items():
            if k == "name":
                out[k] = self.validate_name(v)
            elif k == "joint":
                out[k] = str(int(v))
            else:
                out[k] = self.number(v)
        return self.commands[kind].format(**out)

    @cached_property
    def _command_patterns(self) -> dict[str, re.Pattern]:
        return {kind: _template_regex(tpl, self.name_pattern) for kind, tpl in self.commands.items()}

    def parse_command(self, line: str) -> tuple[str, dict] | None:
        """(kind, fields) of a host line, or None if it matches no template: the simulated controller's
        reading of its input. Values may be given in parentheses or not, as VAL-II's expression syntax
        allows; a parenthesis left open, or a missing argument, is no line at all."""
        for kind, rx in self._command_patterns.items():
            m = rx.fullmatch(line)
            if m:
                fields = {k: m.group(k).strip("() \t") for k in rx.groupindex if not re.fullmatch(r"[gn]\d+_\d+", k)}
                return kind, {k: (v if k == "name" else float(v)) for k, v in fields.items()}
        return None

    def open_prefixes(self) -> dict[str, list[str]]:
        """For each kind of ``PREFIX_SAFE_KINDS`` whose template lets a cut line run: the valid proper
        prefixes of a sample line (location ``p1``, numbers 50 and -10.5, speed 20)."""
        samples = {"speed": {"pct": 20}, "move": {"name": "p1"}, "moves": {"name": "p1"}, "appro": {"name": "p1", "d": 50},
                   "depart": {"d": 50}, "drive": {"joint": 2, "deg": -10.5, "speed": 20}, "ready": {},
                   "define": {"name": "p1", **dict(zip("xyzoat", (350, -10.5, 100, 0, 90, 50)))}}
        out = {kind: self.valid_prefixes(kind, **samples[kind]) for kind in PREFIX_SAFE_KINDS}
        return {k: v for k, v in out.items() if v}

    def valid_prefixes(self, kind: str, **values) -> list[str]:
        """The proper prefixes of the line ``command(kind, **values)`` that this dialect's parser reads
        as a valid line: what a line end put inside the line by noise would make the controller run
        (empty for every kind of ``PREFIX_SAFE_KINDS`` with the default templates)."""
        line = self.command(kind, **values)
        return [line[:k] for k in range(1, len(line)) if line[:k].strip() and self.parse_command(line[:k]) is not None]

    # --- tables of values ----------------------------------------------------------------------
    def format_header(self, names) -> str:
        w = self.field_width
        return "".join(f"{n:>{w}}" for n in names) if w else "  ".join(names)

    def format_values(self, values) -> str:
        w = self.field_width
        parts = [self.number(v, self.decimals) for v in values]
        return "".join(f"{p:>{w}}" for p in parts) if w else "  ".join(parts)

    def parse_header(self, line: str, names) -> None:
        """Check a header line (e.g. ``X Y Z O A T``, right-aligned in ``field_width`` columns);
        ``ProtocolError`` if it differs."""
        w = self.field_width
        if [t.upper() for t in line.split()] != [n.upper() for n in names] or (w and len(line.rstrip()) != w * len(names)):
            raise ProtocolError(f"expected the header {' '.join(names)!r}, got {line.rstrip()!r}")

    def parse_values(self, line: str, n: int = 6) -> tuple[float, ...]:
        """``n`` numbers of a values line; ``ProtocolError`` on a wrong count, width or format."""
        body = line.rstrip()
        w = self.field_width
        if w:
            if len(body) != n * w:
                raise ProtocolError(f"expected {n} fields of {w} characters, got {len(body)} characters: {line!r}")
            toks = [body[i * w : (i + 1) * w].strip() for i in range(n)]
        else:
            toks = body.split()
        rx = rf"-?\d+\.\d{{{self.decimals}}}" if self.decimals else r"-?\d+"
        if len(toks) != n or not all(re.fullmatch(rx, t) for t in toks):
            raise ProtocolError(f"expected {n} numbers with {self.decimals} decimals, got {line!r}")
        return tuple(float(t) for t in toks)

    def _pick(self, values, header, columns) -> tuple[float, ...]:
        up = [h.upper() for h in header]
        return tuple(values[up.index(c.upper())] for c in columns)

    def parse_where(self, lines: list[str]) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(pose x..t, joints JT1..JT6) of WHERE's reply lines, as ``where_lines`` lays them out;
        ``ProtocolError`` on a different layout."""
        if len(lines) != len(self.where_lines):
            raise ProtocolError(f"WHERE: expected {len(self.where_lines)} lines ({', '.join(self.where_lines)}), got {lines!r}")
        by = dict(zip(self.where_lines, lines))
        self.parse_header(by["pose_header"], self.pose_header)
        self.parse_header(by["joint_header"], self.joint_header)
        pose = self._pick(self.parse_values(by["pose"], len(self.pose_header)), self.pose_header, self.pose_columns)
        joints = self._pick(self.parse_values(by["joints"], len(self.joint_header)), self.joint_header, self.joint_columns)
        return pose, joints

    def parse_location(self, lines: list[str]) -> tuple[float, ...]:
        """The pose (x..t) of a location's reply (its pose header and values line)."""
        if len(lines) != 2:
            raise ProtocolError(f"expected a pose header and its values, got {lines!r}")
        self.parse_header(lines[0], self.pose_header)
        return self._pick(self.parse_values(lines[1], len(self.pose_header)), self.pose_header, self.pose_columns)

    def speed_of_status(self, lines: list[str]) -> float:
        """The monitor speed (percent) in the reply to STATUS; ``ProtocolError`` if absent or twice."""
        found = [m.group("pct") for ln in lines for m in [re.search(self.status_speed, ln, re.IGNORECASE)] if m]
        if len(found) != 1:
            raise ProtocolError(f"STATUS: expected one monitor speed ({self.status_speed}), got {lines!r}")
        return float(found[0])

    # --- errors and questions ------------------------------------------------------------------
    @staticmethod
    def error_text_of(line: str) -> str | None:
        """The text of an error line ``*text*``, or None."""
        s = line.strip()
        if len(s) >= 2 and s[0] == "*" and s[-1] == "*":
            return s.strip("*").strip()
        return None

    @cached_property
    def _error_patterns(self) -> list[tuple[re.Pattern, type[ControllerError]]]:
        out = []
        for text, cls in sorted(self.errors, key=lambda tc: -len(tc[0])):
            rx = re.sub(r"\\\{\w+\\\}", r"\\d+", re.escape(text))
            rx = rx.replace(r"\ ", r"\s+")
            out.append((re.compile(rx, re.IGNORECASE), ERROR_CLASSES[cls]))
        return out

    def error_for(self, text: str, command: str | None = None) -> ControllerError:
        """The typed exception for a controller error text (``ControllerError`` if the table lacks it)."""
        for rx, cls in self._error_patterns:
            if rx.search(text):
                return cls(text, command)
        return ControllerError(text, command)

    def error_text(self, cls_name: str, **values) -> str:
        """The controller's wording for an error class (the simulator prints it)."""
        for text, cls in self.errors:
            if cls == cls_name:
                return text.format(**values) if values else text
        raise ConfigError(f"dialect.errors: no text for {cls_name!r}")

    def is_question(self, text: str, question: str) -> bool:
        return " ".join(text.split()).lower().endswith(" ".join(question.split()).lower())

    # --- poses -----------------------------------------------------------------------------------
    def pose_to_H(self, pose) -> np.ndarray:
        """(4, 4) transform of a controller pose (x, y, z, o, a, t) in mm and degrees."""
        return H_from_xyzoat(pose, self.euler)

    def H_to_pose(self, H) -> tuple[float, ...]:
        """Controller pose (x, y, z, o, a, t) of a (4, 4) transform."""
        return xyzoat_from_H(H, self.euler)


def load_dialect(path) -> ValDialect:
    """A dialect from a YAML file of ``ValDialect`` fields; raises ``ConfigError`` naming the problem.
    Templates that let a cut line run (``ValDialect.open_prefixes``) are allowed (a controller may not
    read parenthesised values) but logged as a warning that names them."""
    try:
        d = ValDialect.from_dict(read_yaml(path, "dialect"))
    except ConfigError as exc:
        raise ConfigError(f"{Path(path).name}: {exc}") from None
    open_ = d.open_prefixes()
    if open_:
        _log.warning("%s: a line end that noise puts inside these lines would run their first part (issue 32): %s",
                     Path(path).name, "; ".join(f"{k}: {v!r}" for k, v in open_.items()))
    return d
