"""The finger-measurement layer's entry points: the fingertip corners of a picture (``find_fingertips``) or of a
sequence (``SilhouetteTracker``) from a predicted pose, by the corner search (``fingertips``), the model-based
silhouette fit (``silhouette``) or both; every result is a ``fingertips.FingertipResult``."""

from __future__ import annotations

import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import POINT_NAMES, GripperSpec
from selfview.measurement.discs import as_gray
from selfview.errors import CalibrationError
from selfview.measurement.fingertips import FingertipResult, PredictedFingers, search_corners
from selfview.maths.geometry import transform_points
from selfview.measurement.silhouette import (MAX_LEARNT_RMS_PX, MAX_RMS_PX, MIN_GOOD_FRACTION, fit_silhouette,
                                             learn_appearance, rms_limit)

__all__ = ["find_fingertips", "missed_corners", "model_measurement", "measure_model", "fit_result",
           "SilhouetteTracker", "WIDE_ROUNDS"]

#: The corner search's range [px] around a silhouette fit's pose (``find_fingertips``, model 'auto').
REFINE_SEARCH_PX = 4.0
#: A searched corner this far [px] from where the other corners' pose puts it is not the fingers' (tolerances: ~1 px).
OFF_SHAPE_PX = 3.0


def find_fingertips(image, camera: CameraModel, C_H_G_pred, gripper: GripperSpec, gap_mm: float, *,
                    search_px: float = 60.0, points=range(6), model: bool | str = False,
                    appearance=None) -> FingertipResult:
    """Locate the fingertip corners ``points`` (indices into POINT_NAMES) within ``search_px`` [px] of their
    prediction from ``C_H_G_pred`` (4, 4) and jaw gap ``gap_mm`` [mm]; ``camera`` projects it and undistorts the
    edge points. Returns a ``FingertipResult`` in distorted px; points not found carry a reason and are NaN.
    ``model``: False, the corner search only; True, the model-based measurement (``measure_model``: the fitted
    silhouette's corners, ``quality``, ``lost`` and ``C_H_G``); 'auto', the corner search, and where it misses a
    corner in the picture (``missed_corners``: a tip beside a disc, a weak tip edge, a busy board) the model's
    corners if its fit holds and finds more (never mixed), else, if the fit found the fingers (``MIN_GOOD_FRACTION``)
    but is not believed, the search again within ``REFINE_SEARCH_PX`` of its pose. ``appearance``
    (``silhouette.Appearance``): the faces' grey levels, if known. Raises ``ImageError`` for a blank picture or one
    of the wrong size, ``CalibrationError`` if the prediction puts the fingertips behind the camera or is not
    finite, ``ValueError`` for a transform that is not (4, 4), a jaw gap that is not a positive number or another
    ``model``."""
    if not (model is False or model is True or model == "auto"):  # 0 and 1 compare equal to False and True
        raise ValueError(f"model: expected False (the corner search), True (the model) or 'auto', got {model!r}")
    pred = PredictedFingers(camera, C_H_G_pred, gripper, gap_mm)
    result = search_corners(image, pred, search_px, points)
    if model is not False:
        _drop_off_shape(pred, result)
    if model is False or (model == "auto" and not missed_corners(result)):
        return result
    fitted, fit = measure_model(image, pred, points, result, appearance)
    # with 'auto', the corners the search missed in the picture are named as those it left out, which keep their reason
    missed = {nm: f"not found there ({r})" for nm, r in missed_corners(result).items()} if model == "auto" else {}
    fitted.left_out.update({**missed, **result.left_out})
    if model is True or (fit.ok and fitted.found.sum() > result.found.sum()):
        return fitted
    if model == "auto" and fit.C_H_G is not None and fit.good_fraction >= MIN_GOOD_FRACTION:
        # its nominal boxes miss the real corners by their tolerances; a busy print outscores them over a wider range
        again = search_corners(image, PredictedFingers(pred.camera, fit.C_H_G, pred.gripper, pred.gap_mm),
                               min(float(search_px), REFINE_SEARCH_PX), points)
        _drop_off_shape(pred, again)
        again.left_out.update(result.left_out)
        if again.found.sum() > result.found.sum():
            return again
    return result


