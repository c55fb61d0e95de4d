"""Multi-view calibration of the interior orientation: f, kappa, principal point, aspect and skew.

Tsai's coplanar method, as the paper uses it, takes the principal point (cx, cy) and the horizontal
scale factor ``aspect`` as known. One picture of a plane hardly separates them from f and the plate's
tilt; several pictures of the plate from different poses do. ``calibrate_intrinsics`` finds f, kappa,
cx, cy, aspect and every view's plate pose ``C_H_W`` jointly by Levenberg-Marquardt with an analytic
Jacobian (on the normal equations, assembled view by view: ``selfview.lm``'s SVD of the whole Jacobian
per iteration costs far more for 5 + 6 V (+ 2 N - 1 of the plate's shape) parameters), on the same disc centres as the off-line
calibration (``selfview.discs``: sub-pixel centroids, then their perspective/lens bias removed with the
current model, refitted), minimising the distorted pixel error of the camera model of ``selfview.camera``.

The skew (``CameraModel.skew``, ``skew=True`` by default) is an analogue frame grabber's shear: its PLL
samples line v skew (v - cy) px late, a few tenths of a pixel from the top line to the bottom (Beyer 1992).
The spec's model lacks it (as Tsai's does; OpenCV's and Heikkilae's have it), and a fit without it turns
a 0.3 px shear into a principal point 1-2 px off whose sigma is 4-6 times too small: the same shift of
every line in every view looks, to tilted views, like a moved centre. With the skew free the centre is
unbiased and the sigmas honest (bench/intrinsics.py); ``skew=False`` holds it at the guess's (the spec's 0).

The printed plate is not the specified one (``plate_model``, default 'bow+dots'; 'flat' takes the plate
as specified). A laser print's discs are each off by 10-20 um, the same in every view: a fixed pattern
that no number of views averages out, and that a fit on the nominal plate turns into a principal point
1-4 px off with a sigma of 0.5 px. Paper laid on a board bows by some tenths of a mm. As mrcal estimates
a board's deformation (and a bundle adjustment its target's points), the fit here adds the plate's shape
to the unknowns: a bow z = b_xx xn^2 + b_xy xn yn + b_yy yn^2 (xn, yn the disc's nominal position over
the grid's half-width; three terms, so a cylindrical cockle along any direction is one of them; the
constant and linear terms are the pose's), and each disc's in-plane position correction, gauge-fixed:
the corrections are parametrised on the complement of the grid's similarity transforms, so they cannot
move, turn or scale the grid as a whole (a move or turn is the views' poses; a uniform scale is the
plates' distances). The plate's scale is therefore NOT measured: a plate printed uniformly 0.2 % large is
seen exactly as the specified plate 0.2 % further away; the intrinsics do not depend on it, the poses'
translations carry it, and the plate's printed pitch must be measured apart if they matter. The
corrections have a Gaussian prior per axis (starting at ``PLATE_DOT_PRIOR_MM``, then estimated from the
fitted corrections, within ``PLATE_DOT_SD_RANGE_MM``) that keeps few views well-posed. The disc detector
orients each picture's grid by the picture, so first every view's disc indices are turned onto one
physical grid (``_align_views``: the turn under which its dot pattern matches the other views').

Uncertainty: the covariance of the parameters is ``s^2 (J^T J)^-1`` with ``s^2`` the residual variance
(sum of squares over the degrees of freedom; the plate's prior rows count as observations, weighed by the
noise of the previous fit, so the covariance is the posterior one); the 1-sigma of f, kappa, cx, cy,
aspect is the square root of its diagonal, the plate's shape marginalised. The projection uncertainty at a pixel q is the 1-sigma length (sqrt of the trace) of the
2-D covariance of the pixel where q's ray lands under the intrinsics' covariance (pose marginalised);
being in the camera frame it does not depend on the range.

Stop rule: the views pin the centre when sigma(cx) and sigma(cy) are both below ``STOP_CENTRE_PX`` and
the aspect when sigma(aspect) / aspect is below ``STOP_ASPECT_REL``. When they do not, the information a
further view of a given kind would add (its Jacobian at the current estimate, its own pose eliminated by
the Schur complement) says how many more views of that kind would.

Cross-check: the views are split in two halves (alternately, in order), each calibrated apart; the halves
agree when every parameter differs by at most ``AGREE_SIGMAS`` times their combined 1-sigma.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from selfview.camera import CameraModel, distort
from selfview.cell import PlateSpec
from selfview.discs import DiscDetections, detect_discs, disc_image_bias
from selfview.errors import CalibrationError, ConfigError, ImageError
from selfview.tsai import _cross, _left_jacobian
from selfview.geometry import R_from_rotvec, make_H, rot_axis, trans, transform_points

__all__ = [
    "INTRINSIC_NAMES", "IntrinsicsResult", "ViewFit", "calibrate_intrinsics", "detect_views", "fit_views",
    "projection_sigma_px", "MIN_VIEWS", "STOP_CENTRE_PX", "STOP_ASPECT_REL",
]

#: The intrinsics in the order of the covariance: the skew last, absent when it is not fitted.
INTRINSIC_NAMES = ("f", "kappa", "cx", "cy", "aspect", "skew")
#: Fewest usable views a joint calibration accepts (and each half of the cross-check).
MIN_VIEWS = 4
MIN_VIEWS_HALF = 3
#: Stop rule: the centre pinned to sigma below this in each axis [px], the aspect to this relative sigma.
STOP_CENTRE_PX = 0.3
STOP_ASPECT_REL = 0.0005
#: The halves of the cross-check agree when no parameter differs by more than this many combined sigmas.
AGREE_SIGMAS = 3.0
#: A disc centre this many residual RMS (and at least ``OUTLIER_MIN_PX``) from the model is dropped.
OUTLIER_RMS = 4.0
OUTLIER_MIN_PX = 0.5
#: A view whose residual RMS exceeds this [px] after the fit does not belong to the set (another
#: plate, a moved camera, a blurred picture) and is dropped.
VIEW_MAX_RMS_PX = 1.5
#: Bias-correction rounds (centroid -> image of the centre) after the first fit.
BIAS_ROUNDS = 2
#: Further refits, at most, until the noise that weighs the plate's prior settles (within 20 %).
NOISE_ROUNDS = 4
#: Views whose plate normals (in the camera frame) all lie within this of their mean direction [deg] see
#: parallel planes (the gripper straight down, only lifted and turned; or all square-on): they cannot pin
#: the principal point (Zhang: parallel planes add no constraint on the interior orientation).
PARALLEL_DEG = 5.0
#: Above this sigma of the centre [px] the views do not determine it at all.
UNDETERMINED_CENTRE_PX = 5.0
#: Most further views the advice considers per kind.
MAX_MORE_VIEWS = 60
#: Finite-difference steps of the numeric Jacobian: f (relative), kappa [px^-2], cx, cy [px], aspect,
#: rotation [rad], translation [mm].
_STEP = np.array([1e-6, 1e-12, 1e-4, 1e-4, 1e-7, 1e-7])
_POSE_STEP = np.array([1e-7, 1e-7, 1e-7, 1e-5, 1e-5, 1e-5])


# --- the model ------------------------------------------------------------------------------------
def _project(intr, R, t, p_W, skew: float = 0.0) -> np.ndarray:
    """(N, 2) distorted pixels of plate points ``p_W`` (N, 3) seen at pose (R, t) by intrinsics
    ``intr`` = (f, kappa, cx, cy, aspect[, skew]) (``skew`` when ``intr`` has five); NaN where a point is
    behind the camera or beyond the fold."""
    f, kappa, cx, cy, aspect = intr[:5]
    if len(intr) > 5:
        skew = intr[5]
    pc = p_W @ R.T + t
    z = pc[:, 2]
    if np.any(z <= 0) or f <= 0 or aspect <= 0:
        return np.full((len(p_W), 2), np.nan)
    XY = f * pc[:, :2] / z[:, None]
    try:
        XYh = distort(XY, kappa)
    except CalibrationError:
        return np.full((len(p_W), 2), np.nan)
    return np.column_stack([XYh[:, 0] / aspect + skew * XYh[:, 1] + cx, XYh[:, 1] + cy])


def _intr(camera: CameraModel, ni: int = 6) -> np.ndarray:
    """The intrinsics vector of ``camera``: (f, kappa, cx, cy, aspect[, skew]) (``ni`` 5 or 6)."""
    return np.array([camera.f, camera.kappa, camera.cx, camera.cy, camera.aspect, camera.skew][:ni])


def _with_intr(camera: CameraModel, x) -> CameraModel:
    """``camera`` with the intrinsics ``x[:5]`` (and ``x[5]``, its skew, when given)."""
    c = camera.with_(f=float(x[0]), kappa=float(x[1]), cx=float(x[2]), cy=float(x[3]), aspect=float(x[4]))
    return c.with_(skew=float(x[5])) if len(x) > 5 else c


#: Plate models of the joint fit (``plate_model``): 'flat' (the plate as specified, every disc exactly
#: where the spec puts it), 'bow' (plus a smooth out-of-plane deformation), 'bow+dots' (plus each disc's
#: in-plane position; the default).
PLATE_MODELS = ("flat", "bow", "bow+dots")
#: Prior 1-sigma of each disc's in-plane position error per axis [mm], to start with: a laser print places
#: a disc's edge to about half a 600-dpi dot (10-20 um). The fit then estimates it from the discs'
#: corrections themselves (a variance component, by expectation-maximisation: the mean square of the
#: corrections plus their posterior variance), within ``PLATE_DOT_SD_RANGE_MM``: a well-printed plate is
#: then not given freedom it does not need (which would cost the centre's precision), a poorly printed one
#: gets what it needs.
PLATE_DOT_PRIOR_MM = 0.02
PLATE_DOT_SD_RANGE_MM = (0.0005, 0.05)
#: Prior 1-sigma of each bow coefficient [mm] (the height the bow reaches at the grid's half-width):
#: paper on a board cockles by 0.1-0.5 mm; 1 mm is weak.
PLATE_BOW_PRIOR_MM = 1.0


def _similarity_complement(p0: np.ndarray) -> np.ndarray:
    """(2N, 2N - 4) orthonormal basis of the in-plane corrections (dx, dy interleaved per disc) that do not
    move, turn or scale the grid as a whole: the complement of its similarity transforms about its centre."""
    c = p0[:, :2] - p0[:, :2].mean(0)
    n = len(c)
    modes = np.zeros((2 * n, 4))
    modes[0::2, 0] = 1.0
    modes[1::2, 1] = 1.0
    modes[0::2, 2], modes[1::2, 2] = -c[:, 1], c[:, 0]
    modes[0::2, 3], modes[1::2, 3] = c[:, 0], c[:, 1]
    q, _ = np.linalg.qr(modes)
    u, _, _ = np.linalg.svd(np.eye(2 * n) - q @ q.T)
    return u[:, : 2 * n - 4]


class _PlateShape:
    """The printed plate's shape as parameters: a bow z = b0 xn^2 + b1 xn yn + b2 yn^2 (xn, yn the disc's
    nominal position over the grid's half-width; constant and linear terms are the pose's) and the discs'
    in-plane corrections ``B u`` (``_similarity_complement``), all discs of the grid indexed row * cols + col."""

    def __init__(self, plate: PlateSpec, model: str, prior_w: float, dot_sd_mm: float = PLATE_DOT_PRIOR_MM):
        if model not in PLATE_MODELS:
            raise CalibrationError(f"intrinsics: plate model {model!r}: expected one of {', '.join(PLATE_MODELS)}")
        self.cols = plate.cols
        p0 = plate.disc_centres_W()
        half = max(float(np.abs(p0[:, :2]).max()), 1e-9)
        xn, yn = p0[:, 0] / half, p0[:, 1] / half
        self.Q = np.column_stack([xn * xn, xn * yn, yn * yn]) if model != "flat" else np.zeros((len(p0), 0))
        self.B = _similarity_complement(p0) if model == "bow+dots" else np.zeros((2 * len(p0), 0))
        self.nb, self.nu = self.Q.shape[1], self.B.shape[1]
        self.n = self.nb + self.nu
        # prior rows, in the residuals' units (px): w_b b and w_u u, w = pixel noise / prior sd
        self.w = np.r_[np.full(self.nb, prior_w / PLATE_BOW_PRIOR_MM), np.full(self.nu, prior_w / dot_sd_mm)]

    def index(self, rc) -> np.ndarray:
        return np.asarray(rc)[:, 0] * self.cols + np.asarray(rc)[:, 1]

    def offsets(self, y, idx) -> np.ndarray:
        """(n, 3) displacement of discs ``idx`` from their nominal places for shape parameters ``y``."""
        d = np.zeros((len(idx), 3))
        if self.nb:
            d[:, 2] = self.Q[idx] @ y[: self.nb]
        if self.nu:
            du = self.B @ y[self.nb :]
            d[:, 0], d[:, 1] = du[2 * idx], du[2 * idx + 1]
        return d

    def dp_dy(self, idx) -> np.ndarray:
        """(n, 3, n_shape) derivative of the discs' positions w.r.t. the shape parameters."""
        D = np.zeros((len(idx), 3, self.n))
        D[:, 2, : self.nb] = self.Q[idx]
        D[:, 0, self.nb :] = self.B[2 * idx]
        D[:, 1, self.nb :] = self.B[2 * idx + 1]
        return D


