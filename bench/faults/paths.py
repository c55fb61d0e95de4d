"""Hostile paths at the command line: endless and huge files and FIFOs for every file argument (/dev/zero, a
FIFO nobody writes, a 3 GB sparse file), a full (/dev/full) and a read-only output folder for every output,
and numeric and path fuzz (1_0, full-width digits, 1e308, inf, nan, -1, a 300-character name)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from selfview.bench.faults.common import Tally, _cli_outcome, _in_threads, _limit_child, _quiet_logs

REFUSE_S, REFUSE_MB = 2.0, 200.0  # a hostile file is refused within this processor time and this much memory
CASE_TIMEOUT_S = 20.0  # beyond it the command is killed: a hang (far beyond a loaded machine's slowest start)
SPARSE_BYTES = 3 << 30
_RSS = "selfview-maxrss-kb"
# the peak memory and the processor time (user + system) the child used: its own work, which other work on
# the machine does not lengthen as it lengthens the wall-clock time
_MAIN = ("import atexit, resource, sys\n"
         "u = lambda: resource.getrusage(resource.RUSAGE_SELF)\n"
         f"atexit.register(lambda: print('\\n{_RSS}', u().ru_maxrss, u().ru_utime + u().ru_stime, file=sys.stderr))\n"
         "from selfview.procedures.cli import main\nsys.exit(main())\n")

#: every file argument: (name, argv with {X} for the hostile path, {P} a good picture, {C} a good calibration)
FILE_ARGS = (
    ("track.calibration", ["track", "--calibration", "{X}", "--image", "{P}", "--json"]),
    ("track.image", ["track", "--calibration", "{C}", "--image", "{X}", "--json"]),
    ("calibrate.image", ["calibrate", "--image", "{X}", "--out", "{O}", "--json"]),
    ("calibrate.cell", ["calibrate", "--cell", "{X}", "--image", "{P}", "--out", "{O}", "--json"]),
    ("calibrate.camera", ["calibrate", "--camera", "{X}", "--image", "{P}", "--out", "{O}", "--json"]),
    ("camera.points", ["camera", "--points", "{X}", "--principal-point", "258", "204", "--mode", "tsai"]),
)
ENDLESS = ("zero", "fifo", "sparse")
#: every output: (name, argv with {D} for the output's folder)
OUTPUTS = (
    ("calibrate.out", ["calibrate", "--image", "{P}", "--out", "{D}/cal.yaml", "--json"]),
    ("render.out", ["render", "--out", "{D}/frame.png"]),
    ("render.truth", ["render", "--out", "{W}/frame.png", "--truth", "{D}/truth.json"]),
    ("track.apply", ["track", "--calibration", "{D}/cal.yaml", "--image", "{P}", "--apply", "--json"]),
)
DISKS = ("full", "readonly")
BAD_NUMBERS = ("1_0", "\uff11\uff10", "1e308", "inf", "nan", "-1")
#: numbers at the command line: (name, argv with {V}; whether -1 is a valid value there)
NUMBER_ARGS = (
    ("robot.depart", ["robot", "--url", "{R}", "depart", "{V}"], False),
    ("robot.drive", ["robot", "--url", "{R}", "drive", "1", "{V}", "10"], False),
    ("robot.timeout", ["robot", "--url", "{R}", "--timeout", "{V}", "where"], False),
    ("gripper.timeout", ["gripper", "--url", "{G}", "--timeout", "{V}", "state"], False),
    ("gripper.request_timeout", ["gripper", "--url", "{G}", "--request-timeout", "{V}", "state"], False),
    ("render.seed", ["render", "--seed", "{V}", "--out", "{W}/seed.png"], True),
    ("mock.port", ["mock", "robot", "--port", "{V}"], False),
)
LONG_NAMES = (
    ("render.out", ["render", "--out", "{W}/{L}.png"]),
    ("calibrate.out", ["calibrate", "--image", "{P}", "--out", "{W}/{L}.yaml", "--json"]),
    ("track.calibration", ["track", "--calibration", "{W}/{L}.yaml", "--image", "{P}"]),
)

#: file names holding bytes that are not UTF-8 (as a shell passes $'cal\xff.yaml'): written as given, or a
#: clear refusal; never a crash inside a native call (``{B}``: such a name; whether it must be refused)
NON_UTF8 = (
    ("render.out", ["render", "--out", "{W}/{B}.png"], False),
    ("calibrate.out", ["calibrate", "--image", "{P}", "--out", "{W}/{B}.yaml", "--json"], False),
    ("render.out.extension", ["render", "--out", "{W}/frame.pn{B}"], True),
    ("calibrate.out.empty", ["calibrate", "--image", "{P}", "--out", ""], True),
)
_BYTES_NAME = os.fsdecode(b"cal\xff\xfe")


def _run(argv: list[str], cwd: Path, timeout_s: float = CASE_TIMEOUT_S) -> tuple[int | None, str, float, float]:
    """``selfview argv``: (exit code or None when killed at the timeout, stderr, processor seconds, peak resident MB)."""
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-c", _MAIN, *argv], cwd=cwd, stdin=subprocess.DEVNULL,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, preexec_fn=_limit_child,
                            start_new_session=True)
    try:
        _, err = proc.communicate(timeout=timeout_s)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        code = None
    m = re.search(rf"^{_RSS} (\d+) ([0-9.]+)$", err, flags=re.M)
    mb = int(m.group(1)) / 1024.0 if m else float("nan")
    cpu = float(m.group(2)) if m else time.monotonic() - t0  # (no report: the wall-clock time, an upper bound)
    return code, re.sub(rf"\n?{_RSS} \d+ [0-9.]+\n?", "", err), cpu, mb


def _judge(tally: Tally, kind: str, what: str, res, must_refuse: bool, *, moved: bool = False) -> None:
    code, err, dt, mb = res
    if code is None:
        tally.add(kind, "hang", f"{what}: killed after {CASE_TIMEOUT_S:g} s; stderr ...{err[-160:]!r}")
        return
    bad, seen = _cli_outcome(code, err)
    if moved:
        tally.add(kind, "wrong_value", f"{what}: the controller executed it (exit {code})")
    elif bad:
        tally.add(kind, bad, f"{what}: {seen}")
    elif code == 0:
        tally.add(kind, "wrong_value" if must_refuse else "no_effect", f"{what}: accepted, exit 0")
    elif not err.strip():
        tally.add(kind, "traceback", f"{what}: exit {code} with no message")
    else:
        tally.add(kind, "clear_error")


class Hostile:
    """The hostile files of one worker: a FIFO, a sparse file, a read-only folder; removed by ``close``."""

    def __init__(self, workdir: Path, fixtures: dict):
        self.dir = workdir
        workdir.mkdir(parents=True, exist_ok=True)
        self.fifo = workdir / "fifo.yaml"
        if not self.fifo.exists():
            os.mkfifo(self.fifo)
        self.sparse = workdir / "sparse.yaml"
        with open(self.sparse, "wb") as f:
            f.truncate(SPARSE_BYTES)
        self.readonly = workdir / "readonly"
        self.readonly.mkdir(exist_ok=True)
        shutil.copyfile(fixtures["cal"], self.readonly / "cal.yaml")
        self._immutable = subprocess.run(["chattr", "+i", str(self.readonly)], capture_output=True).returncode == 0
        if not self._immutable:
            os.chmod(self.readonly, 0o555)
        try:  # root ignores permissions: without chattr the folder may still be writable
            (self.readonly / ".probe").touch()
            (self.readonly / ".probe").unlink()
            self.readonly_ok = False
        except OSError:
            self.readonly_ok = True

    def path(self, kind: str) -> str:
        return {"zero": "/dev/zero", "fifo": str(self.fifo), "sparse": str(self.sparse)}[kind]

    def close(self) -> None:
        if self._immutable:
            subprocess.run(["chattr", "-i", str(self.readonly)], capture_output=True)
        os.chmod(self.readonly, 0o755)


def _fill(argv, **subs) -> list[str]:
    return [a.format(**subs) if "{" in a else a for a in argv]


def endless_case(i: int, fixtures: dict, hostile: Hostile, tally: Tally, work: Path) -> None:
    (name, argv), kind = FILE_ARGS[i % len(FILE_ARGS)], ENDLESS[(i // len(FILE_ARGS)) % len(ENDLESS)]
    x = hostile.path(kind)
    res = _run(_fill(argv, X=x, P=fixtures["picture"], C=fixtures["cal"], O=str(work / "out.yaml")), work)
    code, err, dt, mb = res
    what = f"selfview {argv[0]} --{name.split('.')[1]} given {'a 3 GB sparse file' if kind == 'sparse' else 'a FIFO' if kind == 'fifo' else '/dev/zero'}"
    k = f"files.{name}.{kind}"
    if code is not None and (dt > REFUSE_S or mb > REFUSE_MB) and not _cli_outcome(code, err)[0]:
        tally.add(k, "hang", f"{what}: refused only after {dt:.1f} s of processor time and {mb:.0f} MB "
                             f"(bound {REFUSE_S:g} s, {REFUSE_MB:g} MB)")
        return
    _judge(tally, k, what, res, must_refuse=True)


def disk_case(i: int, fixtures: dict, hostile: Hostile, tally: Tally, work: Path) -> None:
    disk = DISKS[(i // len(OUTPUTS)) % len(DISKS)]
    (name, argv) = OUTPUTS[i % len(OUTPUTS)]
    if disk == "full" and name == "track.apply":
        # the calibration it rewrites must be read first (/dev/full cannot be one): the next output instead,
        # so that every planned case runs
        (name, argv) = next(o for o in OUTPUTS[i % len(OUTPUTS) + 1:] + OUTPUTS if o[0] != "track.apply")
    k = f"files.{name}.{disk}"
    if disk == "readonly" and not hostile.readonly_ok:
        tally.notes["files: no read-only folder could be made here (chattr, permissions); its cases did not run"] += 1
        return
    if disk == "full":
        argv = [a.replace("{D}/cal.yaml", "/dev/full").replace("{D}/frame.png", "/dev/full").replace("{D}/truth.json", "/dev/full")
                for a in argv]
    folder = hostile.readonly
    guard = folder / "cal.yaml"
    before = guard.read_bytes()
    res = _run(_fill(argv, D=str(folder), P=fixtures["picture"], W=str(work)), work)
    what = f"selfview {argv[0]} writing to {'/dev/full' if disk == 'full' else 'a read-only folder'}"
    if guard.read_bytes() != before:
        tally.add(k, "lost_file", f"{what}: the calibration file in the folder changed")
        return
    _judge(tally, k, what, res, must_refuse=True)


def number_case(i: int, fixtures: dict, devices: dict, tally: Tally, work: Path) -> None:
    (name, argv, minus_ok), v = NUMBER_ARGS[i % len(NUMBER_ARGS)], BAD_NUMBERS[(i // len(NUMBER_ARGS)) % len(BAD_NUMBERS)]
    if name == "mock.port" and v in ("1_0", "\uff11\uff10"):
        v = "99999"  # an accepted 1_0 would serve on port 10 until killed: an out-of-range port instead
    sim = devices["robot"]
    n0 = len(sim.received)
    res = _run(_fill(argv, V=v, R=devices["robot_url"], G=devices["gripper_url"], W=str(work)), work)
    sent = [ln.strip().upper() for ln in sim.received[n0:]]
    moved = name in ("robot.depart", "robot.drive") and any(ln.startswith(("DEPART", "DO DEPART", "DRIVE", "DO DRIVE"))
                                                            for ln in sent)
    what = f"selfview {' '.join(a for a in argv if '{' not in a and not a.startswith('--url'))} with {v!r}"
    _judge(tally, f"fuzz.{name}", what, res, must_refuse=not (v == "-1" and minus_ok), moved=moved)


def long_name_case(i: int, fixtures: dict, tally: Tally, work: Path) -> None:
    name, argv = LONG_NAMES[i % len(LONG_NAMES)]
    res = _run(_fill(argv, W=str(work), L="n" * 300, P=fixtures["picture"]), work)
    _judge(tally, f"fuzz.{name}.long_name", f"selfview {argv[0]} with a 300-character file name", res, must_refuse=True)


def non_utf8_case(i: int, fixtures: dict, tally: Tally, work: Path) -> None:
    name, argv, must_refuse = NON_UTF8[i % len(NON_UTF8)]
    res = _run(_fill(argv, W=str(work), B=_BYTES_NAME, P=fixtures["picture"]), work)
    _judge(tally, f"fuzz.{name}.non_utf8", f"selfview {argv[0]} with a file name that is not UTF-8", res,
           must_refuse=must_refuse)


FAMILIES = ("endless", "disk", "numbers", "long_names", "non_utf8")


def run_paths(n: int, seed: int, deadline: float, tally: Tally, fixtures: dict, workers: int = 2) -> None:
    """``n`` cases over the four families in turn, each walking through its arguments and values."""
    _quiet_logs()

    def worker(share, seed_, index, deadline_, tally_):
        from selfview.mocks.val_controller import ValController
        from selfview.mocks.valve_terminal import ValveTerminal

        work = Path(fixtures["dir"]) / f"paths{index}"
        hostile = Hostile(work / "hostile", fixtures)
        sim = ValController(None, seed=seed + index, time_scale=0.01, calibrated=True)
        valve = ValveTerminal(None, travel_s=0.01, watchdog_s=None).start()
        devices = {"robot": sim, "robot_url": f"socket://127.0.0.1:{sim.start_tcp(0)}", "gripper_url": valve.url}
        counts = dict.fromkeys(FAMILIES, index)
        try:
            for i in range(share):
                if time.monotonic() >= deadline:
                    break
                fam = FAMILIES[(index + i) % len(FAMILIES)]
                j, counts[fam] = counts[fam], counts[fam] + workers
                if fam == "endless":
                    endless_case(j, fixtures, hostile, tally, work)
                elif fam == "disk":
                    disk_case(j, fixtures, hostile, tally, work)
                elif fam == "numbers":
                    number_case(j, fixtures, devices, tally, work)
                elif fam == "non_utf8":
                    non_utf8_case(j, fixtures, tally, work)
                else:
                    long_name_case(j, fixtures, tally, work)
        finally:
            hostile.close()
            sim.stop()
            valve.stop()

    _in_threads(worker, n, seed, deadline, tally, workers)
