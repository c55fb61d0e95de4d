"""What every campaign shares: the outcomes and their tally, a call with a bound, worker threads, children
under a memory limit, the classification of a command's exit."""

from __future__ import annotations

import os
import re
import resource
import signal
import subprocess
import sys
import threading
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

from selfview.errors import CellError



# Every fault gets exactly one outcome, judged against the simulators' own state (read in-process):
# - clear_error: refused or failed with one of the project's errors (a message, exit 3/4/5, or 130 after
#   Ctrl-C), and the cell is as it should be;
# - no_effect: the operation succeeded and what it returned or did is the truth;
# - hang: no answer within the bound (the driver's own plus a margin, counted in time this process could run;
#   a CLI killed after its timeout); its record says where the call waited and how it ended;
# - traceback: an exception outside the project's error tree, a CLI exit 1 or a "Traceback";
# - unsafe: a motion other than the one checked (a corrupted motion command executed, a motion run twice),
#   a motion reported complete while the arm is elsewhere, a motion still running after the software gave
#   up, a speed above the driver's maximum applied, a valve energised after the driver gave up, jaws
#   driven the other way;
# - wrong_value: a value accepted that differs from the truth (a WHERE pose, a location, a jaw state, valve
#   outputs, a file's content, a speed), including those no check can see (also counted as ``invisible``);
# - lost_file: a calibration file lost, changed or left half-written.
OUTCOMES = ("clear_error", "no_effect", "hang", "traceback", "unsafe", "wrong_value", "lost_file")
EXAMPLE_OUTCOMES = ("unsafe", "wrong_value", "hang", "traceback", "lost_file")
VAL_FAULTS = ("bitflip", "digit_swap", "drop", "dup", "stray_prompt", "error_line", "stall", "cutoff", "nonascii")
MODBUS_FAULTS = ("bitflip", "drop", "dup", "stray_prompt", "stall", "cutoff", "nonascii")
TIME_SCALE = 0.02  # simulated motions take this fraction of real time
POS_TOL_MM, ANG_TOL_DEG = 0.5, 0.5  # "at the target": far above WHERE's 0.01 resolution, far below a fault's effect
WHERE_TOL_MM, WHERE_TOL_DEG = 0.05, 0.05  # a WHERE value against the simulator's pose (2 decimals printed)
CLI_TIMEOUT_S = 60.0
MEM_LIMIT = 3 << 30  # address-space limit of every child process (a bomb must not take the machine)


# --- bookkeeping ------------------------------------------------------------------------------------
class Tally:
    def __init__(self, max_examples: int = 4):
        self.kinds: dict[str, Counter] = defaultdict(Counter)
        self.examples: dict[str, list] = defaultdict(list)
        self.invisible: Counter = Counter()
        self.invisible_why: dict[str, str] = {}
        self.not_fired: Counter = Counter()
        self.notes: Counter = Counter()
        self.max_examples = max_examples
        self._lock = threading.Lock()

    def add(self, kind: str, outcome: str, seen: str = "", *, invisible: str | None = None) -> None:
        assert outcome in OUTCOMES, outcome
        with self._lock:
            self.kinds[kind][outcome] += 1
            if invisible and outcome == "wrong_value":
                self.invisible[kind] += 1
                self.invisible_why[kind] = invisible
            elif outcome in EXAMPLE_OUTCOMES:
                ex = self.examples[outcome]
                if sum(1 for e in ex if e["kind"] == kind) < 2 and len(ex) < 40:
                    ex.append({"kind": kind, "seen": seen[: 3000 if outcome == "hang" else 400]})  # a hang's stacks

    @property
    def total(self) -> int:
        return sum(sum(c.values()) for c in self.kinds.values())

    def to_json(self) -> dict:
        totals = {o: sum(c[o] for c in self.kinds.values()) for o in OUTCOMES}
        return {
            "total": self.total,
            "totals": totals,
            "kinds": {k: {o: c[o] for o in OUTCOMES} for k, c in sorted(self.kinds.items())},
            "examples": {o: self.examples.get(o, []) for o in EXAMPLE_OUTCOMES},
            "invisible": {k: {"wrong_value": n, "why": self.invisible_why[k]} for k, n in sorted(self.invisible.items())},
            "not_fired": dict(sorted(self.not_fired.items())),
            "notes": dict(sorted(self.notes.items())),
        }


