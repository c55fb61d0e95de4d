"""Helpers shared by the command modules."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from selfview.files.cell import Cell, default_cell_path, load_cell


def add_cell_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--cell",
        default=None,
        metavar="CELL.yaml",
        help="cell description (default: the reference cell shipped with selfview)",
    )


def load_cell_arg(args) -> Cell:
    return load_cell(args.cell or default_cell_path())


def _finite(obj):
    """NaN and infinities become null: JSON has no such numbers."""
    import math

    import numpy as np

    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def print_json(obj) -> None:
    """One JSON object on one line of stdout (NaN written as null)."""
    json.dump(_finite(obj), sys.stdout, indent=None, separators=(",", ":"), allow_nan=False)
    sys.stdout.write("\n")
    sys.stdout.flush()


def number(text: str, what: str, *, integer: bool = False, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False) -> float | int:
    """A number a person typed (``selfview.files.io_safe.parse_number``: ASCII digits, finite, in range), or
    ``argparse.ArgumentTypeError`` naming ``what``, which the command line turns into exit 2."""
    from selfview.files.io_safe import parse_number

    try:
        return parse_number(text, integer=integer, lo=lo, hi=hi, lo_open=lo_open)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"{what}: {exc}" if what else str(exc)) from None


def numeric(*, integer: bool = False, lo: float | None = None, hi: float | None = None, lo_open: bool = False,
            name: str = "number"):
    """An argparse ``type`` for a numeric option: ``number`` with this range (argparse names the option)."""
    def parse(text: str):
        return number(text, "", integer=integer, lo=lo, hi=hi, lo_open=lo_open)
    parse.__name__ = name
    return parse


#: The numeric options' types: a timeout or duration (longer than an hour is a typing error, and an
#: infinite wait never ends), a seed, a TCP port, a count, a non-negative time factor.
SECONDS = numeric(lo=0, lo_open=True, hi=3600, name="seconds")
SECONDS_OR_ZERO = numeric(lo=0, hi=3600, name="seconds")
SEED = numeric(integer=True, lo=0, hi=2**32 - 1, name="seed")
PORT = numeric(integer=True, lo=0, hi=65535, name="port")
COUNT = numeric(integer=True, lo=1, hi=1_000_000, name="count")
FACTOR = numeric(lo=0, hi=1000, name="factor")
BAUD = numeric(integer=True, lo=50, hi=4_000_000, name="baud rate")


def serve_until(url: str, duration_s: float | None) -> None:
    """Print ``url`` as the first line of stdout, then wait until ``duration_s`` has passed (forever if
    None) or Ctrl-C; the caller stops its server in ``finally``."""
    import time

    print(url, flush=True)
    end = None if duration_s is None else time.monotonic() + duration_s
    try:
        while end is None or time.monotonic() < end:
            time.sleep(0.2 if end is None else max(0.0, min(0.2, end - time.monotonic())))
    except KeyboardInterrupt:
        pass


def output_file(value: str, option: str, suffixes: tuple[str, ...] = ()) -> Path:
    """The file an option names for writing, checked before anything runs (nothing moves for a name that
    cannot be written): a name (not empty, not a folder), in a folder that exists, ending in one of
    ``suffixes`` when given. ``ConfigError`` (exit 3) naming the option and the value otherwise."""
    from selfview.errors import ConfigError

    shown = repr(value) if not value else value
    if not value or value.endswith("/") or Path(value).name in ("", ".", ".."):
        raise ConfigError(f"{option} {shown}: expected a file name")
    out = Path(value)
    if out.is_dir():
        raise ConfigError(f"{option} {value}: is a folder; expected a file name")
    if not out.parent.is_dir():
        raise ConfigError(f"{option} {value}: the folder {str(out.parent)!r} does not exist")
    if suffixes and out.suffix.lower() not in suffixes:
        raise ConfigError(f"{option} {value}: expected a {' or '.join(suffixes)} file name")
    return out


def write_image(path, image, what: str = "--out") -> None:
    """Write a picture (``selfview.files.io_safe.write_picture``: encoded in memory, written atomically);
    ``ConfigError`` naming ``what`` and the path if it cannot be written."""
    from selfview.errors import ConfigError
    from selfview.files.io_safe import write_picture

    write_picture(path, image, error=ConfigError, what=f"picture ({what})")


def add_view_arguments(p: argparse.ArgumentParser) -> None:
    """``--view [PORT]`` and ``--view-linger S``: the live view (``selfview.procedures.view.viewing``)."""
    g = p.add_argument_group("live view", "a page in the browser on 127.0.0.1 showing the run as it goes")
    g.add_argument("--view", nargs="?", type=PORT, const=0, default=None, metavar="PORT",
                   help="serve the live view (a free port, or PORT); its address is printed on stderr")
    g.add_argument("--view-linger", type=SECONDS_OR_ZERO, default=0.0, metavar="S",
                   help="keep serving the final state S seconds after the command is done (default 0)")
