"""Transcript tests of the PUMA VAL-II driver: the exact bytes it sends and how it parses each reply.

A scripted serial-like port answers each written line with canned bytes (optionally in timed chunks),
like InstrumentKit's ``expected_protocol``; nothing here needs the simulator.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from selfview.drivers.puma_val_serial import (
    ArmPowerOff,
    CommandRejected,
    ControllerError,
    JointLimit,
    MotionAborted,
    OutOfReach,
    PumaVAL,
    ValDialect,
    ValLimits,
    load_dialect,
)
from selfview.drivers.puma_val_serial import OAT_CONVENTIONS, ProgramRunning
from selfview.errors import ConfigError, DeviceError, DeviceTimeout, LimitError, ProtocolError
from selfview.maths.geometry import R_from_rpy, inv_H, rotation_angle, trans
from selfview.mocks.puma260 import READY_DEG, Puma260, make_tool
from selfview.mocks.val_controller import TOOL_LENGTH_MM

CRLF = b"\r\n"
HDR = b"        X        Y        Z        O        A        T"
JHDR = b"      JT1      JT2      JT3      JT4      JT5      JT6"
VAL = ValDialect()
KIN = Puma260()  # the simulator's kinematics, not the driver's: the transcripts are built independently
TOOL = make_tool(TOOL_LENGTH_MM)


def vals(*v) -> bytes:
    return "".join(f"{x:9.2f}" for x in v).encode()


def pose_of(joints) -> tuple[float, ...]:
    """The tool point's pose (VAL's O/A/T) that a controller prints beside ``joints``, to 2 decimals."""
    return tuple(round(v, 2) for v in VAL.H_to_pose(KIN.fk(joints) @ TOOL))


def joints_at(H, near=None) -> tuple[float, ...]:
    return tuple(round(float(v), 2) for v in KIN.ik(np.asarray(H) @ inv_H(TOOL), near if near is not None else JOINTS))


# every angle non-zero, so a convention that drops or swaps one cannot pass
JOINTS = (24.07, -143.39, 24.5, -170.12, 61.11, -155.93)
POSE = pose_of(JOINTS)


def where_reply(joints=JOINTS, pose=None, *, eol=CRLF) -> bytes:
    """What follows WHERE's line end: the pose and joints (the pose from the joints unless given)."""
    pose = pose_of(joints) if pose is None else pose
    return eol + eol.join([HDR, vals(*pose), JHDR, vals(*joints)]) + eol + b"."


def typed(line: bytes, reply) -> list:
    """A command typed without its CR (echoed back), then the CR and the reply."""
    return [(line, line), (b"\r", reply)]


def where(joints=JOINTS, pose=None) -> list:
    return typed(b"WHERE", where_reply(joints, pose))


def status(pct) -> list:
    return typed(b"STATUS", CRLF + b"Program: none\r\nMonitor speed: " + str(pct).encode() + b"\r\nArm power: on\r\n.")


class ScriptedPort:
    """A serial-like port: each write must equal the next scripted line; its reply is then released,
    as one chunk or as (delay_s, bytes) chunks. ``push`` delivers bytes nobody asked for."""

    def __init__(self, script):
        self.script = list(script)
        self.written: list[bytes] = []
        self.write_times: list[float] = []
        self.timeout = 0.01
        self._rx = bytearray()
        self._pending: list[tuple[float, bytes]] = []
        self._cv = threading.Condition()

    def write(self, data: bytes) -> int:
        with self._cv:
            self.written.append(bytes(data))
            self.write_times.append(time.monotonic())
            if not self.script:
                raise AssertionError(f"unscripted write {data!r}")
            expected, reply = self.script.pop(0)
            assert bytes(data) == expected, f"sent {bytes(data)!r}, expected {expected!r}"
            t = time.monotonic()
            for delay, chunk in reply if isinstance(reply, list) else [(0.0, reply)]:
                t += delay
                self._pending.append((t, chunk))
            self._cv.notify_all()
        return len(data)

    def push(self, data: bytes) -> None:
        with self._cv:
            self._pending.append((time.monotonic(), data))
            self._cv.notify_all()

    def _release(self):
        now = time.monotonic()
        while self._pending and self._pending[0][0] <= now:
            self._rx += self._pending.pop(0)[1]

    @property
    def in_waiting(self) -> int:
        with self._cv:
            self._release()
            return len(self._rx)

    def read(self, n: int = 1) -> bytes:
        deadline = time.monotonic() + self.timeout
        with self._cv:
            while True:
                self._release()
                if self._rx:
                    out = bytes(self._rx[:n])
                    del self._rx[:n]
                    return out
                now = time.monotonic()
                if now >= deadline:
                    return b""
                nxt = self._pending[0][0] if self._pending else deadline
                self._cv.wait(max(0.0, min(nxt, deadline) - now))

    def reset_input_buffer(self):
        with self._cv:
            self._rx.clear()

    def close(self):
        pass


