"""Off-line calibration from one picture, end to end, on pictures of two independent renderers.

The accuracy targets (f within 0.2 %, kappa within 3 %, TCP position of C_H_G within 0.02 mm across and
0.08 mm along the optical axis, rotation within 0.02 degrees) are met with room to spare; the tests bound
each figure by what the pipeline achieves, with a stated margin, so that losing a step fails a test.
A robustness case meets its bound; none is allowed to refuse its picture.
"""

import numpy as np
import pytest

from selfview.mocks.render import render
from selfview.errors import CalibrationError, ImageError
from selfview.mocks.world import SimWorld
from selfview.maths.geometry import pose_difference
from selfview.estimation.offline import calibrate_offline
from tests import alt_render

TARGET = {"f_rel": 0.002, "kappa_rel": 0.03, "across_mm": 0.02, "along_mm": 0.08, "rot_deg": 0.02}  # the accuracy targets
MARGIN = 2.0
# Measured on the reference cell (bench-style runs of these very cases; medians over the seeds):
#
# =============================  =======  =======  ========  ========  ========
# figure                         f_rel    kappa    across    along     rot
# =============================  =======  =======  ========  ========  ========
# project renderer, 30 seeds     9.3e-5   7.1e-4   0.0029    0.0100    0.0035
#   95th percentile              1.7e-4   2.4e-3   0.0091    0.0182    0.0106
#   without the disc-bias step   1.9e-4   5.7e-4   0.0031    0.0104    0.0151
# independent renderer, 8 seeds  1.2e-4   1.1e-3   0.0023    0.0121    0.0043
#   without the disc-bias step   2.5e-4   1.1e-3   0.0026    0.0105    0.0154
# robustness, sharp, worst case  1.6e-4   3.1e-3   0.0118    0.0183    0.0077
# robustness, blur 1.5 px, worst 1.0e-4   2.1e-3   0.0355    0.0289    0.0279
# =============================  =======  =======  ========  ========  ========
#
# (mm, degrees; f and kappa relative). Margin: twice the measured figure (seed-to-seed spread, other
# platforms' rounding), so the disc-bias correction's removal (rotation error x4) fails the medians and the
# sharp robustness cases.
# what the pipeline achieves (the table above), each bound being MARGIN times the measured figure
ACHIEVED_MEDIAN = {"f_rel": 9.3e-5, "kappa_rel": 7.1e-4, "across_mm": 0.0029, "along_mm": 0.0100, "rot_deg": 0.0035}
ACHIEVED_P95 = {"f_rel": 1.7e-4, "kappa_rel": 2.4e-3, "across_mm": 0.0091, "along_mm": 0.0182, "rot_deg": 0.0106}
ACHIEVED_ALT = {"f_rel": 1.24e-4, "kappa_rel": 1.05e-3, "across_mm": 0.0023, "along_mm": 0.0121, "rot_deg": 0.0043}
ACHIEVED_ROBUST = {"f_rel": 1.64e-4, "kappa_rel": 3.13e-3, "across_mm": 0.0118, "along_mm": 0.0183, "rot_deg": 0.0077}
# out of focus (blur 1.5 px instead of 0.6) the edges of the discs and fingertips soften: measured f 1.0e-4,
# kappa 2.1e-3, across 0.0355, along 0.0289, rot 0.0279; bound by twice that, but never looser than twice
# the accuracy targets
ACHIEVED_BLURRED = {"f_rel": 1.04e-4, "kappa_rel": 2.12e-3, "across_mm": 0.0355, "along_mm": 0.0289, "rot_deg": 0.0279}


def errors(res, world):
    cal = res.calibration
    true = world.C_H_G
    d = cal.C_H_G[:3, 3] - true[:3, 3]
    return {
        "f_rel": abs(cal.camera.f / world.camera.f - 1),
        "kappa_rel": abs(cal.camera.kappa / world.camera.kappa - 1),
        "across_mm": float(np.hypot(d[0], d[1])),
        "along_mm": float(abs(d[2])),
        "rot_deg": pose_difference(cal.C_H_G, true)[0],
    }


def medians(rows):
    return {k: float(np.median([r[k] for r in rows])) for k in TARGET}


def beyond(errs, achieved, cap=None):
    """The figures of ``errs`` above MARGIN times ``achieved`` (or above ``cap`` where that is tighter)."""
    bound = {k: MARGIN * v if cap is None else min(MARGIN * v, cap[k]) for k, v in achieved.items()}
    return {k: (v, bound[k]) for k, v in errs.items() if not v <= bound[k]}


