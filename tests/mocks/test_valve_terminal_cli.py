"""``selfview mock gripper`` as an operator starts it: URL first on stdout, serving until stopped."""

from __future__ import annotations

import selectors
import signal
import subprocess
import sys
from pathlib import Path

from selfview.drivers.pneumatic_gripper import PneumaticGripper

REPO = Path(__file__).resolve().parents[2]


def first_line(proc: subprocess.Popen, timeout_s: float) -> str:
    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    if not sel.select(timeout_s):
        raise AssertionError(f"no URL on stdout within {timeout_s} s")
    return proc.stdout.readline().strip()


def test_mock_gripper_serves_until_interrupted():
    proc = subprocess.Popen(
        [sys.executable, "-m", "selfview.procedures.cli", "mock", "gripper", "--duration", "60", "--travel", "0.02"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        url = first_line(proc, 30.0)
        assert url.startswith("modbus-tcp://127.0.0.1:") and url.endswith("?unit=1")
        with PneumaticGripper(url) as g:
            assert g.close_jaws() == "closed" and g.open_jaws() == "open"
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0
        assert "2 strokes" in err
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


def test_mock_gripper_duration_and_rtu():
    proc = subprocess.Popen(
        [sys.executable, "-m", "selfview.procedures.cli", "mock", "gripper", "--duration", "0.5", "--rtu"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        url = first_line(proc, 30.0)
        assert url.startswith("modbus-rtu+socket://127.0.0.1:")
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


def test_library_log_lines_only_with_verbose():
    """pymodbus logs each lost reply (and dumps frames) on its own; the operator sees the command's error."""
    from selfview.mocks.valve_terminal import ValveTerminal

    with ValveTerminal() as t:
        t.set_silent()
        errs = []
        for verbose in ([], ["-v"]):
            r = subprocess.run([sys.executable, "-m", "selfview.procedures.cli", *verbose, "gripper", "--url", t.url,
                                "--request-timeout", "0.1", "--retries", "0", "state"],
                               cwd=REPO, capture_output=True, text=True, timeout=60)
            assert r.returncode == 4 and "no reply within 0.1 s" in r.stderr
            errs.append(r.stderr)
    assert "pymodbus" not in errs[0] and len(errs[0].strip().splitlines()) == 2
    assert "pymodbus" in errs[1]
