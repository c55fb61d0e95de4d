"""Contract tests: the PUMA VAL-II driver against the simulated controller over a real pseudo-terminal.

By default the simulator serves the pty; with ``SELFVIEW_PUMA_URL`` set (and ``-m hardware``) the
motion-free part runs against a real controller instead.
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest
import serial

from selfview.drivers.puma_val_serial import (
    ArmPowerOff,
    ValDialect,
    Collision,
    MotionAborted,
    NotCalibrated,
    OutOfReach,
    PumaVAL,
    ValLimits,
)
from selfview.mocks.val_controller import ValController
from selfview.mocks.world import PLATE_BASE_POSE, SimWorld
from selfview.errors import DeviceTimeout, LimitError, ProtocolError
from selfview.maths.geometry import pose_difference, trans

SCALE = 0.02  # motions run at 1/50 of real time


@pytest.fixture
def world(cell):
    return SimWorld(cell, seed=7)


@pytest.fixture
def sim(world):
    c = ValController(world, seed=3, time_scale=SCALE)
    c.start_pty()
    yield c
    c.stop()


@pytest.fixture
def robot(sim):
    r = PumaVAL(sim.url, timeout_s=0.5)
    r.connect()
    yield r
    r.close()


def ready_robot(robot):
    robot.calibrate()
    robot.speed(50)
    return robot


VAL = ValDialect()  # O/A/T in VAL's convention: (90, 90, 0) is the tool pointing down


def assert_pose(where, pose, tol_mm=0.01, tol_deg=0.02):
    ang, dist = pose_difference(where.base_H_T, VAL.pose_to_H(pose))
    assert dist <= tol_mm and ang <= tol_deg, (where.pose, pose, ang, dist)


# --- the contract ---------------------------------------------------------------------------------------
def test_calibrate_speed_define_move_where(robot, sim):
    with pytest.raises(NotCalibrated):
        robot.move("above")
    robot.calibrate()
    assert sim.calibrated
    robot.speed(40)
    assert sim.speed_pct == 40
    targets = [(350, 20, 100, 80, 80, 15), (300, -80, 150.5, 120, 60, -20), (250.25, 60, 220, 45, 30, 90)]
    for i, pose in enumerate(targets):
        robot.define(f"p{i}", pose)
        robot.move(f"p{i}")
        assert_pose(robot.where(), pose)
        ang, dist = pose_difference(VAL.pose_to_H(robot.location(f"p{i}")), VAL.pose_to_H(pose))
        assert dist < 0.006 and ang < 0.01
    # the joints the controller reports are the ones its kinematics hold
    np.testing.assert_allclose(robot.where().joints, sim.joints, atol=0.006)


def test_where_reports_the_simulated_tool_pose(robot, sim, world):
    w = robot.where()
    ang, dist = pose_difference(w.base_H_T, sim.base_H_T)
    assert dist < 0.01 and ang < 0.01
    ang, dist = pose_difference(w.base_H_T, world.base_H_G)  # the world's TCP is the tool point
    assert dist < 0.01 and ang < 0.01


def test_straight_move_onto_the_plate_parks_and_depart_unparks(robot, world):
    ready_robot(robot)
    robot.move("above")
    assert not world.parked
    robot.moves("plate")
    assert world.parked
    # the foam tilted the plate into coincidence: W_H_G is a turn about z and an in-plane shift
    W_H_G = world.W_H_G
    assert abs(W_H_G[2, 3]) < 1e-9 and abs(W_H_G[2, 2] - 1.0) < 1e-9
    robot.depart(40)
    assert not world.parked
    assert_pose(robot.where(), tuple(np.r_[350.0, 0.0, 16.0 + 40.0, robot.where().pose[3:]]))


def test_appro_and_depart(robot):
    ready_robot(robot)
    pose = (320, 30, 60, 90, 90, 0)
    robot.define("t1", pose)
    robot.appro("t1", 50)
    # the tool points down: 50 mm back along its z is 50 mm higher
    assert_pose(robot.where(), (320, 30, 110, 90, 90, 0))
    robot.depart(30)
    assert_pose(robot.where(), (320, 30, 140, 90, 90, 0))


def test_drive_and_ready(robot, sim):
    ready_robot(robot)
    j0 = np.array(robot.where().joints)
    robot.drive(1, -12.5, 30)
    np.testing.assert_allclose(robot.where().joints, j0 + [-12.5, 0, 0, 0, 0, 0], atol=0.006)
    robot.ready()
    np.testing.assert_allclose(robot.where().joints, [0, -90, 90, 0, 0, 0], atol=0.006)


def test_here_and_point(robot, sim):
    pose = robot.here("home")
    assert "HOME" in sim.locations()
    assert robot.location("home") == pose
    assert_pose(robot.where(), pose, tol_mm=0.006)


def test_abort_during_a_move_from_another_thread(robot, sim):
    ready_robot(robot)
    robot.ready()
    robot.speed(5)
    sim.time_scale = 1.0  # real time: READY -> above takes ~10 s, far longer than anything below
    start = robot.where()
    result = {}

    def mover():
        try:
            robot.move("above")
        except Exception as exc:  # collected for the assertions below
            result["exc"] = exc

    t = threading.Thread(target=mover)
    t.start()
    assert sim.moving.wait(10.0)
    for _ in range(2000):  # until the arm has visibly moved (bounded; the motion lasts ~10 s)
        if pose_difference(sim.base_H_T, start.base_H_T)[1] >= 2.0:
            break
        time.sleep(0.005)
    res = robot.abort()
    t.join(10.0)
    assert not t.is_alive()
    assert isinstance(result.get("exc"), MotionAborted)
    assert res.written and res.confirmed and "Motion aborted" in res.detail
    sim.time_scale = SCALE
    stopped = robot.where()
    target = PLATE_BASE_POSE @ trans(0, 0, -60)
    assert pose_difference(stopped.base_H_T, start.base_H_T)[1] > 1.0  # it moved ...
    assert pose_difference(stopped.base_H_T, target)[1] > 1.0  # ... but did not arrive
    assert "ABORT" in sim.received
    robot.speed(50)
    robot.move("above")  # and works on
    assert pose_difference(robot.where().base_H_T, target)[1] < 0.01


def test_a_relocated_location_is_read_again_before_its_limit_check(sim):
    lim = ValLimits(workspace_mm=((100, 450), (-200, 200), (10, 400)))
    robot = PumaVAL(sim.url, limits=lim, timeout_s=0.5)
    ready_robot(robot.connect())
    robot.move("above")
    # someone re-teaches 'above' outside this driver's box (another client, the teach pendant)
    robot.close()
    with PumaVAL(sim.url, timeout_s=0.5) as other:
        other.define("above", PLATE_BASE_POSE @ trans(0, 0, -60) @ trans(0, 0, -450))  # 450 mm higher
    robot.connect()
    with pytest.raises(LimitError, match="outside the workspace"):
        robot.move("above")
    robot.close()
    assert [ln for ln in sim.received if ln.startswith("DO MOVE")] == ["DO MOVE (above)"]


def test_a_controller_with_another_oat_convention_is_named_before_any_motion(world):
    from selfview.drivers.puma_val_serial import OAT_CONVENTIONS
    from selfview.errors import ConfigError

    vplus = ValDialect(euler=OAT_CONVENTIONS["vplus"])
    with ValController(world, seed=1, time_scale=SCALE, dialect=vplus, calibrated=True) as c:
        c.start_pty()
        with PumaVAL(c.url, timeout_s=0.5) as robot:
            with pytest.raises(ConfigError, match="'vplus' convention"):
                robot.move("above")
        assert not any(ln.startswith("DO ") for ln in c.received)


def test_one_noise_byte_during_a_motion_does_not_end_it(robot, sim, monkeypatch):
    ready_robot(robot)
    robot.speed(10)
    target = PLATE_BASE_POSE @ trans(0, 0, -60)
    real_run = sim._run  # noqa: SLF001 - the stray '.' goes out right after the motion's echo

    def run_with_noise(link, inp, head, m):
        sim._send(link, head + ".")  # noqa: SLF001 - a prompt look-alike at the start of a line
        return real_run(link, inp, "", m)

    monkeypatch.setattr(sim, "_run", run_with_noise)
    robot.move("above")
    assert pose_difference(sim.base_H_T, target)[1] < 0.01  # returned only at the target
    assert not sim.moving.is_set()


# --- faults -----------------------------------------------------------------------------------------------
def timed(fn):
    t0 = time.monotonic()
    try:
        fn()
    finally:
        timed.elapsed = time.monotonic() - t0


@pytest.mark.parametrize("mode", ["flip", "drop", "mixed"])
def test_line_noise_is_a_protocol_error_and_the_driver_recovers(robot, sim, mode):
    sim.inject("noise", count=2, mode=mode)
    with pytest.raises(ProtocolError):
        timed(robot.where)
    assert timed.elapsed < robot.timeout_s + 1.0
    assert_pose(robot.where(), robot.where().pose)
    assert sim.received[-3:] == ["", "WHERE", "WHERE"]  # a resync (empty line) before the next command


def test_a_reply_that_never_comes_is_a_timeout_and_the_driver_recovers(robot, sim):
    sim.inject("no_reply")
    with pytest.raises(DeviceTimeout):
        timed(robot.where)
    assert robot.timeout_s <= timed.elapsed < robot.timeout_s + 1.0
    robot.where()


# A BREAK reaches the driver as one NUL byte (the tty's delivery with BRKINT, IGNBRK, PARMRK off, which
# the driver sets); here the simulator writes that NUL into the pty itself.
def test_a_break_mid_reply_is_a_protocol_error_naming_it_and_the_driver_recovers(robot, sim, monkeypatch):
    real, calls = sim._cmd_where, []  # noqa: SLF001

    def where_with_a_break(link, inp, head):
        reply = real(link, inp, head)
        calls.append(reply)
        if len(calls) > 1:
            return reply
        sim._send(link, reply[:40] + "\x00")  # noqa: SLF001
        time.sleep(0.1)  # the line held in BREAK; the rest of the reply (and its prompt) comes after
        return reply[40:]

    real_handle = sim._handle  # noqa: SLF001 - and the resync's CR is answered 50 ms late (a slow link)

    def handle_slowly(link, inp, raw):
        if not raw.strip():
            time.sleep(0.05)
        return real_handle(link, inp, raw)

    monkeypatch.setattr(sim, "_cmd_where", where_with_a_break)
    monkeypatch.setattr(sim, "_handle", handle_slowly)
    with pytest.raises(ProtocolError, match="garbage in the reply to 'WHERE'.*BREAK on the line"):
        timed(robot.where)
    assert timed.elapsed < robot.timeout_s + 1.0
    assert_pose(robot.where(), VAL.H_to_pose(sim.base_H_T))
    assert sim.received[-3:] == ["WHERE", "", "WHERE"]  # a resync (empty line) before the next command


def test_a_break_between_commands_is_followed_by_a_resync(robot, sim):
    before = robot.where()
    assert sim._links[0].write(b"\x00", time.monotonic() + 1.0)  # noqa: SLF001 - unasked, while idle
    time.sleep(0.1)
    assert_pose(robot.where(), before.pose)
    assert sim.received[-3:] == ["WHERE", "", "WHERE"]


def test_a_break_during_a_motion_stops_it_and_never_completes_it(world, monkeypatch):
    with ValController(world, seed=3, time_scale=0.5, calibrated=True) as c:
        c.start_pty()
        real_run = c._run  # noqa: SLF001 - the NUL arrives right after the motion's echo, the arm moving

        def run_with_a_break(link, inp, head, m):
            c._send(link, head + "\x00")  # noqa: SLF001
            return real_run(link, inp, "", m)

        monkeypatch.setattr(c, "_run", run_with_a_break)
        with PumaVAL(c.url, timeout_s=1.0) as robot:
            robot.speed(10)
            with pytest.raises(ProtocolError, match="BREAK on the line.*ABORT sent and confirmed"):
                robot.move("above")
            assert "ABORT" in c.received and not c.moving.is_set()
            target = PLATE_BASE_POSE @ trans(0, 0, -60)
            assert pose_difference(c.base_H_T, target)[1] > 10.0  # stopped on its way, not at the target
            assert_pose(robot.where(), VAL.H_to_pose(c.base_H_T))


def test_the_port_reads_a_break_as_a_nul_whatever_it_was_left_with(sim):
    """BRKINT (as ``stty sane`` or a getty leaves it) would make the kernel flush a reply silently."""
    termios = pytest.importorskip("termios")
    fd = os.open(sim.url, os.O_RDWR | os.O_NOCTTY)
    try:
        attrs = termios.tcgetattr(fd)
        attrs[0] |= termios.BRKINT | termios.IGNBRK | termios.PARMRK
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
        with PumaVAL(sim.url, timeout_s=0.5) as robot:
            flags = termios.tcgetattr(robot._ser.fileno())[0]  # noqa: SLF001
            assert not flags & (termios.BRKINT | termios.IGNBRK | termios.PARMRK), oct(flags)
            robot.where()
    finally:
        os.close(fd)


def test_power_lost_mid_move(robot, sim):
    ready_robot(robot)
    start = robot.where()
    sim.inject("power_loss", at=0.5)
    with pytest.raises(ArmPowerOff) as ei:
        robot.move("above")
    assert ei.value.command == "DO MOVE (above)"
    mid = robot.where()  # WHERE still works without arm power
    assert pose_difference(mid.base_H_T, start.base_H_T)[1] > 1.0
    with pytest.raises(ArmPowerOff):
        robot.move("above")
    sim.power_on()
    robot.move("above")
    assert pose_difference(robot.where().base_H_T, PLATE_BASE_POSE @ trans(0, 0, -60))[1] < 0.01


def test_out_of_reach_targets(robot, sim):
    ready_robot(robot)
    before = sim.joints
    with pytest.raises(OutOfReach):
        robot.move((590, 0, 700, 90, 90, 0))  # in the client's box, beyond the arm's reach
    sim.inject("out_of_reach")
    with pytest.raises(OutOfReach):
        robot.move("above")
    np.testing.assert_array_equal(sim.joints, before)
    robot.move("above")


def test_asynchronous_error_line(robot, sim):
    ready_robot(robot)
    sim.inject("async_error")
    message = b"\r\n*Arm power off*\r\n."
    deadline = time.monotonic() + 3.0
    while robot._port().in_waiting < len(message) and time.monotonic() < deadline:  # noqa: SLF001
        time.sleep(0.005)
    assert not sim.arm_power
    with pytest.raises(ArmPowerOff) as ei:
        robot.speed(20)
    assert ei.value.command is None
    assert "SPEED (20)" not in sim.received  # raised before sending
    robot.speed(20)
    assert sim.speed_pct == 20


def test_pressing_through_the_plate_is_a_collision(sim, world):
    # a box reaching below the table top: only the simulated foam and plate stop the arm
    robot = PumaVAL(sim.url, limits=ValLimits(workspace_mm=((-600, 600), (-600, 600), (-100, 1000))), timeout_s=0.5)
    ready_robot(robot.connect())
    robot.move("above")
    robot.define("deep", PLATE_BASE_POSE @ trans(0, 0, 40))  # 40 mm into a plate on 15 mm of foam
    with pytest.raises(Collision):
        robot.moves("deep")
    assert not sim.arm_power
    depth = (np.linalg.inv(PLATE_BASE_POSE) @ world.base_H_G)[2, 3]
    assert 15.0 < depth < 40.0  # stopped on contact, short of the target
    robot.close()


# --- limits -------------------------------------------------------------------------------------------------
def test_the_robot_never_receives_a_command_that_breaks_a_limit(sim):
    lim = ValLimits(workspace_mm=((100, 450), (-200, 200), (10, 400)), max_speed_pct=30)
    with PumaVAL(sim.url, limits=lim, timeout_s=0.5) as robot:
        robot.calibrate()
        robot.speed(30)
        robot.move("above")
        attempts = [
            lambda: robot.speed(31),
            lambda: robot.define("far", (500, 0, 100, 90, 90, 0)),
            lambda: robot.move((300, 250, 100, 90, 90, 0)),
            lambda: robot.moves((300, 0, 5, 90, 90, 0)),
            lambda: robot.appro("above", -80),
            lambda: robot.depart(400),
            lambda: robot.drive(1, 190, 10),
            lambda: robot.drive(2, 1, 40),
        ]
        for attempt in attempts:
            with pytest.raises(LimitError):
                attempt()
        robot.move((300, 0, 100, 90, 90, 0))  # and a legal one still goes
    d = robot.dialect
    for line in sim.received:
        parsed = d.parse_command(line)
        if parsed is None:
            continue
        kind, f = parsed
        if kind == "speed":
            assert f["pct"] <= 30
        if kind == "define":
            for v, (lo, hi) in zip((f["x"], f["y"], f["z"]), lim.workspace_mm):
                assert lo <= v <= hi, line
        assert kind not in ("depart", "drive", "appro"), line
    assert [ln for ln in sim.received if ln.startswith("DO MOVE")] == ["DO MOVE (above)", "DO MOVE (svtgt)"]


# --- other links and clients --------------------------------------------------------------------------------
def test_an_independent_client_holds_a_terminal_dialogue(sim):
    """Raw pyserial on the pty, as a person at a terminal would type."""
    with serial.Serial(sim.url, 9600, timeout=0.02) as tty:

        def say(line: bytes, until: bytes = b"\r\n.") -> str:
            tty.write(line + b"\r")
            buf = b""
            deadline = time.monotonic() + 3.0
            while not buf.endswith(until) and time.monotonic() < deadline:
                buf += tty.read(256)
            assert buf.endswith(until), buf
            return buf.decode()

        out = say(b"WHERE")
        lines = out.split("\r\n")
        assert lines[0] == "WHERE" and lines[1].split() == list("XYZOAT") and lines[3].split()[0] == "JT1"
        assert [float(v) for v in lines[2].split()[:3]] == pytest.approx([350.0, 0.0, 200.0], abs=0.01)
        assert "Are you sure (Y/N)? " in say(b"CAL", until=b"? ")
        assert say(b"Y") == "Y\r\n."
        assert "*Illegal value*" in say(b"SPEED 200")
        assert "*Unrecognized command*" in say(b"FLY AWAY")
        assert say(b"speed 60") == "speed 60\r\n."
        say(b"DO MOVE above")
        assert "Change? " in say(b"POINT above", until=b"? ")
        assert "   100.00" in say(b",,100", until=b"? ")  # change Z only; asked again
        assert say(b"", until=b"\r\n.").endswith("\r\n.")
    assert sim.speed_pct == 60
    assert sim.locations()["ABOVE"][2, 3] == pytest.approx(100.0)


def test_tcp_link_and_reconnection(world):
    with ValController(world, seed=1, time_scale=SCALE) as c:
        c.start_tcp()
        assert c.url.startswith("socket://127.0.0.1:")
        with PumaVAL(c.url, timeout_s=0.5) as robot:
            robot.speed(20)
        with PumaVAL(c.url, timeout_s=0.5) as robot:  # the controller keeps its state across connections
            robot.calibrate()
            robot.move("above")
            assert c.speed_pct == 20
            assert pose_difference(robot.where().base_H_T, PLATE_BASE_POSE @ trans(0, 0, -60))[1] < 0.01


def test_echo_off_and_lf_dialect(world):
    from selfview.drivers.puma_val_serial import ValDialect

    d = ValDialect(echo=False, controller_eol="\n")
    with ValController(world, seed=1, time_scale=SCALE, dialect=d) as c:
        c.start_pty()
        with PumaVAL(c.url, dialect=d, timeout_s=0.5) as robot:
            robot.calibrate()
            robot.move("above")
            assert robot.location("above") == pytest.approx(robot.where().pose, abs=0.006)


def test_spy_url_dumps_the_traffic(sim, tmp_path):
    dump = tmp_path / "traffic.txt"
    with PumaVAL(f"spy://{sim.url}?file={dump}", timeout_s=0.5) as robot:
        robot.where()
    text = dump.read_text()
    assert "WHERE" in text and "JT1" in text


def test_paced_link_still_parses(world):
    with ValController(world, seed=1, time_scale=SCALE, pace_baud=115200) as c:
        c.start_pty()
        with PumaVAL(c.url, timeout_s=1.0) as robot:
            assert robot.where().pose[:3] == pytest.approx((350.0, 0.0, 200.0), abs=0.01)
            assert robot.last_rx_bytes > 200


@pytest.mark.hardware
@pytest.mark.skipif(not os.environ.get("SELFVIEW_PUMA_URL"), reason="set SELFVIEW_PUMA_URL to a real controller")
def test_real_controller_where():
    with PumaVAL(os.environ["SELFVIEW_PUMA_URL"], timeout_s=2.0) as robot:
        w = robot.where()
        assert len(w.pose) == 6 and len(w.joints) == 6


@pytest.mark.hardware
@pytest.mark.skipif(not os.environ.get("SELFVIEW_PUMA_URL"), reason="set SELFVIEW_PUMA_URL to a real controller")
def test_real_controller_speed_reads_back_and_the_link_settings_hold():
    """Motion-free: SPEED set and read back (then restored), the URL's baud rate and flow control as the
    port was opened, and a second connect() a no-op."""
    url = os.environ["SELFVIEW_PUMA_URL"]
    with PumaVAL(url, timeout_s=5.0) as robot:
        before = robot.speed_now()
        robot.speed(17)
        assert robot.speed_now() == pytest.approx(17)
        robot.speed(before)
        ser = robot._ser
        if url.startswith("serial:"):
            for key in ("baud", "xonxoff", "rtscts"):
                if f"{key}=" in url:
                    want = url.split(f"{key}=")[1].split("&")[0]
                    got = ser.baudrate if key == "baud" else int(getattr(ser, key))
                    assert str(got) == want, (key, got, want)
        robot.connect()
        w = robot.where()
        assert len(w.pose) == 6
