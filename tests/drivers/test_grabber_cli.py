"""``selfview grab`` on recordings, on sim:// and on a missing grabber card."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from selfview.procedures.cli import EXIT_CALIBRATION, EXIT_CONFIG, EXIT_DEVICE, main


def test_grab_from_a_sequence_with_average(tmp_path, capsys):
    rng = np.random.default_rng(3)
    imgs = [rng.integers(40, 200, (90, 120), dtype=np.uint8) for _ in range(2)]
    for i, im in enumerate(imgs):
        cv2.imwrite(str(tmp_path / f"f_{i}.png"), im)
    out = tmp_path / "avg.png"
    assert main(["grab", "--camera", f"frames://{tmp_path}/f_%d.png", "--out", str(out), "--average", "2", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["width"], info["height"], info["average"]) == (120, 90, 2)
    got = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(got, np.rint((imgs[0].astype(float) + imgs[1]) / 2).astype(np.uint8))


def test_grab_from_the_simulated_cell(tmp_path, capsys):
    out = tmp_path / "sim.png"
    assert main(["grab", "--camera", "sim://?noise=0", "--out", str(out), "--seed", "4"]) == 0
    img = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert img.shape == (576, 768) and img.dtype == np.uint8
    from selfview.mocks.render import render
    from selfview.mocks.world import SimWorld
    from selfview.files.cell import default_cell_path, load_cell

    world = SimWorld(load_cell(default_cell_path()), seed=4)
    world.park()
    assert np.array_equal(img, render(world, noise=False).image)  # the parked gripper of world seed 4


def test_grab_failures_exit_codes(tmp_path, capsys):
    assert main(["grab", "--url", "v4l2:///dev/video-selfview-missing", "--out", str(tmp_path / "x.png")]) == EXIT_DEVICE
    assert "no such video device" in capsys.readouterr().err
    assert main(["grab", "--url", "sim://", "--out", str(tmp_path / "no" / "x.png")]) == EXIT_CONFIG
    cv2.imwrite(str(tmp_path / "k_0.png"), np.zeros((40, 40), np.uint8))
    assert main(["grab", "--url", f"frames://{tmp_path}/k_%d.png", "--out", str(tmp_path / "y.png")]) == EXIT_CALIBRATION
    assert "black frame" in capsys.readouterr().err
    assert not (tmp_path / "y.png").exists()


def test_grab_needs_a_camera_and_still_reads_url(tmp_path, capsys):
    assert main(["grab", "--out", str(tmp_path / "x.png")]) == EXIT_CONFIG
    assert "--camera URL is required" in capsys.readouterr().err
    assert main(["grab", "--url", "sim://?noise=0", "--out", str(tmp_path / "x.png")]) == 0
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        main(["grab", "--help"])
    assert info.value.code == 0
    help_text = capsys.readouterr().out
    assert "--camera URL" in help_text and "--url" not in help_text
