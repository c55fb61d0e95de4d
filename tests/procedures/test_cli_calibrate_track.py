"""``selfview calibrate`` and ``selfview track`` on rendered pictures: outputs, files, and failures."""

import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from selfview.mocks.render import render
from selfview.mocks.world import SimWorld
from selfview.procedures.cli import main
from selfview.files.calfile import history_dir, load_calibration


@pytest.fixture(scope="module")
def pictures(cell, tmp_path_factory):
    d = tmp_path_factory.mktemp("pics")
    w = SimWorld(cell, seed=21)
    w.park()
    cv2.imwrite(str(d / "parked.png"), render(w, seed=1).image)
    truth1 = w.truth()
    w.disturb("cable")
    cv2.imwrite(str(d / "cable.png"), render(w, seed=2).image)
    truth2 = w.truth()
    w.reset_disturbance()
    pivot = cell.simulation.disturbances["cable"].pivot_C
    w.disturb_by_angle([0, 1, 0], 0.15, pivot)
    cv2.imwrite(str(d / "nudge.png"), render(w, seed=4).image)
    w.reset_disturbance()
    w.disturb_by_angle([0, 1, 0], 2.5, pivot)
    cv2.imwrite(str(d / "mid.png"), render(w, seed=5).image)
    truth_mid = w.truth()
    w.reset_disturbance()
    np.save(d / "truth_mid.npy", np.asarray(truth_mid["C_H_G"]))
    w.disturb_by_angle([0, 1, 0], 8.0, cell.simulation.disturbances["cable"].pivot_C)
    cv2.imwrite(str(d / "far.png"), render(w, seed=3).image)
    cv2.imwrite(str(d / "blank.png"), np.full((576, 768), 128, np.uint8))
    cv2.imwrite(str(d / "small.png"), np.zeros((480, 640), np.uint8))
    return d, truth1, truth2


def run_json(capsys, argv):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, (json.loads(out) if code == 0 and "--json" in argv else out), err


def test_calibrate_writes_the_file_and_prints_json(pictures, tmp_path, capsys):
    d, truth, _ = pictures
    cal = tmp_path / "cal.yaml"
    code, out, err = run_json(capsys, ["calibrate", "--image", str(d / "parked.png"), "--out", str(cal), "--json"])
    assert code == 0, err
    for key in ("f", "kappa", "C_H_W", "C_H_G", "points_G", "rms_px", "discs_used", "corners_found"):
        assert key in out
    assert out["f"] == pytest.approx(962.0, rel=2e-3)
    assert np.allclose(np.asarray(out["C_H_G"])[:3, 3], np.asarray(truth["C_H_G"])[:3, 3], atol=0.1)
    assert set(out["points_G"]) == {"A-inner-front", "A-inner-back", "B-inner-front", "B-inner-back",
                                    "A-outer-front", "B-outer-front"}
    c = load_calibration(cal)
    assert np.allclose(c.C_H_G, out["C_H_G"]) and c.image_sha256 and c.cell_sha256
    assert set(c.points_G) == {"open", "closed"}
    # a second calibration keeps the first in the history
    code, out2, _ = run_json(capsys, ["calibrate", "--image", str(d / "parked.png"), "--out", str(cal), "--json"])
    assert code == 0 and len(list(history_dir(cal).iterdir())) == 1


@pytest.mark.parametrize("picture, code_expected, words", [
    ("blank.png", 5, "blank"),
    ("small.png", 5, "640x480"),
    ("missing.png", 3, "cannot read"),  # a file fault: the README's 3
])
def test_calibrate_failures_write_nothing(pictures, tmp_path, capsys, picture, code_expected, words):
    d, _, _ = pictures
    cal = tmp_path / "cal.yaml"
    code, _, err = run_json(capsys, ["calibrate", "--image", str(d / picture), "--out", str(cal)])
    assert code == code_expected and words in err
    assert not cal.exists()


def test_calibrate_refuses_to_overwrite_a_foreign_file(pictures, tmp_path, capsys):
    d, _, _ = pictures
    cal = tmp_path / "cal.yaml"
    cal.write_text("somebody: else's file\n")
    code, _, err = run_json(capsys, ["calibrate", "--image", str(d / "parked.png"), "--out", str(cal)])
    assert code == 3 and "not a selfview calibration" in err
    assert cal.read_text() == "somebody: else's file\n"


@pytest.fixture
def calibrated(pictures, tmp_path, capsys):
    d, _, _ = pictures
    cal = tmp_path / "cal.yaml"
    assert main(["calibrate", "--image", str(d / "parked.png"), "--out", str(cal)]) == 0
    capsys.readouterr()
    return cal


