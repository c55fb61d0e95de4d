"""The simulated VAL-II controller and the PUMA 260 kinematics behind it."""

from __future__ import annotations

import time

import numpy as np
import pytest
import serial

from selfview.mocks.puma260 import READY_DEG, ArmConfig, Puma260, Puma260Geometry, Unreachable, make_tool
from selfview.mocks.val_controller import TOOL_LENGTH_MM, ValController, trapezoid_fraction, trapezoid_time
from selfview.mocks.world import PLATE_BASE_POSE, SimWorld
from selfview.errors import ConfigError
from selfview.maths.geometry import inv_H

CONFIGS = [ArmConfig(r, e, w) for r in ("front", "back") for e in ("above", "below") for w in ("noflip", "flip")]


# --- kinematics ---------------------------------------------------------------------------------------------
def test_ready_holds_the_arm_straight_up():
    H = Puma260().fk(READY_DEG)
    g = Puma260Geometry()
    # straight up: the flange sits the sum of the vertical links above the base, offset by the elbow
    # drop (x) and the lateral offset (y), pointing up
    np.testing.assert_allclose(H[:3, 3], [g.elbow_drop_mm, -g.lateral_mm, g.shoulder_mm + g.upper_arm_mm + g.forearm_mm + g.flange_mm], atol=1e-9)
    np.testing.assert_allclose(H[:3, :3], np.eye(3), atol=1e-12)


@pytest.mark.parametrize("cfg", CONFIGS, ids=lambda c: f"{c.reach}-{c.elbow}-{c.wrist}")
def test_inverse_kinematics_round_trips_and_keeps_its_configuration(cfg, rng):
    k = Puma260(config=cfg)
    lims = np.array(k.geometry.joint_limits_deg)
    solved = 0
    for _ in range(300):
        q = rng.uniform(lims[:, 0], lims[:, 1])
        H = k.fk(q)
        try:
            q2 = k.ik(H, q)
        except Unreachable:
            continue
        solved += 1
        np.testing.assert_allclose(k.fk(q2), H, atol=1e-7)
        assert k.within_limits(q2) is None
        # the configuration asked for
        fr = k.frames(q2)
        shoulder, elbow, wrist = fr[0][:3, 3], fr[2][:3, 3], fr[4][:3, 3]
        # reach: the wrist centre lies in front of (r > 0) or behind the upper arm's swing axis
        front = np.cross([0.0, 0.0, 1.0], fr[1][:3, 2])  # horizontal, across joint 2's axis
        r = float(np.dot(wrist - shoulder, front))
        assert (r > 0) == (cfg.reach == "front") or abs(r) < 1e-6
        # elbow: on the upper side of the shoulder-wrist line, seen from the side with the wrist to the right
        x1, y1 = fr[1][:3, 0], fr[1][:3, 1]  # the arm's plane: radial and up
        er, ez = np.dot(elbow - shoulder, x1), np.dot(elbow - shoulder, y1)
        wr, wz = np.dot(wrist - shoulder, x1), np.dot(wrist - shoulder, y1)
        side = np.sign(wr) * (wr * ez - wz * er)
        assert (side > 0) == (cfg.elbow == "above") or abs(side) < 1e-6
        assert (q2[4] >= 0) == (cfg.wrist == "noflip") or abs(q2[4]) < 1e-9
    assert solved > 100  # most random poses have a solution in every configuration


def make_target(x, y, z):
    """The flange pose that puts the tool point at (x, y, z), tool pointing down."""
    T = PLATE_BASE_POSE.copy()
    T[:3, 3] = (x, y, z)
    return T @ inv_H(make_tool(TOOL_LENGTH_MM))


def test_kinematic_errors_are_parameters():
    nominal = Puma260()
    worn = Puma260(Puma260Geometry().with_errors(upper_arm_mm=198.6, joint_offsets_deg=(0.0, 0.2, -0.1, 0.0, 0.0, 0.0)))
    q = np.array([20.0, -140.0, 30.0, -170.0, 50.0, 10.0])
    shift = np.linalg.norm(worn.fk(q)[:3, 3] - nominal.fk(q)[:3, 3])
    assert 0.5 < shift < 5.0
    np.testing.assert_allclose(worn.fk(worn.ik(worn.fk(q), q)), worn.fk(q), atol=1e-7)


