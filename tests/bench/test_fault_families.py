"""The scoring of the fault campaign's host-stall and closed-output families (``bench/faults/stalls.py``,
``bench/faults/epipe.py``): synthetic records of what the simulators saw, each rule broken once, must be
classified as the failure they are; and one real case of each family, end to end."""

from __future__ import annotations

import numpy as np
import pytest

from selfview.bench.faults import epipe, stalls
from selfview.bench.faults.common import Tally

STOP = "selfview robot: error: controller reported *Motion aborted* after 'DO READY'\n  what to do: ..."


def _stall(**kw):
    rec = {"code": 0, "err": "", "moving_exit": False, "moved_after": 0.0, "aborts": [], "motion_after_abort": None,
           "at_target": None, "moving_at_signal": True, "held": True, "moved_suspended": 0.0}
    rec.update(kw)
    return rec


def test_a_host_stall_that_the_command_rides_out_is_no_fault():
    assert stalls.judge("sigstop-long", _stall()) == ("no_effect", "")


@pytest.mark.parametrize("mode, rec, outcome", [
    # the controller finished during the stall: exit 4 is a false device fault
    ("sigstop-long", _stall(code=4, err="no prompt after 'DO READY'", aborts=[5.1]), "wrong_value"),
    ("sigstop-short", _stall(code=0, at_target="12.00 deg (joints) from READY"), "unsafe"),  # done, arm elsewhere
    ("sigstop-long", _stall(code=0, moving_exit=True), "unsafe"),
    ("sigstop-long", _stall(code=4, err=STOP, moved_after=3.0), "unsafe"),
    ("sigstop-long", _stall(code=None, err=""), "hang"),
    ("sigstop-short", _stall(code=1, err="Traceback (most recent call last):\nValueError: x"), "traceback"),
    # Ctrl-Z: no ABORT, a late one, the arm going on while suspended, a motion after the ABORT
    ("sigtstp", _stall(code=4, err=STOP, aborts=[]), "unsafe"),
    ("sigtstp", _stall(code=4, err=STOP, aborts=[2.5]), "unsafe"),
    ("sigtstp", _stall(code=4, err=STOP, aborts=[0.05], held=False), "unsafe"),
    ("sigtstp", _stall(code=4, err=STOP, aborts=[0.05], moved_suspended=4.0), "unsafe"),
    ("sigtstp", _stall(code=4, err=STOP, aborts=[0.05], motion_after_abort="DO READY"), "unsafe"),
    ("sigtstp", _stall(code=0, aborts=[0.05], at_target="3.00 deg (joints) from READY"), "unsafe"),
    ("sigtstp", _stall(code=4, err=STOP, aborts=[0.05]), "clear_error"),
    ("sigtstp", _stall(code=4, err="", aborts=[0.05]), "wrong_value"),  # no message
    # a stalled reply: the ABORT within the target after the motion's end
    ("reply", _stall(code=4, err=STOP, aborts=[6.2], moving_at_signal=False), "unsafe"),
    ("reply", _stall(code=4, err=STOP, aborts=[], moving_at_signal=False), "unsafe"),
    ("reply", _stall(code=4, err=STOP, aborts=[3.9], moving_at_signal=False), "clear_error"),
    ("reply", _stall(code=0, aborts=[3.9], moving_at_signal=False), "wrong_value"),
])
def test_each_broken_rule_of_a_host_stall_is_flagged(mode, rec, outcome):
    got, seen = stalls.judge(mode, rec)
    assert got == outcome, (got, seen)
    assert outcome in ("no_effect", "clear_error") or seen


def _pipe(**kw):
    rec = {"code": 141, "err": "selfview monitor: its standard output was closed (the reader of a pipe ended) ...",
           "closed_early": True, "moving_exit": False, "moved_after": 0.0, "motion_after_abort": None,
           "valve": {"open": False, "close": False}, "safe": {"open": False, "close": False}, "temp_files": []}
    rec.update(kw)
    return rec


@pytest.mark.parametrize("rec, outcome", [
    (_pipe(), "clear_error"),
    (_pipe(code=0, closed_early=False), "no_effect"),  # it had finished before its reader ended
    (_pipe(code=0), "wrong_value"),  # the run cut short, reported as a success
    (_pipe(code=141, err=""), "wrong_value"),  # no message
    (_pipe(valve={"open": True, "close": False}), "unsafe"),
    (_pipe(moved_after=5.0), "unsafe"),
    (_pipe(moving_exit=True), "unsafe"),
    (_pipe(motion_after_abort="DO MOVE ABOVE"), "unsafe"),
    (_pipe(code=1, err="Traceback (most recent call last):\nBrokenPipeError: [Errno 32] Broken pipe"), "traceback"),
    (_pipe(code=-13, err=""), "traceback"),  # killed by SIGPIPE: no cleanup
    (_pipe(temp_files=[".cal.yaml.tmp"]), "lost_file"),
    (_pipe(code=None), "hang"),
])
def test_each_broken_rule_of_a_closed_output_is_flagged(rec, outcome):
    assert epipe.judge(rec)[0] == outcome


