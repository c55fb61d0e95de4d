"""On-line calibration (paper, section 4): how far the camera moved on its mount, from the fingertips.

Three estimators of the new gripper-to-camera transform ``C'_H_G`` from N fingertip points ``p_G``
(N, 3) [mm] and their observed, *distorted* pixels ``uv`` (N, 2), starting from the current ``C_H_G``:

- ``NP-U`` ``differential_update``: the paper's linear update (eq. 13-17), one 6x6 solve.
- ``NP-I`` ``iterative_update``: Gauss-Newton on SE(3) over the same residuals until the step is below
  1e-9 mm, which removes the linearisation error of NP-U (the paper left it out for real-time reasons).
- ``NP-R`` ``recalibrate``: exterior orientation from N >= 4 coplanar points (OpenCV's IPPE, the
  solution nearest the current ``C_H_G``), refined by the same Gauss-Newton.

The six motion parameters (eq. 11-12, 16): ``C'p = Delta* Cp``, i.e. ``Delta* ~ C'_H_C`` maps the old
camera coordinates of a point fixed to the gripper to its new camera coordinates. (delta_x, delta_y,
delta_z) [rad] is the small rotation and (d_x, d_y, d_z) [mm] the translation of that map, both in the
old camera frame: a gripper point moves in the picture's camera frame by ``delta x p + d``. The camera
frame itself moved the opposite way (``C_H_C' = Delta*^-1``: rotation -delta, shift about -d).

Every estimator works in undistorted sensor coordinates X, Y (eq. 3-4: each observation is first
corrected with the camera's kappa, as the paper requires) and reports the reprojection residual of its
result in distorted pixels. Degenerate input raises ``CalibrationError`` naming the cause.
"""

from __future__ import annotations

import math
from functools import partial
from itertools import chain
from operator import attrgetter, mul

import cv2
import numpy as np

from selfview import _native
from selfview.camera import CameraModel, distort
from selfview.cell import POINT_NAMES
from selfview.errors import CalibrationError, ConfigError
from selfview.geometry import delta_star

__all__ = [
    "METHODS",
    "MAX_CONDITION",
    "MotionEstimate",
    "differential_update",
    "iterative_update",
    "recalibrate",
    "select_points",
    "estimate",
    "parse_method",
]

METHODS: tuple[str, ...] = ("3P-U", "4P-U", "5P-U", "3P-I", "4P-I", "5P-I", "4P-R", "5P-R")

#: Largest condition number accepted for the column-scaled normal matrix of the six motion parameters.
#: The reference cell's configurations give 5e3 (4P) to 3e4 (3P); the condition grows as the inverse
#: square of the points' distance from a line, and three points 0.1 mm off a 56 mm line give 9e7, where
#: 0.05 px of pixel noise already moves the TCP estimate by 0.7 mm (one standard deviation; 0.01 mm with
#: the four inner corners): beyond 1e8 the estimate tells more about the noise than about the camera.
MAX_CONDITION = 1e8

_MIN_POINTS = {"U": 3, "I": 3, "R": 4}
_KIND_NAME = {"U": "differential update", "I": "iterative update", "R": "recalibration"}
_DBL_EPSILON = float(np.finfo(float).eps)


#: The attributes of a ``MotionEstimate``, in the order of its constructor's arguments.
_FIELDS = (
    "method",
    "C_H_G",
    "C_H_G_orth",
    "motion",
    "delta_deg",
    "d_mm",
    "residuals_px",
    "rms_px",
    "covariance",
    "condition",
    "points_used",
    "iterations",
    "C_H_G_prior",
)
#: The attributes that may be given as a callable and computed on first access.
_DEFERRED = frozenset({"C_H_G_orth", "residuals_px", "covariance", "condition"})


class MotionEstimate:
    """One on-line estimate of the gripper-to-camera transform.

    ``C_H_G`` (4, 4) the updated transform (NP-U: ``Delta* C_H_G`` of eq. 13, not orthogonal);
    ``C_H_G_orth`` the same with its rotation re-orthonormalised (identical for NP-I and NP-R);
    ``motion`` (6,) (delta_x, delta_y, delta_z [rad], d_x, d_y, d_z [mm]) of ``C'p = Delta* Cp`` (module
    docstring; NP-I and NP-R: the rotation vector and translation of ``C'_H_G C_H_G^-1``);
    ``delta_deg``, ``d_mm`` the measures of eq. 14; ``residuals_px`` (N, 2) observed minus reprojected
    distorted pixels of ``C_H_G``; ``rms_px`` the root mean square of their lengths; ``covariance``
    (6, 6) of ``motion`` [rad, mm] as ``sigma^2 (J^T J)^-1`` with sigma^2 from the residuals (NaN when
    N = 3 leaves no redundancy, unless a prior pixel noise was given); ``condition`` of the column-scaled
    normal matrix; ``points_used`` the point names; ``iterations`` Gauss-Newton steps (1 for NP-U);
    ``C_H_G_prior`` (4, 4) the transform the estimate started from.

    Immutable: every attribute is a read-only property. ``C_H_G_orth``, ``residuals_px``,
    ``covariance`` and ``condition`` may be given as zero-argument callables, called once, on first
    access. The solvers give them so: three SVDs (a 3x3 one, two 6x6 ones) and an array cost together
    about as much as the whole NP-U solve, and a caller needs only some of them, if any.
    """

    # Slots and read-only properties rather than a frozen dataclass: its __init__ sets each field
    # through object.__setattr__, ~2 us for these 13 against ~0.4 us for plain slot stores (NP-U's
    # budget is 50 us).
    __slots__ = tuple(f"_{name}" for name in _FIELDS)

    def __init__(
        self,
        method: str,
        C_H_G: np.ndarray,
        C_H_G_orth,
        motion: np.ndarray,
        delta_deg: float,
        d_mm: float,
        residuals_px,
        rms_px: float,
        covariance,
        condition: float,
        points_used: tuple[str, ...],
        iterations: int,
        C_H_G_prior: np.ndarray | None = None,
    ):
        self._method = method
        self._C_H_G = C_H_G
        self._C_H_G_orth = C_H_G_orth
        self._motion = motion
        self._delta_deg = delta_deg
        self._d_mm = d_mm
        self._residuals_px = residuals_px
        self._rms_px = rms_px
        self._covariance = covariance
        self._condition = condition
        self._points_used = points_used
        self._iterations = iterations
        self._C_H_G_prior = C_H_G_prior

    def __repr__(self) -> str:
        return "MotionEstimate(" + ", ".join(f"{name}={getattr(self, name)!r}" for name in _FIELDS) + ")"

    def __reduce__(self):
        # copy and pickle with the deferred attributes computed (their callables may be closures)
        return MotionEstimate, tuple(getattr(self, name) for name in _FIELDS)

    def to_dict(self) -> dict:
        """Plain JSON-ready summary (lists, degrees, mm, px; NaN as None)."""

        def clean(a):
            return [None if not np.isfinite(v) else float(v) for v in np.ravel(a)]

        return {
            "method": self.method,
            "C_H_G": self.C_H_G.tolist(),
            "C_H_G_orth": self.C_H_G_orth.tolist(),
            "delta_deg": float(self.delta_deg),
            "d_mm": float(self.d_mm),
            "motion": clean(self.motion),
            "points_used": list(self.points_used),
            "rms_px": float(self.rms_px),
            "residuals_px": self.residuals_px.tolist(),
            "motion_sd": clean(np.sqrt(np.abs(np.diag(self.covariance)))),
            "condition": float(self.condition),
            "iterations": int(self.iterations),
        }


