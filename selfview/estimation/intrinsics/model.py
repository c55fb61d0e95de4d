"""The joint fit's camera model: plate points projected with the intrinsics as a vector, and the joint least-squares
problem of all views (residuals and analytic Jacobian)."""

from __future__ import annotations

import numpy as np

from selfview.maths.camera import CameraModel, distort
from selfview.errors import CalibrationError
from selfview.maths.geometry import R_from_rotvec, R_from_rotvecs, cross_rows, make_H, so3_left_jacobians


#: Central-difference steps: f (relative), kappa [px^-2], cx, cy [px], aspect, skew; pose: rotation [rad], shift [mm].
STEP = np.array([1e-6, 1e-12, 1e-4, 1e-4, 1e-7, 1e-7])
POSE_STEP = np.array([1e-7, 1e-7, 1e-7, 1e-5, 1e-5, 1e-5])


def central_differences(fun, x, steps) -> np.ndarray:
    """(..., P) derivatives of ``fun`` (an array) at ``x`` (P,) by central differences of ``steps`` (P,)."""
    cols = []
    for i, h in enumerate(steps):
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        cols.append((fun(xp) - fun(xm)) / (2 * h))
    return np.stack(cols, axis=-1)


def project_points(intr, R, t, p_W, skew: float = 0.0) -> np.ndarray:
    """(N, 2) distorted pixels of plate points ``p_W`` (N, 3) at pose (R, t) by ``intr`` = (f, kappa, cx, cy, aspect[,
    skew]) (else ``skew``); all NaN when any point is behind the camera or beyond the fold."""
    XYh = _distorted_sensor(intr, p_W @ R.T + t)
    return np.full((len(p_W), 2), np.nan) if XYh is None else _sensor_pixels(intr, XYh, skew)


def _distorted_sensor(intr, pc) -> np.ndarray | None:
    """(N, 2) distorted sensor X^, Y^ of camera-frame points ``pc`` (N, 3); None when any is behind the camera or
    beyond the fold (or f, aspect not positive)."""
    f, kappa, aspect = intr[0], intr[1], intr[4]
    z = pc[:, 2]
    if np.any(z <= 0) or f <= 0 or aspect <= 0:
        return None
    try:
        return distort(f * pc[:, :2] / z[:, None], kappa)
    except CalibrationError:
        return None


def _sensor_pixels(intr, XYh, skew: float = 0.0) -> np.ndarray:
    """(N, 2) pixels of distorted sensor coordinates ``XYh`` (N, 2): u = X^ / aspect + skew Y^ + cx, v = Y^ + cy."""
    cx, cy, aspect = intr[2], intr[3], intr[4]
    if len(intr) > 5:
        skew = intr[5]
    return np.column_stack([XYh[:, 0] / aspect + skew * XYh[:, 1] + cx, XYh[:, 1] + cy])


def intrinsics_vector(camera: CameraModel, ni: int = 6) -> np.ndarray:
    """The intrinsics vector of ``camera``: (f, kappa, cx, cy, aspect[, skew]) (``ni`` 5 or 6)."""
    return np.array([camera.f, camera.kappa, camera.cx, camera.cy, camera.aspect, camera.skew][:ni])


def with_intrinsics(camera: CameraModel, x) -> CameraModel:
    """``camera`` with the intrinsics ``x[:5]`` (and ``x[5]``, its skew, when given)."""
    c = camera.with_(f=float(x[0]), kappa=float(x[1]), cx=float(x[2]), cy=float(x[3]), aspect=float(x[4]))
    return c.with_(skew=float(x[5])) if len(x) > 5 else c


