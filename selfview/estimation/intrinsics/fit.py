"""The joint fit of several views' disc centres (bias-corrected, with the plate's shape) and its uncertainty."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import cv2
import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import PlateSpec
from selfview.measurement.discs import DiscDetections
from selfview.errors import CalibrationError, ConfigError, ImageError
from selfview.maths.geometry import make_H
from selfview.estimation.intrinsics.model import (STEP, JointProblem, central_differences, intrinsics_vector,
                                                  project_points, with_intrinsics)
from selfview.estimation.intrinsics.plate import (PLATE_DOT_PRIOR_MM, PLATE_DOT_SD_RANGE_MM, PLATE_MODELS, PlateShape,
                                                  align_views)
from selfview.maths.lm import covariance, levenberg_marquardt
from selfview.measurement.plates import detect_plate, plate_image_bias


#: The intrinsics in the order of the covariance: the skew last, absent when it is not fitted.
INTRINSIC_NAMES = ("f", "kappa", "cx", "cy", "aspect", "skew")
#: Fewest usable views a joint calibration accepts (and each half of the cross-check).
MIN_VIEWS = 4
MIN_VIEWS_HALF = 3

#: A disc centre this many residual RMS (and at least ``OUTLIER_MIN_PX``) from the model is dropped.
OUTLIER_RMS = 4.0
OUTLIER_MIN_PX = 0.5
#: A view whose residual RMS exceeds this [px] does not belong (another plate, moved camera, blur): dropped.
VIEW_MAX_RMS_PX = 1.5
#: Bias-correction rounds after the first fit: a second moved f, cx, cy by under 0.004 sigma on every real set.
BIAS_ROUNDS = 1
#: Further refits, at most, until the noise that weighs the plate's prior settles (within 20 %).
NOISE_ROUNDS = 4
#: The joint LM's relative cost decrease to stop: a step of e sigmas lowers it by about e^2 / (m - n), m - n up to
#: 10^4 here, so it stops within 1e-3 sigma of the minimum.
FTOL = 1e-10
#: Plate normals all within this [deg] of their mean: parallel planes cannot pin the principal point (Zhang).
PARALLEL_DEG = 5.0
#: Above this sigma of the centre [px] the views do not determine it at all.
UNDETERMINED_CENTRE_PX = 5.0


@dataclass
class ViewFit:
    """One view in the joint fit: ``name``; ``C_H_W`` (4, 4); ``discs`` used; ``rms_px`` residual; ``tilt_deg`` plate
    normal to optical axis; ``distance_mm`` to the plate's origin; ``dropped`` outlying disc centres."""

    name: str
    C_H_W: np.ndarray
    discs: int
    rms_px: float
    tilt_deg: float
    distance_mm: float
    dropped: int = 0

    def to_dict(self) -> dict:
        return {"name": self.name, "discs": self.discs, "rms_px": float(self.rms_px), "tilt_deg": float(self.tilt_deg),
                "distance_mm": float(self.distance_mm), "dropped": self.dropped,
                "C_H_W": np.asarray(self.C_H_W).tolist()}


@dataclass
class JointFit:
    """A joint fit: ``camera``, Jacobian ``jac`` and residual variance ``s2`` at its solution; its covariance
    (``cov_full``; ``cov5`` of INTRINSIC_NAMES[:ni]; ``shape_cov``) computed when first asked for."""

    camera: CameraModel
    ni: int
    jac: np.ndarray
    s2: float
    rms_px: float
    views: list
    uv_used: list
    plate_model: str = "flat"
    shape: np.ndarray = field(default_factory=lambda: np.zeros(0))
    prior_noise_px: float = 0.0
    dot_sd_mm: float = PLATE_DOT_PRIOR_MM
    turns: list = field(default_factory=list)
    dropped: list = field(default_factory=list)  # [(view name, why)] left out of the fit
    residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))  # at the solution, rows as ``jac``'s
    # the centroids bias-corrected by this fit (``_bias_corrected``), once for every fit started from it
    bias_memo: dict = field(default_factory=dict, repr=False, compare=False)

    @cached_property
    def cov_full(self) -> np.ndarray:
        return covariance(self.jac, self.s2, normal=True)

    @cached_property
    def reduced(self) -> "ReducedSystem":
        """Its normal equations with each view's pose eliminated, for views left out to first order."""
        return ReducedSystem(self)

    @property
    def cov5(self) -> np.ndarray:
        return self.cov_full[: self.ni, : self.ni]

    @property
    def shape_cov(self) -> np.ndarray:
        ns, n = len(self.shape), len(self.cov_full)
        return self.cov_full[n - ns :, n - ns :] if ns else np.zeros((0, 0))


