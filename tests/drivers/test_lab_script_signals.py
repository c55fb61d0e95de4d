"""A lab script driving the devices itself (no command line, no engine in the main thread): a termination
signal still stops the arm (ABORT) and leaves the valve safe, whichever thread drives them; a signal the
script inherited as ignored (nohup) stays ignored."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from selfview.mocks.val_controller import ValController
from selfview.mocks.valve_terminal import ValveTerminal
from selfview.mocks.world import SimWorld
from tests.conftest import REPO, travel_bound_deg

MAIN = """
import sys
from selfview.drivers.puma_val_serial import PumaVAL
from selfview.drivers.pneumatic_gripper import PneumaticGripper
with PumaVAL(sys.argv[1]) as robot, PneumaticGripper(sys.argv[2], poll_s=None) as gripper:
    gripper.close_jaws()
    robot.ready()
print("finished", flush=True)
"""

WORKER = """
import sys, threading
from selfview.drivers.puma_val_serial import PumaVAL
from selfview.drivers.pneumatic_gripper import PneumaticGripper
from selfview.procedures.engine import CellDevices, Engine, Step

def work():
    robot, gripper = PumaVAL(sys.argv[1]), PneumaticGripper(sys.argv[2], poll_s=None)
    robot.connect(); gripper.connect()
    steps = [Step("gripper", {"state": "closed"}), Step("ready")]
    try:
        Engine(CellDevices(robot=robot, gripper=gripper)).run(lambda e: [e.execute(s) for s in steps], steps)
    finally:
        robot.close(); gripper.close()

t = threading.Thread(target=work)
t.start()
t.join()
print("finished", flush=True)
"""


def _run(script, sig, *, ignored=False, cell=None, locks=None):
    """The script against a slow simulated arm and a valve terminal; ``sig`` sent once the arm moves.
    Returns (return code, stderr, controller's received commands, joints at the signal, joints after,
    valve outputs, seconds from the signal to the arm's stop)."""
    with ValController(SimWorld(cell, seed=2), time_scale=1.0, calibrated=True, speed_pct=5.0) as c, \
            ValveTerminal(travel_s=0.02, watchdog_s=None) as t:
        c.start_pty()
        # its own lock folder: a script killed with the arm moving leaves a record there for the next one
        env = dict(os.environ, PYTHONPATH=str(REPO), SELFVIEW_LOCK_DIR=str(locks))

        def pre():
            if ignored:
                signal.signal(sig, signal.SIG_IGN)

        proc = subprocess.Popen([sys.executable, "-c", script, c.url, t.url], cwd=REPO, env=env, preexec_fn=pre,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert c.moving.wait(60.0), "the arm never started moving"
            time.sleep(0.3)
            valve_before = t.valve_outputs
            t0 = time.monotonic()  # before the pose is read: a stall of this thread counts in stopped_after
            q0 = c.joints
            proc.send_signal(sig)
            while c.moving.is_set() and time.monotonic() - t0 < 3.0:
                time.sleep(0.005)
            stopped_after = time.monotonic() - t0
            q1 = c.joints
            if ignored:
                c.moving.clear()
                proc.send_signal(signal.SIGKILL)  # it went on moving: end the test here
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
        assert valve_before == {"open": False, "close": True}
        return proc.returncode, out, err, list(c.received), q0, q1, t.valve_outputs, stopped_after


@pytest.mark.parametrize("where", ["main", "worker"])
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP], ids=lambda s: signal.Signals(s).name)
def test_a_termination_signal_stops_the_arm_and_makes_the_valve_safe_in_any_thread(cell, where, sig, tmp_path):
    code, out, err, received, q0, q1, valve, stopped_after = _run(MAIN if where == "main" else WORKER, sig, cell=cell,
                                                                  locks=tmp_path)
    assert "ABORT" in received, (received[-5:], err)
    assert stopped_after < 1.0, f"the arm stopped {stopped_after:.2f} s after the signal"
    # no farther than the arm's peak speed for the time it took to stop (travel_bound_deg)
    assert np.abs(q1 - q0).max() < travel_bound_deg(stopped_after), stopped_after
    assert valve == {"open": False, "close": False}, err
    assert code == -sig, err  # it ends by the signal, as an unhandled one would (128 + N in a shell)
    assert "finished" not in out


def test_a_signal_inherited_as_ignored_stays_ignored(cell, tmp_path):
    code, out, err, received, q0, q1, valve, _ = _run(MAIN, signal.SIGHUP, ignored=True, cell=cell, locks=tmp_path)
    assert "ABORT" not in received, err
    assert np.abs(q1 - q0).max() > 6.0  # the arm went on (SIGKILL ended the test)
    assert valve == {"open": False, "close": True}


def test_a_device_a_signal_could_not_stop_is_refused_when_watched():
    """``signals.watch`` takes a robot (abort_now, wait_motion_end) or a gripper (interrupt, safe): half of
    one, or neither, is a TypeError naming what is missing, not a failure in the stop's helper thread."""
    from selfview.drivers import signals

    class HalfRobot:
        def abort_now(self):
            return None

    class HalfGripper:
        def interrupt(self):
            pass

    robot, gripper, other = HalfRobot(), HalfGripper(), object()
    with pytest.raises(TypeError, match=r"abort_now\(\) but no wait_motion_end\(\)"):
        signals.watch(robot)
    with pytest.raises(TypeError, match=r"interrupt\(\) but no safe\(\)"):
        signals.watch(gripper)
    with pytest.raises(TypeError, match="neither a robot"):
        signals.watch(other)
    assert not any(d in (robot, gripper) for d in signals._devices())
