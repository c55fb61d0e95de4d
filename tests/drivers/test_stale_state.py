"""A program that died holding a device (SIGKILL, a crash) in the middle of something that goes on without it:
the next program notices at connect, says what, sends nothing, and goes on once ``devices --reset`` ran."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from selfview.drivers._ownership import StaleState
from selfview.mocks.val_controller import ValController
from selfview.mocks.valve_terminal import ValveTerminal
from selfview.mocks.world import SimWorld
from selfview.procedures.cli import EXIT_DEVICE, main
from tests.conftest import REPO


@pytest.fixture(autouse=True)
def lock_dir(tmp_path, monkeypatch):
    d = tmp_path / "locks"
    d.mkdir(mode=0o700)
    monkeypatch.setenv("SELFVIEW_LOCK_DIR", str(d))
    return d


def _killed_during(argv, started):
    proc = subprocess.Popen([sys.executable, "-m", "selfview.procedures.cli", *argv], cwd=REPO,
                            env=dict(os.environ, PYTHONPATH=str(REPO)), stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        t0 = time.monotonic()
        while not started() and time.monotonic() - t0 < 60:
            time.sleep(0.01)
        assert started(), "the command never started"
        proc.send_signal(signal.SIGKILL)  # no handler, no cleanup: as a power cut of the host
        proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


def test_a_host_killed_during_a_motion_is_noticed_at_the_next_connect(cell, capsys):
    from selfview.drivers.puma_val_serial import PumaVAL

    with ValController(SimWorld(cell, seed=2), time_scale=1.0, calibrated=True, speed_pct=5.0) as c:
        c.start_pty()
        _killed_during(["robot", "--url", c.url, "ready"], c.moving.is_set)
        n = len(c.received)
        assert main(["robot", "--url", c.url, "where"]) == EXIT_DEVICE
        err = capsys.readouterr().err
        assert "ended without letting go while a motion was running (DO READY)" in err and "--reset" in err, err
        assert len(c.received) == n  # nothing was sent
        with pytest.raises(StaleState):  # a lab script too, until the operator resets
            PumaVAL(c.url).connect()
        main(["devices", "--real", "--robot", c.url, "--reset"])
        assert "ABORT" in c.received[n:] and not c.moving.is_set()
        capsys.readouterr()
        assert main(["robot", "--url", c.url, "where"]) == 0, capsys.readouterr().err


def test_a_host_killed_with_the_valve_energised_is_noticed_at_the_next_connect(capsys):
    with ValveTerminal(travel_s=0.02, watchdog_s=None) as t:
        t.stick_jaw()
        _killed_during(["gripper", "--url", t.url, "--timeout", "60", "close"], lambda: t.valve_outputs["close"])
        assert main(["gripper", "--url", t.url, "state"]) == EXIT_DEVICE
        err = capsys.readouterr().err
        assert "while the valve was energised (close on)" in err and "--reset" in err, err
        assert t.valve_outputs == {"open": False, "close": True}
        main(["devices", "--real", "--gripper", t.url, "--reset"])
        assert t.valve_outputs == {"open": False, "close": False}
        capsys.readouterr()
        assert main(["gripper", "--url", t.url, "state"]) == 0, capsys.readouterr().err


def test_a_program_that_ends_normally_leaves_no_record(capsys):
    with ValveTerminal(travel_s=0.02, watchdog_s=None) as t:
        assert main(["gripper", "--url", t.url, "close"]) == 0  # the valve stays energised, as asked
        assert t.valve_outputs == {"open": False, "close": True}
        assert main(["gripper", "--url", t.url, "state"]) == 0, capsys.readouterr().err


def test_the_energised_valve_is_recorded_before_the_write_that_energises_it(lock_dir):
    """A host that dies between the terminal taking the write and the driver hearing its answer (under load
    that window is wide) must still leave the record: the record is written ahead of the write."""
    from selfview.drivers.pneumatic_gripper import PneumaticGripper

    with ValveTerminal(travel_s=0.02, watchdog_s=None) as t, PneumaticGripper(t.url, poll_s=None) as g:
        seen = []
        for name in ("write_coil", "write_register", "mask_write_register"):
            real = getattr(g.link, name)

            def spy(*a, _real=real, **k):
                seen.append(" ".join(p.read_text() for p in lock_dir.iterdir() if p.is_file()))
                return _real(*a, **k)

            setattr(g.link, name, spy)
        g.close_jaws()
        assert seen and "busy: the valve was energised (close on)" in seen[-1], seen
        g.open_jaws()
        assert "busy: the valve was energised (open on)" in seen[-1], seen