def test_a_suspended_command_holds_the_arm_and_a_stalled_host_reports_no_fault(tmp_path):
    """End to end, one case each: Ctrl-Z during ``robot ready`` (ABORT before the stop, exit 4), and a
    SIGSTOP during ``robot depart`` shorter than the reply limit (exit 0, no ABORT)."""
    tally = Tally()
    rng = np.random.default_rng(4)
    stalls.stall_case("ready", "sigtstp", rng, tally, tmp_path / "a")
    stalls.stall_case("depart", "sigstop-short", rng, tally, tmp_path / "b")
    kinds = tally.to_json()["kinds"]
    assert kinds["stall.sigtstp.ready"]["clear_error"] == 1, tally.to_json()["examples"]
    assert kinds["stall.sigstop-short.depart"]["no_effect"] == 1, tally.to_json()["examples"]


@pytest.mark.parametrize("command", ["robot-depart", "gripper-close"])
def test_a_command_whose_output_goes_away_ends_141_with_the_arm_still(command, tmp_path):
    tally = Tally()
    epipe.epipe_case(command, {}, np.random.default_rng(1), tally, tmp_path)
    assert tally.to_json()["kinds"][f"epipe.{command}"]["clear_error"] == 1, tally.to_json()["examples"]


def test_a_call_past_its_bound_is_a_hang_that_names_where_it_waits():
    """The campaign's bound on an in-process call: past it, the record says where the call is stuck (its
    own frames, innermost last) and where the process's other threads are, with no path of this machine;
    waited for once more as long, it is still stuck, and the record says so with its stack again."""
    import threading

    from selfview.bench.faults.common import _call

    gate, peer_gate = threading.Event(), threading.Event()

    def wait_forever_here():
        gate.wait()

    def peer():
        peer_gate.wait()

    t = threading.Thread(target=peer, name="peer", daemon=True)
    t.start()
    try:
        status, record, snap = _call(wait_forever_here, 0.2, after=lambda: "snapshot")
    finally:
        gate.set()
        peer_gate.set()
    assert status == "hang" and snap is None
    late, _, at_bound = record.partition("\nat the bound of 0.2 s (and ")
    at_bound = at_bound.partition(" s in which the process was stalled), ")[2]
    assert late.startswith("still running ") and "wait_forever_here: gate.wait()" in late, record
    head, _, rest = at_bound.partition("other threads")
    assert head.startswith("thread fault-op waits in:"), record
    frames = [ln.strip() for ln in head.splitlines()[1:]]
    mine = [i for i, ln in enumerate(frames) if ln.startswith("bench/test_fault_families.py:")]
    assert mine and frames[mine[-1]].endswith("wait_forever_here: gate.wait()"), record
    assert frames[mine[-1] - 1].startswith("bench/faults/common.py:") and frames[-1].split(":")[0].endswith("/threading.py"), record
    assert "test_fault_families.py" in rest and "> " in rest and " peer" in rest, record  # the peer, by its own frame
    assert "/work/" not in record and "/usr/" not in record and "site-packages" not in record
    assert _call(lambda: 7, 1.0, after=lambda: "snapshot") == ("ok", 7, "snapshot")


def test_a_call_that_returns_after_its_bound_is_a_hang_that_says_when_and_how_it_ended(monkeypatch):
    """A call released just after the bound (once its stacks are taken) is still a hang, and its record
    says that it returned, after how long, and with which error."""
    import threading

    from selfview.bench.faults import common
    from selfview.errors import DeviceTimeout

    gate = threading.Event()
    stacks = common.thread_stacks

    def stacks_then_release(t):
        text = stacks(t)
        gate.set()
        return text

    def slow():
        gate.wait()
        raise DeviceTimeout("no reply to 'WHERE' within 0.20 s")

    monkeypatch.setattr(common, "thread_stacks", stacks_then_release)
    status, record, _ = common._call(slow, 1.0)
    assert status == "hang"
    late, _, at_bound = record.partition("\nat the bound of 1 s (and ")
    at_bound = at_bound.partition(" s in which the process was stalled), ")[2]
    took = float(late.split(" s after it started")[0].removeprefix("returned "))
    assert took >= 1.0 and late.endswith("with DeviceTimeout: no reply to 'WHERE' within 0.20 s"), record
    assert at_bound.startswith("thread fault-op waits in:") and "slow: gate.wait()" in at_bound, record


def test_time_in_which_the_process_was_stalled_is_added_to_the_bound_and_noted(monkeypatch):
    """A call that ends after the bound, within the time the heartbeat saw the process stalled (a loaded
    machine, a stop), is counted by its outcome, and the notes say a call ran past its bound so; the added
    time is at most one more bound, so a call that never returns is still a hang."""
    import threading

    from selfview.bench.faults import common

    gate = threading.Event()
    beat = common.heartbeat()

    def stalled_then_release(since):
        gate.set()  # the call can end now: after its bound, within the stalled time
        return 5.0

    monkeypatch.setattr(beat, "stalled", stalled_then_release)
    tally = common.Tally()
    monkeypatch.setattr(common, "_NOTES", tally)
    assert common._call(lambda: gate.wait() and "done", 0.3) == ("ok", "done", None)
    assert list(tally.notes.values()) == [1] and "ran past its 0.3 s bound while this process was stalled" in next(iter(tally.notes))

    never = threading.Event()
    try:
        status, record, _ = common._call(never.wait, 0.2)
    finally:
        never.set()
    assert status == "hang" and "at the bound of 0.2 s (and 0.2 s in which the process was stalled)" in record, record
