"""Judging disc detections on real photographs against ``cv2.findCirclesGrid``: its grid in both of its
modes, the nearest of its centres to each of ours, and whether our (row, col) indexing is OpenCV's up to
a symmetry of the grid. Shared by the disc-photograph tests."""

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
