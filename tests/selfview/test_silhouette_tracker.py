"""The production per-frame measurement, ``SilhouetteTracker``: what it finds, what it refuses, and the
quality figure it reports (on the simulated cell: ``selfview.mocks.world`` and ``selfview.mocks.render``)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

import selfview.measurement.silhouette as sil
from selfview.measurement import _native
from selfview.files.cell import default_cell_path, load_cell
from selfview.maths.geometry import trans
from selfview.mocks.render import render
from selfview.mocks.world import SimWorld
from selfview.estimation.online import estimate
from selfview.measurement.silhouette import fit_silhouette, learn_appearance
from selfview.measurement.fingers import SilhouetteTracker
from tests.selfview.test_silhouette_speed import _looking_at

TCP_MM = 0.05  # the on-line accuracy a tracked frame must give (4P-I on its corners, any TCP axis)
TILT_DEG = 0.3  # the camera's creep between two frames about its y axis (some 6 px in the picture)


@functools.lru_cache(maxsize=None)
def _cell():
    return load_cell(default_cell_path())


def _world(tilt_deg: float = 0.0) -> SimWorld:
    """The cell with the jaws as calibrated and the gripper lifted off the plate; the camera turned by
    ``tilt_deg`` about its y axis (through the mount's pivot), which moves finger A towards the left border."""
    cell = _cell()
    w = SimWorld(cell, seed=5)
    state = cell.gripper.calibrate_in
    w.set_jaw(cell.gripper.gap(state), state)
    w.park()
    w.unpark()
    if tilt_deg:
        w.disturb_by_angle((0.0, 1.0, 0.0), tilt_deg)
    return w


def _tcp_err(res, w: SimWorld, pred) -> float:
    """4P-I from the tracker's corners: its largest TCP error [mm] against the world's truth."""
    est = estimate("4P-I", pred, w.points_G(), res.uv, res.found, w.camera)
    return float(np.abs(est.C_H_G[:3, 3] - w.C_H_G[:3, 3]).max())


def _creep(tilt0: float, frames: int, points=range(4)):
    """A tracker primed on a picture at ``tilt0`` (predicted from the pose one creep before), then
    ``frames`` pictures each one creep further: [(result, world)] of those frames."""
    w = _world(tilt0 - TILT_DEG)
    pred = w.C_H_G
    w.disturb_by_angle((0.0, 1.0, 0.0), TILT_DEG)
    tr = SilhouetteTracker(w.camera, _cell().gripper, points=points)
    first = tr.find(render(w, seed=1).image, pred, w.jaw_gap_mm)
    assert first.lost is None and not first.tracked
    out = []
    for k in range(frames):
        w.disturb_by_angle((0.0, 1.0, 0.0), TILT_DEG)
        out.append((tr.find(render(w, seed=2 + k).image, pred, w.jaw_gap_mm), w.C_H_G.copy()))
    return tr, pred, w, out


def test_follows_a_creeping_camera_and_reports_its_quality():
    tr, pred, w, frames = _creep(TILT_DEG, 3)
    assert tr.tracked_frames == 3 and tr.searches == 1 and tr.last_failure is None
    for res, truth in frames:
        assert res.tracked and res.lost is None and res.found[:4].all() and not res.found[4:].any()
        est = estimate("4P-I", pred, w.points_G(), res.uv, res.found, w.camera)
        assert np.abs(est.C_H_G[:3, 3] - truth[:3, 3]).max() < TCP_MM
        q = res.quality
        assert q["ok"] and q["reason"] is None and q["good_fraction"] > 0.9
        assert all(f > 0.9 for f in q["finger_fraction"])
        assert q["rms_px"] < 0.3 and max(q["tcp_sd_mm"]) < sil.MAX_TCP_SD_MM and q["n_samples"] > 300
        # both fingers run out of the picture on their far side: part of each is seen, never more than all
        assert all(0.3 < v <= 1.0 for v in q["finger_visible"])


def test_a_finger_cut_by_the_left_border_is_tracked_within_0_05_mm():
    """The camera turned until finger A's outer corner and much of the finger lie beyond the left border,
    its inner corners still in the picture: the fit counts only what it can see, and holds."""
    tr, pred, w, frames = _creep(16 * TILT_DEG, 3, points=range(6))
    for res, truth in frames:
        assert res.tracked and res.lost is None
        assert res.found[:4].all() and res.found[5] and not res.found[4]
        assert res.reasons[4] == "outside the picture"
        est = estimate("4P-I", pred, w.points_G(), res.uv, res.found, w.camera)
        assert np.abs(est.C_H_G[:3, 3] - truth[:3, 3]).max() < TCP_MM
        vis_a, vis_b = res.quality["finger_visible"]
        assert vis_a < 0.2 < vis_b  # finger A mostly outside, and the figure says so
    assert tr.tracked_frames == 3


def _picture_and_levels():
    w = _world()
    pic = render(w, seed=1)
    app = learn_appearance(pic.image, w.camera, w.C_H_G, _cell().gripper, w.jaw_gap_mm)
    return w, pic, app


def test_a_finger_mostly_hidden_is_lost_with_the_reason_never_a_pose():
    """Finger B painted over from column 660 on (a third of its samples left): the per-finger support
    (``MIN_GOOD_FRACTION``) refuses the fit, though the rest would make a pose; the tracker reports a
    missed frame. A tenfold looser threshold would take it."""
    w, pic, app = _picture_and_levels()
    cell = _cell()
    img = pic.image.copy()
    img[:, 660:] = np.median(img[:, :300])
    fit = fit_silhouette(img, w.camera, w.C_H_G, cell.gripper, w.jaw_gap_mm, appearance=app, rounds=(3.0,))
    assert not fit.ok and "finger B's edge samples support the fit" in fit.reason
    assert 0.1 < fit.finger_fraction[1] < sil.MIN_GOOD_FRACTION and fit.finger_fraction[0] > 0.9
    assert not fit.found.any() and fit.quality()["ok"] is False
    tr = SilhouetteTracker(w.camera, cell.gripper, points=range(4))
    assert tr.find(pic.image, w.C_H_G, w.jaw_gap_mm).lost is None
    res = tr.find(img, w.C_H_G, w.jaw_gap_mm)
    assert res.lost is not None and not res.found.any() and np.isnan(res.uv).all() and res.C_H_G is None
    assert tr.lost_frames == 1 and tr.last_failure.startswith("lost:")


def test_a_start_a_millimetre_off_with_a_short_range_is_refused():
    """From a pose 1 mm off (some 8 px) with a 3 px search range no edge is reached: lost, with the share
    of supporting samples in the reason."""
    w, pic, app = _picture_and_levels()
    fit = fit_silhouette(pic.image, w.camera, trans(1.0, 0.0, 0.0) @ w.C_H_G, _cell().gripper, w.jaw_gap_mm,
                         appearance=app, rounds=(3.0,))
    assert not fit.ok and fit.reason.startswith("lost:") and fit.good_fraction < 0.2
    # the same pose with the default ranges finds the fingertips again
    again = fit_silhouette(pic.image, w.camera, trans(1.0, 0.0, 0.0) @ w.C_H_G, _cell().gripper, w.jaw_gap_mm,
                           appearance=app)
    assert again.ok and np.abs(again.C_H_G[:3, 3] - w.C_H_G[:3, 3]).max() < TCP_MM


@pytest.mark.parametrize("kernel", [None, _native.sil])
def test_a_point_the_other_finger_hides_is_never_found(kernel, monkeypatch):
    """A camera beyond finger B on the line from finger A's inner front corner through B: that corner is
    hidden (the kernel and the numpy code alike), the others not."""
    monkeypatch.setattr(_native, "sil", kernel)
    g = _cell().gripper
    gap = g.gap(g.calibrate_in)
    p_G6 = g.points_G(gap=gap)
    box = np.asarray(g.finger_boxes_G(gap), float).reshape(2, 2, 3)
    through_B = np.array([-gap / 2 - g.finger_thickness / 2, p_G6[0, 1], -3.0])
    H = _looking_at(p_G6[0] + 8.0 * (through_B - p_G6[0]), p_G6[0])
    cam = _world().camera
    uv, inside, hidden = sil._points_seen(cam, H, p_G6, box)
    assert inside[0] and hidden[0]
    assert not hidden[[2, 3, 5]].any()  # finger B's own points: nothing in front of them
    # what a fit at that pose reports: the hidden point not found, with the reason
    uv, found, reasons = sil._points_found(cam, H, p_G6, box, range(6))
    assert not found[0] and reasons[0] == "occluded by finger B" and np.isfinite(uv[0]).all()
    assert found[2] and reasons[2] is None


def test_a_new_jaw_gap_is_searched_for_and_bad_arguments_are_refused():
    w, pic, _ = _picture_and_levels()
    cell = _cell()
    tr = SilhouetteTracker(w.camera, cell.gripper)
    tr.find(pic.image, w.C_H_G, w.jaw_gap_mm)
    assert tr.primed
    tr.find(pic.image, w.C_H_G, w.jaw_gap_mm + 2.0)
    assert tr.last_failure.startswith("the jaw gap changed") and tr.searches == 2
    with pytest.raises(TypeError, match="camera"):
        SilhouetteTracker("camera", cell.gripper)
    with pytest.raises(ValueError, match="points"):
        SilhouetteTracker(w.camera, cell.gripper, points=[6])
    with pytest.raises(ValueError, match="track_rounds"):
        SilhouetteTracker(w.camera, cell.gripper, track_rounds=(0.5,))
    with pytest.raises(ValueError, match="gap_mm"):
        tr.find(pic.image, w.C_H_G, -1.0)


def test_rms_limit_is_the_old_gate_until_a_level_is_learnt_then_the_level_with_its_margin():
    assert sil.rms_limit(None) == sil.MAX_RMS_PX
    assert sil.rms_limit(0.2) == sil.MAX_RMS_PX  # a level under the old gate does not tighten it
    assert sil.rms_limit(0.8) == pytest.approx(sil.RMS_MARGIN * 0.8)
    with pytest.raises(ValueError, match="level_px"):
        sil.rms_limit(sil.MAX_LEARNT_RMS_PX + 0.1)
    with pytest.raises(ValueError, match="level_px"):
        SilhouetteTracker(_world().camera, _cell().gripper, rms_level_px=2.0)


def test_tracker_learns_the_residual_level_at_its_first_fit_from_the_calibrated_pose():
    w = _world()
    tr = SilhouetteTracker(w.camera, _cell().gripper, points=range(4))
    assert tr.rms_level_px is None
    first = tr.find(render(w, seed=1).image, w.C_H_G, w.jaw_gap_mm)
    assert first.lost is None
    assert tr.rms_level_px == pytest.approx(first.quality["rms_px"], abs=1e-4) and tr.rms_level_px < 0.3
    tr.reset()  # the level is the gripper's: a reset keeps it
    assert tr.rms_level_px == pytest.approx(first.quality["rms_px"], abs=1e-4)
    # a wrong level's gate refuses what the learnt one accepts: a fit over the limit given is lost with the reason
    fit = sil.fit_silhouette(render(w, seed=2).image, w.camera, w.C_H_G, _cell().gripper, w.jaw_gap_mm,
                             rounds=(8.0,), max_rms_px=0.5 * tr.rms_level_px)
    assert not fit.ok and fit.reason.startswith("lost: edge residual")


def test_tracker_follows_real_fingers_whose_right_fit_leaves_over_the_old_gate():
    """Issue 30: world 2's realistic fingers (off their nominal faces) leave 0.82-0.85 px at the true pose,
    over the old 0.6 px gate; the tracker learns that level at its first fit and tracks the next frames
    (the camera crept between them). The nominal model's pose of these fingers is off the truth by a bias
    (about 0.1 mm); a tracked frame's pose keeps that bias within TCP_MM across the picture and within twice
    that in depth (the biased model's weak axis; measured 0.007 and 0.060 mm): it followed the camera."""
    cell = _cell()
    w = SimWorld(cell, seed=2, imperfections="realistic")
    w.set_jaw(cell.gripper.gap(cell.gripper.calibrate_in), cell.gripper.calibrate_in)
    w.park()
    w.unpark()
    old = fit_silhouette(render(w, seed=1).image, w.camera, w.C_H_G, cell.gripper, w.jaw_gap_mm, rounds=(8.0,))
    assert not old.ok and old.reason.startswith("lost: edge residual") and old.rms_px > sil.MAX_RMS_PX
    tr = SilhouetteTracker(w.camera, cell.gripper, points=range(4))
    pred = w.C_H_G
    first = tr.find(render(w, seed=1).image, pred, w.jaw_gap_mm)
    assert first.lost is None and tr.rms_level_px == pytest.approx(first.quality["rms_px"], abs=1e-4)
    bias = tr.last_fit.C_H_G[:3, 3] - w.C_H_G[:3, 3]
    for k in range(2):
        w.disturb_by_angle((0.0, 1.0, 0.0), TILT_DEG)
        res = tr.find(render(w, seed=2 + k).image, pred, w.jaw_gap_mm)
        assert res.lost is None and res.tracked, res.lost
        moved = np.abs(tr.last_fit.C_H_G[:3, 3] - w.C_H_G[:3, 3] - bias)
        assert moved[:2].max() < TCP_MM and moved[2] < 2 * TCP_MM, moved


def test_a_fit_a_few_px_off_world_2s_real_fingers_is_lost_under_the_learnt_limit():
    """The learnt gate (world 2's level, 0.85 px) still loses a wrong fit: from a start 0.5-1.2 mm (4-10 px)
    off with a 3 px range the fit cannot reach the fingers' edges and is lost (its few supporting samples
    leave a small residual: the support fractions are what catch it)."""
    cell = _cell()
    w = SimWorld(cell, seed=2, imperfections="realistic")
    w.set_jaw(cell.gripper.gap(cell.gripper.calibrate_in), cell.gripper.calibrate_in)
    w.park()
    w.unpark()
    img = render(w, seed=1).image
    for dx in (0.5, 1.2):
        fit = fit_silhouette(img, w.camera, trans(dx, 0.0, 0.0) @ w.C_H_G, cell.gripper, w.jaw_gap_mm,
                             rounds=(3.0,), max_rms_px=sil.rms_limit(0.85))
        assert not fit.ok and fit.reason.startswith("lost:") and fit.uv[np.isfinite(fit.uv)].size == 0, dx


def test_a_fit_that_diverges_behind_the_camera_is_lost_not_raised(monkeypatch):
    """A solve that ends with the fingertips behind the camera (seen in a servo run right after the camera
    moved on its mount) is a lost fit with no pose: the tracker searches again instead of raising while it
    compares that pose with the last one, which ended the servo run."""
    w = _world()
    tr = SilhouetteTracker(w.camera, _cell().gripper, points=range(4))
    assert tr.find(render(w, seed=1).image, w.C_H_G, w.jaw_gap_mm).lost is None
    solve = sil._solve

    def diverged(*a, **k):
        H, *rest = solve(*a, **k)
        H = H.copy()
        H[2, 3] = -H[2, 3]  # the fingers mirrored behind the camera's plane
        return (H, *rest)

    monkeypatch.setattr(sil, "_solve", diverged)
    res = tr.find(render(w, seed=2).image, w.C_H_G, w.jaw_gap_mm)
    assert not res.found.any() and res.lost
    assert "behind the camera" in tr.last_failure
    fit = fit_silhouette(render(w, seed=3).image, w.camera, w.C_H_G, _cell().gripper, w.jaw_gap_mm, rounds=(3.0,))
    assert not fit.ok and fit.C_H_G is None and "diverged" in fit.reason
