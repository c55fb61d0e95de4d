"""The paper's camera model (eq. 1-4) in the pixel units of ``CONVENTIONS.md``; integer (u, v) is a pixel's centre.
Distorted sensor coordinates [px]: X^ = aspect (u - cx - skew (v - cy)), Y^ = v - cy; undistorted (eq. 4):
X = X^ (1 + kappa r^2), Y = Y^ (1 + kappa r^2), r^2 = X^^2 + Y^^2; eq. 3: X = f x / z, Y = f y / z (camera frame, mm).
``distort`` inverts eq. 4 exactly by solving kappa r^3 + r - R = 0 for the distorted radius r."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from selfview.errors import CalibrationError, ConfigError

__all__ = ["CameraModel", "undistort", "distort", "max_undistorted_radius", "MAX_SKEW"]

#: Largest |skew|: 0.01 shears a CCIR picture 5.8 px top to bottom, ten times the worst analogue grabber's PLL shear.
MAX_SKEW = 0.01


def _as_points(a, dim: int, name: str) -> tuple[np.ndarray, bool]:
    a = np.asarray(a, dtype=float)
    single = a.ndim == 1
    a = np.atleast_2d(a)
    if a.shape[-1] != dim or a.ndim != 2:
        raise ValueError(f"{name}: expected shape (N, {dim}) or ({dim},), got {np.shape(a)}")
    return a, single


def undistort(XY_hat, kappa: float) -> np.ndarray:
    """Eq. 4: distorted sensor coordinates (N, 2) -> undistorted (N, 2), pixel units."""
    XY_hat = np.asarray(XY_hat, dtype=float)
    r2 = np.sum(XY_hat * XY_hat, axis=-1, keepdims=True)
    return XY_hat * (1.0 + kappa * r2)


def max_undistorted_radius(kappa: float) -> float:
    """Largest undistorted radius [px] a pixel sees: inf for kappa >= 0, else R(r) = r + kappa r^3 at its peak."""
    if kappa >= 0:
        return np.inf
    r = np.sqrt(-1.0 / (3.0 * kappa))
    return float(r + kappa * r**3)


def _distorted_radius(R: np.ndarray, kappa: float) -> np.ndarray:
    """The root r of kappa r^3 + r - R = 0 on the branch through r = 0."""
    R = np.asarray(R, dtype=float)
    if kappa == 0.0:
        return R.copy()
    if kappa > 0:
        # monotonic: one real root, by Cardano
        p, q = 1.0 / kappa, -R / kappa
        disc = np.sqrt((q / 2) ** 2 + (p / 3) ** 3)
        r = np.cbrt(-q / 2 + disc) + np.cbrt(-q / 2 - disc)
    else:
        Rmax = max_undistorted_radius(kappa)
        if np.any(R > Rmax * (1 + 1e-12)):
            raise CalibrationError(f"point beyond the lens's field of view: undistorted radius {float(np.max(R)):.1f} "
                                   f"px exceeds {Rmax:.1f} px reachable with kappa={kappa:.3e}")
        p = 1.0 / kappa  # negative
        m = 2.0 * np.sqrt(-p / 3.0)
        arg = np.clip(3.0 * (-R / kappa) / (p * m), -1.0, 1.0)
        # three real roots: k=1 of the trigonometric form is on the rising branch through r = 0
        r = m * np.cos(np.arccos(arg) / 3.0 - 2.0 * np.pi / 3.0)
    # Newton polish: the closed forms lose digits to cancellation for small kappa r^2
    for _ in range(3):
        r = r - (kappa * r**3 + r - R) / (3 * kappa * r**2 + 1.0)
    return r


def distort(XY, kappa: float) -> np.ndarray:
    """Inverse of eq. 4, (N, 2) -> (N, 2) px; ``CalibrationError`` for a point beyond the lens's fold (kappa < 0)."""
    XY = np.asarray(XY, dtype=float)
    R = np.sqrt(np.sum(XY * XY, axis=-1, keepdims=True))
    r = _distorted_radius(R, kappa)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(R > 0, r / np.where(R > 0, R, 1.0), 1.0)
    return XY * scale


