"""``calibrate_intrinsics``: the joint calibration from the plate's pictures, with stop rule, advice and cross-check."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import PlateSpec
from selfview.errors import CalibrationError
from selfview.estimation.intrinsics.advice import (MAX_MORE_VIEWS, STOP_ASPECT_REL, STOP_CENTRE_PX, more_views_advice,
                                                   stop_met)
from selfview.estimation.intrinsics.checks import halves_cross_check
from selfview.estimation.intrinsics.plate import PLATE_MODELS
from selfview.estimation.intrinsics.evidence import chi2_3_sf, heldout_test, sign_test_p
from selfview.maths.lm import wald_chi2
from selfview.estimation.intrinsics.fit import (MIN_VIEWS, UNDETERMINED_CENTRE_PX, VIEW_MAX_RMS_PX, JointFit, sigmas_of,
                                                detect_views, fit_views, leave_views_out, projection_sigma_px)

#: The skew is kept only this many sigmas from 0 (0.3 % false alarms) by its formal sigma and by its jackknife's,
#: which sees a skew standing for something the model lacks change from view to view; else it is held at 0.
SKEW_SIGNIFICANCE = 3.0
#: Level for a richer plate model ('auto'): the held-out sign test and the bow's chi-square against 0.
PLATE_TEST_LEVEL = 0.01
PLATE_STEPS = ("flat", "bow", "bow+dots")


@dataclass
class IntrinsicsResult:
    """A joint calibration of the interior orientation from several views (see the module)."""

    camera: CameraModel
    covariance: np.ndarray  # (n, n) of INTRINSIC_NAMES[:n]: n = 6 with the skew fitted, 5 without
    sigma: dict
    rms_px: float
    views: list
    skipped: list
    projection_sigma_px: dict
    stop_rule: dict
    cross_check: dict
    residual_sigma_px: float = 0.0
    plate_shape: dict = field(default_factory=dict)
    skew_fit: dict = field(default_factory=dict)

    @property
    def views_used(self) -> int:
        return len(self.views)

    def summary(self) -> dict:
        c = self.camera
        return {
            "f": c.f, "kappa": c.kappa, "principal_point": [c.cx, c.cy], "aspect": c.aspect, "skew": c.skew,
            "width": c.width, "height": c.height, "sigma": dict(self.sigma),
            "covariance": np.asarray(self.covariance).tolist(), "rms_px": self.rms_px, "views_used": self.views_used,
            "views": [v.to_dict() for v in self.views], "views_skipped": list(self.skipped),
            "projection_sigma_px": dict(self.projection_sigma_px), "stop_rule": self.stop_rule,
            "cross_check": self.cross_check, "plate_shape": self.plate_shape, "skew_fit": dict(self.skew_fit),
        }


def _plate_summary(fit: JointFit) -> dict:
    """The fitted plate: model, bow coefficients [mm] (xx, xy, yy at the half-width) and 1-sigma, the discs' error sd
    and correction rms [mm], each view's turn onto the plate's grid [deg] (None: kept as found)."""
    out = {"model": fit.plate_model, "turns_deg": list(fit.turns)}
    if fit.plate_model == "flat":
        return out
    out["bow_mm"] = [float(v) for v in fit.shape[:3]]
    out["bow_sigma_mm"] = [float(v) for v in np.sqrt(np.clip(np.diag(fit.shape_cov)[:3], 0, None))]
    if fit.plate_model == "bow+dots":
        u = fit.shape[3:]
        out["dot_sd_mm"] = float(fit.dot_sd_mm)
        out["dot_rms_mm"] = float(np.sqrt(u @ u / (len(u) + 4)))
    return out


def calibrate_intrinsics(images, plate: PlateSpec, camera_guess: CameraModel, names=None, *,
                         skip_unusable: bool = False, cross_check: bool = True, detections=None,
                         plate_model: str = "auto", skew: bool | str = "auto") -> IntrinsicsResult:
    """Joint calibration of f, kappa, cx, cy, aspect, skew and each view's ``C_H_W`` from the plate's pictures.

    ``images`` (H, W) (or ``detections``); ``camera_guess`` the start (its size checks the pictures); ``skip_unusable``:
    skip and list a picture without the plate. ``skew`` 'auto': kept only when pinned (``SKEW_SIGNIFICANCE``), else
    held at 0; True: fitted; False: held at the guess's. ``plate_model`` 'auto' or one of ``PLATE_MODELS``. Raises
    ``ImageError`` (no plate, wrong size), ``CalibrationError`` (under ``MIN_VIEWS`` views, no centre, no convergence).
    """
    if detections is None:
        dets, names, skipped = detect_views(images, plate, camera_guess, names, skip_unusable=skip_unusable)
    else:
        dets = list(detections)
        names = list(names) if names is not None else [f"view {i + 1}" for i in range(len(dets))]
        skipped = []
    if len(dets) < MIN_VIEWS:
        raise CalibrationError(
            f"intrinsics: {len(dets)} usable view(s) of the plate; at least {MIN_VIEWS} are needed (12 or more, "
            "tilted 20-40 deg in different directions, pin the centre and the aspect)"
        )
    _check_options(skew, plate_model)
    plate_why, held, bow_unconfirmed = f"{plate_model}: as asked", None, False
    if plate_model == "auto":
        plate_model, plate_why, chosen, bow_unconfirmed = _choose_plate_model(dets, names, plate, camera_guess)
        if chosen is not None and camera_guess.skew == 0.0:
            held = (list(names), chosen)  # the fit the skew decision would redo, if it comes to it on these views
    fit = fit_views(dets, plate, camera_guess, names, plate_model=plate_model, fit_skew=skew is not False,
                    start=held[1] if held else None)
    fit, dets, names = _drop_misfits(fit, dets, names, plate, plate_model, skew is not False, skipped)
    fit, skew_fit = _decide_skew(fit, skew, bow_unconfirmed, dets, names, plate, plate_model,
                                 held[1] if held and held[0] == names else None)
    skipped += [{"name": nm, "reason": why} for nm, why in fit.dropped]
    dets, names = _only(dets, names, {v.name for v in fit.views})
    sig = sigmas_of(fit.cov5)
    tilts = [v.tilt_deg for v in fit.views]
    if not (np.all(np.isfinite(fit.cov5)) and max(sig["cx"], sig["cy"]) < UNDETERMINED_CENTRE_PX):
        raise CalibrationError(
            f"intrinsics: the {len(dets)} views do not determine the principal point (sigma "
            f"{max(sig['cx'], sig['cy']):.3g} px): they see the plate {min(tilts):.0f}-{max(tilts):.0f} deg from "
            "square-on; take views tilted 20-40 deg in different directions"
        )
    return IntrinsicsResult(
        camera=fit.camera, covariance=fit.cov5, sigma=sig, rms_px=fit.rms_px, views=fit.views, skipped=skipped,
        projection_sigma_px=projection_sigma_px(fit.camera, fit.cov5), stop_rule=_stop_rule(fit, plate, sig),
        cross_check=halves_cross_check(fit) if cross_check else {"done": False, "why": "not asked for"},
        residual_sigma_px=float(np.sqrt(fit.s2)), plate_shape={**_plate_summary(fit), "why": plate_why},
        skew_fit=skew_fit,
    )


def _decide_skew(fit: JointFit, skew, bow_unconfirmed: bool, dets, names, plate, plate_model: str,
                 held: JointFit | None = None):
    """(fit, skew_fit): with ``skew`` 'auto', the skew kept only when pinned, else the fit redone with it held at 0
    (or ``held``, that fit already made on the same views); ``skew_fit`` says which and why."""
    skew_fit = {"fitted": skew is not False, "note": "skew fitted" if skew is True else "skew held at the guess's"}
    if skew is False:
        return fit, skew_fit
    val, sd = fit.camera.skew, float(np.sqrt(max(fit.cov5[5, 5], 0.0)))
    z = abs(val) / sd if sd > 0 and np.isfinite(sd) else 0.0
    skew_fit.update(value=float(val), sigma=sd, sigmas_from_zero=float(z), limit_sigmas=SKEW_SIGNIFICANCE)
    why = None
    if skew == "auto" and bow_unconfirmed:
        why = (f"it measures {val:.1e} +- {sd:.1e}, but the plate's bow, which the views measure and are too "
               "few to confirm, is left out of the flat plate, and a skew would take it up")
    elif skew == "auto" and not z >= SKEW_SIGNIFICANCE:
        why = f"the views measure it as {val:.1e} +- {sd:.1e} ({z:.1f} sigmas from 0, under {SKEW_SIGNIFICANCE:g})"
    elif skew == "auto":
        sd_jk = _jackknife_sigma(fit, 5)
        z_jk = abs(val) / sd_jk if sd_jk and np.isfinite(sd_jk) else 0.0
        skew_fit.update(jackknife_sigma=sd_jk, jackknife_sigmas_from_zero=float(z_jk))
        if sd_jk is None:
            why = (f"it measures {val:.1e} +- {sd:.1e}, but {len(fit.views)} views are too few to check it "
                   f"with views left out (at least {MIN_VIEWS + 1})")
        elif not z_jk >= SKEW_SIGNIFICANCE:
            why = (f"it measures {val:.1e} +- {sd:.1e}, but leaving views out moves it by {sd_jk:.1e} "
                   f"({z_jk:.1f} of those from 0): it stands for something the views do not share, not "
                   "for the grabber's shear")
        else:
            skew_fit["note"] = (f"skew fitted: {val:.2e} +- {sd:.1e}, {z:.0f} sigmas from 0 ({z_jk:.0f} by "
                                "the views left out in turn)")
    if why is not None:
        skew_fit.update(fitted=False, note=f"skew not fitted: {why}; it is held at 0 (the spec's camera model)")
        fit = held or fit_views(dets, plate, fit.camera.with_(skew=0.0), names, plate_model=plate_model,
                                fit_skew=False, start=fit)
    return fit, skew_fit


def _only(dets, names, kept: set):
    """(detections, names) of the views named in ``kept``, in their order."""
    keep = [k for k in range(len(dets)) if names[k] in kept]
    return [dets[k] for k in keep], [names[k] for k in keep]


def _check_options(skew, plate_model: str) -> None:
    """``calibrate_intrinsics``'s ``skew`` and ``plate_model``, or ``CalibrationError`` naming the one at fault."""
    if skew not in (True, False, "auto"):
        raise CalibrationError(f"intrinsics: skew={skew!r}: expected 'auto', True or False")
    if plate_model != "auto" and plate_model not in PLATE_MODELS:
        raise CalibrationError(f"intrinsics: plate model {plate_model!r}: expected 'auto' or one of "
                               f"{', '.join(PLATE_MODELS)}")


