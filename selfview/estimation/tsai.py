"""Tsai's coplanar camera calibration (the paper's reference [8]), stage by stage as Willson's v3.0b3 ``cal_main.c``.

From N >= 5 plate points ``p_W`` (z = 0, mm) and their pixels ``uv``, principal point and aspect known: f [px], kappa
[px^-2] and ``C_H_W`` (eq. 1-4 in ``selfview.maths.camera``'s units: ``X^ = aspect (u - cx)``, ``Y^ = v - cy``,
``X = X^ (1 + kappa r^2)``). Stages 1-4 are linear, then by mode 5a ``tsai``, 5b ``full*`` or 5c ``willson``."""

from __future__ import annotations

import re
from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from selfview.maths.camera import CameraModel, distort
from selfview.errors import CalibrationError, CalibrationFileError, ConfigError
from selfview.maths.geometry import R_from_rotvec, R_from_rpy, cross_rows, make_H, so3_left_jacobian, transform_points
from selfview.files.io_safe import parse_number, read_bounded
from selfview.maths.lm import covariance, levenberg_marquardt

__all__ = ["FREE_CENTRE_MODES", "MODES", "TsaiResult", "calibrate_coplanar", "load_willson_points", "parse_willson_log",
           "residual_stats"]

MODES = ("tsai", "full", "full+centre", "willson")
#: The modes that calibrate the principal point (the given one only starts them).
FREE_CENTRE_MODES = ("full+centre", "willson")
#: A plate tilted further than this from square-on (its normal against the optical axis) is refused as edge-on.
EDGE_ON_LIMIT_DEG = 85.0
#: Largest condition number of the column-equilibrated linear f/Tz system (above: all points at one depth, square-on).
F_TZ_COND_LIMIT = 1.0e6
#: Largest relative standard error of f after stage 5a (above: f and Tz inseparable); Willson's 6.6 m data give 2.8 %.
F_REL_SD_LIMIT = 0.05
#: The same on the final refinement: one view of a plane hardly separates the principal point from f and the tilt.
FULL_REL_SD_LIMIT = 0.10
#: Smallest image noise [px] assumed in judging separation, so that exact data of a square-on plate do not pass.
SEPARABILITY_NOISE_PX = 0.02
#: Willson's lmdif tolerances (cal_main.h): relative cost reduction and relative step.
WILLSON_FTOL, WILLSON_XTOL = 1.0e-5, 1.0e-7
#: Willson's lmdif budget of residual evaluations per parameter (cal_main.h: MAXFEV = 1000 n).
WILLSON_MAXFEV_PER_PARAM = 1000
#: Tolerances of the f, Tz, kappa stage when it only starts a full refinement.
INIT_FTOL, INIT_XTOL = 1.0e-8, 1.0e-8
#: Tolerances of the full refinements, tight enough to reach the minimum to machine precision.
FULL_FTOL, FULL_XTOL = 1.0e-12, 1.0e-10
#: Residual evaluations the full refinement may spend (10 to 30 when the data determine it).
FULL_MAX_NFEV = 400
#: Smallest ratio of the second to the first singular value of the centred points (collinearity).
COLLINEAR_LIMIT = 1.0e-3


@dataclass(frozen=True)
class TsaiResult:
    """Result of ``calibrate_coplanar``: ``camera`` (f [px], kappa [px^-2], principal point, aspect, size); ``C_H_W``
    (4, 4) plate -> camera [mm]; ``residuals_px`` (N, 2) observed minus model, distorted px; ``rms_px``, ``mean_px``,
    ``max_px``, ``sse_px2`` of the per-point distances; ``mode``; ``iterations`` of Levenberg-Marquardt, all stages."""

    camera: CameraModel
    C_H_W: np.ndarray
    residuals_px: np.ndarray
    rms_px: float
    mean_px: float
    max_px: float
    sse_px2: float
    mode: str
    iterations: int

    @property
    def errors_px(self) -> np.ndarray:
        """(N,) distance between each observed and modelled point, pixels."""
        return np.hypot(self.residuals_px[:, 0], self.residuals_px[:, 1])

    def to_dict(self) -> dict:
        """Plain numbers and lists for JSON and YAML."""
        return {**self.camera.to_dict(), "C_H_W": np.asarray(self.C_H_W, dtype=float).tolist(),
                "rms_px": float(self.rms_px), "mean_px": float(self.mean_px), "max_px": float(self.max_px),
                "sse_px2": float(self.sse_px2), "mode": self.mode, "n_points": int(len(self.residuals_px)),
                "iterations": int(self.iterations)}


