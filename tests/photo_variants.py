"""Real photographs changed the ways real pictures differ: turned in the picture, a lamp's shadow across
them, uneven light, glare. Shared by the tests and ``bench/discs_vs_opencv.py``."""

from __future__ import annotations

import cv2
import numpy as np


def turned(img: np.ndarray, deg: float) -> np.ndarray:
    """The photograph turned by ``deg`` about its centre on a canvas that holds all of it."""
    M, (W, H) = turn_matrix(img.shape, deg)
    return cv2.warpAffine(img, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=float(np.percentile(img, 75)))


def turn_matrix(shape, deg: float):
    """(2 x 3 affine from the photograph's pixels to ``turned``'s, the turned canvas's (width, height))."""
    h, w = shape
    M = cv2.getRotationMatrix2D((w / 2, h / 2), deg, 1.0)
    c, s = abs(M[0, 0]), abs(M[0, 1])
    W, H = int(np.ceil(w * c + h * s)), int(np.ceil(w * s + h * c))
    M[:, 2] += ((W - w) / 2, (H - h) / 2)
    return M, (W, H)


def shadowed(img: np.ndarray, share: float = 0.45, soft_px: float = 3.0) -> np.ndarray:
    """A lamp's shadow over the picture's left part: a soft edge running through the grid at a slant."""
    h, w = img.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    edge = 0.42 * w + 0.25 * (v - h / 2)
    light = share + (1 - share) / (1 + np.exp(np.clip(-(u - edge) / soft_px, -50, 50)))
    return np.clip(img * light, 0, 255).astype(np.uint8)


def ramp(img: np.ndarray) -> np.ndarray:
    """Uneven light: half the light on the left, all of it on the right."""
    h, w = img.shape
    light = np.linspace(0.5, 1.0, w, dtype=np.float32)[None, :]
    return np.clip(img * light, 0, 255).astype(np.uint8)


def camera_turned(img: np.ndarray, camera, axis: str, deg: float):
    """The picture as the camera ``camera`` (kappa taken as 0) would have taken it turned by ``deg`` about
    its own x or y ``axis`` (a homography K R K^-1), on a canvas that holds the grid's part of it, and that
    camera for the new canvas (its centre moved with the canvas), and the homography from the old picture's
    pixels to the new: (picture, camera, H)."""
    if axis not in ("x", "y"):
        raise ValueError(f"camera_turned axis {axis!r}: expected 'x' or 'y'")
    if not np.isfinite(deg):
        raise ValueError(f"camera_turned deg {deg!r}: expected a finite angle in degrees")
    h, w = img.shape
    K = np.array([[camera.f / camera.aspect, 0, camera.cx], [0, camera.f, camera.cy], [0, 0, 1.0]])
    R = cv2.Rodrigues(np.radians(deg) * (np.array([1.0, 0, 0]) if axis == "x" else np.array([0, 1.0, 0])))[0]
    H = K @ R @ np.linalg.inv(K)
    if np.any(H[2] @ np.array([[0, w, 0, w], [0, 0, h, h], [1.0, 1, 1, 1]]) <= 0):
        raise ValueError(f"camera_turned deg {deg!r}: part of the picture would lie behind the turned camera "
                         f"(keep the turn about {axis} under 90 deg less half the field of view)")
    corners = cv2.perspectiveTransform(np.array([[[0, 0]], [[w, 0]], [[0, h]], [[w, h]]], np.float32), H).reshape(-1, 2)
    lo, hi = corners.min(0) - 10, corners.max(0) + 10
    T = np.array([[1, 0, -lo[0]], [0, 1, -lo[1]], [0, 0, 1.0]])
    size = (int(hi[0] - lo[0]), int(hi[1] - lo[1]))
    out = cv2.warpPerspective(img, T @ H, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=float(np.percentile(img, 75)))
    cam = camera.with_(kappa=0.0, cx=camera.cx - lo[0], cy=camera.cy - lo[1], width=size[0], height=size[1])
    return out, cam, T @ H


def plate_tilted(img: np.ndarray, p_W: np.ndarray, uv: np.ndarray, f: float, axis: str, deg: float):
    """The photograph's plate as a camera of focal length ``f`` [px] would see it from ``deg`` off square-on
    (the plate turned about its own x or y ``axis`` through the grid's centre, the centre on the optical
    axis at the distance where the grid spans about half the picture's width square-on): the picture warped
    by the homography from the photo's pixels to the new view through the plate (from the discs' plate
    points ``p_W`` (N, 3) [mm] and their pixels ``uv`` (N, 2), lens distortion taken as none), on a canvas
    of the photo's size. Returns (picture, H) with H the photo-to-picture homography."""
    if axis not in ("x", "y"):
        raise ValueError(f"plate_tilted axis {axis!r}: expected 'x' or 'y'")
    if not 0 <= abs(deg) < 80:
        raise ValueError(f"plate_tilted deg {deg!r}: expected a tilt under 80 deg")
    h, w = img.shape
    Hp, _ = cv2.findHomography(p_W[:, :2].astype(np.float64), uv.astype(np.float64))
    centre = p_W[:, :2].mean(0)
    span = np.ptp(p_W[:, :2], axis=0).max()
    R = cv2.Rodrigues(np.radians(deg) * (np.array([1.0, 0, 0]) if axis == "x" else np.array([0, 1.0, 0])))[0]
    t = np.array([0.0, 0.0, 2 * f * span / w])
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    shift = np.array([[1, 0, -centre[0]], [0, 1, -centre[1]], [0, 0, 1.0]])
    G = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ shift
    H = G @ np.linalg.inv(Hp)
    out = cv2.warpPerspective(img, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=float(np.percentile(img, 75)))
    return out, H


def hazed(img: np.ndarray, pedestal: float = 100.0, gain: float = 0.2) -> np.ndarray:
    """Glare or haze, a raised black level: ``pedestal`` grey levels on ink and paper alike, the picture's own light
    scaled by ``gain`` (at the defaults the print's 0.75-0.8 contrast falls to about 0.25), in 8 bits as a camera
    gives it."""
    return np.clip(pedestal + gain * img.astype(np.float32), 0, 255).astype(np.uint8)
