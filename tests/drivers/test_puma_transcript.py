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
from selfview.errors import ConfigError, DeviceTimeout, LimitError, ProtocolError
from selfview.geometry import H_from_xyzoat, R_from_rpy, rotation_angle

CRLF = b"\r\n"
HDR = b"        X        Y        Z        O        A        T"
JHDR = b"      JT1      JT2      JT3      JT4      JT5      JT6"


def vals(*v) -> bytes:
    return "".join(f"{x:9.2f}" for x in v).encode()


POSE = (350.0, 20.0, 100.0, 0.0, 180.0, 0.0)
JOINTS = (24.07, -143.39, 24.5, -180.0, 61.11, -155.93)


def where_reply(pose=POSE, joints=JOINTS, *, echo=True, eol=CRLF) -> bytes:
    head = b"WHERE" + eol if echo else eol
    return head + eol.join([HDR, vals(*pose), JHDR, vals(*joints)]) + eol + b"."


class ScriptedPort:
    """A serial-like port: each write must equal the next scripted line; its reply is then released,
    as one chunk or as (delay_s, bytes) chunks. ``push`` delivers bytes nobody asked for."""

    def __init__(self, script):
        self.script = list(script)
        self.written: list[bytes] = []
        self.timeout = 0.01
        self._rx = bytearray()
        self._pending: list[tuple[float, bytes]] = []
        self._cv = threading.Condition()

    def write(self, data: bytes) -> int:
        with self._cv:
            self.written.append(bytes(data))
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
    with pytest.raises(ConfigError, match="timeout_s"):
        PumaVAL("loop://", timeout_s=0)
    with pytest.raises(ConfigError, match="protocol 'nope'"):
        PumaVAL("nope://x").connect()


def test_command_before_connect_is_a_device_error():
    with pytest.raises(Exception, match="not open"):
        PumaVAL(ScriptedPort([])).where()


# --- WHERE in its variants -----------------------------------------------------------------------------
def check_where(w):
    assert w.pose == POSE and w.joints == JOINTS
    np.testing.assert_allclose(w.base_H_T, H_from_xyzoat(POSE), atol=1e-12)


def test_where_with_echo_and_crlf():
    r, port = robot([(b"WHERE\r", where_reply())])
    check_where(r.where())
    assert port.written == [b"\r", b"WHERE\r"]


def test_where_without_echo_and_with_lf_endings():
    r, port = robot([(b"WHERE\r", where_reply(echo=False, eol=b"\n"))])
    check_where(r.where())


def test_where_with_a_pause_inside_a_number_is_not_a_prompt():
    whole = where_reply()
    cut = whole.index(b"350.") + 4  # the line stops at "350." for far longer than the prompt silence
    r, port = robot([(b"WHERE\r", [(0.0, whole[:cut]), (0.08, whole[cut:])])])
    check_where(r.where())


def test_prompt_right_after_the_last_number():
    reply = where_reply()
    assert reply.endswith(b"-155.93\r\n.")
    r, _ = robot([(b"WHERE\r", [(0.0, reply[:-1]), (0.03, reply[-1:])])])
    check_where(r.where())


@pytest.mark.parametrize(
    "old, new, match",
    [(b"   350.00", b"  350.00", "fields of 9 characters"), (b"        Z", b"       Z", "expected the header")],
    ids=["in a value", "in a header"],
)
def test_where_with_a_dropped_character_is_a_protocol_error_then_resync(old, new, match):
    bad = where_reply().replace(old, new, 1)
    r, port = robot([(b"WHERE\r", bad), SYNC, (b"WHERE\r", where_reply())])
    with pytest.raises(ProtocolError, match=match):
        r.where()
    check_where(r.where())
    assert port.written == [b"\r", b"WHERE\r", b"\r", b"WHERE\r"]


def test_garbage_bytes_are_a_protocol_error_then_resync():
    bad = bytearray(where_reply())
    bad[30] ^= 0x80
    r, port = robot([(b"WHERE\r", bytes(bad)), SYNC, (b"WHERE\r", where_reply())])
    with pytest.raises(ProtocolError, match="garbage"):
        r.where()
    check_where(r.where())


