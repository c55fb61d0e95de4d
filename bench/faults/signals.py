"""Termination signals (SIGINT, SIGTERM, SIGHUP, SIGQUIT; one, or two 0-30 ms apart) at a random moment of every
command that moves the arm or switches the valve: ``selfview park``, ``selfview robot ready`` / ``depart``,
``selfview gripper open`` (its stroke held by a stuck jaw), the cell's calibrate procedure, and a lab script
driving the devices from a worker thread. Judged from the simulators' side: the arm stopped (ABORT received if it was moving), the valve's
outputs in their safe state, the exit status 128 + the signal's number, the calibration file intact. The devices are held in this
process and the command talks to them with ``--real`` through the proxy's serial-cable model, so the
controller goes on when the host leaves, as a real one does; the calibrate procedure runs as a lab script
runs it (``CellSession.calibrate``, the CLI's exit codes)."""

from __future__ import annotations

import os
import shutil
import signal
import sys
import time
from pathlib import Path

import numpy as np

from selfview.bench._proxy import FaultProxy
from selfview.errors import CellError
from selfview.bench.faults.common import CLI_TIMEOUT_S, Tally, _away_from_ready, _cli_outcome, _file_state, _in_turn, _quiet_logs, _run_child, _selfview


# --- signals during the commands that move the arm -------------------------------------------------------
SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT")
COMMANDS = ("park", "calibrate", "robot-ready", "robot-depart", "gripper-open", "script-thread")
#: the commands whose valve must be in its safe state after a signal
_VALVE_SAFE = ("park", "calibrate", "gripper-open", "script-thread")


def _kind(command: str, signame: str, twice: bool) -> str:
    if signame == "SIGINT" and not twice and command in ("park", "calibrate"):
        return f"sigint.{command}"  # the first campaign's kinds, kept for comparison
    return f"signal.{command}.{signame}" + ("-twice" if twice else "")


def sigint_case(command: str, fixtures: dict, rng, tally: Tally, workdir: Path, signame: str = "SIGINT",
                twice: bool = False) -> None:
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.valve_terminal import ValveTerminal

    signum = getattr(signal, signame)
    workdir.mkdir(parents=True, exist_ok=True)
    frames = workdir / "frames"
    frames.mkdir(exist_ok=True)
    shutil.copyfile(fixtures["picture"], frames / "img_000.png")
    guard = workdir / "cal.yaml"
    shutil.copyfile(fixtures["cal"], guard)
    for p in workdir.glob("cal.yaml.history"):
        shutil.rmtree(p)
    scale = 0.1
    sim = ValController(None, seed=int(rng.integers(1 << 30)), time_scale=scale, calibrated=True)
    if command in ("robot-ready", "script-thread"):  # from a pose away from READY
        _away_from_ready(sim)
    proxy = FaultProxy(sim.start_tcp(0), serial=True).start()
    valve = ValveTerminal(None, travel_s=0.05, watchdog_s=None, initial="closed").start()
    if command == "gripper-open":
        valve.stick_jaw()  # the stroke never confirms: the command waits, the valve energised, until the signal
    urls = (f"socket://127.0.0.1:{proxy.port}", valve.url, f"frames://{frames}/img_%03d.png?loop=1")
    if command == "park":
        argv = ["park", "--real", "--robot", urls[0], "--gripper", urls[1], "--camera", urls[2], "--time-scale", str(scale)]
    elif command == "robot-ready":
        argv = ["robot", "--url", urls[0], "ready"]
    elif command == "robot-depart":
        argv = ["robot", "--url", urls[0], "depart", "80"]
    elif command == "gripper-open":
        argv = ["gripper", "--url", urls[1], "--timeout", "20", "open"]
    elif command == "script-thread":  # a lab script driving the devices from a worker thread
        argv = ["-c", _THREAD_SCRIPT, *urls[:2]]
    else:  # `selfview calibrate` needs --image (its parser), so the cell's calibrate runs through the Python API
        argv = ["-c", _CALIBRATE_SCRIPT, *urls, str(guard)]
    delay = float(rng.uniform(0.0, {"park": 1.2, "calibrate": 2.5}.get(command, 0.8)))
    gap = float(rng.uniform(0.0, 0.03))
    sent = {}

    def started():
        return valve.valve_outputs["open"] if command == "gripper-open" else bool(sim.received)

    def sigint_when(proc):
        t0 = time.monotonic()
        while not started() and proc.poll() is None and time.monotonic() - t0 < 30.0:
            time.sleep(0.005)
        time.sleep(delay)
        if proc.poll() is None:
            sent["q"] = sim.joints
            sent["moving"] = sim.moving.is_set()
            sent["n_received"] = len(sim.received)
            os.kill(proc.pid, signum)
            if twice:
                time.sleep(gap)
                if proc.poll() is None:
                    os.kill(proc.pid, signum)

    before = _file_state(guard)
    outputs_before = valve.valve_outputs
    try:
        code, err = _selfview_cell(argv, workdir, sigint_when)
        if code == -signum and signum != signal.SIGINT:
            # a program ends by the signal itself (the shell's 128 + N) once it has made the cell safe and let
            # go of the devices: a lab script is given back its own dispositions, the command line the
            # default ones (for SIGTERM, SIGHUP, SIGQUIT: the end of the program), e.g. at a second signal
            # that comes after the stop; the cell's state is judged below, and any other signal (SIGSEGV,
            # SIGABRT) is still a crash
            code = 128 + signum
        if command == "script-thread":
            if "work done" in err and code == -signal.SIGINT and err.rstrip().endswith("\nKeyboardInterrupt"):
                err = ""  # Ctrl-C once its work was done: the interpreter's own report of an unhandled Ctrl-C
        q_exit, moving_exit = sim.joints, sim.moving.is_set()
        time.sleep(0.3)  # 3 s of simulated time
        q_later = sim.joints
        outputs = valve.valve_outputs
        safe = valve.io_map.drive(valve.io_map.safe_state)
        after_signal = [ln.strip().upper() for ln in sim.received[sent.get("n_received", 0):]]
    finally:
        proxy.stop()
        sim.stop()
        valve.stop()
    k = _kind(command, signame, twice)
    what = (f"selfview {command.replace('-', ' ')}, {signame}{' twice' if twice else ''} {delay:.2f} s after the "
            "first command" + (" during a motion" if sent.get("moving") else ""))
    after = _file_state(guard)
    # the procedure had ended when the signal came (its file written, its last motion, the DEPART, done and
    # nothing moving, as the simulator saw it): the valve as the procedure left it is what is expected
    ended = ((command == "calibrate" and not sent.get("moving") and after != before
              and any(ln.strip().upper().startswith("DO DEPART") for ln in sim.received[:sent.get("n_received", 0)]))
             or (command == "script-thread" and "work done" in err))  # the script had let go of the devices
    bad_exit, seen = _cli_outcome(code, err)
    moved = float(np.max(np.abs(q_later - q_exit)))
    interrupted = "q" in sent and code not in (0, None)
    valve_unsafe = (command in _VALVE_SAFE and interrupted and outputs != safe and not ended
                    and (outputs != outputs_before or "cell left" in err))
    lost = False
    if command == "calibrate" and after != before:
        from selfview.files.calfile import load_calibration

        try:
            load_calibration(guard)
            lost = bool(after[1])  # a new complete file is fine; a left temp file is not
        except CellError:
            lost = True
    if code is None:
        outcome, seen = "hang", f"{what}: {seen}"
    elif moving_exit or moved > 0.01:
        outcome, seen = "unsafe", f"{what}: exit {code}, the arm moved {moved:.2f} deg (joints) after the command exited"
    elif sent.get("moving") and interrupted and "ABORT" not in after_signal:
        outcome, seen = "unsafe", f"{what}: exit {code}, the controller received no ABORT after the signal"
    elif valve_unsafe:
        outcome, seen = "unsafe", f"{what}: exit {code}, valve outputs {outputs} left, not the safe {safe}"
    elif bad_exit:
        outcome, seen = bad_exit, f"{what}: {seen}"
    elif lost:
        outcome, seen = "lost_file", f"{what}: exit {code}, the calibration file was lost or left half-written"
    elif "q" not in sent or code == 0:
        outcome = "no_effect"  # the command ended before the signal: nothing was interrupted
    elif code in (128 + signum, -signal.SIGINT if signum == signal.SIGINT else 128 + signum):
        outcome = "clear_error"
    else:
        outcome, seen = "traceback", (f"{what}: exit {code} instead of {128 + signum}: "
                                      f"{err.strip().splitlines()[-1:]}")
    tally.add(k, outcome, seen)


