"""Fingertip corners followed from frame to frame (``selfview.tracking``).

Judged like the search (``test_fingertips.py``): on pictures of the independent test renderer
(``tests/alt_render.py``) and of the project's renderer, against their truth, and against the full
search on the same pictures. Each sequence: a picture the tracker is primed on (by the full search),
then pictures of a camera creeping on its mount, each with new sensor noise.
"""

from __future__ import annotations

import numpy as np
import pytest

from selfview.errors import CalibrationError, ImageError
from selfview.fingertips import find_fingertips
from selfview.tracking import FingertipTracker
from tests.alt_render import render_world


def _render(renderer: str, world, seed: int, **kw):
    if renderer == "alt":
        return render_world(world, seed=seed, **kw)
    from selfview.mocks.render import render

    return render(world, seed=seed)


def _world(cell, seed: int, parked: bool):
    from selfview.mocks.world import SimWorld

    w = SimWorld(cell, seed)
    w.park()
    if not parked:
        w.unpark()  # lifted over the table: its texture behind the fingers
    return w


@pytest.mark.parametrize("renderer", ["alt", "project"])
@pytest.mark.parametrize("seed,parked", [(0, True), (2, False)])
def test_follows_a_creeping_camera_as_accurately_as_the_search(cell, renderer, seed, parked):
    w = _world(cell, seed, parked)
    tr = FingertipTracker(w.camera, cell.gripper)
    first = tr.find(_render(renderer, w, seed).image, w.C_H_G, w.jaw_gap_mm)
    assert not first.tracked and first.found[:4].all() and tr.primed
    rng = np.random.default_rng(seed)
    err_t, err_s, apart = [], [], []
    for i in range(4):
        w.disturb_by_angle(rng.normal(size=3), 0.05)  # about 1 px a frame
        pic = _render(renderer, w, 100 + i)
        res = tr.find(pic.image, w.C_H_G, w.jaw_gap_mm)
        assert res.tracked, tr.last_failure
        assert res.found[:4].all() and not res.found[4:].any()
        assert all(r is None for r in res.reasons[:4]) and res.reasons[4:] == ["not requested"] * 2
        assert np.all(res.n_edge_points[:4] >= 12) and np.all(res.edge_rms_px[:4] < 0.25)
        full = find_fingertips(pic.image, w.camera, w.C_H_G, cell.gripper, w.jaw_gap_mm, points=range(4))
        err_t.append(np.linalg.norm(res.uv[:4] - pic.corner_uv[:4], axis=1))
        err_s.append(np.linalg.norm(full.uv[:4] - pic.corner_uv[:4], axis=1))
        apart.append(np.linalg.norm(res.uv[:4] - full.uv[:4], axis=1))
    err_t, err_s, apart = map(np.concatenate, (err_t, err_s, apart))
    assert tr.searches == 1 and tr.tracked_frames == 4
    # as accurate as the search (whose own bounds are mean 0.15, max 0.5 px on these pictures)
    assert err_t.mean() < 0.12 and err_t.max() < 0.45, err_t
    assert err_t.mean() < err_s.mean() + 0.03, (err_t.mean(), err_s.mean())
    assert apart.mean() < 0.1, apart


def test_a_jump_beyond_the_tracking_range_is_searched_for(cell):
    w = _world(cell, 1, parked=False)
    before = w.C_H_G
    tr = FingertipTracker(w.camera, cell.gripper, track_px=8.0)
    tr.find(render_world(w, seed=1).image, before, w.jaw_gap_mm)
    w.disturb("cable")  # the fingertips move some 10-20 px in the picture
    pic = render_world(w, seed=2)
    res = tr.find(pic.image, before, w.jaw_gap_mm)
    assert not res.tracked and isinstance(tr.last_failure, str) and tr.last_failure
    assert res.found[:4].all()
    assert np.linalg.norm(res.uv[:4] - pic.corner_uv[:4], axis=1).max() < 0.7
    # and from there on it is followed again
    w.disturb_by_angle((0.0, 0.0, 1.0), 0.05)
    pic = render_world(w, seed=3)
    res = tr.find(pic.image, before, w.jaw_gap_mm)
    assert res.tracked, tr.last_failure
    assert np.linalg.norm(res.uv[:4] - pic.corner_uv[:4], axis=1).max() < 0.7


def test_an_object_covering_a_corner_is_not_tracked_over(cell):
    from selfview.geometry import transform_points

    w = _world(cell, 3, parked=True)
    tr = FingertipTracker(w.camera, cell.gripper)
    tr.find(render_world(w, seed=3).image, w.C_H_G, w.jaw_gap_mm)
    assert tr.primed
    p = 0.8 * transform_points(w.C_H_G, w.points_G())[0]  # on the line of sight to A-inner-front
    occluder = (p - [2.5, 2.5, 1.0], p + [2.5, 2.5, 1.0], 235.0)
    pic = render_world(w, seed=4, occluders=(occluder,))
    res = tr.find(pic.image, w.C_H_G, w.jaw_gap_mm)
    assert not res.tracked and tr.last_failure
    assert not res.found[0] and "occluded" in res.reasons[0], res.reasons[0]
    assert res.found[[2, 3]].all()


