"""The printed plate's shape in the joint fit (a bow, each disc's in-plane error) and each view's grid turn."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import PlateSpec
from selfview.errors import CalibrationError
from selfview.estimation.intrinsics.model import intrinsics_vector, project_points


#: Plate models: 'flat' (as specified), 'bow' (plus a bow), 'bow+dots' (plus each disc's in-plane position; default).
PLATE_MODELS = ("flat", "bow", "bow+dots")
#: Starting prior 1-sigma of a disc's in-plane error per axis [mm] (half a 600-dpi dot), then estimated from the
#: corrections (EM) within ``PLATE_DOT_SD_RANGE_MM``.
PLATE_DOT_PRIOR_MM = 0.02
PLATE_DOT_SD_RANGE_MM = (0.0005, 0.05)
#: Prior 1-sigma of each bow coefficient [mm] at the grid's half-width: paper cockles 0.1-0.5 mm; 1 mm is weak.
PLATE_BOW_PRIOR_MM = 1.0


def _similarity_complement(p0: np.ndarray) -> np.ndarray:
    """(2N, 2N - 4) orthonormal basis of in-plane corrections (dx, dy per disc) that do not move, turn or scale
    the grid as a whole."""
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


def _turn90(a: np.ndarray, k: int) -> np.ndarray:
    """(N, 2) vectors ``a`` turned by k * 90 deg."""
    for _ in range(k % 4):
        a = np.column_stack([-a[:, 1], a[:, 0]])
    return a


class PlateShape:
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


#: A view's grid turn (a square grid's indices follow the picture) is the one whose high-passed disc errors correlate
#: best with the other views' (at least ``ALIGN_MIN_CORR``, by ``ALIGN_MIN_MARGIN`` over the next); else kept.
ALIGN_MIN_CORR = 0.4
ALIGN_MIN_MARGIN = 0.2
ALIGN_MIN_COMMON = 10


def _dot_field(det, uv, camera: CameraModel, H) -> np.ndarray | None:
    """(N, 2) a view's residuals on the plate [mm] less a quadratic field (smooth errors); None under 15 discs."""
    if len(uv) < 15:
        return None
    x = intrinsics_vector(camera)
    R, t = H[:3, :3], H[:3, 3]
    p = det.p_W
    m = project_points(x, R, t, p)
    h = 0.01
    jx = (project_points(x, R, t, p + [h, 0, 0]) - m) / h
    jy = (project_points(x, R, t, p + [0, h, 0]) - m) / h
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


def _turned(det, k: int, plate: PlateSpec, p0=None):
    """``det`` with its grid turned by k * 90 deg about its centre (None off the grid); ``p0`` the disc centres."""
    mid = np.array([(plate.cols - 1) / 2, (plate.rows - 1) / 2])
    cr = _turn90(det.rc[:, ::-1] - mid, k) + mid  # (col, row): whole or half numbers, exact
    whole = np.round(cr)
    if not np.all(np.abs(cr - whole) <= 1e-8):
        return None
    rc = whole[:, ::-1].astype(det.rc.dtype)
    if rc.min() < 0 or rc[:, 0].max() >= plate.rows or rc[:, 1].max() >= plate.cols:
        return None
    p0 = plate.disc_centres_W() if p0 is None else p0
    return replace(det, rc=rc, p_W=p0[rc[:, 0] * plate.cols + rc[:, 1]].copy())


def align_views(dets, uvs, fit, plate: PlateSpec):
    """(detections re-indexed on one physical grid, [turn in deg per view or None when kept as found])."""
    n_disc = plate.rows * plate.cols
    p0 = plate.disc_centres_W()
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
            dq = _turned(dets[k], q, plate, p0)
            if dq is None:
                continue
            e = _turn90(fields[k], q)
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
            choice, turns[k] = best[0], 0.0
        else:
            scored = sorted([b for b in best if np.isfinite(b[0])], key=lambda b: -b[0])
            second = scored[1][0] if len(scored) > 1 else -1.0
            if not scored or scored[0][0] < ALIGN_MIN_CORR or scored[0][0] - second < ALIGN_MIN_MARGIN:
                continue
            choice, turns[k] = scored[0], 90.0 * scored[0][1]
        _, q, dq, idx, e = choice
        out[k] = dq
        acc[idx] += e
        cnt[idx] += 1
    return out, turns