@pytest.mark.parametrize("method", ["3P-U", "4P-U", "5P-U", "3P-I", "4P-I", "5P-I", "4P-R", "5P-R"])
def test_track_each_method(pictures, calibrated, capsys, method):
    d, _, truth2 = pictures
    code, out, err = run_json(capsys, ["track", "--calibration", str(calibrated), "--image", str(d / "cable.png"),
                                       "--method", method, "--json"])
    assert code == 0, err
    for key in ("method", "C_H_G", "delta_deg", "d_mm", "decision", "points_used", "rms_px"):
        assert key in out
    assert out["method"] == method and len(out["points_used"]) == int(method[0])
    assert np.allclose(np.asarray(out["C_H_G"])[:3, 3], np.asarray(truth2["C_H_G"])[:3, 3], atol=0.1)
    assert out["applied"] is False


def test_track_auto_follows_the_policy_and_apply_writes_atomically(pictures, calibrated, capsys, cell_path,
                                                                   monkeypatch):
    d, _, _ = pictures
    before = load_calibration(calibrated).C_H_G
    before_bytes = calibrated.read_bytes()
    # the shared reference cell's limits: update below 1 deg / 2 mm, alarm above 5 deg / 10 mm
    policy = ["--cell", str(cell_path), "track", "--calibration", str(calibrated), "--method", "auto", "--json"]
    policy = policy[2:] + policy[:2]
    code, out, err = run_json(capsys, policy + ["--image", str(d / "nudge.png")])
    assert code == 0, err
    assert out["decision"] == "update" and out["applied"] is False and out["delta_deg"] < 1.0
    code, out, err = run_json(capsys, policy + ["--image", str(d / "mid.png"), "--apply"])
    assert code == 0, err
    assert out["decision"] == "recalibrate" and out["method"].endswith("-R") and out["applied"] is True
    after = load_calibration(calibrated)
    assert not np.allclose(after.C_H_G, before)
    assert np.allclose(after.C_H_G[:3, 3], np.load(d / "truth_mid.npy")[:3, 3], atol=0.1)
    assert after.updates and after.updates[-1]["by"] == "track"
    kept = list(history_dir(calibrated).iterdir())
    assert len(kept) == 1 and kept[0].read_bytes() == before_bytes  # the previous file, byte for byte
    assert not [p.name for p in calibrated.parent.iterdir() if p.name.endswith(".tmp")]  # no temporary left
    # atomic: when the final rename onto the file fails, the command fails and the file is as it was
    now = calibrated.read_bytes()
    real_replace = os.replace

    def failing_replace(src, dst, *a, **kw):
        if Path(dst) == calibrated:
            raise OSError(28, "No space left on device")
        return real_replace(src, dst, *a, **kw)

    monkeypatch.setattr(os, "replace", failing_replace)
    code = main(policy + ["--image", str(d / "mid.png"), "--apply"])
    err = capsys.readouterr()[1]
    monkeypatch.setattr(os, "replace", real_replace)
    # a clear error naming the file and the cause, exit 3 (a file problem), the previous file unchanged
    assert code == 3 and str(calibrated) in err and "no space left" in err.lower() and "unchanged" in err, (code, err)
    assert calibrated.read_bytes() == now
    assert not [p.name for p in calibrated.parent.iterdir() if p.name.endswith(".tmp")]


def test_track_auto_raises_the_alarm_for_a_large_move_and_writes_nothing(pictures, calibrated, capsys):
    d, _, _ = pictures
    before = calibrated.read_bytes()
    code = main(["track", "--calibration", str(calibrated), "--image", str(d / "far.png"), "--method", "auto",
                 "--apply"])
    _, err = capsys.readouterr()
    # 8 degrees: beyond the alarm limit (an alarm, exit 6), or the fingertips left their search windows (not
    # found, exit 5); never an update
    assert (code == 6 and "alarm" in err.lower()) or (code == 5 and "fingertips not found" in err), (code, err)
    assert calibrated.read_bytes() == before


def test_track_with_a_corrupt_calibration_file(pictures, tmp_path, capsys):
    d, _, _ = pictures
    bad = tmp_path / "cal.yaml"
    bad.write_text(yaml.safe_dump({"format": "selfview-calibration", "version": 1, "checksum": "sha256:0"}))
    code = main(["track", "--calibration", str(bad), "--image", str(d / "cable.png")])
    assert code == 3 and "checksum" in capsys.readouterr().err