class _Joint:
    """Parameters x = (f, kappa, cx, cy, aspect, [skew,] then per view omega (3), t (3), then the plate's
    shape (``_PlateShape``: bow, disc corrections) if ``shape``) with view k's rotation exp(omega_k) R0_k;
    ``ni`` intrinsics: 6 with the skew free, 5 with it held at ``skew``. Residuals model minus observation,
    per view (u then v of its points), then the shape's prior rows. ``blocks`` [(first row, end row,
    columns)] lists which columns each group of rows touches."""

    def __init__(self, p_W: list, uv: list, R0: list, shape: _PlateShape | None = None, idx: list | None = None,
                 *, ni: int = 5, skew: float = 0.0):
        if ni not in (5, 6):
            raise ValueError(f"intrinsics: expected 5 or 6 intrinsic parameters, got {ni}")
        self.p_W, self.uv, self.R0 = p_W, uv, R0
        self.ni, self.skew = int(ni), float(skew)
        self.n = [len(p) for p in p_W]
        self.off = np.concatenate([[0], np.cumsum([2 * k for k in self.n])])
        self.shape = shape if shape is not None and shape.n else None
        self.idx = idx
        V = len(p_W)
        ni = self.ni
        self.n_params = ni + 6 * V + (self.shape.n if self.shape else 0)
        sc = np.arange(ni + 6 * V, self.n_params)
        self.blocks = [(int(self.off[k]), int(self.off[k + 1]), np.r_[0:ni, ni + 6 * k : ni + 6 + 6 * k, sc])
                       for k in range(V)]
        if self.shape:
            self.blocks.append((int(self.off[-1]), int(self.off[-1]) + self.shape.n, sc))
        self.m_data = int(self.off[-1])

    def points(self, x, k) -> np.ndarray:
        if not self.shape:
            return self.p_W[k]
        return self.p_W[k] + self.shape.offsets(x[self.ni + 6 * len(self.p_W) :], self.idx[k])

    def view(self, x, k) -> np.ndarray:
        j = self.ni + 6 * k
        R = R_from_rotvec(x[j : j + 3]) @ self.R0[k]
        m = _project(x[: self.ni], R, x[j + 3 : j + 6], self.points(x, k), self.skew)
        return (m - self.uv[k]).T.ravel()

    def residuals(self, x) -> np.ndarray:
        r = [self.view(x, k) for k in range(len(self.p_W))]
        if self.shape:
            r.append(self.shape.w * x[self.ni + 6 * len(self.p_W) :])
        return np.concatenate(r)

    def jacobian(self, x) -> np.ndarray:
        """Analytic (as ``selfview.tsai``'s full model, with cx, cy, the aspect, the skew and the plate's shape
        added: u = X^ / aspect + skew Y^ + cx)."""
        f, kappa, cx, cy, aspect = x[:5]
        ni = self.ni
        skew = x[5] if ni > 5 else self.skew
        V = len(self.p_W)
        s0 = ni + 6 * V
        J = np.zeros((int(self.off[-1]) + (self.shape.n if self.shape else 0), len(x)))
        for k in range(V):
            j = ni + 6 * k
            R = R_from_rotvec(x[j : j + 3]) @ self.R0[k]
            d = self.points(x, k) @ R.T
            pc = d + x[j + 3 : j + 6]
            z = pc[:, 2]
            if np.any(z <= 0):
                raise CalibrationError("intrinsics: a disc lies behind the camera near the current parameters")
            X, Y = f * pc[:, 0] / z, f * pc[:, 1] / z
            XYh = distort(np.column_stack([X, Y]), kappa)
            Xh, Yh = XYh[:, 0], XYh[:, 1]
            rh2 = Xh * Xh + Yh * Yh
            a = 1.0 + kappa * rh2
            c = 2.0 * kappa / (a + 2.0 * kappa * rh2)
            m00, m11, m01 = (1.0 - c * Xh * Xh) / a, (1.0 - c * Yh * Yh) / a, -c * Xh * Yh / a
            Jl = _left_jacobian(x[j : j + 3])
            n = len(z)
            r0 = self.off[k]
            D = self.shape.dp_dy(self.idx[k]) if self.shape else None
            for row, (mu0, mu1) in ((0, (m00 / aspect + skew * m01, m01 / aspect + skew * m11)), (1, (m01, m11))):
                g = np.column_stack([mu0, mu1, -(mu0 * X + mu1 * Y) / f]) * (f / z)[:, None]
                rows = slice(r0 + row * n, r0 + (row + 1) * n)
                J[rows, 0] = (mu0 * X + mu1 * Y) / f
                J[rows, 1] = -(mu0 * Xh + mu1 * Yh) * rh2
                J[rows, j : j + 3] = _cross(d, g) @ Jl
                J[rows, j + 3 : j + 6] = g
                if D is not None:
                    J[rows, s0:] = np.einsum("na,nas->ns", g @ R, D)
            J[r0 : r0 + n, 2] = 1.0
            J[r0 + n : r0 + 2 * n, 3] = 1.0
            J[r0 : r0 + n, 4] = -Xh / aspect**2
            if ni > 5:
                J[r0 : r0 + n, 5] = Yh
        if self.shape:
            J[int(self.off[-1]) :, s0:] = np.diag(self.shape.w)
        if not np.all(np.isfinite(J)):
            raise CalibrationError("intrinsics: the model cannot see every disc near the current parameters")
        return J

    def pose(self, x, k) -> np.ndarray:
        j = self.ni + 6 * k
        return make_H(R_from_rotvec(x[j : j + 3]) @ self.R0[k], x[j + 3 : j + 6])


