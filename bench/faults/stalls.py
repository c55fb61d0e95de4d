"""Host stalls (``stall.<mode>.<command>``): ``selfview robot ready`` / ``depart`` driving the VAL simulator on a
pty, its own process stopped mid-motion while the controller goes on:

- ``sigstop-short`` / ``sigstop-long``: SIGSTOP for a time shorter, or longer, than the driver's reply limit
  of the motion, then SIGCONT (a suspended or swapped-out host). The controller finished the motion, its
  complete reply waiting in the buffer: the command must report it done (exit 0), never a device fault,
  and send no ABORT;
- ``sigtstp``: Ctrl-Z (SIGTSTP) mid-motion, SIGCONT some time later. The arm is held: ABORT reaches the
  controller before the program stops, the arm does not move while it is suspended, and on resume the
  command reports the ABORT (exit 4 with a message) and moves nothing more;
- ``reply``: the controller's replies stop reaching the host from the motion's start (a cut reply line,
  the controller goes on): the command gives up with ABORT within ``ABORT_AFTER_END_S`` of the motion's
  end, and exits 4 with a message.

Judged from the simulator's side: what it received and when, whether its arm moved after the command
exited or while it was suspended, where the arm is."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np

from selfview.bench.faults.common import (CLI_TIMEOUT_S, Tally, _arm_after_exit, _away_from_ready, _cli_command,
                                          _cli_outcome, _in_turn, _limit_child, _quiet_logs)

COMMANDS = ("ready", "depart")
MODES = ("sigtstp", "sigstop-long", "reply", "sigstop-short")  # in turn: a short run still holds Ctrl-Z and a long stall
ABORT_AFTER_END_S = 5.0  # the target: a stalled reply's ABORT at most this long after the motion's end
ABORT_BEFORE_STOP_S = 1.0  # Ctrl-Z: the ABORT at the controller at most this long after the signal
DEPART_MM = 60.0
#: the latest ABORT after a stalled reply seen in this process, in seconds after the motion's end (reported in the notes)
_LATEST: dict = {}


class Recorder:
    """The simulator's received lines and the starts and ends of its motions, with their times (polled)."""

    def __init__(self, sim, period_s: float = 0.002):
        self.sim, self.period_s = sim, period_s
        self.lines: list[tuple[float, str]] = []
        self.motions: list[tuple[float, bool]] = []  # (time, moving) at each change
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._poll, name="stall-recorder", daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._done.set()
        self._thread.join(1.0)

    def _poll(self) -> None:
        n, moving = 0, False
        while True:
            now = time.monotonic()
            received = self.sim.received
            while len(received) > n:
                self.lines.append((now, received[n].strip().upper()))
                n += 1
            if self.sim.moving.is_set() != moving:
                moving = not moving
                self.motions.append((now, moving))
            if self._done.is_set():
                return
            time.sleep(self.period_s)

    def first(self, text: str, after: float = 0.0) -> float | None:
        """When the controller first received ``text`` at or after ``after``, or None."""
        return next((t for t, ln in self.lines if ln == text and t >= after), None)

    def motion_end(self) -> float | None:
        return next((t for t, m in self.motions if not m), None)


def _stopped(pid: int) -> bool:
    """Whether process ``pid`` is stopped (job control), from its /proc state."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] in ("T", "t")
    except (OSError, IndexError):
        return False


def _wait_for(cond, timeout_s: float, period_s: float = 0.005) -> bool:
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 >= timeout_s:
            return False
        time.sleep(period_s)
    return True


def _reply_limit(sim, command: str) -> float:
    """The driver's reply limit for the motion (``ValLimits``' own formula at the controller's SPEED)."""
    from selfview.drivers.puma_val_serial import ValLimits

    lim = ValLimits()
    if command == "ready":
        return lim.joint_timeout_s(np.asarray(lim.ready_joints_deg) - sim.joints, sim.speed_pct)
    return lim.cartesian_timeout_s(DEPART_MM, 0.0, sim.speed_pct)


