"""``selfview verify`` on the simulated cell: parks, spread, sigma, verdict and the error against the truth."""

import json

import numpy as np
import pytest

from selfview.files.cell import default_cell_path, load_cell
from selfview.procedures.cli import main
from selfview.procedures.verification import PLACES, centre_in_hull, spread


def test_every_park_keeps_the_plate_centre_between_the_fingertips():
    cell = load_cell(default_cell_path())
    pG = cell.gripper.points_G(cell.gripper.calibrate_in)
    assert all(centre_in_hull(pG, (dx, dy), t) for dx, dy, t in PLACES)
    assert not centre_in_hull(pG, (0.0, 8.0), 0.0) and not centre_in_hull(pG, (40.0, 0.0), 0.0)


def test_spread_of_known_transforms():
    from selfview.maths.geometry import make_H, rot_z

    Hs = [make_H(rot_z(np.radians(a))[:3, :3], (x, 0.0, 100.0)) for a, x in ((-0.1, -1.0), (0.0, 0.0), (0.1, 1.0))]
    sp = spread(Hs)
    assert sp["spread_mm"] == pytest.approx([1.0, 0.0, 0.0]) and sp["range_mm"] == pytest.approx([2.0, 0, 0])
    assert sp["spread_deg"] == pytest.approx(np.sqrt(2 / 3) * 0.1, rel=1e-6)


def test_verify_on_the_realistic_cell_says_no_go_below_its_spread_and_measures_the_truth(capsys):
    code = main(["verify", "--parks", "3", "--target-mm", "0.001", "--profile", "realistic", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 5 and out["verdict"] == "no-go" and "over the target 0.001 mm" in out["reason"]
    assert len(out["parks"]) == 3 and all(p["corners_found"] == 6 for p in out["parks"])
    tcp = np.array([p["tcp_mm"] for p in out["parks"]])
    assert out["spread_mm"] == pytest.approx(tcp.std(axis=0, ddof=1).tolist())
    assert all(0 < s < 0.5 for s in out["spread_mm"]) and 0 < out["spread_deg"] < 0.2
    assert len(out["sigma_mm"]) == 3 and all(s > 0 for s in out["sigma_mm"])
    # the plate's print scale moves every park alike: the truth error along the axis exceeds the spread
    err = out["truth_error_mm"]
    assert len(err) == 3 and abs(err[2]) > out["spread_mm"][2] and abs(err[2]) < 1.0
    assert "print scale" in out["cannot_see"] and "camera file" in out["cannot_see"]


def test_verify_on_the_ideal_cell_is_go_within_a_target(capsys):
    code = main(["verify", "--parks", "3", "--profile", "ideal", "--target-mm", "0.2"])
    text = capsys.readouterr().out
    assert code == 0, text
    assert "GO: the TCP's spread over 3 parks" in text and "against the simulator's truth" in text
    with pytest.raises(SystemExit) as stop:  # fewer parks than a spread needs: a usage error
        main(["verify", "--parks", "2"])
    assert stop.value.code == 2


def test_too_few_parks_or_no_places_are_refused_with_the_reason():
    from types import SimpleNamespace

    from selfview.errors import ConfigError
    from selfview.procedures.verification import park_and_calibrate, verify_summary

    with pytest.raises(ValueError, match="at least 2"):
        spread([np.eye(4)])
    with pytest.raises(ValueError, match="at least 2"):
        spread([np.eye(4), np.full((4, 4), np.nan)])
    with pytest.raises(ConfigError, match="at least 2 places"):
        verify_summary([], [], 0.25)
    with pytest.raises(ConfigError, match="no places"):  # nothing is planned, nothing moves
        park_and_calibrate(SimpleNamespace(), None, [], "open")