def test_missing_prompt_is_a_protocol_error():
    r, port = robot([(b"WHERE\r", where_reply()[:-1] + b"#"), SYNC, (b"WHERE\r", where_reply())])
    with pytest.raises(ProtocolError, match="without the prompt"):
        r.where()
    check_where(r.where())
    assert port.written[-2:] == [b"\r", b"WHERE\r"]


def test_silence_is_a_device_timeout_then_resync():
    r, port = robot([(b"WHERE\r", b""), SYNC, (b"WHERE\r", where_reply())])
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match="no reply to 'WHERE'"):
        r.where()
    assert time.monotonic() - t0 < r.timeout_s + 1.0  # ends within its timeout (+ slack), never hangs
    check_where(r.where())
    assert port.written == [b"\r", b"WHERE\r", b"\r", b"WHERE\r"]


# --- error lines ----------------------------------------------------------------------------------------
def test_error_lines_map_through_the_table():
    cases = [
        (b"*Arm power off*", ArmPowerOff),
        (b"*Location out of reach*", OutOfReach),
        (b"*Joint 3 limit stop*", JointLimit),
        (b"*Unrecognized command*", CommandRejected),
        (b"*Bad karma*", ControllerError),
    ]
    script = [(b"SPEED 10\r", b"SPEED 10\r\n" + line + b"\r\n.") for line, _ in cases]
    r, port = robot(script)
    for line, cls in cases:
        with pytest.raises(cls) as ei:
            r.speed(10)
        assert type(ei.value) is cls
        assert ei.value.text == line.strip(b"*").decode() and ei.value.command == "SPEED 10"


def test_asynchronous_error_line_is_raised_before_the_next_command_is_sent():
    r, port = robot([(b"WHERE\r", where_reply())])
    port.push(b"\r\n*Arm power off*\r\n.")
    with pytest.raises(ArmPowerOff) as ei:
        r.where()
    assert ei.value.command is None and "asynchronous" in str(ei.value)
    assert port.written == [b"\r"]  # WHERE was not sent
    check_where(r.where())


# --- commands, byte for byte ---------------------------------------------------------------------------
def test_calibrate_answers_the_question_with_yes():
    r, port = robot([(b"CAL\r", b"CAL\r\nAre you sure (Y/N)? "), (b"Y\r", [(0.0, b"Y\r\n"), (0.05, b".")])])
    r.calibrate()
    assert port.written == [b"\r", b"CAL\r", b"Y\r"]


def test_calibrate_without_echo():
    r, port = robot([(b"CAL\r", b"\r\nAre you sure (Y/N)? "), (b"Y\r", b"\r\n.")])
    r.calibrate()
    assert port.written[-2:] == [b"CAL\r", b"Y\r"]


def test_unexpected_question_is_a_protocol_error_and_resync_answers_it():
    r, port = robot([(b"SPEED 20\r", b"SPEED 20\r\nReally (Y/N)? "), (b"\r", b"\r\n."), (b"SPEED 20\r", b"SPEED 20\r\n.")])
    with pytest.raises(ProtocolError, match="unexpected question"):
        r.speed(20)
    r.speed(20)
    assert port.written == [b"\r", b"SPEED 20\r", b"\r", b"SPEED 20\r"]


def test_speed_and_its_limit():
    r, port = robot([(b"SPEED 30\r", b"SPEED 30\r\n."), (b"SPEED 12.5\r", b"\r\n.")], limits=ValLimits(max_speed_pct=40))
    r.speed(30)
    r.speed(12.5)
    for bad in (41, 0, -5, float("nan")):
        with pytest.raises(LimitError, match="nothing was sent"):
            r.speed(bad)
    assert port.written == [b"\r", b"SPEED 30\r", b"SPEED 12.5\r"]


def test_speed_with_unexpected_text_is_a_protocol_error():
    r, port = robot([(b"SPEED 30\r", b"SPEED 30\r\nhello\r\n."), SYNC])
    with pytest.raises(ProtocolError, match="unexpected reply"):
        r.speed(30)