def _drop_misfits(fit: JointFit, dets, names, plate: PlateSpec, plate_model: str, fit_skew: bool, skipped: list):
    """(fit, detections, names) without the views over ``VIEW_MAX_RMS_PX`` (listed in ``skipped``), refitted."""
    bad = {v.name: v.rms_px for v in fit.views if v.rms_px > VIEW_MAX_RMS_PX}
    if not bad or len(fit.views) - len(bad) < MIN_VIEWS:
        return fit, dets, names
    for nm, rms in bad.items():
        skipped.append({"name": nm, "reason": f"does not fit the other views (residual rms "
                                              f"{rms:.2f} px > {VIEW_MAX_RMS_PX} px)"})
    dets, names = _only(dets, names, set(names) - set(bad))
    return fit_views(dets, plate, fit.camera, names, plate_model=plate_model, fit_skew=fit_skew, start=fit), dets, names


def _stop_rule(fit: JointFit, plate: PlateSpec, sig: dict) -> dict:
    """Whether the views pin the centre and the aspect, the sigmas against the limits and, if not, the advice."""
    met = stop_met(sig, fit.camera.aspect)
    stop = {"met": met, "sigma_centre_px": max(sig["cx"], sig["cy"]),
            "sigma_aspect_pct": 100 * sig["aspect"] / fit.camera.aspect, "limit_centre_px": STOP_CENTRE_PX,
            "limit_aspect_pct": 100 * STOP_ASPECT_REL}
    if met:
        return stop
    adv = more_views_advice(fit, plate)
    stop["more_views"] = adv
    best = [(n, k) for k, n in adv["views_needed"].items() if n is not None]
    if best:
        n, k = min(best)
        stop["advice"] = (f"{n} more view(s) {k} (plate about {adv['distance_mm']:.0f} mm away, tilt axes turning "
                          f"by 90 deg from view to view) would pin the centre to < {STOP_CENTRE_PX} px and the "
                          f"aspect to < {100 * STOP_ASPECT_REL:g} %")
    else:
        stop["advice"] = f"more than {MAX_MORE_VIEWS} further views of any kind would be needed"
    return stop