def _read_only(name: str) -> property:
    """The property ``name`` of ``MotionEstimate`` over its slot ``_name``; a deferred attribute
    replaces a callable by its value on first access."""
    slot = f"_{name}"
    if name not in _DEFERRED:
        return property(attrgetter(slot))

    def get(self):
        value = getattr(self, slot)
        if callable(value):
            value = value()
            setattr(self, slot, value)
        return value

    return property(get)


for _name in _FIELDS:
    _property = _read_only(_name)
    _property.__set_name__(MotionEstimate, _name)  # names it in the error on assignment
    setattr(MotionEstimate, _name, _property)
del _name, _property


# --- input checks and shared pieces ------------------------------------------------------------------
# Speed: NP-U must take under 50 us, about 35 trivial numpy calls on the target machine. A numpy or
# OpenCV call costs 1-2 us whatever its size in a timing loop, up to twice that amid a solve; a Python
# float operation a few tens of ns. So the per-point arithmetic (N <= 6) runs on Python floats (the
# inputs become lists once, in _prepare); numpy builds only the (2N, 7) least-squares matrix and its
# normal matrix, with np.dot rather than @ (the matmul ufunc costs more per call); OpenCV does the 6x6
# algebra, at a fraction of numpy.linalg's cost per call. The diagnostics that need an SVD of their own
# (condition number, covariance, C_H_G_orth) are computed when first read (MotionEstimate), and the
# conditioning check gets by without one (_checked_inverse). Where the compiled kernel is built
# (selfview._cnpu, see differential_update and _gauss_newton_native) it takes the common case of NP-U
# and of the Gauss-Newton of NP-I and NP-R in a few us; this Python code stays the reference it is
# tested against, and takes every other case.
def _prepare(C_H_G, p_G, uv, camera, names, kind: str):
    """Validated input: float arrays H (4, 4), P (N, 3), uv (N, 2); the same as nested lists of Python
    floats (Hl, Pl, uvl: what the per-point arithmetic reads); the point names and the method label."""
    if not isinstance(camera, CameraModel):
        raise TypeError(f"camera: expected a selfview.camera.CameraModel, got {type(camera).__name__}")
    H = np.asarray(C_H_G, dtype=float)
    P = np.asarray(p_G, dtype=float)
    uv = np.asarray(uv, dtype=float)
    if H.shape != (4, 4):
        raise ValueError(f"C_H_G: expected a (4, 4) transform, got shape {H.shape}")
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f"p_G: expected shape (N, 3), got {P.shape}")
    if uv.shape != (len(P), 2):
        raise ValueError(f"uv: expected shape ({len(P)}, 2) to match p_G, got {uv.shape}")
    n = len(P)
    names = _point_names(names, n)
    label = f"{n}P-{kind}"
    need = _MIN_POINTS[kind]
    if n < need:
        raise CalibrationError(f"{label} ({_KIND_NAME[kind]}): needs at least {need} points, got {n}")
    Hl, Pl, uvl = H.tolist(), P.tolist(), uv.tolist()
    if kind != "U":  # NP-I and NP-R start from, or choose by, the nearest rotation: it must not mirror
        (a, b, c, _), (d, e, f, _), (g, h, i, _) = Hl[:3]
        det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
        if not det > 0.0 and math.isfinite(det):
            raise CalibrationError(f"{label}: C_H_G is no rigid motion (its 3x3 part has determinant {det:.3g})")
    # One sum rather than a test per number: a NaN or an infinity anywhere makes the sum non-finite.
    # (So can an overflow of huge finite values, which the exact checks then let through.)
    if not math.isfinite(sum(chain(*Hl, *Pl, *uvl))):
        if not np.isfinite(H).all():
            raise CalibrationError(f"{label}: C_H_G contains non-finite values")
        for arr, what in ((uv, "observed pixel"), (P, "gripper point")):
            bad = ~np.isfinite(arr).all(axis=1)
            if bad.any():
                which = ", ".join(names[i] for i in np.flatnonzero(bad))
                raise CalibrationError(f"{label}: {what} of {which} is not finite (NaN: not found?)")
    return H, P, uv, Hl, Pl, uvl, names, label


