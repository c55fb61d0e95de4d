"""The worn PUMA 260: true geometry off the nominal one, encoder noise, and its VAL-II simulator."""

from __future__ import annotations

import numpy as np
import pytest

from selfview.drivers.puma_val_serial import PumaVAL
from selfview.mocks.kinematic_errors import (LINKS, PROFILES, RATED_RP_MM, WORN_NOISY_PUMA, WORN_PUMA, KinematicErrors,
                                             PerturbedPuma260, PerturbedValController, arm_profile, iso9283)
from selfview.mocks.puma260 import Puma260Geometry, make_tool
from selfview.mocks.val_controller import TOOL_LENGTH_MM
from selfview.mocks.world import PLATE_BASE_POSE, SimWorld
from selfview.errors import ConfigError
from selfview.maths.geometry import inv_H, pose_difference, trans

TOOL = make_tool(TOOL_LENGTH_MM)
ABOVE_F = PLATE_BASE_POSE @ trans(0.0, 0.0, -60.0) @ inv_H(TOOL)  # flange pose with the TCP above the plate


def test_a_perfect_arm_is_its_nominal_model():
    r = PerturbedPuma260(KinematicErrors(), seed=4)
    assert r.true.geometry == r.nominal.geometry == Puma260Geometry()
    s = r.move(ABOVE_F)
    np.testing.assert_allclose(s.base_H_F_true, ABOVE_F, atol=1e-9)
    np.testing.assert_allclose(s.base_H_F_nominal, ABOVE_F, atol=1e-9)
    o = r.observe(ABOVE_F)
    np.testing.assert_allclose(o.base_H_F_nominal, ABOVE_F, atol=1e-9)


def test_the_error_pattern_is_seeded_and_scales_with_the_level():
    half, full = PerturbedPuma260(WORN_PUMA.scaled(0.5), seed=7), PerturbedPuma260(WORN_PUMA, seed=7)
    other = PerturbedPuma260(WORN_PUMA, seed=8)
    for nm in LINKS:
        assert half.link_errors_mm[nm] == pytest.approx(0.5 * full.link_errors_mm[nm])
        assert abs(full.link_errors_mm[nm]) <= WORN_PUMA.link_mm
        assert getattr(full.true.geometry, nm) == pytest.approx(getattr(Puma260Geometry(), nm) + full.link_errors_mm[nm])
    np.testing.assert_allclose(half.joint_offset_errors_deg, 0.5 * np.array(full.joint_offset_errors_deg))
    assert max(map(abs, full.joint_offset_errors_deg)) <= WORN_PUMA.joint_offset_deg
    assert full.link_errors_mm != other.link_errors_mm
    s = full.summary()
    assert s["seed"] == 7 and s["link_mm"] == 1.0 and len(s["joint_offset_errors_deg"]) == 6


def test_the_controller_believes_it_reached_the_target_the_arm_did_not():
    r = PerturbedPuma260(WORN_PUMA, seed=3)
    s = r.move(ABOVE_F)
    np.testing.assert_allclose(s.base_H_F_nominal, ABOVE_F, atol=1e-9)  # its own kinematics say: arrived
    np.testing.assert_allclose(r.nominal.fk(s.q_read), s.base_H_F_nominal, atol=1e-12)
    rot, mm = pose_difference(s.base_H_F_true, ABOVE_F)
    assert 0.3 < mm < 5.0 and 0.02 < rot < 0.6  # a worn arm: about a millimetre and a tenth of a degree


def test_observing_a_true_pose_reports_it_through_the_nominal_kinematics():
    r = PerturbedPuma260(WORN_PUMA, seed=3)
    o = r.observe(ABOVE_F)
    np.testing.assert_allclose(o.base_H_F_true, ABOVE_F)
    np.testing.assert_allclose(r.nominal.fk(o.q_read), o.base_H_F_nominal, atol=1e-12)
    np.testing.assert_allclose(r.true.fk(r.true.ik(ABOVE_F)), ABOVE_F, atol=1e-7)
    assert 0.3 < pose_difference(o.base_H_F_nominal, ABOVE_F)[1] < 5.0


def test_encoder_noise_has_its_standard_deviation():
    r = PerturbedPuma260(KinematicErrors(encoder_sd_deg=0.02), seed=1)
    q_true = r.true.ik(ABOVE_F)
    reads = np.array([r.observe(ABOVE_F, q_true).q_read for _ in range(400)])
    err = reads - q_true
    assert np.all(np.abs(err.mean(axis=0)) < 0.005)
    np.testing.assert_allclose(err.std(axis=0), 0.02, rtol=0.2)
    # without noise the reading is exact
    assert np.allclose(PerturbedPuma260(seed=1).observe(ABOVE_F, q_true).q_read, q_true)


def test_a_noise_seed_gives_the_same_robot_encoder_draws_of_its_own():
    base, same = PerturbedPuma260(WORN_PUMA, seed=1), PerturbedPuma260(WORN_PUMA, seed=1)
    a, b = PerturbedPuma260(WORN_PUMA, seed=1, noise_seed=0), PerturbedPuma260(WORN_PUMA, seed=1, noise_seed=1)
    for r in (a, b):  # the same worn robot
        assert r.link_errors_mm == base.link_errors_mm and r.joint_offset_errors_deg == base.joint_offset_errors_deg
    draws = {nm: np.array([r.encoder_error_deg() for _ in range(4)])
             for nm, r in (("base", base), ("same", same), ("a", a), ("b", b))}
    np.testing.assert_array_equal(draws["base"], draws["same"])  # without a noise seed: the robot's one stream
    for x, y in (("a", "b"), ("a", "base"), ("b", "base")):
        assert np.all(np.abs(draws[x] - draws[y]).max(axis=1) > 1e-4), (x, y)
    with pytest.raises(ConfigError, match="noise_seed"):
        PerturbedPuma260(WORN_PUMA, seed=1, noise_seed=-1)
    with pytest.raises(ConfigError, match="noise_seed"):
        PerturbedPuma260(WORN_PUMA, seed=1, noise_seed=True)


