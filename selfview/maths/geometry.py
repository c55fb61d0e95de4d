"""Homogeneous transforms and rotation parametrisations (``CONVENTIONS.md``): ``A_H_B`` (4, 4) maps frame B to frame A,
``p_A = A_H_B p_B``; translations in mm, angles in radians (degrees: controller poses, ``pose_difference``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfview.errors import ConfigError

__all__ = ["make_H", "inv_H", "trans", "rot_x", "rot_y", "rot_z", "rot_axis", "delta_star", "orthonormalize",
           "is_rigid", "check_rigid", "R_from_rotvec", "rotvec_from_R", "H_from_rotvec", "R_from_rpy", "rpy_from_R",
           "EulerConvention", "VAL_OAT", "H_from_xyzoat", "xyzoat_from_H", "transform_points", "rotation_angle",
           "pose_difference", "so3_left_jacobian", "cross_rows", "hat"]


def make_H(R: np.ndarray, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) transform from a (3, 3) rotation ``R`` and a translation ``t`` (mm)."""
    H = np.eye(4)
    H[:3, :3] = np.asarray(R, dtype=float)
    H[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return H


def inv_H(H: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (4, 4) transform (uses R^T, not a general inverse)."""
    H = np.asarray(H, dtype=float)
    return make_H(H[:3, :3].T, -H[:3, :3].T @ H[:3, 3])


def trans(dx: float, dy: float, dz: float) -> np.ndarray:
    """Trans(dx, dy, dz) of eq. 11."""
    return make_H(np.eye(3), (dx, dy, dz))


def _rot3(axis: int, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    if axis == 0:
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == 1:
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def rot_x(a: float) -> np.ndarray:
    """Rot(x, a), a in radians, as a (4, 4) transform."""
    return make_H(_rot3(0, a))


def rot_y(a: float) -> np.ndarray:
    """Rot(y, a), a in radians, as a (4, 4) transform."""
    return make_H(_rot3(1, a))


def rot_z(a: float) -> np.ndarray:
    """Rot(z, a), a in radians, as a (4, 4) transform."""
    return make_H(_rot3(2, a))


def rot_axis(axis, angle: float, point=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(4, 4) rotation by ``angle`` (rad) about the line through ``point`` (mm) along ``axis``."""
    axis = np.asarray(axis, dtype=float).reshape(3)
    n = np.linalg.norm(axis)
    if n == 0:
        raise ValueError("rotation axis has zero length")
    R = R_from_rotvec(axis / n * angle)
    p = np.asarray(point, dtype=float).reshape(3)
    return make_H(R, p - R @ p)


def delta_star(delta, d) -> np.ndarray:
    """Delta* of eq. 12 from rotations ``delta`` (3,) [rad] and translations ``d`` (3,) [mm]; first order in delta."""
    dx, dy, dz = map(float, delta)
    # np.fromiter on a flat tuple: a third cheaper than np.array (NP-U's 50 us budget per picture)
    rows = (
        1.0, -dz, dy, float(d[0]),
        dz, 1.0, -dx, float(d[1]),
        -dy, dx, 1.0, float(d[2]),
        0.0, 0.0, 0.0, 1.0,
    )  # fmt: skip
    return np.fromiter(rows, float, 16).reshape(4, 4)


def orthonormalize(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius norm, by SVD) to a (3, 3) matrix, or to a (4, 4) transform's rotation block."""
    M = np.asarray(M, dtype=float)
    if M.shape == (4, 4):
        return make_H(orthonormalize(M[:3, :3]), M[:3, 3])
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def is_rigid(H, tol: float = 1e-6) -> bool:
    """True if ``H`` is a (4, 4) rigid transform within ``tol`` (``check_rigid`` accepts it)."""
    try:
        check_rigid(H, tol=tol)
    except ConfigError:
        return False
    return True


def check_rigid(H, name: str = "transform", tol: float = 1e-3) -> np.ndarray:
    """``H`` as a float (4, 4) array, rotation re-orthonormalised; ``ConfigError`` naming ``name`` and the fault.
    ``tol`` admits matrices printed to 4 digits."""
    try:
        A = np.asarray(H, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name}: expected a 4x4 nested list of numbers, got {H!r}") from exc
    if A.shape != (4, 4):
        raise ConfigError(f"{name}: expected a 4x4 matrix, got shape {A.shape}")
    if not np.all(np.isfinite(A)):
        raise ConfigError(f"{name}: contains non-finite values")
    if not np.allclose(A[3], [0, 0, 0, 1], atol=tol):
        raise ConfigError(f"{name}: bottom row must be [0, 0, 0, 1], got {A[3].tolist()}")
    R = A[:3, :3]
    err = np.abs(R.T @ R - np.eye(3)).max()
    if err > tol or np.linalg.det(R) < 0:
        raise ConfigError(f"{name}: not a rigid transform (rotation block off orthonormal by {err:.2e}, "
                          f"det {np.linalg.det(R):+.4f}); expected a rotation with det +1")
    return orthonormalize(A)


def hat(v) -> np.ndarray:
    """(3, 3) cross-product matrix of v (3,): hat(v) @ p = v x p."""
    return _hats(np.asarray(v, dtype=float).reshape(1, 3))[0]


def R_from_rotvec(v) -> np.ndarray:
    """(3, 3) rotation from a rotation vector (axis * angle, rad), Rodrigues' formula."""
    return R_from_rotvecs(np.asarray(v, dtype=float).reshape(1, 3))[0]


def _hats(V: np.ndarray) -> np.ndarray:
    K = np.zeros((len(V), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -V[:, 2], V[:, 1], -V[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = V[:, 2], -V[:, 1], V[:, 0]
    return K


def R_from_rotvecs(V) -> np.ndarray:
    """(N, 3, 3) rotations from rotation vectors (N, 3), ``R_from_rotvec`` of each row."""
    V = np.asarray(V, dtype=float).reshape(-1, 3)
    th = np.linalg.norm(V, axis=1)
    small = th < 1e-12
    K = _hats(V)
    Kn = K / np.where(small, 1.0, th)[:, None, None]
    s = np.where(small, 1.0, np.sin(th))[:, None, None]
    c = np.where(small, 0.0, 1 - np.cos(th))[:, None, None]
    return np.eye(3) + s * Kn + c * (Kn @ Kn)


def rotvec_from_R(R) -> np.ndarray:
    """Rotation vector (rad) of a (3, 3) rotation, exact near 0 and pi."""
    R = np.asarray(R, dtype=float)[:3, :3]
    th = rotation_angle(R)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if th < 1e-6:
        return w / 2
    if np.pi - th < 1e-4:
        # near pi the antisymmetric part vanishes: take the axis from the symmetric part
        B = (R + np.eye(3)) / 2
        k = int(np.argmax(np.diag(B)))
        axis = B[:, k] / np.sqrt(max(B[k, k], 1e-300))
        if np.dot(axis, w) < 0:
            axis = -axis
        return axis / np.linalg.norm(axis) * th
    return w / (2 * np.sin(th)) * th


def H_from_rotvec(rv, t) -> np.ndarray:
    """(4, 4) transform from a rotation vector (rad) and a translation (mm)."""
    return make_H(R_from_rotvec(rv), t)


def R_from_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Roll-pitch-yaw (rad): R = Rz(yaw) Ry(pitch) Rx(roll), fixed axes x, y, z."""
    return _rot3(2, yaw) @ _rot3(1, pitch) @ _rot3(0, roll)


def rpy_from_R(R) -> tuple[float, float, float]:
    """Inverse of ``R_from_rpy``; at pitch = +-90 degrees roll is set to 0."""
    R = np.asarray(R, dtype=float)[:3, :3]
    pitch = np.arctan2(-R[2, 0], np.hypot(R[0, 0], R[1, 0]))
    if np.hypot(R[0, 0], R[1, 0]) < 1e-9:
        return 0.0, float(pitch), float(np.arctan2(-R[0, 1], R[1, 1]))
    return float(np.arctan2(R[2, 1], R[2, 2])), float(pitch), float(np.arctan2(R[1, 0], R[0, 0]))


@dataclass(frozen=True)
class EulerConvention:
    """How a controller's three angles (VAL's O, A, T) [deg] map to a rotation, with intrinsic rotations E:
    ``R = base @ E(sequence[0], s0*(a0+o0)) @ E(sequence[1], s1*(a1+o1)) @ E(sequence[2], s2*(a2+o2)) @ tool``,
    ``signs`` s, ``offsets_deg`` o, ``base``, ``tool`` (3, 3). Default: VAL's ZYZ (O about z, A new y, T new z)."""

    sequence: str = "zyz"
    signs: tuple[float, float, float] = (1.0, 1.0, 1.0)
    offsets_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    base: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    tool: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    def __post_init__(self):
        seq = self.sequence.lower()
        if len(seq) != 3 or any(c not in "xyz" for c in seq) or seq[0] == seq[1] or seq[1] == seq[2]:
            raise ConfigError(f"euler sequence: expected three axes like 'zyz' or 'zyx', got {self.sequence!r}")
        for nm in ("base", "tool"):
            R = np.asarray(getattr(self, nm), dtype=float)
            if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                raise ConfigError(f"euler {nm}: expected a 3x3 rotation, got {getattr(self, nm)!r}")

    def to_R(self, angles_deg) -> np.ndarray:
        """(3, 3) rotation from three angles in degrees."""
        R = np.asarray(self.base, dtype=float)
        for ax, a, s, o in zip(self.sequence.lower(), angles_deg, self.signs, self.offsets_deg):
            R = R @ _rot3("xyz".index(ax), np.radians(s * (float(a) + o)))
        return R @ np.asarray(self.tool, dtype=float)

    def from_R(self, R) -> tuple[float, float, float]:
        """Three angles in degrees (each in (-180, 180]) that ``to_R`` maps back to ``R``."""
        R = np.asarray(self.base, dtype=float).T @ np.asarray(R, dtype=float)[:3, :3] @ np.asarray(self.tool).T
        i, j, k = ("xyz".index(c) for c in self.sequence.lower())
        angs = _proper_euler(R, i, j) if i == k else _tait_bryan(R, i, j, k)  # zyz-like, or zyx-like
        degs = (np.degrees(a) / s - o for a, s, o in zip(angs, self.signs, self.offsets_deg))
        return tuple(float(v) if abs(v) == 180.0 else float((v + 180.0) % 360.0 - 180.0) for v in degs)


def _third_angle(R, a, b, i, j, k):
    """The last angle c of R = E_i(a) E_j(b) E_k(c), from R after a and b: near gimbal lock a and c each rest on
    rounding noise, and taking both from R gave errors up to 18 degrees."""
    M = (_rot3(i, a) @ _rot3(j, b)).T @ R
    u, v = (k + 1) % 3, (k + 2) % 3
    return np.arctan2(M[v, u], M[u, u])


def _proper_euler(R, i, j):
    # R = E_i(a) E_j(b) E_i(c), with the third axis m completing i, j
    m = 3 - i - j
    par = 1.0 if (i, j, m) in ((0, 1, 2), (1, 2, 0), (2, 0, 1)) else -1.0
    sb = np.hypot(R[i, j], R[i, m])
    b = np.arctan2(sb, R[i, i])
    a = 0.0 if sb < 1e-9 else np.arctan2(R[j, i], -par * R[m, i])  # gimbal lock: c takes all of a + c
    return a, b, _third_angle(R, a, b, i, j, i)


def _tait_bryan(R, i, j, k):
    par = 1.0 if (i, j, k) in ((0, 1, 2), (1, 2, 0), (2, 0, 1)) else -1.0
    # R = E_i(a) E_j(b) E_k(c); b by atan2: arcsin of 1 - 1e-16 falls 1e-8 rad short of 90 deg, missing gimbal lock
    cb = np.hypot(R[i, i], R[i, j])
    b = np.arctan2(par * R[i, k], cb)
    a = np.arctan2(par * R[k, j], R[j, j]) if cb < 1e-9 else np.arctan2(-par * R[j, k], R[k, k])  # gimbal lock: c = 0
    return a, b, _third_angle(R, a, b, i, j, k)


VAL_OAT = EulerConvention()


def H_from_xyzoat(pose, convention: EulerConvention = VAL_OAT) -> np.ndarray:
    """(4, 4) transform from a controller pose ``(x, y, z, o, a, t)`` (mm, degrees)."""
    x, y, z, o, a, t = (float(v) for v in pose)
    return make_H(convention.to_R((o, a, t)), (x, y, z))


def xyzoat_from_H(H, convention: EulerConvention = VAL_OAT) -> tuple[float, ...]:
    """Controller pose ``(x, y, z, o, a, t)`` (mm, degrees) of a (4, 4) transform."""
    H = np.asarray(H, dtype=float)
    o, a, t = convention.from_R(H[:3, :3])
    return (float(H[0, 3]), float(H[1, 3]), float(H[2, 3]), o, a, t)


def transform_points(H, p) -> np.ndarray:
    """Apply a (4, 4) transform to points ``p`` of shape (N, 3) or (3,)."""
    H = np.asarray(H, dtype=float)
    return np.asarray(p, dtype=float) @ H[:3, :3].T + H[:3, 3]


def rotation_angle(R) -> float:
    """Angle (rad) of a rotation, the magnitude of its rotation vector."""
    R = np.asarray(R, dtype=float)[:3, :3]
    return float(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0)))


def pose_difference(A_H_B, A_H_B_ref) -> tuple[float, float]:
    """(rotation angle in degrees, translation distance in mm) between two estimates of one transform."""
    A, B = np.asarray(A_H_B, dtype=float), np.asarray(A_H_B_ref, dtype=float)
    dR = orthonormalize(A[:3, :3]) @ B[:3, :3].T
    return float(np.degrees(rotation_angle(dR))), float(np.linalg.norm(A[:3, 3] - B[:3, 3]))


def so3_left_jacobian(omega: np.ndarray) -> np.ndarray:
    """Left Jacobian of SO(3) at rotation vector ``omega``: exp(omega + d) = exp(J_l d) exp(omega)."""
    return so3_left_jacobians(np.asarray(omega, dtype=float).reshape(1, 3))[0]


def so3_left_jacobians(Omega) -> np.ndarray:
    """(N, 3, 3) left Jacobians of SO(3) at the rotation vectors (N, 3) (``so3_left_jacobian`` of each row)."""
    Omega = np.asarray(Omega, dtype=float).reshape(-1, 3)
    th = np.linalg.norm(Omega, axis=1)
    small = th < 1e-8
    K = _hats(Omega)
    t = np.where(small, 1.0, th)
    a = np.where(small, 0.5, (1 - np.cos(t)) / t**2)[:, None, None]
    b = np.where(small, 0.0, (t - np.sin(t)) / t**3)[:, None, None]
    return np.eye(3) + a * K + b * (K @ K)


def cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of (N, 3) arrays (cheaper than np.cross)."""
    return np.column_stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])