def point_reply(name: bytes, pose, *, echo=True) -> bytes:
    return (name if echo else b"") + CRLF + HDR + CRLF + vals(*pose) + CRLF + b"Change? "


def test_define_from_pose_and_from_matrix():
    line = b"DO SET p1 = TRANS(350, 20, 100, 0, 90, 0)\r"
    r, port = robot([(line, line[:-1] + b"\r\n."), (line, b"\r\n.")])
    r.define("p1", (350, 20, 100, 0, 90, 0))
    r.define("p1", H_from_xyzoat((350, 20, 100, 0, 90, 0)))
    assert port.written == [b"\r", line, line]


def test_define_rejects_bad_names_poses_and_points_outside_the_box():
    r, port = robot([])
    with pytest.raises(ConfigError, match="location name"):
        r.define("1abc", POSE)
    with pytest.raises(ConfigError, match="6 numbers"):
        r.define("p1", (1, 2, 3))
    with pytest.raises(ConfigError, match="not a rigid transform"):
        r.define("p1", np.diag([1.0, 1.0, 2.0, 1.0]))
    with pytest.raises(LimitError, match="x = 900.00 mm"):
        r.define("p1", (900, 0, 100, 0, 180, 0))
    assert port.written == [b"\r"]


def test_point_reads_a_location_and_answers_change_with_an_empty_line():
    r, port = robot([(b"POINT p1\r", point_reply(b"POINT p1", POSE)), (b"\r", b"\r\n.")])
    assert r.location("p1") == POSE
    assert port.written == [b"\r", b"POINT p1\r", b"\r"]


def test_here_records_and_returns_the_pose():
    r, port = robot([(b"HERE p2\r", point_reply(b"HERE p2", POSE, echo=False)), (b"\r", b"\r\n.")])
    assert r.here("p2") == POSE


def motion_script(cmd: bytes, *, prefix=()):
    return [*prefix, (b"WHERE\r", where_reply()), (cmd, [(0.0, cmd[:-1] + CRLF), (0.05, b".")])]


def test_move_to_a_defined_location():
    define = b"DO SET p1 = TRANS(350, 20, 100, 0, 180, 0)\r"
    r, port = robot(motion_script(b"DO MOVE p1\r", prefix=[(define, b"\r\n.")]))
    r.define("p1", POSE)
    r.move("p1")
    assert port.written == [b"\r", define, b"WHERE\r", b"DO MOVE p1\r"]


def test_move_to_an_unknown_name_reads_it_first_and_moves_to_a_pose_through_the_scratch_location():
    scratch = b"DO SET svtgt = TRANS(300, 0, 150, 0, 180, 0)\r"
    script = [(b"POINT far\r", point_reply(b"POINT far", POSE)), (b"\r", b"\r\n.")]
    script += motion_script(b"DO MOVE far\r")
    script += motion_script(b"DO MOVES svtgt\r", prefix=[(scratch, b"\r\n.")])
    r, port = robot(script)
    r.move("far")
    r.moves((300, 0, 150, 0, 180, 0))
    assert port.written[1:] == [b"POINT far\r", b"\r", b"WHERE\r", b"DO MOVE far\r", scratch, b"WHERE\r", b"DO MOVES svtgt\r"]


def test_appro_depart_drive_ready_bytes():
    define = b"DO SET p1 = TRANS(350, 20, 100, 0, 180, 0)\r"
    script = [(define, b"\r\n.")]
    script += motion_script(b"DO APPRO p1, 30\r")
    script += motion_script(b"DO DEPART 50\r")
    script += motion_script(b"DO DRIVE 2, -10.5, 20\r")
    script += motion_script(b"DO READY\r")
    r, port = robot(script)
    r.define("p1", POSE)
    r.appro("p1", 30)
    r.depart(50)
    r.drive(2, -10.5, 20)
    r.ready()
    assert [w for w in port.written if w.startswith(b"DO ") and not w.startswith(b"DO SET")] == [
        b"DO APPRO p1, 30\r",
        b"DO DEPART 50\r",
        b"DO DRIVE 2, -10.5, 20\r",
        b"DO READY\r",
    ]