def test_unreachable_poses_say_why():
    k = Puma260()
    with pytest.raises(Unreachable, match="reaches"):
        k.ik(make_target(800, 0, 300))
    with pytest.raises(Unreachable, match="lateral offset"):
        k.ik(make_target(0, 0, 300))
    with pytest.raises(ValueError, match="upper arm"):
        Puma260Geometry(upper_arm_mm=0.0)
    with pytest.raises(ValueError, match="ArmConfig.elbow"):
        ArmConfig(elbow="sideways")


def test_the_taught_locations_over_and_on_the_plate_are_reachable(cell):
    c = ValController(SimWorld(cell, seed=0))
    locs = c.locations()
    for name in ("ABOVE", "PLATE"):
        q = c.kin.ik(locs[name] @ inv_H(c.tool))
        assert c.kin.within_limits(q) is None
    assert c.world.contact(locs["PLATE"]) == "parked"
    assert c.world.contact(locs["ABOVE"]) == "free"


# --- motion profile -------------------------------------------------------------------------------------------
def test_trapezoid_and_triangle_profiles():
    assert trapezoid_time(100.0, 50.0, 200.0) == pytest.approx(100 / 50 + 50 / 200)
    assert trapezoid_time(1.0, 50.0, 200.0) == pytest.approx(2 * np.sqrt(1 / 200))
    assert trapezoid_time(0.0, 50.0, 200.0) == 0.0
    for dist in (1.0, 100.0):
        T = trapezoid_time(dist, 50.0, 200.0)
        s = [trapezoid_fraction(t, dist, 50.0, 200.0) for t in np.linspace(0, T, 101)]
        assert s[0] == 0.0 and s[-1] == 1.0 and np.all(np.diff(s) >= 0)
        assert trapezoid_fraction(T / 2, dist, 50.0, 200.0) == pytest.approx(0.5)


def test_joint_motion_takes_the_slowest_joints_profile():
    c = ValController(None, speed_pct=50)
    q1 = np.array(READY_DEG) + [30.0, 0, 0, 90.0, 0, 0]
    m = c._joint_motion(q1)  # noqa: SLF001 - the planned duration is what we check
    top = c.kin.geometry.joint_speed_deg_s
    assert m.T == pytest.approx(trapezoid_time(30.0, top[0] * 0.5, top[0] / c.accel_time_s))


# --- the controller on its links -------------------------------------------------------------------------------
class Terminal:
    """A raw pyserial client on the controller's pty."""

    def __init__(self, url):
        self.tty = serial.Serial(url, 9600, timeout=0.02)

    def say(self, line: bytes, until: bytes = b"\r\n.") -> bytes:
        self.tty.write(line + b"\r")
        buf = b""
        deadline = time.monotonic() + 3.0
        while not buf.endswith(until) and time.monotonic() < deadline:
            buf += self.tty.read(512)
        return buf

    def close(self):
        self.tty.close()


@pytest.fixture
def term_sim(cell):
    sims = []

    def make(**kw):
        kw.setdefault("time_scale", 0.01)
        c = ValController(SimWorld(cell, seed=0), **kw)
        c.start_pty()
        sims.append(c)
        return c, Terminal(c.url)

    yield make
    for c in sims:
        c.stop()


def test_noise_is_seeded(term_sim):
    replies = []
    for seed in (5, 5, 6):
        c, t = term_sim(seed=seed)
        clean = t.say(b"WHERE")
        c.inject("noise", count=3, mode="mixed")
        replies.append(t.say(b"WHERE"))
        t.close()
        assert replies[-1] != clean
    assert replies[0] == replies[1] != replies[2]


def test_echo_off_sends_no_echo(term_sim):
    c, t = term_sim(echo=False)
    out = t.say(b"SPEED 30")
    assert out == b"\r\n."
    assert t.say(b"WHERE").startswith(b"\r\n        X")
    t.close()


def test_straight_moves_stay_on_the_line(term_sim, monkeypatch):
    c, t = term_sim(calibrated=True)
    seen = []
    real = c.world.set_tcp
    monkeypatch.setattr(c.world, "set_tcp", lambda H: (seen.append(np.array(H)), real(H))[1])
    t.say(b"DO SET a = TRANS(300, -60, 120, 90, 90, 0)")  # VAL's O/A/T: the tool down
    t.say(b"DO SET b = TRANS(380, 60, 60, 90, 60, 30)")
    t.say(b"DO MOVE a")
    seen.clear()
    t.say(b"DO MOVES b")
    assert len(seen) >= 2
    p0, p1 = np.array([300, -60, 120.0]), np.array([380, 60, 60.0])
    u = (p1 - p0) / np.linalg.norm(p1 - p0)
    for H in seen:
        d = H[:3, 3] - p0
        assert np.linalg.norm(d - np.dot(d, u) * u) < 1e-6
    np.testing.assert_allclose(seen[-1][:3, 3], p1, atol=1e-6)
    t.close()