def test_monitor_prints_each_decision_and_how_the_fingertips_were_found(tmp_path, capsys):
    """``selfview park`` -> ``calibrate`` -> ``monitor`` on the simulated cell (one seed throughout): the
    first frame's fingertips are searched for, the next ones tracked while the camera creeps."""
    pic, cal = tmp_path / "parked.png", tmp_path / "cal.yaml"
    assert main(["park", "--seed", "5", "--time-scale", "0.01", "--out", str(pic)]) == 0
    assert main(["calibrate", "--image", str(pic), "--out", str(cal)]) == 0
    capsys.readouterr()
    code = main(["monitor", "--seed", "5", "--time-scale", "0.01", "--calibration", str(cal), "--frames", "3",
                 "--drift", "0.05", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    recs = [json.loads(line) for line in out.splitlines() if line.strip()]
    assert [r["frame"] for r in recs] == [1, 2, 3] and all(r["action"] == "update" for r in recs)
    assert recs[0]["fingertips"] == "searched (no earlier frame)"
    assert [r["fingertips"] for r in recs[1:]] == ["tracked", "tracked"]


def test_monitor_whose_output_goes_away_ends_non_zero_after_the_cleanup(tmp_path, capsys):
    """``monitor | head -1``: the reader ends after the first line; the monitor makes the cell safe, says so and
    ends with 141 (128 + SIGPIPE), not 0 as if its twelve frames had been watched."""
    import os
    import subprocess
    import sys

    from tests.conftest import REPO

    pic, cal = tmp_path / "parked.png", tmp_path / "cal.yaml"
    assert main(["park", "--seed", "5", "--time-scale", "0.01", "--out", str(pic)]) == 0
    assert main(["calibrate", "--image", str(pic), "--out", str(cal)]) == 0
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-m", "selfview.procedures.cli", "monitor", "--seed", "5", "--time-scale",
                             "0.01", "--calibration", str(cal), "--frames", "12", "--json"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        first = proc.stdout.readline()
        proc.stdout.close()  # what head -1 does
        err = proc.stderr.read().decode()
        proc.wait(120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    assert json.loads(first)["frame"] == 1
    assert proc.returncode == 141, err
    assert "standard output was closed" in err and "valve set to its safe state" in err and "Traceback" not in err, err


def _another_writer(path):
    """What another program does meanwhile: its own update of the calibration file (a different C_H_G)."""
    from selfview.files.calfile import save_calibration

    other = load_calibration(path)
    other.C_H_G = other.C_H_G.copy()
    other.C_H_G[0, 3] += 1.0
    other.updates.append({"by": "another program"})
    save_calibration(other, path, expected=load_calibration(path))
    return path.read_bytes()


def test_track_apply_never_overwrites_a_file_changed_since_it_was_read(pictures, calibrated, capsys, monkeypatch):
    import selfview.procedures.results as results

    d, _, _ = pictures
    real, box = results.keep_pictures, {}

    def meanwhile(out, *a, **kw):  # runs after track read the file, before it saves
        box["theirs"] = _another_writer(calibrated)
        return real(out, *a, **kw)

    monkeypatch.setattr(results, "keep_pictures", meanwhile)
    code = main(["track", "--calibration", str(calibrated), "--image", str(d / "mid.png"), "--method", "auto", "--apply"])
    err = capsys.readouterr().err
    assert code == 3 and str(calibrated) in err, err
    assert calibrated.read_bytes() == box["theirs"]  # the other program's update stands


def test_monitor_apply_never_overwrites_a_file_changed_since_it_was_read(tmp_path, capsys, monkeypatch):
    from selfview.procedures.runs import CellSession

    pic, cal = tmp_path / "parked.png", tmp_path / "cal.yaml"
    assert main(["park", "--seed", "5", "--time-scale", "0.01", "--out", str(pic)]) == 0
    assert main(["calibrate", "--image", str(pic), "--out", str(cal)]) == 0
    real, box = CellSession.monitor, {}

    def meanwhile(self, *a, **kw):
        out = real(self, *a, **kw)
        box["theirs"] = _another_writer(cal)
        return out

    monkeypatch.setattr(CellSession, "monitor", meanwhile)
    capsys.readouterr()
    code = main(["monitor", "--seed", "5", "--time-scale", "0.01", "--calibration", str(cal), "--frames", "2", "--apply"])
    err = capsys.readouterr().err
    assert code == 3 and str(cal) in err, err
    assert cal.read_bytes() == box["theirs"]
