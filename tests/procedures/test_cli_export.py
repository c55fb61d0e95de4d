"""``selfview export``: the files load with OpenCV and as YAML, and the OpenCV distortion reproduces the kappa model."""

import json

import cv2
import numpy as np
import pytest
import yaml

from selfview.files.calfile import load_calibration, save_calibration
from selfview.procedures.cli import main


@pytest.fixture(scope="module")
def calfile(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    assert main(["calibrate", "--out", str(d / "cal.yaml"), "--no-pictures", "--json"]) == 0
    cal = load_calibration(d / "cal.yaml")
    # a camera with a grabber's aspect and shear and a stronger lens: the fit must hold for it too
    cal.camera = cal.camera.with_(aspect=1.03, skew=0.0008, kappa=4e-7, cx=391.2, cy=281.7)
    save_calibration(cal, d / "sheared.yaml")
    return d


@pytest.mark.parametrize("name", ["cal.yaml", "sheared.yaml"])
def test_opencv_file_loads_and_reproduces_the_kappa_model(calfile, name, capsys):
    capsys.readouterr()
    out = calfile / (name + ".yml")
    assert main(["export", str(calfile / name), "--format", "opencv", "--out", str(out), "--json"]) == 0
    said = json.loads(capsys.readouterr().out)
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    K, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat().ravel()
    H = fs.getNode("C_H_G").mat()
    stated = fs.getNode("distortion_fit_max_px").real()
    assert fs.getNode("C_H_G_from_frame").string() == "gripper_tcp" and fs.getNode("C_H_G_to_frame").string() == "camera_optical_frame"
    assert "p_camera = C_H_G p_gripper_tcp" in fs.getNode("C_H_G_direction").string()
    fs.release()
    cal = load_calibration(calfile / name)
    cam = cal.camera
    assert np.allclose(H, cal.C_H_G) and stated == pytest.approx(said["fit_max_px"])
    assert stated < 0.05
    # points off the fitting grid: OpenCV's model maps each ray where the kappa model puts its pixel
    rng = np.random.default_rng(3)
    uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (500, 2))
    rays = np.column_stack([cam.undistort_pixels(uv) / cam.f, np.ones(500)])
    xd, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), np.eye(3), dist)
    back = np.column_stack([xd.reshape(-1, 2), np.ones(500)]) @ K.T  # the whole K, its skew term too
    err = np.linalg.norm(back[:, :2] - uv, axis=1)
    assert err.max() <= stated * 1.5 + 1e-4
    # OpenCV's own undistortion gives the model's rays, to the stated shear it drops
    und = cv2.undistortPoints(uv.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    dropped = said["skew_dropped_max_px"]
    assert (dropped < 1e-6) == (cam.skew == 0)
    assert np.abs(und - rays[:, :2]).max() * cam.f < 2 * dropped + 0.05


def test_ros_files_load_as_yaml_and_name_both_frames(calfile, capsys):
    out = calfile / "cam.camera_info.yaml"
    assert main(["export", str(calfile / "cal.yaml"), "--format", "ros", "--out", str(out)]) == 0
    info = yaml.safe_load(out.read_text())
    cal = load_calibration(calfile / "cal.yaml")
    K = np.reshape(info["camera_matrix"]["data"], (3, 3))
    assert info["distortion_model"] == "plumb_bob" and len(info["distortion_coefficients"]["data"]) == 5  # the reference lens
    assert (info["image_width"], info["image_height"]) == (768, 576) and K[0, 0] == pytest.approx(cal.camera.f)
    tf = yaml.safe_load((calfile / "cam.transform.yaml").read_text())
    assert tf["header"]["frame_id"] == "camera_optical_frame" and tf["child_frame_id"] == "gripper_tcp"
    t = tf["transform"]["translation"]
    assert np.allclose([t["x"], t["y"], t["z"]], cal.C_H_G[:3, 3] / 1000.0)
    q = tf["transform"]["rotation"]
    x, y, z, w = q["x"], q["y"], q["z"], q["w"]
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    assert np.allclose(R, cal.C_H_G[:3, :3], atol=1e-9)
    assert "p_camera = C_H_G p_gripper_tcp" in (calfile / "cam.transform.yaml").read_text()


def test_json_export(calfile):
    assert main(["export", str(calfile / "cal.yaml"), "--format", "json"]) == 0
    doc = json.loads((calfile / "cal.export.json").read_text())
    assert doc["C_H_G"]["from_frame"] == "gripper_tcp" and doc["C_H_G"]["to_frame"] == "camera_optical_frame"
    assert doc["camera"]["opencv"]["fit_max_px"] < 0.05


def test_export_refuses_a_missing_folder(calfile, capsys):
    assert main(["export", str(calfile / "cal.yaml"), "--format", "json", "--out", str(calfile / "no" / "x.json")]) == 3
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.parametrize("fmt", ["opencv", "ros", "json"])
def test_an_export_on_a_full_disk_says_so_and_leaves_no_file(calfile, tmp_path, fmt, monkeypatch, capsys):
    import errno
    import shutil

    from selfview.files import io_safe

    shutil.copy(calfile / "cal.yaml", tmp_path / "cal.yaml")
    real = io_safe._write_all

    def full(fd, data):
        real(fd, data[:10])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io_safe, "_write_all", full)
    capsys.readouterr()
    assert main(["export", str(tmp_path / "cal.yaml"), "--format", fmt]) == 3
    out, err = capsys.readouterr()
    assert "no space left" in err and str(tmp_path) in err and "written" not in out, err
    assert [p.name for p in tmp_path.iterdir()] == ["cal.yaml"]  # no 0-byte export, no temporary file