class ReducedSystem:
    """A fit's normal equations on its shared parameters (intrinsics, shape), each view's pose eliminated (Schur): per
    view its rows (``Jh``, ``rh``) and share (``Sk``, ``gk``); totals ``S``, ``g`` with the prior; scales ``sc``."""

    def __init__(self, fit: JointFit):
        J, r, ni, V = fit.jac, fit.residuals, fit.ni, len(fit.views)
        self.fit, self.n = fit, np.array([len(u) for u in fit.uv_used])
        off = np.r_[0, np.cumsum(2 * self.n)]
        shared = np.r_[0:ni, ni + 6 * V : J.shape[1]]
        sc = np.linalg.norm(J[:, shared], axis=0)
        self.sc = np.where(sc > 0, sc, 1.0)
        self.Jh, self.rh = [], []
        for k in range(V):
            rows = slice(off[k], off[k + 1])
            q, _ = np.linalg.qr(J[rows, ni + 6 * k : ni + 6 * k + 6])
            js, rk = J[rows][:, shared] / self.sc, r[rows]
            self.Jh.append(js - q @ (q.T @ js))
            self.rh.append(rk - q @ (q.T @ rk))
        self.jp, self.rp = J[off[-1] :][:, shared] / self.sc, r[off[-1] :]
        self.Sk = np.array([a.T @ a for a in self.Jh])
        self.gk = np.array([a.T @ b for a, b in zip(self.Jh, self.rh)])
        self.S, self.g = self.Sk.sum(0) + self.jp.T @ self.jp, self.gk.sum(0) + self.jp.T @ self.rp

    def without(self, drop) -> tuple[np.ndarray, np.ndarray]:
        """(scaled change of the shared parameters, the reduced matrix of the views left) with the views
        ``drop`` (indices) left out; ``CalibrationError`` when the views left do not determine them."""
        drop = list(drop)
        Sd = self.S - self.Sk[drop].sum(0)
        try:
            return np.linalg.solve(Sd, self.gk[drop].sum(0) - self.g), Sd
        except np.linalg.LinAlgError:
            names = ", ".join(repr(self.fit.views[k].name) for k in drop)
            raise CalibrationError(f"intrinsics: without view(s) {names} the other views do not determine the "
                                   "camera") from None

    def fit_without(self, drop) -> tuple[np.ndarray, np.ndarray, float]:
        """(shared parameters, covariance, residual variance) of the fit without views ``drop``, to first order."""
        d, Sd = self.without(drop)
        keep = [k for k in range(len(self.n)) if k not in set(drop)]
        e = [self.rh[k] + self.Jh[k] @ d for k in keep] + [self.rp + self.jp @ d]
        m = int(2 * self.n[keep].sum()) + len(self.rp)
        s2 = float(sum(v @ v for v in e)) / max(m - len(self.sc) - 6 * len(keep), 1)
        x = np.r_[intrinsics_vector(self.fit.camera, self.fit.ni), self.fit.shape] + d / self.sc
        try:
            cov = s2 * np.linalg.inv(Sd) / np.outer(self.sc, self.sc)
        except np.linalg.LinAlgError:
            cov = np.full((len(d), len(d)), np.inf)
        return x, cov, s2


def leave_views_out(fit: JointFit) -> tuple[np.ndarray, np.ndarray]:
    """Each view left out in turn, to first order: (``delta`` (V, P) change of the shared parameters, ``heldout`` (V,)
    mean square [px^2] of view k's residuals predicted by the others). ``CalibrationError`` when undetermined."""
    rs, V = fit.reduced, len(fit.views)
    delta, heldout = np.zeros((V, len(rs.sc))), np.zeros(V)
    for k in range(V):
        d, _ = rs.without([k])
        e = rs.rh[k] + rs.Jh[k] @ d
        delta[k], heldout[k] = d / rs.sc, float(e @ e) / rs.n[k]
    return delta, heldout


