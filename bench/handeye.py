"""Classical hand/eye calibration, AX = XB (the paper's references [7, 9, 11]): the yardstick the self-viewing
method is compared with. From N stations (flange pose ``base_H_F_i`` from the kinematics, plate pose
``C_H_W_i`` from the picture) it solves ``X = F_H_C`` over all station pairs, ``A X = X B`` with
``A = base_H_F_j^-1 base_H_F_i`` and ``B = C_H_W_j C_H_W_i^-1``, by Tsai-Lenz or Park-Martin (pure numpy);
``C_H_G = X^-1 F_H_G`` then carries every error of the kinematics, which the self-viewing method avoids.
Degenerate input (under three stations, parallel rotation axes, stations out of order) raises
``CalibrationError``. ``plate_pose`` gives ``C_H_W`` from a picture's discs with f and kappa held fixed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import PlateSpec
from selfview.measurement.discs import DiscDetections
from selfview.measurement.plates import correct_plate_bias
from selfview.errors import CalibrationError, ConfigError
from selfview.maths.geometry import R_from_rotvec, check_rigid, hat, inv_H, make_H, rotation_angle, rotvec_from_R
from selfview.estimation.online import recalibrate
from selfview.estimation.tsai import calibrate_coplanar

__all__ = ["METHODS", "HandEyeResult", "plate_pose", "relative_motions", "calibrate_handeye"]

METHODS: tuple[str, ...] = ("tsai-lenz", "park-martin")

#: Motions that turn less than this carry no usable rotation axis (deg).
MIN_MOTION_DEG = 0.5
#: Smallest ratio of the second to the first singular value of the motions' unit rotation axes:
#: below it the axes are parallel (the sine of the largest angle between them is about this).
PARALLEL_LIMIT = 0.02
#: Largest median difference (deg) between a robot motion's rotation angle and the camera's: above it
#: the two lists do not describe the same motions (stations paired out of order).
MAX_ANGLE_MISMATCH_DEG = 2.0

# The identity and the half turns about x, y, z: one of them is always within 120 deg of any rotation.
_PRE_TURNS = (np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]))


@dataclass(frozen=True)
class HandEyeResult:
    """Result of ``calibrate_handeye``.

    ``F_H_C`` (4, 4) X of ``A X = X B``: the camera's pose in the flange frame; ``C_H_F`` its inverse;
    ``base_H_W`` (4, 4) the plate in the base frame, averaged over the stations; ``plate_spread_mm`` the
    RMS distance of each station's ``base_H_F_i X C_H_W_i`` origin from that mean (how consistent the
    stations are); ``rotation_residual_deg``, ``translation_residual_mm`` RMS residuals of the rotation
    and translation parts of A X = X B over the motions; ``n_poses``, ``n_motions``; ``method``.
    """

    method: str
    F_H_C: np.ndarray
    C_H_F: np.ndarray
    base_H_W: np.ndarray
    plate_spread_mm: float
    rotation_residual_deg: float
    translation_residual_mm: float
    n_poses: int
    n_motions: int

    def C_H_G(self, F_H_G) -> np.ndarray:
        """The gripper-to-camera transform (4, 4) through the tool transform ``F_H_G`` (4, 4)."""
        return self.C_H_F @ np.asarray(F_H_G, dtype=float)

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "F_H_C": self.F_H_C.tolist(),
            "base_H_W": self.base_H_W.tolist(),
            "plate_spread_mm": self.plate_spread_mm,
            "rotation_residual_deg": self.rotation_residual_deg,
            "translation_residual_mm": self.translation_residual_mm,
            "n_poses": self.n_poses,
            "n_motions": self.n_motions,
        }


def plate_pose(det: DiscDetections, camera: CameraModel, plate: PlateSpec) -> np.ndarray:
    """``C_H_W`` (4, 4) of a plate from its detected discs (``selfview.measurement.discs.DiscDetections``) with the
    interior orientation ``camera`` held fixed (f, kappa from an earlier calibration): Tsai's pose as
    the start, the exterior orientation refined over all discs (``selfview.estimation.online.recalibrate``), the
    discs' perspective bias removed and the pose refined again. Raises ``CalibrationError``."""
    ts = calibrate_coplanar(det.p_W, det.uv, cx=camera.cx, cy=camera.cy, aspect=camera.aspect,
                            width=camera.width, height=camera.height,
                            f_guess=camera.f, kappa_guess=camera.kappa)
    C_H_W = recalibrate(ts.C_H_W, det.p_W, det.uv, camera).C_H_G
    uv_c = correct_plate_bias(det, camera, C_H_W, plate)
    return recalibrate(C_H_W, det.p_W, uv_c, camera).C_H_G