def _jackknife_sigma(fit: JointFit, i: int) -> float | None:
    """The jackknife sigma of the fit's shared parameter ``i`` (intrinsics, then shape), views left out to first
    order; None when too few views or the others do not determine the camera without one."""
    V = len(fit.views)
    if V - 1 < MIN_VIEWS:
        return None
    try:
        v = leave_views_out(fit)[0][:, i]
    except CalibrationError:
        return None
    return float(np.sqrt((V - 1) / V * np.sum((v - v.mean()) ** 2)))


def _choose_plate_model(dets, names, plate, camera_guess: CameraModel):
    """(model, why, its fit with the skew held or None, bow_unconfirmed): each richer model only when it predicts the
    views left out better; ``bow_unconfirmed``: a bow measured, too few views to confirm it (a skew takes it up)."""
    try:
        fits = {"flat": fit_views(dets, plate, camera_guess, names, plate_model="flat", fit_skew=False)}
    except CalibrationError as e:
        return "flat", f"flat: the flat plate's fit failed ({e})", None, False
    chosen, notes, unconfirmable = "flat", [], False
    for simple, rich in zip(PLATE_STEPS, PLATE_STEPS[1:]):
        try:
            f = fit_views(dets, plate, fits[simple].camera, names, plate_model=rich, fit_skew=False, start=fits[simple])
        except CalibrationError as e:
            notes.append(f"the {rich} plate's fit failed ({e})")
            break
        if f.plate_model != rich:
            notes.append(f"the {rich} plate is not fitted: the printed dot pattern is not recognised in most views")
            break
        if rich == "bow":
            chi2 = wald_chi2(f.shape[:3], f.shape_cov[:3, :3])
            measured = chi2_3_sf(chi2) < PLATE_TEST_LEVEL
            notes.append(f"the views {'measure' if measured else 'measure no'} bow (chi-square {chi2:.3g}, 3 dof)")
        t = heldout_test(fits[simple], f)
        if rich == "bow":  # a bow the views measure, where too few views could ever confirm it
            unconfirmable = measured and not sign_test_p(t["views"], 0) < PLATE_TEST_LEVEL
        left = (f" ({len(f.dropped)} view(s) it could not tie to the printed grid left out: "
                f"{', '.join(nm for nm, _ in f.dropped)})") if f.dropped else ""
        verdict = "predicts" if t["p"] < PLATE_TEST_LEVEL else "does not predict"
        notes.append(f"{rich} {verdict} the views left out in turn better than {simple} ({t['better']} of "
                     f"{t['views']} views better, sign test p = {t['p']:.2g}, level {PLATE_TEST_LEVEL:g}; held-out rms "
                     f"{t['rms_rich_px']:.3f} vs {t['rms_simple_px']:.3f} px){left}")
        if not t["p"] < PLATE_TEST_LEVEL:
            break
        fits[rich], chosen = f, rich
    if unconfirmable and chosen == "flat":
        notes.append(f"{t['views']} views are too few to confirm it (all better would be p = "
                     f"{sign_test_p(t['views'], 0):.2g})")
    return chosen, f"{chosen}: " + "; ".join(notes), fits[chosen], unconfirmable and chosen == "flat"
