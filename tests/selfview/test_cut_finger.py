"""A finger cut by the picture's border to a sliver, its inner corners still in view, is still measured.

The camera turned on its cable (about the camera's y axis, around the cable's pivot) by 5.5 to 6.3 deg
pushes finger A out over the left border until only a sliver of its inner face is left (its inner-front
corner 3 to 20 px from the border, its outer corner outside). Tracked from the pose of a degree before,
the silhouette holds and 4P-I gives the gripper within 0.05 mm (measured 0.021-0.026 mm). Before, the
faces' grey levels were read at the starting pose, where half of the sliver's face is paper, and the fit
was lost ("0 % of finger A's edge samples support the fit").
"""

import numpy as np
import pytest

from selfview.files.cell import POINT_NAMES
from selfview.measurement.fingers import model_measurement
from selfview.maths.geometry import pose_difference
from selfview.mocks.render import render
from selfview.mocks.world import SimWorld
from selfview.estimation.offline import calibrate_offline
from selfview.estimation.online import estimate


@pytest.fixture(scope="module")
def calibrated(cell):
    w = SimWorld(cell, seed=21)
    w.park()
    return w, calibrate_offline(render(w, seed=1).image, cell).calibration


@pytest.mark.parametrize("start, angle", [(4.5, 5.5), (5.5, 6.3)])
def test_a_finger_cut_by_the_border_is_tracked(cell, calibrated, start, angle):
    w, cal = calibrated
    pivot = cell.simulation.disturbances["cable"].pivot_C
    w.reset_disturbance()
    w.disturb_by_angle([0, 1, 0], start, pivot)
    H_start = w.C_H_G.copy()
    w.reset_disturbance()
    w.disturb_by_angle([0, 1, 0], angle, pivot)
    pic = render(w, seed=2)
    k_in, k_out = POINT_NAMES.index("A-inner-front"), POINT_NAMES.index("A-outer-front")
    # the picture shows what it must: finger A's outer corner gone, its inner corners near the border
    assert not pic.corner_visible[k_out] and pic.corner_visible[:4].all()
    assert 0 < pic.corner_uv[k_in, 0] < 25
    gap = cell.gripper.gap(cal.state)
    res, fit = model_measurement(pic.image, cal.camera, H_start, cell.gripper, gap)
    assert fit.ok, fit.reason
    assert res.found[:4].all()
    est = estimate("4P-I", cal.C_H_G, cal.points_G[cal.state], res.uv, res.found, cal.camera)
    _, dist_mm = pose_difference(est.C_H_G, w.C_H_G)
    assert dist_mm < 0.05
    w.reset_disturbance()