def _at_target(sim, command: str, H0) -> str | None:
    """None if the arm is at the motion's target, else where it is."""
    from selfview.drivers.puma_val_serial import ValLimits
    from selfview.maths.geometry import trans

    if command == "ready":
        err = float(np.max(np.abs(sim.joints - np.asarray(ValLimits().ready_joints_deg))))
        return None if err <= 0.05 else f"{err:.2f} deg (joints) from READY"
    goal = (H0 @ trans(0.0, 0.0, -DEPART_MM))[:3, 3]
    mm = float(np.linalg.norm(sim.base_H_T[:3, 3] - goal))
    return None if mm <= 0.5 else f"{mm:.2f} mm from the DEPART's target"


def judge(mode: str, rec: dict) -> tuple[str, str]:
    """The outcome of a case from its record (what the simulator saw; keys below), and what was seen.

    ``code`` (None: killed at the bound) and ``err``: the command's exit; ``moved_after`` (deg of joints
    after it exited), ``moving_exit``; ``aborts`` (times ABORT arrived, s after the signal or, for
    ``reply``, after the motion's end); ``motion_after_abort`` (a motion line received after an ABORT);
    ``at_target`` (None, or where the arm is); ``moving_at_signal``; for ``sigtstp`` ``held`` (the arm
    stopped while the command was suspended) and ``moved_suspended`` (deg)."""
    code, err = rec["code"], rec["err"]
    bad, seen = _cli_outcome(code, err)
    first = _arm_after_exit(rec)
    if first:
        return first
    if mode == "sigtstp" and rec["moving_at_signal"]:
        if not rec["aborts"] or rec["aborts"][0] > ABORT_BEFORE_STOP_S:
            return "unsafe", f"Ctrl-Z during a motion: no ABORT within {ABORT_BEFORE_STOP_S:g} s (ABORTs at {rec['aborts']} s)"
        if not rec["held"] or rec["moved_suspended"] > 0.01:
            return "unsafe", f"the arm went on {rec['moved_suspended']:.2f} deg while the command was suspended"
    if mode == "reply":
        if not rec["aborts"] or rec["aborts"][0] > ABORT_AFTER_END_S:
            return "unsafe", (f"the reply stalled: ABORT at {rec['aborts'][:1]} s after the motion's end, not within "
                              f"{ABORT_AFTER_END_S:g} s")
    if bad:
        return bad, seen
    if code == 0:
        if rec["at_target"] is not None:
            return "unsafe", f"exit 0: reported done with the arm {rec['at_target']}"
        if mode == "reply":
            return "wrong_value", "exit 0 although no reply reached the host"
        return "no_effect", ""
    if mode.startswith("sigstop"):
        return "wrong_value", (f"a false device fault: the controller finished the motion, the command exited {code}: "
                               f"{err.strip()[-200:]!r}")
    if code == 4 and err.strip():
        return "clear_error", ""
    return "wrong_value", f"exit {code} (expected 4 with a message): {err.strip()[-200:]!r}"