def test_a_line_cut_short_by_a_line_end_runs_nothing(term_sim):
    """Issue 32: noise puts a line end inside a typed line and the controller executes what came before it.
    Every proper prefix of the driver's motion, SPEED and location lines, typed and ended, is refused as a
    syntax error and moves nothing (a location 'p' exists, so 'DO MOVE p' of 'DO MOVE p1' would run); the
    whole lines run, and a cut bare line ('DO APPRO plate, 5' of 'DO APPRO plate, 50') is a real motion."""
    c, t = term_sim(calibrated=True)
    d = c.dialect
    for name, pose in (("p", (300, -60, 120, 90, 90, 0)), ("p1", (380, 60, 60, 90, 60, 30))):
        assert t.say(d.command("define", name=name, **dict(zip("xyzoat", pose))).encode()).endswith(b"\r\n.")
    assert set(c.locations()) >= {"P", "P1", "ABOVE", "PLATE"}
    lines = [d.command("appro", name="plate", d=50), d.command("move", name="p1"), d.command("moves", name="above"),
             d.command("depart", d=60), d.command("drive", joint=1, deg=-12.5, speed=50), d.command("speed", pct=20),
             d.command("define", name="p1", x=350, y=-20, z=100, o=0, a=90, t=-45.5), d.command("ready")]
    before, speed, where = c.joints, c.speed_pct, c.locations()
    for line in lines:
        for k in range(1, len(line)):
            out = t.say(line[:k].encode())
            assert out.endswith(b"*Unrecognized command*\r\n."), (line[:k], out)
            assert not c.moving.is_set()
    np.testing.assert_array_equal(c.joints, before)
    assert c.speed_pct == speed and {k: v.tolist() for k, v in c.locations().items()} == {k: v.tolist() for k, v in where.items()}
    assert t.say(lines[0].encode()).endswith(b"\r\n.")  # the whole line is read and runs
    appro = c.joints
    assert np.max(np.abs(appro - before)) > 1.0
    t.say(d.command("ready").encode())
    t.say(b"DO APPRO plate, 5")  # the bare form's prefix: a real motion, 45 mm nearer the plate
    assert np.max(np.abs(c.joints - appro)) > 1.0
    t.close()


def test_drive_past_a_joint_limit_is_refused_by_the_controller(term_sim):
    c, t = term_sim(calibrated=True)
    before = c.joints
    assert b"*Joint 1 limit stop*" in t.say(b"DO DRIVE 1, 300, 10")
    assert b"*Illegal value*" in t.say(b"DO DRIVE 7, 1, 10")
    np.testing.assert_array_equal(c.joints, before)
    t.close()


def test_async_error_text_and_world_start_pose(term_sim):
    c, t = term_sim()
    # the controller starts where the world's gripper is
    np.testing.assert_allclose(c.base_H_T, c.world.base_H_G, atol=1e-9)
    c.inject("async_error", text="Emergency stop")
    buf = b""
    deadline = time.monotonic() + 2.0
    while not buf.endswith(b"\r\n.") and time.monotonic() < deadline:
        buf += t.tty.read(256)
    assert buf == b"\r\n*Emergency stop*\r\n."
    assert c.arm_power  # only a power-off text turns the power off
    t.close()


def test_without_a_world_and_stop_is_clean():
    c = ValController(None, time_scale=0.0)
    path = c.start_pty()
    c.start_tcp()
    t = Terminal(path)
    assert b"  -90.00" in t.say(b"WHERE")  # READY: JT2 = -90
    t.close()
    c.stop()
    c.stop()
    assert not any(th.is_alive() for th in c._threads)  # noqa: SLF001


def test_bad_settings_are_named(cell):
    with pytest.raises(ConfigError, match="fault 'fire'"):
        ValController(None).inject("fire")
    with pytest.raises(ConfigError, match="time_scale"):
        ValController(None, time_scale=-1)
    with pytest.raises(ConfigError, match="pace_baud"):
        ValController(None, pace_baud=0)
    c = ValController(None)
    c.start_tcp()
    try:
        with pytest.raises(ConfigError, match="cannot listen"):
            ValController(None).start_tcp(int(c.url.rsplit(":", 1)[1]))
    finally:
        c.stop()