@dataclass
class ViewFit:
    """One view in the joint fit: ``name``; ``C_H_W`` (4, 4); ``discs`` used; ``rms_px`` of its residuals;
    ``tilt_deg`` angle between the plate's normal and the optical axis; ``distance_mm`` to the plate's
    origin; ``dropped`` disc centres dropped as outliers."""

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
class _Fit:
    camera: CameraModel
    cov5: np.ndarray  # (ni, ni) of the intrinsics fitted: INTRINSIC_NAMES[:ni]
    cov_full: np.ndarray
    jac: np.ndarray
    s2: float
    rms_px: float
    views: list
    uv_used: list
    p_W_used: list
    plate_model: str = "flat"
    shape: np.ndarray = field(default_factory=lambda: np.zeros(0))
    shape_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    prior_noise_px: float = 0.0
    dot_sd_mm: float = PLATE_DOT_PRIOR_MM
    turns: list = field(default_factory=list)
    dropped: list = field(default_factory=list)  # [(view name, why)] left out of the fit


@dataclass
class _LMOut:
    x: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    cost: float
    converged: bool
    message: str


def _normal(J, r, blocks) -> tuple[np.ndarray, np.ndarray]:
    """J^T J and J^T r of the joint problem, block by block (``_Joint.blocks``): each view's rows touch
    only the 5 intrinsics, its own 6 pose parameters and the plate's shape, so the products stay small."""
    p = J.shape[1]
    A = np.zeros((p, p))
    g = np.zeros(p)
    for r0, r1, cols in blocks:
        Jk = J[r0:r1][:, cols]
        A[np.ix_(cols, cols)] += Jk.T @ Jk
        g[cols] += Jk.T @ r[r0:r1]
    return A, g


def _lm_normal(fun, jac, x0, blocks, *, max_iter: int = 100, rtol: float = 1e-12) -> _LMOut:
    """Levenberg-Marquardt on the normal equations, damping scaled by their diagonal (Marquardt).

    The joint problem has 5 + 6 V parameters and thousands of residuals; ``selfview.lm``'s SVD of the
    whole Jacobian per iteration costs far more than the (5 + 6 V)-square normal equations here, and the
    problem is well scaled once the columns are. Stops when the cost's relative decrease or the step's
    relative size falls below ``rtol``."""
    x = np.asarray(x0, float).copy()
    r = fun(x)
    if not np.all(np.isfinite(r)):
        raise CalibrationError("intrinsics: the model cannot see every disc at the starting parameters")
    cost = float(r @ r)
    lam = 1e-3
    J = jac(x)
    converged, message = False, f"no convergence in {max_iter} iterations"
    for _ in range(max_iter):
        A, g = _normal(J, r, blocks)
        dA = np.sqrt(np.where(np.diag(A) > 0, np.diag(A), 1.0))
        As = A / np.outer(dA, dA)
        gs = g / dA
        improved = False
        for _ in range(30):
            try:
                step = -np.linalg.solve(As + lam * np.eye(len(x)), gs) / dA
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            xn = x + step
            rn = fun(xn)
            cn = float(rn @ rn) if np.all(np.isfinite(rn)) else np.inf
            if cn <= cost:
                improved = True
                break
            lam *= 10
        if not improved:
            converged, message = True, "no further decrease"
            break
        rel = (cost - cn) / max(cost, 1e-300)
        small = float(np.linalg.norm(step * dA)) <= rtol * max(float(np.linalg.norm(x * dA)), 1e-300)
        x, r, cost = xn, rn, cn
        lam = max(lam / 10, 1e-12)
        J = jac(x)
        if rel <= rtol or small:
            converged, message = True, "relative decrease of the cost or of the step below tolerance"
            break
    return _LMOut(x, r, J, cost, converged, message)


def _covariance(J, s2, blocks) -> np.ndarray:
    """``s2 (J^T J)^-1`` with the columns scaled (inf everywhere if J is rank-deficient)."""
    A, _ = _normal(J, np.zeros(len(J)), blocks)
    d = np.sqrt(np.where(np.diag(A) > 0, np.diag(A), 1.0))
    As = A / np.outer(d, d)
    w = np.linalg.eigvalsh(As)
    if not (np.all(np.isfinite(w)) and w[0] > 1e-14 * w[-1]):
        return np.full(A.shape, np.inf)
    return s2 * np.linalg.inv(As) / np.outer(d, d)


def _initial_pose(p_W, uv, camera: CameraModel) -> np.ndarray:
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
           dot_sd_mm: float = PLATE_DOT_PRIOR_MM, fit_skew: bool = True) -> _Fit:
    """Joint LM from ``camera0``, ``poses0`` (and the plate's shape ``shape0``); drops outlying discs once
    and refits. ``plate_model`` (``PLATE_MODELS``; needs ``rc`` and ``plate``): what of the plate's shape is
    fitted; ``noise_px`` the disc centres' noise that weighs the shape's prior against the pixels;
    ``fit_skew``: the skew is fitted (else held at ``camera0``'s)."""
    ni = 6 if fit_skew else 5
    shape = None
    if plate_model != "flat":
        if rc is None or plate is None:
            raise CalibrationError("intrinsics: fitting the plate's shape needs the discs' grid indices and the plate")
        shape = _PlateShape(plate, plate_model, float(noise_px), float(dot_sd_mm))
    ns = shape.n if shape else 0
    y0 = np.zeros(ns) if shape0 is None or len(shape0) != ns else np.asarray(shape0, float)
    keep = [np.ones(len(p), bool) for p in p_W]
    for attempt in range(2):
        P = [p[k] for p, k in zip(p_W, keep)]
        U = [u[k] for u, k in zip(uv, keep)]
        idx = [shape.index(r[k]) for r, k in zip(rc, keep)] if shape else None
        model = _Joint(P, U, [H[:3, :3] for H in poses0], shape, idx, ni=ni, skew=camera0.skew)
        x0 = np.concatenate([_intr(camera0, ni), *[np.concatenate([np.zeros(3), H[:3, 3]]) for H in poses0], y0])
        res = _lm_normal(model.residuals, model.jacobian, x0, model.blocks)
        poses0 = [model.pose(res.x, k) for k in range(len(P))]
        y0 = res.x[len(res.x) - ns :] if ns else y0
        try:
            camera0 = _with_intr(camera0, res.x[:ni])
        except ConfigError as exc:  # a skew no grabber has: the views do not fit this camera model
            raise CalibrationError(f"intrinsics: the joint fit left the camera model ({exc})") from None
        dist = [np.hypot(*model.view(res.x, k).reshape(2, -1)) for k in range(len(P))]
        rms = float(np.sqrt(np.mean(np.concatenate(dist) ** 2)))
        if attempt == 1:
            break
        lim = max(OUTLIER_RMS * rms, OUTLIER_MIN_PX)
        changed = False
        for k, d in enumerate(dist):
            idx_k = np.flatnonzero(keep[k])
            bad = idx_k[d > lim]
            if len(bad):
                keep[k][bad] = False
                changed = True
        if not changed:
            break
    if not (res.converged and res.x[0] > 0 and res.x[4] > 0):
        raise CalibrationError(f"intrinsics: the joint fit did not converge ({res.message})")
    m, n = res.jacobian.shape
    s2 = res.cost / max(m - n, 1)  # the prior rows count as observations of the shape's parameters
    cov = _covariance(res.jacobian, s2, model.blocks)
    views = []
    for k in range(len(P)):
        H = poses0[k]
        tilt = float(np.degrees(np.arccos(min(1.0, abs(H[2, 2])))))
        views.append(ViewFit(names[k], H, int(keep[k].sum()), float(np.sqrt(np.mean(dist[k] ** 2))), tilt,
                             float(np.linalg.norm(H[:3, 3])), int((~keep[k]).sum())))
    return _Fit(camera0, cov[:ni, :ni], cov, res.jacobian, float(s2), rms, views, U, P, plate_model,
                np.asarray(y0, float), cov[n - ns :, n - ns :] if ns else np.zeros((0, 0)), float(noise_px), float(dot_sd_mm))


