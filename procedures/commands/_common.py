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
