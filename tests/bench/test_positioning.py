"""The positioning study's pieces: its conditions, one servo run on a worn arm's cell, the summary the checks read."""

from __future__ import annotations

import numpy as np
import pytest

from selfview.bench.kinematics_vs_selfview import F_H_G
from selfview.errors import LimitError
from selfview.bench.positioning import (CALIBRATIONS, DirectRig, ServoSettings, _summary, arm_repeatability, conditions,
                                        headline_profile, main, run_start, start_arm, station_spread)
from selfview.maths.geometry import inv_H, make_H, rot_x, rot_y, rot_z, trans
from selfview.mocks.kinematic_errors import PROFILES as ARMS
from selfview.mocks.world import SimWorld


def test_every_calibration_is_compared_and_the_move_and_the_control_are_on_the_worn_arm():
    conds = conditions(("none", "worn"))
    plain = {(c["calibration"], c["profile"]) for c in conds if not c["camera_moved"] and not c["taught_goal"]}
    assert plain == {(c, p) for c in CALIBRATIONS for p in ("none", "worn")}
    assert {c["calibration"] for c in conds if c["camera_moved"]} == {"selfview-offline", "selfview-online", "axxb"}
    assert all(c["profile"] == "worn" for c in conds if c["camera_moved"] or c["taught_goal"])
    # the most worn profile, whatever the order the profiles are named in; an unknown one is named
    assert all(c["profile"] == "worn" for c in conditions(("worn", "none")) if c["camera_moved"] or c["taught_goal"])
    with pytest.raises(ValueError, match="'worst'"):
        conditions(("none", "worst"))
    # the worn PUMA as a lab has it carries the move and the control, not the sloppy sensitivity arm after it
    assert headline_profile(("none", "worn-noisy", "worn")) == "worn" == headline_profile(("worn", "half-worn"))
    assert headline_profile(("worn-noisy", "none")) == "worn-noisy"
    moved = {c["profile"] for c in conditions(("none", "worn", "worn-noisy")) if c["camera_moved"] or c["taught_goal"]}
    assert moved == {"worn"}


def test_a_worn_arm_lands_off_its_command_and_a_perfect_one_does_not():
    perfect = arm_repeatability(1, "none")
    assert perfect["rp_mm"] < 1e-6 and perfect["ap_mm"] < 1e-6 and perfect["landings"] == 30
    worn = arm_repeatability(1, "worn")
    # absolute accuracy and repeatability apart: about 1 mm off the command, landing within about 0.1 mm of it
    assert 0.5 < worn["ap_mm"] < 3.0 and worn["rp_mm"] < 0.2 * worn["ap_mm"]
    assert worn["repeatability_mm"] < worn["rp_mm"] < worn["accuracy_mm"]


@pytest.mark.parametrize("profile", [p for p in ARMS if ARMS[p].rp_mm])
def test_each_arm_repeats_to_the_iso_9283_rp_its_encoder_noise_was_set_from(profile):
    # RP of 300 landings scatters by about 3 % (1 sd) about the arm's own figure: 10 % is a wrong noise, not chance
    rp = arm_repeatability(2, profile, moves=300)["rp_mm"]
    assert rp == pytest.approx(ARMS[profile].rp_mm, rel=0.1), (profile, rp)


def test_the_sloppy_arm_repeats_six_times_worse_with_the_same_geometry():
    worn, noisy = arm_repeatability(1, "worn", moves=300), arm_repeatability(1, "worn-noisy", moves=300)
    assert noisy["rp_mm"] == pytest.approx(worn["rp_mm"] * 0.02 / ARMS["worn"].errors.encoder_sd_deg, rel=0.15)
    assert noisy["ap_mm"] == pytest.approx(worn["ap_mm"], abs=0.1)  # the same absolute accuracy


def test_bad_profile_names_are_refused():
    for bad in (("none", "worst"), (), "worn"):
        with pytest.raises(ValueError, match="profile"):
            conditions(bad)
    with pytest.raises(ValueError, match="'tired'.*none, half-worn, worn, worn-noisy"):
        arm_repeatability(1, "tired")
    with pytest.raises(ValueError, match="'tired'"):
        start_arm(1, 0, "tired")
    assert main_exits(["--profiles", "none,tired"]) == 2


def main_exits(argv) -> int:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    return exc.value.code