def _err_text(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"


def _is_clear(exc: BaseException) -> bool:
    """One of the project's errors, with a message."""
    return isinstance(exc, CellError) and bool(str(exc).strip())


class Heartbeat:
    """A thread that sleeps ``period_s`` over and over and notes each wake-up later than ``late_s``: the
    spans in which this process could not run its Python code (the machine's load on a niced process, a
    stop, a thread holding the interpreter). ``stalled(since)`` is how much of the time since ``since``
    they cover. One per process (``heartbeat()``)."""

    def __init__(self, period_s: float = 0.05, late_s: float = 0.25):
        self.period_s, self.late_s = period_s, late_s
        self._gaps: list[tuple[float, float]] = []
        self._lock = threading.Lock()
        threading.Thread(target=self._run, name="campaign-heartbeat", daemon=True).start()

    def _run(self) -> None:
        while True:
            t = time.monotonic()
            time.sleep(self.period_s)
            now = time.monotonic()
            if now - t - self.period_s > self.late_s:
                self.note_gap(t + self.period_s, now)

    def note_gap(self, start: float, end: float) -> None:
        with self._lock:
            self._gaps = [g for g in self._gaps if g[1] > end - 3600.0] + [(start, end)]

    def stalled(self, since: float) -> float:
        """Seconds since ``since`` in which the process was seen not running."""
        with self._lock:
            return sum(max(0.0, e - max(s, since)) for s, e in self._gaps)


_HEARTBEAT: list[Heartbeat] = []
_HEARTBEAT_LOCK = threading.Lock()


def heartbeat() -> Heartbeat:
    with _HEARTBEAT_LOCK:
        if not _HEARTBEAT:
            _HEARTBEAT.append(Heartbeat())
        return _HEARTBEAT[0]


def _call(fn, timeout_s: float, after=None):
    """Run ``fn()`` in a thread; (status 'ok'|'error'|'hang', value or exception, after()'s snapshot
    taken in the thread the instant ``fn`` ended).

    The bound is ``timeout_s`` of time in which this process could run: spans in which the heartbeat saw it
    stalled (``Heartbeat``) are added to it, up to ``timeout_s`` more, and a call that returned only thanks
    to them is counted by its outcome and noted in the tally's notes. For a hang the value is what the call
    was doing at the bound (``thread_stacks``) and how it ended: the call is waited for once more as long,
    and the record says when it returned and how, or that it was still running (then with its stack again)."""
    box: dict = {}
    beat = heartbeat()
    t0 = time.monotonic()

    def work():
        try:
            box["value"] = fn()
            box["status"] = "ok"
        except BaseException as exc:  # classified by the caller
            box["value"] = exc
            box["status"] = "error"
        finally:
            box["took"] = time.monotonic() - t0
            if after is not None:
                try:
                    box["snap"] = after()
                except BaseException as exc:  # the snapshot reads the simulator: should not fail
                    box["snap"] = exc

    t = threading.Thread(target=work, name="fault-op", daemon=True)
    t.start()
    t.join(timeout_s)
    while t.is_alive() and time.monotonic() - t0 < timeout_s + min(beat.stalled(t0), timeout_s) - 0.01:
        t.join(t0 + timeout_s + min(beat.stalled(t0), timeout_s) - time.monotonic())
    stalled = beat.stalled(t0)
    if t.is_alive():
        at_bound = thread_stacks(t)
        t.join(timeout_s)
        if t.is_alive():
            late = f"still running {time.monotonic() - t0:.1f} s after it started; " + thread_stacks(t).split("other threads")[0]
        else:
            got = box["value"]
            late = (f"returned {box['took']:.1f} s after it started, "
                    + (f"with {_err_text(got)[:300]}" if box["status"] == "error" else "with a value"))
        return "hang", (f"{late}\nat the bound of {timeout_s:g} s (and {min(stalled, timeout_s):.1f} s in which the "
                        f"process was stalled), {at_bound}"), None
    if box["took"] > timeout_s and _NOTES is not None:
        _NOTES.notes[f"a call ran past its {timeout_s:g} s bound while this process was stalled (counted by its outcome)"] += 1
    return box["status"], box.get("value"), box.get("snap")


def thread_stacks(stuck: threading.Thread, depth: int = 12) -> str:
    """Where ``stuck`` waits and what every other thread of the process is doing, as a short text: the
    innermost ``depth`` frames of ``stuck`` (file, line, function, source), then one line per place where
    other threads are (their innermost frame in the project's own code, and their innermost frame), each
    place once with its count. Files are named from the project's folders or by their last two parts."""
    import traceback

    def where(fs) -> str:
        return f"{_short_file(fs.filename)}:{fs.lineno} {fs.name}"

    frames = sys._current_frames()
    top = frames.get(stuck.ident)
    if top is None:
        return f"thread {stuck.name}: ended while its stack was being taken"
    stack = traceback.extract_stack(top)[-depth:]
    lines = [f"thread {stuck.name} waits in:"] + [f"  {where(fs)}: {(fs.line or '').strip()[:80]}" for fs in stack]
    others: Counter = Counter()
    for ident, frame in frames.items():
        if ident in (stuck.ident, threading.get_ident()):
            continue
        st = traceback.extract_stack(frame)
        mine = [fs for fs in st if _PROJECT_FILE.search(fs.filename)]
        inner = where(st[-1])
        others[f"{where(mine[-1])} > {inner}" if mine and mine[-1] is not st[-1] else inner] += 1
    lines.append(f"other threads ({sum(others.values())}):")
    lines += [f"  {n} x {w}" for w, n in others.most_common()]
    return "\n".join(lines)


# the last of the project's folders in the path: a clone in a folder named "selfview" is not one of them
_PROJECT_FILE = re.compile(r"^.*[/\\]((?:selfview|drivers|mocks|procedures|bench)[/\\].+)$")


def _short_file(path: str) -> str:
    """A source file named from the project's own folders, else by its last two parts (no path of this machine)."""
    m = _PROJECT_FILE.search(path)
    return m.group(1) if m else "/".join(Path(path).parts[-2:])


def _limit_child():
    """preexec_fn of every child: an address-space limit (a YAML or PNG bomb cannot take the machine), and a
    terminal's signal dispositions, as an operator's shell gives them (a campaign started as a background job
    or under nohup would otherwise hand its ignored SIGINT, SIGQUIT and SIGHUP down, and the children would
    rightly keep ignoring them)."""
    for sig in (signal.SIGINT, signal.SIGQUIT, signal.SIGHUP, signal.SIGTERM, signal.SIGTSTP):
        signal.signal(sig, signal.SIG_DFL)
    try:
        resource.setrlimit(resource.RLIMIT_AS, (MEM_LIMIT, MEM_LIMIT))
    except (ValueError, OSError):
        pass


class _RigDead(Exception):
    pass

_NOTES: Tally | None = None  # where the log handler counts what the simulators' event loops log


def set_notes(tally: Tally) -> None:
    global _NOTES
    _NOTES = tally


def _quiet_logs() -> None:
    """The engine and the drivers log each failure; the campaign classifies them instead. Errors that
    the simulators' event loops log (asyncio) are counted in the JSON's notes."""
    import logging

    for name in ("selfview", "pymodbus"):
        lg = logging.getLogger(name)
        lg.addHandler(logging.NullHandler())
        lg.propagate = False

    class _Count(logging.Handler):
        def emit(self, record):
            if _NOTES is not None:
                _NOTES.notes[f"asyncio (the valve terminal's server) logged: {record.getMessage()[:60]}"] += 1

    lg = logging.getLogger("asyncio")
    if not any(isinstance(h, _Count) for h in lg.handlers):
        lg.addHandler(_Count())
        lg.propagate = False

def _in_threads(fn, n, seed, deadline, tally, workers):
    shares = [n // workers + (1 if i < n % workers else 0) for i in range(workers)]
    threads = []
    for i, share in enumerate(shares):
        if share:
            t = threading.Thread(target=_guarded, args=(fn, share, seed, i, deadline, tally), daemon=True)
            t.start()
            threads.append(t)
    for t in threads:
        t.join(max(0.0, deadline - time.monotonic()) + 60.0)
        if t.is_alive():
            tally.notes[f"{fn.__name__}: a worker did not finish"] += 1


def _in_turn(plan, case, salt: int, name: str, n, seed, deadline, tally, fixtures, workers) -> None:
    """``n`` cases over ``plan``'s items in turn, shared among ``workers`` threads until ``deadline``: each
    worker calls ``case(item, rng, folder)`` with its own random stream (``salt`` keeps the families'
    streams apart) and its own folder ``<name><worker>`` below the campaign's."""

    def worker(share, seed_, index, deadline_, tally_):
        rng = np.random.default_rng([seed, salt, index])
        for i in range(share):
            if time.monotonic() >= deadline:
                break
            case(plan[(index + workers * i) % len(plan)], rng, Path(fixtures["dir"]) / f"{name}{index}")

    _in_threads(worker, n, seed, deadline, tally, workers)


def _guarded(fn, share, seed, i, deadline, tally):
    try:
        fn(share, seed, i, deadline, tally)
    except Exception as exc:  # a fault of the campaign itself: said in the JSON, never hidden
        import traceback

        where = _no_machine_paths(traceback.format_exc().splitlines()[-3].strip())
        tally.notes[f"{fn.__name__}: campaign error {_err_text(exc)} at {where}"] += 1


def _build(cls, seed: int, tally: Tally):
    """A new rig (three tries: a loaded machine can miss a first exchange)."""
    for attempt in range(3):
        try:
            return cls(seed + 7919 * attempt)
        except CellError as exc:
            tally.notes[f"{cls.__name__}: a new rig failed its first exchange ({type(exc).__name__}); tried again"] += 1
    return cls(seed + 7919 * 3)


def _no_machine_paths(text: str) -> str:
    """A traceback line with its file named from the project's own folders (no path of this machine)."""
    return re.sub(r'"[^"]*?/((?:selfview|drivers|mocks|procedures|bench)/[^"/]+(?:/[^"/]+)*)"', r'"\1"', text)


def _draw(kinds, weights, rng) -> str:
    w = np.array([weights.get(k, 1.0) for k in kinds])
    return str(kinds[int(rng.choice(len(kinds), p=w / w.sum()))])

def _selfview(argv, cwd, timeout_s=CLI_TIMEOUT_S, sigint_when=None):
    """Run ``selfview argv``; (returncode or None on a hang, stderr). ``sigint_when(proc)`` (optional)
    is called in this thread once the process runs, to send Ctrl-C."""
    return _run_child(_cli_command(argv), cwd, timeout_s, sigint_when)


def _run_child(cmd, cwd, timeout_s, sigint_when=None):
    """Run ``cmd`` in its own session under the memory limit; (returncode or None on a hang, stderr)."""
    proc = subprocess.Popen(cmd, cwd=cwd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=_limit_child, start_new_session=True)
    if sigint_when is not None:
        sigint_when(proc)
    try:
        _, err = proc.communicate(timeout=timeout_s)
        return proc.returncode, err
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        _, err = proc.communicate()
        return None, err


def _cli_outcome(code, err) -> tuple[str | None, str]:
    """hang / traceback from an exit, or None when the exit is one of the documented ones."""
    if code is None:
        return "hang", f"killed after {CLI_TIMEOUT_S:g} s; stderr ...{err[-200:]!r}"
    if code == -signal.SIGINT and "Traceback" not in err:
        return None, ""  # ended by the Ctrl-C itself (the shell's exit status 130), e.g. while exiting
    if code < 0:
        return "traceback", f"killed by signal {-code}; stderr ...{err[-200:]!r}"
    if "Traceback (most recent call last)" in err or code == 1:
        tail = [ln for ln in err.strip().splitlines() if ln.strip()][-1:] or [""]
        return "traceback", f"exit {code}: {tail[0][:300]}"
    return None, ""


def _file_state(path: Path) -> tuple:
    """What must not change: the bytes of ``path`` and the folder's other files (a left temp file)."""
    blob = path.read_bytes() if path.exists() else None
    others = sorted(p.name for p in path.parent.iterdir() if p.name.startswith(".") and p.name.endswith(".tmp"))
    return blob, others

def _thread_deaths(tally: Tally):
    """Count threads that die of an exception (the simulators' server threads) instead of printing them."""
    def hook(args):
        tally.notes[f"thread {args.thread.name if args.thread else '?'} died: {args.exc_type.__name__}"] += 1

    threading.excepthook = hook




def _away_from_ready(sim) -> None:
    """Put the VAL simulator's arm at a pose away from READY (the simulator owns its state; no motion)."""
    with sim._state:
        sim._joints = sim._joints + np.array([60.0, -30.0, 40.0, 30.0, 30.0, 45.0])


def _cli_command(argv) -> list[str]:
    """The command line of ``selfview argv`` as ``_selfview`` runs it (for a child this process drives itself)."""
    return [sys.executable, "-c", "import sys; from selfview.procedures.cli import main; sys.exit(main())", *argv]


def _arm_after_exit(rec: dict) -> tuple[str, str] | None:
    """The first rule a command driving the VAL simulator broke, from a case's record (``code``, None when it
    was killed at the bound; ``err``; ``moving_exit``; ``moved_after`` deg of joints after it exited;
    ``motion_after_abort``, a motion line the controller received after an ABORT): hang or unsafe, or None."""
    code = rec["code"]
    if code is None:
        return "hang", _cli_outcome(code, rec["err"])[1]
    if rec["moving_exit"] or rec["moved_after"] > 0.01:
        return "unsafe", f"exit {code}, the arm moved {rec['moved_after']:.2f} deg after the command exited"
    if rec["motion_after_abort"]:
        return "unsafe", f"exit {code}, a motion ({rec['motion_after_abort']!r}) was sent after the ABORT"
    return None
