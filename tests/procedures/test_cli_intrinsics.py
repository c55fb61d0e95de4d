"""``selfview intrinsics`` and ``selfview calibrate --camera`` / on the cell: a lab's new camera, end to end
on the simulated cell (its camera drawn realistic, unknown to the calibration), and the bad inputs."""

import json

import cv2
import numpy as np
import pytest

from selfview.files.calfile import load_calibration
from selfview.files.camfile import CameraFile, load_camera_file, save_camera_file
from selfview.estimation.intrinsics import TARGET_ACROSS_MM, TARGET_ALONG_MM
from selfview.mocks.world import SimWorld
from selfview.procedures.cli import main

SEED = 3


def run(capsys, argv):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, (json.loads(out) if code == 0 and "--json" in argv else out), err


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """The robot takes 12 views on the simulated cell and measures its realistic camera."""
    d = tmp_path_factory.mktemp("intr")
    cam = d / "camera.yaml"
    code = main(["intrinsics", "--sim-camera", "realistic", "--seed", str(SEED), "--json", "--out", str(cam),
                 "--save-views", str(d / "views")])
    assert code == 0
    return d, cam


def test_intrinsics_on_the_cell_measures_the_camera(measured, cell, capsys):
    d, cam = measured
    cf = load_camera_file(cam)
    truth = SimWorld(cell, seed=SEED, camera="realistic").camera
    c = cf.camera
    assert np.hypot(c.cx - truth.cx, c.cy - truth.cy) < 0.5  # px
    assert abs(c.aspect / truth.aspect - 1) < 5e-4 and abs(c.f / truth.f - 1) < 5e-4
    assert cf.figures["stop_rule"]["met"] and cf.figures["views_used"] >= 10
    assert len(cf.provenance["pictures"]) == 12 and all(len(p["sha256"]) == 64 for p in cf.provenance["pictures"])
    assert cf.provenance["source"].startswith("simulated cell")
    assert len(list((d / "views").glob("view_*.png"))) == 12
    assert not cf.figures["skew_fit"]["fitted"] and "skew not fitted:" in cam.read_text()


def test_intrinsics_json_from_picture_files(measured, tmp_path, capsys):
    d, _ = measured
    views = sorted(str(p) for p in (d / "views").glob("view_*.png"))
    code, out, err = run(capsys, ["intrinsics", "--images", *views, "--json"])
    assert code == 0, err
    for key in ("f", "kappa", "principal_point", "aspect", "sigma", "rms_px", "views_used", "projection_sigma_px",
                "stop_rule", "cross_check", "warnings"):
        assert key in out
    # a camera without shear: the views do not pin a skew, so it is held at 0 and the output says so
    assert set(out["sigma"]) == {"f", "kappa", "cx", "cy", "aspect"} and out["skew"] == 0.0
    assert not out["skew_fit"]["fitted"] and out["skew_fit"]["note"].startswith("skew not fitted:")
    code, text, err = run(capsys, ["intrinsics", "--images", *views])
    assert code == 0 and "skew not fitted:" in text and "nan" not in text and "None" not in text
    assert set(out["projection_sigma_px"]) == {"centre", "top_left", "top_right", "bottom_left", "bottom_right"}
    assert out["out"] is None and out["cross_check"]["done"]


def test_calibrate_with_the_camera_file_meets_the_targets_and_records_it(measured, cell, tmp_path, capsys):
    _, cam = measured
    cal = tmp_path / "cal.yaml"
    code, out, err = run(capsys, ["calibrate", "--sim-camera", "realistic", "--seed", str(SEED), "--camera", str(cam),
                                  "--out", str(cal), "--json"])
    assert code == 0, err
    truth = SimWorld(cell, seed=SEED, camera="realistic").C_H_G[:3, 3]
    e = np.asarray(out["C_H_G"])[:3, 3] - truth
    assert np.hypot(e[0], e[1]) < TARGET_ACROSS_MM and abs(e[2]) < TARGET_ALONG_MM
    assert out["warnings"] == []
    assert len(out["tcp_sigma_mm"]) == 3 and all(0 < s < 0.1 for s in out["tcp_sigma_mm"])
    assert out["camera_file"]["path"] == str(cam)
    assert load_calibration(cal).residuals["camera_file"]["sha256"] == out["camera_file"]["sha256"]