SYNC = (b"\r", b"\r\n.")


def robot(script, **kw) -> tuple[PumaVAL, ScriptedPort]:
    port = ScriptedPort([SYNC, *script])
    kw.setdefault("timeout_s", 0.3)
    r = PumaVAL(port, **kw)
    r.connect()
    return r, port


# --- connecting ----------------------------------------------------------------------------------------
def test_construct_does_no_io_and_connect_sends_one_cr():
    port = ScriptedPort([SYNC])
    r = PumaVAL(port)
    assert port.written == [] and not r.connected
    r.connect()
    r.connect()  # idempotent
    assert port.written == [b"\r"] and r.connected
    r.close()
    r.close()
    assert not r.connected


def test_connect_over_loop_url_times_out_without_a_prompt():
    # loop:// returns our own CR: a line end, never a prompt
    r = PumaVAL("loop://", timeout_s=0.2)
    with pytest.raises(DeviceTimeout, match="no prompt"):
        r.connect()
    assert not r.connected


def test_bad_arguments_are_named():
    with pytest.raises(ConfigError, match="robot URL"):
        PumaVAL("")
    for t in (0, float("inf"), True):
        with pytest.raises(ConfigError, match="timeout_s"):
            PumaVAL("loop://", timeout_s=t)
    for b in (0, True, 9600.0):
        with pytest.raises(ConfigError, match="baudrate"):
            PumaVAL("loop://", baudrate=b)
    with pytest.raises(ConfigError, match="protocol 'nope'"):
        PumaVAL("nope://x").connect()


def test_command_before_connect_is_a_device_error():
    with pytest.raises(DeviceError, match="not open"):
        PumaVAL(ScriptedPort([])).where()


# --- WHERE in its variants -----------------------------------------------------------------------------
def check_where(w):
    assert w.pose == POSE and w.joints == JOINTS
    assert all(v != 0 for v in w.pose + w.joints)
    np.testing.assert_allclose(w.base_H_T, VAL.pose_to_H(POSE), atol=1e-12)


def test_where_typed_echoed_then_executed():
    r, port = robot(where())
    check_where(r.where())
    assert port.written == [b"\r", b"WHERE", b"\r"]


def test_where_without_echo_and_with_lf_endings():
    d = ValDialect(echo=False, controller_eol="\n")
    r, port = robot([(b"WHERE\r", where_reply(eol=b"\n"))], dialect=d)
    check_where(r.where())
    assert port.written == [b"\r", b"WHERE\r"]  # no echo to compare: typed and executed at once


def test_where_with_a_pause_inside_a_number_is_not_a_prompt():
    whole = where_reply()
    cut = whole.index(b"337.") + 4  # the line stops at "337." for far longer than the prompt silence
    r, port = robot([(b"WHERE", b"WHERE"), (b"\r", [(0.0, whole[:cut]), (0.08, whole[cut:])])])
    check_where(r.where())


def test_prompt_right_after_the_last_number():
    reply = where_reply()
    assert reply.endswith(b"-155.93\r\n.")
    r, _ = robot([(b"WHERE", b"WHERE"), (b"\r", [(0.0, reply[:-1]), (0.03, reply[-1:])])])
    check_where(r.where())


@pytest.mark.parametrize(
    "old, new, match",
    [(b"   337.04", b"  337.04", "fields of 9 characters"), (b"        Z", b"       Z", "expected the header")],
    ids=["in a value", "in a header"],
)
def test_where_with_a_dropped_character_is_a_protocol_error_then_resync(old, new, match):
    bad = where_reply().replace(old, new, 1)
    r, port = robot([*typed(b"WHERE", bad), SYNC, *where()])
    with pytest.raises(ProtocolError, match=match):
        r.where()
    check_where(r.where())
    assert port.written == [b"\r", b"WHERE", b"\r", b"\r", b"WHERE", b"\r"]


def test_garbage_bytes_are_a_protocol_error_then_resync():
    bad = bytearray(where_reply())
    bad[30] ^= 0x80
    r, port = robot([*typed(b"WHERE", bytes(bad)), SYNC, *where()])
    with pytest.raises(ProtocolError, match="garbage"):
        r.where()
    check_where(r.where())


def test_missing_prompt_is_a_protocol_error():
    r, port = robot([*typed(b"WHERE", where_reply()[:-1] + b"#"), SYNC, *where()])
    with pytest.raises(ProtocolError, match="without the prompt"):
        r.where()
    check_where(r.where())
    assert port.written[-3:] == [b"\r", b"WHERE", b"\r"]


