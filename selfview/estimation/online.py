"""On-line calibration (paper, section 4): how far the camera moved on its mount, from fingertip points ``p_G`` (N, 3)
[mm] and their distorted pixels ``uv`` (N, 2), from the current ``C_H_G``: NP-U the paper's linear update (eq. 11-17),
NP-I Gauss-Newton on SE(3), NP-R OpenCV's exterior orientation refined likewise. The motion ``C'p = Delta* Cp`` (eq.
11-12, 16): (delta_x, delta_y, delta_z) [rad], (d_x, d_y, d_z) [mm] in the old camera frame. Solved in undistorted
sensor coordinates (eq. 3-4); residuals in distorted pixels."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from selfview.maths.camera import CameraModel, distort
from selfview.files.cell import POINT_NAMES
from selfview.errors import CalibrationError, ConfigError
from selfview.maths.geometry import H_from_rotvec, cross_rows, delta_star, make_H, orthonormalize, rotvec_from_R

__all__ = [
    "METHODS", "MODEL_METHOD", "MAX_CONDITION", "MotionEstimate", "differential_update", "iterative_update",
    "recalibrate", "select_points", "estimate", "model_estimate", "parse_method",
]

METHODS: tuple[str, ...] = ("3P-U", "4P-U", "5P-U", "3P-I", "4P-I", "5P-I", "4P-R", "5P-R")

#: Largest condition number of the column-scaled normal matrix of the motion: the reference cell gives 5e3 (4P) to 3e4
#: (3P); at 9e7 (three points 0.1 mm off a 56 mm line) 0.05 px of noise moves the TCP by 0.7 mm.
MAX_CONDITION = 1e8

_MIN_POINTS = {"U": 3, "I": 3, "R": 4}
_KIND_NAME = {"U": "differential update", "I": "iterative update", "R": "recalibration"}


@dataclass(frozen=True, repr=True, eq=False)
class MotionEstimate:
    """One on-line estimate: ``C_H_G`` (4, 4) updated (NP-U: ``Delta* C_H_G`` of eq. 13, not orthogonal), ``C_H_G_orth``
    its rotation re-orthonormalised; ``motion`` (6,) (delta [rad], d [mm]) of ``C'p = Delta* Cp`` (NP-I, NP-R: rotation
    vector and translation of ``C'_H_G C_H_G^-1``); ``delta_deg``, ``d_mm`` of eq. 14; ``residuals_px`` (N, 2) observed
    minus reprojected distorted px, ``rms_px``; ``covariance`` (6, 6) of ``motion`` (NaN for N = 3 without a prior
    noise); ``condition``; ``points_used`` names; ``iterations`` (1 for NP-U); ``C_H_G_prior`` (4, 4) the start."""

    method: str
    C_H_G: np.ndarray
    C_H_G_orth: np.ndarray
    motion: np.ndarray
    delta_deg: float
    d_mm: float
    residuals_px: np.ndarray
    rms_px: float
    covariance: np.ndarray
    condition: float
    points_used: tuple
    iterations: int
    C_H_G_prior: np.ndarray | None = None

    def to_dict(self) -> dict:
        """Plain JSON-ready summary (lists, degrees, mm, px; NaN as None)."""

        def clean(a):
            return [None if not np.isfinite(v) else float(v) for v in np.ravel(a)]

        return {
            "method": self.method, "C_H_G": self.C_H_G.tolist(), "C_H_G_orth": self.C_H_G_orth.tolist(),
            "delta_deg": float(self.delta_deg), "d_mm": float(self.d_mm), "motion": clean(self.motion),
            "points_used": list(self.points_used), "rms_px": float(self.rms_px),
            "residuals_px": self.residuals_px.tolist(), "motion_sd": clean(np.sqrt(np.abs(np.diag(self.covariance)))),
            "condition": float(self.condition), "iterations": int(self.iterations),
        }


def _estimate(label, H, H_orth, motion, res_px, N, cond, rss, names, iters, H0, prior_sigma_px) -> MotionEstimate:
    """The ``MotionEstimate`` of a solve: normal matrix ``N`` (6, 6), its condition, residual sum of squares ``rss``."""
    rms = float(np.sqrt(np.mean(np.sum(res_px**2, axis=1))))
    if prior_sigma_px is not None:
        sigma2 = float(prior_sigma_px) ** 2
    else:
        dof = 2 * len(res_px) - 6
        sigma2 = rss / dof if dof > 0 else math.nan
    Ns, d = _scaled(N)
    cov = sigma2 * np.linalg.inv(Ns) / np.outer(d, d)  # well conditioned: checked before
    return MotionEstimate(label, H, H_orth, motion, math.degrees(float(np.linalg.norm(motion[:3]))),
                          float(np.linalg.norm(motion[3:])), res_px, rms, cov, cond, names, iters, H0)


def _prepare(C_H_G, p_G, uv, camera, names, kind: str, prior_sigma_px=None):
    """Validated (H (4, 4), P (N, 3), uv (N, 2), camera, names, label); a camera with skew becomes the camera without
    it seeing ``deskew_pixels(uv)``: the same rays, so the same motion."""
    if not isinstance(camera, CameraModel):
        raise TypeError(f"camera: expected a selfview.maths.camera.CameraModel, got {type(camera).__name__}")
    H, P, uv = (np.asarray(a, dtype=float) for a in (C_H_G, p_G, uv))
    if H.shape != (4, 4):
        raise ValueError(f"C_H_G: expected a (4, 4) transform, got shape {H.shape}")
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"p_G: expected shape (N, 3), got {P.shape}")
    if uv.shape != (len(P), 2):
        raise ValueError(f"uv: expected shape ({len(P)}, 2) to match p_G, got {uv.shape}")
    n = len(P)
    names = _point_names(names, n)
    label = f"{n}P-{kind}"
    if n < _MIN_POINTS[kind]:
        raise CalibrationError(f"{label} ({_KIND_NAME[kind]}): needs at least {_MIN_POINTS[kind]} points, got {n}")
    if kind != "U":  # NP-I and NP-R start from, or choose by, the nearest rotation: it must not mirror
        det = float(np.linalg.det(H[:3, :3]))
        if not det > 0.0 and math.isfinite(det):
            raise CalibrationError(f"{label}: C_H_G is no rigid motion (its 3x3 part has determinant {det:.3g})")
    if not np.isfinite(H).all():
        raise CalibrationError(f"{label}: C_H_G contains non-finite values")
    for arr, what in ((uv, "observed pixel"), (P, "gripper point")):
        bad = ~np.isfinite(arr).all(axis=1)
        if bad.any():
            which = ", ".join(names[i] for i in np.flatnonzero(bad))
            raise CalibrationError(f"{label}: {what} of {which} is not finite (NaN: not found?)")
    if prior_sigma_px is not None and not (math.isfinite(prior_sigma_px) and prior_sigma_px > 0.0):
        raise ValueError(f"prior_sigma_px: expected a positive pixel noise, got {prior_sigma_px!r}")
    if camera.skew:
        uv, camera = camera.deskew_pixels(uv), camera.without_skew()
    return H, P, uv, camera, names, label


def _point_names(names, n: int) -> tuple[str, ...]:
    """``names`` as strings, by default those of ``POINT_NAMES``."""
    if names is None:
        return POINT_NAMES[:n] if n <= len(POINT_NAMES) else tuple(f"point-{i + 1}" for i in range(n))
    names = tuple(str(s) for s in names)
    if len(names) != n:
        raise ValueError(f"names: expected {n} names for {n} points, got {len(names)}")
    return names


def _pixel_residuals(camera: CameraModel, uv: np.ndarray, XY_pred: np.ndarray) -> np.ndarray:
    """(N, 2) observed pixels minus those of the predicted undistorted sensor points ``XY_pred``."""
    d = camera.pixel_to_sensor(uv) - distort(XY_pred, camera.kappa)
    return np.column_stack([d[:, 0] / camera.aspect, d[:, 1]])


def _camera_points(H: np.ndarray, P: np.ndarray, label: str) -> np.ndarray:
    """Eq. 15: the gripper points P (N, 3) in the camera, C p = C_H_G G p; raises for one behind it."""
    p_C = P @ H[:3, :3].T + H[:3, 3]
    if not np.all(p_C[:, 2] > 0.0):
        raise CalibrationError(f"{label}: a point lies behind the camera (z = {float(np.min(p_C[:, 2])):.3g} mm <= 0)")
    return p_C


def _collinear_reason(P: np.ndarray) -> str | None:
    """Why points (N, 3) cannot fix a pose, or None: they coincide, or lie within 1 % of their extent of one line."""
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    if s[0] == 0.0:
        return "all points coincide"
    if s[1] <= 1e-2 * s[0]:
        return f"the points are collinear (spread across the line {s[1] / s[0]:.2%} of the spread along it)"
    return None


def _scaled(N: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The column-scaled (Jacobi) form N / (d_i d_j), d_i = sqrt(N_ii), of a normal matrix, and d."""
    d = np.sqrt(np.maximum(N.diagonal(), 1e-300))
    return N / np.outer(d, d), d