#: the cell's calibration procedure as a lab script runs it, with the CLI's exit codes
_CALIBRATE_SCRIPT = r'''
import sys
from selfview.files.cell import default_cell_path, load_cell
from selfview.errors import CellError
from selfview.procedures.cli import exit_code_for
from selfview.procedures.runs import CellSession
robot, gripper, camera, out = sys.argv[1:5]
try:
    with CellSession.real(load_cell(default_cell_path()), robot=robot, gripper=gripper, camera=camera,
                          progress=lambda s: print(s, file=sys.stderr, flush=True)) as s:
        s.calibrate(out=out)
except KeyboardInterrupt as exc:
    print("interrupted", file=sys.stderr)
    sys.exit(128 + getattr(exc, "signum", 2))
except CellError as exc:
    code, hint = exit_code_for(exc)
    print(f"error: {exc}\n  what to do: {hint}", file=sys.stderr)
    sys.exit(code)
'''


#: a lab script that drives the arm and the valve itself, from a worker thread (no engine in the main thread)
_THREAD_SCRIPT = r'''
import sys, threading
from selfview.drivers.pneumatic_gripper import PneumaticGripper
from selfview.drivers.puma_val_serial import PumaVAL
robot_url, gripper_url = sys.argv[1:3]

def work():
    with PumaVAL(robot_url) as robot, PneumaticGripper(gripper_url, poll_s=None) as gripper:
        gripper.open_jaws()
        robot.ready()
        print("work done", file=sys.stderr, flush=True)  # what the script set out to do is done

t = threading.Thread(target=work)
t.start()
t.join()
'''


def _selfview_cell(argv, cwd, sigint_when):
    if argv[0] == "-c":  # a script, not the selfview command
        return _run_child([sys.executable, *argv], cwd, CLI_TIMEOUT_S, sigint_when)
    return _selfview(argv, cwd, timeout_s=CLI_TIMEOUT_S, sigint_when=sigint_when)


def run_sigint(n: int, seed: int, deadline: float, tally: Tally, fixtures: dict, workers: int = 2,
               signals_too: bool = True) -> None:
    """``n`` cases: Ctrl-C during park and calibrate, and (``signals_too``) every termination signal, once or
    twice, during every command that moves the arm, in turn."""
    _quiet_logs()
    plan = [(c, "SIGINT", False) for c in ("park", "calibrate")]
    if signals_too:
        # command by command within each signal: a section cut short by its budget (a loaded machine) has
        # still tried every command
        plan += [(c, sg, tw) for sg in SIGNALS for tw in (False, True) for c in COMMANDS
                 if (c, sg, tw) not in plan]

    _in_turn(plan, lambda item, rng, folder: sigint_case(item[0], fixtures, rng, tally, folder, item[1], item[2]),
             5, "sigint", n, seed, deadline, tally, fixtures, workers)