def test_silence_is_a_device_timeout_then_resync():
    r, port = robot([*typed(b"WHERE", b""), SYNC, *where()])
    with pytest.raises(DeviceTimeout, match="no reply to 'WHERE'"):
        r.where()
    check_where(r.where())
    assert port.written == [b"\r", b"WHERE", b"\r", b"\r", b"WHERE", b"\r"]


def test_the_program_prompt_is_named_instead_of_a_timeout():
    r, port = robot([*typed(b"WHERE", CRLF + b"*")], timeout_s=5.0)
    t0 = time.monotonic()
    with pytest.raises(ProgramRunning, match="program is running"):
        r.where()
    assert time.monotonic() - t0 < r.timeout_s  # said at once, not after the 5 s wait


# --- WHERE's pose against the kinematics of its own joints ---------------------------------------------
def swapped(pose, i, a, b) -> tuple:
    """``pose`` with two digits of value ``i`` swapped (a digit swap on the line)."""
    txt = list(f"{pose[i]:.2f}")
    txt[a], txt[b] = txt[b], txt[a]
    return pose[:i] + (float("".join(txt)),) + pose[i + 1 :]


@pytest.mark.parametrize("where_bad", ["pose", "joints"])
def test_a_digit_swap_in_where_is_read_again(where_bad):
    bad_pose = swapped(POSE, 0, 1, 2) if where_bad == "pose" else POSE  # 337.04 -> 373.04
    bad_joints = swapped(JOINTS, 1, 1, 2) if where_bad == "joints" else JOINTS  # -143.39 -> -134.39
    r, port = robot([*where(bad_joints, bad_pose), *where()])
    check_where(r.where())
    assert port.written.count(b"WHERE") == 2


def test_where_that_never_agrees_with_its_joints_is_refused():
    bad = swapped(POSE, 2, 1, 2)  # z 102.64 -> 120.64
    r, port = robot([*where(JOINTS, bad)] * 3 + [SYNC, *where()])
    with pytest.raises(ProtocolError, match="from the kinematics of its own joint angles"):
        r.where()
    check_where(r.where())


def test_a_wrong_oat_convention_is_named_on_the_first_where():
    # a controller printing O/A/T the V+ way, a driver expecting VAL's: refused before anything moves
    vplus = ValDialect(euler=OAT_CONVENTIONS["vplus"])
    pose = tuple(round(v, 2) for v in vplus.H_to_pose(KIN.fk(JOINTS) @ TOOL))
    r, _ = robot([*where(JOINTS, pose)] * 3)
    with pytest.raises(ConfigError, match="'vplus' convention.*euler: vplus"):
        r.where()
    r2, _ = robot(where(JOINTS, pose), dialect=vplus)
    assert r2.where().joints == JOINTS


def test_the_where_layout_is_dialect_data():
    # a controller that prints a seventh column (here a hand opening) in the joint line
    d = ValDialect(joint_header=("JT1", "JT2", "JT3", "JT4", "JT5", "JT6", "HAND"))
    reply = CRLF + CRLF.join([HDR, vals(*POSE), JHDR + b"     HAND", vals(*JOINTS, 12.5)]) + CRLF + b"."
    r, _ = robot(typed(b"WHERE", reply), dialect=d)
    check_where(r.where())
    r2, _ = robot(typed(b"WHERE", reply) + [SYNC])
    with pytest.raises(ProtocolError, match="expected the header"):
        r2.where()  # the default layout refuses it, naming why


# --- error lines ----------------------------------------------------------------------------------------
def test_error_lines_map_through_the_table():
    cases = [
        (b"*Arm power off*", ArmPowerOff),
        (b"*Location out of reach*", OutOfReach),
        (b"*Joint 3 limit stop*", JointLimit),
        (b"*Unrecognized command*", CommandRejected),
        (b"*Bad karma*", ControllerError),
    ]
    script = [x for line, _ in cases for x in typed(b"SPEED (10)", CRLF + line + b"\r\n.")]
    r, port = robot(script)
    for line, cls in cases:
        with pytest.raises(cls) as ei:
            r.speed(10)
        assert type(ei.value) is cls
        assert ei.value.text == line.strip(b"*").decode() and ei.value.command == "SPEED (10)"


def test_asynchronous_error_line_is_raised_before_the_next_command_is_sent():
    r, port = robot(where())
    port.push(b"\r\n*Arm power off*\r\n.")
    with pytest.raises(ArmPowerOff) as ei:
        r.where()
    assert ei.value.command is None and "asynchronous" in str(ei.value)
    assert port.written == [b"\r"]  # WHERE was not sent
    check_where(r.where())


