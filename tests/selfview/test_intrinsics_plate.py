"""selfview.estimation.intrinsics on a printed plate that is not the specified one: the plate's bow and its discs'
position errors fitted with the camera (fitted as
specified, the realistic plate puts the image centre 1.2-3.9 px off on the seeds below).

The pictures are the project's renderer's: the independent test renderer draws only the specified plate.
"""

from __future__ import annotations

import numpy as np
import pytest

from selfview.maths.geometry import R_from_rotvec, inv_H, make_H, trans
from selfview.estimation.intrinsics import calibrate_intrinsics, detect_views, fit_views
from selfview.estimation.intrinsics.model import JointProblem
from selfview.estimation.intrinsics.plate import PlateShape, _similarity_complement
from selfview.mocks.imperfections import PROFILES
from selfview.mocks.render import render
from selfview.mocks.world import PLATE_BASE_POSE, SimWorld
from selfview.procedures.viewplan import plan_view_poses

SEEDS = (0, 1, 2)
#: Centre error bound [px] on the realistic plate: the largest measured over these seeds (and over 12
#: seeds, bench/intrinsics.py --profile realistic:plate) is 0.55 px; 0.8 px leaves a margin of about 1.5.
#: The plate taken as specified misses by 1.2-3.9 px on these seeds (measured with OpenCV 4.14, NumPy 2.4;
#: 1-8 px, median 4, over 12).
CENTRE_BOUND_PX = 0.8


@pytest.fixture(scope="module")
def plate_views(cell):
    """Per seed: (detections of the 12 planned views, names, the true camera, the world's printed plate)."""
    imp = PROFILES["realistic"].only("plate")
    out = []
    for seed in SEEDS:
        w = SimWorld(cell, seed=seed, imperfections=imp, camera="realistic")
        plate = PLATE_BASE_POSE @ trans(0.0, 0.0, 4.0)
        lean = (inv_H(plate) @ np.array([0.0, 0.0, 0.0, 1.0]))[:2]
        imgs = []
        for i, v in enumerate(plan_view_poses(cell, 12, lean_W=lean)):
            w.set_tcp(plate @ v["W_H_G"])
            imgs.append(render(w, seed=seed * 100 + i).image)
        dets, names, _ = detect_views(imgs, cell.plate, cell.camera.guess(), skip_unusable=True)
        out.append((dets, names, w.camera, w.imperfect))
    return out


def test_realistic_plate_centre_within_its_sigma_and_the_bound(cell, plate_views):
    z, errs, flat_errs = [], [], []
    for dets, names, truth, printed in plate_views:
        r = calibrate_intrinsics(None, cell.plate, cell.camera.guess(), names, detections=dets, cross_check=False)
        c = r.camera
        e = np.array([c.f - truth.f, c.cx - truth.cx, c.cy - truth.cy, c.aspect - truth.aspect])
        s = np.array([r.sigma[k] for k in ("f", "cx", "cy", "aspect")])
        z.append(e / s)
        errs.append(np.hypot(e[1], e[2]))
        assert np.all(np.abs(e / s) < 3.5), (e, s)  # no parameter off by more than 3.5 of its sigmas
        assert r.rms_px < 0.03  # the shape explains the pictures down to the centroids' noise (flat: 0.13 px)
        ps = r.plate_shape
        assert ps["model"] == "bow+dots"
        # the print's dot errors are 15 um per axis: the fitted ones' sd is that, within the draw's spread
        assert 0.010 < ps["dot_sd_mm"] < 0.020, ps
        # the bow, a cylinder 0.2 mm high across 110 mm: its quadratic over the grid's half-width (31.5 mm)
        # has trace 0.2 (31.5 / 55)^2 = 0.066 mm and no second curvature (turn-invariant figures)
        bxx, bxy, byy = ps["bow_mm"]
        half = 0.5 * float(min(cell.plate.size))
        trace = printed.imp.plate_bow_mm * (3.5 * cell.plate.pitch / half) ** 2
        assert abs(bxx + byy - trace) < 0.2 * trace, ps["bow_mm"]
        assert abs(bxx * byy - bxy**2 / 4) < 0.1 * trace**2, ps["bow_mm"]
        assert sum(t is not None for t in ps["turns_deg"]) >= 10 and any(t for t in ps["turns_deg"] if t)
        flat = fit_views(dets, cell.plate, cell.camera.guess(), names, plate_model="flat").camera
        flat_errs.append(np.hypot(flat.cx - truth.cx, flat.cy - truth.cy))
    z = np.array(z)
    # honest sigmas: errors within a factor 2 of the sigmas (RMS over seeds and parameters)
    assert np.sqrt(np.mean(z**2)) < 2.0, z
    assert max(errs) < CENTRE_BOUND_PX, errs
    # the same detections on the plate as specified: the centre error this fit removes
    # (per seed a draw of the print's errors: each seed's flat fit is worse, and on average beyond the bound)
    assert all(f > e for f, e in zip(flat_errs, errs)), (flat_errs, errs)
    assert np.mean(flat_errs) > CENTRE_BOUND_PX, flat_errs  # 1.2-3.9 px on these seeds (see CENTRE_BOUND_PX)


