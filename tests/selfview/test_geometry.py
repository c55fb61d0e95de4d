import numpy as np
import pytest

from selfview.errors import ConfigError
from selfview.maths.geometry import (
    EulerConvention,
    H_from_rotvec,
    H_from_xyzoat,
    R_from_rotvec,
    R_from_rpy,
    check_rigid,
    delta_star,
    inv_H,
    make_H,
    orthonormalize,
    pose_difference,
    rot_axis,
    rot_x,
    rot_y,
    rot_z,
    rotvec_from_R,
    rpy_from_R,
    trans,
    transform_points,
    xyzoat_from_H,
)


def random_H(rng):
    return H_from_rotvec(rng.normal(size=3), rng.uniform(-200, 200, 3))


def test_inverse_and_composition(rng):
    for _ in range(50):
        A, B = random_H(rng), random_H(rng)
        assert np.allclose(inv_H(A) @ A, np.eye(4), atol=1e-12)
        p = rng.normal(size=(7, 3)) * 50
        assert np.allclose(transform_points(A @ B, p), transform_points(A, transform_points(B, p)))


def test_elementary_rotations_follow_right_hand_rule():
    assert np.allclose(transform_points(rot_z(np.pi / 2), [1, 0, 0]), [0, 1, 0])
    assert np.allclose(transform_points(rot_x(np.pi / 2), [0, 1, 0]), [0, 0, 1])
    assert np.allclose(transform_points(rot_y(np.pi / 2), [0, 0, 1]), [1, 0, 0])
    assert np.allclose(trans(1, 2, 3)[:3, 3], [1, 2, 3])


def test_rot_axis_keeps_the_pivot_fixed(rng):
    pivot = np.array([0.0, -15.0, -20.0])
    H = rot_axis([0.2, 1.0, 0.1], 0.3, pivot)
    assert np.allclose(transform_points(H, pivot), pivot)
    assert not np.allclose(transform_points(H, [0, 0, 110]), [0, 0, 110])


def test_rotvec_round_trip_including_near_pi(rng):
    vs = [rng.normal(size=3) for _ in range(100)]
    vs += [np.array([0, 0, np.pi - 1e-9]), np.array([np.pi, 0, 0]) * (1 - 1e-7), np.zeros(3), np.array([1e-9, 0, 0])]
    for v in vs:
        th = np.linalg.norm(v)
        if th > np.pi:
            v = v / th * (th % np.pi)
        R = R_from_rotvec(v)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.allclose(R_from_rotvec(rotvec_from_R(R)), R, atol=1e-9)


def test_rpy_round_trip(rng):
    for _ in range(100):
        a = rng.uniform([-3, -1.5, -3], [3, 1.5, 3])
        assert np.allclose(rpy_from_R(R_from_rpy(*a)), a, atol=1e-9)


def test_delta_star_is_first_order_of_the_exact_motion():
    d = np.array([0.5, -0.2, 0.1])
    for eps in (1e-2, 1e-3):
        delta = np.array([1.0, -2.0, 0.5]) * eps
        exact = trans(*d) @ rot_x(delta[0]) @ rot_y(delta[1]) @ rot_z(delta[2])
        err = np.abs(delta_star(delta, d) - exact).max()
        assert err < 5 * eps**2  # second-order small
    D = delta_star([0.01, 0.02, 0.03], [1, 2, 3])
    assert D[0, 1] == -0.03 and D[2, 1] == 0.01 and D[0, 2] == 0.02 and D[2, 3] == 3


def test_orthonormalize_gives_nearest_rotation(rng):
    R = R_from_rotvec(rng.normal(size=3))
    noisy = R + rng.normal(scale=1e-3, size=(3, 3))
    Q = orthonormalize(noisy)
    assert np.allclose(Q @ Q.T, np.eye(3), atol=1e-12) and np.linalg.det(Q) > 0
    assert np.linalg.norm(Q - R) < np.linalg.norm(noisy - R)
    H = make_H(noisy, [1, 2, 3])
    assert np.allclose(orthonormalize(H)[:3, 3], [1, 2, 3])


@pytest.mark.parametrize("seq", ["zyz", "zxz", "zyx", "xyz"])
def test_euler_conventions_round_trip(seq, rng):
    conv = EulerConvention(sequence=seq)
    for _ in range(200):
        a = rng.uniform(-179, 179, 3)
        a[1] = rng.uniform(1, 179) if seq[0] == seq[2] else rng.uniform(-89, 89)
        H = H_from_xyzoat([10, 20, 30, *a], conv)
        back = xyzoat_from_H(H, conv)
        assert np.allclose(H_from_xyzoat(back, conv), H, atol=1e-9)
    # the gimbal-locked case still maps back to the same rotation
    H = H_from_xyzoat([0, 0, 0, 30, 0, 40], EulerConvention("zyz"))
    assert np.allclose(H_from_xyzoat(xyzoat_from_H(H), EulerConvention("zyz")), H, atol=1e-9)