# --- commands, byte for byte ---------------------------------------------------------------------------
def test_calibrate_answers_the_question_with_yes():
    script = [*where(), (b"CAL", b"CAL"), (b"\r", CRLF + b"Are you sure (Y/N)? "), (b"Y", b"Y"), (b"\r", [(0.0, CRLF), (0.05, b".")])]
    r, port = robot(script)
    r.calibrate()
    assert port.written[-4:] == [b"CAL", b"\r", b"Y", b"\r"]


def test_calibrate_without_echo():
    d = ValDialect(echo=False)
    r, port = robot([(b"WHERE\r", where_reply()), (b"CAL\r", b"\r\nAre you sure (Y/N)? "), (b"Y\r", b"\r\n.")], dialect=d)
    r.calibrate()
    assert port.written[-2:] == [b"CAL\r", b"Y\r"]


def test_calibrate_and_ready_outside_the_workspace_are_refused():
    lim = ValLimits(workspace_mm=((-600, 600), (-600, 600), (0, 900)))  # READY's tool point is at z = 965
    r, port = robot([*where(READY_DEG)], limits=lim)
    with pytest.raises(LimitError, match="READY"):
        r.ready()
    with pytest.raises(LimitError, match="CAL"):
        r.calibrate()  # from READY, outside this box
    assert b"CAL" not in port.written and not any(w.startswith(b"DO READY") for w in port.written)


def test_unexpected_question_is_a_protocol_error_and_resync_answers_it():
    script = [*typed(b"SPEED (20)", CRLF + b"Really (Y/N)? "), (b"\r", b"\r\n."), *typed(b"SPEED (20)", b"\r\n."), *status(20)]
    r, port = robot(script)
    with pytest.raises(ProtocolError, match="unexpected question"):
        r.speed(20)
    r.speed(20)


def test_speed_is_read_back_and_limited():
    script = [*typed(b"SPEED (30)", b"\r\n."), *status(30), *typed(b"SPEED (12.5)", b"\r\n."), *status(12.5)]
    r, port = robot(script, limits=ValLimits(max_speed_pct=40))
    r.speed(30)
    r.speed(12.5)
    for bad in (41, 0, -5, float("nan")):
        with pytest.raises(LimitError, match="nothing was sent"):
            r.speed(bad)
    assert [w for w in port.written if w.startswith(b"SPEED")] == [b"SPEED (30)", b"SPEED (12.5)"]


def test_a_speed_the_controller_does_not_hold_is_an_error():
    r, port = robot([*typed(b"SPEED (20)", b"\r\n."), *status(2)])
    with pytest.raises(ProtocolError, match="reads back SPEED 2, not 20"):
        r.speed(20)


def test_an_echo_that_differs_after_its_first_word_is_erased_before_it_runs():
    # 'SPEED (02)' for 'SPEED (20)': the first word matches, the line does not; CTRL-U, never CR
    r, port = robot([(b"SPEED (20)", b"SPEED (02)"), (b"\x15", b""), SYNC, *typed(b"SPEED (20)", b"\r\n."), *status(20)])
    with pytest.raises(ProtocolError, match="echo of 'SPEED \\(20\\)' came back as b'SPEED \\(02\\)'.*nothing ran"):
        r.speed(20)
    assert port.written == [b"\r", b"SPEED (20)", b"\x15"]  # no CR after the corrupted line
    r.speed(20)


def test_a_corrupted_motion_command_never_runs():
    p1 = VAL.pose_to_H(POSE)
    script = [*point(b"p1"), *where(), *status(20)]
    script += [(b"DO APPRO p1, (50)", b"DO APPRO p1, (20)"), (b"\x15", b"")]
    r, port = robot(script)
    with pytest.raises(ProtocolError, match="nothing ran"):
        r.appro("p1", 50)
    assert port.written[-2:] == [b"DO APPRO p1, (50)", b"\x15"]  # no CR, and no ABORT: nothing started
    assert p1 is not None


def test_a_line_end_noise_put_inside_a_motion_line_stops_the_arm_first():
    # noise turned a byte into CR inside the line: the controller executed 'DO APPRO p1, (5'. The default templates
    # make that a syntax error (no prefix of a motion line is valid), but a dialect may not (bare numbers from a
    # lab's YAML: 'DO APPRO p1, 5' of 'DO APPRO p1, 50' is a real motion). So never "nothing ran": ABORT goes out at once, before anything else (no CTRL-U first), and the error says the line may have run
    script = [*point(b"p1"), *where(), *status(20)]
    script += [(b"DO APPRO p1, (50)", b"DO APPRO p1, (5\r\n"), (b"\x15ABORT\r", b"ABORT\r\n*Motion aborted*\r\n.")]
    r, port = robot(script)
    with pytest.raises(ProtocolError, match=r"a line end reached the controller.*may have run.*ABORT sent and confirmed"):
        r.appro("p1", 50)
    assert port.written[-2:] == [b"DO APPRO p1, (50)", b"\x15ABORT\r"]