def _bias_corrected(dets, camera, poses, plate) -> list:
    return [d.uv - disc_image_bias(camera, H, d.p_W, plate.disc_diameter / 2) for d, H in zip(dets, poses)]


#: Alignment of the views' disc indices: the disc detector orients each picture's grid by the picture (x
#: towards growing u), so on a square grid without a marker one view's disc (r, c) may be another's turned
#: by 90, 180 or 270 deg. A printed plate's dot errors are the same in every view: a view's turn is the one
#: under which its high-passed disc errors correlate best with the other views' (at least
#: ``ALIGN_MIN_CORR``, and by ``ALIGN_MIN_MARGIN`` over the next turn); else its indices are kept as found
#: (the dots are then below the noise and a turn matters little). When fewer than half the views can be
#: turned so, 'bow+dots' falls back to 'bow' (the summary's ``plate_shape['model']`` says which was fitted).
ALIGN_MIN_CORR = 0.4
ALIGN_MIN_MARGIN = 0.2
ALIGN_MIN_COMMON = 10


def _dot_field(det, uv, camera: CameraModel, H) -> np.ndarray | None:
    """(N, 2) a view's residuals carried back onto the plate [mm] (each disc's apparent in-plane position
    error), less their fit by a quadratic field (pose, camera and bow errors are smooth over the plate);
    None with too few discs."""
    if len(uv) < 15:
        return None
    x = _intr(camera)
    R, t = H[:3, :3], H[:3, 3]
    p = det.p_W
    m = _project(x, R, t, p)
    h = 0.01
    jx = (_project(x, R, t, p + [h, 0, 0]) - m) / h
    jy = (_project(x, R, t, p + [0, h, 0]) - m) / h
    Jp = np.stack([jx, jy], axis=2)  # (N, 2 px, 2 mm)
    r = uv - m
    if not (np.all(np.isfinite(Jp)) and np.all(np.isfinite(r))):
        return None
    d = np.linalg.solve(Jp, r[:, :, None])[:, :, 0]
    sc = max(float(np.abs(p[:, :2]).max()), 1e-9)
    xn, yn = p[:, 0] / sc, p[:, 1] / sc
    Bm = np.column_stack([np.ones_like(xn), xn, yn, xn * xn, xn * yn, yn * yn])
    coef, *_ = np.linalg.lstsq(Bm, d, rcond=None)
    return d - Bm @ coef


def _turned(det, k: int, plate: PlateSpec):
    """``det`` with its grid turned by k * 90 deg about the grid's centre (None when it leaves the grid)."""
    from dataclasses import replace

    c = np.column_stack([det.rc[:, 1] - (plate.cols - 1) / 2, det.rc[:, 0] - (plate.rows - 1) / 2])
    for _ in range(k % 4):
        c = np.column_stack([-c[:, 1], c[:, 0]])
    col, row = c[:, 0] + (plate.cols - 1) / 2, c[:, 1] + (plate.rows - 1) / 2
    if not (np.allclose(col, np.round(col)) and np.allclose(row, np.round(row))):
        return None
    rc = np.column_stack([np.round(row), np.round(col)]).astype(det.rc.dtype)
    if rc.min() < 0 or rc[:, 0].max() >= plate.rows or rc[:, 1].max() >= plate.cols:
        return None
    p0 = plate.disc_centres_W()
    return replace(det, rc=rc, p_W=p0[rc[:, 0] * plate.cols + rc[:, 1]].copy())


def _align_views(dets, uvs, fit: _Fit, plate: PlateSpec):
    """(detections re-indexed on one physical grid, [turn in deg per view or None when kept as found])."""
    n_disc = plate.rows * plate.cols
    fields = [_dot_field(d, u, fit.camera, v.C_H_W) for d, u, v in zip(dets, uvs, fit.views)]
    anchored = [all(b != "centred" for b in d.index_basis.values()) for d in dets]
    order = sorted(range(len(dets)), key=lambda k: (fields[k] is None, not anchored[k], -len(dets[k])))
    acc, cnt = np.zeros((n_disc, 2)), np.zeros(n_disc)
    out, turns = list(dets), [None] * len(dets)
    for k in order:
        if fields[k] is None or not anchored[k]:
            continue
        best = []
        for q in range(4):
            dq = _turned(dets[k], q, plate)
            if dq is None:
                continue
            e = fields[k]
            for _ in range(q):
                e = np.column_stack([-e[:, 1], e[:, 0]])
            idx = dq.rc[:, 0] * plate.cols + dq.rc[:, 1]
            com = cnt[idx] > 0
            if com.sum() >= ALIGN_MIN_COMMON:
                ref = acc[idx[com]] / cnt[idx[com], None]
                corr = float(np.sum(ref * e[com]) / np.sqrt(np.sum(ref**2) * np.sum(e[com] ** 2) + 1e-300))
            else:
                corr = np.nan
            best.append((corr, q, dq, idx, e))
        if not cnt.any():  # the first usable view sets the grid
            if not best:
                continue
            choice = best[0]
            turns[k] = 0.0
        else:
            scored = sorted([b for b in best if np.isfinite(b[0])], key=lambda b: -b[0])
            if not scored:
                continue
            second = scored[1][0] if len(scored) > 1 else -1.0
            if scored[0][0] < ALIGN_MIN_CORR or scored[0][0] - second < ALIGN_MIN_MARGIN:
                continue
            choice = scored[0]
            turns[k] = 90.0 * choice[1]
        _, q, dq, idx, e = choice
        out[k] = dq
        acc[idx] += e
        cnt[idx] += 1
    return out, turns