def missed_corners(result: FingertipResult) -> dict:
    """{name: why} of the requested corners a measurement left unfound, neither outside the picture nor hidden."""
    return {nm: r for nm, ok, r in zip(result.names, result.found, result.reasons)
            if not ok and not (r and (r.startswith(("outside", "occluded")) or r == "not requested"))}


def _drop_off_shape(pred: PredictedFingers, res: FingertipResult) -> None:
    """Mark not found in ``res``, worst first, one at a time, a corner over ``OFF_SHAPE_PX`` from where the pose of
    the other found corners (five or more) puts it: the search may take a print's edge beside a finger's for it."""
    p_G = pred.gripper.points_G(gap=pred.gap_mm)
    while res.found.sum() >= 5:
        k_all = np.flatnonzero(res.found)
        off = np.zeros(len(k_all))
        for i, k in enumerate(k_all):
            H = _pose_from_corners(pred, res, np.delete(k_all, i))
            if H is None:
                return
            off[i] = np.linalg.norm(pred.camera.project(transform_points(H, p_G[k:k + 1]))[0] - res.uv[k])
        worst = int(np.argmax(off))
        if off[worst] <= OFF_SHAPE_PX:
            return
        k = k_all[worst]
        res.found[k] = False
        res.reasons[k] = f"off the fingers' shape: {off[worst]:.1f} px from where the other corners put it"
        res.left_out[res.names[k]] = res.reasons[k]
        res.uv[k] = np.nan
        res.edge_rms_px[k] = np.nan


def _pose_from_corners(pred: PredictedFingers, res: FingertipResult, k=None):
    """C_H_G (4, 4) by NP-I from the prediction with corners ``k`` of ``res`` (default: found); None: < 3 or failed."""
    from selfview.estimation.online import iterative_update

    k = np.flatnonzero(res.found) if k is None else k
    if len(k) < 3:
        return None
    p_G = pred.gripper.points_G(gap=pred.gap_mm)[k]
    try:
        return iterative_update(pred.C_H_G, p_G, res.uv[k], pred.camera).C_H_G_orth
    except CalibrationError:
        return None


def fit_result(fit, points) -> FingertipResult:
    """The ``FingertipResult`` of a silhouette fit for the requested ``points``: the model's corners if the
    fit holds, else every point not found with the fit's reason (``lost``)."""
    want = {int(k) for k in points}
    if fit.ok:
        reasons = [None if fit.found[k] else (fit.reasons[k] or "not found") for k in range(6)]
        reasons = [r if k in want else "not requested" for k, r in enumerate(reasons)]
        found = fit.found & np.array([k in want for k in range(6)])
        uv = np.where(found[:, None], fit.uv, np.nan)
        return FingertipResult(uv=uv, found=found, reasons=reasons, edge_rms_px=np.where(found, fit.rms_px, np.nan),
                               names=POINT_NAMES, n_edge_points=np.where(found, fit.n_samples, 0),
                               quality=fit.quality(), C_H_G=fit.C_H_G)
    why = fit.reason or "the silhouette does not fit"
    reasons = [why if k in want else "not requested" for k in range(6)]
    return FingertipResult(uv=np.full((6, 2), np.nan), found=np.zeros(6, bool), reasons=reasons,
                           edge_rms_px=np.full(6, np.nan), names=POINT_NAMES, n_edge_points=np.zeros(6, int),
                           quality=fit.quality(), lost=why)


def model_measurement(image, camera, C_H_G_pred, gripper, gap_mm, points=range(6), searched=None, appearance=None,
                      starts=None, rounds=None):
    """``measure_model`` from the prediction's parts. Returns (FingertipResult, SilhouetteFit)."""
    return measure_model(image, PredictedFingers(camera, C_H_G_pred, gripper, gap_mm), points, searched,
                         appearance, starts, rounds)