def test_speed_with_unexpected_text_is_a_protocol_error():
    r, port = robot([*typed(b"SPEED (30)", b"\r\nhello\r\n."), SYNC])
    with pytest.raises(ProtocolError, match="unexpected reply"):
        r.speed(30)


def point_reply(pose) -> bytes:
    return CRLF + HDR + CRLF + vals(*pose) + CRLF + b"Change? "


def define_line(name: str, pose) -> bytes:
    return VAL.command("define", name=name, **dict(zip("xyzoat", VAL.H_to_pose(VAL.pose_to_H(pose))))).encode()


def test_define_from_pose_and_from_matrix():
    line = b"DO SET p1 = (TRANS(350, 20, 100, 30, 60, 40))"
    r, port = robot([*typed(line, b"\r\n."), *typed(line, b"\r\n.")])
    r.define("p1", (350, 20, 100, 30, 60, 40))
    r.define("p1", VAL.pose_to_H((350, 20, 100, 30, 60, 40)))
    assert port.written == [b"\r", line, b"\r", line, b"\r"]


def test_define_rejects_bad_names_poses_and_points_outside_the_box():
    r, port = robot([])
    with pytest.raises(ConfigError, match="location name"):
        r.define("1abc", POSE)
    with pytest.raises(ConfigError, match="6 numbers"):
        r.define("p1", (1, 2, 3))
    with pytest.raises(ConfigError, match="not a rigid transform"):
        r.define("p1", np.diag([1.0, 1.0, 2.0, 1.0]))
    with pytest.raises(LimitError, match="x = 900.00 mm"):
        r.define("p1", (900, 0, 100, 30, 60, 40))
    assert port.written == [b"\r"]


def test_point_reads_a_location_and_answers_change_with_an_empty_line():
    r, port = robot(point(b"p1"))
    assert r.location("p1") == POSE
    assert port.written == [b"\r", b"POINT p1", b"\r", b"\r", b"POINT p1", b"\r", b"\r"]  # read until two agree


def test_a_corrupted_location_is_read_again_until_two_replies_agree():
    bad = (POSE[0] + 180.0,) + POSE[1:]  # one digit of X changed on the line
    once = lambda pose: [*typed(b"POINT p1", point_reply(pose)), (b"\r", b"\r\n.")]  # noqa: E731
    r, port = robot([*once(bad), *once(POSE), *once(POSE)])
    assert r.location("p1") == POSE
    r, port = robot([*once(bad), *once(POSE), *once(bad), *once(POSE)])
    with pytest.raises(ProtocolError, match="no two replies in a row agree"):
        r.location("p1")


def test_here_records_and_returns_the_pose():
    r, port = robot([*typed(b"HERE p2", point_reply(POSE)), (b"\r", b"\r\n.")])
    assert r.here("p2") == POSE


# --- motions ------------------------------------------------------------------------------------------------
def point(name: bytes, pose=POSE) -> list:
    """A location read: POINT until two replies in a row agree (twice when the line is clean)."""
    return [*typed(b"POINT " + name, point_reply(pose)), (b"\r", b"\r\n.")] * 2


def motion(cmd: bytes, arrive=JOINTS, *, start=JOINTS, speed=20) -> list:
    """WHERE (start), STATUS (before every motion), the motion (prompt after 50 ms), CR answered, WHERE at the end."""
    out = [*where(start)]
    if speed is not None:
        out += status(speed)
    out += [(cmd, cmd), (b"\r", [(0.0, CRLF), (0.05, b".")]), (b"\r", b"\r\n."), *where(arrive)]
    return out


def test_move_reads_its_target_from_the_controller_each_time():
    r, port = robot([*point(b"p1"), *motion(b"DO MOVE (p1)"), *point(b"p1"), *motion(b"DO MOVE (p1)")])
    r.move("p1")
    r.move("p1")
    assert port.written.count(b"POINT p1") == 4  # never a cached copy (each read twice)


def test_a_relocated_target_outside_the_box_is_refused():
    far = (POSE[0] + 400.0,) + POSE[1:]
    r, port = robot([*point(b"p1"), *motion(b"DO MOVE (p1)"), *point(b"p1", far)])
    r.move("p1")
    with pytest.raises(LimitError, match="outside the workspace"):
        r.move("p1")  # re-taught on the controller since: read again, refused
    assert port.written.count(b"DO MOVE (p1)") == 1


def test_moves_to_a_pose_goes_through_the_scratch_location():
    target = (300.0, 0.0, 150.0, 90.0, 90.0, 0.0)
    q = joints_at(VAL.pose_to_H(target))
    r, port = robot([*typed(define_line("svtgt", target), b"\r\n."), *motion(b"DO MOVES (svtgt)", arrive=q)])
    r.moves(target)
    assert b"DO MOVES (svtgt)" in port.written


