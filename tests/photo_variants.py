"""Real photographs changed the ways real pictures differ: turned in the picture, a lamp's shadow across
them, uneven light. Shared by the tests and ``bench/discs_vs_opencv.py``."""

from __future__ import annotations

import cv2
import numpy as np


def turned(img: np.ndarray, deg: float) -> np.ndarray:
    """The photograph turned by ``deg`` about its centre on a canvas that holds all of it."""
    h, w = img.shape
    M = cv2.getRotationMatrix2D((w / 2, h / 2), deg, 1.0)
    c, s = abs(M[0, 0]), abs(M[0, 1])
    W, H = int(np.ceil(w * c + h * s)), int(np.ceil(w * s + h * c))
    M[:, 2] += ((W - w) / 2, (H - h) / 2)
    return cv2.warpAffine(img, M, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=float(np.percentile(img, 75)))


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