def residual_stats(residuals) -> tuple[float, float, float, float]:
    """(rms, mean, max, sse) of the per-point distances of residuals (N, 2) [px, px^2]."""
    d2 = np.sum(np.asarray(residuals, dtype=float) ** 2, axis=1)
    d = np.sqrt(d2)
    return float(np.sqrt(d2.mean())), float(d.mean()), float(d.max()), float(d2.sum())


def _check_inputs(p_W, uv, cx, cy, aspect, mode, width, height, f_guess=None):
    try:
        p, q = np.asarray(p_W, dtype=float), np.asarray(uv, dtype=float)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"coplanar calibration: points are not numbers ({exc})") from exc
    for name, a, k in (("p_W", p, 3), ("uv", q, 2)):
        if a.ndim != 2 or a.shape[1] != k:
            raise CalibrationError(f"coplanar calibration: {name} must have shape (N, {k}), got {a.shape}")
    if len(p) != len(q):
        raise CalibrationError(f"coplanar calibration: {len(p)} plate points but {len(q)} image points")
    for name, a in (("p_W", p), ("uv", q)):
        bad = ~np.all(np.isfinite(a), axis=1)
        if bad.any():
            raise CalibrationError(f"coplanar calibration: {name} has non-finite values (NaN or inf) at row(s) "
                                   f"{np.flatnonzero(bad)[:10].tolist()}")
    if len(p) < 5:
        raise CalibrationError(f"coplanar calibration needs at least 5 points, got {len(p)}")
    for name, v in (("cx", cx), ("cy", cy), ("aspect", aspect)):
        if not np.isfinite(v):
            raise ConfigError(f"coplanar calibration: {name} must be a finite number, got {v!r}")
    if aspect <= 0:
        raise ConfigError(f"coplanar calibration: aspect must be positive, got {aspect!r}")
    if mode not in MODES:
        raise ConfigError(f"coplanar calibration: mode must be one of {', '.join(MODES)}; got {mode!r}")
    if int(width) <= 0 or int(height) <= 0:
        raise ConfigError(f"coplanar calibration: picture size must be positive, got {width}x{height}")
    if f_guess is not None and not (np.isfinite(f_guess) and f_guess > 0):
        raise ConfigError(f"coplanar calibration: f_guess must be a positive focal length in px, got {f_guess!r}")
    i = int(np.argmax(np.abs(p[:, 2])))
    if abs(p[i, 2]) > 1e-6 * max(float(np.ptp(p[:, :2], axis=0).max()), 1.0):
        raise CalibrationError(f"non-coplanar points in a coplanar call: z must be 0 on the plate, point {i} has "
                               f"z = {p[i, 2]:.6g} mm")
    _check_spread(p[:, :2], "plate points", "collinear plate points: they do not span the plate's plane")
    return p, q


def _check_spread(xy: np.ndarray, what: str, cause: str) -> None:
    s = np.linalg.svd(xy - xy.mean(axis=0), compute_uv=False)
    if s[0] == 0 or s[1] < COLLINEAR_LIMIT * s[0]:
        ratio = 0.0 if s[0] == 0 else s[1] / s[0]
        raise CalibrationError(f"{cause} (spread ratio of the {what} {ratio:.2e} < {COLLINEAR_LIMIT:.0e})")


def _sensor(uv, cx, cy, aspect, kappa):
    """Distorted (X^, Y^) and undistorted (X, Y) sensor coordinates [px] of pixels ``uv`` (N, 2) (eq. 4)."""
    Xh = aspect * (uv[:, 0] - cx)
    Yh = uv[:, 1] - cy
    a = 1.0 + kappa * (Xh * Xh + Yh * Yh)
    return Xh, Yh, Xh * a, Yh * a