def test_characters_are_echoed_as_typed_and_ctrl_u_erases_the_line(term_sim):
    c, t = term_sim(calibrated=True)
    t.tty.write(b"SPEED 33")  # typed, not yet executed
    buf = b""
    deadline = time.monotonic() + 3.0
    while buf != b"SPEED 33" and time.monotonic() < deadline:
        buf += t.tty.read(64)
    assert buf == b"SPEED 33" and c.speed_pct == 50.0
    assert t.say(b"\x15") == b"\r\n\r\n."  # erased: a fresh line, then the empty line's prompt
    assert c.speed_pct == 50.0 and "SPEED 33" not in c.received
    assert t.say(b"SPEED 22") == b"SPEED 22\r\n." and c.speed_pct == 22.0
    assert b"Monitor speed: 22" in t.say(b"STATUS")
    t.close()


def test_a_byte_above_0x7f_gets_an_error_and_the_controller_goes_on(term_sim):
    c, t = term_sim()
    out = t.say(b"WH\xc5RE")
    assert b"*Unrecognized command*" in out and out.endswith(b"\r\n.")
    assert t.say(b"WHERE").endswith(b"\r\n.")  # the server thread is alive
    assert all(th.is_alive() for th in c._threads)  # noqa: SLF001
    t.close()


def test_a_byte_above_0x7f_on_tcp_too(cell):
    import socket

    with ValController(None, time_scale=0.0) as c:
        port = c.start_tcp()
        for _ in range(2):  # a second client is served after the first one's bad byte
            with socket.create_connection(("127.0.0.1", port), timeout=5.0) as s:
                s.sendall(b"SPEED \xff\r")
                buf = b""
                while not buf.endswith(b"\r\n."):
                    chunk = s.recv(256)
                    assert chunk, buf
                    buf += chunk
                assert b"*Unrecognized command*" in buf


def test_the_program_prompt(term_sim):
    c, t = term_sim()
    c.program_running = True
    assert t.say(b"WHERE", until=b"\r\n*").endswith(b"\r\n*")
    t.close()


def test_the_arm_goes_on_when_a_tcp_client_leaves_mid_motion(cell):
    import socket

    world = SimWorld(cell, seed=0)
    with ValController(world, time_scale=0.2, calibrated=True) as c:
        port = c.start_tcp()
        target = c.locations()["ABOVE"]
        s = socket.create_connection(("127.0.0.1", port), timeout=5.0)
        s.sendall(b"DO MOVE above\r")
        assert c.moving.wait(5.0)
        s.close()  # the client goes away while the arm moves
        deadline = time.monotonic() + 10.0
        while c.moving.is_set() and time.monotonic() < deadline:
            time.sleep(0.01)
        # as on a pty (and on the real controller): the arm reached its target
        np.testing.assert_allclose(c.base_H_T[:3, 3], target[:3, 3], atol=1e-6)


def test_replies_are_formatted_by_the_simulators_own_code(term_sim, monkeypatch):
    from selfview.drivers.puma_val_serial import ValDialect

    # a bug in the driver's formatting must not be shared by the simulator
    monkeypatch.setattr(ValDialect, "format_values", lambda self, values: "BROKEN")
    monkeypatch.setattr(ValDialect, "format_header", lambda self, names: "BROKEN")
    c, t = term_sim()
    out = t.say(b"WHERE")
    assert b"BROKEN" not in out and b"       X        Y" in out
    t.close()


def test_stop_joins_the_paced_output_before_it_closes_the_pty():
    # at 100 baud WHERE's reply takes seconds: stop() comes in the middle of it
    c = ValController(time_scale=0.0, pace_baud=100)
    path = c.start_pty()
    with serial.Serial(path, timeout=0.05) as port:
        port.write(b"WHERE\r")
        got = b""
        t_end = time.monotonic() + 10.0
        while len(got) < 8 and time.monotonic() < t_end:  # the echo, then the reply under way
            got += port.read(16)
        assert len(got) >= 8
        threads = list(c._threads)
        t0 = time.monotonic()
        c.stop()
        took = time.monotonic() - t0
        assert not any(t.is_alive() for t in threads)  # nothing writes once the pty is closed
        assert took < 1.0, f"stop() took {took:.2f} s"
    c.stop()  # twice is fine