def test_appro_depart_drive_ready_bytes():
    goal = VAL.pose_to_H(POSE) @ trans(0, 0, -30)
    q_appro = joints_at(goal)
    q_depart = joints_at(VAL.pose_to_H(pose_of(q_appro)) @ trans(0, 0, -50), q_appro)
    q_drive = tuple(round(v, 2) for v in np.add(q_depart, (0, -10.5, 0, 0, 0, 0)))
    script = point(b"p1") + motion(b"DO APPRO p1, (30)", arrive=q_appro)
    script += [*where(q_appro), *status(20), (b"DO DEPART (50)", b"DO DEPART (50)"), (b"\r", [(0.0, CRLF), (0.05, b".")]), (b"\r", b"\r\n."), *where(q_depart)]
    script += motion(b"DO DRIVE 2, (-10.5), (20)", arrive=q_drive, start=q_depart)
    script += motion(b"DO READY", arrive=READY_DEG, start=q_drive)
    r, port = robot(script)
    r.appro("p1", 30)
    r.depart(50)
    r.drive(2, -10.5, 20)
    r.ready()
    assert [w for w in port.written if w.startswith(b"DO ")] == [
        b"DO APPRO p1, (30)",
        b"DO DEPART (50)",
        b"DO DRIVE 2, (-10.5), (20)",
        b"DO READY",
    ]


def test_motion_limits_are_checked_before_sending():
    lim = ValLimits(workspace_mm=((-400, 400), (-400, 400), (20, 600)), max_speed_pct=30)
    low = (POSE[0], POSE[1], 60.0) + POSE[3:]
    r, port = robot([*point(b"p1", low), *where(), *where()], limits=lim)
    with pytest.raises(LimitError, match="distance -100 mm.*beyond the location"):
        r.appro("p1", -100)  # beyond p1 along its approach: refused before anything is read or sent
    with pytest.raises(LimitError, match=r"APPRO p1, 700: z = 7\d\d.\d\d mm is outside the workspace"):
        r.appro("p1", 700)  # the tool z points (nearly) down: 700 mm back along it is above z = 600
    with pytest.raises(LimitError, match=r"DEPART 600: z = 69\d.\d\d mm"):
        r.depart(600)  # the tool z points (nearly) down: 600 mm back along it is ~590 mm up
    with pytest.raises(LimitError, match="JT1 would reach 224.07"):
        r.drive(1, 200, 10)
    with pytest.raises(LimitError, match="speed 50"):
        r.drive(1, 10, 50)
    with pytest.raises(ConfigError, match="DRIVE joint"):
        r.drive(7, 10, 10)
    for deg in ("ten", None, float("nan")):
        with pytest.raises(ConfigError, match="DRIVE angle: expected a finite number of degrees"):
            r.drive(1, deg, 10)
    with pytest.raises(LimitError, match="x = 500.00"):
        r.move((500, 0, 100, 90, 90, 0))
    assert not any(w.startswith((b"DO APPRO", b"DO DEPART", b"DO DRIVE", b"DO MOVE")) for w in port.written)


def test_one_noise_prompt_does_not_end_a_motion():
    # a '.' at the start of a line 10 ms into the move; the real end comes 0.3 s later
    script = [*point(b"p1"), *where(), *status(20), (b"DO MOVE (p1)", b"DO MOVE (p1)")]
    script += [(b"\r", [(0.0, CRLF), (0.01, b".")])]  # the noise: looks like the prompt
    script += [(b"\r", [(0.3, b"."), (0.0, CRLF + b".")])]  # our CR waits behind the motion's real end
    script += where()
    r, port = robot(script)
    t0 = time.monotonic()
    r.move("p1")
    i = port.written.index(b"DO MOVE (p1)")
    assert port.written[i + 1 : i + 4] == [b"\r", b"\r", b"WHERE"]
    assert port.write_times[i + 3] - t0 >= 0.3  # WHERE only after the controller's real prompt


def test_a_prompt_with_the_arm_short_of_its_target_is_an_error_and_aborts():
    elsewhere = tuple(round(v, 2) for v in np.add(JOINTS, (8.0, 0, 0, 0, 0, 0)))
    script = [*point(b"p1"), *where(), *status(20), (b"DO MOVE (p1)", b"DO MOVE (p1)"), (b"\r", [(0.0, CRLF), (0.01, b".")])]
    script += [(b"\r", b"\r\n."), *where(elsewhere), (b"\x15ABORT\r", b"ABORT\r\n*Motion aborted*\r\n.")]
    r, port = robot(script)
    with pytest.raises(ProtocolError, match="WHERE puts the arm .* from its target.*ABORT sent and confirmed"):
        r.move("p1")
    assert port.written[-1] == b"\x15ABORT\r"


