"""Fixtures: the reference material in tests/data, the reference cell, a seeded world."""

from __future__ import annotations

import atexit
import os
import resource
import shutil
import signal
import tempfile
from pathlib import Path

# One BLAS thread unless the run says otherwise (before numpy loads), as the command line has it
# (procedures/cli.py): the tests that run a command in this process otherwise fit with OpenBLAS's threads,
# which only contend on a loaded machine (the BoofCV photographs' intrinsics command: 47 s with them,
# 9 s without, at load 7 on 2 cores).
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def travel_bound_deg(stopped_after_s: float) -> float:
    """How far [deg] an arm sent to READY may turn in ``stopped_after_s`` seconds before it stops: READY at SPEED 5
    from the simulated world's start turns JT4 fastest, 25.6 deg/s at its peak (the simulated controller's joint
    motion: 180 deg in 7.0 s), plus 0.5 deg for a test's 5 ms polling and the controller's step. A fixed bound
    (3 deg, about 0.1 s) failed on a loaded machine: 3.99 deg (0.16 s at that speed) from a test's reading of
    the pose to the stop, which still came within 0.5 s of the signal."""
    return 25.6 * stopped_after_s + 0.5


DATA = REPO / "tests" / "data"  # reference material copied into the repository: see its README


# the test run's own lock folder (mode 0700, removed at the end): a record that a killed test program leaves
# (a motion, an energised valve) never meets the devices of another run on this machine
_LOCKS = tempfile.mkdtemp(prefix="selfview-test-locks-")
os.environ["SELFVIEW_LOCK_DIR"] = _LOCKS
atexit.register(shutil.rmtree, _LOCKS, ignore_errors=True)


def _ignore(signum, frame):
    """Ignore the signal here, as the harness asked, without handing the ignoring down to the children."""


# A harness that starts the suite as a background job (SIGINT and SIGQUIT ignored) or under nohup (SIGHUP
# ignored) hands those ignored signals down to every program the tests start, and selfview rightly keeps an
# inherited ignored signal ignored (a calibration under nohup goes on when the terminal closes). The tests that
# send a program Ctrl-C or a hang-up expect the dispositions a terminal gives. So the suite's own process keeps
# ignoring what it was told to ignore, through a handler that does nothing, which exec resets to the default in
# each child. (The tests of an inherited ignored signal set SIG_IGN in their child themselves.)
for _sig in (signal.SIGINT, signal.SIGQUIT, signal.SIGHUP, signal.SIGTERM, signal.SIGTSTP):
    if signal.getsignal(_sig) == signal.SIG_IGN:
        signal.signal(_sig, _ignore)

# No core files: a test program killed by SIGQUIT (a test of a stop that failed) is the test's failure, not a
# core image left in the folder the suite runs in. Inherited by every program the tests start.
resource.setrlimit(resource.RLIMIT_CORE, (0, resource.getrlimit(resource.RLIMIT_CORE)[1]))


class SignalEscaped(Exception):
    """A termination signal reached the test process outside any handler of the code under test."""


def _escaped(signum, frame):
    raise SignalEscaped(f"{signal.Signals(signum).name} reached the test process: the code under test did not take it")


@pytest.fixture(autouse=True)
def _signals_that_escape_fail_the_test():
    """The in-process signal tests send SIGTERM, SIGHUP or SIGQUIT to this process for the code under test
    (the engine, the command line) to take. Where that code fails to take one, the signal's default action
    would end the whole run (or selfview's own handler would stop it as a Ctrl-C): here it fails that one test
    instead (``SignalEscaped``). The handler is this process's own, so ``selfview.drivers.signals.install`` leaves it
    alone, as it leaves a lab script's own handler; SIGINT stays pytest's (Ctrl-C ends a test run)."""
    sigs = [s for s in (signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT) if signal.getsignal(s) is not _ignore]
    old = {s: signal.signal(s, _escaped) for s in sigs}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h if h is not None else signal.SIG_DFL)


@pytest.fixture(scope="session")
def willson_dir() -> Path:
    """Reg Willson's Tsai v3.0b3 data and logs, shipped as package data (the report reads them too)."""
    return REPO / "selfview" / "data" / "reference" / "tsai-willson"


@pytest.fixture(scope="session")
def niftycal_dir() -> Path:
    """NiftyCal's real dot-grid detections."""
    return DATA / "niftycal-dots"


@pytest.fixture(scope="session")
def cell_path() -> Path:
    """The reference cell exactly as the project's conventions publish it (``tests/data/spec/cell.yaml``)."""
    return DATA / "spec" / "cell.yaml"


@pytest.fixture(scope="session")
def cell(cell_path):
    from selfview.files.cell import load_cell

    return load_cell(cell_path)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)
