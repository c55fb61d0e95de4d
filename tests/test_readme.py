"""The README as a newcomer runs it: the tour's commands and the Python snippet, on the simulated cell."""

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()

#: The tour's paper experiment takes minutes; tests/procedures/test_cli_experiment.py runs it in small.
LONG = ("experiment",)


def tour() -> list[str]:
    block = README.split("## A tour", 1)[1].split("\n## ", 1)[0]
    return [ln.strip().split("  #")[0].strip() for ln in block.splitlines() if ln.startswith("    selfview ")]


def run(argv, cwd, timeout=240):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, *argv], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def test_the_tour_lists_the_commands():
    cmds = tour()
    assert len(cmds) >= 12 and all(c.startswith("selfview ") for c in cmds)
    named = {c.split()[1] for c in cmds}
    assert {"intrinsics", "calibrate", "verify", "export", "track", "camera", "devices", "monitor"} <= named
    assert "Exit codes: 0 ok, 1 internal error" in README and "130 interrupted" in README


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_every_tour_command_runs_as_written(tmp_path):
    (tmp_path / "selfview").symlink_to(REPO / "selfview")  # the tour runs in a checkout's folder
    for cmd in tour():
        argv = shlex.split(cmd)
        if argv[1] in LONG:
            continue
        r = run(["-m", "selfview.procedures.cli", *argv[1:]], tmp_path)
        assert r.returncode == 0, f"{cmd}: exit {r.returncode}\n{r.stderr[-2000:]}"
    for name in ("camera.yaml", "cal.yaml", "cal.opencv.yml", "parked.png", "truth.json", "moved.png"):
        assert (tmp_path / name).is_file(), name
    assert list(tmp_path.glob("cal.annotated-*.png"))


@pytest.mark.timeout(300)
def test_the_python_snippet_runs_as_written(tmp_path):
    code = re.search(r"```python\n(.*?)```", README, re.S).group(1)
    (tmp_path / "snippet.py").write_text(code)
    r = run(["snippet.py"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert re.match(r"rms \d\.\d{3} px; last frame: (update|recalibrate)", r.stdout)
    assert (tmp_path / "calibration.yaml").is_file()


@pytest.mark.timeout(300)
def test_the_picture_snippet_runs_as_written(tmp_path):
    """The one-call API on the files its comment makes: a go, the TCP with its sigma, then the tracked frame."""
    code = next(c for c in re.findall(r"```python\n(.*?)```", README, re.S) if "calibrate_picture" in c)
    for line in code.splitlines():
        if line.startswith("# selfview render"):
            for cmd in line[2:].split(";"):
                r = run(["-m", "selfview.procedures.cli", *shlex.split(cmd)[1:]], tmp_path)
                assert r.returncode == 0, r.stderr[-2000:]
    (tmp_path / "snippet.py").write_text(code)
    r = run(["snippet.py"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    first, second = r.stdout.splitlines()
    assert re.match(r"go \[.*\] \+- \[0\.0\d+, 0\.0\d+, 0\.0\d+\] mm", first), first
    assert re.match(r"(update|recalibrate) \[.*\] \+- \[.*\] mm", second), second
    assert (tmp_path / "cal.yaml").is_file()