def test_a_motion_that_ends_turned_from_its_target_is_not_arrived():
    # the arm at the target's point but the hand turned 5 deg about its own axis (JT6): the tool point is
    # where it should be, the orientation is not, so the motion has not arrived
    turned = tuple(round(v, 2) for v in np.add(JOINTS, (0, 0, 0, 0, 0, 5.0)))
    script = [*point(b"p1"), *where(), *status(20), (b"DO MOVE (p1)", b"DO MOVE (p1)"), (b"\r", [(0.0, CRLF), (0.01, b".")])]
    script += [(b"\r", b"\r\n."), *where(turned), (b"\x15ABORT\r", b"ABORT\r\n*Motion aborted*\r\n.")]
    r, port = robot(script)
    with pytest.raises(ProtocolError, match="from its target.*ABORT sent and confirmed"):
        r.move("p1")
    assert port.written[-1] == b"\x15ABORT\r"


def test_a_motion_that_outlasts_its_wait_is_aborted_first_thing():
    lim = ValLimits(timeout_factor=0.001, timeout_margin_s=0.2)  # a wait far shorter than the motion
    script = [*point(b"p1"), *where(), *status(20), (b"DO MOVE (p1)", b"DO MOVE (p1)"), (b"\r", CRLF)]
    script += [(b"\x15ABORT\r", b"ABORT\r\n*Motion aborted*\r\n.")]
    r, port = robot(script, limits=lim)
    with pytest.raises(DeviceTimeout, match="ABORT sent and confirmed"):
        r.move("p1")
    # ABORT went out right after the motion's CR: no resynchronising CR before it
    assert port.written[-3:] == [b"DO MOVE (p1)", b"\r", b"\x15ABORT\r"]


def test_an_abort_that_gets_no_answer_says_so():
    lim = ValLimits(timeout_factor=0.001, timeout_margin_s=0.2)
    script = [*point(b"p1"), *where(), *status(20), (b"DO MOVE (p1)", b"DO MOVE (p1)"), (b"\r", CRLF)]
    script += [(b"\x15ABORT\r", b"")]  # the reply path has stalled
    r, port = robot(script, limits=lim)
    with pytest.raises(DeviceTimeout, match="ABORT sent, NOT confirmed"):
        r.move("p1")
    assert port.written[-1] == b"\x15ABORT\r"


def test_idle_abort_is_written_at_once_and_confirmed():
    r, port = robot([(b"\x15ABORT\r", b"ABORT\r\n.")])
    res = r.abort()
    assert res.written and res.confirmed and "prompt" in res.detail
    assert port.written == [b"\r", b"\x15ABORT\r"]


def test_abort_on_a_closed_link_is_reported_not_raised():
    r, port = robot([])
    r.close()
    res = r.abort()
    assert not res.written and "closed" in str(res)


def test_abort_from_another_thread_interrupts_a_waiting_move():
    # the controller echoes the move, then stays silent until it reads ABORT
    script = [*point(b"p1"), *where(), *status(20), (b"DO MOVE (p1)", b"DO MOVE (p1)"), (b"\r", CRLF)]
    script += [(b"\x15ABORT\r", b"ABORT\r\n*Motion aborted*\r\n.")]
    r, port = robot(script, timeout_s=1.0)
    result = {}
    sent = threading.Event()

    def mover():
        try:
            r.move("p1")
        except Exception as exc:  # collected for the assertion below
            result["exc"] = exc

    orig = port.write

    def spy(data):
        n = orig(data)
        if data == b"\r" and port.written[-2:-1] == [b"DO MOVE (p1)"]:
            sent.set()
        return n

    port.write = spy
    t = threading.Thread(target=mover)
    t.start()
    assert sent.wait(5.0)
    res = r.abort()
    t.join(5.0)
    assert not t.is_alive()
    assert isinstance(result.get("exc"), MotionAborted)
    assert res.confirmed and "Motion aborted" in res.detail
    assert port.written[-2:] == [b"\r", b"\x15ABORT\r"]


