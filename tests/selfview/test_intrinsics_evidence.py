"""The evidence behind the plate model: views left out to first order (``fit.leave_views_out``; the halves' cross-check) against refits
without them, the sign test, and the plate model chosen by what the views show (flat, bent, too few views)."""

from __future__ import annotations

import numpy as np
import pytest

from selfview.maths.camera import CameraModel
from selfview.maths.geometry import inv_H, transform_points
from selfview.measurement.discs import DiscDetections, disc_image_bias
from selfview.estimation.intrinsics import calibrate_intrinsics, fit_views
from selfview.estimation.intrinsics.evidence import chi2_3_sf, sign_test_p
from selfview.estimation.intrinsics.checks import halves_cross_check
from selfview.estimation.intrinsics.fit import leave_views_out
from selfview.estimation.intrinsics.model import intrinsics_vector
from selfview.procedures.viewplan import plan_view_poses

TRUE = CameraModel(f=962.0, kappa=1.9e-7, cx=391.2, cy=279.9, aspect=1.043)
NOISE_PX = 0.03


def views_of(cell, n: int, bow_mm: float = 0.0, seed: int = 0):
    """Disc detections of ``n`` planned views of a plate bent by ``bow_mm`` at the grid's half-width (z =
    bow (xn^2 + yn^2)): the true disc images' centroids plus noise, indexed on the plate as specified."""
    rng = np.random.default_rng(seed)
    p = cell.plate.disc_centres_W()
    half = float(np.abs(p[:, :2]).max())
    bent = p + np.column_stack([np.zeros((len(p), 2)), bow_mm * ((p[:, 0] / half) ** 2 + (p[:, 1] / half) ** 2)])
    rc = np.column_stack(np.divmod(np.arange(len(p)), cell.plate.cols))
    dets = []
    for v in plan_view_poses(cell, n, lean_W=(-1.0, 0.0)):
        C_H_W = cell.mount_guess_C_H_G @ inv_H(v["W_H_G"])
        uv = TRUE.project(transform_points(C_H_W, bent))
        ok = TRUE.in_image(uv, margin=12)
        uv = uv[ok] + disc_image_bias(TRUE, C_H_W, bent[ok], cell.plate.disc_diameter / 2)
        dets.append(DiscDetections(uv=uv + rng.normal(0, NOISE_PX, uv.shape), rc=rc[ok], p_W=p[ok],
                                   area_px=np.full(ok.sum(), 100.0), n_blobs=int(ok.sum()), rejected={}))
    return dets


def test_views_left_out_to_first_order_match_refits(cell):
    """Leaving a view out moves f, cx, cy as a refit without it does, to a tenth of the move plus 3/4 of their
    sigmas, well under the moves it tells apart (the flat plate's fit of a bent one moves by up to 5 sigmas;
    measured: within a tenth of both with numpy 2 and OpenCV 5, 0.6 sigma on the bow's cy for view 0 with
    numpy 1.26 and OpenCV 4.10, where the refit lands elsewhere); the view's residuals predicted by
    the others (its pose refitted) are the noise's size, above its own fit's."""
    dets = views_of(cell, 8, bow_mm=0.3)
    names = [f"v{k}" for k in range(len(dets))]
    for model in ("flat", "bow"):
        fit = fit_views(dets, cell.plate, cell.camera.guess(), names, bias=False, plate_model=model, fit_skew=False)
        delta, heldout = leave_views_out(fit)
        sd = np.sqrt(np.diag(fit.cov5))
        for k in (0, 5):
            keep = [i for i in range(len(dets)) if i != k]
            sub = fit_views([dets[i] for i in keep], cell.plate, fit.camera, [names[i] for i in keep], bias=False,
                            plate_model=model, fit_skew=False)
            exact = np.array([sub.camera.f - fit.camera.f, sub.camera.cx - fit.camera.cx, sub.camera.cy - fit.camera.cy])
            lin = delta[k, [0, 2, 3]]
            assert np.all(np.abs(lin - exact) < 0.1 * np.abs(exact) + 0.75 * sd[[0, 2, 3]]), (model, k, lin, exact, sd)
            assert np.any(np.abs(exact) > 0.2 * sd[[0, 2, 3]])  # leaving a view out does move them
        own = np.array([v.rms_px for v in fit.views]) ** 2  # mean square per disc of du^2 + dv^2
        if model == "bow":
            assert np.all(heldout > own) and 0.5 < np.sqrt(np.mean(heldout) / 2) / NOISE_PX < 2.0, heldout


def test_sign_test_and_chi_square():
    assert sign_test_p(6, 0) == pytest.approx(1 / 64)
    assert sign_test_p(12, 1) == pytest.approx(14 / 8192)
    assert sign_test_p(0, 5) == 1.0 and sign_test_p(0, 0) == 1.0
    assert chi2_3_sf(11.345) == pytest.approx(0.01, rel=1e-3) and chi2_3_sf(0.0) == pytest.approx(1.0)


