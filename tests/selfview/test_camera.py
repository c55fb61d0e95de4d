import numpy as np
import pytest

from selfview.maths.camera import CameraModel, distort, max_undistorted_radius, undistort
from selfview.errors import CalibrationError, ConfigError
from selfview.maths.geometry import H_from_rotvec, transform_points


def grid(cam, n=60):
    u, v = np.meshgrid(np.linspace(-0.5, cam.width - 0.5, n), np.linspace(-0.5, cam.height - 0.5, n))
    return np.column_stack([u.ravel(), v.ravel()])


@pytest.mark.parametrize("kappa", [1.9e-7, -1.9e-7, 0.0, 2e-6, -6e-7, 1e-13])
@pytest.mark.parametrize("aspect", [1.0, 0.95])
def test_round_trip_over_the_whole_image(kappa, aspect):
    cam = CameraModel(f=962.0, kappa=kappa, aspect=aspect)
    uv = grid(cam)
    back = cam.distort_to_pixels(cam.undistort_pixels(uv))
    assert np.abs(back - uv).max() < 1e-9


def test_distortion_matches_eq4_definition():
    XYh = np.array([[300.0, -200.0], [10.0, 5.0]])
    k = 1.9e-7
    r2 = (XYh**2).sum(1, keepdims=True)
    assert np.allclose(undistort(XYh, k), XYh * (1 + k * r2))
    assert np.allclose(distort(undistort(XYh, k), k), XYh, atol=1e-12)


def test_negative_kappa_beyond_the_fold_raises():
    k = -1e-6
    Rmax = max_undistorted_radius(k)
    with pytest.raises(CalibrationError, match="field of view"):
        distort(np.array([[Rmax * 1.01, 0.0]]), k)


def test_pixel_centre_convention():
    cam = CameraModel(f=962.0)
    assert np.allclose(cam.pixel_to_sensor([383.5, 287.5]), [0, 0])
    assert cam.in_image([[0, 0], [767, 575], [-0.6, 10], [10, 575.6]]).tolist() == [True, True, False, False]


def test_backprojection_agrees_with_projection(rng):
    cam = CameraModel(f=962.0, kappa=1.9e-7)
    for _ in range(20):
        C_H_P = H_from_rotvec(rng.normal(scale=0.4, size=3), [rng.uniform(-20, 20), rng.uniform(-20, 20), 150])
        z = rng.uniform(-5, 5, 30)
        p_P = np.column_stack([rng.uniform(-40, 40, (30, 2)), z])
        p_C = transform_points(C_H_P, p_P)
        uv = cam.project(p_C)
        q, zc = cam.backproject_to_plane(uv, C_H_P, z)
        assert np.abs(q - p_P).max() < 1e-9
        assert np.abs(zc - p_C[:, 2]).max() < 1e-9
        rays = cam.rays(uv)
        assert np.allclose(rays * p_C[:, 2:3] / rays[:, 2:3], p_C)


def test_backprojection_refuses_edge_on_plane_and_points_behind():
    cam = CameraModel(f=962.0)
    edge_on = H_from_rotvec([np.pi / 2, 0, 0], [0, 0, 100])
    with pytest.raises(CalibrationError, match="edge-on"):
        cam.backproject_to_plane([[383.5, 287.5]], edge_on)
    with pytest.raises(CalibrationError, match="behind"):
        cam.project([[0, 0, -5.0]])


def test_invalid_parameters_are_rejected():
    with pytest.raises(ConfigError, match="f"):
        CameraModel(f=-1)
    with pytest.raises(ConfigError, match="size"):
        CameraModel(f=900, width=0, height=0)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        CameraModel(f=900).undistort_pixels(np.zeros((3, 3)))