def fit_views(dets: list[DiscDetections], plate: PlateSpec, camera0: CameraModel, names: list[str] | None = None,
              *, bias: bool = True, plate_model: str = "bow+dots", fit_skew: bool = True) -> _Fit:
    """The joint fit of views' disc detections from ``camera0`` (a starting camera): first poses by
    planar PnP, a fit on the centroids, then ``BIAS_ROUNDS`` rounds of bias correction and refit
    (``bias=False``: the centroids as measured). ``plate_model`` (``PLATE_MODELS``): what of the printed
    plate's shape is fitted with the camera; ``fit_skew``: the grabber's skew too. The shape's prior is weighed with the previous fit's noise
    (its residual sigma); the fit is repeated (at most ``NOISE_ROUNDS`` times) until that noise settles."""
    if plate_model not in PLATE_MODELS:
        raise CalibrationError(f"intrinsics: plate model {plate_model!r}: expected one of {', '.join(PLATE_MODELS)}")
    names = names or [f"view {i + 1}" for i in range(len(dets))]
    poses = [_initial_pose(d.p_W, d.uv, camera0) for d in dets]
    normals = np.array([H[:3, 2] for H in poses])
    mean = normals.sum(0) / np.linalg.norm(normals.sum(0))
    spread = float(np.degrees(np.arccos(np.clip(normals @ mean, -1, 1))).max())
    if spread < PARALLEL_DEG:
        tilts = [float(np.degrees(np.arccos(min(1.0, abs(H[2, 2]))))) for H in poses]
        raise CalibrationError(
            f"intrinsics: the {len(dets)} views do not determine the principal point: they all see the plate from "
            f"one direction (its normal within {spread:.1f} deg in every view, {min(tilts):.0f}-{max(tilts):.0f} deg "
            f"from square-on), as when the gripper only looks straight down; take views with the gripper tilted "
            "20-40 deg about different axes in the plate"
        )
    uv = [d.uv for d in dets]
    turns = [0.0] * len(dets)
    dropped: list = []
    if plate_model != "flat":
        # a first camera on the plate as specified, then the views' discs on one physical grid
        fit = _solve([d.p_W for d in dets], uv, camera0, poses, names, fit_skew=fit_skew)
        uv = _bias_corrected(dets, fit.camera, [v.C_H_W for v in fit.views], plate)
        dets, turns = _align_views(dets, uv, fit, plate)
        if plate_model == "bow+dots" and sum(t is not None for t in turns) < max(2, (len(dets) + 1) // 2):
            # the dot pattern is not seen in most views (a print better than the noise shows): per-disc
            # corrections could not be tied to the physical discs, and on the pictures' own grids they
            # would take up what is fixed in the picture (a grabber's shear) as a deformation of the plate
            plate_model = "bow"
        unaligned = [k for k, t in enumerate(turns) if t is None]
        if plate_model == "bow+dots" and unaligned and len(dets) - len(unaligned) >= MIN_VIEWS:
            # a view whose discs could not be tied to the physical grid would give the dots' corrections
            # to the wrong discs (in the picture: a fixed pattern the fit cannot explain, which biases the
            # centre by pixels while its sigma stays small): left out, and said
            keep = [k for k in range(len(dets)) if k not in unaligned]
            dropped = [(names[k], "its discs could not be tied to the plate's grid (the printed dot pattern is "
                                  "not recognised in it), so the plate's per-disc corrections cannot apply")
                       for k in unaligned]
            dets, uv, names, turns = ([a[k] for k in keep] for a in (dets, uv, names, turns))
        poses = [_initial_pose(d.p_W, u, fit.camera) for d, u in zip(dets, uv)]
        camera0 = fit.camera
    P = [d.p_W for d in dets]
    rc = [d.rc for d in dets]
    kw = {"rc": rc, "plate": plate, "plate_model": plate_model, "fit_skew": fit_skew}
    fit = _solve(P, uv, camera0, poses, names, **kw)
    for rnd in range(BIAS_ROUNDS + NOISE_ROUNDS if bias else NOISE_ROUNDS):
        noise, sd = float(np.sqrt(fit.s2)), fit.dot_sd_mm
        if plate_model == "bow+dots":
            nb = 3
            u, cu = fit.shape[nb:], fit.shape_cov[nb:, nb:]
            sd = float(np.sqrt((u @ u + np.trace(cu)) / len(u))) if np.all(np.isfinite(cu)) else sd
            sd = float(np.clip(sd, *PLATE_DOT_SD_RANGE_MM))
        if rnd >= (BIAS_ROUNDS if bias else 0):
            if plate_model == "flat" or (abs(noise / fit.prior_noise_px - 1.0) < 0.2 and abs(sd / fit.dot_sd_mm - 1.0) < 0.2):
                break
        else:
            uv = _bias_corrected(dets, fit.camera, [v.C_H_W for v in fit.views], plate)
        fit = _solve(P, uv, fit.camera, [v.C_H_W for v in fit.views], names, shape0=fit.shape, noise_px=noise,
                     dot_sd_mm=sd, **kw)
    fit.turns = turns
    fit.dropped = dropped
    return fit


def detect_views(images, plate: PlateSpec, camera: CameraModel, names=None, *, skip_unusable: bool = False):
    """Disc detections of each picture. Returns (detections, names kept, skipped [{name, reason}]).

    A picture without the plate raises ``ImageError`` naming it, unless ``skip_unusable``."""
    names = list(names) if names is not None else [f"view {i + 1}" for i in range(len(images))]
    dets, kept, skipped = [], [], []
    for img, nm in zip(images, names):
        try:
            dets.append(detect_discs(img, plate, camera=camera))
            kept.append(nm)
        except ImageError as exc:
            if not skip_unusable:
                raise ImageError(f"{nm}: {exc}") from None
            skipped.append({"name": nm, "reason": str(exc)})
    return dets, kept, skipped


# --- uncertainty figures --------------------------------------------------------------------------
def _pixel_jacobian(camera: CameraModel, uv, ni: int = 5) -> np.ndarray:
    """(2, ni) derivative of where the ray of pixel ``uv`` lands, w.r.t. (f, kappa, cx, cy, aspect[, skew])."""
    xy = camera.undistort_pixels(np.atleast_2d(uv))[0] / camera.f
    p = np.array([[xy[0], xy[1], 1.0]])
    x = _intr(camera, ni)
    J = np.zeros((2, ni))
    for i in range(ni):
        h = _STEP[i] * (abs(x[i]) if i == 0 else 1.0)
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        J[:, i] = (_project(xp, np.eye(3), np.zeros(3), p, camera.skew)[0]
                   - _project(xm, np.eye(3), np.zeros(3), p, camera.skew)[0]) / (2 * h)
    return J


def projection_sigma_px(camera: CameraModel, cov5: np.ndarray) -> dict:
    """1-sigma [px] of the projection at the picture's centre and its four corners (see the module);
    ``cov5`` the covariance of ``INTRINSIC_NAMES[:n]``, n 5 or 6."""
    W, H = camera.width, camera.height
    pts = {"centre": ((W - 1) / 2, (H - 1) / 2), "top_left": (0.0, 0.0), "top_right": (W - 1.0, 0.0),
           "bottom_left": (0.0, H - 1.0), "bottom_right": (W - 1.0, H - 1.0)}
    out = {}
    for nm, q in pts.items():
        J = _pixel_jacobian(camera, q, len(cov5))
        out[nm] = float(np.sqrt(max(np.trace(J @ cov5 @ J.T), 0.0)))
    return out


def _sigmas(cov5) -> dict:
    d = np.sqrt(np.clip(np.diag(cov5), 0, None))
    return {nm: float(v) for nm, v in zip(INTRINSIC_NAMES, d)}


def _stop_met(sig: dict, aspect: float) -> bool:
    return bool(max(sig["cx"], sig["cy"]) < STOP_CENTRE_PX and sig["aspect"] / aspect < STOP_ASPECT_REL)


#: Kinds of further views the advice weighs: (label, tilt of the plate from square-on [deg]).
VIEW_KINDS = (("tilted 35 deg", 35.0), ("tilted 20 deg", 20.0), ("square-on", 0.0))


def _view_information(camera: CameraModel, plate: PlateSpec, distance: float, tilt_deg: float, azimuth_deg: float,
                      s2: float, ni: int = 5, shape: "_PlateShape | None" = None, y=None) -> np.ndarray | None:
    """(ni, ni) information on the intrinsics that one view of the plate adds, its pose eliminated: the
    plate's centre at ``distance`` on the optical axis, tilted ``tilt_deg`` about an in-plane axis at
    ``azimuth_deg``; the discs that fall in the picture. With the plate's shape (``shape`` at parameters
    ``y``): (ni + n_shape) square, on the intrinsics and the shape (the same printed plate in every view)."""
    a = np.radians(azimuth_deg)
    H = trans(0, 0, distance) @ rot_axis((np.cos(a), np.sin(a), 0.0), np.radians(tilt_deg))
    p = plate.disc_centres_W()
    x = _intr(camera, ni)
    uv = _project(x, H[:3, :3], H[:3, 3], p, camera.skew)
    ok = np.all(np.isfinite(uv), axis=1)
    ok[ok] = camera.in_image(uv[ok], margin=10)
    if ok.sum() < 8:
        return None
    if shape is None:
        model = _Joint([p[ok]], [uv[ok]], [H[:3, :3]], ni=ni, skew=camera.skew)
        J = model.jacobian(np.concatenate([x, np.zeros(3), H[:3, 3]]))
        A = _normal(J, np.zeros(len(J)), model.blocks)[0] / s2
        Aii, Aip, App = A[:ni, :ni], A[:ni, ni:], A[ni:, ni:]
        return Aii - Aip @ np.linalg.solve(App, Aip.T)
    model = _Joint([p[ok]], [uv[ok]], [H[:3, :3]], shape, [np.flatnonzero(ok)], ni=ni, skew=camera.skew)
    J = model.jacobian(np.concatenate([x, np.zeros(3), H[:3, 3], y]))[: model.m_data]  # no second prior
    A = J.T @ J / s2
    keep = np.r_[0:ni, ni + 6 : len(A)]
    Ak, Akp, App = A[np.ix_(keep, keep)], A[keep, ni : ni + 6], A[ni : ni + 6, ni : ni + 6]
    return Ak - Akp @ np.linalg.solve(App, Akp.T)


def more_views_advice(fit: _Fit, plate: PlateSpec) -> dict:
    """How many more views of each kind (``VIEW_KINDS``) would meet the stop rule, from the covariance.

    With the plate's shape fitted, on the joint information of the intrinsics and the shape: a further
    view sees the same printed plate, whose uncertain shape it shares with the views taken (counting only
    the intrinsics' marginal information, as if the new view's plate were known, promised the stop rule
    after one more view where six did not reach it)."""
    ni = len(fit.cov5)
    ns = len(fit.shape) if fit.plate_model != "flat" else 0
    shape = None
    if ns:
        n = len(fit.cov_full)
        idx = np.r_[0:ni, n - ns : n]
        cov0 = fit.cov_full[np.ix_(idx, idx)]
        shape = _PlateShape(plate, fit.plate_model, fit.prior_noise_px, fit.dot_sd_mm)
        if shape.n != ns:
            shape, cov0 = None, fit.cov5
    else:
        cov0 = fit.cov5
    m = len(cov0)
    try:
        info0 = np.linalg.inv(cov0)
    except np.linalg.LinAlgError:
        info0 = np.zeros((m, m))
    if not np.all(np.isfinite(info0)):
        info0 = np.zeros((m, m))
    dist = float(np.median([v.distance_mm for v in fit.views]))
    out = {}
    for label, tilt in VIEW_KINDS:
        info = info0.copy()
        need = None
        for n in range(1, MAX_MORE_VIEWS + 1):
            add = _view_information(fit.camera, plate, dist, tilt, 90.0 * (n - 1) + 45.0 * ((n - 1) // 4), fit.s2, ni,
                                    shape, fit.shape if shape is not None else None)
            if add is None:
                break
            info += add
            try:
                cov = np.linalg.inv(info)
            except np.linalg.LinAlgError:
                continue
            cov = cov[:ni, :ni]
            if np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0) and _stop_met(_sigmas(cov), fit.camera.aspect):
                need = n
                break
        out[label] = need
    return {"distance_mm": dist, "views_needed": out}


# --- the result -----------------------------------------------------------------------------------
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
    extras: dict = field(default_factory=dict)

    @property
    def views_used(self) -> int:
        return len(self.views)

    def summary(self) -> dict:
        c = self.camera
        return {
            "f": c.f, "kappa": c.kappa, "principal_point": [c.cx, c.cy], "aspect": c.aspect, "skew": c.skew,
            "width": c.width, "height": c.height,
            "sigma": dict(self.sigma),
            "covariance": np.asarray(self.covariance).tolist(),
            "rms_px": self.rms_px,
            "views_used": self.views_used,
            "views": [v.to_dict() for v in self.views],
            "views_skipped": list(self.skipped),
            "projection_sigma_px": dict(self.projection_sigma_px),
            "stop_rule": self.stop_rule,
            "cross_check": self.cross_check,
            "plate_shape": self.plate_shape,
        }


def _plate_summary(fit: _Fit) -> dict:
    """What the fit found of the printed plate: its model, the bow's coefficients [mm] (z at the grid's
    half-width: xx, xy, yy) with their 1-sigma, the discs' position error sd [mm] and rms of their fitted
    corrections, each view's turn of its disc indices onto the plate's grid [deg] (None: kept as found)."""
    out = {"model": fit.plate_model, "turns_deg": list(fit.turns)}
    if fit.plate_model == "flat":
        return out
    nb = 3
    out["bow_mm"] = [float(v) for v in fit.shape[:nb]]
    out["bow_sigma_mm"] = [float(v) for v in np.sqrt(np.clip(np.diag(fit.shape_cov)[:nb], 0, None))]
    if fit.plate_model == "bow+dots":
        u = fit.shape[nb:]
        out["dot_sd_mm"] = float(fit.dot_sd_mm)
        out["dot_rms_mm"] = float(np.sqrt(u @ u / (len(u) + 4)))
    return out


def _cross_check(dets, names, plate, fit: _Fit) -> dict:
    n = len(dets)
    if n < 2 * MIN_VIEWS_HALF:
        return {"done": False, "why": f"{n} views; the cross-check needs {2 * MIN_VIEWS_HALF} (two halves of "
                                      f"{MIN_VIEWS_HALF})"}
    halves = []
    for idx in (range(0, n, 2), range(1, n, 2)):
        idx = list(idx)
        try:
            h = fit_views([dets[i] for i in idx], plate, fit.camera, [names[i] for i in idx], plate_model=fit.plate_model,
                          fit_skew=len(fit.cov5) > 5)
        except CalibrationError as exc:
            return {"done": False, "why": f"a half could not be calibrated: {exc}"}
        halves.append(h)
    a, b = halves
    xa, xb = _intr(a.camera, len(a.cov5)), _intr(b.camera, len(b.cov5))
    comb = np.sqrt(np.diag(a.cov5) + np.diag(b.cov5))
    ratio = np.abs(xa - xb) / comb
    agree = bool(np.all(np.isfinite(ratio)) and np.all(ratio <= AGREE_SIGMAS))
    return {
        "done": True,
        "agree": agree,
        "halves": [{nm: float(v) for nm, v in zip(INTRINSIC_NAMES, x)} for x in (xa, xb)],
        "difference": {nm: float(v) for nm, v in zip(INTRINSIC_NAMES, xa - xb)},
        "combined_sigma": {nm: float(v) for nm, v in zip(INTRINSIC_NAMES, comb)},
        "ratio": {nm: float(v) for nm, v in zip(INTRINSIC_NAMES, ratio)},
        "limit_sigmas": AGREE_SIGMAS,
    }


def calibrate_intrinsics(images, plate: PlateSpec, camera_guess: CameraModel, names=None, *,
                         skip_unusable: bool = False, cross_check: bool = True, detections=None,
                         plate_model: str = "bow+dots", skew: bool = True) -> IntrinsicsResult:
    """Joint calibration of f, kappa, cx, cy, aspect, the grabber's skew and each view's ``C_H_W`` from
    pictures of the plate (``skew=False``: the skew held at ``camera_guess``'s, the spec's model).

    ``images`` (H, W) pictures (or ``detections``, a list of ``DiscDetections``, instead); ``plate`` the
    plate; ``camera_guess`` the starting camera (the cell's nominal one: its size checks the pictures);
    ``names`` per picture, for messages; ``skip_unusable``: a picture without the plate is skipped (and
    listed) instead of refused. Raises ``ImageError`` (a picture without the plate, of the wrong size) or
    ``CalibrationError`` (fewer than ``MIN_VIEWS`` usable views; views that do not determine the centre,
    all seen square-on; no convergence).
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
    fit = fit_views(dets, plate, camera_guess, names, plate_model=plate_model, fit_skew=skew)
    # a view that does not fit the others: drop it and refit
    bad = {v.name: v.rms_px for v in fit.views if v.rms_px > VIEW_MAX_RMS_PX}
    if bad and len(fit.views) - len(bad) >= MIN_VIEWS:
        for nm, rms in bad.items():
            skipped.append({"name": nm, "reason": f"does not fit the other views (residual rms "
                                                  f"{rms:.2f} px > {VIEW_MAX_RMS_PX} px)"})
        keep = [k for k in range(len(dets)) if names[k] not in bad]
        dets, names = [dets[k] for k in keep], [names[k] for k in keep]
        fit = fit_views(dets, plate, fit.camera, names, plate_model=plate_model, fit_skew=skew)
    for nm, why in fit.dropped:
        skipped.append({"name": nm, "reason": why})
    used = {v.name for v in fit.views}
    keep = [k for k in range(len(dets)) if names[k] in used]
    dets, names = [dets[k] for k in keep], [names[k] for k in keep]
    sig = _sigmas(fit.cov5)
    tilts = [v.tilt_deg for v in fit.views]
    if not (np.all(np.isfinite(fit.cov5)) and max(sig["cx"], sig["cy"]) < UNDETERMINED_CENTRE_PX):
        raise CalibrationError(
            f"intrinsics: the {len(dets)} views do not determine the principal point (sigma "
            f"{max(sig['cx'], sig['cy']):.3g} px): they see the plate {min(tilts):.0f}-{max(tilts):.0f} deg from "
            "square-on; take views tilted 20-40 deg in different directions"
        )
    met = _stop_met(sig, fit.camera.aspect)
    stop = {
        "met": met,
        "sigma_centre_px": max(sig["cx"], sig["cy"]),
        "sigma_aspect_pct": 100 * sig["aspect"] / fit.camera.aspect,
        "limit_centre_px": STOP_CENTRE_PX,
        "limit_aspect_pct": 100 * STOP_ASPECT_REL,
    }
    if not met:
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
    xc = _cross_check(dets, names, plate, fit) if cross_check else {"done": False, "why": "not asked for"}
    return IntrinsicsResult(
        camera=fit.camera, covariance=fit.cov5, sigma=sig, rms_px=fit.rms_px, views=fit.views, skipped=skipped,
        projection_sigma_px=projection_sigma_px(fit.camera, fit.cov5), stop_rule=stop, cross_check=xc,
        residual_sigma_px=float(np.sqrt(fit.s2)), plate_shape=_plate_summary(fit),
    )


# --- views the robot can take ---------------------------------------------------------------------
#: Ranges of the planned views: lift of the fingertips off the plate [mm], tilt of the gripper about
#: axes in the plate [deg], turn about the approach axis [deg]; the fingertips stay this far [mm] above
#: the plate; the camera should see the plate this far from square-on [deg].
LIFT_MM = (15.0, 120.0)
MAX_TILT_DEG = 40.0
MAX_TURN_DEG = 90.0
#: With a direction to lean towards (the robot's base), the wrist may move at most this far from it [deg].
LEAN_TOLERANCE_DEG = 60.0
CLEARANCE_MM = 8.0
#: The camera sees the plate at most this far from square-on [deg] (the discs stay measurable).
MAX_CAMERA_TILT_DEG = 48.0


def _fingers_clear(W_H_G, gripper, gap) -> float:
    """Height [mm] of the lowest finger corner above the plate (W's z points into the plate)."""
    corners = []
    for lo, hi in gripper.finger_boxes_G(gap):
        for x in (lo[0], hi[0]):
            for y in (lo[1], hi[1]):
                for z in (lo[2], hi[2]):
                    corners.append((x, y, z))
    return float(-np.max(transform_points(W_H_G, np.array(corners))[:, 2]))


def plan_view_poses(cell, n: int = 12, *, state: str | None = None, C_H_G=None, lean_W=None) -> list[dict]:
    """``n`` gripper poses relative to the plate for the views of ``calibrate_intrinsics``.

    Each is the gripper tilted (at most ``MAX_TILT_DEG``) about an axis in the plate through the point
    under the TCP, lifted along its approach axis (``LIFT_MM``, more when the fingers need it to clear
    the plate by ``CLEARANCE_MM``) and turned about it (at most ``MAX_TURN_DEG``), chosen so that the
    plate's normal, in the gripper's (and so the camera's) frame, is tilted 25-40 deg in directions turning
    round from view to view (views that differ only by a turn about the approach axis or a lift see
    parallel planes, which cannot pin the principal point), at lifts spread over the range, the camera
    (mount ``C_H_G``, default the cell's guess) seeing the plate at most ``MAX_CAMERA_TILT_DEG`` from
    square-on with its centre in the picture. ``lean_W`` (2,): a direction in the plate (x, y of W) towards the robot's base;
    tilts then move the wrist within ``LEAN_TOLERANCE_DEG`` of it (a tilt away from the base takes the
    wrist out of a small arm's reach). Returns [{W_H_G (4, 4), lift_mm, tilt_deg, axis_deg, turn_deg,
    camera_tilt_deg, camera_azimuth_deg}]. Raises ``CalibrationError`` when no pose fits.
    """
    if n < 1:
        raise CalibrationError(f"view plan: expected at least one view, got {n}")
    C_H_G = cell.mount_guess_C_H_G if C_H_G is None else np.asarray(C_H_G, float)
    gap = cell.gripper.gap(state or cell.gripper.calibrate_in)
    cam = cell.camera.guess()
    lean = None if lean_W is None else np.asarray(lean_W, float)[:2] / np.linalg.norm(np.asarray(lean_W, float)[:2])
    cands = []
    for tilt in np.arange(0.0, MAX_TILT_DEG + 1e-9, 5.0):
        for axis in np.arange(0.0, 360.0, 22.5 if tilt else 360.0):
            a = np.radians(axis)
            Rt = rot_axis((np.cos(a), np.sin(a), 0.0), np.radians(tilt))
            if lean is not None and tilt > 0:
                wrist = -Rt[:2, 2]  # where the wrist moves, horizontally
                if wrist @ lean < np.cos(np.radians(LEAN_TOLERANCE_DEG)) * np.linalg.norm(wrist):
                    continue
            for turn in np.arange(-MAX_TURN_DEG, MAX_TURN_DEG + 1e-9, 22.5):
                W_H_C = Rt @ make_H(R_from_rotvec((0, 0, np.radians(turn))), (0, 0, 0)) @ np.linalg.inv(C_H_G)
                d = W_H_C[:3, 2]  # optical axis in W
                ctilt = float(np.degrees(np.arccos(np.clip(d[2], -1, 1))))
                caz = float(np.degrees(np.arctan2(d[1], d[0])) % 360.0)
                # the plate's normal in the gripper frame (rigidly tied to the camera): only its direction
                # tells views apart for the interior orientation; a turn alone does not change it
                nG = (np.linalg.inv(Rt @ make_H(R_from_rotvec((0, 0, np.radians(turn))), (0, 0, 0))))[:3, 2]
                naz = float(np.degrees(np.arctan2(nG[1], nG[0])) % 360.0)
                if ctilt <= MAX_CAMERA_TILT_DEG:
                    cands.append((tilt, axis, turn, ctilt, caz, naz))
    cands = np.array(cands)
    lifts = np.linspace(LIFT_MM[0] + 15.0, LIFT_MM[1], 4)
    out = []
    used: set[int] = set()
    for i in range(n):
        az = (360.0 * i / n + 45.0 * (i % 2)) % 360.0
        want_tilt = (35.0, 25.0, 40.0, 30.0)[i % 4]
        daz = np.abs((cands[:, 5] - az + 180.0) % 360.0 - 180.0)
        score = np.abs(cands[:, 0] - want_tilt) + 0.3 * daz
        for j in np.argsort(score):
            if int(j) in used:
                continue
            tilt, axis, turn, ctilt, caz, _ = cands[j]
            a = np.radians(axis)
            Rt = rot_axis((np.cos(a), np.sin(a), 0.0), np.radians(tilt))
            Rz = make_H(R_from_rotvec((0, 0, np.radians(turn))), (0, 0, 0))
            want = float(lifts[(i * 3) % len(lifts)])
            found = None
            for lift in sorted(np.arange(LIFT_MM[0], LIFT_MM[1] + 1e-9, 5.0), key=lambda v: abs(v - want)):
                W_H_G = Rt @ trans(0, 0, -lift) @ Rz
                if _fingers_clear(W_H_G, cell.gripper, gap) < CLEARANCE_MM:
                    continue
                C_H_W = C_H_G @ np.linalg.inv(W_H_G)
                if not cam.in_image(cam.project(transform_points(C_H_W, np.zeros((1, 3)))), margin=60)[0]:
                    continue
                found = lift
                break
            if found is None:
                continue
            lift = float(found)
            used.add(int(j))
            out.append({"W_H_G": W_H_G, "lift_mm": lift, "tilt_deg": float(tilt), "axis_deg": float(axis),
                        "turn_deg": float(turn), "camera_tilt_deg": float(ctilt), "camera_azimuth_deg": float(caz)})
            break
        else:
            raise CalibrationError(f"view plan: no pose for view {i + 1} keeps the fingers clear and the plate in view")
    return out


# --- one picture: is the nominal camera wrong? how sure is the TCP? --------------------------------
#: Accuracy targets of the off-line calibration [mm]: TCP across and along the optical axis.
TARGET_ACROSS_MM = 0.02
TARGET_ALONG_MM = 0.08
#: The picture shows the camera's centre and aspect differ from the assumed ones when the chi-square of
#: the difference (3 degrees of freedom) exceeds this (p = 1e-4 for a right camera).
CAMERA_CHI2_LIMIT = 21.1


def _one_view(result, camera: CameraModel, ni: int = 5):
    """(model, x) of the one-view problem at the off-line result: the intrinsics (f and kappa the picture's,
    the rest ``camera``'s; ``ni`` 5: the skew held at ``camera``'s, 6: free) and the pose."""
    ts = result.tsai
    H = ts.C_H_W
    model = _Joint([result.discs.p_W], [result.disc_uv_corrected], [H[:3, :3]], ni=ni, skew=camera.skew)
    x = np.concatenate([_intr(camera.with_(f=ts.camera.f, kappa=ts.camera.kappa), ni), np.zeros(3), H[:3, 3]])
    return model, x


def _tcp_of(result, cell, cam: CameraModel, C_H_W) -> np.ndarray:
    from selfview.pcc import solve_pcc

    ft = result.fingertips
    found = np.asarray(ft.found, bool)
    cal = result.calibration
    pG = cal.points_G[cal.state][found]
    return solve_pcc(ft.uv[found], pG, C_H_W, cam).C_H_G[:3, 3]


def camera_check(result, cell, camera: CameraModel | None = None) -> dict:
    """Does the picture of an off-line calibration (``selfview.offline.OfflineResult``) show that the
    assumed camera's principal point or aspect (``camera``, default the cell's nominal one) is wrong by
    enough to cost more than the accuracy targets?

    One view with f, kappa, cx, cy, aspect and the pose all free (the skew held at the assumed camera's:
    one view does not pin it); the difference of (cx, cy, aspect) from
    the assumed ones is significant when its chi-square exceeds ``CAMERA_CHI2_LIMIT``; its cost is how far
    the TCP moves when the picture is calibrated again with the picture's own centre and aspect.
    Returns {significant, chi2, centre_offset_px [dx, dy], aspect, aspect_sigma, centre_sigma_px,
    tcp_shift_mm [3], costly, warning (str or None)}.
    """
    from selfview.tsai import calibrate_coplanar

    cam0 = camera or cell.camera.guess()
    model, x0 = _one_view(result, cam0)
    out = {"significant": False, "costly": False, "warning": None}
    try:
        res = _lm_normal(model.residuals, model.jacobian, x0, model.blocks)
    except (CalibrationError, np.linalg.LinAlgError) as exc:
        out["why"] = f"the one-view fit failed: {exc}"
        return out
    m, n = res.jacobian.shape
    s2 = res.cost / max(m - n, 1)
    cov = _covariance(res.jacobian, s2, model.blocks)
    d = res.x[2:5] - np.array([cam0.cx, cam0.cy, cam0.aspect])
    C3 = cov[2:5, 2:5]
    if not (res.converged and np.all(np.isfinite(C3))):
        out["why"] = "one picture does not determine the centre and the aspect"
        return out
    try:
        chi2 = float(d @ np.linalg.solve(C3, d))
    except np.linalg.LinAlgError:
        out["why"] = "one picture does not determine the centre and the aspect"
        return out
    sig = np.sqrt(np.diag(C3))
    out.update(chi2=chi2, centre_offset_px=[float(d[0]), float(d[1])], centre_sigma_px=[float(sig[0]), float(sig[1])],
               aspect=float(res.x[4]), aspect_sigma=float(sig[2]), assumed_aspect=float(cam0.aspect),
               significant=bool(chi2 > CAMERA_CHI2_LIMIT))
    if not out["significant"]:
        return out
    try:
        own = cam0.with_(cx=float(res.x[2]), cy=float(res.x[3]), aspect=float(res.x[4]))
        ts = calibrate_coplanar(result.discs.p_W, own.deskew_pixels(result.disc_uv_corrected), cx=own.cx, cy=own.cy,
                                aspect=own.aspect, mode="full", width=cam0.width, height=cam0.height)
        shift = (_tcp_of(result, cell, ts.camera.with_(skew=cam0.skew), ts.C_H_W)
                 - result.calibration.C_H_G[:3, 3])
    except CalibrationError as exc:
        out["why"] = f"recalibrating with the picture's own centre failed: {exc}"
        return out
    across, along = float(np.hypot(shift[0], shift[1])), float(abs(shift[2]))
    out.update(tcp_shift_mm=[float(v) for v in shift], costly=bool(across > TARGET_ACROSS_MM or along > TARGET_ALONG_MM))
    if out["costly"]:
        out["warning"] = (
            f"the picture shows the camera's principal point {np.hypot(d[0], d[1]):.1f} px from the assumed "
            f"({cam0.cx:.1f}, {cam0.cy:.1f}) (offset {d[0]:+.1f}, {d[1]:+.1f} px, +- {sig[0]:.1f}, {sig[1]:.1f}) and its "
            f"aspect {res.x[4]:.4f} +- {sig[2]:.4f} instead of {cam0.aspect:.4f}; that moves the TCP by "
            f"{across:.3f} mm across and {along:.3f} mm along the optical axis (targets {TARGET_ACROSS_MM} and "
            f"{TARGET_ALONG_MM} mm): measure the camera with 'selfview intrinsics' and calibrate with "
            "--camera CAMERA.yaml"
        )
    return out


def tcp_sigma(result, cell, camera_cov3: np.ndarray | None = None) -> dict:
    """1-sigma of the TCP in camera axes [mm] of an off-line calibration, from the covariance of the camera
    calibration and the PCC together.

    Three parts, propagated to ``C_H_G``'s translation by its derivatives (central differences through
    Tsai's pose and ``selfview.pcc.solve_pcc``): the picture's own noise in the disc centres (the
    covariance of f, kappa and the plate pose, scaled by the residual); the uncertainty of the principal
    point and aspect (``camera_cov3`` (3, 3) of cx, cy, aspect, or (4, 4) with the skew, from a camera file;
    None: taken as exact),
    through the pose and f they shift and directly; the fingertip corners' (each from two line fits: the
    edge points' RMS over sqrt(n/2) per axis). Returns {tcp_sigma_mm [3], parts {...}}.
    """
    cal = result.calibration
    cam = cal.camera
    model, x = _one_view(result, cam, ni=6)
    r = model.residuals(x)
    J = model.jacobian(x)
    m = len(r)
    p_idx = np.r_[0:2, 6:12]
    Jp, Jt = J[:, p_idx], J[:, 2:6]
    s2 = float(r @ r) / max(m - len(p_idx), 1)
    N = Jp.T @ Jp
    Ninv = np.linalg.inv(N)
    cov_p = s2 * Ninv
    dp_dt = -Ninv @ Jp.T @ Jt
    R0 = result.tsai.C_H_W[:3, :3]
    ft = result.fingertips
    found = np.asarray(ft.found, bool)
    pG = cal.points_G[cal.state][found]
    from selfview.pcc import solve_pcc

    def tcp(xv, uv=None):
        c = _with_intr(cam, xv[:6])
        H = make_H(R_from_rotvec(xv[6:9]) @ R0, xv[9:12])
        return solve_pcc(ft.uv[found] if uv is None else uv, pG, H, c).C_H_G[:3, 3]

    steps = np.r_[_STEP[0] * x[0], _STEP[1:], _POSE_STEP]
    G = np.zeros((3, 12))
    for i in range(12):
        xp, xm = x.copy(), x.copy()
        xp[i] += steps[i]
        xm[i] -= steps[i]
        G[:, i] = (tcp(xp) - tcp(xm)) / (2 * steps[i])
    Gp = G[:, p_idx]
    parts = {"picture": Gp @ cov_p @ Gp.T}
    if camera_cov3 is not None:
        C = np.asarray(camera_cov3, float)
        if C.shape not in ((3, 3), (4, 4)):
            raise ValueError(f"tcp_sigma: camera_cov3: expected (3, 3) or (4, 4), got {C.shape}")
        Gt = (G[:, 2:6] + Gp @ dp_dt)[:, : len(C)]
        parts["camera_file"] = Gt @ C @ Gt.T
    uv = ft.uv[found]
    n_edge = ft.n_edge_points[found] if ft.n_edge_points is not None else np.full(len(uv), 20)
    sc = np.nan_to_num(ft.edge_rms_px[found], nan=0.1) / np.sqrt(np.maximum(np.asarray(n_edge, float), 2) / 2)
    Cc = np.zeros((3, 3))
    for k in range(len(uv)):
        for a in range(2):
            up, um = uv.copy(), uv.copy()
            up[k, a] += 1e-3
            um[k, a] -= 1e-3
            g = (tcp(x, up) - tcp(x, um)) / 2e-3
            Cc += np.outer(g, g) * sc[k] ** 2
    parts["corners"] = Cc
    total = sum(parts.values())
    return {"tcp_sigma_mm": [float(v) for v in np.sqrt(np.clip(np.diag(total), 0, None))],
            "parts": {k: [float(v) for v in np.sqrt(np.clip(np.diag(c), 0, None))] for k, c in parts.items()}}
