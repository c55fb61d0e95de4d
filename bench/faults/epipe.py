"""Standard output gone (``epipe.<command>``): a command driving the simulated devices (the VAL simulator on a
pty, the valve terminal on 127.0.0.1, a camera of pictures) with its standard output a pipe whose reader
ends early, as ``| head -1`` does: ``selfview monitor --real --json`` (the reader takes 0 to 2 lines),
``selfview robot ready`` / ``depart``, ``selfview park --real``, ``selfview gripper close`` and ``selfview devices
--real`` (the reader takes none).

The command must end 141 (128 + SIGPIPE, documented in ``selfview --help``) once the cell is safe, with no
traceback on stderr and no temporary file left; judged from the simulators' side: the arm still after the
command exited, the valve's outputs in their safe state (monitor, which stops the cell), no motion line
after an ABORT."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path

import numpy as np

from selfview.bench.faults.common import (CLI_TIMEOUT_S, Tally, _arm_after_exit, _away_from_ready, _cli_command,
                                          _cli_outcome, _in_turn, _limit_child, _quiet_logs)

COMMANDS = ("monitor", "robot-ready", "robot-depart", "park", "gripper-close", "devices")
EXIT_PIPE = 128 + signal.SIGPIPE
SCALE = 0.1  # the simulator's motions take this fraction of real time


def _frames(fixtures: dict, workdir: Path, rng) -> Path:
    """Three pictures of the parked gripper, each with its own sensor noise (the monitor takes a picture
    identical to the previous one for a stuck grabber)."""
    import cv2

    frames = workdir / "frames"
    if frames.exists():
        shutil.rmtree(frames)
    frames.mkdir(parents=True)
    img = fixtures["image"].astype(float)
    for i in range(3):
        noisy = np.clip(img + rng.normal(0.0, 2.0, img.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(frames / f"img_{i:03d}.png"), noisy)
    return frames


def judge(rec: dict) -> tuple[str, str]:
    """The outcome from a case's record: ``code`` (None: killed at the bound), ``err``; ``closed_early`` (the
    reader ended while the command ran); ``moving_exit``, ``moved_after`` (deg after the exit);
    ``motion_after_abort``; ``valve`` and ``safe`` (outputs, or None where not judged); ``temp_files``."""
    code, err = rec["code"], rec["err"]
    bad, seen = _cli_outcome(code, err)
    first = _arm_after_exit(rec)
    if first:
        return first
    if rec["valve"] is not None and rec["valve"] != rec["safe"]:
        return "unsafe", f"exit {code}, valve outputs {rec['valve']} left, not the safe {rec['safe']}"
    if bad:
        return bad, seen
    if rec["temp_files"]:
        return "lost_file", f"exit {code}, temporary files left: {rec['temp_files'][:3]}"
    if not rec["closed_early"]:
        return "no_effect", ""  # the command had ended before its reader did
    if code == EXIT_PIPE and "standard output was closed" in err:
        return "clear_error", ""
    return "wrong_value", f"its output went away, exit {code} (expected {EXIT_PIPE} with a message): {err.strip()[-200:]!r}"


def epipe_case(command: str, fixtures: dict, rng, tally: Tally, workdir: Path) -> None:
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.valve_terminal import ValveTerminal

    workdir.mkdir(parents=True, exist_ok=True)
    sim = ValController(None, seed=int(rng.integers(1 << 30)), time_scale=SCALE, calibrated=True)
    if command.startswith("robot"):
        _away_from_ready(sim)
    tty = sim.start_pty()
    valve = ValveTerminal(None, travel_s=0.05, watchdog_s=None, initial="closed").start()
    cell = ["--real", "--robot", tty, "--gripper", valve.url, "--time-scale", str(SCALE)]
    lines = int(rng.integers(0, 3)) if command == "monitor" else 0
    if command == "monitor":
        cal = workdir / "cal.yaml"
        shutil.copyfile(fixtures["cal"], cal)
        frames = _frames(fixtures, workdir, rng)
        argv = ["monitor", *cell, "--camera", f"frames://{frames}/img_%03d.png?loop=1", "--calibration", str(cal),
                "--frames", "12", "--json"]
    elif command == "park":
        frames = _frames(fixtures, workdir, rng)
        argv = ["park", *cell, "--camera", f"frames://{frames}/img_%03d.png?loop=1", "--out", str(workdir / "parked.png")]
    elif command == "gripper-close":
        argv = ["gripper", "--url", valve.url, "close"]
    elif command == "devices":
        frames = _frames(fixtures, workdir, rng)
        argv = ["devices", *cell, "--camera", f"frames://{frames}/img_%03d.png?loop=1"]
    else:
        argv = ["robot", "--url", tty, *(["ready"] if command == "robot-ready" else ["depart", "60"])]
    box: dict = {}
    proc = subprocess.Popen(_cli_command(argv), cwd=workdir, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, preexec_fn=_limit_child, start_new_session=True)

    def reader():  # ``head -N``: N lines, then the pipe's read end is closed
        for _ in range(lines):
            if not proc.stdout.readline():
                break
        box["closed_early"] = proc.poll() is None
        proc.stdout.close()

    def errors():
        box["err"] = proc.stderr.read().decode("utf-8", errors="replace")

    threads = [threading.Thread(target=f, daemon=True) for f in (reader, errors)]
    for t in threads:
        t.start()
    try:
        try:
            proc.wait(CLI_TIMEOUT_S)
            code = proc.returncode
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5.0)
            code = None
        for t in threads:
            t.join(5.0)
        q_exit, moving_exit = sim.joints, sim.moving.is_set()
        time.sleep(0.3)  # 3 s of the simulator's time
        received = [ln.strip().upper() for ln in sim.received]
        rec = {"code": code, "err": box.get("err", ""), "closed_early": box.get("closed_early", True),
               "moving_exit": moving_exit, "moved_after": float(np.max(np.abs(sim.joints - q_exit))),
               "valve": valve.valve_outputs if command == "monitor" else None,
               "safe": valve.io_map.drive(valve.io_map.safe_state)}
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5.0)
        sim.stop()
        valve.stop()
    first_abort = received.index("ABORT") if "ABORT" in received else len(received)
    rec["motion_after_abort"] = next((ln for ln in received[first_abort:] if ln.startswith("DO ")), None)
    rec["temp_files"] = sorted(p.name for p in workdir.rglob("*") if p.name.endswith(".tmp"))
    outcome, seen = judge(rec)
    what = f"selfview {command.replace('-', ' ')} | head -{lines}"
    tally.add(f"epipe.{command}", outcome, f"{what}: {seen}" if seen else "")


def run_epipe(n: int, seed: int, deadline: float, tally: Tally, fixtures: dict, workers: int = 2) -> None:
    """``n`` cases, the commands in turn."""
    _quiet_logs()

    _in_turn(COMMANDS, lambda command, rng, folder: epipe_case(command, fixtures, rng, tally, folder),
             10, "epipe", n, seed, deadline, tally, fixtures, workers)