def measure_model(image, pred: PredictedFingers, points=range(6), searched=None, appearance=None, starts=None,
                  rounds=None, max_rms_px: float = MAX_RMS_PX):
    """The model-based measurement: silhouette fits from ``starts`` (default the prediction), first from the pose of
    the corners ``searched`` found (three or more), lost over the residual ``max_rms_px``; the believed fit with the
    most good samples wins (the first over 0.8 stops). Returns (FingertipResult, SilhouetteFit)."""
    cands = list(starts) if starts is not None else [pred.C_H_G]
    if searched is not None:
        H = _pose_from_corners(pred, searched)
        if H is not None:
            cands.insert(0, H)
    if not cands:
        cands = [pred.C_H_G]
    cam, gripper, gap = pred.camera, pred.gripper, pred.gap_mm
    if appearance is None or not appearance.levels:
        # the faces' levels where the fingers most likely are: at the found corners' pose, else the first start
        appearance = learn_appearance(image, cam, cands[0], gripper, gap)
    best = None
    kw = {} if rounds is None else {"rounds": rounds}
    for H in cands:
        fit = fit_silhouette(image, cam, H, gripper, gap, appearance=appearance, points=points, max_rms_px=max_rms_px,
                             **kw)
        if best is None or (fit.ok, fit.good_fraction) > (best.ok, best.good_fraction):
            best = fit
        if fit.ok and fit.good_fraction > 0.8:
            break
    return fit_result(best, points), best


WIDE_ROUNDS = (60.0, 24.0, 10.0, 5.0, 3.0)  # a search's fit from a start that may be far off [px]