@pytest.mark.parametrize(
    "options, mean, worst",
    [
        ((("gain", 0.97),), 0.15, 0.45),
        ((("gain", 1.03),), 0.15, 0.45),
        ((("blur_sigma", 1.5),), 0.3, 0.8),
        ((("gradient", (0.4, -0.3)), ("vignetting", 0.3)), 0.15, 0.45),
    ],
)
def test_a_change_of_light_or_focus(cell, options, mean, worst):
    """Tracked or searched for again, the corners stay within the search's own bounds."""
    w = _world(cell, 2, parked=True)
    tr = FingertipTracker(w.camera, cell.gripper)
    tr.find(render_world(w, seed=2).image, w.C_H_G, w.jaw_gap_mm)
    w.disturb_by_angle((1.0, 0.0, 0.0), 0.05)
    opts = dict(options)
    pic = render_world(w, seed=5, **opts)
    res = tr.find(pic.image, w.C_H_G, w.jaw_gap_mm)
    assert res.found[:4].all(), res.reasons
    err = np.linalg.norm(res.uv[:4] - pic.corner_uv[:4], axis=1)
    assert err.mean() < mean and err.max() < worst, (err, res.tracked, tr.last_failure)


def test_missing_points_are_reported_and_searched_for_again(cell):
    w = _world(cell, 4, parked=True)
    before = w.C_H_G
    w.disturb_by_angle((0.0, 1.0, 0.0), 3.0)  # A's outer point leaves the picture
    pic = render_world(w, seed=4)
    assert not pic.corner_visible[4]
    tr = FingertipTracker(w.camera, cell.gripper, points=range(6), search_px=80.0, refresh_frames=2)
    res = tr.find(pic.image, before, w.jaw_gap_mm)
    assert not res.found[4] and "outside the picture" in res.reasons[4]
    assert tr.primed and res.found[:4].all()
    for i in range(3):
        res = tr.find(render_world(w, seed=10 + i).image, before, w.jaw_gap_mm)
        assert res.found[:4].all() and not res.found[4]
        if i < 2:
            assert res.tracked, tr.last_failure
            assert res.reasons[4].startswith(f"not found at the last search, {i + 1} frame(s) ago: outside the picture")
    # after two tracked frames the missing point was looked for again
    assert not res.tracked and "searching again for A-outer-front" in tr.last_failure
    assert tr.searches == 2 and tr.tracked_frames == 2


def test_a_new_jaw_gap_a_blank_picture_and_bad_arguments(cell):
    w = _world(cell, 0, parked=False)
    tr = FingertipTracker(w.camera, cell.gripper)
    img = render_world(w, seed=0).image
    tr.find(img, w.C_H_G, w.jaw_gap_mm)
    res = tr.find(img, w.C_H_G, w.jaw_gap_mm + 2.0)
    assert not res.tracked and "jaw gap changed" in tr.last_failure
    tr.find(img, w.C_H_G, w.jaw_gap_mm)
    with pytest.raises(ImageError, match="blank"):
        tr.find(np.full((576, 768), 90, np.uint8), w.C_H_G, w.jaw_gap_mm)
    with pytest.raises(ImageError, match="camera model expects"):
        tr.find(img[:, :700], w.C_H_G, w.jaw_gap_mm)
    with pytest.raises(ValueError, match="indices 0..5"):
        FingertipTracker(w.camera, cell.gripper, points=[6])
    with pytest.raises(ValueError, match="track_px"):
        FingertipTracker(w.camera, cell.gripper, track_px=float("nan"))
    with pytest.raises(TypeError, match="CameraModel"):
        FingertipTracker("camera", cell.gripper)
    # a bad prediction or jaw gap is refused, also while primed (it would not be used when tracking)
    tr.find(img, w.C_H_G, w.jaw_gap_mm)
    assert tr.primed
    with pytest.raises(ValueError, match="jaw gap"):
        tr.find(img, w.C_H_G, float("nan"))
    with pytest.raises(ValueError, match="jaw gap"):
        tr.find(img, w.C_H_G, -5.0)
    with pytest.raises(ValueError, match=r"\(4, 4\) transform"):
        tr.find(img, np.eye(3), w.jaw_gap_mm)
    with pytest.raises(CalibrationError, match="non-finite"):
        find_fingertips(img, w.camera, np.full((4, 4), np.nan), cell.gripper, w.jaw_gap_mm)