class JointProblem:
    """x = (f, kappa, cx, cy, aspect[, skew], per view omega (3), t (3), then ``shape``'s parameters); view k's rotation
    exp(omega_k) R0_k; ``ni`` 6 with the skew free, 5 with it held at ``skew``. Residuals model minus observation, per
    view (u then v), then the shape's prior rows. Raises ``ValueError`` for another ``ni``."""

    def __init__(self, p_W: list, uv: list, R0: list, shape=None, idx: list | None = None,
                 *, ni: int = 5, skew: float = 0.0):
        if ni not in (5, 6):
            raise ValueError(f"intrinsics: expected 5 or 6 intrinsic parameters, got {ni}")
        self.p_W, self.uv, self.R0 = p_W, uv, np.asarray(R0, float).reshape(-1, 3, 3)
        self.ni, self.skew = int(ni), float(skew)
        self.n = [len(p) for p in p_W]
        self.off = np.concatenate([[0], np.cumsum([2 * k for k in self.n])]).astype(int)
        self.shape = shape if shape is not None and shape.n else None
        self.idx = idx
        self.m_data = int(self.off[-1])
        # each stacked point's view, its u and v rows in the residuals, its pose columns
        self.vid = np.repeat(np.arange(len(p_W)), self.n)
        first = np.repeat(self.off[:-1], self.n)
        local = np.arange(len(self.vid)) - np.repeat(np.cumsum([0, *self.n[:-1]]), self.n)
        self.ru, self.rv = first + local, first + local + np.repeat(self.n, self.n)
        self.P = np.concatenate(p_W).reshape(-1, 3) if len(self.vid) else np.zeros((0, 3))
        self.UV = np.concatenate(uv).reshape(-1, 2) if len(self.vid) else np.zeros((0, 2))
        self.idx_all = np.concatenate(idx) if self.shape else None
        self.dp_dy = self.shape.dp_dy(self.idx_all) if self.shape else None  # constant: the shape is linear
        self.pose_cols = self.ni + 6 * self.vid[:, None] + np.arange(6)
        self._last = None  # (x, _camera_points(x)) of the last parameters projected

    def _y(self, x):
        return x[self.ni + 6 * len(self.p_W) :]

    def points(self, x, k) -> np.ndarray:
        return self.p_W[k] + self.shape.offsets(self._y(x), self.idx[k]) if self.shape else self.p_W[k]

    def view(self, x, k) -> np.ndarray:
        j = self.ni + 6 * k
        R = R_from_rotvec(x[j : j + 3]) @ self.R0[k]
        m = project_points(x[: self.ni], R, x[j + 3 : j + 6], self.points(x, k), self.skew)
        return (m - self.uv[k]).T.ravel()

    def _camera_points(self, x):
        """(rotations, d = R p, camera-frame points, distorted sensor coordinates or None) at ``x``; the last kept,
        as the solver asks for the Jacobian where it has just evaluated the residuals."""
        if self._last is not None and np.array_equal(self._last[0], x):
            return self._last[1]
        poses = x[self.ni : self.ni + 6 * len(self.p_W)].reshape(-1, 6)
        Rv = (R_from_rotvecs(poses[:, :3]) @ self.R0)[self.vid]
        P = self.P + self.shape.offsets(self._y(x), self.idx_all) if self.shape else self.P
        d = np.einsum("nij,nj->ni", Rv, P)
        pc = d + poses[self.vid, 3:]
        out = (Rv, d, pc, _distorted_sensor(x[: self.ni], pc))
        self._last = (np.array(x, float), out)
        return out

    def residuals(self, x) -> np.ndarray:
        """Every view's residuals; all NaN when a point is behind the camera or beyond the fold (no such step is
        accepted)."""
        XYh = self._camera_points(x)[3]
        if XYh is None:
            m = np.full((len(self.vid), 2), np.nan)
        else:
            m = _sensor_pixels(x[: self.ni], XYh, self.skew) - self.UV
        r = np.empty(self.m_data)
        r[self.ru], r[self.rv] = m[:, 0], m[:, 1]
        return np.concatenate([r, self.shape.w * self._y(x)]) if self.shape else r

    def jacobian(self, x) -> np.ndarray:
        """Analytic (as ``tsai``'s full model, with cx, cy, aspect, skew and shape: u = X^ / aspect + skew Y^ + cx);
        ``CalibrationError`` when a disc is behind the camera or the Jacobian is not finite."""
        f, kappa, cx, cy, aspect = x[:5]
        ni = self.ni
        skew = x[5] if ni > 5 else self.skew
        s0 = ni + 6 * len(self.p_W)
        J = np.zeros((self.m_data + (self.shape.n if self.shape else 0), len(x)))
        Rv, d, pc, XYh = self._camera_points(x)
        z = pc[:, 2]
        if np.any(z <= 0):
            raise CalibrationError("intrinsics: a disc lies behind the camera near the current parameters")
        X, Y = f * pc[:, 0] / z, f * pc[:, 1] / z
        if XYh is None:  # beyond the fold: the camera model's own error
            XYh = distort(np.column_stack([X, Y]), kappa)
        Xh, Yh = XYh[:, 0], XYh[:, 1]
        rh2 = Xh * Xh + Yh * Yh
        a = 1.0 + kappa * rh2
        c = 2.0 * kappa / (a + 2.0 * kappa * rh2)
        m00, m11, m01 = (1.0 - c * Xh * Xh) / a, (1.0 - c * Yh * Yh) / a, -c * Xh * Yh / a
        Jl = so3_left_jacobians(x[ni:s0].reshape(-1, 6)[:, :3])[self.vid]
        D = self.dp_dy
        for rows, (mu0, mu1) in ((self.ru, (m00 / aspect + skew * m01, m01 / aspect + skew * m11)),
                                 (self.rv, (m01, m11))):
            g = np.column_stack([mu0, mu1, -(mu0 * X + mu1 * Y) / f]) * (f / z)[:, None]
            J[rows, 0] = (mu0 * X + mu1 * Y) / f
            J[rows, 1] = -(mu0 * Xh + mu1 * Yh) * rh2
            J[rows[:, None], self.pose_cols] = np.column_stack([np.einsum("na,nab->nb", cross_rows(d, g), Jl), g])
            if D is not None:
                J[rows, s0:] = np.einsum("na,nas->ns", np.einsum("na,nab->nb", g, Rv), D)
        J[self.ru, 2] = 1.0
        J[self.rv, 3] = 1.0
        J[self.ru, 4] = -Xh / aspect**2
        if ni > 5:
            J[self.ru, 5] = Yh
        if self.shape:
            J[self.m_data :, s0:] = np.diag(self.shape.w)
        if not np.all(np.isfinite(J)):
            raise CalibrationError("intrinsics: the model cannot see every disc near the current parameters")
        return J

    def normal_matrix(self, J) -> np.ndarray:
        """J^T J skipping the zero blocks: view k's pose columns meet only its own rows (block-diagonal poses)."""
        shared = np.r_[0 : self.ni, self.ni + 6 * len(self.p_W) : J.shape[1]]
        Js = J[:, shared]
        A = np.zeros((J.shape[1], J.shape[1]))
        A[np.ix_(shared, shared)] = Js.T @ Js
        for k in range(len(self.p_W)):
            rows, c = slice(self.off[k], self.off[k + 1]), self.ni + 6 * k
            Jp = J[rows, c : c + 6]
            A[c : c + 6, c : c + 6] = Jp.T @ Jp
            A[c : c + 6, shared] = Jp.T @ Js[rows]
            A[shared, c : c + 6] = A[c : c + 6, shared].T
        return A

    def pose(self, x, k) -> np.ndarray:
        j = self.ni + 6 * k
        return make_H(R_from_rotvec(x[j : j + 3]) @ self.R0[k], x[j + 3 : j + 6])