@pytest.mark.parametrize("bow_mm, n, model", [(0.0, 8, "flat"), (0.3, 8, "bow"), (0.3, 6, "flat")])
def test_the_plate_model_follows_the_evidence(cell, bow_mm, n, model):
    """A flat plate stays flat; a plate bent by 0.3 mm gets its bow when 8 views confirm it left out in turn
    (its discs have no print errors: their corrections predict nothing more, so the bow stays); 6 views
    cannot confirm it at the 1 % level (6 of 6 is p = 1/64), so the plate stays flat and the bow the views
    measure holds the skew at 0."""
    dets = views_of(cell, n, bow_mm=bow_mm, seed=1)
    r = calibrate_intrinsics(None, cell.plate, cell.camera.guess(), detections=dets, cross_check=False)
    ps = r.plate_shape
    assert ps["model"] == model, ps["why"]
    assert r.views_used == n and "sign test" in ps["why"]
    if bow_mm and model == "flat":
        assert "the views measure bow" in ps["why"] and f"{n} of {n} views better" in ps["why"]
        assert r.camera.skew == 0.0 and "bow" in r.skew_fit["note"]
    if model == "bow":
        assert abs(sum(ps["bow_mm"][::2]) - 2 * bow_mm) < 0.1 * bow_mm, ps["bow_mm"]
        assert abs(r.camera.cx - TRUE.cx) < 3 * r.sigma["cx"] and abs(r.camera.f - TRUE.f) < 3 * r.sigma["f"]


def test_halves_to_first_order_match_their_refits(cell):
    """The cross-check's halves (alternate views, each with the other half left out to first order, no refit)
    land where refits of each half land: f, cx, cy within a tenth of the move from the whole fit plus half
    their sigmas (measured: 0.2 sigma at most, on a move of 2.6), the halves' combined sigmas within 5 % of the
    refits' (their own residual variance; measured: 1 %)."""
    dets = views_of(cell, 8, bow_mm=0.3, seed=2)
    names = [f"v{k}" for k in range(len(dets))]
    for model in ("flat", "bow"):
        fit = fit_views(dets, cell.plate, cell.camera.guess(), names, bias=False, plate_model=model, fit_skew=False)
        xc = halves_cross_check(fit)
        assert xc["done"], xc
        refits = [fit_views(dets[h::2], cell.plate, fit.camera, names[h::2], bias=False, plate_model=model,
                            fit_skew=False, start=fit) for h in (0, 1)]
        whole = intrinsics_vector(fit.camera, 5)[[0, 2, 3]]
        for half, sub in zip(xc["halves"], refits):
            lin = np.array([half["f"], half["cx"], half["cy"]])
            exact = intrinsics_vector(sub.camera, 5)[[0, 2, 3]]
            sd = np.sqrt(np.diag(sub.cov5))[[0, 2, 3]]
            assert np.all(np.abs(lin - exact) < 0.1 * np.abs(exact - whole) + 0.5 * sd), (model, lin, exact, sd)
            assert np.any(np.abs(exact - whole) > 0.2 * sd)  # a half alone does move them
        comb = np.sqrt(np.diag(refits[0].cov5) + np.diag(refits[1].cov5))
        got = np.array([xc["combined_sigma"][nm] for nm in ("f", "kappa", "cx", "cy", "aspect")])
        assert np.all(np.abs(got / comb - 1) < 0.05), (model, got / comb)


def test_a_bent_plate_refit_from_a_skewed_start_holds_the_skew(cell):
    """The skew's refit with it held at 0 (``calibrate._decide_skew``) starts from the fit with it free; on a
    bent plate that start's camera carries its fitted skew: the refit holds the skew at the camera given and
    lands where a cold fit with it held lands, within a tenth of a sigma: the two stop at the solver's
    tolerance from different starts (measured: 3e-4 sigma with numpy 2 / OpenCV 5, 0.06 sigma on f with numpy
    1.26 / OpenCV 4.10). Without the fix the refit keeps the start's skew."""
    dets = views_of(cell, 8, bow_mm=0.3, seed=1)
    names = [f"v{k}" for k in range(len(dets))]
    free = fit_views(dets, cell.plate, cell.camera.guess(), names, plate_model="bow", fit_skew=True)
    assert free.camera.skew != 0.0
    held = fit_views(dets, cell.plate, free.camera.with_(skew=0.0), names, plate_model="bow", fit_skew=False, start=free)
    cold = fit_views(dets, cell.plate, cell.camera.guess(), names, plate_model="bow", fit_skew=False)
    assert held.camera.skew == 0.0
    sd = np.sqrt(np.diag(cold.cov5))
    assert np.all(np.abs(intrinsics_vector(held.camera, 5) - intrinsics_vector(cold.camera, 5)) < 0.1 * sd)
