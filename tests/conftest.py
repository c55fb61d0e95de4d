"""Shared fixtures: where the shared reference material is, the reference cell, a seeded world."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


def shared_dir() -> Path:
    """The shared material beside the repository (``../shared``), or ``$SELFVIEW_SHARED``."""
    env = os.environ.get("SELFVIEW_SHARED")
    p = Path(env) if env else REPO.parent / "shared"
    if not (p / "spec" / "cell.yaml").is_file():
        raise RuntimeError(f"shared material not found at {p}; set SELFVIEW_SHARED to its folder")
    return p


@pytest.fixture(scope="session")
def shared() -> Path:
    return shared_dir()


@pytest.fixture(scope="session")
def cell_path(shared) -> Path:
    return shared / "spec" / "cell.yaml"


@pytest.fixture(scope="session")
def cell(cell_path):
    from selfview.cell import load_cell

    return load_cell(cell_path)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
