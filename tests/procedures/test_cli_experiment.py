import json
import subprocess
import sys
from pathlib import Path

import pytest

from selfview.procedures.cli import main

REPO = Path(__file__).resolve().parents[2]
METHODS = ("3P-U", "4P-U", "5P-U", "3P-I", "4P-I", "5P-I", "4P-R", "5P-R")


def test_experiment_writes_its_results_folder(tmp_path, capsys):
    out = tmp_path / "run"
    # the perfect cell: its figures are the method's own (the default, realistic, adds a real cell's errors)
    code = main(["experiment", "--trials", "3", "--out", str(out), "--json", "--quiet", "--seed", "11",
                 "--profile", "ideal", "--sim-camera", "ideal"])
    assert code == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["folder"] == str(out)
    res = json.loads((out / "results.json").read_text())
    for series in ("cable", "tilt"):
        ser = res["summary"][series]
        assert ser["trials"] + sum(f["series"] == series for f in res["summary"]["failures"]) == 3
        ok = [m for m in METHODS if "reference" in ser["methods"][m]]
        assert len(ok) >= 5  # most methods ran on most trials
        for m in ok:
            for against in ("reference", "truth"):
                e = ser["methods"][m][against]
                assert len(e["mean_mm"]) == 3 and len(e["max_mm"]) == 3
                assert all(0 <= a <= b for a, b in zip(e["mean_mm"], e["max_mm"]))
        # the on-line estimates of a 1.5 or 4.5 mm shift land within a fraction of a mm
        assert max(ser["methods"]["4P-I"]["truth"]["mean_mm"]) < 0.2
    assert res["config"]["seed"] == 11 and res["config"]["profile"] == "ideal" and res["cell"]["sha256"]
    assert res["environment"]["selfview"]
    assert len(res["trials"]) >= 4
    for f in ("tables.md", "errors.png", "trial1_offline.png", "trial1_online.png", "trial1_picture1.png"):
        assert (out / f).stat().st_size > 0
    tables = (out / "tables.md").read_text()
    assert "Table 1" in tables and "Table 2" in tables and "| 4P-U" in tables
    # a run never overwrites an earlier run's folder
    assert main(["experiment", "--trials", "1", "--out", str(out), "--quiet"]) == 3
    assert "already holds" in capsys.readouterr().err


def test_bad_arguments_name_the_problem(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["experiment", "--trials", "0", "--quiet"])
    assert stop.value.code == 2 and "--trials" in capsys.readouterr().err
    assert main(["experiment", "--robot", "/dev/ttyS0", "--quiet"]) == 3
    assert "--real" in capsys.readouterr().err
    assert main(["experiment", "--real", "--quiet"]) == 3
    assert "robot URL" in capsys.readouterr().err
    assert main(["experiment", "--profile", "perfect", "--quiet"]) == 3
    assert "paper-like" in capsys.readouterr().err  # names the profiles there are


@pytest.mark.parametrize("script, args, expect", [
    ("offline_calibration.py", ["cal.yaml"], "saved to cal.yaml"),
    ("monitoring_loop.py", ["6"], "frame 6:"),
    ("picture_files.py", ["parked.png", "moved.png"], "tracking: "),
])
def test_examples_run(tmp_path, script, args, expect):
    if script == "picture_files.py":
        assert main(["render", "--out", str(tmp_path / "parked.png")]) == 0
        assert main(["render", "--out", str(tmp_path / "moved.png"), "--disturb", "cable"]) == 0
    r = subprocess.run([sys.executable, str(REPO / "examples" / script), *args], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert expect in r.stdout


def test_profile_option_where_a_simulated_cell_is_built():
    """Every command that builds a simulated cell builds the same one by default (ideal, the nominal camera),
    takes ``--profile`` and ``--sim-camera`` and passes them to the world."""
    from selfview.procedures.cli import build_parser
    from selfview.procedures.simcell import SimulatedCell
    from selfview.files.cell import default_cell_path, load_cell

    p = build_parser()
    for cmd in ("park", "monitor", "devices", "render", "experiment", "verify", "calibrate", "intrinsics"):
        extra = {"render": ["--out", "x.png"], "monitor": ["--calibration", "cal.yaml"]}.get(cmd, [])
        assert p.parse_args([cmd, *extra]).profile == "ideal"
        if cmd != "render":
            assert p.parse_args([cmd, *extra]).sim_camera == "ideal"
        assert p.parse_args([cmd, *extra, "--profile", "paper-like"]).profile == "paper-like"
    sim = SimulatedCell(load_cell(default_cell_path()), seed=2, profile="paper-like")
    assert sim.world.imperfections.finger_dim_sd_mm > 0


@pytest.mark.parametrize("existed", [False, True])
def test_a_failed_write_leaves_no_partial_results_folder(tmp_path, capsys, monkeypatch, existed):
    import errno

    import selfview.procedures.runs as runs

    real_write = runs.write_experiment_folder

    def disk_fills(folder, *a, **kw):
        (Path(folder) / "tables.md").write_text("half")
        (Path(folder) / "pictures").mkdir()
        raise OSError(errno.ENOSPC, "No space left on device", str(Path(folder) / "errors.png"))

    monkeypatch.setattr(runs, "write_experiment_folder", disk_fills)
    out = tmp_path / "run"
    if existed:
        out.mkdir()
    argv = ["experiment", "--trials", "1", "--series", "cable", "--profile", "ideal", "--sim-camera", "ideal",
            "--out", str(out), "--quiet"]
    assert main(argv) == 3
    err = capsys.readouterr().err
    assert "No space left on device" in err and "errors.png" in err and "Traceback" not in err
    assert out.is_dir() == existed and (not existed or list(out.iterdir()) == [])
    monkeypatch.setattr(runs, "write_experiment_folder", real_write)
    assert main(argv) == 0 and (out / "results.json").is_file()


def test_no_error_plot_when_every_trial_failed(tmp_path):
    """A run whose every trial failed (e.g. no fingertip found off-line) writes its folder without the plot
    instead of crashing in matplotlib (0 rows of subplots)."""
    from selfview.procedures.results import plot_errors

    summary = {"failures": [{"series": "cable", "index": 0, "seed": 0, "error": "CalibrationError: ..."}]}
    assert plot_errors(summary, tmp_path / "errors.png", METHODS) is None
    assert not (tmp_path / "errors.png").exists()
