"""The ``selfview mock robot`` and ``selfview robot`` commands, end to end."""

from __future__ import annotations

import json
import select
import signal
import subprocess
import sys

import numpy as np
import pytest

from selfview.errors import DeviceError, ProtocolError
from selfview.procedures.cli import main
from tests.conftest import REPO, travel_bound_deg


@pytest.fixture
def mock_robot():
    """``selfview mock robot --link tcp --duration 5`` in a subprocess; yields the URL of its first line."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "selfview.procedures.cli", "mock", "robot", "--link", "tcp", "--duration", "5", "--time-scale", "0.02"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 30.0)
        assert ready, "the mock printed no URL within 30 s"
        url = proc.stdout.readline().strip()
        yield url, proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        proc.stdout.close()
        proc.stderr.close()


def run_json(capsys, *argv) -> dict:
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


def test_mock_robot_and_robot_where_json(mock_robot, capsys):
    url, proc = mock_robot
    assert url.startswith("socket://127.0.0.1:")
    out = run_json(capsys, "robot", "--url", url, "where", "--json")
    assert out["command"] == "where"
    # the simulated world starts with the gripper 200 mm above the plate centre, pointing down
    assert [out["where"]["pose"][k] for k in "xyz"] == pytest.approx([350.0, 0.0, 200.0], abs=0.01)
    assert len(out["where"]["joints"]) == 6 and len(out["where"]["base_H_T"]) == 4

    assert main(["robot", "--url", url, "calibrate"]) == 0
    capsys.readouterr()
    out = run_json(capsys, "robot", "--url", url, "move", "above", "--json")
    assert out["where"]["pose"]["z"] == pytest.approx(80.0, abs=0.01)
    out = run_json(capsys, "robot", "--url", url, "moves", "340", "10", "90", "90", "90", "0", "--json")
    assert [out["where"]["pose"][k] for k in "xyz"] == pytest.approx([340.0, 10.0, 90.0], abs=0.01)

    proc.send_signal(signal.SIGINT)
    assert proc.wait(10) == 0
    assert "received" in proc.stderr.read()


def test_robot_cli_reports_an_unreachable_controller(capsys):
    import socket

    # a port the OS gave us, kept bound and not listening: a connection is refused, deterministically
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as held:
        held.bind(("127.0.0.1", 0))
        port = held.getsockname()[1]
        assert main(["robot", "--url", f"socket://127.0.0.1:{port}", "--timeout", "0.2", "where"]) == 4
    assert "cannot open" in capsys.readouterr().err


def test_robot_cli_pty_in_process(cell, capsys):
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.world import SimWorld

    with ValController(SimWorld(cell, seed=2), time_scale=0.0, calibrated=True) as c:
        c.start_pty()
        out = run_json(capsys, "robot", "--url", c.url, "drive", "1", "5", "10", "--json")
        assert out["where"]["joints"][0] == pytest.approx(c.joints[0], abs=0.006)
        out = run_json(capsys, "robot", "--url", c.url, "point", "plate", "--json")
        assert out["location"]["pose"][2] == pytest.approx(16.0)
        assert main(["robot", "--url", c.url, "here", "h1"]) == 0
        assert "h1:" in capsys.readouterr().out
        assert "H1" in c.locations()
        # refused before sending: exit 4 with the reason; a malformed number: exit 3
        assert main(["robot", "--url", c.url, "speed", "90"]) == 4
        assert "nothing was sent" in capsys.readouterr().err
        assert main(["robot", "--url", c.url, "move", "350", "0", "x", "0", "180", "0"]) == 2
        assert "MOVE Z: not a number in ASCII digits" in capsys.readouterr().err
        assert main(["robot", "--url", c.url, "--max-speed", "90", "speed", "90"]) == 0
        assert "SPEED 90" in capsys.readouterr().out
        assert c.speed_pct == 90
    assert [ln for ln in c.received if ln.startswith("SPEED")] == ["SPEED (90)"]


def test_robot_cli_motion_goes_through_the_engine_and_ctrl_c_aborts_it(cell, capsys):
    import threading

    from selfview.mocks.val_controller import ValController
    from selfview.mocks.world import SimWorld

    with ValController(SimWorld(cell, seed=2), time_scale=1.0, calibrated=True, speed_pct=5.0) as c:
        c.start_pty()
        target = c.locations()["ABOVE"]
        main_thread = threading.get_ident()
        # Ctrl-C as soon as the arm moves (an event, not a clock)
        ctrl_c = threading.Thread(target=lambda: c.moving.wait(30.0) and signal.pthread_kill(main_thread, signal.SIGINT))
        ctrl_c.start()
        try:
            code = main(["robot", "--url", c.url, "move", "above"])
        finally:
            ctrl_c.join(30.0)
        err = capsys.readouterr().err
        assert code == 130, err
        assert "this is a bug" not in err and "ABORT sent and confirmed" in err
        assert "ABORT" in c.received and not c.moving.is_set()
        assert np.linalg.norm(c.base_H_T[:3, 3] - target[:3, 3]) > 1.0  # stopped short of its target


def test_robot_cli_with_the_reply_line_stalled_mid_motion_writes_abort_and_gives_up_in_its_bound(cell, capsys, tmp_path):
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.world import SimWorld

    limits = tmp_path / "limits.yaml"
    limits.write_text("timeout_factor: 1.0\ntimeout_margin_s: 0.5\n")
    with ValController(SimWorld(cell, seed=2), time_scale=0.0, calibrated=True) as c:
        c.start_pty()
        c.inject("stall")  # the reply line goes dead as the motion starts
        code = main(["robot", "--url", c.url, "--timeout", "0.5", "--limits", str(limits), "move", "above"])
        err = capsys.readouterr().err
        assert code == 4, err
        assert "ABORT sent, NOT confirmed" in err
        rx = c.received
        # the wait came from the speed read from the controller, and ABORT followed the motion directly
        assert rx.index("STATUS") < rx.index("DO MOVE (above)") < rx.index("ABORT")
        assert "" not in rx[rx.index("DO MOVE (above)") : rx.index("ABORT")]  # no resynchronising CR first


def test_robot_cli_abort_while_another_client_moves_the_arm(cell, capsys):
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.world import SimWorld

    with ValController(SimWorld(cell, seed=2), time_scale=0.0) as c:
        c.start_pty()
        assert main(["robot", "--url", c.url, "abort", "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert out["abort"]["written"] and out["abort"]["confirmed"]
        assert c.received == ["ABORT"]  # ABORT first: no CR before it


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT], ids=lambda s: signal.Signals(s).name)
def test_a_termination_signal_during_robot_ready_aborts_the_motion_and_exits_128_plus_n(cell, sig):
    import os
    import time

    from selfview.mocks.val_controller import ValController
    from selfview.mocks.world import SimWorld

    with ValController(SimWorld(cell, seed=2), time_scale=1.0, calibrated=True, speed_pct=5.0) as c:
        c.start_pty()
        env = dict(os.environ, PYTHONPATH=str(REPO))
        proc = subprocess.Popen([sys.executable, "-m", "selfview.procedures.cli", "robot", "--url", c.url, "ready"],
                                cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert c.moving.wait(60.0), "the arm never started moving"
            time.sleep(0.3)
            t_signal = time.monotonic()  # before the pose is read: a stall of this thread counts in stopped_after
            q_at_signal = c.joints
            proc.send_signal(sig)
            while c.moving.is_set() and time.monotonic() - t_signal < 5.0:
                time.sleep(0.005)
            stopped_after = time.monotonic() - t_signal
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
        assert proc.returncode == 128 + sig, err
        assert "ABORT" in c.received, c.received
        assert stopped_after < 0.5, f"the arm stopped {stopped_after:.3f} s after the signal"
        # no farther than the arm's peak speed for the time it took to stop (travel_bound_deg)
        travel = np.abs(c.joints - q_at_signal).max()
        assert travel < travel_bound_deg(stopped_after), (travel, stopped_after)
        assert f"terminated by {signal.Signals(sig).name}" in err and "ABORT sent and confirmed" in err
        assert "this is a bug" not in err and "Traceback" not in err


def test_a_stalled_reply_line_gets_abort_within_5_s_of_the_motions_expected_end(capsys):
    import threading
    import time

    from selfview.drivers.puma_val_serial import PumaVAL
    from selfview.mocks.val_controller import ValController

    with ValController(time_scale=1.0, calibrated=True, speed_pct=50.0) as c:  # starts at READY
        c.start_pty()
        with PumaVAL(c.url) as r:
            t0 = time.monotonic()
            r.move("above")
            duration = time.monotonic() - t0  # the motion's real duration at SPEED 50 (about 1.2 s)
            r.ready()
        c.inject("stall", after_s=0.2)  # the reply line dies 0.2 s into the motion
        seen = {}

        def watch():
            while "t" not in seen and time.monotonic() - t0 < 30.0:
                if c.received.count("ABORT"):
                    seen["t"] = time.monotonic()
                time.sleep(0.005)

        t0 = time.monotonic()
        watcher = threading.Thread(target=watch)
        watcher.start()
        code = main(["robot", "--url", c.url, "move", "above"])
        watcher.join(30.0)
        err = capsys.readouterr().err
        assert code == 4 and "ABORT sent" in err, err
        # from the start of the command: the STATUS, POINT and WHERE before the motion take well under 1 s
        assert seen["t"] - t0 < duration + 5.0, f"ABORT {seen['t'] - t0:.2f} s after the start of a {duration:.2f} s motion"


def test_a_speed_changed_by_another_program_refuses_the_next_motion(capsys):
    from selfview.drivers.puma_val_serial import PumaVAL
    from selfview.mocks.val_controller import ValController

    with ValController(time_scale=0.0, calibrated=True) as c:
        pty = c.start_pty()
        port = c.start_tcp()
        with PumaVAL(pty) as r, PumaVAL(f"socket://127.0.0.1:{port}") as other:
            r.speed(20)
            r.move("above")
            other.speed(50)  # a lab script on the controller's other terminal
            with pytest.raises(ProtocolError, match="SPEED is 50, not the 20.*another program"):
                r.depart(40)
            assert not [ln for ln in c.received if ln.startswith("DO DEPART")]


def test_the_serial_port_is_opened_exclusively():
    from selfview.drivers.puma_val_serial import PumaVAL
    from selfview.mocks.val_controller import ValController

    with ValController(time_scale=0.0, calibrated=True) as c:
        c.start_pty()
        with PumaVAL(c.url):
            with pytest.raises(DeviceError, match="another program holds the port"):
                PumaVAL(c.url).connect()
            assert main(["robot", "--url", c.url, "where"]) == 4
        with PumaVAL(c.url) as again:  # free once the first has closed it
            assert again.where().joints


@pytest.mark.parametrize("argv", [["appro", "plate", "-15"], ["depart", "-10"]])
def test_negative_appro_and_depart_are_refused_before_anything_moves(cell, capsys, argv):
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.world import SimWorld

    with ValController(SimWorld(cell, seed=2), time_scale=0.0, calibrated=True) as c:
        c.start_pty()
        assert main(["robot", "--url", c.url, *argv]) == 4
        assert "beyond the location" in capsys.readouterr().err
        assert not [ln for ln in c.received if ln.startswith("DO ")]


def test_a_stall_of_the_host_longer_than_the_reply_limit_is_no_device_fault():
    """The host is suspended (SIGSTOP) through the motion and past its reply limit: the controller's complete
    reply waits in the buffer, and on resume it counts (exit 0, no ABORT)."""
    import os
    import time

    from selfview.mocks.val_controller import ValController

    with ValController(time_scale=1.0, calibrated=True, speed_pct=50.0) as c:  # starts at READY
        c.start_pty()
        env = dict(os.environ, PYTHONPATH=str(REPO))
        proc = subprocess.Popen([sys.executable, "-m", "selfview.procedures.cli", "robot", "--url", c.url, "move", "above"],
                                cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert c.moving.wait(60.0), "the arm never started moving"
            time.sleep(0.3)  # the command is waiting for the motion's reply
            proc.send_signal(signal.SIGSTOP)
            t0 = time.monotonic()
            while c.moving.is_set() and time.monotonic() - t0 < 30:
                time.sleep(0.01)
            # the motion (READY to 'above' at SPEED 50) takes 1.1 s here and its wait is 4.8 s (its expected
            # duration plus a margin, measured on this simulated controller): 12 s is well past both
            time.sleep(12.0)
            proc.send_signal(signal.SIGCONT)
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
        assert proc.returncode == 0, err
        assert "ABORT" not in c.received, err


def test_ctrl_z_stops_the_arm_before_the_program_and_resume_says_so(cell):
    import os
    import time

    from selfview.mocks.val_controller import ValController
    from selfview.mocks.world import SimWorld

    with ValController(SimWorld(cell, seed=2), time_scale=1.0, calibrated=True, speed_pct=5.0) as c:
        c.start_pty()
        env = dict(os.environ, PYTHONPATH=str(REPO))
        # its own process group in this session, whose parent is outside it: a group the kernel may stop (an
        # orphaned one, as under setsid or with a parent gone, has SIGTSTP discarded, as POSIX says)
        proc = subprocess.Popen([sys.executable, "-m", "selfview.procedures.cli", "robot", "--url", c.url, "ready"],
                                cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                process_group=0)
        try:
            assert c.moving.wait(60.0), "the arm never started moving"
            time.sleep(0.3)
            t0 = time.monotonic()  # before the pose is read: a stall of this thread counts in stopped_after
            q0 = c.joints
            proc.send_signal(signal.SIGTSTP)
            while c.moving.is_set() and time.monotonic() - t0 < 5.0:
                time.sleep(0.005)
            stopped_after = time.monotonic() - t0
            assert not c.moving.is_set(), "the arm went on while the program was suspended"
            state = ""
            while time.monotonic() - t0 < 10.0 and state != "T":
                with open(f"/proc/{proc.pid}/stat") as f:
                    state = f.read().rsplit(")", 1)[1].split()[0]
                time.sleep(0.01)
            assert state == "T", "the program was not suspended"
            # no farther than the arm's peak speed for the time it took to stop, as above
            assert np.abs(c.joints - q0).max() < travel_bound_deg(stopped_after), stopped_after
            proc.send_signal(signal.SIGCONT)
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(5)
        assert "ABORT" in c.received
        assert "resumed" in err and proc.returncode == 4, err  # the stopped motion is not taken up again
        assert "Traceback" not in err


def test_a_slow_motion_longer_than_the_margin_is_waited_for_to_its_end():
    """The motion wait's lower side: at SPEED 5 a drive of joint 1 takes about 4.5 s, longer than the
    wait's fixed margin; it must end at its target, not in a false timeout and an ABORT."""
    from selfview.drivers.puma_val_serial import PumaVAL
    from selfview.drivers.puma_val_serial.limits import PUMA260_JOINT_SPEED_DEG_S
    from selfview.mocks.val_controller import ValController

    deg = 4.5 * PUMA260_JOINT_SPEED_DEG_S[0] * 0.05 * 0.5  # 4.5 s at SPEED 5 and DRIVE speed 50
    with ValController(time_scale=1.0, calibrated=True, speed_pct=5.0) as c:
        c.start_pty()
        with PumaVAL(c.url) as r:
            q0 = r.where().joints[0]
            r.drive(1, deg, 50)
            assert r.where().joints[0] == pytest.approx(q0 + deg, abs=0.1)
        assert "ABORT" not in c.received
