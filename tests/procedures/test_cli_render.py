"""``selfview render``: the picture and ground truth it writes are those of the simulated cell it builds."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from selfview.mocks.render import render
from selfview.mocks.world import SimWorld
from selfview.procedures.cli import EXIT_CONFIG, main
from selfview.files.cell import POINT_NAMES


def run(capsys, *argv):
    code = main(["render", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


def test_writes_the_picture_and_truth_of_the_parked_disturbed_cell(tmp_path, capsys, cell_path, cell):
    img, truth = tmp_path / "pic.png", tmp_path / "truth.json"
    code, out, _ = run(capsys, "--cell", cell_path, "--out", img, "--truth", truth,
                       "--seed", 3, "--state", "closed", "--disturb", "cable")
    assert code == 0
    summary = json.loads(out)
    assert summary["out"] == str(img) and summary["state"] == "closed" and summary["disturb"] == ["cable"]

    # the same steps in-process give the same bytes and the same truth
    world = SimWorld(cell, 3)
    world.park()
    world.set_jaw(cell.gripper.gap("closed"), "closed")
    world.disturb("cable")
    expect = render(world, seed=3)
    got = cv2.imread(str(img), cv2.IMREAD_UNCHANGED)
    assert got.dtype == np.uint8 and got.shape == (cell.camera.height, cell.camera.width)
    assert np.array_equal(got, expect.image)
    t = json.loads(truth.read_text())
    assert t == json.loads(json.dumps(expect.truth))
    assert t["jaw_gap_mm"] == cell.gripper.gap("closed") and t["parked"]
    assert set(t) >= {"f", "kappa", "principal_point", "C_H_G", "C_H_W", "discs", "corners"}
    assert list(t["corners"]) == list(POINT_NAMES)
    assert summary["visible_discs"] == sum(d[4] for d in t["discs"])
    # the disturbance moved the camera: the mount differs from the undisturbed cell's
    still = SimWorld(cell, 3)
    assert not np.allclose(t["C_H_G"], still.C_H_G, atol=1e-3)


def test_defaults_and_seeds(tmp_path, capsys, cell):
    a, b, c = (tmp_path / f"{n}.png" for n in "abc")
    assert run(capsys, "--out", a)[0] == 0
    assert run(capsys, "--out", b)[0] == 0
    assert run(capsys, "--out", c, "--seed", 1)[0] == 0
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()
    truth = tmp_path / "t.json"
    run(capsys, "--out", a, "--truth", truth)
    assert json.loads(truth.read_text())["jaw_gap_mm"] == cell.gripper.gap(cell.gripper.calibrate_in)


def test_free_gripper(tmp_path, capsys):
    truth = tmp_path / "t.json"
    code, out, _ = run(capsys, "--out", tmp_path / "free.png", "--truth", truth, "--free")
    assert code == 0 and not json.loads(out)["parked"]
    t = json.loads(truth.read_text())
    assert t["parked"] is False and not any(d[4] for d in t["discs"])


@pytest.mark.parametrize(
    "args, word",
    [
        (["--out", "{tmp}/missing/pic.png"], "--out"),
        (["--out", "{tmp}/pic.jpg"], ".png"),
        (["--out", "{tmp}/folder.png"], "is a folder"),
        (["--out", "{tmp}/pic.png", "--truth", "{tmp}/missing/t.json"], "--truth"),
        (["--out", "{tmp}/pic.png", "--state", "half"], "half"),
        (["--out", "{tmp}/pic.png", "--disturb", "wobble"], "wobble"),
        (["--out", "{tmp}/pic.png", "--cell", "{tmp}/none.yaml"], "none.yaml"),
    ],
)
def test_bad_arguments_exit_3_naming_what_is_wrong(tmp_path, capsys, args, word):
    (tmp_path / "folder.png").mkdir()
    code, _, err = run(capsys, *(a.format(tmp=tmp_path) for a in args))
    assert code == EXIT_CONFIG
    assert word in err
    assert not (tmp_path / "pic.png").exists()


@pytest.mark.parametrize(
    "argv, word",
    [
        (["render", "--seed", "-1", "--out", "{tmp}/p.png"], "--seed: out of range: -1"),
        (["render", "--seed", "1_0", "--out", "{tmp}/p.png"], "ASCII digits"),  # float() and int() take 1_0 as 10
        (["render", "--seed", "\uff13", "--out", "{tmp}/p.png"], "ASCII digits"),  # a full-width 3
        (["park", "--seed", "-5"], "--seed: out of range: -5"),
        (["experiment", "--trials", "0"], "--trials"),
        (["experiment", "--time-scale", "nan"], "--time-scale"),
        (["mock", "robot", "--port", "99999"], "--port: out of range: 99999"),
        (["mock", "gripper", "--duration", "inf"], "--duration"),
        (["mock", "robot", "--time-scale", "1e308"], "--time-scale"),
        (["grab", "--url", "sim://", "--out", "{tmp}/p.png", "--timeout", "1e10"], "--timeout"),
        (["camera", "--points", "{tmp}/p.dat", "--principal-point", "1e308", "0"], "--principal-point"),
    ],
)
def test_numbers_are_ascii_finite_and_in_range_or_exit_2(tmp_path, capsys, argv, word):
    with pytest.raises(SystemExit) as stop:
        main([a.format(tmp=tmp_path) for a in argv])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and word in err and "Traceback" not in err
    assert list(tmp_path.iterdir()) == []


def test_file_names_the_system_refuses_exit_3(tmp_path, capsys):
    long_name = str(tmp_path / ("a" * 300 + ".yaml"))
    picture = tmp_path / "p.png"
    assert run(capsys, "--out", picture)[0] == 0
    for argv in (["calibrate", "--image", str(picture), "--out", long_name],
                 ["calibrate", "--image", str(picture), "--out", "/dev/full"],
                 ["track", "--calibration", "/dev/full", "--image", str(picture)],
                 ["render", "--out", str(picture), "--truth", "/dev/full"]):
        code = main(argv)
        err = capsys.readouterr().err
        assert code == EXIT_CONFIG and "Traceback" not in err and ("/dev/full" in err or "aaaa" in err), err