def test_disc_corrections_cannot_move_turn_or_scale_the_grid(cell):
    p0 = cell.plate.disc_centres_W()
    B = _similarity_complement(p0)
    n = len(p0)
    assert B.shape == (2 * n, 2 * n - 4)
    np.testing.assert_allclose(B.T @ B, np.eye(2 * n - 4), atol=1e-12)
    c = p0[:, :2]
    modes = [np.tile([1.0, 0.0], n), np.tile([0.0, 1.0], n), np.column_stack([-c[:, 1], c[:, 0]]).ravel(), c.ravel()]
    for m in modes:  # shift x, shift y, turn, scale: orthogonal to every correction
        assert np.abs(B.T @ m).max() < 1e-10 * np.linalg.norm(m)


def test_joint_jacobian_with_the_plate_shape_matches_differences(cell):
    """The analytic Jacobian against central differences: 1e-5 relative is far below what would bend the
    LM's steps (and far above the differences' rounding)."""
    rng = np.random.default_rng(3)
    cam = cell.camera.guess()
    p0 = cell.plate.disc_centres_W()
    shape = PlateShape(cell.plate, "bow+dots", 0.02)
    poses, P, uv, idx = [], [], [], []
    for k in range(3):
        H = make_H(R_from_rotvec(rng.normal(0, 0.3, 3)), (rng.normal(0, 5), rng.normal(0, 5), 180.0 + 20 * k))
        keep = np.sort(rng.choice(len(p0), 40, replace=False))
        poses.append(H)
        P.append(p0[keep])
        uv.append(rng.normal(0, 1, (40, 2)) + (cam.cx, cam.cy))
        idx.append(keep)
    model = JointProblem(P, uv, [H[:3, :3] for H in poses], shape, idx)
    x = np.concatenate([[cam.f, cam.kappa, cam.cx, cam.cy, cam.aspect],
                        *[np.r_[np.zeros(3), H[:3, 3]] for H in poses], rng.normal(0, 0.05, shape.n)])
    J = model.jacobian(x)
    for i in [0, 2, 3, 4, 5, 8, 23, 24, 25, 26, 60, len(x) - 1]:
        h = 1e-6 * max(1.0, abs(x[i]))
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        num = (model.residuals(xp) - model.residuals(xm)) / (2 * h)
        assert np.abs(J[:, i] - num).max() < 1e-5 * max(np.abs(num).max(), 1e-9), i
    # the stacked views' residuals are each view's own, in order; the blocked normal matrix is J^T J
    r = model.residuals(x)
    assert np.allclose(r[: model.m_data], np.concatenate([model.view(x, k) for k in range(3)]), rtol=0, atol=1e-9)
    assert np.allclose(r[model.m_data :], shape.w * x[5 + 18 :], rtol=0, atol=0)
    A = J.T @ J
    assert np.abs(model.normal_matrix(J) - A).max() <= 1e-12 * np.abs(A).max()


def test_a_view_of_another_print_is_left_out_and_named(cell, plate_views):
    """A view whose dot pattern matches none of the others (here: another print of the plate, seen by the
    same camera) cannot be tied to the plate's grid; its discs would give the per-disc corrections to the
    wrong discs (24-view sets with two such views missed the centre by 1-3 px with sigmas 4 times too
    small), so it is left out and named in ``skipped``, and the fit is the fit of the others."""
    dets, names, truth, _ = plate_views[0]
    other = SimWorld(cell, seed=7, imperfections=PROFILES["realistic"].only("plate"), camera=truth)
    plate = PLATE_BASE_POSE @ trans(0.0, 0.0, 4.0)
    lean = (inv_H(plate) @ np.array([0.0, 0.0, 0.0, 1.0]))[:2]
    other.set_tcp(plate @ plan_view_poses(cell, 12, lean_W=lean)[5]["W_H_G"])
    extra, _, _ = detect_views([render(other, seed=71).image], cell.plate, cell.camera.guess(), ["other print"])
    r = calibrate_intrinsics(None, cell.plate, cell.camera.guess(), names + ["other print"], detections=dets + extra,
                             cross_check=False)
    assert [s["name"] for s in r.skipped] == ["other print"] and "plate's grid" in r.skipped[0]["reason"]
    assert r.views_used == len(dets) and "other print" not in [v.name for v in r.views]
    assert np.hypot(r.camera.cx - truth.cx, r.camera.cy - truth.cy) < CENTRE_BOUND_PX