class SilhouetteTracker:
    """The fingertips of a sequence of pictures by the model-based measurement (``selfview.measurement.silhouette``).

    ``find(image, C_H_G_pred, gap_mm)`` returns a ``FingertipResult`` (``tracked`` when it followed the last frame);
    ``searches``, ``tracked_frames``, ``lost_frames`` count the kinds of frame; ``last_failure`` says why the last
    frame was searched (None: tracked); ``reset()`` forgets the last pose. A frame is fitted from the last pose with
    ``track_rounds`` [px] and the last grey levels, again within 3 px when the tips moved over ``refine_px`` [px]; a
    fit not believed makes it searched (full-range fits from the last pose and ``C_H_G_pred``, then the corner
    search's pose); where none holds, a missed frame (reason in ``result.lost``), never a pose. The residual limit
    is the gripper's: the first frame's fit from ``C_H_G_pred`` (up to ``MAX_LEARNT_RMS_PX``) gives ``rms_level_px``
    (unless given), later frames are lost over ``rms_limit(rms_level_px)``, over ``MAX_RMS_PX`` until then; ``reset()``
    keeps it. Raises ``TypeError`` for a camera that is not a ``CameraModel``, ``ValueError`` for bad ``points`` or
    ``track_rounds``."""

    def __init__(self, camera: CameraModel, gripper: GripperSpec, *, points=range(4), search_px: float = 60.0,
                 track_rounds=(8.0,), refine_px: float = 2.0, appearance=None, rms_level_px: float | None = None):
        if not isinstance(camera, CameraModel):
            raise TypeError(f"camera: expected a selfview.maths.camera.CameraModel, got {type(camera).__name__}")
        want = sorted({int(k) for k in points})
        if not want or any(k < 0 or k > 5 for k in want):
            raise ValueError(f"points: expected indices 0..5 into POINT_NAMES, got {list(points)}")
        rounds = tuple(float(r) for r in track_rounds)
        if not rounds or any(not (1.0 <= r <= 60.0) for r in rounds):
            raise ValueError(f"track_rounds: expected search ranges of 1..60 px, got {track_rounds!r}")
        self.camera = camera
        self.gripper = gripper
        self.points = tuple(want)
        self.search_px = float(search_px)
        self.track_rounds = rounds
        self.refine_px = float(refine_px)
        self.searches = self.tracked_frames = self.lost_frames = 0
        self.last_failure: str | None = None
        self.last_fit = None
        self._app0 = appearance
        rms_limit(rms_level_px)  # a level no right fit gives is named now
        self.rms_level_px = None if rms_level_px is None else float(rms_level_px)
        self._learn = rms_level_px is None
        self.reset()

    def reset(self) -> None:
        """Forget the last pose: the next frame is searched for."""
        self._H = None
        self._gap = None
        self._app = self._app0

    @property
    def primed(self) -> bool:
        return self._H is not None

    def find(self, image, C_H_G_pred, gap_mm: float) -> FingertipResult:
        pred = PredictedFingers(self.camera, C_H_G_pred, self.gripper, gap_mm)
        gap_mm = pred.gap_mm
        a = np.asarray(image)
        # a grabber's frame needs no other check per frame (float32 where the search needs it); else float32, checked
        grabbed = a.dtype == np.uint8 and a.shape == (int(self.camera.height), int(self.camera.width))
        img = a if grabbed else as_gray(image, self.camera)
        why = None
        if self._H is not None and self._gap is not None and abs(gap_mm - self._gap) > 1e-6:
            why = f"the jaw gap changed ({self._gap:.2f} -> {gap_mm:.2f} mm)"
            self.reset()
        limit = rms_limit(self.rms_level_px)
        if self._H is None and self._learn:
            # the first frame, where the calibration puts the fingers: the fit known good gives the level
            res, fit = measure_model(img, pred, self.points, appearance=self._app, rounds=self.track_rounds,
                                     max_rms_px=MAX_LEARNT_RMS_PX)
            if fit.ok:
                self._learn = False
                self.rms_level_px = float(fit.rms_px)
                self._take(fit, gap_mm)
                self.searches += 1
                self.last_failure = None
                return res
        if self._H is not None:
            fit = fit_silhouette(img, self.camera, self._H, self.gripper, gap_mm, appearance=self._app,
                                 rounds=self.track_rounds, points=self.points, frame=True, max_rms_px=limit)
            if fit.C_H_G is not None and self._moved_px(fit.C_H_G, gap_mm) > self.refine_px:
                # a larger step than usual: once more with a short range around the new pose
                again = fit_silhouette(img, self.camera, fit.C_H_G, self.gripper, gap_mm, appearance=fit.appearance,
                                       rounds=(min(self.track_rounds[-1], 3.0),), points=self.points, frame=True,
                                       max_rms_px=limit)
                fit = again if again.ok or not fit.ok else fit
            if fit.ok:
                self._take(fit, gap_mm)
                self.tracked_frames += 1
                self.last_failure = None
                res = fit_result(fit, self.points)
                res.tracked = True
                return res
            why = fit.reason
        self.last_failure = why
        img = img.astype(np.float32, copy=False)
        starts = ([self._H] if self._H is not None else []) + [pred.C_H_G]
        res, fit = measure_model(img, pred, self.points, appearance=self._app, starts=starts, max_rms_px=limit)
        if not fit.ok:
            # the corner search's pose (three corners or more), and fits reaching as far as it searches
            searched = search_corners(img, pred, self.search_px, range(6))
            res2, fit2 = measure_model(img, pred, self.points, searched=searched, appearance=self._app,
                                       starts=[], rounds=WIDE_ROUNDS, max_rms_px=limit)
            if fit2.ok:
                res, fit = res2, fit2
        self.searches += 1
        if fit.ok:
            self._take(fit, gap_mm)
        else:
            self.lost_frames += 1
        return res

    def _moved_px(self, H, gap_mm: float) -> float:
        """How far [px] the fingertip points moved in the picture from the last pose to ``H``."""
        p = self.gripper.points_G(gap=gap_mm)
        a = self.camera.project_undistorted(transform_points(self._H, p))
        b = self.camera.project_undistorted(transform_points(H, p))
        return float(np.max(np.linalg.norm(a - b, axis=1)))

    def _take(self, fit, gap_mm: float) -> None:
        self._H = fit.C_H_G.copy()
        self._gap = float(gap_mm)
        self._app = fit.appearance
        self.last_fit = fit