@pytest.mark.parametrize("kwargs, match", [
    ({"link_mm": -1.0}, "link_mm"), ({"joint_offset_deg": float("nan")}, "joint_offset_deg"),
    ({"encoder_sd_deg": "0.02"}, "encoder_sd_deg"),
])
def test_bad_error_bounds_are_refused(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        KinematicErrors(**kwargs)


def test_bad_arguments_are_refused():
    with pytest.raises(ConfigError, match="level"):
        WORN_PUMA.scaled(-0.5)
    with pytest.raises(ConfigError, match="expected a KinematicErrors"):
        PerturbedPuma260({"link_mm": 1.0})
    with pytest.raises(ConfigError, match="expected a PerturbedPuma260"):
        PerturbedValController(None, robot=PerturbedPuma260().nominal)
    with pytest.raises(ConfigError, match="geometry comes from the robot"):
        PerturbedValController(None, robot=PerturbedPuma260(), geometry=Puma260Geometry())


@pytest.mark.parametrize("errors", [KinematicErrors(), WORN_PUMA], ids=["perfect", "worn"])
def test_the_val_simulator_reports_nominal_and_moves_the_world_truly(cell, errors):
    world = SimWorld(cell, seed=2)
    robot = PerturbedPuma260(errors, seed=5)
    sim = PerturbedValController(world, robot=robot, time_scale=0.0, calibrated=True)
    path = sim.start_pty()
    try:
        with PumaVAL(path, timeout_s=5.0) as arm:
            arm.move("above")
            where = arm.where()
            true_tcp = world.base_H_G.copy()
            # WHERE is the nominal kinematics at the joints read (printed to 0.01 deg); the world stands where
            # the true arm put it
            nominal = robot.nominal.fk(where.joints) @ TOOL
            # rotation (the angle of R_where R_nominal^T) and translation apart: WHERE prints the six joints
            # and O, A, T to 0.01 deg (rounding <= 0.005 deg each: at most 0.045 deg summed) and X, Y, Z to
            # 0.01 mm; the joints' rounding moves the TCP by <= 0.005 deg x ~400 mm of reach = 0.035 mm per
            # joint, 0.21 mm summed over six
            rot_nom, mm_nom = pose_difference(where.base_H_T, nominal)
            assert rot_nom < 0.05 and mm_nom < 0.22, (rot_nom, mm_nom)
            rot, mm = pose_difference(where.base_H_T, true_tcp)
            if errors == KinematicErrors():
                assert mm < 0.02 and rot < 1e-3
            else:
                assert 0.3 < mm < 5.0
            arm.move("plate")  # 4 mm into the foam: the worn arm still parks the gripper
        assert world.parked and abs(world.W_H_G[0, 3]) < 5.0
    finally:
        sim.stop()


def test_iso_9283_rp_is_the_mean_plus_three_sd_of_the_distances_from_the_barycentre():
    # distances 1, 1, 3, 3 from the barycentre (0, 0, 0): mean 2, sd (n - 1) sqrt(4 / 3); the command 4 mm away
    landings = [(1.0, 0.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 3.0, 0.0), (0.0, -3.0, 0.0)]
    got = iso9283(landings, (0.0, 0.0, 4.0))
    assert got["rp_mm"] == pytest.approx(2.0 + 3.0 * np.sqrt(4.0 / 3.0))
    assert got["ap_mm"] == pytest.approx(4.0) and got["rms_mm"] == pytest.approx(np.sqrt(5.0)) and got["landings"] == 4
    for bad in ([(1.0, 2.0, 3.0)], [(1.0, 2.0), (3.0, 4.0)]):
        with pytest.raises(ConfigError, match="iso9283"):
            iso9283(bad, (0.0, 0.0, 0.0))


def test_the_worn_arm_has_the_worn_geometry_and_twice_the_rated_repeatability():
    worn, noisy, half = arm_profile("worn"), arm_profile("worn-noisy"), arm_profile("half-worn")
    assert worn.errors is WORN_PUMA and noisy.errors is WORN_NOISY_PUMA and worn.rp_mm == 2 * RATED_RP_MM
    assert (worn.errors.link_mm, worn.errors.joint_offset_deg) == (noisy.errors.link_mm, noisy.errors.joint_offset_deg)
    assert noisy.errors.encoder_sd_deg == 0.02 and noisy.rp_mm is None  # the sensitivity arm: its RP only measured
    assert half.errors == WORN_PUMA.scaled(0.5) and half.rp_mm == RATED_RP_MM
    assert arm_profile("none").errors == KinematicErrors()
    assert list(PROFILES) == ["none", "half-worn", "worn", "worn-noisy"]
    assert worn.to_dict()["stated_rp_mm"] == 0.1 and worn.to_dict()["encoder_sd_deg"] == WORN_PUMA.encoder_sd_deg


@pytest.mark.parametrize("name", ["tired", "", None, "WORN"])
def test_an_unknown_arm_profile_is_refused_naming_the_known_ones(name):
    with pytest.raises(ConfigError, match="none, half-worn, worn, worn-noisy"):
        arm_profile(name)
