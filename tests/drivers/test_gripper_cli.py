"""``selfview gripper`` against the simulated terminal: actions, JSON, io maps, exit codes."""

from __future__ import annotations

import json
import socket

import pytest

from selfview.mocks.valve_terminal import ValveTerminal
from selfview.procedures.cli import EXIT_CONFIG, EXIT_DEVICE, main


@pytest.fixture
def terminal():
    with ValveTerminal(travel_s=0.02) as t:
        yield t


def test_close_open_state(terminal, capsys):
    assert main(["gripper", "--url", terminal.url, "close", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["state"] == "closed" and out["closed_sensor"] and not out["open_sensor"]
    assert out["valve_outputs"] == {"open": False, "close": True} and out["action"] == "close"
    assert terminal.position == 0.0
    assert main(["gripper", "--url", terminal.url, "state"]) == 0
    assert capsys.readouterr().out.strip() == "closed"
    assert main(["gripper", "--url", terminal.url, "open"]) == 0
    assert capsys.readouterr().out.strip() == "open"
    assert main(["gripper", "--url", terminal.url, "safe"]) == 0
    assert terminal.valve_outputs == {"open": False, "close": False}


def test_io_map_file(tmp_path, capsys):
    path = tmp_path / "festo.yaml"
    path.write_text("open_valve: 40001.0\nclose_valve: 40001.1\nopen_sensor: 30001.0\nclosed_sensor: 30001.1\n")
    from selfview.drivers.pneumatic_gripper import IoMap, Point

    m = IoMap(open_valve=Point.parse("hr:0.0"), close_valve=Point.parse("hr:0.1"),
              open_sensor=Point.parse("ir:0.0"), closed_sensor=Point.parse("ir:0.1"))
    with ValveTerminal(io_map=m, travel_s=0.02) as t:
        assert main(["gripper", "--url", t.url, "--io-map", str(path), "close"]) == 0
        assert t.table("holding_register")[0] == 0b10
    bad = tmp_path / "bad.yaml"
    bad.write_text("open_valve: 40001.0\nclose_valve: di:3\n")
    assert main(["gripper", "--url", "modbus-tcp://127.0.0.1:1", "--io-map", str(bad), "state"]) == EXIT_CONFIG
    assert "bad.yaml" in capsys.readouterr().err


def test_exit_codes(terminal, capsys):
    # a port taken from the OS and kept bound without listening: connections to it are refused, and no
    # other program can take it meanwhile
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
        assert main(["gripper", "--url", f"modbus-tcp://127.0.0.1:{port}?unit=1", "state"]) == EXIT_DEVICE
    assert "connection refused" in capsys.readouterr().err
    assert main(["gripper", "--url", "modbus://127.0.0.1", "state"]) == EXIT_CONFIG
    terminal.stick_jaw()
    assert main(["gripper", "--url", terminal.url, "--timeout", "0.1", "close"]) == EXIT_DEVICE
    assert "still 'open'" in capsys.readouterr().err


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT"])
@pytest.mark.parametrize("action", ["close", "open"])
def test_a_signal_during_a_jaw_stroke_leaves_the_valve_safe_and_says_so(sig, action):
    import os
    import signal
    import subprocess
    import sys
    import time

    from tests.conftest import REPO

    signum = getattr(signal, sig)
    # a stuck jaw never confirms and no watchdog drops the outputs: only the command can make them safe
    with ValveTerminal(travel_s=0.02, watchdog_s=None, initial="closed" if action == "open" else "open") as t:
        t.stick_jaw()
        env = dict(os.environ, PYTHONPATH=str(REPO))
        proc = subprocess.Popen([sys.executable, "-m", "selfview.procedures.cli", "gripper", "--url", t.url,
                                 "--timeout", "60", action], cwd=REPO, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        try:
            end = time.monotonic() + 60
            while not t.valve_outputs[action] and proc.poll() is None and time.monotonic() < end:
                time.sleep(0.01)
            assert t.valve_outputs[action], "the command never energised the valve"
            proc.send_signal(signum)
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
        assert proc.returncode == 128 + signum, err
        assert t.valve_outputs == {"open": False, "close": False}, err
        assert "valve set to its safe state" in err and "Traceback" not in err, err
        assert "had NOT ended" not in err, err  # the jaw wait ended at the signal, not at its own timeout
