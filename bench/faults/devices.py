"""A second process on each device while ``selfview park`` owns it: ``selfview robot speed`` on the robot's
serial port (a pty, or a link to it), ``selfview gripper open`` on the valve terminal (its address as park
wrote it, or spelled otherwise); and a robot command killed (SIGKILL) during its motion, then the next one
(``killed_case``). One process owns a device: the second
must be refused. Judged from the simulators' side: the controller received the second's command, or the
jaws moved at its request."""

from __future__ import annotations

import contextlib
import shutil
import threading
import time
from pathlib import Path

from selfview.bench.faults.common import Tally, _away_from_ready, _cli_outcome, _in_turn, _quiet_logs, _selfview

#: the second process names the device as park does, or (``-spelling``) another way: the valve terminal's
#: address spelled otherwise (localhost, 127.000.000.001, 2130706433), the robot's port through a symbolic link
DEVICES = ("robot", "gripper", "robot-spelling", "gripper-spelling", "robot-killed")
_HOST_SPELLINGS = ("localhost", "127.000.000.001", "2130706433")
SECOND_TIMEOUT_S = 20.0


@contextlib.contextmanager
def _most_connections(valve, box: dict):
    """While inside: the most programs the valve terminal served at once, in ``box["most_connections"]``."""
    done = threading.Event()
    box["most_connections"] = 0

    def count():
        while not done.wait(0.005):
            box["most_connections"] = max(box["most_connections"], valve.active_connections)

    counter = threading.Thread(target=count, name="connections", daemon=True)
    counter.start()
    try:
        yield
    finally:
        done.set()
        counter.join(1.0)


def killed_case(rng, tally: Tally, workdir: Path) -> None:
    """``selfview robot ready`` killed (SIGKILL: no handler, no cleanup, as a power cut of the host) during
    its motion; the next ``selfview robot where`` must refuse with a message and send nothing, and go on
    once ``selfview devices --reset`` has stopped the arm and cleared the record."""
    from selfview.mocks.val_controller import ValController

    workdir.mkdir(parents=True, exist_ok=True)
    sim = ValController(None, seed=int(rng.integers(1 << 30)), time_scale=0.5, calibrated=True, speed_pct=10.0)
    _away_from_ready(sim)
    tty = sim.start_pty()
    delay = float(rng.uniform(0.0, 0.3))

    def kill_when(proc):
        t0 = time.monotonic()
        while not sim.moving.is_set() and proc.poll() is None and time.monotonic() - t0 < 30.0:
            time.sleep(0.005)
        time.sleep(delay)
        if proc.poll() is None:
            proc.kill()

    try:
        code, _ = _selfview(["robot", "--url", tty, "ready"], workdir, timeout_s=SECOND_TIMEOUT_S, sigint_when=kill_when)
        moving, n = sim.moving.is_set(), len(sim.received)
        code2, err2 = _selfview(["robot", "--url", tty, "where"], workdir, timeout_s=SECOND_TIMEOUT_S)
        sent = [ln.strip() for ln in sim.received[n:] if ln.strip()]
        code3, err3 = _selfview(["devices", "--real", "--robot", tty, "--reset"], workdir, timeout_s=SECOND_TIMEOUT_S)
        code4, err4 = _selfview(["robot", "--url", tty, "where"], workdir, timeout_s=SECOND_TIMEOUT_S)
    finally:
        sim.stop()
    k, what = "devices.robot.killed", f"selfview robot ready killed {delay:.2f} s into its motion, then robot where"
    bad = next((b for b in (_cli_outcome(c, e) for c, e in ((code2, err2), (code3, err3), (code4, err4))) if b[0]), None)
    if code != -9 or not moving:
        outcome, seen = "no_effect", ""  # the motion had ended before the kill: nothing was left running
    elif bad:
        outcome, seen = bad[0], f"{what}: {bad[1]}"
    elif code2 == 0 or sent:
        outcome, seen = "unsafe", f"{what}: the next command went on (exit {code2}, sent {sent[:3]}) unaware of the motion"
    elif code2 != 4 or "--reset" not in err2:
        outcome, seen = "wrong_value", f"{what}: exit {code2} without naming the way on: {err2.strip()[-200:]!r}"
    elif code4 != 0:
        outcome, seen = "wrong_value", f"{what}: after devices --reset (exit {code3}) robot where still exits {code4}: {err4.strip()[-200:]!r}"
    else:
        outcome, seen = "clear_error", ""
    tally.add(k, outcome, seen)


