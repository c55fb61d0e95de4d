"""Judging disc detections on real photographs against ``cv2.findCirclesGrid``: its grid in both of its
modes, the nearest of its centres to each of ours, and whether our (row, col) indexing is OpenCV's up to
a symmetry of the grid; ``cv2.calibrateCamera`` on our discs. Shared by the disc-photograph tests."""

from __future__ import annotations

import cv2
import numpy as np

#: findCirclesGrid's two ways of assembling the grid from its blobs.
OPENCV_MODES = {
    "findCirclesGrid": cv2.CALIB_CB_SYMMETRIC_GRID,
    "clustering": cv2.CALIB_CB_SYMMETRIC_GRID | cv2.CALIB_CB_CLUSTERING,
}


def opencv_grid(img, plate, mode: str = "findCirclesGrid"):
    """OpenCV's (cols * rows, 2) disc centres of ``plate`` in ``img`` (rows of ``plate.cols``), or None
    when it does not find the whole grid."""
    ok, c = cv2.findCirclesGrid(img, (plate.cols, plate.rows), flags=OPENCV_MODES[mode])
    return c.reshape(-1, 2).astype(float) if ok else None


def nearest(uv, ref):
    """For each of ``uv`` the index of and distance to the nearest of ``ref``."""
    d = np.linalg.norm(uv[:, None, :] - ref[None, :, :], axis=2)
    return np.argmin(d, axis=1), np.min(d, axis=1)


def same_indexing(rc, ref_idx, cols):
    """True when our (row, col) map onto OpenCV's (row, col) by one symmetry of the square plus a shift."""
    ref = np.column_stack([ref_idx // cols, ref_idx % cols])
    for M in ([[1, 0], [0, 1]], [[0, 1], [1, 0]]):
        for s in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            m = np.asarray(M) * np.asarray(s)[:, None]
            mapped = rc @ m.T
            if np.all(mapped - mapped[0] == ref - ref[0]):
                return True
    return False


def opencv_intrinsics(dets, cam0, size):
    """cv2.calibrateCamera (fx, fy, cx, cy, k1 free) on our discs ``dets`` from ``cam0``: (f, cx, cy) and
    their sigmas; f is fy (the spec's aspect scales u)."""
    obj = [d.p_W.astype(np.float32) for d in dets]
    img = [d.uv.astype(np.float32).reshape(-1, 1, 2) for d in dets]
    K0 = np.array([[cam0.f, 0, cam0.cx], [0, cam0.f, cam0.cy], [0, 0, 1.0]])
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_ZERO_TANGENT_DIST | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
    _, K, _, _, _, sd, _, _ = cv2.calibrateCameraExtended(obj, img, size, K0, np.zeros(5), flags=flags)
    return np.array([K[1, 1], K[0, 2], K[1, 2]]), np.ravel(sd)[1:4]