def view_tilt_distance(C_H_W) -> tuple[float, float]:
    """(tilt [deg] of the plate's normal from the optical axis, distance [mm] to W's origin) of a view."""
    H = np.asarray(C_H_W, float)
    return float(np.degrees(np.arccos(min(1.0, abs(H[2, 2]))))), float(np.linalg.norm(H[:3, 3]))


def initial_pose(p_W, uv, camera: CameraModel) -> np.ndarray:
    """A first ``C_H_W`` of one view: planar PnP (IPPE) on the undistorted pixels of ``camera``."""
    und = camera.undistorted_pixels(uv)
    K = np.array([[camera.f / camera.aspect, 0, camera.cx], [0, camera.f, camera.cy], [0, 0, 1.0]])
    ok, rv, tv = cv2.solvePnP(p_W.astype(np.float64), und.astype(np.float64), K, None, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        raise CalibrationError("intrinsics: no first pose for a view (planar PnP failed)")
    H = make_H(cv2.Rodrigues(rv)[0], tv.ravel())
    if H[2, 3] <= 0:
        raise CalibrationError("intrinsics: a view's plate lies behind the camera")
    return H


def _solve(p_W: list, uv: list, camera0: CameraModel, poses0: list, names: list, *, rc: list | None = None,
           plate: PlateSpec | None = None, plate_model: str = "flat", shape0=None, noise_px: float = 0.05,
           dot_sd_mm: float = PLATE_DOT_PRIOR_MM, fit_skew: bool = True) -> JointFit:
    """Joint LM from ``camera0``, ``poses0``, ``shape0``, outlying discs dropped once. ``plate_model`` needs ``rc`` and
    ``plate``; ``noise_px`` weighs the shape's prior against the pixels; ``fit_skew`` else held at ``camera0``'s."""
    ni = 6 if fit_skew else 5
    shape = None
    if plate_model != "flat":
        if rc is None or plate is None:
            raise CalibrationError("intrinsics: fitting the plate's shape needs the discs' grid indices and the plate")
        shape = PlateShape(plate, plate_model, float(noise_px), float(dot_sd_mm))
    ns = shape.n if shape else 0
    y0 = np.zeros(ns) if shape0 is None or len(shape0) != ns else np.asarray(shape0, float)
    keep = [np.ones(len(p), bool) for p in p_W]
    for attempt in range(2):
        P = [p[k] for p, k in zip(p_W, keep)]
        U = [u[k] for u, k in zip(uv, keep)]
        idx = [shape.index(r[k]) for r, k in zip(rc, keep)] if shape else None
        model = JointProblem(P, U, [H[:3, :3] for H in poses0], shape, idx, ni=ni, skew=camera0.skew)
        x0 = np.concatenate([intrinsics_vector(camera0, ni), *[np.r_[np.zeros(3), H[:3, 3]] for H in poses0], y0])
        res = levenberg_marquardt(model.residuals, x0, model.jacobian, normal=model.normal_matrix, ftol=FTOL)
        poses0 = [model.pose(res.x, k) for k in range(len(P))]
        y0 = res.x[len(res.x) - ns :] if ns else y0
        try:
            camera0 = with_intrinsics(camera0, res.x[:ni])
        except ConfigError as exc:  # a skew no grabber has: the views do not fit this camera model
            raise CalibrationError(f"intrinsics: the joint fit left the camera model ({exc})") from None
        dist = [np.hypot(*res.residuals[model.off[k] : model.off[k + 1]].reshape(2, -1)) for k in range(len(P))]
        rms = float(np.sqrt(np.mean(np.concatenate(dist) ** 2)))
        bad = [d > max(OUTLIER_RMS * rms, OUTLIER_MIN_PX) for d in dist]
        if attempt == 1 or not any(b.any() for b in bad):
            break
        for k, b in enumerate(bad):
            keep[k][np.flatnonzero(keep[k])[b]] = False
    if not (res.converged and res.x[0] > 0 and res.x[4] > 0):
        raise CalibrationError(f"intrinsics: the joint fit did not converge ({res.message})")
    m, n = res.jacobian.shape
    s2 = res.cost / max(m - n, 1)  # the prior rows count as observations of the shape's parameters
    views = [ViewFit(names[k], H, int(keep[k].sum()), float(np.sqrt(np.mean(dist[k] ** 2))),
                     *view_tilt_distance(H), int((~keep[k]).sum())) for k, H in enumerate(poses0)]
    return JointFit(camera0, ni, res.jacobian, float(s2), rms, views, U, plate_model, np.asarray(y0, float),
                    float(noise_px), float(dot_sd_mm), residuals=res.residuals)


def _bias_corrected(dets, camera, poses, plate, memo: dict | None = None) -> list:
    """Each view's centroids less their perspective and lens bias; ``memo`` (a fit's ``bias_memo``) keeps each by its
    exact inputs."""
    if memo is None:
        return [d.uv - plate_image_bias(plate, camera, H, d.p_W) for d, H in zip(dets, poses)]
    out = []
    for d, H in zip(dets, poses):
        key = (camera, plate.disc_diameter, plate.pattern, np.asarray(H, float).tobytes(), d.uv.tobytes(),
               d.p_W.tobytes())
        if key not in memo:
            memo[key] = d.uv - plate_image_bias(plate, camera, H, d.p_W)
        out.append(memo[key])
    return out


def _dot_sd(fit: JointFit) -> float:
    """The discs' error sd [mm] a 'bow+dots' fit's corrections say (within ``PLATE_DOT_SD_RANGE_MM``)."""
    if fit.plate_model != "bow+dots":
        return fit.dot_sd_mm
    u, cu = fit.shape[3:], fit.shape_cov[3:, 3:]
    sd = float(np.sqrt((u @ u + np.trace(cu)) / len(u))) if np.all(np.isfinite(cu)) else fit.dot_sd_mm
    return float(np.clip(sd, *PLATE_DOT_SD_RANGE_MM))


def _first_poses(dets, names, camera0: CameraModel, start: JointFit | None, fit_skew: bool):
    """(camera, poses, warm): ``start``'s when it fitted every view named (a turned view's pose by PnP), else
    ``camera0`` and planar PnP."""
    turned = {v.name for v, t in zip(start.views, start.turns) if t} if start is not None else set()
    known = {v.name: v.C_H_W for v in start.views if v.name not in turned} if start is not None else {}
    warm = bool(known) and all(nm in known or nm in turned for nm in names)
    if warm:
        camera0 = start.camera if fit_skew else start.camera.with_(skew=camera0.skew)
    poses = [known[nm] if nm in known else initial_pose(d.p_W, d.uv, camera0) for d, nm in zip(dets, names)]
    return camera0, poses, warm


def _check_directions(poses) -> None:
    """``CalibrationError`` when ``poses`` all see the plate from one direction (within ``PARALLEL_DEG``)."""
    normals = np.array([H[:3, 2] for H in poses])
    mean = normals.sum(0) / np.linalg.norm(normals.sum(0))
    spread = float(np.degrees(np.arccos(np.clip(normals @ mean, -1, 1))).max())
    if spread < PARALLEL_DEG:
        tilts = [view_tilt_distance(H)[0] for H in poses]
        raise CalibrationError(
            f"intrinsics: the {len(poses)} views do not determine the principal point: they all see the plate from "
            f"one direction (its normal within {spread:.1f} deg in every view, {min(tilts):.0f}-{max(tilts):.0f} deg "
            f"from square-on), as when the gripper only looks straight down; take views with the gripper tilted "
            "20-40 deg about different axes in the plate"
        )


def fit_views(dets: list[DiscDetections], plate: PlateSpec, camera0: CameraModel, names: list[str] | None = None,
              *, bias: bool = True, plate_model: str = "bow+dots", fit_skew: bool = True,
              start: JointFit | None = None) -> JointFit:
    """The joint fit of views' disc detections from ``camera0``: PnP poses, a fit, ``BIAS_ROUNDS`` of bias correction
    (``bias=False``: none), refits until the noise weighing the shape's prior settles (``NOISE_ROUNDS``). ``start``: a
    fit of these views to start warm from, its bias correction taken at once. ``CalibrationError`` for an unknown
    ``plate_model`` or under ``MIN_VIEWS_HALF`` views, ``ValueError`` for names not one per view."""
    if plate_model not in PLATE_MODELS:
        raise CalibrationError(f"intrinsics: plate model {plate_model!r}: expected one of {', '.join(PLATE_MODELS)}")
    if len(dets) < MIN_VIEWS_HALF:  # the fewest a half of the cross-check fits
        raise CalibrationError(f"intrinsics: {len(dets)} view(s) of the plate; a joint fit needs at least "
                               f"{MIN_VIEWS_HALF}")
    names = names or [f"view {i + 1}" for i in range(len(dets))]
    if len(names) != len(dets):
        raise ValueError(f"names: expected {len(dets)} names for {len(dets)} views, got {len(names)}")
    camera0, poses, warm = _first_poses(dets, names, camera0, start, fit_skew)
    _check_directions(poses)
    uv = _bias_corrected(dets, camera0, poses, plate, start.bias_memo) if warm and bias else [d.uv for d in dets]
    rounds = BIAS_ROUNDS if bias and not warm else 0
    turns, dropped = [0.0] * len(dets), []
    if plate_model != "flat":
        # a first camera on the plate as specified (or the start's), then the discs on one physical grid
        reuse = warm and [v.name for v in start.views] == list(names) and not any(start.turns)
        fit = start if reuse else _solve([d.p_W for d in dets], uv, camera0, poses, names, fit_skew=fit_skew)
        uv = _bias_corrected(dets, fit.camera, [v.C_H_W for v in fit.views], plate, fit.bias_memo)
        dets, turns = align_views(dets, uv, fit, plate)
        if plate_model == "bow+dots" and sum(t is not None for t in turns) < max(2, (len(dets) + 1) // 2):
            # dots not seen in most views: per-disc corrections on the pictures' own grids would take up a shear
            plate_model = "bow"
        unaligned = [k for k, t in enumerate(turns) if t is None]
        if plate_model == "bow+dots" and unaligned and len(dets) - len(unaligned) >= MIN_VIEWS:
            # an untied view's dot corrections go to the wrong discs: the centre off by pixels, its sigma small
            keep = [k for k in range(len(dets)) if k not in unaligned]
            dropped = [(names[k], "its discs could not be tied to the plate's grid (the printed dot pattern is "
                                  "not recognised in it), so the plate's per-disc corrections cannot apply")
                       for k in unaligned]
            dets, uv, names, turns = ([a[k] for k in keep] for a in (dets, uv, names, turns))
        poses = [initial_pose(d.p_W, u, fit.camera) for d, u in zip(dets, uv)]
        camera0 = fit.camera if fit_skew else fit.camera.with_(skew=camera0.skew)  # a held skew stays held
    same = warm and start.plate_model == plate_model and start.prior_noise_px > 0
    noise0 = {"noise_px": start.prior_noise_px, "dot_sd_mm": start.dot_sd_mm} if same else {}
    if warm and not same and start.s2 > 0:  # a simpler model's start: its residual sigma, the noise to settle
        noise0 = {"noise_px": float(np.sqrt(start.s2))}
    P = [d.p_W for d in dets]
    kw = {"rc": [d.rc for d in dets], "plate": plate, "plate_model": plate_model, "fit_skew": fit_skew}
    fit = _solve(P, uv, camera0, poses, names, **kw, **noise0)
    for rnd in range(rounds + NOISE_ROUNDS):
        noise, sd = float(np.sqrt(fit.s2)), _dot_sd(fit)
        if rnd < rounds:
            new = _bias_corrected(dets, fit.camera, [v.C_H_W for v in fit.views], plate)
            if all(np.array_equal(a, b) for a, b in zip(new, uv)):
                rounds = rnd  # no bias to correct (a board's corners): only the noise's rounds are left
            uv = new
        if rnd >= rounds and (plate_model == "flat" or (abs(noise / fit.prior_noise_px - 1.0) < 0.2
                                                        and abs(sd / fit.dot_sd_mm - 1.0) < 0.2)):
            break
        fit = _solve(P, uv, fit.camera, [v.C_H_W for v in fit.views], names, shape0=fit.shape, noise_px=noise,
                     dot_sd_mm=sd, **kw)
    fit.turns, fit.dropped = turns, dropped
    return fit


def detect_views(images, plate: PlateSpec, camera: CameraModel, names=None, *, skip_unusable: bool = False):
    """Disc detections of each picture. Returns (detections, names kept, skipped [{name, reason}]).

    A picture without the plate raises ``ImageError`` naming it, unless ``skip_unusable``."""
    names = list(names) if names is not None else [f"view {i + 1}" for i in range(len(images))]
    dets, kept, skipped = [], [], []
    for img, nm in zip(images, names):
        try:
            dets.append(detect_plate(img, plate, camera=camera))
            kept.append(nm)
        except ImageError as exc:
            if not skip_unusable:
                raise ImageError(f"{nm}: {exc}") from None
            skipped.append({"name": nm, "reason": str(exc)})
    return dets, kept, skipped


def guess_camera(dets: list[DiscDetections], width: int, height: int) -> CameraModel:
    """A starting camera for ``width`` x ``height`` px pictures: centre in the middle, aspect 1, kappa 0, f from the
    homographies (Zhang's constraints, least squares in 1/f^2). ``CalibrationError`` when f is undetermined."""
    cx, cy = (width - 1) / 2, (height - 1) / 2
    A, b = [], []
    for d in dets:
        H, _ = cv2.findHomography(d.p_W[:, :2], d.uv - [cx, cy])
        if H is None:
            continue
        h1, h2 = H[:, 0], H[:, 1]
        A += [h1[0] * h2[0] + h1[1] * h2[1], h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2]
        b += [-h1[2] * h2[2], -(h1[2] ** 2 - h2[2] ** 2)]
    A, b = np.asarray(A), np.asarray(b)
    w = float(A @ b / (A @ A)) if len(A) and A @ A > 0 else 0.0
    if not w > 0:
        raise CalibrationError("intrinsics: the views do not give a first focal length (all seen square-on?); "
                               "give a cell file with the camera's focal_guess (--cell)")
    return CameraModel(f=1 / np.sqrt(w), kappa=0.0, cx=cx, cy=cy, aspect=1.0, width=int(width), height=int(height))


def _pixel_jacobians(camera: CameraModel, uv, ni: int = 5) -> np.ndarray:
    """(N, 2, ni) derivative of where the rays of pixels ``uv`` (N, 2) land w.r.t. the intrinsics."""
    uv = np.atleast_2d(np.asarray(uv, float))
    xy = camera.undistort_pixels(uv) / camera.f
    p = np.column_stack([xy, np.ones(len(xy))])
    x = intrinsics_vector(camera, ni)
    steps = STEP[:ni] * np.r_[abs(x[0]), np.ones(ni - 1)]
    return central_differences(lambda xv: project_points(xv, np.eye(3), np.zeros(3), p, camera.skew), x, steps)


def projection_sigma_px(camera: CameraModel, cov5: np.ndarray) -> dict:
    """1-sigma [px] of the projection at the centre and the corners; ``cov5`` (n, n) of ``INTRINSIC_NAMES[:n]``."""
    W, H = camera.width, camera.height
    pts = {"centre": ((W - 1) / 2, (H - 1) / 2), "top_left": (0.0, 0.0), "top_right": (W - 1.0, 0.0),
           "bottom_left": (0.0, H - 1.0), "bottom_right": (W - 1.0, H - 1.0)}
    Js = _pixel_jacobians(camera, list(pts.values()), len(cov5))
    return {nm: float(np.sqrt(max(np.trace(J @ cov5 @ J.T), 0.0))) for nm, J in zip(pts, Js)}


def named(values) -> dict:
    """{name in ``INTRINSIC_NAMES``: float} of intrinsics ``values`` (5 or 6)."""
    return {nm: float(v) for nm, v in zip(INTRINSIC_NAMES, values)}


def sigmas_of(cov5) -> dict:
    return named(np.sqrt(np.clip(np.diag(cov5), 0, None)))
