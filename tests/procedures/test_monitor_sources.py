"""The monitor over frames:// picture sequences that lie: frozen, one black frame, alternating poses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from selfview.files.calfile import save_calibration
from selfview.errors import AlarmError
from selfview.mocks.render import LIFTED_W_H_G, render
from selfview.mocks.world import SimWorld
from selfview.estimation.offline import calibrate_offline
from selfview.procedures.runs import CellSession

SEED = 2


@pytest.fixture(scope="module")
def setup(cell, tmp_path_factory):
    """A calibration of the simulated cell (its parked picture), and the world to render the frames from."""
    d = tmp_path_factory.mktemp("mon")
    w = SimWorld(cell, seed=SEED)
    w.park()
    cal = d / "cal.yaml"
    save_calibration(calibrate_offline(render(w, seed=SEED).image, cell).calibration, cal)
    w.set_tcp(w.base_H_plate0 @ LIFTED_W_H_G)
    return w, cal


def _frames(folder, images):
    for i, img in enumerate(images):
        assert cv2.imwrite(str(folder / f"f_{i:03d}.png"), img)
    return f"frames://{folder}/f_%03d.png"


def _monitor(cell, cal, url, n):
    seen = []
    with CellSession.simulated(cell, seed=SEED, camera_url=url) as s:
        try:
            s.monitor(cal, frames=n, on_decision=seen.append)
        except AlarmError as exc:
            return seen, str(exc)
    return seen, None


def _text(records):
    return " ".join(f"{r['action']} {r['reason']} {r.get('fingertips', '')}" for r in records)


def test_a_frozen_source_is_missed_frames_then_the_alarm(cell, setup, tmp_path):
    w, cal = setup
    img = render(w, seed=5).image
    seen, alarm = _monitor(cell, cal, _frames(tmp_path, [img] * 6), 6)
    acts = [r["action"] for r in seen]
    assert acts[0] == "update" and "update" not in acts[1:], acts  # the first frame is a real one
    assert acts[1:cell.monitor.max_missed_frames] == ["missed"] * (cell.monitor.max_missed_frames - 1)
    assert alarm is not None and "bit-identical" in alarm and acts[-1] == "alarm"
    assert "nan" not in _text(seen) and "None" not in _text(seen)


def test_one_black_frame_is_a_missed_frame_and_the_run_goes_on(cell, setup, tmp_path):
    w, cal = setup
    imgs = [render(w, seed=10 + k).image for k in range(4)]
    imgs[1] = np.zeros_like(imgs[1])
    seen, alarm = _monitor(cell, cal, _frames(tmp_path, imgs), 4)
    assert alarm is None and [r["action"] for r in seen] == ["update", "missed", "update", "update"]
    assert "black frame" in seen[1]["reason"] and "nan" not in _text(seen) and "None" not in _text(seen)


def test_a_pose_alternating_between_two_values_raises_the_alarm(cell, setup, tmp_path):
    w, cal = setup
    axis = cell.simulation.disturbances["cable"]
    imgs = []
    for k in range(8):
        w.reset_disturbance()
        if k % 2:
            w.disturb_by_angle(axis.axis_C, 2 * cell.monitor.update_limit.angle_deg, axis.pivot_C, series="switch")
        imgs.append(render(w, seed=20 + k).image)
    w.reset_disturbance()
    seen, alarm = _monitor(cell, cal, _frames(tmp_path, imgs), 8)
    assert alarm is not None and "camera mount loose or source switching" in alarm, [r["action"] for r in seen]
    assert "nan" not in _text(seen) and "None" not in _text(seen)


def test_track_auto_on_a_picture_without_fingers_says_not_found(cell, setup, tmp_path, capsys):
    from selfview.procedures.cli import main

    _, cal = setup
    pic = tmp_path / "table.png"
    rng = np.random.default_rng(0)
    cv2.imwrite(str(pic), cv2.GaussianBlur(rng.uniform(40, 220, (576, 768)), (0, 0), 3).astype(np.uint8))
    code = main(["track", "--calibration", str(cal), "--image", str(pic), "--method", "auto"])
    out, err = capsys.readouterr()
    assert code == 5 and "not found" in err, (code, out, err)
    assert "nan" not in out + err and "None" not in out + err
