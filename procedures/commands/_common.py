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


def print_json(obj) -> None:
    json.dump(obj, sys.stdout, indent=None, separators=(",", ":"), allow_nan=False)
    sys.stdout.write("\n")
    sys.stdout.flush()
