"""Ctrl-C at a random moment of ``selfview park`` and of the cell's calibrate procedure."""

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
from selfview.bench.faults.common import CLI_TIMEOUT_S, Tally, _cli_outcome, _file_state, _in_threads, _quiet_logs, _run_child, _selfview


# --- Ctrl-C during park and calibrate ----------------------------------------------------------------
def sigint_case(command: str, fixtures: dict, rng, tally: Tally, workdir: Path) -> None:
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.valve_terminal import ValveTerminal

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
    proxy = FaultProxy(sim.start_tcp(0), serial=True).start()
    valve = ValveTerminal(None, travel_s=0.05, watchdog_s=None, initial="closed").start()
    urls = (f"socket://127.0.0.1:{proxy.port}", valve.url, f"frames://{frames}/img_%03d.png?loop=1")
    if command == "park":
        argv = ["park", "--real", "--robot", urls[0], "--gripper", urls[1], "--camera", urls[2], "--time-scale", str(scale)]
    else:  # `selfview calibrate` needs --image (its parser), so the cell's calibrate runs through the Python API
        argv = ["-c", _CALIBRATE_SCRIPT, *urls, str(guard)]
    delay = float(rng.uniform(0.0, 1.2 if command == "park" else 2.5))
    sent = {}

    def sigint_when(proc):
        t0 = time.monotonic()
        while not sim.received and proc.poll() is None and time.monotonic() - t0 < 30.0:
            time.sleep(0.005)
        time.sleep(delay)
        if proc.poll() is None:
            sent["q"] = sim.joints
            sent["moving"] = sim.moving.is_set()
            os.kill(proc.pid, signal.SIGINT)

    before = _file_state(guard)
    try:
        code, err = _selfview_cell(argv, workdir, sigint_when)
        q_exit, moving_exit = sim.joints, sim.moving.is_set()
        time.sleep(0.3)  # 3 s of simulated time
        q_later = sim.joints
        outputs = valve.valve_outputs
    finally:
        proxy.stop()
        sim.stop()
        valve.stop()
    k = f"sigint.{command}"
    what = f"selfview {command}, Ctrl-C {delay:.2f} s after the first command" + (
        " during a motion" if sent.get("moving") else "")
    after = _file_state(guard)
    bad_exit, seen = _cli_outcome(code, err)
    moved = float(np.max(np.abs(q_later - q_exit)))
    lost = False
    if command == "calibrate" and after != before:
        from selfview.calfile import load_calibration

        try:
            load_calibration(guard)
            lost = bool(after[1])  # a new complete file is fine; a left temp file is not
        except CellError:
            lost = True
    if bad_exit:
        outcome, seen = bad_exit, f"{what}: {seen}"
    elif moving_exit or moved > 0.01:
        outcome, seen = "unsafe", f"{what}: exit {code}, the arm moved {moved:.2f} deg (joints) after the command exited"
    elif code not in (0, None) and any(outputs.values()) and "stopping the robot" in err:  # the engine's cleanup ran
        outcome, seen = "unsafe", f"{what}: exit {code}, valve outputs {outputs} energised after the engine's cleanup"
    elif lost:
        outcome, seen = "lost_file", f"{what}: exit {code}, the calibration file was lost or left half-written"
    elif "q" not in sent or code == 0:
        outcome = "no_effect"  # the command ended before the signal: nothing was interrupted
    elif code in (130, -signal.SIGINT):
        outcome = "clear_error"
    else:
        outcome, seen = "traceback", f"{what}: exit {code} instead of 130: {err.strip().splitlines()[-1:]}"
    tally.add(k, outcome, seen)


#: the cell's calibration procedure as a lab script runs it, with the CLI's exit codes
_CALIBRATE_SCRIPT = r'''
import sys
from selfview.cell import default_cell_path, load_cell
from selfview.errors import CellError
from selfview.procedures.cli import exit_code_for
from selfview.procedures.runs import CellSession
robot, gripper, camera, out = sys.argv[1:5]
try:
    with CellSession.real(load_cell(default_cell_path()), robot=robot, gripper=gripper, camera=camera,
                          progress=lambda s: print(s, file=sys.stderr, flush=True)) as s:
        s.calibrate(out=out)
except KeyboardInterrupt:
    print("interrupted", file=sys.stderr)
    sys.exit(130)
except CellError as exc:
    code, hint = exit_code_for(exc)
    print(f"error: {exc}\n  what to do: {hint}", file=sys.stderr)
    sys.exit(code)
'''


def _selfview_cell(argv, cwd, sigint_when):
    if argv[0] == "-c":  # a script, not the selfview command
        return _run_child([sys.executable, *argv], cwd, CLI_TIMEOUT_S, sigint_when)
    return _selfview(argv, cwd, timeout_s=CLI_TIMEOUT_S, sigint_when=sigint_when)


def run_sigint(n: int, seed: int, deadline: float, tally: Tally, fixtures: dict, workers: int = 2) -> None:
    _quiet_logs()

    def worker(share, seed_, index, deadline_, tally_):
        rng = np.random.default_rng([seed, 5, index])
        for i in range(share):
            if time.monotonic() >= deadline:
                break
            command = ("park", "calibrate")[(index + i) % 2]
            sigint_case(command, fixtures, rng, tally, Path(fixtures["dir"]) / f"sigint{index}")

    _in_threads(worker, n, seed, deadline, tally, workers)