def test_calibrate_refuses_another_cameras_file_before_writing(measured, tmp_path, capsys):
    """A camera file of another camera of the same size (f 1052 px where this one has 962): the plate's disc
    residual with it is over a pixel against 0.2 px with the picture's own f, so nothing is written (exit 5);
    --force writes and warns. The right file's residual is within a hundredth of a pixel of the picture's own."""
    _, cam = measured
    cf = load_camera_file(cam)
    other = tmp_path / "other.yaml"
    save_camera_file(CameraFile(cf.camera.with_(f=1052.0), cf.sigma, cf.covariance), other)
    cal = tmp_path / "cal.yaml"
    argv = ["calibrate", "--sim-camera", "realistic", "--seed", str(SEED), "--profile", "realistic", "--out", str(cal)]
    code, _, err = run(capsys, argv + ["--camera", str(other)])
    assert code == 5 and not cal.exists(), err
    assert f"the camera file {other} does not fit this picture" in err
    assert "what to do: measure this camera with 'selfview intrinsics --out CAMERA.yaml'" in err
    rms = float(err.split("residual with its camera (f 1052.0 px) is ")[1].split(" px")[0])
    assert rms > 0.5  # px
    code, out, err = run(capsys, argv + ["--camera", str(other), "--force", "--json"])
    assert code == 0 and cal.exists() and not out["camera_file_fit"]["fits"]
    assert any("does not fit" in w and "--force" in w for w in out["warnings"])
    code, out, err = run(capsys, argv + ["--camera", str(cam), "--json", "--out", str(tmp_path / "right.yaml")])
    fit = out["camera_file_fit"]
    assert code == 0 and fit["fits"] and fit["excess_px"] < 0.02 and fit["refusal"] is None, fit


def test_calibrate_without_the_camera_file_warns(cell, tmp_path, capsys):
    cal = tmp_path / "cal.yaml"
    code, out, err = run(capsys, ["calibrate", "--sim-camera", "realistic", "--seed", str(SEED), "--out", str(cal),
                                  "--json"])
    assert code == 0
    assert len(out["warnings"]) == 1 and "selfview intrinsics" in out["warnings"][0]
    assert "warning: the picture shows the camera's principal point" in err
    assert "camera_file" not in load_calibration(cal).residuals
    # the nominal camera on a cell that has it: no warning
    code, out, err = run(capsys, ["calibrate", "--seed", str(SEED), "--out", str(tmp_path / "c2.yaml"), "--json"])
    assert code == 0 and out["warnings"] == [] and "warning" not in err


def test_bad_inputs_write_nothing(measured, tmp_path, capsys):
    d, cam = measured
    views = sorted(str(p) for p in (d / "views").glob("view_*.png"))
    out = tmp_path / "cam.yaml"
    # too few views
    code, _, err = run(capsys, ["intrinsics", "--images", *views[:3], "--out", str(out)])
    assert code == 5 and "at least 4" in err and not out.exists()
    # a picture without the plate among the views: named, nothing written
    blank = tmp_path / "table.png"
    cv2.imwrite(str(blank), (np.random.default_rng(0).uniform(60, 200, (576, 768))).astype(np.uint8))
    code, _, err = run(capsys, ["intrinsics", "--images", *views[:6], str(blank), "--out", str(out)])
    assert code == 5 and "table.png" in err and not out.exists()
    # the stop rule not met: not written without --force
    code, _, err = run(capsys, ["intrinsics", "--images", *views[:4], "--out", str(out)])
    if code == 5:
        assert "stop rule not met" in err and not out.exists()
    # a camera file for another picture size: calibrate refuses before anything
    cf = load_camera_file(cam)
    other = tmp_path / "other.yaml"
    save_camera_file(CameraFile(cf.camera.with_(width=640, height=480), cf.sigma, cf.covariance), other)
    cal = tmp_path / "cal.yaml"
    code, _, err = run(capsys, ["calibrate", "--image", views[0], "--camera", str(other), "--out", str(cal)])
    assert code == 3 and "640x480" in err and not cal.exists()
    # a calibration file given as a camera file
    code, _, err = run(capsys, ["calibrate", "--image", views[0], "--camera", str(tmp_path / "none.yaml"), "--out", str(cal)])
    assert code == 3 and "no such camera file" in err and not cal.exists()


def test_intrinsics_dry_run_moves_nothing(capsys):
    code, out, err = run(capsys, ["intrinsics", "--dry-run", "--views", "5"])
    assert code == 0
    assert err.count("moves(target=plate view") == 5 and "grab" in err


@pytest.mark.slow
def test_experiment_on_a_realistic_camera_measures_it_first(cell):
    """The experiment as a lab runs it with a new camera: intrinsics once, then park, calibrate, disturb,
    re-measure; the off-line reference then stays within the targets of the truth."""
    from selfview.procedures.experiment import run_direct

    records, summary = run_direct(cell, ("cable",), trials=1, seed=4, camera="realistic")
    cam = summary["camera"]
    assert cam["stop_rule_met"]
    t, m = cam["truth"], cam["measured"]
    assert np.hypot(*np.subtract(t["principal_point"], m["principal_point"])) < 0.5
    e = records[0].reference_err_truth_mm
    assert np.hypot(e[0], e[1]) < TARGET_ACROSS_MM and e[2] < TARGET_ALONG_MM


def test_measure_intrinsics_refuses_names_that_do_not_match_the_pictures(cell):
    from selfview.errors import ConfigError
    from selfview.procedures.intrinsics import measure_intrinsics

    pictures = [np.zeros((576, 768), np.uint8)] * 3
    for camera in (None, cell.camera.guess()):
        with pytest.raises(ConfigError, match="3 picture\\(s\\) but 2 name\\(s\\)"):
            measure_intrinsics(pictures, cell.plate, camera, ["a", "b"])