def stall_case(command: str, mode: str, rng, tally: Tally, workdir: Path) -> None:
    from selfview.mocks.val_controller import ValController

    workdir.mkdir(parents=True, exist_ok=True)
    sim = ValController(None, seed=int(rng.integers(1 << 30)), time_scale=1.0, calibrated=True)
    _away_from_ready(sim)
    tty = sim.start_pty()
    H0 = sim.base_H_T
    limit = _reply_limit(sim, command)
    pause = (float(rng.uniform(0.05, 1.0)) if mode == "sigstop-short"
             else float(rng.uniform(limit + 0.5, limit + 2.0)) if mode == "sigstop-long"
             else float(rng.uniform(0.2, 1.5)))
    delay = float(rng.uniform(0.0, 0.4))
    argv = ["robot", "--url", tty, *(["ready"] if command == "ready" else ["depart", f"{DEPART_MM:g}"])]
    if mode == "reply":
        sim.inject("stall", after_s=0.0)
    rec: dict = {"moving_at_signal": False, "held": True, "moved_suspended": 0.0}
    t_sig = None
    # its own process group in this session (not orphaned): the kernel carries out a SIGTSTP's stop
    proc = subprocess.Popen(_cli_command(argv), cwd=workdir, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=_limit_child, process_group=0)
    try:
        with Recorder(sim) as seen_by_sim:
            _wait_for(lambda: sim.moving.is_set() or proc.poll() is not None, 30.0)
            time.sleep(delay)
            if mode != "reply" and proc.poll() is None:
                rec["moving_at_signal"], t_sig = sim.moving.is_set(), time.monotonic()
                os.kill(proc.pid, signal.SIGSTOP if mode.startswith("sigstop") else signal.SIGTSTP)
                if mode == "sigtstp":
                    rec["suspended"] = _wait_for(lambda: _stopped(proc.pid) or proc.poll() is not None, 3.0) and proc.poll() is None
                    time.sleep(0.2)  # the ABORT's stop (a tick of the simulator) is over
                    rec["held"] = not sim.moving.is_set()
                    q_held = sim.joints
                    time.sleep(pause)
                    rec["moved_suspended"] = float(np.max(np.abs(sim.joints - q_held)))
                else:
                    time.sleep(pause)
                os.kill(proc.pid, signal.SIGCONT)
            try:
                _, rec["err"] = proc.communicate(timeout=CLI_TIMEOUT_S)
                rec["code"] = proc.returncode
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                rec["code"], rec["err"] = None, proc.communicate()[1]
            q_exit, rec["moving_exit"] = sim.joints, sim.moving.is_set()
            time.sleep(0.3)
            rec["moved_after"] = float(np.max(np.abs(sim.joints - q_exit)))
        rec["at_target"] = _at_target(sim, command, H0)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5.0)
        sim.stop()
    ref = seen_by_sim.motion_end() if mode == "reply" else t_sig
    rec["aborts"] = ([round(t - ref, 3) for t, ln in seen_by_sim.lines if ln == "ABORT" and t >= ref]
                     if ref is not None else [])
    t_abort = seen_by_sim.first("ABORT")
    rec["motion_after_abort"] = next((ln for t, ln in seen_by_sim.lines if t_abort is not None and t > t_abort
                                      and ln.startswith("DO ")), None)
    if mode == "reply" and rec["aborts"]:
        _LATEST["s"] = max(_LATEST.get("s", 0.0), rec["aborts"][0])
    if mode == "sigtstp" and rec["moving_at_signal"] and not rec.get("suspended"):
        tally.notes["stall.sigtstp: a command did not stop on Ctrl-Z (it had ended, or the stop was not carried out)"] += 1
    outcome, seen = judge(mode, rec)
    what = (f"selfview robot {command}, {mode} ({pause:.2f} s; the reply limit {limit:.1f} s) {delay:.2f} s into the motion")
    tally.add(f"stall.{mode}.{command}", outcome, f"{what}: {seen}" if seen else "")


def run_stalls(n: int, seed: int, deadline: float, tally: Tally, fixtures: dict, workers: int = 2) -> None:
    """``n`` cases: each mode against each command, in turn."""
    _quiet_logs()
    plan = [(c, m) for c in COMMANDS for m in MODES]

    _in_turn(plan, lambda item, rng, folder: stall_case(*item, rng, tally, folder),
             9, "stalls", n, seed, deadline, tally, fixtures, workers)
    if "s" in _LATEST:
        tally.notes[f"stall.reply: the latest ABORT after a stalled reply came {_LATEST['s']:.2f} s after the motion's end "
                    f"(target {ABORT_AFTER_END_S:g} s)"] += 1
