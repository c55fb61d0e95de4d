"""``calibrate`` and ``track`` keep the picture they used and an annotated copy, named in the calibration file."""

import json

import cv2
import numpy as np

from selfview.calfile import load_calibration
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
