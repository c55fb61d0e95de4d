import numpy as np
import pytest
import yaml

from selfview.calfile import Calibration, history_dir, load_calibration, save_calibration
from selfview.camera import CameraModel
from selfview.errors import CalibrationFileError
from selfview.geometry import H_from_rotvec


def make_cal(rng, f=962.0):
    return Calibration(
        camera=CameraModel(f=f, kappa=1.9e-7),
        C_H_W=H_from_rotvec(rng.normal(size=3) * 0.3, [1.0, 2.0, 110.0]),
        C_H_G=H_from_rotvec(rng.normal(size=3) * 0.3, [0.1, -0.2, 111.0]),
        points_G={"open": np.arange(18.0).reshape(6, 3) * 1e-7 + 1 / 3, "closed": np.ones((6, 3))},
        state="open",
        residuals={"rms_px": np.float64(0.0123456789), "discs_used": np.int64(57), "per_disc": np.zeros((2, 2))},
        image_sha256="ab" * 32,
        cell_sha256="cd" * 32,
    )


def test_round_trip_is_exact(tmp_path, rng):
    cal = make_cal(rng)
    p = tmp_path / "cal.yaml"
    assert save_calibration(cal, p) is None
    back = load_calibration(p)
    assert back.camera == cal.camera
    assert np.array_equal(back.C_H_G, cal.C_H_G) or np.allclose(back.C_H_G, cal.C_H_G, atol=1e-15)
    assert np.array_equal(back.points_G["open"], cal.points_G["open"])
    assert back.residuals["discs_used"] == 57 and back.state == "open"
    assert yaml.safe_load(p.read_text())["format"] == "selfview-calibration"


def test_previous_calibration_is_kept(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng, f=950.0), p)
    first = p.read_bytes()
    kept = save_calibration(make_cal(rng, f=960.0), p)
    assert kept is not None and kept.parent == history_dir(p)
    assert kept.read_bytes() == first
    assert load_calibration(p).camera.f == 960.0
    assert load_calibration(kept).camera.f == 950.0
    assert not list(tmp_path.glob(".cal.yaml.*.tmp"))  # no temporary left behind


@pytest.mark.parametrize(
    "content, message",
    [
        ("camera: [1, 2\n", "not valid YAML"),
        ("just: a mapping\n", "not a selfview calibration"),
        ("", "not a selfview calibration"),
    ],
)
def test_corrupt_or_foreign_files_are_refused_and_kept(tmp_path, rng, content, message):
    p = tmp_path / "cal.yaml"
    p.write_text(content)
    with pytest.raises(CalibrationFileError, match=message):
        load_calibration(p)
    with pytest.raises(CalibrationFileError, match=message):
        save_calibration(make_cal(rng), p)
    assert p.read_text() == content  # nothing overwritten


def test_altered_file_fails_its_checksum(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng), p)
    doc = yaml.safe_load(p.read_text())
    doc["camera"]["f"] = 1000.0
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationFileError, match="checksum"):
        load_calibration(p)


def test_truncated_file_is_refused(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng), p)
    p.write_bytes(p.read_bytes()[: len(p.read_bytes()) // 2])
    with pytest.raises(CalibrationFileError):
        load_calibration(p)


def test_unknown_version_and_missing_file(tmp_path, rng):
    p = tmp_path / "cal.yaml"
    save_calibration(make_cal(rng), p)
    doc = yaml.safe_load(p.read_text())
    doc["version"] = 99
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(CalibrationFileError, match="version 99"):
        load_calibration(p)
    with pytest.raises(CalibrationFileError, match="no such calibration file"):
        load_calibration(tmp_path / "none.yaml")
