"""Helpers shared by the command modules."""

from __future__ import annotations

import argparse
import json
import sys

from selfview.cell import Cell, default_cell_path, load_cell


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


def positive_seconds(text: str) -> float:
    """argparse type: a number of seconds > 0."""
    v = float(text)
    if not v > 0:
        raise ValueError(text)
    return v


def check_port(port: int, who: str) -> None:
    if not 0 <= port <= 65535:
        raise SystemExit(f"selfview {who}: --port {port} out of 0..65535")


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


def write_image(path, image, what: str = "--out") -> None:
    """Write a picture with OpenCV; ``ConfigError`` naming ``what`` if it cannot be written."""
    import cv2

    from selfview.errors import ConfigError

    try:
        ok = cv2.imwrite(str(path), image)
    except cv2.error as exc:
        raise ConfigError(f"{what} {path}: cannot write the picture ({exc})") from exc
    if not ok:
        raise ConfigError(f"{what} {path}: cannot write the picture (no such folder, or an extension OpenCV cannot write)")