def _check_poses(base_H_F, C_H_W) -> tuple[list[np.ndarray], list[np.ndarray]]:
    if isinstance(base_H_F, np.ndarray) and base_H_F.ndim == 3:
        base_H_F = list(base_H_F)
    if isinstance(C_H_W, np.ndarray) and C_H_W.ndim == 3:
        C_H_W = list(C_H_W)
    if len(base_H_F) != len(C_H_W):
        raise ConfigError(f"hand/eye: {len(base_H_F)} robot poses for {len(C_H_W)} camera poses; one of each per station")
    F = [check_rigid(H, f"base_H_F[{i}]") for i, H in enumerate(base_H_F)]
    C = [check_rigid(H, f"C_H_W[{i}]") for i, H in enumerate(C_H_W)]
    if len(F) < 3:
        raise CalibrationError(
            f"hand/eye calibration needs at least 2 motions (3 stations) with different rotation axes, got {len(F)} station(s)"
        )
    return F, C


def relative_motions(base_H_F, C_H_W) -> tuple[np.ndarray, np.ndarray]:
    """The motions (A, B) of ``A X = X B`` for all pairs i < j of stations: A (M, 4, 4) of the flange
    (``base_H_F_j^-1 base_H_F_i``), B (M, 4, 4) of the camera (``C_H_W_j C_H_W_i^-1``), M = N (N - 1) / 2.
    Raises ``ConfigError`` for unequal lists or a matrix that is not a rigid transform."""
    F, C = _check_poses(base_H_F, C_H_W)
    A, B = [], []
    for i in range(len(F)):
        Ci = inv_H(C[i])
        for j in range(i + 1, len(F)):
            A.append(inv_H(F[j]) @ F[i])
            B.append(C[j] @ Ci)
    return np.array(A), np.array(B)


def _check_motions(A: np.ndarray, B: np.ndarray) -> None:
    """Refuse motions that cannot determine X, naming why."""
    ang_A = np.array([np.degrees(rotation_angle(a)) for a in A])
    ang_B = np.array([np.degrees(rotation_angle(b)) for b in B])
    mism = float(np.median(np.abs(ang_A - ang_B)))
    if mism > MAX_ANGLE_MISMATCH_DEG:
        raise CalibrationError(
            f"hand/eye: the robot's and the camera's motions turn by different angles (median difference "
            f"{mism:.2f} deg > {MAX_ANGLE_MISMATCH_DEG} deg): the stations are not paired in order (robot pose i "
            "with picture i)"
        )
    use = ang_A >= MIN_MOTION_DEG
    if use.sum() < 2:
        raise CalibrationError(
            f"hand/eye: only {int(use.sum())} motion(s) turn the flange by {MIN_MOTION_DEG} deg or more; "
            "at least 2 rotations about different axes are needed"
        )
    axes = np.array([rotvec_from_R(a) for a in A[use]])
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    s = np.linalg.svd(axes, compute_uv=False)
    if s[1] < PARALLEL_LIMIT * s[0]:
        raise CalibrationError(
            f"hand/eye: the rotation axes of all {int(use.sum())} motions are parallel (spread {s[1] / s[0]:.1e} < "
            f"{PARALLEL_LIMIT}): X's translation along that axis is undetermined; turn the wrist about a second axis"
        )