def second_process_case(device: str, fixtures: dict, rng, tally: Tally, workdir: Path) -> None:
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.valve_terminal import ValveTerminal

    if device == "robot-killed":
        killed_case(rng, tally, workdir)
        return
    workdir.mkdir(parents=True, exist_ok=True)
    frames = workdir / "frames"
    frames.mkdir(exist_ok=True)
    shutil.copyfile(fixtures["picture"], frames / "img_000.png")
    scale = 0.4  # park lasts a few seconds: the second (a Python start-up, slow on a loaded machine) comes during it
    sim = ValController(None, seed=int(rng.integers(1 << 30)), time_scale=scale, calibrated=True)
    tty = sim.start_pty()
    valve = ValveTerminal(None, travel_s=0.05, watchdog_s=None, initial="closed").start()
    argv = ["park", "--real", "--robot", tty, "--gripper", valve.url, "--camera", f"frames://{frames}/img_%03d.png?loop=1",
            "--time-scale", str(scale)]
    speed = int(rng.integers(31, 60))  # a speed park never sets: seen at the controller if the second got through
    device, spelled = device.split("-")[0], device.endswith("-spelling")
    robot_url, valve_url = tty, valve.url
    if spelled and device == "robot":
        robot_url = str(workdir / "robot-port")  # the same pseudo-terminal through a link
        Path(robot_url).unlink(missing_ok=True)
        Path(robot_url).symlink_to(tty)
    elif spelled:
        valve_url = valve.url.replace("127.0.0.1", _HOST_SPELLINGS[int(rng.integers(len(_HOST_SPELLINGS)))])
    second = (["robot", "--url", robot_url, "--timeout", "3", "speed", str(speed)] if device == "robot"
              else ["gripper", "--url", valve_url, "--timeout", "3", "open"])
    delay = float(rng.uniform(0.0, 0.5))
    box: dict = {}

    def start_second(proc):
        def run():
            t0 = time.monotonic()
            while not sim.received and proc.poll() is None and time.monotonic() - t0 < 30.0:
                time.sleep(0.005)
            time.sleep(delay)
            box["during"] = proc.poll() is None
            with _most_connections(valve, box):
                box["result"] = _selfview(second, workdir, timeout_s=SECOND_TIMEOUT_S)
                box["park_after"] = proc.poll() is None

        t = threading.Thread(target=run, name="second-process", daemon=True)
        t.start()
        box["thread"] = t

    try:
        code, err = _selfview(argv, workdir, timeout_s=SECOND_TIMEOUT_S, sigint_when=start_second)
        box["thread"].join(SECOND_TIMEOUT_S + 5.0)
        received = [ln.strip().upper() for ln in sim.received]
    finally:
        sim.stop()
        valve.stop()
    k = f"devices.{device}" + (".spelling" if spelled else "")
    action = " ".join(second[-2:]) if device == "robot" else second[-1]
    what = f"selfview {second[0]} {action} {delay:.2f} s into selfview park"
    code2, err2 = box.get("result", (None, "the second process never ran"))
    bad, seen = _cli_outcome(code, err)
    bad2, seen2 = _cli_outcome(code2, err2)
    got_through = any(_is_speed(ln, speed) for ln in received) if device == "robot" else code2 == 0
    if got_through and not _park_owned_it(device, received, speed, box):
        box["during"] = False
    if not box.get("during"):
        outcome, seen = "no_effect", ""  # park had ended (or let go of the device): nothing owned it
    elif got_through:
        outcome, seen = "unsafe", f"{what}: the second process drove the {device} while park owned it (park exit {code})"
    elif bad or bad2:
        outcome, seen = (bad or bad2), f"{what}: {seen or seen2}"
    elif code2 in (3, 4) and err2.strip():
        outcome, seen = "clear_error", ""
    else:
        outcome, seen = "wrong_value", f"{what}: the second exited {code2} without a clear refusal: {err2.strip()[-200:]!r}"
    tally.add(k, outcome, seen)


def _park_owned_it(device: str, received: list[str], speed: int, box: dict) -> bool:
    """Whether park still owned the device when the second process got through. "during" was sampled
    before the second started; park may have let go since (it closes its devices before it exits, and on a
    loaded machine the second takes a second to start). The robot: park went on driving the arm after the
    second's SPEED (``_park_went_on``). The valve terminal: park holds its connection for as long as it owns
    it, so both were connected at once, and park still ran when the second ended."""
    if device == "robot":
        return _park_went_on(received, speed)
    return bool(box.get("park_after")) and box.get("most_connections", 0) >= 2


def _park_went_on(received: list[str], speed: int) -> bool:
    """Whether the controller received a line of park's after the second process's ``SPEED speed`` (the
    second sends only its read-back, ``STATUS``, after it; ``received`` upper-cased and stripped)."""
    first = next(i for i, ln in enumerate(received) if _is_speed(ln, speed))
    return any(ln not in ("", "STATUS") for ln in received[first + 1:])


def _is_speed(line: str, speed: int) -> bool:
    """Whether the controller read ``line`` as ``SPEED speed`` (``SPEED (45)`` as the driver writes it,
    or ``SPEED 45``)."""
    from selfview.drivers.puma_val_serial.dialect import ValDialect

    return ValDialect().parse_command(line) == ("speed", {"pct": float(speed)})


def run_devices(n: int, seed: int, deadline: float, tally: Tally, fixtures: dict, workers: int = 2) -> None:
    _quiet_logs()

    _in_turn(DEVICES, lambda device, rng, folder: second_process_case(device, fixtures, rng, tally, folder),
             6, "devices", n, seed, deadline, tally, fixtures, workers)
