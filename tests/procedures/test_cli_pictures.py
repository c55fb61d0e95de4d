"""``calibrate`` and ``track`` keep the picture they used and an annotated copy, named in the calibration file."""

import json
import os

import cv2
import numpy as np

from selfview.files.calfile import load_calibration
from selfview.mocks.render import render
from selfview.mocks.world import SimWorld
from selfview.procedures.cli import main


def test_calibrate_and_track_keep_their_pictures(cell, tmp_path, capsys):
    w = SimWorld(cell, seed=5)
    w.park()
    parked = render(w, seed=1).image
    cv2.imwrite(str(tmp_path / "parked.png"), parked)
    w.disturb("cable")
    cv2.imwrite(str(tmp_path / "moved.png"), render(w, seed=2).image)
    cal = tmp_path / "cal.yaml"
    assert main(["calibrate", "--image", str(tmp_path / "parked.png"), "--out", str(cal), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    names = load_calibration(cal).pictures
    assert names == out["pictures"] and set(names) == {"picture", "annotated"}
    kept = cv2.imread(str(tmp_path / names["picture"]), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(kept, parked)  # the very picture, losslessly
    ann = cv2.imread(str(tmp_path / names["annotated"]))
    assert ann.shape == (1152, 1536, 3) and np.abs(ann[..., 1].astype(int) - ann[..., 2]).max() > 100  # drawn in colour
    assert main(["track", "--calibration", str(cal), "--image", str(tmp_path / "moved.png"), "--method", "auto",
                 "--apply", "--json"]) == 0
    tr = json.loads(capsys.readouterr().out)
    assert tr["pictures"]["picture"].startswith("cal.track-picture-") and (tmp_path / tr["pictures"]["annotated"]).is_file()
    assert load_calibration(cal).pictures == {f"track {k}": v for k, v in tr["pictures"].items()}
    assert (tmp_path / names["picture"]).is_file()  # the calibration's picture stays beside its history copy


def test_no_pictures_keeps_none(cell, tmp_path, capsys):
    w = SimWorld(cell, seed=6)
    w.park()
    cv2.imwrite(str(tmp_path / "parked.png"), render(w, seed=1).image)
    assert main(["calibrate", "--image", str(tmp_path / "parked.png"), "--out", str(tmp_path / "c.yaml"),
                 "--no-pictures"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.yaml", "parked.png"]  # nor any lock file
    assert load_calibration(tmp_path / "c.yaml").pictures == {}


def _selfview(*argv: bytes, cwd):
    import os
    import subprocess
    import sys

    from tests.conftest import REPO

    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable.encode(), b"-m", b"selfview.procedures.cli", *argv], cwd=cwd, env=env,
                          capture_output=True, timeout=300)


def test_a_name_with_a_byte_that_is_not_utf8_is_written_as_given_and_no_native_call_crashes(cell, tmp_path):
    w = SimWorld(cell, seed=6)
    w.park()
    parked = render(w, seed=1).image
    cv2.imwrite(str(tmp_path / "parked.png"), parked)
    r = _selfview(b"calibrate", b"--image", b"parked.png", b"--out", b"cal\xff.yaml", cwd=tmp_path)
    assert r.returncode == 0, r.stderr.decode(errors="replace")
    names = sorted(os.fsencode(p.name) for p in tmp_path.iterdir())
    assert b"cal\xff.yaml" in names and sum(n.startswith(b"cal\xff.") and n.endswith(b".png") for n in names) == 2
    kept = load_calibration(tmp_path / os.fsdecode(b"cal\xff.yaml")).pictures
    assert np.array_equal(cv2.imdecode(np.fromfile(tmp_path / kept["picture"], np.uint8), cv2.IMREAD_UNCHANGED), parked)
    for argv, name in (([b"render", b"--out"], b"r\xff.png"), ([b"grab", b"--camera", b"sim://", b"--out"], b"g\xff.png")):
        r = _selfview(*argv, name, cwd=tmp_path)
        assert r.returncode == 0 and (tmp_path / os.fsdecode(name)).stat().st_size > 1000, r.stderr
    for argv in ([b"render", b"--out", b"r.pn\xff"], [b"calibrate", b"--image", b"parked.png", b"--out", b""],
                 [b"park", b"--out", b""], [b"park", b"--out", b"no-folder/p.png"],
                 [b"grab", b"--camera", b"sim://", b"--out", b""], [b"grab", b"--camera", b"sim://", b"--out", b"g.pn\xff"]):
        r = _selfview(*argv, cwd=tmp_path)
        err = r.stderr.decode(errors="replace")
        assert r.returncode == 3 and "--out" in err and "Traceback" not in err, (argv, err)
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp") or p.name.startswith(".")]


def test_a_picture_that_cannot_be_written_is_named_with_its_cause(tmp_path, monkeypatch):
    import errno

    import pytest

    from selfview.files import io_safe
    from selfview.errors import ConfigError

    img = np.zeros((8, 8), np.uint8)
    with pytest.raises(ConfigError, match=r"p\.gif: cannot write the picture: the name must end in one of \.png"):
        io_safe.write_picture(tmp_path / "p.gif", img)
    real = io_safe._write_all

    def full(fd, data):
        real(fd, data[:3])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io_safe, "_write_all", full)
    with pytest.raises(ConfigError, match=f"{tmp_path / 'p.png'}: cannot write the picture: no space left"):
        io_safe.write_picture(tmp_path / "p.png", img)
    assert list(tmp_path.iterdir()) == []  # no 0-byte "written" file, no temporary file