def _check_conditioning(N: np.ndarray, P: np.ndarray, label: str) -> float:
    """Condition number of the column-scaled normal matrix N (6, 6), inf if singular; ``CalibrationError`` above
    ``MAX_CONDITION``, naming collinear points when that is the cause."""
    if not np.min(N.diagonal()) > 0.0:
        raise CalibrationError(f"{label}: a motion parameter does not affect any observation")
    s = np.linalg.svd(_scaled(N)[0], compute_uv=False)
    cond = float(s[0] / s[-1]) if s[-1] > 0.0 else math.inf
    if not cond <= MAX_CONDITION:
        why = _collinear_reason(P) or "ill-conditioned point configuration"
        raise CalibrationError(f"{label}: {why}; condition number {cond:.3g} of the scaled normal system exceeds "
                               f"{MAX_CONDITION:.0e}, the motion would be meaningless")
    return cond


def _eq17(p_C: np.ndarray, XY: np.ndarray, f: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 17: (A (2N, 6), b (2N,)), rows X_i, Y_i per point, divided by its depth z_i: residuals in pixels (to first
    order), weighed as the reprojection error."""
    x, y, z = p_C.T
    X, Y = XY.T
    zero = np.zeros_like(x)
    rows_X = np.column_stack([-X * y, f * z + X * x, -f * y, np.full_like(x, f), zero, -X, X * z - f * x])
    rows_Y = np.column_stack([-f * z - Y * y, Y * x, f * x, zero, np.full_like(x, f), -Y, Y * z - f * y])
    Ab = np.empty((2 * len(x), 7))
    Ab[0::2], Ab[1::2] = rows_X / z[:, None], rows_Y / z[:, None]
    return Ab[:, :6], Ab[:, 6]


def differential_update(C_H_G, p_G, uv, camera: CameraModel, names=None, *,
                        prior_sigma_px: float | None = None) -> MotionEstimate:
    """``NP-U``: the paper's differential update from N >= 3 points (eq. 13-17); ``prior_sigma_px`` replaces the
    residuals' pixel noise in the covariance. Raises ``CalibrationError`` for fewer than 3 points, non-finite input,
    points behind the camera, collinear points or an ill-conditioned system; ``ValueError`` for wrong shapes."""
    H0, P, uv, camera, names, label = _prepare(C_H_G, p_G, uv, camera, names, "U", prior_sigma_px)
    f = camera.f
    XY = camera.undistort_pixels(uv)
    p_C = _camera_points(H0, P, label)  # eq. 15
    A, b = _eq17(p_C, XY, f)
    N = A.T @ A
    cond = _check_conditioning(N, P, label)
    x = np.linalg.solve(N, A.T @ b)
    H = delta_star(x[:3], x[3:]) @ H0  # eq. 13
    p_new = p_C + cross_rows(x[None, :3], p_C) + x[3:]  # eq. 16: C'p_i = Delta* C p_i
    if not np.all(p_new[:, 2] > 0.0):
        raise CalibrationError(f"{label}: the update moves a point behind the camera; the motion is not small")
    res = _pixel_residuals(camera, uv, f * p_new[:, :2] / p_new[:, 2:3])
    r = A @ x - b
    return _estimate(label, H, orthonormalize(H), x, res, N, cond, float(r @ r), names, 1, H0, prior_sigma_px)


def _linearise(H: np.ndarray, P: np.ndarray, XY: np.ndarray, f: float, label: str):
    """At pose H: camera points p (N, 3), Jacobian J (2N, 6) of the projections (eq. 3) under p -> p + omega x p + v,
    residuals r (2N,) observed minus projected; rows X, Y per point."""
    p = _camera_points(H, P, label)
    x, y, z = p.T
    u, v = f * x / z, f * y / z
    J = np.zeros((2 * len(p), 6))
    JX, JY = J[0::2], J[1::2]
    JX[:, 0], JX[:, 1], JX[:, 2], JX[:, 3], JX[:, 5] = -u * y / z, f + u * x / z, -v, f / z, -u / z
    JY[:, 0], JY[:, 1], JY[:, 2], JY[:, 4], JY[:, 5] = -f - v * y / z, v * x / z, u, f / z, -v / z
    return p, J, (XY - np.column_stack([u, v])).ravel()


def _gauss_newton(H0, H_start, P, uv, camera, names, label, tol, max_iter, prior_sigma_px) -> MotionEstimate:
    """Gauss-Newton on SE(3) from ``H_start`` (NP-U's left perturbation), damped only after a step that raised the
    cost, until no point moves ``tol`` mm in a step."""
    import cv2  # here, not at the top: ``METHODS`` is read by the command line, which does not load OpenCV

    if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0.0):
        raise ValueError(f"tol: expected a positive step in mm, got {tol!r}")
    if isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer)) or max_iter < 1:
        raise ValueError(f"max_iter: expected a whole number of iterations >= 1, got {max_iter!r}")
    XY = camera.undistort_pixels(uv)
    H = H_start.copy()
    lam, best, moved = 0.0, None, math.inf
    for it in range(1, max_iter + 1):
        p, J, r = _linearise(H, P, XY, camera.f, label)
        cost = float(r @ r)
        if best is not None and cost > best[0] * (1.0 + 1e-12) + 1e-30:
            cost, H, p, J, r = best  # the step raised the cost: go back and damp
            lam = max(10.0 * lam, 1e-6)
        else:
            if best is None:
                _check_conditioning(J.T @ J, P, label)  # refuse a degenerate configuration before iterating
            lam = 0.1 * lam if lam > 1e-9 else 0.0
            best = (cost, H, p, J, r)
        N = J.T @ J
        # the right-hand side as a column: OpenCV 5 reads a 1-D array as a 1-D matrix, 4.x as a column
        ok, step = cv2.solve(N + lam * np.diag(N.diagonal()), (J.T @ r)[:, None], flags=cv2.DECOMP_CHOLESKY)
        if not ok:
            raise CalibrationError(f"{label}: the normal system became singular during the iteration")
        step = step.ravel()
        w, t = step[:3], step[3:]
        moved = math.sqrt(float(np.max(np.sum((cross_rows(w[None], p) + t) ** 2, axis=1))))
        H = H_from_rotvec(w, t) @ H
        if moved < tol:
            break
    else:
        raise CalibrationError(f"{label}: no convergence in {max_iter} iterations (the last step moved the points "
                               f"{moved:.3g} mm)")
    N = J.T @ J
    cond = _check_conditioning(N, P, label)  # the final configuration must be well conditioned too
    r_after = r - J @ step  # the residual after the last, sub-tolerance step
    res = _pixel_residuals(camera, uv, XY - r_after.reshape(-1, 2))
    C_H_C = H @ np.linalg.inv(H0)  # the total motion (H0 may be a non-orthogonal NP-U result)
    motion = np.concatenate([rotvec_from_R(orthonormalize(C_H_C[:3, :3])), C_H_C[:3, 3]])
    return _estimate(label, H, H, motion, res, N, cond, float(r_after @ r_after), names, it, H0, prior_sigma_px)


def iterative_update(C_H_G, p_G, uv, camera: CameraModel, names=None, tol: float = 1e-9, max_iter: int = 50, *,
                     prior_sigma_px: float | None = None) -> MotionEstimate:
    """``NP-I``: NP-U's problem solved exactly, Gauss-Newton to steps under ``tol`` mm. Raises ``CalibrationError``
    for fewer than 3 points, non-finite input, a mirroring ``C_H_G``, points behind the camera, collinear points, an
    ill-conditioned system or no convergence in ``max_iter`` steps."""
    H0, P, uv, camera, names, label = _prepare(C_H_G, p_G, uv, camera, names, "I", prior_sigma_px)
    return _gauss_newton(H0, orthonormalize(H0), P, uv, camera, names, label, tol, max_iter, prior_sigma_px)


def recalibrate(C_H_G, p_G, uv, camera: CameraModel, names=None, *, tol: float = 1e-9, max_iter: int = 50,
                prior_sigma_px: float | None = None) -> MotionEstimate:
    """``NP-R``: exterior orientation from N >= 4 points (OpenCV's IPPE, SQPnP if not coplanar), the solution nearest
    ``C_H_G`` refined as NP-I. Raises ``CalibrationError`` for fewer than 4 points, non-finite input, a mirroring
    ``C_H_G``, collinear points, no solution, an ill-conditioned system or no convergence."""
    import cv2  # see _gauss_newton

    H0, P, uv, camera, names, label = _prepare(C_H_G, p_G, uv, camera, names, "R", prior_sigma_px)
    why = _collinear_reason(P)
    if why:
        raise CalibrationError(f"{label}: {why}; the exterior orientation is undetermined")
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    # OpenCV solves in a frame F turned like the estimate (p_F = R0 p_G) for a small rotation: its IPPE fails on exact
    # data within ~0.01 deg of a half turn, which the reference cell's mount guess is.
    H_ref = orthonormalize(H0)
    R0 = H_ref[:3, :3]
    obj = (P @ R0.T).reshape(-1, 1, 3)
    img = (camera.undistort_pixels(uv) / camera.f).reshape(-1, 1, 2)
    flag = cv2.SOLVEPNP_IPPE if s[2] <= 1e-6 * s[0] else cv2.SOLVEPNP_SQPNP
    try:
        n_sol, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, np.eye(3), None, flags=flag)
    except cv2.error as exc:
        raise CalibrationError(f"{label}: OpenCV's solvePnPGeneric failed ({exc.err})") from exc
    cands = [make_H(cv2.Rodrigues(rv)[0] @ R0, tv.ravel()) for rv, tv in zip(rvecs[:n_sol], tvecs[:n_sol])
             if np.isfinite(rv).all() and np.isfinite(tv).all()]  # C_H_G = C_H_F F_H_G
    if not cands:
        raise CalibrationError(f"{label}: the exterior orientation has no solution for these points")

    def distance(Hc):  # mean distance [mm] of the points under Hc and under the current estimate
        return float(np.mean(np.linalg.norm(P @ (Hc[:3, :3] - R0).T + (Hc[:3, 3] - H_ref[:3, 3]), axis=1)))

    return _gauss_newton(H0, min(cands, key=distance), P, uv, camera, names, label, tol, max_iter, prior_sigma_px)


def parse_method(method: str) -> tuple[int, str]:
    """(number of points, kind 'U' | 'I' | 'R') of a method name like '4P-U'; ``ConfigError`` if unknown."""
    if method not in METHODS:
        raise ConfigError(f"on-line method {method!r}: expected one of {', '.join(METHODS)}")
    return int(method[0]), method[-1]


def select_points(method: str, found) -> list[int]:
    """Indices into ``POINT_NAMES`` that ``method`` ('4P-U' or '4P') uses given ``found`` (6,) bool: 3P 1-3, 4P 1-4, 5P
    1-5 or, without 5, 1-4 and 6 (CONVENTIONS.md). Raises ``CalibrationError`` naming the points needed, not found."""
    found = np.asarray(found, dtype=bool)
    if found.shape != (len(POINT_NAMES),):
        raise ValueError(f"found: expected shape ({len(POINT_NAMES)},), got {found.shape}")
    key = method[:2] if isinstance(method, str) else method
    if key not in ("3P", "4P", "5P"):
        raise ConfigError(f"on-line method {method!r}: expected 3P, 4P or 5P (e.g. one of {', '.join(METHODS)})")
    n = int(key[0])
    base = list(range(min(n, 4)))
    missing = [POINT_NAMES[i] for i in base if not found[i]]
    if n == 5:
        if found[4] or found[5]:
            base.append(4 if found[4] else 5)
        else:
            missing.append(f"{POINT_NAMES[4]} or {POINT_NAMES[5]}")
    if missing:
        raise CalibrationError(f"{method}: needs {', '.join(missing)}, not found")
    return base


#: The model's own estimate, beside ``METHODS``: the silhouette fit's pose (``FingertipResult.C_H_G``).
MODEL_METHOD = "E"


def model_estimate(C_H_G, C_H_G_model, rms_px: float = float("nan")) -> MotionEstimate:
    """Estimate 'E': the model fit's pose ``C_H_G_model`` (4, 4) as the new ``C_H_G`` (eq. 14), no covariance."""
    H0, H = np.asarray(C_H_G, dtype=float), np.asarray(C_H_G_model, dtype=float)
    if H0.shape != (4, 4) or not np.all(np.isfinite(H0)):
        raise ValueError(f"C_H_G: expected a finite (4, 4) transform, got shape {H0.shape}")
    if H.shape != (4, 4) or not np.all(np.isfinite(H)):
        raise CalibrationError("E: the model-based measurement gave no pose (measure with the model)")
    M = H @ np.linalg.inv(H0)
    w = rotvec_from_R(M[:3, :3])
    return MotionEstimate(MODEL_METHOD, H.copy(), H.copy(), np.r_[w, M[:3, 3]], float(np.degrees(np.linalg.norm(w))),
                          float(np.linalg.norm(M[:3, 3])), np.zeros((0, 2)), float(rms_px), np.full((6, 6), np.nan),
                          float("nan"), (), 0, H0.copy())


def estimate(method: str, C_H_G, p_G6, uv6, found6, camera: CameraModel, *, model_C_H_G=None,
             model_rms_px: float = float("nan"), **kwargs) -> MotionEstimate:
    """Run ``method`` (of ``METHODS``, or 'E' with ``model_C_H_G``) on ``p_G6`` (6, 3) [mm], ``uv6`` (6, 2) px (NaN if
    not found), ``found6`` (6,). Raises ``ConfigError`` for an unknown method, ``CalibrationError`` as the solvers."""
    if method == MODEL_METHOD:
        if model_C_H_G is None:
            raise ConfigError("on-line method 'E' is the model's own estimate: it needs the model-based "
                              "measurement's pose")
        return model_estimate(C_H_G, model_C_H_G, model_rms_px)
    _, kind = parse_method(method)
    p_G6, uv6 = np.asarray(p_G6, dtype=float), np.asarray(uv6, dtype=float)
    if p_G6.shape != (6, 3) or uv6.shape != (6, 2):
        raise ValueError(f"estimate: expected p_G6 (6, 3) and uv6 (6, 2), got {p_G6.shape} and {uv6.shape}")
    idx = select_points(method, found6)
    names = tuple(POINT_NAMES[i] for i in idx)
    solver = {"U": differential_update, "I": iterative_update, "R": recalibrate}[kind]
    return solver(C_H_G, p_G6[idx], uv6[idx], camera, names, **kwargs)
