"""A save of the calibration file killed (SIGKILL) at each file-system call it makes, one call per case: the
file must still load (the old version or the new one), and the next save must leave no temporary file."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path


from selfview.errors import CellError
from selfview.bench.faults.common import CLI_TIMEOUT_S, Tally, _in_threads, _limit_child

#: the os functions a save may call; the child is killed just before the k-th call to any of them
CALLS = ("open", "write", "fsync", "fdatasync", "close", "replace", "rename", "link", "unlink", "mkdir", "makedirs",
         "fchmod", "chmod", "stat", "lstat", "ftruncate")

_SAVER = r'''
import os, signal, sys
from selfview.files.calfile import load_calibration, save_calibration
src, out, k = sys.argv[1], sys.argv[2], int(sys.argv[3])
cal = load_calibration(src)
seen = []
def wrap(name, fn):
    def call(*a, **kw):
        seen.append(name)
        if len(seen) == k:
            print(name, file=sys.stderr, flush=True)
            os.kill(os.getpid(), signal.SIGKILL)
        return fn(*a, **kw)
    return call
for name in sys.argv[4].split(","):
    if hasattr(os, name):
        setattr(os, name, wrap(name, getattr(os, name)))
save_calibration(cal, out)
print(len(seen), ",".join(seen), file=sys.stderr)
'''


def _save(src: str, out: Path, k: int) -> tuple[int | None, str]:
    proc = subprocess.run([sys.executable, "-c", _SAVER, src, str(out), str(k), ",".join(CALLS)],
                          capture_output=True, text=True, timeout=CLI_TIMEOUT_S, preexec_fn=_limit_child)
    return proc.returncode, proc.stderr


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.name.endswith(".tmp"))


def calls_of_a_save(fixtures: dict, workdir: Path) -> int:
    """How many of ``CALLS`` one save of the calibration file makes (over an existing file, with history)."""
    workdir.mkdir(parents=True, exist_ok=True)
    out = workdir / "count.yaml"
    out.write_bytes(Path(fixtures["cal"]).read_bytes())
    code, err = _save(fixtures["cal"], out, 0)
    return int(err.split()[0]) if code == 0 and err.split() and err.split()[0].isdigit() else 0


def save_case(k: int, fixtures: dict, tally: Tally, workdir: Path) -> None:
    from selfview.files.calfile import load_calibration, save_calibration

    workdir.mkdir(parents=True, exist_ok=True)
    for p in workdir.iterdir():  # a fresh folder per case
        if p.is_dir():
            import shutil

            shutil.rmtree(p)
        else:
            p.unlink()
    out = workdir / "cal.yaml"
    out.write_bytes(Path(fixtures["cal"]).read_bytes())
    try:
        code, err = _save(fixtures["cal"], out, k)
    except subprocess.TimeoutExpired:
        tally.add("save.hang", "hang", f"a save killed at call {k} did not end within {CLI_TIMEOUT_S:g} s")
        return
    call = err.strip().splitlines()[0] if err.strip() else "?"
    kind = f"save.{call}" if code == -9 else "save.completed"
    what = f"a save killed just before its call {k} (os.{call})"
    try:
        load_calibration(out)
    except CellError as exc:
        tally.add(kind, "lost_file", f"{what}: the calibration file no longer loads: {exc}")
        return
    try:  # the next save cleans up after the killed one
        save_calibration(load_calibration(fixtures["cal"]), out)
    except CellError as exc:
        tally.add(kind, "lost_file", f"{what}: the next save failed: {exc}")
        return
    left = _leftovers(workdir)
    if left:
        tally.add(kind, "lost_file", f"{what}: the next save left the killed one's temporary files {left[:3]}")
    elif code == -9:
        tally.add(kind, "clear_error")
    elif code == 0:
        tally.add(kind, "no_effect")
    else:
        tally.add(kind, "traceback", f"{what}: the save exited {code}: {err.strip()[-200:]!r}")


def run_saves(n: int, seed: int, deadline: float, tally: Tally, fixtures: dict, workers: int = 2) -> None:
    """``n`` killed saves, the kill moving through every call of a save in turn."""
    total = calls_of_a_save(fixtures, Path(fixtures["dir"]) / "saves-count")
    if total == 0:
        tally.notes["saves: a clean save could not be counted; the family did not run"] += 1
        return

    def worker(share, seed_, index, deadline_, tally_):
        for i in range(share):
            if time.monotonic() >= deadline:
                break
            save_case(1 + (index + workers * i) % total, fixtures, tally, Path(fixtures["dir"]) / f"saves{index}")

    _in_threads(worker, n, seed, deadline, tally, workers)
    tally.notes[f"saves: one save makes {total} file-system calls"] += 1