@dataclass(frozen=True)
class CameraModel:
    """Interior orientation (eq. 3-4): ``f`` focal length [px]; ``kappa`` [px^-2]; ``cx, cy`` principal point [px];
    ``aspect`` horizontal sampling factor; ``width, height`` [px]; ``skew`` the grabber's PLL shear [px of u per px of v
    below cy], |skew| <= ``MAX_SKEW``, 0 in the spec (OpenCV's ``K[0, 1] = skew * fy``, fy = f, fx = f / aspect).
    ``ConfigError`` for impossible values."""

    f: float
    kappa: float = 0.0
    cx: float = 383.5
    cy: float = 287.5
    aspect: float = 1.0
    width: int = 768
    height: int = 576
    skew: float = 0.0

    def __post_init__(self):
        for name in ("f", "kappa", "cx", "cy", "aspect", "skew"):
            v = getattr(self, name)
            if not np.isfinite(v):
                raise ConfigError(f"camera {name}: expected a finite number, got {v!r}")
        if self.f <= 0:
            raise ConfigError(f"camera f: expected a positive focal length in px, got {self.f!r}")
        if self.aspect <= 0:
            raise ConfigError(f"camera aspect: expected a positive ratio, got {self.aspect!r}")
        if abs(self.skew) > MAX_SKEW:
            raise ConfigError(f"camera skew: {self.skew!r} shears the picture by {abs(self.skew) * self.height:.1f} px "
                              f"from its top line to its bottom one; a grabber's shear is a few tenths of a pixel "
                              f"(|skew| <= {MAX_SKEW})")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ConfigError(f"camera size: expected positive width and height, got {self.width}x{self.height}")

    def check_size(self, width: int, height: int, source: str = "the camera file") -> None:
        """``ConfigError`` unless this camera was measured on ``width`` x ``height`` pictures (the cell's)."""
        if (int(self.width), int(self.height)) != (int(width), int(height)):
            raise ConfigError(f"{source} was measured on {self.width}x{self.height} pictures; this cell's camera "
                              f"gives {width}x{height}: it belongs to another camera or grabber setting")

    def with_(self, **changes) -> "CameraModel":
        """A copy with some parameters changed."""
        return replace(self, **changes)

    @property
    def principal_point(self) -> tuple[float, float]:
        return (self.cx, self.cy)

    def pixel_to_sensor(self, uv) -> np.ndarray:
        """Pixels (N, 2) -> distorted sensor coordinates X^, Y^ (N, 2)."""
        uv, single = _as_points(uv, 2, "uv")
        Yh = uv[:, 1] - self.cy
        u = uv[:, 0] - self.cx if not self.skew else uv[:, 0] - self.cx - self.skew * Yh
        out = np.column_stack([self.aspect * u, Yh])
        return out[0] if single else out

    def sensor_to_pixel(self, XY_hat) -> np.ndarray:
        """Distorted sensor coordinates (N, 2) -> pixels (N, 2)."""
        XY_hat, single = _as_points(XY_hat, 2, "XY_hat")
        u = XY_hat[:, 0] / self.aspect + self.cx
        if self.skew:
            u = u + self.skew * XY_hat[:, 1]
        out = np.column_stack([u, XY_hat[:, 1] + self.cy])
        return out[0] if single else out

    def deskew_pixels(self, uv) -> np.ndarray:
        """Pixels (N, 2) -> the pixels of the same rays in ``without_skew()``: u - skew (v - cy)."""
        uv, single = _as_points(uv, 2, "uv")
        out = uv.copy()
        if self.skew:
            out[:, 0] -= self.skew * (uv[:, 1] - self.cy)
        return out[0] if single else out

    def without_skew(self) -> "CameraModel":
        """This camera with skew 0, for code that takes (cx, cy, aspect) alone, fed with ``deskew_pixels``."""
        return self if not self.skew else replace(self, skew=0.0)

    def undistort_pixels(self, uv) -> np.ndarray:
        """Pixels (N, 2) -> undistorted sensor coordinates X, Y (N, 2) of eq. 3-4."""
        return undistort(self.pixel_to_sensor(uv), self.kappa)

    def distort_to_pixels(self, XY) -> np.ndarray:
        """Undistorted sensor coordinates X, Y (N, 2) -> pixels (N, 2) (exact inverse of eq. 4)."""
        return self.sensor_to_pixel(distort(XY, self.kappa))

    def undistorted_pixels(self, uv) -> np.ndarray:
        """Pixels (N, 2) -> where they would lie in a distortion-free picture, in pixels (N, 2)."""
        return self.sensor_to_pixel(self.undistort_pixels(uv))

    def project_undistorted(self, p_C) -> np.ndarray:
        """Camera-frame points (N, 3) [mm] -> undistorted sensor coords (N, 2), eq. 3; CalibrationError if z <= 0."""
        p, single = _as_points(p_C, 3, "p_C")
        z = p[:, 2]
        if np.any(z <= 0):
            raise CalibrationError(f"{int(np.sum(z <= 0))} point(s) lie behind or on the camera's plane (z <= 0)")
        out = self.f * p[:, :2] / z[:, None]
        return out[0] if single else out

    def project(self, p_C) -> np.ndarray:
        """Camera-frame points (N, 3) [mm] -> pixels (N, 2), distortion applied."""
        p, single = _as_points(p_C, 3, "p_C")
        uv = self.distort_to_pixels(self.project_undistorted(p))
        return uv[0] if single else uv

    def in_image(self, uv, margin: float = 0.0) -> np.ndarray:
        """Boolean mask (N,): pixel centres inside the picture, at least ``margin`` px from its border."""
        uv, _ = _as_points(uv, 2, "uv")
        lo, hi = -0.5 + margin, np.array([self.width, self.height]) - 0.5 - margin
        return np.all((uv >= lo) & (uv <= hi), axis=1)

    def rays(self, uv) -> np.ndarray:
        """Pixels (N, 2) -> unit viewing directions (N, 3) in the camera frame."""
        uv, single = _as_points(uv, 2, "uv")
        XY = self.undistort_pixels(uv)
        d = np.column_stack([XY / self.f, np.ones(len(XY))])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return d[0] if single else d

    def backproject_to_plane(self, uv, C_H_P, z_P=0.0, min_cos: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 8: where the rays of pixels (N, 2) meet the plane z = ``z_P`` [mm, scalar or (N,)] of frame P.
        ``C_H_P`` (4, 4) maps P to the camera. Returns (p_P (N, 3) in frame P, z_C (N,) depths in the camera frame);
        ``CalibrationError`` for a plane seen edge-on or met behind the camera."""
        uv, single = _as_points(uv, 2, "uv")
        H = np.asarray(C_H_P, dtype=float)
        R, t = H[:3, :3], H[:3, 3]
        XY = self.undistort_pixels(uv)
        zP = np.broadcast_to(np.asarray(z_P, dtype=float), (len(uv),))
        # eq. 8 per point: [r1 r2 -X/f; r4 r5 -Y/f; r7 r8 -1] [x y zc]^T = -r3 z - t
        A = np.empty((len(uv), 3, 3))
        A[:, :, :2] = R[:, :2]
        A[:, :2, 2] = -XY / self.f
        A[:, 2, 2] = -1.0
        b = -(R[:, 2][None, :] * zP[:, None]) - t[None, :]
        cosang = np.abs(self.rays(uv) @ R[:, 2])  # edge-on test: angle between ray and plane normal
        if np.any(cosang < min_cos):
            raise CalibrationError(f"plane seen nearly edge-on: a viewing ray meets it at "
                                   f"{np.degrees(np.arcsin(cosang.min())):.1f} deg")
        sol = np.linalg.solve(A, b[..., None])[..., 0]
        zc = sol[:, 2]
        if np.any(zc <= 0):
            raise CalibrationError("plane meets a viewing ray behind the camera")
        pts = np.column_stack([sol[:, 0], sol[:, 1], zP])
        return (pts[0], zc[0]) if single else (pts, zc)

    @classmethod
    def from_dict(cls, d: dict) -> "CameraModel":
        """From a ``to_dict`` mapping; KeyError, TypeError or ValueError if malformed, ConfigError if impossible."""
        pp = d["principal_point"]
        return cls(f=float(d["f"]), kappa=float(d["kappa"]), cx=float(pp[0]), cy=float(pp[1]),
                   aspect=float(d["aspect"]), width=int(d["width"]), height=int(d["height"]),
                   skew=float(d.get("skew", 0.0)))

    def to_dict(self) -> dict:
        return {"f": float(self.f), "kappa": float(self.kappa), "principal_point": [float(self.cx), float(self.cy)],
                "aspect": float(self.aspect), "width": int(self.width), "height": int(self.height),
                **({"skew": float(self.skew)} if self.skew else {})}
