import numpy as np
import pytest

from selfview.mocks.world import PLATE_BASE_POSE, SimWorld
from selfview.errors import ConfigError
from selfview.maths.geometry import inv_H, pose_difference, rot_z, transform_points


def test_true_mount_lies_within_the_configured_error(cell):
    sim = cell.simulation
    seen = []
    for seed in range(40):
        w = SimWorld(cell, seed=seed)
        ang, dist = pose_difference(w.C_H_G, cell.mount_guess_C_H_G)
        assert ang <= sim.mount_error_angle_deg + 1e-9 and dist <= sim.mount_error_shift_mm + 1e-9
        seen.append(ang)
        assert w.camera.f == sim.true_f and w.camera.kappa == sim.true_kappa
    assert max(seen) > 0.5 * sim.mount_error_angle_deg  # the errors really are drawn


def test_same_seed_same_world(cell):
    a, b = SimWorld(cell, seed=7), SimWorld(cell, seed=7)
    assert np.array_equal(a.C_H_G, b.C_H_G)
    assert np.array_equal(a.park(), b.park())
    assert np.array_equal(a.disturb("cable").C_H_Cnew, b.disturb("cable").C_H_Cnew)
    assert not np.array_equal(SimWorld(cell, seed=8).C_H_G, a.mount_C_H_G)


def test_parking_satisfies_the_plane_coincidence_constraint(cell):
    w = SimWorld(cell, seed=1)
    W_H_G = w.park(turn_deg=90)
    assert w.parked
    # eq. 5: rotation about z only, translation orthogonal to z
    R, t = W_H_G[:3, :3], W_H_G[:3, 3]
    assert np.allclose(R @ [0, 0, 1], [0, 0, 1]) and abs(t[2]) < 1e-12
    assert np.allclose(w.C_H_W @ W_H_G, w.C_H_G)
    # the fingertip points lie on the plate plane
    p_W = transform_points(inv_H(w.C_H_W) @ w.C_H_G, w.points_G())
    assert np.allclose(p_W[:, 2], 0)


@pytest.mark.parametrize("series", ["cable", "tilt"])
def test_disturbances_move_the_tcp_as_configured(cell, series):
    spec = cell.simulation.disturbances[series]
    dominant = {"cable": 0, "tilt": 1}[series]  # the paper: cable moves the TCP along C x, tilt along C y
    shifts = []
    for seed in range(30):
        w = SimWorld(cell, seed=seed)
        before = w.C_H_G[:3, 3]
        d = w.disturb(series)
        moved = w.C_H_G[:3, 3] - before
        assert np.allclose(moved, d.tcp_shift_C)
        assert np.argmax(np.abs(moved)) == dominant
        shifts.append(np.linalg.norm(moved))
        # the camera rotated about an axis through the pivot: the pivot stays put
        assert np.allclose(transform_points(d.C_H_Cnew, spec.pivot_C), spec.pivot_C)
    assert np.mean(shifts) == pytest.approx(spec.tcp_shift_mm, abs=3 * spec.tcp_shift_sd_mm / np.sqrt(30) + 0.05)
    w.reset_disturbance()
    assert np.array_equal(w.C_H_G, w.mount_C_H_G)


def test_disturbances_accumulate_and_unknown_series_is_named(cell):
    w = SimWorld(cell, seed=2)
    w.disturb_by_angle([0, 1, 0], 0.5)
    w.disturb_by_angle([0, 1, 0], 0.5)
    ang, _ = pose_difference(w.C_H_G, w.mount_C_H_G)
    assert ang == pytest.approx(1.0)
    with pytest.raises(ConfigError, match="wobble.*cable, tilt"):
        w.disturb("wobble")


def test_pressing_the_gripper_onto_the_plate_parks_it(cell):
    w = SimWorld(cell, seed=3)
    above = PLATE_BASE_POSE @ rot_z(0.1)
    above[:3, 3] += [2.0, -1.0, 30.0]  # 30 mm above the plate (base z up)
    assert w.set_tcp(above) == "free" and not w.parked
    pressed = above.copy()
    pressed[2, 3] = PLATE_BASE_POSE[2, 3] - 3.0  # 3 mm into the foam
    assert w.set_tcp(pressed) == "parked" and w.parked
    assert np.allclose(w.W_H_G[:2, 3], [2.0, 1.0])  # W's y points the other way from base y
    assert np.allclose(w.base_H_W @ w.W_H_G, w.base_H_G)
    crushed = above.copy()
    crushed[2, 3] = PLATE_BASE_POSE[2, 3] - 40.0
    assert w.set_tcp(crushed) == "collision" and not w.parked


def test_world_requires_a_simulation_section(cell):
    import dataclasses

    with pytest.raises(ConfigError, match="simulation"):
        SimWorld(dataclasses.replace(cell, simulation=None))