def test_every_start_drives_the_same_worn_arm_but_lands_with_encoder_draws_of_its_own():
    # one noise stream for every start made each run's k-th motion land off by the same draw: the worn rows'
    # final errors were one vector for every start and every calibration
    arms = [start_arm(1, s, "worn") for s in range(3)]
    assert all(a.link_errors_mm == arms[0].link_errors_mm for a in arms)
    target = make_H(np.diag([1.0, -1.0, -1.0]), (350.0, 170.0, 60.0)) @ inv_H(F_H_G)
    landed = np.array([[a.move(target).base_H_F_true[:3, 3] for _ in range(3)] for a in arms])  # (start, k, xyz)
    for i in range(3):
        for j in range(i):
            assert np.all(np.linalg.norm(landed[i] - landed[j], axis=1) > 0.001), (i, j)
    assert np.all(np.linalg.norm(landed - target[:3, 3], axis=2) < 3.0)  # each still near its command


def test_one_start_with_the_true_calibration_converges_and_the_summary_has_the_keys_the_checks_read(cell):
    world = SimWorld(cell, seed=1, imperfections="ideal")
    runs = [run_start(1, 0, "none", (world.C_H_G, world.camera), True, False, False, ServoSettings(), "ideal")]
    r = runs[0]
    assert r["converged"] and r["held"], r["reason"]
    assert np.linalg.norm(r["true_error_mm"]) < 0.2 and r["true_error_deg"] < 0.2 and r["iterations"] <= 20
    s = _summary({"calibration": "truth", "profile": "none", "camera_moved": False, "taught_goal": False}, runs)
    for key in ("calibration", "profile", "camera_moved", "starts", "median_mm", "p95_mm", "max_mm", "median_deg",
                "converged", "held"):
        assert key in s
    assert s["starts"] == 1 and s["converged"] == 1 and s["held"] == 1 and s["median_mm"] == s["max_mm"]


def test_a_servo_step_out_of_the_arms_reach_is_a_limit_error_the_run_catches_and_nothing_moves(cell):
    # Unreachable (a ValueError) escaped run_start's ``except CellError``: one step out of reach in one run ended
    # the whole study, every run before it lost
    world = SimWorld(cell, seed=1, imperfections="ideal")
    rig = DirectRig(world, start_arm(1, 0, "none"), 1)
    rig.place(make_H(np.diag([1.0, -1.0, -1.0]), (350.0, 170.0, 60.0)))
    before, tcp = rig.where(), world.base_H_G.copy()
    with pytest.raises(LimitError, match="out of the arm's reach"):
        rig.tool_step(trans(0.0, 0.0, -900.0), 1000.0, 1.0)
    assert np.array_equal(rig.where(), before) and np.array_equal(world.base_H_G, tcp)
    rig.tool_step(trans(0.0, 0.0, -5.0), 10.0, 1.0)  # a step within reach still moves
    assert np.linalg.norm(rig.where()[:3, 3] - before[:3, 3]) == pytest.approx(5.0, abs=1e-6)


def test_the_stations_spread_says_how_far_and_about_which_axes_the_flange_turns():
    turns = [trans(350.0, 0.0, 300.0) @ rot_z(np.radians(20.0 * k)) for k in range(4)]  # one axis: 20, 40, 60 deg
    one = station_spread(turns, turns)
    assert one["stations"] == 4 and one["motions"] == 6
    assert (one["rotation_deg_min"], one["rotation_deg_median"], one["rotation_deg_max"]) == pytest.approx((20, 30, 60))
    assert one["axis_spread"] == pytest.approx([0.0, 0.0], abs=1e-9)
    three = [turns[0], turns[0] @ rot_x(0.5), turns[0] @ rot_y(0.5), turns[0] @ rot_z(0.5)]  # about x, y and z
    assert min(station_spread(three, three)["axis_spread"]) > 0.5


def test_a_failing_run_drops_the_runs_not_yet_started_instead_of_waiting_for_them(monkeypatch):
    """The study's pool, when a run raises (or Ctrl-C): the pending runs are cancelled and the error comes at
    once; a ``with`` block would wait for every submitted run first (tens of minutes in the full study)."""
    import selfview.bench.positioning as pos

    shut = []

    class Pool:
        def __init__(self, *a, **k):
            pass

        def map(self, *a, **k):
            raise RuntimeError("a worker failed")

        def shutdown(self, wait=True, cancel_futures=False):
            shut.append((wait, cancel_futures))

    monkeypatch.setattr(pos, "ProcessPoolExecutor", Pool)
    with pytest.raises(RuntimeError, match="a worker failed"):
        pos.main(["--profiles", "none", "--starts", "1"])
    assert shut == [(False, True)]