def test_the_bounds_are_within_the_targets():
    for achieved in (ACHIEVED_MEDIAN, ACHIEVED_ALT):
        assert all(MARGIN * achieved[k] <= TARGET[k] for k in TARGET)


@pytest.mark.slow
def test_accuracy_over_30_seeds_on_the_project_renderer(cell):
    rows = []
    for seed in range(30):
        w = SimWorld(cell, seed=seed)
        w.park()
        rows.append(errors(calibrate_offline(render(w, seed=seed).image, cell), w))
    med = medians(rows)
    assert beyond(med, ACHIEVED_MEDIAN) == {}, f"medians {med}"
    p95 = {k: float(np.percentile([r[k] for r in rows], 95)) for k in TARGET}
    assert beyond(p95, ACHIEVED_P95) == {}, f"95th percentiles {p95}"


@pytest.mark.slow
def test_accuracy_on_an_independent_renderer(cell):
    rows = []
    for seed in range(8):
        w = SimWorld(cell, seed=100 + seed)
        w.park()
        pic = alt_render.render_world(w, seed=seed)
        rows.append(errors(calibrate_offline(pic.image, cell), w))
    med = medians(rows)
    assert beyond(med, ACHIEVED_ALT) == {}, f"medians {med}"


def _robust_world(cell, case, seed):
    w = SimWorld(cell, seed=seed)
    if case == "rotated90":
        w.park(turn_deg=90)
    else:
        w.park()
    if case == "bottom_row_cut":
        # slide the plate half a pitch and more towards the camera's bottom edge
        W_H_G = w.W_H_G.copy()
        W_H_G[1, 3] -= 6.0
        w.W_H_G = W_H_G
        w.version += 1
    return w


ROBUST = [
    ("fingers_cover_discs", {}),
    ("bottom_row_cut", {}),
    ("rotated90", {}),
    ("brighter", {"gain": 1.03}),
    ("darker", {"gain": 0.97}),
    ("out_of_focus", {"blur_px": 1.5}),
]


@pytest.mark.parametrize("renderer", ["project", "independent"])
@pytest.mark.parametrize("case, kw", ROBUST, ids=[c for c, _ in ROBUST])
def test_robustness(cell, renderer, case, kw):
    w = _robust_world(cell, case, seed=31)
    if renderer == "project":
        img = render(w, seed=5, **kw).image
    else:
        opt = {"gain": kw.get("gain", 1.0), "blur_sigma": kw.get("blur_px", 0.6)}
        img = alt_render.render_world(w, seed=5, **opt).image
    # every case is calibrated (none refuses its picture: a refusal fails here with its reason)
    res = calibrate_offline(img, cell)
    if case == "out_of_focus":
        bad = beyond(errors(res, w), ACHIEVED_BLURRED, cap={k: 2.0 * v for k, v in TARGET.items()})
    else:
        bad = beyond(errors(res, w), ACHIEVED_ROBUST)
    assert bad == {}, f"{case}: (error, bound) beyond the bound: {bad}"


def test_unusable_pictures_fail_clearly(cell):
    with pytest.raises(ImageError, match="blank"):
        calibrate_offline(np.full((576, 768), 200, np.uint8), cell)
    with pytest.raises(ImageError, match="640x480"):
        calibrate_offline(np.zeros((480, 640), np.uint8), cell)
    with pytest.raises(ImageError, match="colour"):
        calibrate_offline(np.zeros((576, 768, 3), np.uint8), cell)
    w = SimWorld(cell, seed=3)
    w.park()
    # no plate in the picture: the gripper over the textured table
    w.unpark()
    w.base_H_plate0 = w.base_H_plate0.copy()
    w.base_H_plate0[0, 3] += 500.0
    with pytest.raises((ImageError, CalibrationError), match="disc|plate"):
        calibrate_offline(render(w, seed=1).image, cell)
    # no fingers in the picture: the independent renderer leaves them out
    w2 = SimWorld(cell, seed=4)
    w2.park()
    pic = alt_render.render_world(w2, fingers=False)
    with pytest.raises(CalibrationError, match="fingertip"):
        calibrate_offline(pic.image, cell)


def test_a_mount_guess_that_is_no_transform_is_named(cell):
    w = SimWorld(cell, seed=3)
    w.park()
    img = render(w, seed=1).image
    for bad in (np.eye(3), np.full((4, 4), np.nan)):
        with pytest.raises(ValueError, match=r"C_H_G_guess: expected a finite \(4, 4\) transform"):
            calibrate_offline(img, cell, C_H_G_guess=bad)