def _deskewed(uv, camera):
    """(pixels, camera) for the estimators, which take the camera's (cx, cy, aspect) alone: a camera with a
    grabber's skew (``CameraModel.skew``) becomes the same camera without it, seeing ``deskew_pixels(uv)``:
    the same rays, so the same motion (the residuals then differ from the picture's by skew * dv, a
    part in a thousand). A camera without skew and malformed input (left to the checks) pass as they are."""
    if not isinstance(camera, CameraModel) or not camera.skew:
        return uv, camera
    a = np.asarray(uv, dtype=float)
    if a.ndim != 2 or a.shape[-1] != 2:
        return uv, camera
    return camera.deskew_pixels(a), camera.without_skew()


def _point_names(names, n: int) -> tuple[str, ...]:
    """The names of n points: ``names`` as strings, or by default those of ``POINT_NAMES``."""
    if names is None:
        return POINT_NAMES[:n] if n <= len(POINT_NAMES) else tuple(f"point-{i + 1}" for i in range(n))
    names = tuple(str(s) for s in names)
    if len(names) != n:
        raise ValueError(f"names: expected {n} names for {n} points, got {len(names)}")
    return names


def _undistort(camera: CameraModel, uv_list) -> list[tuple[float, float, float, float]]:
    """Eq. 4 per point: pixels [(u, v)] -> [(X^, Y^, X, Y)], distorted and undistorted sensor coordinates."""
    a, cx, cy, k = camera.aspect, camera.cx, camera.cy, camera.kappa
    out = []
    for u, v in uv_list:
        Xh, Yh = a * (u - cx), v - cy
        s = 1.0 + k * (Xh * Xh + Yh * Yh)
        out.append((Xh, Yh, Xh * s, Yh * s))
    return out


def _pixel_residuals(camera: CameraModel, obs, predicted) -> tuple[list[tuple[float, float]], float]:
    """([(du, dv)], their root mean square length) in pixels: each observed distorted sensor point
    (X^, Y^) (of ``obs`` [(X^, Y^, X, Y)]) minus the distorted image of its predicted undistorted point
    (X, Y) (``predicted`` [(X, Y)]).

    Inverts eq. 4 by Newton on kappa r^3 + r = R from the observed radius, which lies close; falls
    back to the closed form of ``selfview.camera.distort`` (which raises beyond the lens's fold)."""
    k, k3, aspect = camera.kappa, 3.0 * camera.kappa, camera.aspect
    out, sum_sq = [], 0.0
    for (Xh, Yh, _, _), (X, Y) in zip(obs, predicted):
        R = math.hypot(X, Y)
        r = math.hypot(Xh, Yh)
        # three steps, quadratic: 10 px off -> 1e-17 px (kappa 2e-7, r 400 px); a tuple costs less than range
        for _ in (1, 2, 3):
            slope = k3 * r * r + 1.0
            if slope <= 0.0:
                break
            r -= (k * r * r * r + r - R) / slope
        if k3 * r * r + 1.0 > 0.0 and abs(k * r * r * r + r - R) <= 1e-9 * (1.0 + R):
            s = r / R if R > 0.0 else 1.0
            Xp, Yp = X * s, Y * s
        else:
            Xp, Yp = distort(np.array([[X, Y]]), k)[0].tolist()
        du, dv = (Xh - Xp) / aspect, Yh - Yp
        out.append((du, dv))
        sum_sq += du * du + dv * dv
    return out, math.sqrt(sum_sq / len(out))


def _camera_points(H_rows, P_list, label: str) -> list[tuple[float, float, float]]:
    """Eq. 15: gripper points [(x, y, z)] -> [(x, y, z)] in the camera, with the rows of C_H_G as lists;
    raises for a point behind the camera."""
    (r11, r12, r13, t1), (r21, r22, r23, t2), (r31, r32, r33, t3) = H_rows[:3]
    out = []
    for gx, gy, gz in P_list:
        z = r31 * gx + r32 * gy + r33 * gz + t3
        if not z > 0.0:
            raise CalibrationError(f"{label}: a point lies behind the camera (z = {z:.3g} mm <= 0)")
        out.append((r11 * gx + r12 * gy + r13 * gz + t1, r21 * gx + r22 * gy + r23 * gz + t2, z))
    return out


def _spread(P: np.ndarray) -> np.ndarray:
    """(3,) singular values (descending) of the centred points (N, 3): their extent along the principal
    axes [mm, times sqrt(N)]."""
    Q = P - P.sum(axis=0) / len(P)
    _, w = cv2.eigen(np.dot(Q.T, Q))[:2]
    return np.sqrt(np.maximum(w.ravel(), 0.0))


def _collinear_reason(P: np.ndarray, s: np.ndarray | None = None) -> str | None:
    """Why points (N, 3) cannot fix a pose, or None: they coincide, or lie within 1 % of their extent
    of one line. ``s`` their ``_spread`` if known."""
    s = _spread(P) if s is None else s
    if s[0] == 0.0:
        return "all points coincide"
    if s[1] <= 1e-2 * s[0]:
        return f"the points are collinear (spread across the line {s[1] / s[0]:.2%} of the spread along it)"
    return None


def _rows_array(flat: list[float]) -> np.ndarray:
    """The (2N, 7) matrix [A | b] from its rows concatenated in one flat list of floats.

    ``np.fromiter`` on a flat list costs under half of ``np.array`` on a list of row tuples."""
    return np.fromiter(flat, float).reshape(-1, 7)