@pytest.mark.parametrize("seq", ["zyz", "zxz", "xyx", "zyx", "xyz", "zxy", "yxz"])
def test_euler_angles_at_and_near_the_middle_angles_singularity_map_back_to_the_rotation(seq, rng):
    # VAL's O/A/T (a z-x-y set) with the tool straight down is A = 90: the angles of a rotation whose
    # entries rounding left at 1 - 1e-16 once came back up to 18 degrees away from it
    conv = EulerConvention(sequence=seq)
    lock = (0.0, 180.0) if seq[0] == seq[2] else (90.0, -90.0)
    worst = 0.0
    for mid in lock:
        for off in (0.0, 1e-9, -1e-9, 1e-7, -1e-5, 1e-3):
            for _ in range(40):
                a = (rng.uniform(-180, 180), mid + off, rng.choice([rng.uniform(-180, 180), 180.0, -180.0]))
                # through a product, so the entries carry rounding as a robot's forward kinematics do
                R = conv.to_R(a) @ R_from_rotvec([0.0, 0.0, 0.3]) @ R_from_rotvec([0.0, 0.0, -0.3])
                back = conv.from_R(R)
                assert all(-180.0 <= v <= 180.0 for v in back)
                worst = max(worst, np.linalg.norm(rotvec_from_R(conv.to_R(back).T @ R)))
    assert worst < 1e-9  # rad: the floating-point floor, far below WHERE's 0.005 deg (9e-5 rad) print step


def test_euler_convention_is_adjustable_by_data():
    flipped = EulerConvention(sequence="zyz", signs=(1, -1, 1), offsets_deg=(90, 0, 0))
    H1 = H_from_xyzoat([0, 0, 0, 0, 30, 0], flipped)
    H2 = H_from_xyzoat([0, 0, 0, 90, -30, 0], EulerConvention())
    assert np.allclose(H1, H2)
    with pytest.raises(ConfigError, match="sequence"):
        EulerConvention(sequence="zzy")


def test_check_rigid_names_the_fault():
    with pytest.raises(ConfigError, match="mount.*4x4"):
        check_rigid([[1, 0], [0, 1]], "mount")
    with pytest.raises(ConfigError, match="not a rigid"):
        check_rigid(np.diag([2.0, 1, 1, 1]), "mount")
    with pytest.raises(ConfigError, match="bottom row"):
        check_rigid([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]], "mount")
    with pytest.raises(ConfigError, match="det"):
        check_rigid(np.diag([1.0, 1, -1, 1]), "mount")
    H = check_rigid(np.round(H_from_rotvec([0.3, 0.2, 0.1], [1, 2, 3]), 4), "mount")
    assert np.allclose(H[:3, :3] @ H[:3, :3].T, np.eye(3), atol=1e-12)


def test_pose_difference():
    A = H_from_rotvec([0, 0, np.radians(2.0)], [0, 0, 3.0])
    ang, dist = pose_difference(A, np.eye(4))
    assert ang == pytest.approx(2.0) and dist == pytest.approx(3.0)


def test_so3_left_jacobian_and_cross_rows():
    from selfview.maths.geometry import cross_rows, so3_left_jacobian

    rng = np.random.default_rng(7)
    for omega in (rng.normal(0, 1, 3), np.array([1e-10, 0.0, 0.0])):
        d = rng.normal(0, 1e-6, 3)
        lhs = R_from_rotvec(omega + d)
        rhs = R_from_rotvec(so3_left_jacobian(omega) @ d) @ R_from_rotvec(omega)
        assert np.abs(lhs - rhs).max() < 1e-11  # first order in |d| ~ 1e-6: the rest is ~1e-12
        assert np.abs(lhs - R_from_rotvec(omega)).max() > 1e-7  # the step itself is seen
    a, b = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    assert np.allclose(cross_rows(a, b), np.cross(a, b), rtol=0, atol=1e-14)


def test_batched_rotations_and_left_jacobians_are_each_rows_own():
    """Rows near 0 (the series branch) mixed with large and near-pi ones: each row as the one-vector function."""
    from selfview.maths.geometry import R_from_rotvecs, so3_left_jacobian, so3_left_jacobians

    V = np.vstack([np.random.default_rng(8).normal(0, 1, (4, 3)), [[0, 0, 0], [1e-13, 0, 0], [3e-9, 0, 0],
                                                                   [0, np.pi - 1e-9, 0]]])
    Rs, Js = R_from_rotvecs(V), so3_left_jacobians(V)
    assert Rs.shape == Js.shape == (len(V), 3, 3)
    for v, R, J in zip(V, Rs, Js):
        assert np.abs(R - R_from_rotvec(v)).max() < 1e-15 and np.abs(R @ R.T - np.eye(3)).max() < 1e-14
        assert np.abs(J - so3_left_jacobian(v)).max() < 1e-15
    K = np.array([[0, 0, 0], [0, 0, -3e-9], [0, 3e-9, 0]])  # [v]x of (3e-9, 0, 0)
    assert np.abs(Js[6] - (np.eye(3) + 0.5 * K)).max() < 1e-20  # the series below 1e-8 rad