# --- the dialect is data -----------------------------------------------------------------------------
def test_dialect_from_yaml_changes_commands_errors_and_layout(tmp_path):
    f = tmp_path / "dialect.yaml"
    f.write_text(
        "echo: false\n"
        "field_width: null\n"
        "errors: [['Power is off', ArmPowerOff]]\n"
        "commands: {where: 'W', speed: 'SP {pct}'}\n"
        "euler: {sequence: zyx}\n"
    )
    d = load_dialect(f)
    pose = tuple(round(v, 2) for v in d.H_to_pose(KIN.fk(JOINTS) @ TOOL))
    body = " ".join(f"{v:.2f}" for v in pose) + "\r\n" + "JT1 JT2 JT3 JT4 JT5 JT6\r\n" + " ".join(f"{v:.2f}" for v in JOINTS)
    reply = b"\r\nX Y Z O A T\r\n" + body.encode() + b"\r\n."
    r, port = robot([(b"W\r", reply), (b"SP 5\r", b"\r\n*Power is off*\r\n.")], dialect=d)
    w = r.where()
    assert w.pose == pose and w.joints == JOINTS
    o, a, t = (np.radians(v) for v in pose[3:])
    np.testing.assert_allclose(w.base_H_T[:3, :3], R_from_rpy(t, a, o), atol=1e-12)  # Rz(O) Ry(A) Rx(T)
    assert np.degrees(rotation_angle(w.base_H_T[:3, :3].T @ VAL.pose_to_H(w.pose)[:3, :3])) > 10  # not VAL's
    with pytest.raises(ArmPowerOff):
        r.speed(5)
    assert port.written == [b"\r", b"W\r", b"SP 5\r"]


def test_named_oat_conventions():
    assert ValDialect.from_dict({"euler": "vplus"}).euler == OAT_CONVENTIONS["vplus"]
    val = ValDialect()
    # VAL: all zero = the hand along -Y, fingers horizontal; READY (tool up) is O 90, A -90, T 0
    np.testing.assert_allclose(val.pose_to_H((0, 0, 0, 0, 0, 0))[:3, 2], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(val.H_to_pose(KIN.fk(READY_DEG) @ TOOL)[3:], (90, -90, 0), atol=1e-9)
    np.testing.assert_allclose(val.pose_to_H((0, 0, 0, 90, 90, 0))[:3, 2], [0, 0, -1], atol=1e-12)  # tool down
    with pytest.raises(ConfigError, match="not one of val, vplus"):
        ValDialect.from_dict({"euler": "kuka"})


@pytest.mark.parametrize(
    "data, match",
    [
        ({"prompt": ".."}, "dialect.prompt"),
        ({"program_prompt": "."}, "must differ"),
        ({"errors": [["x", "NoSuchError"]]}, "unknown class"),
        ({"commands": {"move": "DO MOVE"}}, "must use the fields"),
        ({"colour": 1}, "unknown key"),
        ({"euler": {"sequence": "zzy"}}, "euler sequence"),
        ({"joint_header": ["J1", "J2", "J3", "J4", "J5", "J6"]}, "joint_header"),
        ({"where_lines": ["pose", "pose_header", "joint_header", "joints"]}, "where_lines"),
        ({"status_speed": "speed (\\d+)"}, "status_speed"),
    ],
)
def test_bad_dialects_are_named(data, match):
    with pytest.raises(ConfigError, match=match):
        ValDialect.from_dict(data)


def test_limits_from_yaml(tmp_path):
    f = tmp_path / "limits.yaml"
    f.write_text("workspace_mm: [[0, 500], [-300, 300], [10, 600]]\nmax_speed_pct: 25\n")
    lim = ValLimits.load(f)
    assert lim.max_speed_pct == 25 and lim.workspace_mm[2] == (10.0, 600.0)
    with pytest.raises(LimitError, match="y = 400.00 mm"):
        lim.check_position((100, 400, 100), "target")
    f.write_text("max_sped_pct: 25\n")
    with pytest.raises(ConfigError, match="unknown key.*max_sped_pct"):
        ValLimits.load(f)
    f.write_text("workspace_mm: [[10, 0], [0, 1], [0, 1]]\n")
    with pytest.raises(ConfigError, match="min < max"):
        ValLimits.load(f)
    with pytest.raises(ConfigError, match="cannot read"):
        ValLimits.load(tmp_path / "missing.yaml")


def test_kinematics_agree_with_the_simulators_and_load_from_yaml(tmp_path, rng):
    from selfview.drivers.puma_val_serial import PumaKinematics

    k = PumaKinematics()
    lims = np.array(KIN.geometry.joint_limits_deg)
    for q in rng.uniform(lims[:, 0], lims[:, 1], size=(50, 6)):
        # two implementations of one chain: agreement to a micrometre
        assert np.abs(k.tool(q)[:3, 3] - (KIN.fk(q) @ TOOL)[:3, 3]).max() < 1e-3
    f = tmp_path / "kin.yaml"
    f.write_text("tool_mm: [0, 0, 120]\n")
    assert PumaKinematics.load(f).tool_mm == (0.0, 0.0, 120.0)
    f.write_text("tool_mm: [0, 0]\n")
    with pytest.raises(ConfigError, match="tool_mm"):
        PumaKinematics.load(f)