def _rotation_tsai_lenz(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """R_X from ``skew(p_A + p_B) c = p_B - p_A`` (Tsai and Lenz), the camera frame pre-turned so that
    the rotation left to find is well away from a half turn."""
    best = None
    for Q in _PRE_TURNS:
        # A X = X B  <=>  A (X Q^T) = (X Q^T) (Q B Q^T): solve for R' = R_X Q^T, then R_X = R' Q
        rows, rhs = [], []
        for a, b in zip(A, B):
            ra, rb = a[:3, :3], Q @ b[:3, :3] @ Q.T
            pa = 2.0 * np.sin(rotation_angle(ra) / 2.0) * _unit_axis(ra)
            pb = 2.0 * np.sin(rotation_angle(rb) / 2.0) * _unit_axis(rb)
            rows.append(hat(pa + pb))
            rhs.append(pb - pa)
        c, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)
        theta = 2.0 * np.arctan(np.linalg.norm(c))
        if best is None or theta < best[0]:
            n = np.linalg.norm(c)
            R1 = R_from_rotvec(c / n * theta) if n > 0 else np.eye(3)
            best = (theta, R1 @ Q)
    return best[1]


def _unit_axis(R: np.ndarray) -> np.ndarray:
    v = rotvec_from_R(R)
    n = np.linalg.norm(v)
    return v / n if n > 0 else np.zeros(3)


def _rotation_park_martin(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """R_X = (M^T M)^(-1/2) M^T with M = sum beta alpha^T (Park and Martin), as the nearest rotation."""
    M = np.zeros((3, 3))
    for a, b in zip(A, B):
        M += np.outer(rotvec_from_R(b[:3, :3]), rotvec_from_R(a[:3, :3]))
    U, _, Vt = np.linalg.svd(M.T)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _translation(A: np.ndarray, B: np.ndarray, R_X: np.ndarray) -> np.ndarray:
    """t_X from ``(R_A - I) t_X = R_X t_B - t_A`` over all motions, least squares."""
    L = np.vstack([a[:3, :3] - np.eye(3) for a in A])
    r = np.concatenate([R_X @ b[:3, 3] - a[:3, 3] for a, b in zip(A, B)])
    t, *_ = np.linalg.lstsq(L, r, rcond=None)
    return t


def calibrate_handeye(base_H_F, C_H_W, method: str = "tsai-lenz") -> HandEyeResult:
    """Solve ``A X = X B`` for X = ``F_H_C`` from N >= 3 stations (module docstring).

    ``base_H_F`` N (4, 4) flange poses in the robot's base frame [mm] (from its kinematics), ``C_H_W``
    N (4, 4) poses of the fixed plate in the camera [mm] (from the pictures), in the same order;
    ``method`` one of ``METHODS``. Raises ``ConfigError`` for an unknown method, unequal lists or a
    matrix that is not rigid; ``CalibrationError`` for fewer than 2 motions, parallel rotation axes,
    or robot and camera motions that do not match.
    """
    if method not in METHODS:
        raise ConfigError(f"hand/eye method {method!r}: expected one of {', '.join(METHODS)}")
    F, C = _check_poses(base_H_F, C_H_W)
    A, B = relative_motions(F, C)
    _check_motions(A, B)
    R_X = _rotation_tsai_lenz(A, B) if method == "tsai-lenz" else _rotation_park_martin(A, B)
    X = make_H(R_X, _translation(A, B, R_X))
    # residuals of A X = X B and the plate's consistency over the stations
    rot_res, tr_res = [], []
    for a, b in zip(A, B):
        L, R = a @ X, X @ b
        rot_res.append(np.degrees(np.linalg.norm(rotvec_from_R(L[:3, :3] @ R[:3, :3].T))))
        tr_res.append(np.linalg.norm(L[:3, 3] - R[:3, 3]))
    plates = np.array([f @ X @ c for f, c in zip(F, C)])
    t_mean = plates[:, :3, 3].mean(axis=0)
    U, _, Vt = np.linalg.svd(plates[:, :3, :3].sum(axis=0))
    R_mean = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    spread = float(np.sqrt(np.mean(np.sum((plates[:, :3, 3] - t_mean) ** 2, axis=1))))
    return HandEyeResult(
        method=method,
        F_H_C=X,
        C_H_F=inv_H(X),
        base_H_W=make_H(R_mean, t_mean),
        plate_spread_mm=spread,
        rotation_residual_deg=float(np.sqrt(np.mean(np.square(rot_res)))),
        translation_residual_mm=float(np.sqrt(np.mean(np.square(tr_res)))),
        n_poses=len(F),
        n_motions=len(A),
    )