def _scaled(N: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The column-scaled (Jacobi) form Ns = N / (d_i d_j), d_i = sqrt(N_ii), of a normal matrix N (6, 6)
    with a positive diagonal, and the scale d_i d_j (6, 6)."""
    d = np.sqrt(N.diagonal())
    dd = d[:, None] * d
    return N / dd, dd


def _condition(N: np.ndarray) -> float:
    """Condition number of the column-scaled form of a normal matrix N (6, 6) with a positive diagonal:
    the ratio of its extreme singular values (OpenCV's SVD without U and V), inf if singular."""
    w = cv2.SVDecomp(_scaled(N)[0], flags=cv2.SVD_NO_UV)[0].ravel().tolist()
    inv_cond = w[-1] / w[0] if w[0] > 0.0 else 0.0  # smallest / largest, as cv2.invert reports it
    return 1.0 / inv_cond if inv_cond > 0.0 else math.inf


def _checked_inverse(N: np.ndarray, P: np.ndarray, label: str) -> np.ndarray:
    """N^-1 (6, 6) of a normal matrix by Cholesky, once the condition number of its column-scaled form
    (``_condition``) is known not to exceed ``MAX_CONDITION``.

    Raises ``CalibrationError`` otherwise, naming collinear points when that is the cause.

    Speed: the check needs no SVD (~6 us) unless the points are close to a degenerate configuration.
    The scaled form Ns has a unit diagonal, so its largest eigenvalue lies in [1, 6], and
    t = trace(Ns^-1) = sum_i N_ii (N^-1)_ii lies in [1, 6] / (its smallest one): t / 6 <= cond <= 6 t.
    A t that bounds the condition below MAX_CONDITION / 100 (a margin for the rounding of N^-1, then
    below 1e-9 relative) settles it; any other goes to the exact ``_condition``."""
    diagonal = N.diagonal().tolist()
    if not min(diagonal) > 0.0:
        raise CalibrationError(f"{label}: a motion parameter does not affect any observation")
    ok, N_inv = cv2.invert(N, flags=cv2.DECOMP_CHOLESKY)  # ok = 0: not positive definite
    # (sum over lists: numpy's trace of N * N_inv costs three times as much)
    if ok and 0.0 < 6.0 * sum(map(mul, diagonal, N_inv.diagonal().tolist())) <= MAX_CONDITION / 100.0:
        return N_inv
    cond = _condition(N)
    if not cond <= MAX_CONDITION:
        why = _collinear_reason(P)
        raise CalibrationError(
            f"{label}: {why or 'ill-conditioned point configuration'}; condition number {cond:.3g} of "
            f"the scaled normal system exceeds {MAX_CONDITION:.0e}, the motion would be meaningless"
        )
    if not ok:  # well enough conditioned, but not positive definite to Cholesky
        N_inv = _svd_inverse(N)
    return N_inv


def _svd_inverse(N: np.ndarray) -> np.ndarray:
    """N^-1 (6, 6) of a normal matrix by OpenCV's SVD inverse of its column-scaled form: what the
    covariances are computed with."""
    Ns, dd = _scaled(N)
    return cv2.invert(Ns, flags=cv2.DECOMP_SVD)[1] / dd


def _sigma2(rss: float, n_eq: int, prior_sigma_px: float | None) -> float:
    """Variance of one residual component: the prior's, or rss / (2N - 6); NaN without redundancy."""
    if prior_sigma_px is not None:
        return float(prior_sigma_px) ** 2
    dof = n_eq - 6
    return rss / dof if dof > 0 else math.nan


def _orthonormal(H: np.ndarray) -> np.ndarray:
    """``geometry.orthonormalize`` of a (4, 4) transform (the nearest rotation, by SVD), through
    OpenCV's 3x3 SVD: numpy's costs over ten times more per call at this size."""
    _, U, Vt = cv2.SVDecomp(H[:3, :3])
    R = np.dot(U, Vt)
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0.0:
        U[:, 2] = -U[:, 2]
        R = np.dot(U, Vt)
    out = H.copy()
    out[:3, :3] = R
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _estimate(method, H, H_orth, motion, res_px, rms_px, cov, cond, names, iters, H0) -> MotionEstimate:
    """The ``MotionEstimate``; ``res_px`` the residuals as [(du, dv)]; ``H_orth``, ``cov`` and ``cond``
    values or callables (deferred, see ``MotionEstimate``)."""
    m = motion.tolist()
    return MotionEstimate(
        method,
        H,
        H_orth,
        motion,
        math.degrees(math.sqrt(m[0] ** 2 + m[1] ** 2 + m[2] ** 2)),  # eq. 14
        math.sqrt(m[3] ** 2 + m[4] ** 2 + m[5] ** 2),
        partial(np.array, res_px),
        rms_px,
        cov,
        cond,
        tuple(names),
        iters,
        H0,
    )


# --- NP-U -------------------------------------------------------------------------------------------
def _eq17(p_C, obs, f: float) -> np.ndarray:
    """The two rows of eq. 17 per point, each divided by the point's precalculated depth z_i, as the
    augmented matrix [A | b] (2N, 7).

    The division keeps each equation and makes its residual a pixel (to first order: the paper's rows
    are ``z' (X_obs - X_pred)``), so the least squares weighs the points as the reprojection error does
    and its residual estimates the pixel noise; the paper leaves the weighting open."""
    rows = []
    for (x, y, z), (_, _, X, Y) in zip(p_C, obs):
        iz = 1.0 / z
        rows += (-X * y * iz, (f * z + X * x) * iz, -f * y * iz, f * iz, 0.0, -X * iz, (-f * x + X * z) * iz)
        rows += ((-f * z - Y * y) * iz, Y * x * iz, f * x * iz, 0.0, f * iz, -Y * iz, (-f * y + Y * z) * iz)
    return _rows_array(rows)


def _ls_covariance(Ab: np.ndarray, N: np.ndarray, x: np.ndarray, prior_sigma_px: float | None) -> np.ndarray:
    """NP-U's covariance of the motion x (6,), the least-squares solution of [A | b] (2N, 7) with the
    normal matrix N = A^T A (6, 6)."""
    # |b - A x|^2 at the least-squares solution, from the residuals themselves (b^T b - x^T A^T b
    # from the normal matrix would cancel to a few digits at small residuals)
    r = np.dot(Ab[:, :6], x) - Ab[:, 6]
    return _sigma2(float(np.dot(r, r)), len(Ab), prior_sigma_px) * _svd_inverse(N)


class _KernelResult(tuple):
    """(blob, N, x, prior_sigma_px, H) of one solve by the compiled kernel (``selfview._cnpu.np_u``):
    its blob holds [A | b] (2N, 7) of eq. 17, then the residuals (N, 2); x the motion, H ``C'_H_G``.
    The methods are the deferred attributes of its ``MotionEstimate``, computed as the Python code
    computes them (the normal matrix by numpy from the same [A | b]).

    (One tuple and four bound methods cost a third of four ``functools.partial``.)"""

    __slots__ = ()

    def _normal(self) -> tuple[np.ndarray, np.ndarray]:
        blob, n = self[0], self[1]
        Ab = np.frombuffer(blob, float, 14 * n).reshape(2 * n, 7)
        return Ab, np.dot(Ab.T, Ab)[:6, :6]

    def residuals(self) -> np.ndarray:
        blob, n = self[0], self[1]
        return np.frombuffer(blob, float, 2 * n, 112 * n).reshape(n, 2).copy()

    def covariance(self) -> np.ndarray:
        return _ls_covariance(*self._normal(), self[2], self[3])

    def condition(self) -> float:
        return _condition(self._normal()[1])

    def orthonormal(self) -> np.ndarray:
        return _orthonormal(self[4])


#: The default point names by their number (``_point_names``), for the kernel's path.
_DEFAULT_NAMES = {n: _point_names(None, n) for n in range(len(POINT_NAMES) + 1)}


def _kernel_estimate(method, H, H_orth, x, delta_deg, d_mm, rms, later, names, n, iterations, H0) -> MotionEstimate:
    """The ``MotionEstimate`` of a solve by a compiled kernel: ``later`` (``_KernelResult`` or
    ``_GaussNewtonKernelResult``) gives the deferred residuals, covariance and condition."""
    return MotionEstimate(
        method,
        H,
        H_orth,
        x,
        delta_deg,
        d_mm,
        later.residuals,
        rms,
        later.covariance,
        later.condition,
        _DEFAULT_NAMES[n] if names is None and n in _DEFAULT_NAMES else _point_names(names, n),
        iterations,
        H0,
    )


def differential_update(
    C_H_G, p_G, uv, camera: CameraModel, names=None, *, prior_sigma_px: float | None = None
) -> MotionEstimate:
    """``NP-U``: the paper's differential update from N >= 3 points (eq. 13-17).

    ``C p_i = C_H_G G p_i`` (eq. 15) with the current ``C_H_G`` (4, 4); two rows of eq. 17 per point with
    the undistorted sensor coordinates (X_i, Y_i) of ``uv`` (N, 2, distorted pixels); least squares for
    (delta_x, delta_y, delta_z [rad], d_x, d_y, d_z [mm]), whose meaning the module docstring states;
    delta and d of eq. 14; ``C'_H_G = Delta* C_H_G`` (eq. 13, left non-orthogonal as the paper leaves it;
    ``C_H_G_orth`` re-orthonormalised). Its error grows with the square of the motion. The residuals
    are those of eq. 16, ``Delta* C p_i``, reprojected. ``prior_sigma_px`` replaces the residuals'
    estimate of the pixel noise in the covariance.

    Raises ``CalibrationError`` for fewer than 3 points, non-finite input, points behind the camera,
    collinear points or an ill-conditioned system; ``ValueError`` for arrays of the wrong shape.
    """
    uv, camera = _deskewed(uv, camera)
    npu = _native.npu
    if npu is not None and isinstance(camera, CameraModel):
        # The compiled kernel computes what the code below computes (selfview/_native.py) in about a
        # tenth of its time; it returns None for any case it leaves to that code (which raises the
        # errors), which then starts from the arrays converted here (np.asarray returns them as they are).
        C_H_G = np.asarray(C_H_G, dtype=float)
        p_G = np.asarray(p_G, dtype=float)
        uv = np.asarray(uv, dtype=float)
        H, x = np.empty((4, 4)), np.empty(6)
        out = npu.np_u(C_H_G, p_G, uv, camera, MAX_CONDITION, H, x)
        if out is not None:
            rms, delta_deg, d_mm, blob = out
            n = len(p_G)
            later = _KernelResult((blob, n, x, prior_sigma_px, H))
            return _kernel_estimate(f"{n}P-U", H, later.orthonormal, x, delta_deg, d_mm, rms, later, names, n, 1, C_H_G)
    H0, P, _, Hl, Pl, uvl, names, label = _prepare(C_H_G, p_G, uv, camera, names, "U")
    f = camera.f
    obs = _undistort(camera, uvl)
    p_C = _camera_points(Hl, Pl, label)  # eq. 15
    Ab = _eq17(p_C, obs, f)
    M = np.dot(Ab.T, Ab)  # [[A^T A, A^T b], [b^T A, b^T b]]; np.dot: the same product as @, called faster
    N = M[:6, :6]
    x = np.dot(_checked_inverse(N, P, label), M[:6, 6])  # the least squares: N x = A^T b
    dx, dy, dz, tx, ty, tz = x.tolist()
    H = np.dot(delta_star((dx, dy, dz), (tx, ty, tz)), H0)  # eq. 13
    predicted = []
    for px, py, pz in p_C:
        # eq. 16: C'p_i = Delta* C p_i
        xn, yn, zn = px - dz * py + dy * pz + tx, dz * px + py - dx * pz + ty, -dy * px + dx * py + pz + tz
        if not zn > 0.0:
            raise CalibrationError(f"{label}: the update moves a point behind the camera; the motion is not small")
        predicted.append((f * xn / zn, f * yn / zn))
    res, rms = _pixel_residuals(camera, obs, predicted)
    covariance = partial(_ls_covariance, Ab, N, x, prior_sigma_px)  # deferred (MotionEstimate)
    return _estimate(label, H, partial(_orthonormal, H), x, res, rms, covariance, partial(_condition, N), names, 1, H0)


# --- NP-I (and the refinement of NP-R) --------------------------------------------------------------
def _linearise(RT, P_list, obs, f: float, label: str):
    """At the pose RT = [R | t] (3 rows of 4 floats): the camera points [(x, y, z)] and [J | r] (2N, 7),
    the Jacobian of the undistorted projections (eq. 3) under a left perturbation ``p -> p + omega x p + v``
    (omega [rad], v [mm]) beside the residuals observed minus projected; rows X, Y per point."""
    (r11, r12, r13, t1), (r21, r22, r23, t2), (r31, r32, r33, t3) = RT
    pts, rows = [], []
    for (gx, gy, gz), (_, _, X, Y) in zip(P_list, obs):
        x = r11 * gx + r12 * gy + r13 * gz + t1
        y = r21 * gx + r22 * gy + r23 * gz + t2
        z = r31 * gx + r32 * gy + r33 * gz + t3
        if not z > 0.0:
            raise CalibrationError(f"{label}: a point lies behind the camera (z = {z:.3g} mm <= 0)")
        iz = 1.0 / z
        fa, fc, fiz = f * x * iz, f * y * iz, f * iz
        rows += (-fa * y * iz, f + fa * x * iz, -fc, fiz, 0.0, -fa * iz, X - fa)
        rows += (-f - fc * y * iz, fc * x * iz, fa, 0.0, fiz, -fc * iz, Y - fc)
        pts.append((x, y, z))
    return pts, _rows_array(rows)


def _perturbed(RT, w1: float, w2: float, w3: float, v1: float, v2: float, v3: float) -> list[list[float]]:
    """The pose [R | t] (3 rows of 4 floats) after the left perturbation (omega, v): ``Rot(omega) [R | t]``
    with v added to t. Rot(omega) by Rodrigues' formula, evaluated as ``cv2.Rodrigues`` does; in Python
    floats, because cv2.Rodrigues, a matrix product and a column update cost ~6 us at this size."""
    th = math.sqrt(w1 * w1 + w2 * w2 + w3 * w3)
    if th < _DBL_EPSILON:  # cv2.Rodrigues: the identity
        R = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    else:
        c, s = math.cos(th), math.sin(th)
        c1, x, y, z = 1.0 - c, w1 / th, w2 / th, w3 / th
        R = (
            (c + c1 * (x * x), c1 * (x * y) - s * z, c1 * (x * z) + s * y),
            (c1 * (x * y) + s * z, c + c1 * (y * y), c1 * (y * z) - s * x),
            (c1 * (x * z) - s * y, c1 * (y * z) + s * x, c + c1 * (z * z)),
        )
    (p1, p2, p3, p4), (q1, q2, q3, q4), (s1, s2, s3, s4) = RT
    return [
        [a * p1 + b * q1 + c * s1, a * p2 + b * q2 + c * s2, a * p3 + b * q3 + c * s3, a * p4 + b * q4 + c * s4 + v]
        for (a, b, c), v in zip(R, (v1, v2, v3))
    ]


def _largest_move(pts, w1: float, w2: float, w3: float, v1: float, v2: float, v3: float) -> float:
    """How far [mm] the left perturbation (omega, v) moves the farthest of the points [(x, y, z)]: the
    largest |omega x p + v|. (A plain loop with products: ``** 2`` in a generator costs twice as much.)"""
    largest = 0.0
    for x, y, z in pts:
        a, b, c = w2 * z - w3 * y + v1, w3 * x - w1 * z + v2, w1 * y - w2 * x + v3
        d2 = a * a + b * b + c * c
        if d2 > largest:
            largest = d2
    return math.sqrt(largest)


def _gauss_newton(H0, H_start, P, P_list, obs, camera, names, label, tol, max_iter, prior_sigma_px) -> MotionEstimate:
    """Minimise the undistorted-sensor reprojection error of the points P (N, 3) (``P_list`` the same
    as lists) over C_H_G from ``H_start`` by Gauss-Newton on SE(3) (left perturbation: the motion
    parameters of NP-U), damped (Levenberg) only after a step that raised the cost. Stops when no point
    moves ``tol`` mm in a step. The pose is carried as rows of Python floats between the steps."""
    RT = H_start[:3].tolist()
    lam, best, moved = 0.0, None, math.inf
    for it in range(1, max_iter + 1):
        pts, Jr = _linearise(RT, P_list, obs, camera.f, label)
        M = np.dot(Jr.T, Jr)  # [[J^T J, J^T r], [r^T J, r^T r]]
        cost = M.item(6, 6)
        if best is not None and cost > best[0] * (1.0 + 1e-12) + 1e-30:
            cost, RT, pts, Jr, M = best  # the step raised the cost: go back and damp
            lam = max(10.0 * lam, 1e-6)
        else:
            if best is None:
                _checked_inverse(M[:6, :6], P, label)  # refuse a degenerate configuration before iterating
            lam = 0.1 * lam if lam > 1e-9 else 0.0
            best = (cost, RT, pts, Jr, M)
        N = M[:6, :6] + lam * np.diag(M.diagonal()[:6]) if lam else M[:6, :6]
        ok, step = cv2.solve(N, M[:6, 6], flags=cv2.DECOMP_CHOLESKY)
        if not ok:
            raise CalibrationError(f"{label}: the normal system became singular during the iteration")
        w1, w2, w3, v1, v2, v3 = step.ravel().tolist()
        moved = _largest_move(pts, w1, w2, w3, v1, v2, v3)
        RT = _perturbed(RT, w1, w2, w3, v1, v2, v3)
        if moved < tol:
            break
    else:
        raise CalibrationError(
            f"{label}: no convergence in {max_iter} iterations (the last step moved the points {moved:.3g} mm)"
        )
    H = np.array([*RT, (0.0, 0.0, 0.0, 1.0)])
    N = M[:6, :6]
    _checked_inverse(N, P, label)  # the final configuration must be well conditioned too
    r = (Jr[:, 6] - np.dot(Jr[:, :6], step.ravel())).tolist()  # residual after the last, sub-tolerance step
    res, rms = _pixel_residuals(camera, obs, [(X - r[2 * i], Y - r[2 * i + 1]) for i, (_, _, X, Y) in enumerate(obs)])
    C_H_C = np.dot(H, cv2.invert(H0)[1])  # the total motion (H0 may be a non-orthogonal NP-U result)
    motion = np.concatenate([cv2.Rodrigues(C_H_C[:3, :3])[0].ravel(), C_H_C[:3, 3]])

    def covariance():  # deferred (MotionEstimate)
        return _sigma2(sum(v * v for v in r), len(r), prior_sigma_px) * _svd_inverse(N)

    return _estimate(label, H, H, motion, res, rms, covariance, partial(_condition, N), names, it, H0)


class _GaussNewtonKernelResult(tuple):
    """(blob, N, prior_sigma_px) of one Gauss-Newton by the compiled kernel (``selfview._cnpu.np_i``):
    its blob holds the normal matrix J^T J (6, 6) of the last accepted linearisation, the residuals
    (N, 2) [px] and the linearised residuals (2N,) after the last step. The methods are the deferred
    attributes of its ``MotionEstimate``, computed as ``_gauss_newton`` computes them."""

    __slots__ = ()

    def _normal(self) -> np.ndarray:
        return np.frombuffer(self[0], float, 36).reshape(6, 6).copy()

    def residuals(self) -> np.ndarray:
        blob, n = self[0], self[1]
        return np.frombuffer(blob, float, 2 * n, 288).reshape(n, 2).copy()

    def covariance(self) -> np.ndarray:
        blob, n = self[0], self[1]
        r = np.frombuffer(blob, float, 2 * n, 288 + 16 * n).tolist()
        return _sigma2(sum(v * v for v in r), len(r), self[2]) * _svd_inverse(self._normal())

    def condition(self) -> float:
        return _condition(self._normal())


def _gauss_newton_native(kind, H0, H_start, P, uv, camera, names, tol, max_iter, prior_sigma_px):
    """``_gauss_newton`` by the compiled kernel, from ``H_start`` (4, 4) or, if None, from ``H0`` (4, 4)
    made orthonormal: the ``MotionEstimate`` (method ``NP-<kind>``), or None for a case the kernel
    leaves to the Python code (which raises the errors)."""
    H, x = np.empty((4, 4)), np.empty(6)
    out = _native.npu.np_i(H0, H_start, P, uv, camera, MAX_CONDITION, tol, max_iter, H, x)
    if out is None:
        return None
    rms, delta_deg, d_mm, iterations, blob = out
    n = len(P)
    later = _GaussNewtonKernelResult((blob, n, prior_sigma_px))
    return _kernel_estimate(f"{n}P-{kind}", H, H, x, delta_deg, d_mm, rms, later, names, n, iterations, H0)


def iterative_update(
    C_H_G,
    p_G,
    uv,
    camera: CameraModel,
    names=None,
    tol: float = 1e-9,
    max_iter: int = 50,
    *,
    prior_sigma_px: float | None = None,
) -> MotionEstimate:
    """``NP-I``: the exact update, Gauss-Newton on SE(3) from the current ``C_H_G`` (4, 4).

    Minimises the residuals NP-U linearises, in undistorted sensor coordinates (eq. 3-4), so NP-I is
    the exact solution of the same problem: the observations are corrected once and the Jacobian is
    closed-form. (The distortion's local scale 1 + 3 kappa r^2 stays below 1.1 over the picture, so
    weighing by distorted pixels would change the solution insignificantly.) Iterates until no point
    moves more than ``tol`` mm in a step; orthogonal by construction. ``motion`` is the rotation vector
    and translation of ``C'_H_G C_H_G^-1``: the parameters of NP-U (module docstring), exact.

    Raises ``CalibrationError`` for fewer than 3 points, non-finite input, a mirroring ``C_H_G``, points
    behind the camera, collinear points, an ill-conditioned system or no convergence in ``max_iter`` steps.
    """
    uv, camera = _deskewed(uv, camera)
    if _native.npu is not None and isinstance(camera, CameraModel):
        # the compiled Gauss-Newton (as in differential_update: None hands the case to the code below)
        C_H_G = np.asarray(C_H_G, dtype=float)
        p_G = np.asarray(p_G, dtype=float)
        est = _gauss_newton_native("I", C_H_G, None, p_G, np.asarray(uv, dtype=float), camera, names, tol, max_iter,
                                   prior_sigma_px)
        if est is not None:
            return est
    H0, P, _, _, Pl, uvl, names, label = _prepare(C_H_G, p_G, uv, camera, names, "I")
    obs = _undistort(camera, uvl)
    return _gauss_newton(H0, _orthonormal(H0), P, Pl, obs, camera, names, label, tol, max_iter, prior_sigma_px)


# --- NP-R -------------------------------------------------------------------------------------------
_EYE3 = np.eye(3)  # the camera matrix of normalised coordinates (OpenCV only reads it)
_EYE3.flags.writeable = False

def _mean_point_distance(Ha: np.ndarray, Hb: np.ndarray, P_list) -> float:
    """Mean distance [mm] between the camera coordinates of the points [(x, y, z)] under two transforms."""
    (a1, a2, a3, a4), (b1, b2, b3, b4), (c1, c2, c3, c4) = (Ha[:3] - Hb[:3]).tolist()
    total = 0.0
    for x, y, z in P_list:
        dx, dy, dz = a1 * x + a2 * y + a3 * z + a4, b1 * x + b2 * y + b3 * z + b4, c1 * x + c2 * y + c3 * z + c4
        total += math.sqrt(dx * dx + dy * dy + dz * dz)
    return total / len(P_list)


def recalibrate(
    C_H_G,
    p_G,
    uv,
    camera: CameraModel,
    names=None,
    *,
    tol: float = 1e-9,
    max_iter: int = 50,
    prior_sigma_px: float | None = None,
) -> MotionEstimate:
    """``NP-R``: exterior orientation of the camera with respect to the gripper from N >= 4 points.

    Coplanar points (the fingertips all lie in z = 0 of G) go to OpenCV's IPPE (``solvePnPGeneric``)
    as undistorted normalised coordinates (X/f, Y/f, corrected by our kappa model; identity camera
    matrix, no OpenCV distortion); of its two solutions the one nearest the current ``C_H_G`` (mean
    distance of the points) is refined by the Gauss-Newton of NP-I over all the points. Points that are
    not coplanar start from SQPnP instead. ``motion`` as for NP-I, relative to ``C_H_G``.

    Raises ``CalibrationError`` for fewer than 4 points, non-finite input, a mirroring ``C_H_G``,
    collinear points, no solution, an ill-conditioned system or no convergence.
    """
    uv, camera = _deskewed(uv, camera)
    H0, P, uv, _, Pl, uvl, names, label = _prepare(C_H_G, p_G, uv, camera, names, "R")
    s = _spread(P)
    why = _collinear_reason(P, s)
    if why:
        raise CalibrationError(f"{label}: {why}; the exterior orientation is undetermined")
    obs = _undistort(camera, uvl)
    # OpenCV gets the points in a frame F turned like the camera's current estimate, p_F = R0 p_G, so
    # that the pose it solves for, C_H_F, is a small rotation: its IPPE turns garbage for exact data
    # when the pose is within ~0.01 deg of a half turn (its matrix -> rotation vector conversion), and
    # the reference cell's mount guess is exactly a half turn.
    H_ref = _orthonormal(H0)
    R0 = H_ref[:3, :3]
    obj = np.dot(P, R0.T).reshape(-1, 1, 3)
    f = camera.f
    img = np.array([(X / f, Y / f) for _, _, X, Y in obs]).reshape(-1, 1, 2)
    flag = cv2.SOLVEPNP_IPPE if s[2] <= 1e-6 * s[0] else cv2.SOLVEPNP_SQPNP
    try:
        n_sol, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, _EYE3, None, flags=flag)
    except cv2.error as exc:
        raise CalibrationError(f"{label}: OpenCV's solvePnPGeneric failed ({exc.err})") from exc
    cands = []
    for rv, tv in zip(rvecs[:n_sol], tvecs[:n_sol]):
        t = tv.ravel().tolist()
        if not math.isfinite(sum(rv.ravel().tolist()) + sum(t)):
            continue
        Hc = np.empty((4, 4))  # C_H_G = C_H_F F_H_G
        Hc[:3, :3] = np.dot(cv2.Rodrigues(rv)[0], R0)
        Hc[:3, 3] = t
        Hc[3] = (0.0, 0.0, 0.0, 1.0)
        cands.append(Hc)
    if not cands:
        raise CalibrationError(f"{label}: the exterior orientation has no solution for these points")
    start = min(cands, key=lambda Hc: _mean_point_distance(Hc, H_ref, Pl))
    if _native.npu is not None:
        est = _gauss_newton_native("R", H0, start, P, uv, camera, names, tol, max_iter, prior_sigma_px)
        if est is not None:
            return est
    return _gauss_newton(H0, start, P, Pl, obs, camera, names, label, tol, max_iter, prior_sigma_px)


# --- methods by name ---------------------------------------------------------------------------------
def parse_method(method: str) -> tuple[int, str]:
    """(number of points, kind 'U' | 'I' | 'R') of a method name like '4P-U'; ``ConfigError`` if unknown."""
    if method not in METHODS:
        raise ConfigError(f"on-line method {method!r}: expected one of {', '.join(METHODS)}")
    return int(method[0]), method[-1]


def select_points(method: str, found) -> list[int]:
    """Indices (0-based, into the six points of ``POINT_NAMES``) that ``method`` uses.

    3P: points 1-3; 4P: 1-4; 5P: 1-5, or 1-4 and 6 when 5 is not found (CONVENTIONS.md). ``method`` may
    be a full name ('4P-U') or just its count ('4P'); ``found`` (6,) bool. Raises ``CalibrationError``
    naming the points that are needed but not found."""
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
        extra = 4 if found[4] else 5 if found[5] else None
        if extra is None:
            missing.append(f"{POINT_NAMES[4]} or {POINT_NAMES[5]}")
        else:
            base.append(extra)
    if missing:
        raise CalibrationError(f"{method}: needs {', '.join(missing)}, not found")
    return base


def estimate(method: str, C_H_G, p_G6, uv6, found6, camera: CameraModel, **kwargs) -> MotionEstimate:
    """Run the on-line method named ``method`` (one of ``METHODS``) on the six points.

    ``p_G6`` (6, 3) gripper points [mm], ``uv6`` (6, 2) observed distorted pixels (NaN where not found),
    ``found6`` (6,) bool; the method picks its points by ``select_points``. ``kwargs`` go to the solver
    (``prior_sigma_px``; ``tol``, ``max_iter`` for I and R). Raises ``ConfigError`` for an unknown
    method, ``CalibrationError`` as the solvers do."""
    _, kind = parse_method(method)
    p_G6 = np.asarray(p_G6, dtype=float)
    uv6 = np.asarray(uv6, dtype=float)
    if p_G6.shape != (6, 3) or uv6.shape != (6, 2):
        raise ValueError(f"estimate: expected p_G6 (6, 3) and uv6 (6, 2), got {p_G6.shape} and {uv6.shape}")
    idx = select_points(method, found6)
    names = tuple(POINT_NAMES[i] for i in idx)
    solver = {"U": differential_update, "I": iterative_update, "R": recalibrate}[kind]
    return solver(C_H_G, p_G6[idx], uv6[idx], camera, names, **kwargs)