def _rpy_paul(r: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw [rad] of a nearly orthonormal R = Rz Ry Rx by Paul's formulas from rows 1-2 and r7 (Willson's
    reading: an unnormalised third row does not enter)."""
    r1, r2, r3, r4, r5, r6, r7 = r.ravel()[:7]
    rz = np.arctan2(r4, r1)
    sg, cg = np.sin(rz), np.cos(rz)
    ry = np.arctan2(-r7, r1 * cg + r4 * sg)
    rx = np.arctan2(r3 * sg - r6 * cg, r5 * cg - r2 * sg)
    return float(rx), float(ry), float(rz)


def _radial_alignment(xw, yw, Xd, Yd):
    """Stages 1-3: (Tx, Ty, r (3, 3) not quite orthonormal, as Willson's). 1: ``U = (r1, r2, Tx, r4, r5) / Ty`` from
    ``Y^ (r1 x + r2 y + Tx) = X^ (r4 x + r5 y + Ty)``; 2: ``|Ty|`` from U, its sign from the point farthest from the
    image centre; 3: r3, r6 from unit rows, r6's sign from ``r1 r4 + r2 r5``."""
    A = np.column_stack([Yd * xw, Yd * yw, Yd, -Xd * xw, -Xd * yw])
    U, *_ = np.linalg.lstsq(A, Xd, rcond=None)
    r1p, r2p, _, r4p, r5p = U
    tiny = 1e-12 * max(np.abs(U[[0, 1, 3, 4]]).max(), 1e-300)
    det = r1p * r5p - r4p * r2p
    # A vanishing row or column of the 2x2 block makes the general formula 0/0 (Tsai 1987, eq. 10).
    for a, b, c, d in ((r1p, r2p, r4p, r5p), (r4p, r5p, r1p, r2p), (r1p, r4p, r2p, r5p), (r2p, r5p, r1p, r4p)):
        if abs(a) < tiny and abs(b) < tiny:
            ty2 = 1.0 / (c**2 + d**2)
            break
    else:
        sr = r1p**2 + r2p**2 + r4p**2 + r5p**2
        ty2 = (sr - np.sqrt(max(sr * sr - 4.0 * det * det, 0.0))) / (2.0 * det * det)
    if not np.isfinite(ty2) or ty2 <= 0:
        raise CalibrationError("radial alignment stage failed: no real Ty (points degenerate or mislabelled)")
    k = int(np.argmax(Xd * Xd + Yd * Yd))
    ty = np.sqrt(ty2)
    x = (U[0] * xw[k] + U[1] * yw[k] + U[2]) * ty
    y = (U[3] * xw[k] + U[4] * yw[k] + 1.0) * ty
    if np.signbit(x) != np.signbit(Xd[k]) or np.signbit(y) != np.signbit(Yd[k]):
        ty = -ty
    tx = U[2] * ty
    r1, r2, r4, r5 = U[0] * ty, U[1] * ty, U[3] * ty, U[4] * ty
    r3 = np.sqrt(max(1.0 - r1 * r1 - r2 * r2, 0.0))
    r6 = np.sqrt(max(1.0 - r4 * r4 - r5 * r5, 0.0))
    if not np.signbit(r1 * r4 + r2 * r5):
        r6 = -r6
    row3 = [r2 * r6 - r3 * r5, r3 * r4 - r1 * r6, r1 * r5 - r2 * r4]  # row 1 x row 2
    return float(tx), float(ty), np.array([[r1, r2, r3], [r4, r5, r6], row3])


def _approximate_f_Tz(xw, yw, Yd, r, ty, with_cond=True):
    """Stage 4: (f, Tz, condition of the column-equilibrated system or NaN) by least squares from
    ``f y - Y^ Tz = Y^ w``, kappa = 0; f < 0 asks for the other solution for R."""
    yc = r[1, 0] * xw + r[1, 1] * yw + ty
    w = r[2, 0] * xw + r[2, 1] * yw
    A = np.column_stack([yc, -Yd])
    cond = np.nan
    if with_cond:
        norms = np.linalg.norm(A, axis=0)
        if np.any(norms == 0):
            return np.nan, np.nan, np.inf
        s = np.linalg.svd(A / norms, compute_uv=False)
        cond = float(s[0] / s[1]) if s[1] > 0 else np.inf
    sol, *_ = np.linalg.lstsq(A, w * Yd, rcond=None)
    return float(sol[0]), float(sol[1]), cond


def _linear_pose(xw, yw, Xd, Yd, with_cond=True):
    """Stages 1-4 in the given plate frame: (Tx, Ty, r, f, Tz, cond)."""
    tx, ty, r = _radial_alignment(xw, yw, Xd, Yd)
    f, tz, cond = _approximate_f_Tz(xw, yw, Yd, r, ty, with_cond)
    if not f >= 0:  # also NaN: the other solution for R (Willson), r3, r6, r7, r8 negated
        r = r * np.array([[1.0, 1.0, -1.0], [1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])
        f, tz, cond = _approximate_f_Tz(xw, yw, Yd, r, ty, with_cond)
        if not f >= 0:
            raise CalibrationError("no pose with a positive focal length fits: the plate coordinates may be "
                                   "left-handed or the correspondences mislabelled")
    return tx, ty, r, f, tz, cond


def _linear_stages(xy, Xd, Yd):
    """Stages 1-4, in a plate frame moved off the camera's y-z plane if need be (Willson's FAQ 3.3): (its origin (2,) in
    W, xy in it, Tx, Ty, r, f, Tz, R_lin, tilt [deg]); ``CalibrationError`` for a plate edge-on or a singular f/Tz."""
    origin = np.zeros(2)
    try:
        tx, ty, r, f_lin, tz, cond = _linear_pose(xy[:, 0], xy[:, 1], Xd, Yd)
        moved = abs(ty) < 0.25 * np.abs(r[1, 0] * xy[:, 0] + r[1, 1] * xy[:, 1] + ty).max()
    except CalibrationError:
        moved = True
    if moved:
        origin = xy[int(np.argmax(np.abs(Yd)))].copy()
        xy = xy - origin
        tx, ty, r, f_lin, tz, cond = _linear_pose(xy[:, 0], xy[:, 1], Xd, Yd)
    R_lin = R_from_rpy(*_rpy_paul(r))
    tilt = float(np.degrees(np.arccos(min(abs(R_lin[2, 2]), 1.0))))
    if tilt > EDGE_ON_LIMIT_DEG:
        raise CalibrationError(f"plate seen nearly edge-on: tilted {tilt:.1f} deg from square-on "
                               f"(limit {EDGE_ON_LIMIT_DEG:g} deg)")
    if not cond <= F_TZ_COND_LIMIT:
        raise _inseparable(tilt, f"the linear f/Tz system is singular, condition number {cond:.3g}")
    return origin, xy, tx, ty, r, f_lin, tz, R_lin, tilt


class _FTzKappa:
    """Stage 5a's model: undistorted sensor residuals [px] of (``Xd``, ``Yd``) in (f, Tz, kappa), the pose of stages 1-3
    (camera x, y ``xc``, ``yc`` and depth - Tz ``w`` of each point)."""

    def __init__(self, xc, yc, w, Xd, Yd):
        self.xy = np.concatenate([xc, yc])
        self.w2 = np.concatenate([w, w])
        self.XYd = np.concatenate([Xd, Yd])
        self.r2 = np.concatenate([Xd * Xd + Yd * Yd] * 2)

    def residuals(self, x):
        """(2N,) model minus observation, x of all points, then y."""
        return x[0] * self.xy / (self.w2 + x[1]) - self.XYd * (1.0 + x[2] * self.r2)

    def jacobian(self, x):
        zc = self.w2 + x[1]
        return np.column_stack([self.xy / zc, -x[0] * self.xy / zc**2, -self.XYd * self.r2])

    def distances(self, x):
        """(N,) per-point distances: Willson's residuals."""
        e = self.residuals(x).reshape(2, -1)
        return np.hypot(e[0], e[1])

    def f_relative_sd(self, x) -> float:
        """Relative standard error of f at ``x`` (noise >= ``SEPARABILITY_NOISE_PX``): large when f and Tz trade."""
        e = self.residuals(x)
        sigma2 = max(float(e @ e) / max(len(e) - 3, 1), SEPARABILITY_NOISE_PX**2)
        return _relative_sd(covariance(self.jacobian(x), sigma2), x, 0)


def _relative_sd(C: np.ndarray, x, i: int) -> float:
    """Standard error of x[i] relative to it, from covariance C (inf if undetermined)."""
    with np.errstate(all="ignore"):
        v = float(np.sqrt(C[i, i]) / abs(x[i]))
    return v if np.isfinite(v) else np.inf


def _refine_tsai(model: _FTzKappa, f, tz, kappa, willson: bool):
    """Stage 5a: f, Tz, kappa minimising the undistorted sensor-plane error. ``willson``: as his
    ``cc_compute_exact_f_and_Tz`` (per-point distances, forward differences, his tolerances, kappa step 1 / r_max^2)."""
    if willson:
        return levenberg_marquardt(model.distances, [f, tz, kappa], "forward", ftol=WILLSON_FTOL, xtol=WILLSON_XTOL,
                                   scale=[1.0, 1.0, 1.0 / model.r2.max()])
    return levenberg_marquardt(model.residuals, [f, tz, kappa], model.jacobian, ftol=INIT_FTOL, xtol=INIT_XTOL)


class _FullModel:
    """Stage 5b's model: x = (omega (3), t (3) [mm], f [px], kappa [px^-2] [, cx, cy]), R = exp(omega) R0; residuals in
    distorted pixels, model minus observation (u of all points, then v), and their analytic Jacobian."""

    def __init__(self, p_W, uv, R0, cx, cy, aspect, free_centre):
        self.q = np.asarray(p_W, dtype=float) @ R0.T  # plate points rotated by R0, (N, 3)
        self.uv = np.asarray(uv, dtype=float)
        self.cx, self.cy, self.aspect, self.free_centre = cx, cy, aspect, free_centre
        self._key, self._m = None, None

    def model(self, x):
        """``_project_full`` at ``x``, cached for the Jacobian."""
        key = x.tobytes()
        if key != self._key:
            self._key, self._m = key, _project_full(self.q, x, self.cx, self.cy, self.aspect, self.free_centre)
        return self._m

    def residuals(self, x):
        m = self.model(x)
        if m is None:
            return np.full(2 * len(self.q), np.nan)  # lets the solver reject the step
        return np.concatenate([m["u"] - self.uv[:, 0], m["v"] - self.uv[:, 1]])

    def jacobian(self, x):
        m = self.model(x)
        f_, k_ = x[6], x[7]
        X, Y, Xh, Yh, z, d = m["X"], m["Y"], m["Xh"], m["Yh"], m["z"], m["d"]
        rh2 = Xh * Xh + Yh * Yh
        a = 1.0 + k_ * rh2
        # d(distorted)/d(undistorted) = (a I + 2 k Xh Xh^T)^-1 = (I - c Xh Xh^T) / a  (eq. 4 inverted)
        c = 2.0 * k_ / (a + 2.0 * k_ * rh2)
        m00, m01, m11 = (1.0 - c * Xh * Xh) / a, -c * Xh * Yh / a, (1.0 - c * Yh * Yh) / a
        Jl = so3_left_jacobian(x[:3])
        rows = []
        for mu0, mu1 in ((m00 / self.aspect, m01 / self.aspect), (m01, m11)):
            # d(pixel)/d(p_C) through eq. 3, X = f x / z, Y = f y / z
            g = np.column_stack([mu0, mu1, -(mu0 * X + mu1 * Y) / f_]) * (f_ / z)[:, None]
            # omega's columns: g d p_C / d omega = g (-[R q]x) J_l(omega) = (R q x g) J_l
            rows.append(np.hstack([cross_rows(d, g) @ Jl, g, ((mu0 * X + mu1 * Y) / f_)[:, None],
                                   (-(mu0 * Xh + mu1 * Yh) * rh2)[:, None]]))
        J = np.vstack(rows)
        if self.free_centre:  # du/dcx = dv/dcy = 1
            J = np.hstack([J, np.kron(np.eye(2), np.ones((len(self.q), 1)))])
        return J


def _refine_full(p_W, uv, C_H_W, f, kappa, cx, cy, aspect, free_centre):
    """Stage 5b: pose, f, kappa [, cx, cy] minimising the distorted pixel error from ``C_H_W``. Returns (C_H_W, f,
    kappa, cx, cy, residuals (N, 2) [px], iterations)."""
    R0 = C_H_W[:3, :3]
    model = _FullModel(p_W, uv, R0, cx, cy, aspect, free_centre)
    x0 = np.concatenate([np.zeros(3), C_H_W[:3, 3], [f, kappa], [cx, cy] if free_centre else []])
    lm = levenberg_marquardt(model.residuals, x0, model.jacobian, ftol=FULL_FTOL, xtol=FULL_XTOL,
                             max_nfev=FULL_MAX_NFEV)
    f, kappa = float(lm.x[6]), float(lm.x[7])
    if free_centre:
        cx, cy = float(lm.x[8]), float(lm.x[9])
    _check_full_separable(lm.jacobian, lm.cost, lm.x, free_centre)
    if not (lm.converged and f > 0):
        raise CalibrationError(f"full refinement failed ({lm.message}; f = {f:.4g} px)")
    C_H_W = make_H(R_from_rotvec(lm.x[:3]) @ R0, lm.x[3:6])
    return C_H_W, f, kappa, cx, cy, -lm.residuals.reshape(2, -1).T, lm.iterations


def _project_full(q, x, cx, cy, aspect, free_centre):
    """Per-point arrays of ``_FullModel`` at ``x``; None where a point is behind the camera or past the lens's fold."""
    R = R_from_rotvec(x[:3])
    d = q @ R.T
    pc = d + x[3:6]
    z = pc[:, 2]
    if np.any(z <= 0):
        return None
    XY = x[6] * pc[:, :2] / z[:, None]
    try:
        XYh = distort(XY, x[7])
    except CalibrationError:
        return None
    ccx, ccy = (x[8], x[9]) if free_centre else (cx, cy)
    return {"d": d, "z": z, "X": XY[:, 0], "Y": XY[:, 1], "Xh": XYh[:, 0], "Yh": XYh[:, 1],
            "u": XYh[:, 0] / aspect + ccx, "v": XYh[:, 1] + ccy}


class _LastTrial:
    """Residuals of one of Willson's stages, ``fun(x)`` -> (residuals (N,), state), remembering recent states: his
    stages leave the pose of their last evaluation (the last trial step, taken or not) to start the next stage."""

    def __init__(self, fun, n_params: int):
        self.fun = fun
        self.calls: deque = deque(maxlen=n_params + 2)

    def __call__(self, x):
        r, state = self.fun(x)
        self.calls.append((np.array(x, dtype=float), state))
        return r

    def last_trial_state(self, x):
        """State of the last call that was no forward-difference column at ``x`` (``levenberg_marquardt`` differences
        once more after its last step; lmdif does not)."""
        for xc, state in reversed(self.calls):
            if np.count_nonzero(xc != x) != 1:
                return state
        return None


class _WillsonStages:
    """Residuals of Willson's stages after f/Tz/kappa for plate points ``xy`` (N, 2) [mm] and pixels ``uv`` (N, 2): per
    point, the distance [px] of the projection from the undistorted observation (his ``err[i] = hypot(...)``)."""

    def __init__(self, xy, uv, aspect):
        self.xy, self.uv, self.aspect = xy, uv, aspect

    def five(self, p, early: bool):
        """``p`` = (f [px], Tz [mm], kappa [px^-2], cx, cy [px]); Tx, Ty, R by stages 1-4 from the distorted (``early``
        False) or undistorted observations. State: (Tx, Ty, r), or None with NaN residuals if those stages fail."""
        f, tz, kappa, cx, cy = p
        Xh, Yh, X, Y = _sensor(self.uv, cx, cy, self.aspect, kappa)
        try:
            tx, ty, r, *_ = _linear_pose(self.xy[:, 0], self.xy[:, 1], *((X, Y) if early else (Xh, Yh)), False)
        except CalibrationError:
            return np.full(len(X), np.nan), None
        xc, yc, w = r[:, :2] @ self.xy.T + np.array([[tx], [ty], [0.0]])
        zc = w + tz
        return np.hypot(f * xc / zc - X, f * yc / zc - Y), (tx, ty, r)

    def pose(self, p, cx=None, cy=None):
        """``p`` = (Rx, Ry, Rz [rad] of R = Rz Ry Rx, Tx, Ty, Tz [mm], kappa [px^-2], f [px][, cx, cy]); state None."""
        if len(p) == 10:
            cx, cy = p[8], p[9]
        R = R_from_rpy(p[0], p[1], p[2])
        pc = self.xy @ R[:, :2].T + p[3:6]
        _, _, X, Y = _sensor(self.uv, cx, cy, self.aspect, p[6])
        return np.hypot(p[7] * pc[:, 0] / pc[:, 2] - X, p[7] * pc[:, 1] / pc[:, 2] - Y), None


def _willson_stage(fun, x0):
    """One lmdif call as Willson's (forward differences, his tolerances and budget, scaled by the Jacobian's columns);
    like him it takes the point where lmdif stopped, also out of budget."""
    n = len(x0)
    return levenberg_marquardt(fun, x0, "forward", ftol=WILLSON_FTOL, xtol=WILLSON_XTOL,
                               max_nfev=WILLSON_MAXFEV_PER_PARAM * n, scale=np.ones(n))


def _willson_full(p, uv, xy, origin, aspect, f, tz, kappa, cx, cy):
    """Stage 5c, Willson's ``coplanar_calibration_with_full_optimization`` (``docs/tsai-willson.md``), from stage 5a;
    ``xy`` (N, 2) [mm]: ``p`` (N, 3) in the stages' frame at ``origin``. Returns (C_H_W, f, kappa, cx, cy, iterations);
    ``CalibrationError`` if the linear stages fail, f <= 0, a point is behind the camera or the centre undetermined."""
    stages = _WillsonStages(xy, uv, aspect)
    x, iterations = np.array([f, tz, kappa, cx, cy], dtype=float), 0
    for early in (False, True):
        fun = _LastTrial(lambda v, early=early: stages.five(v, early), 5)
        lm = _willson_stage(fun, x)
        x, iterations = lm.x, iterations + lm.iterations
    f, tz, kappa, cx, cy = x
    state = fun.last_trial_state(x) or stages.five(x, True)[1]
    if state is None:
        raise CalibrationError("Willson's full optimisation: the linear stages fail where the 5-parameter stages end")
    tx, ty, r = state
    lm = _willson_stage(lambda v: stages.pose(v, cx, cy)[0], np.array([*_rpy_paul(r), tx, ty, tz, kappa, f]))
    iterations += lm.iterations
    lm = _willson_stage(lambda v: stages.pose(v)[0], np.append(lm.x, [cx, cy]))
    iterations += lm.iterations
    R = R_from_rpy(*lm.x[:3])
    C_H_W = make_H(R, lm.x[3:6] - R @ np.array([origin[0], origin[1], 0.0]))
    kappa, f, cx, cy = (float(v) for v in lm.x[6:])
    depth = transform_points(C_H_W, p)[:, 2]
    if not (f > 0 and np.all(depth > 0)):
        raise CalibrationError(f"Willson's full optimisation failed: f = {f:.4g} px, nearest point at depth "
                               f"{depth.min():.4g} mm")
    # one view may not determine the centre: judged on the distorted pixel error, as for full+centre
    model = _FullModel(p, uv, R, cx, cy, aspect, True)
    xf = np.concatenate([np.zeros(3), C_H_W[:3, 3], [f, kappa, cx, cy]])
    e = model.residuals(xf)
    if np.all(np.isfinite(e)):
        _check_full_separable(model.jacobian(xf), float(e @ e), xf, True)
    return C_H_W, f, kappa, cx, cy, iterations


def calibrate_coplanar(p_W, uv, *, cx: float, cy: float, aspect: float = 1.0, mode: str = "full", width: int = 768,
                       height: int = 576, f_guess: float | None = None, kappa_guess: float = 0.0) -> TsaiResult:
    """Tsai's coplanar calibration from plate points ``p_W`` (N, 3) [mm, z = 0] and their pixels ``uv`` (N, 2), the
    principal point (``cx``, ``cy``) [px] and ``aspect`` known; ``width``, ``height`` [px] go to the camera. ``mode``:
    ``tsai`` refines f, Tz, kappa as Tsai published it; ``full`` pose, f, kappa; ``full+centre`` also the principal
    point; ``willson`` stops where Willson's full optimisation does, not at a minimum. ``kappa_guess`` [px^-2] is
    taken off the observations and starts the refinement (0 as Willson); ``f_guess`` [px] replaces the linear f.
    Raises ``CalibrationError`` naming the cause (bad points, plate edge-on, f not separable from Tz, plate coordinates
    mirrored against ``CONVENTIONS.md``, no pose with f > 0, no convergence); ``ConfigError`` for a bad mode,
    principal point, aspect or ``f_guess``."""
    p, q = _check_inputs(p_W, uv, cx, cy, aspect, mode, width, height, f_guess)
    Xh, Yh, Xd, Yd = _sensor(q, cx, cy, aspect, kappa_guess)
    _check_spread(np.column_stack([Xh, Yh]), "image points", "image points collinear: the plate is seen edge-on")

    origin, xy, tx, ty, r, f_lin, tz, R_lin, tilt = _linear_stages(p[:, :2], Xd, Yd)
    xc, yc, w = (r @ np.column_stack([xy, np.zeros(len(xy))]).T + np.array([[tx], [ty], [0.0]]))
    if f_guess is not None:
        f_lin = float(f_guess)
        tz = float(Yd @ (f_lin * yc - w * Yd) / (Yd @ Yd))

    # stage 5a keeps the linear R, as Willson does
    stage = _FTzKappa(xc, yc, w, Xh, Yh)
    lm = _refine_tsai(stage, f_lin, tz, kappa_guess, willson=mode in ("tsai", "willson"))
    f, tz, kappa = (float(v) for v in lm.x)
    rel_sd = stage.f_relative_sd(lm.x)
    if not rel_sd <= F_REL_SD_LIMIT:
        raise _inseparable(tilt, f"standard error of f {100 * rel_sd:.3g} % > {100 * F_REL_SD_LIMIT:g} %")
    if not (lm.converged and f > 0 and np.all(w + tz > 0)):
        raise CalibrationError(f"Tsai refinement of f, Tz, kappa failed ({lm.message}; f = {f:.4g} px, "
                               f"Tz = {tz:.4g} mm)")
    iterations = lm.iterations
    C_H_W = make_H(R_lin, np.array([tx, ty, tz]) - R_lin @ np.array([origin[0], origin[1], 0.0]))
    if float(C_H_W[:3, 2] @ C_H_W[:3, 3]) <= 0:  # mirrored: the camera's position in W, -R^T t, has z >= 0
        raise CalibrationError("plate coordinates mirrored: the camera comes out on the +z side of the plate, but W "
                               "must be right-handed with z pointing into the plate, away from the camera (index the "
                               "grid so that x cross y points away from the camera)")
    ccx, ccy = cx, cy
    if mode == "willson":
        C_H_W, f, kappa, ccx, ccy, its = _willson_full(p, q, xy, origin, aspect, f, tz, kappa, cx, cy)
        iterations += its
    if mode in ("tsai", "willson"):
        try:
            residuals = q - _camera(f, kappa, ccx, ccy, aspect, width, height).project(transform_points(C_H_W, p))
        except CalibrationError as exc:
            raise CalibrationError(f"Tsai's model does not reach every point: {exc}") from exc
    else:
        C_H_W, f, kappa, ccx, ccy, residuals, its = _refine_full(p, q, C_H_W, f, kappa, cx, cy, aspect,
                                                                 mode == "full+centre")
        iterations += its
    rms, mean, mx, sse = residual_stats(residuals)
    return TsaiResult(camera=_camera(f, kappa, ccx, ccy, aspect, width, height), C_H_W=C_H_W, residuals_px=residuals,
                      rms_px=rms, mean_px=mean, max_px=mx, sse_px2=sse, mode=mode, iterations=int(iterations))


def _camera(f, kappa, cx, cy, aspect, width, height) -> CameraModel:
    return CameraModel(f=f, kappa=kappa, cx=cx, cy=cy, aspect=aspect, width=int(width), height=int(height))


def _check_full_separable(J, cost: float, x, free: bool) -> None:
    """``CalibrationError`` if ``_FullModel``'s Jacobian ``J`` (2N, P) and ``cost`` [px^2] at ``x`` give a relative
    standard error of f above ``FULL_REL_SD_LIMIT`` (``free``: the principal point was calibrated too)."""
    m, n = J.shape
    rel_sd = _relative_sd(covariance(J, max(cost / (m - n), SEPARABILITY_NOISE_PX**2)), x, 6)
    if not rel_sd <= FULL_REL_SD_LIMIT:
        what = "the principal point, f and the tilt" if free else "f and the pose"
        fix = "; fix the principal point (mode full)" if free else ""
        raise CalibrationError(f"one view of the plate cannot separate {what}: standard error of f "
                               f"{100 * rel_sd:.3g} % > {100 * FULL_REL_SD_LIMIT:g} %{fix}")


def _inseparable(tilt: float, detail: str) -> CalibrationError:
    return CalibrationError(f"f cannot be separated from Tz: the plate is seen nearly square-on "
                            f"(tilt {tilt:.1f} deg) or from too far for its size ({detail}); tilt the plate "
                            "30 deg or more, or bring it closer")


def load_willson_points(path) -> tuple[np.ndarray, np.ndarray]:
    """(p_W (N, 3) [mm], uv (N, 2) [px]) from Willson's format, ``xw yw zw u v`` a line, ``#`` comments. Raises
    ``CalibrationFileError`` for a missing or unreadable file, a malformed line (naming it) or no points."""
    path = Path(path)
    blob = read_bounded(path, 16 << 20, error=CalibrationFileError, what="points file", missing="no such points file")
    try:
        text = blob.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise CalibrationFileError(f"{path}: cannot read the points file ({exc})") from None
    rows = []
    for no, line in enumerate(text.splitlines(), start=1):
        parts = line.split("#", 1)[0].split()
        if not parts:
            continue
        if len(parts) != 5:
            raise CalibrationFileError(f"{path}, line {no}: expected 5 numbers 'xw yw zw u v', got {len(parts)} "
                                       f"field(s): {line.strip()!r}")
        try:
            rows.append([parse_number(s) for s in parts])
        except ValueError as exc:
            raise CalibrationFileError(f"{path}, line {no}: {exc} in {line.strip()!r}") from None
    if not rows:
        raise CalibrationFileError(f"{path}: no points (expected lines 'xw yw zw u v')")
    a = np.array(rows)
    return a[:, :3].copy(), a[:, 3:].copy()


_WILLSON_NUM = r"([-+]?\d+\.\d+(?:e[-+]?\d+)?)"


def parse_willson_log(log_text: str) -> dict[str, dict[str, float]]:
    """The calibration sections of a Willson log by title, each name -> value: f, kappa1, Tx, Ty, Tz, Rx, Ry, Rz [deg],
    Cx, Cy and '<kind>_<stat>' for the error blocks (e.g. 'distorted_mean')."""
    out = {}
    for block in log_text.split("-" * 40):
        m = re.search(r"^(Coplanar calibration.*?)\s*$", block, re.M)
        if not m:
            continue
        vals: dict[str, float] = {}
        for name in ("f", "kappa1", "Tx", "Ty", "Tz", "Rx", "Ry", "Rz", "Cx", "Cy"):
            hit = re.search(rf"\b{name} = {_WILLSON_NUM}", block)
            if hit:
                vals[name] = float(hit.group(1))
        for kind in ("distorted", "undistorted"):
            hit = re.search(rf"\n\s*{kind} image plane error:\s*\n\s*mean = {_WILLSON_NUM},\s*stddev = {_WILLSON_NUM},"
                            rf"\s*max = {_WILLSON_NUM}\s*\[pix\],\s*sse = {_WILLSON_NUM}", block)
            if hit:
                for stat, v in zip(("mean", "stddev", "max", "sse"), hit.groups()):
                    vals[f"{kind}_{stat}"] = float(v)
        out[m.group(1).strip()] = vals
    return out