def test_motion_limits_are_checked_before_sending():
    define = b"DO SET p1 = TRANS(350, 20, 100, 0, 180, 0)\r"
    lim = ValLimits(workspace_mm=((-400, 400), (-400, 400), (20, 600)), max_speed_pct=30)
    script = [(define, b"\r\n."), (b"WHERE\r", where_reply()), (b"WHERE\r", where_reply())]
    r, port = robot(script, limits=lim)
    r.define("p1", POSE)
    with pytest.raises(LimitError, match="z = 0.00 mm"):
        r.appro("p1", -100)  # tool z points down: -100 along it is 100 mm lower
    with pytest.raises(LimitError, match="z = 700.00 mm"):
        r.depart(600)  # from z = 100 up by 600 mm
    with pytest.raises(LimitError, match="JT1 would reach 224.07"):
        r.drive(1, 200, 10)
    with pytest.raises(LimitError, match="speed 50"):
        r.drive(1, 10, 50)
    with pytest.raises(ConfigError, match="DRIVE joint"):
        r.drive(7, 10, 10)
    with pytest.raises(LimitError, match="x = 500.00"):
        r.move((500, 0, 100, 0, 180, 0))
    assert not any(w.startswith((b"DO APPRO", b"DO DEPART", b"DO DRIVE", b"DO MOVE")) for w in port.written)


def test_idle_abort():
    r, port = robot([(b"ABORT\r", b"ABORT\r\n.")])
    r.abort()
    assert port.written == [b"\r", b"ABORT\r"]


def test_abort_from_another_thread_interrupts_a_waiting_move():
    # the controller echoes the move, then stays silent until it reads ABORT
    define = b"DO SET p1 = TRANS(350, 20, 100, 0, 180, 0)\r"
    script = [(define, b"\r\n."), (b"WHERE\r", where_reply()), (b"DO MOVE p1\r", b"DO MOVE p1\r\n")]
    script += [(b"ABORT\r", b"ABORT\r\n*Motion aborted*\r\n.")]
    r, port = robot(script, timeout_s=1.0)
    r.define("p1", POSE)
    result = {}

    def mover():
        try:
            r.move("p1")
        except Exception as exc:  # collected for the assertion below
            result["exc"] = exc

    t = threading.Thread(target=mover)
    t.start()
    deadline = time.monotonic() + 2
    while b"DO MOVE p1\r" not in port.written and time.monotonic() < deadline:
        time.sleep(0.005)
    r.abort()
    t.join(2)
    assert not t.is_alive()
    assert isinstance(result.get("exc"), MotionAborted)
    assert port.written[-2:] == [b"DO MOVE p1\r", b"ABORT\r"]


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
    reply = b"\r\nX Y Z O A T\r\n350.00 20.00 100.00 10.00 30.00 40.00\r\nJT1 JT2 JT3 JT4 JT5 JT6\r\n1.00 2.00 3.00 4.00 5.00 6.00\r\n."
    r, port = robot([(b"W\r", reply), (b"SP 5\r", b"\r\n*Power is off*\r\n.")], dialect=d)
    w = r.where()
    assert w.pose == (350.0, 20.0, 100.0, 10.0, 30.0, 40.0) and w.joints == (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
    zyx = R_from_rpy(np.radians(40), np.radians(30), np.radians(10))  # Rz(O) Ry(A) Rx(T)
    np.testing.assert_allclose(w.base_H_T[:3, :3], zyx, atol=1e-12)
    assert np.degrees(rotation_angle(w.base_H_T[:3, :3].T @ H_from_xyzoat(w.pose)[:3, :3])) > 10  # not VAL's zyz
    with pytest.raises(ArmPowerOff):
        r.speed(5)
    assert port.written == [b"\r", b"W\r", b"SP 5\r"]


@pytest.mark.parametrize(
    "data, match",
    [
        ({"prompt": ".."}, "dialect.prompt"),
        ({"errors": [["x", "NoSuchError"]]}, "unknown class"),
        ({"commands": {"move": "DO MOVE"}}, "must use the fields"),
        ({"colour": 1}, "unknown key"),
        ({"euler": {"sequence": "zzy"}}, "euler sequence"),
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
