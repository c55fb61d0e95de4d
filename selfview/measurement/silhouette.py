"""Model-based fingertip measurement: the visible silhouette of both finger prisms fitted at once.

Samples every ``STEP_PX`` along the visible box edges seek steps of the finger's polarity and face levels along their
normals; IRLS with Tukey weights fits the camera motion over rounds of shrinking ranges; the corners are the model's
points at the fit, a fit below the quality gates is lost with the reason. ``_csil`` runs the inner steps when built."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from selfview.measurement import _native
from selfview.maths.camera import CameraModel
from selfview.files.cell import GripperSpec
from selfview.measurement.discs import as_gray
from selfview.measurement.fingertips import box_edges, tukey_weights
from selfview.maths.geometry import cross_rows, inv_H, make_H, transform_points

__all__ = ["Appearance", "SilhouetteFit", "fit_silhouette", "learn_appearance", "rms_limit", "MIN_GOOD_FRACTION"]

STEP_PX = 4.0  # samples along each edge
PLATEAU_PX = 3  # px each side of a step that show its two grey levels
MIN_CONTRAST = 8.0  # grey levels between the two sides of a step
LEVEL_TOL = 0.18  # a face's grey level may change this much (fraction, at least LEVEL_TOL_GREY)
LEVEL_TOL_GREY = 12.0
CANDIDATES = 3
ROUNDS = (24.0, 10.0, 5.0, 3.0)  # the search range R of each round of sampling [px]
SCALE_FLOOR_PX = 0.35  # robust scale's floor in the last round
MIN_GOOD_FRACTION = 0.5  # of the samples (and of each finger's), that support the fit
MAX_RMS_PX = 0.6  # of the supporting samples' distances, until this gripper's level is learnt (``rms_limit``)
#: Bound of a good fit's learnt residual level: the nominal model on real fingers (faces off 0.1 mm) leaves 0.36-0.83 px
MAX_LEARNT_RMS_PX = 1.0
#: A frame is lost over this factor of the learnt level: right fits on world 2's grasps reach 1.38 times (0.58-0.81 px)
RMS_MARGIN = 1.5
MAX_TCP_SD_MM = 0.02  # the fitted pose's TCP standard deviation (any camera axis)
BORDER_PX = 3.0
#: Interquartile spread (of the level, and grey) over which samples are not one face: a face 2, half off one 20-130.
FACE_SPREAD, FACE_SPREAD_GREY = 0.15, 8.0
MIN_FINGER_SAMPLES = 25  # a finger with fewer samples in the picture is not judged on its own


@dataclass
class Appearance:
    """Grey levels of the finger faces the camera sees: {(finger, normal axis, side): level}."""

    levels: dict = field(default_factory=dict)

    def copy(self) -> "Appearance":
        return Appearance(dict(self.levels))


@dataclass
class SilhouetteFit:
    """The fitted silhouette: ``C_H_G`` (4, 4) the fitted pose (None: not fitted); ``uv`` (6, 2) its points [distorted
    px] and ``found`` (6,) in the picture and not hidden, when ``ok``; ``reason`` why not ok; ``good_fraction`` of the
    ``n_samples`` supporting it, ``finger_fraction`` (2,) per finger (NaN: too few to judge); ``finger_visible`` (2,)
    each finger's edge samples' share in the picture, not hidden; ``rms_px``; ``tcp_sd_mm`` (3,) the TCP's standard
    deviation (camera axes); ``appearance`` the faces' levels at the fit (for the next frame); ``reasons`` per point."""

    C_H_G: np.ndarray | None
    uv: np.ndarray
    found: np.ndarray
    ok: bool
    reason: str | None
    good_fraction: float
    finger_fraction: np.ndarray
    rms_px: float
    tcp_sd_mm: np.ndarray
    n_samples: int
    appearance: Appearance
    reasons: list
    covariance: np.ndarray | None = None
    finger_visible: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))

    def quality(self) -> dict:
        def num(v):
            return None if v is None or not math.isfinite(v) else round(float(v), 5)

        return {"ok": bool(self.ok), "reason": self.reason, "good_fraction": num(self.good_fraction),
                "finger_fraction": [num(v) for v in self.finger_fraction],
                "finger_visible": [num(v) for v in self.finger_visible], "rms_px": num(self.rms_px),
                "tcp_sd_mm": [num(v) for v in self.tcp_sd_mm], "n_samples": int(self.n_samples)}


@dataclass
class _EdgeSet:
    a_G: np.ndarray  # (E, 3) one end
    b_G: np.ndarray  # (E, 3) the other
    finger: np.ndarray  # (E,)
    faces: list  # per edge: [(finger, axis, side), ...] seen (1: silhouette, 2: crease)
    d_in: np.ndarray  # (E, 3) the direction into each edge's first face (G)
    box: np.ndarray  # (2, 2, 3) the boxes: finger, lo/hi


_EDGE_CACHE: dict = {}


def _visible_edges(boxes, C_H_G) -> _EdgeSet:
    """The boxes' edges seen from the camera at ``C_H_G`` (cached: they change only as it crosses a face's plane)."""
    cam_G = inv_H(C_H_G)[:3, 3]
    b = np.asarray(boxes, float).reshape(-1, 3)
    key = (b.tobytes(), tuple(np.sign(cam_G[None, :] - b).ravel().astype(int)))
    hit = _EDGE_CACHE.get(key)
    if hit is None:
        if len(_EDGE_CACHE) > 64:
            _EDGE_CACHE.clear()
        edges = [e for f, (lo, hi) in enumerate(boxes)
                 for e in box_edges(np.asarray(lo, float), np.asarray(hi, float), cam_G, f).values()]
        hit = _EDGE_CACHE[key] = _EdgeSet(
            np.array([e.a_G for e in edges]), np.array([e.b_G for e in edges]),
            np.array([e.finger for e in edges], np.int64), [e.faces for e in edges],
            np.array([e.into[0] for e in edges], float).reshape(-1, 3), np.ascontiguousarray(b.reshape(-1, 2, 3)))
    return hit


def _blocked(o, d, lo, hi) -> np.ndarray:
    """(M,) whether rays o + t d (G) cross the box (lo, hi) ((3,) or (M, 3)) before t = 1 (0 / 0 bounds nothing)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    tn, tf = np.minimum(t1, t2), np.maximum(t1, t2)
    nan = np.isnan(tn)
    tn[nan], tf[nan] = -np.inf, np.inf
    tn, tf = tn.max(axis=1), np.minimum(tf.min(axis=1), 1.0)
    return (tn < tf - 1e-6) & (tn > 1e-6) & (tf - tn > 1e-4)


@dataclass
class _Samples:
    p_G: np.ndarray  # (S, 3)
    edge: np.ndarray  # (S,)
    uv: np.ndarray  # (S, 2) predicted, distorted px
    n: np.ndarray  # (S, 2) unit image normal, towards the first face
    faces: list  # per edge, as _EdgeSet


_CAM_FIELDS = ("f", "kappa", "cx", "cy", "aspect", "width", "height", "skew")


def _cam_params(cam) -> np.ndarray | None:
    """The camera as the kernel takes it (8,), or None unless ``cam`` is the ``CameraModel`` the kernel mirrors."""
    if type(cam) is not CameraModel or tuple(f.name for f in dataclasses.fields(cam)) != _CAM_FIELDS:
        return None
    return np.array([float(getattr(cam, k)) for k in _CAM_FIELDS])


def _sample(cam: CameraModel, es: _EdgeSet, boxes, C_H_G, margin: float) -> _Samples:
    """Points every STEP_PX along the visible edges, in the picture and not hidden by the other finger."""
    kernel = _native.sil
    cp = None if kernel is None else _cam_params(cam)
    if cp is not None and len(es.a_G):
        n = len(es.a_G) * 400
        p, edge, uv, nrm = np.empty((n, 3)), np.empty(n, np.int64), np.empty((n, 2)), np.empty((n, 2))
        S = kernel.sample(es.a_G, es.b_G, es.d_in, es.finger, es.box, np.ascontiguousarray(C_H_G, float), cp,
                          float(margin), STEP_PX, p, edge, uv, nrm)
        if S >= 0:
            return _Samples(p[:S], edge[:S], uv[:S], nrm[:S], es.faces)
    return _sample_py(cam, es, boxes, C_H_G, margin)


def _sample_py(cam: CameraModel, es: _EdgeSet, boxes, C_H_G, margin: float) -> _Samples:
    """``_sample`` in numpy (the compiled kernel's reference)."""
    empty = _Samples(np.zeros((0, 3)), np.zeros(0, int), np.zeros((0, 2)), np.zeros((0, 2)), es.faces)
    E = len(es.a_G)
    ends = transform_points(C_H_G, np.vstack([es.a_G, es.b_G]))
    fe = np.flatnonzero((ends[:E, 2] > 1.0) & (ends[E:, 2] > 1.0))  # the edges in front of the camera
    if not len(fe):
        return empty
    nf = len(fe)
    # one projection: the ends, each edge's middle and a point a step into its first face (its side)
    m_G = 0.5 * (es.a_G[fe] + es.b_G[fe])
    mid = transform_points(C_H_G, np.vstack([m_G, m_G + 0.05 * es.d_in[fe]]))
    uv_e = cam.project(np.vstack([ends[fe], ends[E + fe], mid]))
    counts = np.clip(np.linalg.norm(uv_e[nf:2 * nf] - uv_e[:nf], axis=1) / STEP_PX, 2, 400).astype(int)
    side = uv_e[3 * nf:] - uv_e[2 * nf:3 * nf]
    k = np.repeat(np.arange(nf), counts)  # the samples' edge, among the front ones
    edge = fe[k]
    starts = np.cumsum(counts) - counts
    t = (np.arange(len(k)) - starts[k] + 0.5) / counts[k]
    p = es.a_G[edge] + t[:, None] * (es.b_G - es.a_G)[edge]
    uv = cam.project(transform_points(C_H_G, p))
    # tangents: forward differences along an edge, its last one backward
    tan = np.empty_like(uv)
    tan[:-1] = uv[1:] - uv[:-1]
    last = starts + counts - 1
    tan[last] = tan[last - 1]
    keep = np.flatnonzero(cam.in_image(uv, margin=margin))
    if len(keep):
        o = inv_H(C_H_G)[:3, 3]
        box = np.asarray(boxes, float)  # (2, 2, 3): finger, lo/hi
        other = 1 - es.finger[edge[keep]]
        keep = keep[~_blocked(o, p[keep] - o[None], box[other, 0], box[other, 1])]
    if not len(keep):
        return empty
    tan = tan[keep]
    tan /= np.linalg.norm(tan, axis=1, keepdims=True) + 1e-12
    nrm = np.column_stack([-tan[:, 1], tan[:, 0]])
    sgn = np.sign(np.sum(nrm * side[k[keep]], axis=1))
    nrm *= np.where(sgn == 0, 1.0, sgn)[:, None]
    return _Samples(p[keep], edge[keep], uv[keep], nrm, es.faces)


def _finger_visible(cam: CameraModel, es: _EdgeSet, C_H_G, s: _Samples) -> np.ndarray:
    """(2,) the share of each finger's edge samples (as ``_sample`` spaces them) that ``s`` kept."""
    ends = transform_points(C_H_G, np.vstack([es.a_G, es.b_G]))
    E = len(es.a_G)
    front = (ends[:E, 2] > 1.0) & (ends[E:, 2] > 1.0)
    total = np.zeros(2)
    if front.any():
        uv = cam.project(np.vstack([ends[:E][front], ends[E:][front]]))
        n = np.clip(np.linalg.norm(uv[front.sum():] - uv[:front.sum()], axis=1) / STEP_PX, 2, 400).astype(int)
        total = np.bincount(es.finger[front], weights=n, minlength=2)
    kept = np.bincount(es.finger[s.edge], minlength=2)
    return np.where(total > 0, np.minimum(kept / np.maximum(total, 1), 1.0), 0.0)


def _remap(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``img`` (float32) at (x, y) of any shape (border replicated), rounded to 1/32 px as
    OpenCV 4 and ``_csil.c`` round (OpenCV 5 does not). Maps go in rows of 4096 (cv2 takes at most 32767 a side)."""
    shape = x.shape
    x = np.rint(np.asarray(x, np.float32) * np.float32(32)) / np.float32(32)
    y = np.rint(np.asarray(y, np.float32) * np.float32(32)) / np.float32(32)
    n, cols = x.size, 4096
    rows = max(1, -(-n // cols))
    mx, my = np.zeros(rows * cols, np.float32), np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x.ravel(), y.ravel()
    out = cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.ravel()[:n].reshape(shape)


def _level_ok(measured, level) -> np.ndarray:
    return np.abs(measured - level) <= np.maximum(LEVEL_TOL * level, LEVEL_TOL_GREY)


def _profiles(img, s: _Samples, R: float):
    """Profiles along the samples' normals, R + PLATEAU_PX + 1 px either side: (S, L) profile, (S, L - 2) its
    derivative D at ``pos`` (L - 2,) [px], A = |D|, A's peaks within R as (rows, m) (m indexes D[:, 1:-1])."""
    Ri = int(math.ceil(R))
    P = PLATEAU_PX
    offs = np.arange(-Ri - P - 1, Ri + P + 2, dtype=np.float32)  # profile positions
    x = s.uv[:, 0:1] + offs[None] * s.n[:, 0:1]
    y = s.uv[:, 1:2] + offs[None] * s.n[:, 1:2]
    prof = _remap(img, x.astype(np.float32), y.astype(np.float32))  # (S, L)
    D = 0.5 * (prof[:, 2:] - prof[:, :-2])  # derivative at offs[1:-1]
    pos = offs[1:-1]
    A = np.abs(D)
    near = np.abs(pos[1:-1]) <= R
    A1 = A[:, 1:-1]
    peak = (A1 >= A[:, :-2]) & (A1 > A[:, 2:]) & near[None]
    rows, m = np.nonzero(peak)
    return prof, D, A, pos, rows, m


def _gate_and_rank(face, other, rows, m, S: int, D, A, pos, lev1, lev2, n_cand: int):
    """``_profiles``'s best ``n_cand`` peaks through the gates (contrast, levels ``lev1``/``lev2`` (S,) of ``face``/
    ``other``, polarity), ranked by face level, else contrast: (S, C) offsets [px], levels, contrasts (NaN: none)."""
    contrast = face - other
    j = m + 1  # index into D and A
    ok = np.abs(contrast) >= MIN_CONTRAST
    l1, l2 = lev1[rows], lev2[rows]
    has1 = np.isfinite(l1)
    ok &= ~has1 | _level_ok(face, l1)
    ok &= ~np.isfinite(l2) | _level_ok(other, l2)
    # polarity: the derivative's sign is the face side's minus the other side's
    ok &= np.sign(D[rows, j]) == np.sign(contrast)
    k = np.flatnonzero(ok)
    rows, j, face, contrast = rows[k], j[k], face[k], contrast[k]
    # a stable sort: ties rank by position
    score = np.where(has1[k], np.abs(face - np.where(has1[k], l1[k], 0)), -np.abs(contrast))
    o = np.lexsort((score, rows))
    rows, j, face, contrast = rows[o], j[o], face[o], contrast[o]
    first = np.searchsorted(rows, rows)  # each row's first entry (rows ascending)
    rank = np.arange(len(rows)) - first
    C = min(n_cand, D.shape[1] - 2)
    t = np.flatnonzero(rank < C)
    rows, j, rank = rows[t], j[t], rank[t]
    # sub-pixel: a parabola through |D| at the peak and its neighbours
    a0, a1, a2 = A[rows, j - 1], A[rows, j], A[rows, j + 1]
    den = a0 - 2 * a1 + a2
    big = np.abs(den) > 1e-9
    frac = np.where(big, 0.5 * (a0 - a2) / np.where(big, den, 1.0), 0.0)
    out = np.full((3, S, C), np.nan)
    out[0, rows, rank] = pos[j] + np.clip(frac, -0.5, 0.5)
    out[1, rows, rank] = face[t]
    out[2, rows, rank] = contrast[t]
    return out[0], out[1], out[2]


def _motion(xi) -> np.ndarray:
    # OpenCV's Rodrigues: a tenth of geometry.R_from_rotvec's time per call
    return make_H(cv2.Rodrigues(np.asarray(xi[:3], float))[0], xi[3:])


def _gauss_newton_step(J, w, r):
    """(J^T W J, step) of residuals ``r`` (S,), Jacobian ``J`` (S, 6), weights ``w``; step None when singular."""
    Jw = J * w[:, None]
    JtWJ = Jw.T @ J
    g = Jw.T @ r
    d = np.sqrt(np.maximum(JtWJ.diagonal(), 1e-12))
    try:
        return JtWJ, -np.linalg.solve(JtWJ / (d[:, None] * d) + 1e-6 * np.eye(6), g / d) / d
    except np.linalg.LinAlgError:
        return JtWJ, None


def _candidates(img, s: _Samples, R: float, app: Appearance, n_cand: int = CANDIDATES):
    """Up to ``n_cand`` candidates along each normal: (S, C) offsets [px], face levels, contrasts (NaN: none)."""
    return _candidates_q(img, s, R, app, None, n_cand)[:3]


def _levels(s: _Samples, app: Appearance):
    """(S,) the level of each sample's first face and (S,) of its second (a crease), NaN: none learnt."""
    e1 = np.array([app.levels.get(fs[0], np.nan) for fs in s.faces], float)
    e2 = np.array([app.levels.get(fs[1], np.nan) if len(fs) == 2 else np.nan for fs in s.faces], float)
    return e1[s.edge], e2[s.edge]


_GATES = np.array([PLATEAU_PX, MIN_CONTRAST, LEVEL_TOL, LEVEL_TOL_GREY], float)
_NO_CAMERA = np.array([1.0, 0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0])  # the kernel's camera when no q is wanted


def _candidates_q(img, s: _Samples, R: float, app: Appearance, cam, n_cand: int = CANDIDATES):
    """``_candidates`` and, with ``cam``, their undistorted sensor coordinates q (S, C, 2) (NaN: none)."""
    kernel = _native.sil
    cp = None if kernel is None else _NO_CAMERA if cam is None else _cam_params(cam)
    if cp is not None and img.dtype in (np.float32, np.uint8) and img.ndim == 2 and img.flags.c_contiguous:
        S = len(s.edge)
        C = min(n_cand, 2 * int(math.ceil(R)) + 2 * PLATEAU_PX - 1)
        lev1, lev2 = _levels(s, app)
        off, face, con, q = np.empty((S, C)), np.empty((S, C)), np.empty((S, C)), np.empty((S, C, 2))
        kernel.candidates(img, np.ascontiguousarray(s.uv, float), np.ascontiguousarray(s.n, float), lev1, lev2,
                          float(R), _GATES, cp, off, face, con, q)
        return off, face, con, (q if cam is not None else None)
    off, face, con = _candidates_np(img.astype(np.float32, copy=False), s, R, app, n_cand)
    return off, face, con, (None if cam is None else _undistorted(cam, s, off))


def _undistorted(cam: CameraModel, s: _Samples, off) -> np.ndarray:
    """(S, C, 2) the undistorted sensor coordinates of the candidates at offsets ``off`` (S, C) (NaN: none)."""
    uvc = s.uv[:, None, :] + off[..., None] * s.n[:, None, :]
    return cam.undistort_pixels(uvc.reshape(-1, 2)).reshape(uvc.shape)  # NaN stays NaN


def _candidates_np(img, s: _Samples, R: float, app: Appearance, n_cand: int = CANDIDATES):
    """``_candidates`` in numpy (the compiled kernel's reference)."""
    P = PLATEAU_PX
    prof, D, A, pos, rows, m = _profiles(img, s, R)
    L = prof.shape[1]
    # the sides of the peak at D[:, m + 1]: profile m + 2 +- k, k = 2..P, the ends replicated
    flat = prof.ravel()
    base = rows * L
    face, other = np.zeros(len(rows), np.float32), np.zeros(len(rows), np.float32)
    for k in range(2, P + 1):
        face += flat[base + np.minimum(m + 2 + k, L - 1)]
        other += flat[base + np.maximum(m + 2 - k, 0)]
    face, other = face / (P - 1), other / (P - 1)
    return _gate_and_rank(face, other, rows, m, len(s.edge), D, A, pos, *_levels(s, app), n_cand)


def _solve(cam, es, s: _Samples, q, C_H_G, floor: float, iters: int = 6, start_floor: float | None = None):
    """IRLS of the camera motion on the candidates q (S, C, 2) (undistorted sensor coordinates, NaN: none), the
    scale's floor halving each iteration from ``start_floor`` (default ``floor``) to ``floor``: far candidates weigh
    first. Returns (C_H_G, weights (S,), residuals (S,), picked candidate (S,), J^T W J (6, 6), scale). An edge with
    camera-frame ends A, B has the line l = A x B, r = l . (x, y, f) / |l_12|; under the motion (w, t) on the left
    dl = w x l + t x (B - A), so a row of the Jacobian is [l x q, (B - A) x q] / |l_12| - r V, V = d|l_12| / |l_12|."""
    kernel = _native.sil
    if kernel is not None:
        S = len(s.edge)
        H, JtWJ = np.empty((4, 4)), np.empty((6, 6))
        w, r, pick = np.empty(S), np.empty(S), np.empty(S, np.int64)
        code, sigma = kernel.solve(np.ascontiguousarray(q, float), s.edge.astype(np.int64, copy=False), es.a_G, es.b_G,
                                   np.ascontiguousarray(C_H_G, float), float(cam.f), float(floor), int(iters),
                                   -1.0 if start_floor is None else float(start_floor), H, w, r, pick, JtWJ)
        if code != 2:
            return H, w, r, pick.astype(int), JtWJ, sigma
    return _solve_py(cam, es, s, q, C_H_G, floor, iters, start_floor)


#: K (4, 6) of an edge, flattened, from V (11,): m, Dn (the edge's line and direction, over |l_12|), m2 m1, m2 m0,
#: Dn2 m1, Dn2 m0, m0 Dn1 - m1 Dn0: rows 0-2 the cross products [m x q, Dn x q], row 3 the derivative of |l_12|
_K_OF_V = np.zeros((11, 24))
_K_OF_V[[2, 1, 2, 0, 1, 0, 5, 4, 5, 3, 4, 3, 6, 7, 8, 9, 10],
        [1, 2, 6, 8, 12, 13, 4, 5, 9, 11, 15, 16, 18, 19, 21, 22, 23]] = \
    [1, -1, -1, 1, 1, -1, 1, -1, -1, 1, 1, -1, 1, -1, 1, -1, 1]


def _solve_py(cam, es, s: _Samples, q, C_H_G, floor: float, iters: int = 6, start_floor: float | None = None):
    """``_solve`` in numpy (the compiled kernel's reference)."""
    e = s.edge
    f = float(cam.f)
    H = np.array(C_H_G, float)
    S, C = q.shape[:2]
    r, pick, JtWJ = np.full(S, np.nan), np.zeros(S, int), np.zeros((6, 6))
    sigma, sel, wh = floor, np.zeros(0, int), np.zeros(0)
    rows = np.arange(S)
    bad = ~np.isfinite(q).all(axis=2)  # (S, C) no candidate
    qx, qy = np.where(bad, 0.0, q[..., 0]), np.where(bad, 0.0, q[..., 1])
    ab = np.vstack([es.a_G, es.b_G])
    E = len(es.a_G)
    V = np.empty((E, 11))  # per edge: m, Dn and the products its row of K holds (K = V @ _K_OF_V)
    with np.errstate(divide="ignore", invalid="ignore"):  # an edge through the centre: no sample names it
        for it in range(iters):
            P = ab @ H[:3, :3].T + H[:3, 3]
            PA, PB = P[:E], P[E:]
            l = cross_rows(PA, PB)
            N = np.hypot(l[:, 0], l[:, 1])[:, None]
            m = np.divide(l, N, out=V[:, :3])
            Dn = np.divide(PB - PA, N, out=V[:, 3:6])
            me = m.take(e, axis=0)
            rc = qx * me[:, 0:1]
            rc += qy * me[:, 1:2]
            rc += f * me[:, 2:3]
            np.copyto(rc, np.inf, where=bad)
            pick = np.argmin(np.abs(rc), axis=1)
            r = rc[rows, pick]
            sel = np.flatnonzero(np.isfinite(r))
            if len(sel) < 12:
                return H, np.zeros(S), r, pick, JtWJ, sigma
            rh = r[sel]
            fl = floor if start_floor is None else max(floor, start_floor * 0.5**it)
            wh, sigma = tukey_weights(rh, fl)
            np.multiply(m[:, 2:3], m[:, 1::-1], out=V[:, 6:8])
            np.multiply(Dn[:, 2:3], m[:, 1::-1], out=V[:, 8:10])
            V[:, 10] = m[:, 0] * Dn[:, 1] - m[:, 1] * Dn[:, 0]
            K = (V @ _K_OF_V).reshape(E, 4, 6)  # a sample's row of the Jacobian is (x, y, f, r) @ K of its edge
            ps = pick[sel]
            u4 = np.column_stack([qx[sel, ps], qy[sel, ps], np.full(len(sel), f), rh])
            J = np.matmul(u4[:, None, :], K.take(e[sel], axis=0))[:, 0]
            JtWJ, dxi = _gauss_newton_step(J, wh, rh)
            if dxi is None:
                break
            H = _motion(dxi) @ H
            if fl <= floor and np.abs(dxi[:3]).max() < 1e-7 and np.abs(dxi[3:]).max() < 1e-5:
                break
    w = np.zeros(S)
    w[sel] = wh
    return H, w, r, pick, JtWJ, sigma


def _coarse_shift(off: np.ndarray, nrm: np.ndarray, R: float, cell: float = 2.0, tol: float = 1.5) -> np.ndarray:
    """The image shift (2,) [px] within +-R most samples agree with (a candidate within ``tol`` of n_i . d): a vote
    over a grid of ``cell`` px, then the least squares of the samples agreeing around the best cell."""
    g = np.arange(-R, R + cell / 2, cell)
    dx, dy = np.meshgrid(g, g)
    d = np.column_stack([dx.ravel(), dy.ravel()])
    has = np.isfinite(off)
    kernel = _native.sil
    if kernel is not None:
        votes = np.empty(len(d), np.int64)
        kernel.vote(np.ascontiguousarray(off, float), np.ascontiguousarray(nrm, float), g, float(tol), votes)
    else:
        votes = _votes_py(off, has, nrm @ d.T, tol)
    return _refine_shift(off, has, nrm, d[int(np.argmax(votes))], cell, tol)


def _votes_py(off, has, proj, tol):
    """``_coarse_shift``'s vote in numpy: (D,) per cell the samples with a candidate within ``tol`` of proj (S, D)."""
    agree = np.zeros(proj.shape, bool)
    tmp, hit = np.empty(proj.shape), np.empty(proj.shape, bool)
    for c in range(off.shape[1]):
        m = has[:, c]
        if not m.any():
            continue
        if m.all():
            np.subtract(proj, off[:, c:c + 1], out=tmp)
            np.abs(tmp, out=tmp)
            np.less_equal(tmp, tol, out=hit)
            agree |= hit
        else:
            i = np.flatnonzero(m)
            agree[i] |= np.abs(proj[i] - off[i, c:c + 1]) <= tol
    return np.count_nonzero(agree, axis=0)


def _refine_shift(off, has, nrm, best, cell, tol):
    """``_coarse_shift``'s refinement around the best cell ``best`` (2,)."""
    pb = nrm @ best
    r = np.where(has, off - pb[:, None], np.inf)
    k = np.argmin(np.abs(r), axis=1)
    rows = np.arange(len(off))
    ok = np.abs(r[rows, k]) <= tol
    if ok.sum() >= 6:
        sol, *_ = np.linalg.lstsq(nrm[ok], off[rows[ok], k[ok]], rcond=None)
        if np.all(np.abs(sol - best) <= 2 * cell):
            return sol
    return best


_OTHER6 = np.array([1, 1, 0, 0, 1, 0], np.int64)  # the other finger of each fingertip point


def _points_seen(camera: CameraModel, H, p_G6, box):
    """The fingertip points p_G6 (6, 3) at ``H``: pixels (6, 2) (NaN when one is behind the camera), whether each is
    half a pixel inside the picture, whether the other finger hides it (``box`` (2, 2, 3): finger, lo/hi)."""
    uv6 = np.full((6, 2), np.nan)
    pts_C = transform_points(H, p_G6)
    if np.all(pts_C[:, 2] > 0):
        uv6 = camera.project(pts_C)
    o = inv_H(H)[:3, 3]
    box = np.asarray(box, float)
    inside6 = camera.in_image(uv6, margin=0.5)
    hidden6 = _blocked(o, p_G6 - o[None], box[_OTHER6, 0], box[_OTHER6, 1])
    return uv6, inside6, hidden6


def _points_found(camera: CameraModel, H, p_G6, box, points):
    """The points a fit at ``H`` reports: uv (6, 2), found (6,) (requested, in the picture, unhidden), reasons (6,)."""
    uv6, inside6, hidden6 = _points_seen(camera, H, p_G6, box)
    want = {int(k) for k in points}
    found = np.zeros(6, bool)
    reasons: list = [None] * 6
    for k in range(6):
        if k not in want:
            reasons[k] = "not requested"
        elif not inside6[k]:
            reasons[k] = "outside the picture"
        elif hidden6[k]:
            reasons[k] = f"occluded by finger {'AB'[_OTHER6[k]]}"
        else:
            found[k] = True
    return uv6, found, reasons


def rms_limit(level_px: float | None) -> float:
    """The edge residual [px] over which a fit is lost: ``RMS_MARGIN`` times a good fit's level ``level_px``, not under
    ``MAX_RMS_PX`` (None: not learnt, ``MAX_RMS_PX``). Raises ``ValueError`` over ``MAX_LEARNT_RMS_PX``."""
    if level_px is None:
        return MAX_RMS_PX
    if not (0.0 <= float(level_px) <= MAX_LEARNT_RMS_PX):
        raise ValueError(f"level_px: a right fit's edge residual is 0..{MAX_LEARNT_RMS_PX} px, got {level_px!r}")
    return max(MAX_RMS_PX, RMS_MARGIN * float(level_px))


def learn_appearance(image, camera: CameraModel, C_H_G, gripper: GripperSpec, gap_mm: float) -> Appearance:
    """The grey level of every visible finger face at ``C_H_G`` (a pose that fits): the median in the picture, 2 px
    inside its edges; a face spreading over ``FACE_SPREAD`` stays unlearnt (its edges matched by contrast alone)."""
    img = as_gray(image, camera).astype(np.float32)
    boxes = np.asarray(gripper.finger_boxes_G(gap_mm), float)  # (2, 2, 3): finger, lo/hi
    cam_G = inv_H(np.asarray(C_H_G, float))[:3, 3]
    u, v = np.meshgrid(np.linspace(0.12, 0.88, 9), np.linspace(0.02, 0.98, 60))  # over a face, 12 % in from its sides
    u, v = u.ravel(), v.ravel()
    app = Appearance()
    for f, (lo, hi) in enumerate(boxes):
        for ax in range(3):
            j, k = [m for m in range(3) if m != ax]
            for side in (-1, 1):
                plane = hi[ax] if side > 0 else lo[ax]
                if side * (cam_G[ax] - plane) <= 1e-9:
                    continue
                p = np.zeros((u.size, 3))
                p[:, ax] = plane
                p[:, j] = lo[j] + u * (hi[j] - lo[j])
                p[:, k] = lo[k] + v * (hi[k] - lo[k])
                pc = transform_points(C_H_G, p)
                if np.any(pc[:, 2] <= 0):
                    continue
                uv = camera.project(pc)
                inside = camera.in_image(uv, margin=2) & ~_blocked(cam_G, p - cam_G[None], *boxes[1 - f])
                if inside.sum() < 10:
                    continue
                q1, med, q3 = np.percentile(_remap(img, uv[inside, 0], uv[inside, 1]), [25, 50, 75])
                if q3 - q1 <= max(FACE_SPREAD_GREY, FACE_SPREAD * med):
                    app.levels[(f, ax, side)] = float(med)
    return app


def _fit_image(image, camera: CameraModel, frame: bool) -> np.ndarray:
    """What ``fit_silhouette`` reads: float32 (8-bit with ``frame``) of the camera's size as is, else ``as_gray``'s."""
    a = np.asarray(image)
    size = (int(camera.height), int(camera.width))
    if a.dtype == np.float32 and a.shape == size:
        return a
    if frame and a.dtype == np.uint8 and a.shape == size:
        return a if _native.sil is not None and a.flags.c_contiguous else a.astype(np.float32)
    return as_gray(image, camera)


def _fit_rounds(img, camera: CameraModel, boxes, H, app: Appearance, rounds):
    """``fit_silhouette``'s rounds from ``H``: the last round's (H, edges, samples, (levels seen, weights, residuals,
    picks, J^T W J)); the last item None when a round finds under 20 edge samples in the picture."""
    es = _visible_edges(boxes, H)
    rounds = tuple(rounds)
    if rounds[0] >= 16.0:
        # far from the start: first the image shift most samples vote for, as a small turn
        s = _sample(camera, es, boxes, H, margin=BORDER_PX)
        if len(s.edge) < 20:
            return H, es, s, None
        off, _, _ = _candidates(img, s, rounds[0], app, n_cand=8)
        du, dv = _coarse_shift(off, s.n, rounds[0])
        H = _motion(np.array([-dv / camera.f, du / camera.f, 0.0, 0.0, 0.0, 0.0])) @ H
        rounds = rounds[1:] or (3.0,)
        es = _visible_edges(boxes, H)
    for i, R in enumerate(rounds):
        s = _sample(camera, es, boxes, H, margin=BORDER_PX)
        if len(s.edge) < 20:
            return H, es, s, None
        off, lev, _, q = _candidates_q(img, s, R, app, camera)
        last = i == len(rounds) - 1
        floor = SCALE_FLOOR_PX if last else max(SCALE_FLOOR_PX, R / 6.0)
        H, w, r, pick, JtWJ, _ = _solve(camera, es, s, q, H, floor, iters=6 if last else 3,
                                        start_floor=max(floor, R / 6.0))
    return H, es, s, (lev, w, r, pick, JtWJ)


def _tcp_sd(H, JtWJ, w, r):
    """The motion's covariance (6, 6) from the supporting samples' weights ``w``, residuals ``r`` [px], and the TCP's
    standard deviation (3,) [mm, camera axes]; None and NaN from 6 samples or fewer or a singular J^T W J."""
    if len(r) <= 6:
        return None, np.full(3, np.nan)
    try:
        cov = float(np.sum(w * r**2) / (len(r) - 6)) * np.linalg.inv(JtWJ)
    except np.linalg.LinAlgError:
        return None, np.full(3, np.nan)
    t = H[:3, 3]  # the TCP (G's origin) in C moves by [-t]x dθ + dt under the motion
    Jt = np.array([[0.0, t[2], -t[1], 1.0, 0.0, 0.0], [-t[2], 0.0, t[0], 0.0, 1.0, 0.0],
                   [t[1], -t[0], 0.0, 0.0, 0.0, 1.0]])  # [-[t]x, I]
    return cov, np.sqrt(np.maximum(np.diag(Jt @ cov @ Jt.T), 0.0))


def _lost_reason(gf: float, ff, rms: float, tcp_sd, n_s: int, max_rms_px: float) -> str | None:
    """Why a fit with these quality figures (as ``SilhouetteFit`` names them) is lost, or None."""
    if gf < MIN_GOOD_FRACTION:
        return f"lost: {100 * gf:.0f} % of {n_s} edge samples support the fit (needs {100 * MIN_GOOD_FRACTION:.0f} %)"
    if np.nanmin(ff, initial=1.0) < MIN_GOOD_FRACTION:
        f = int(np.nanargmin(ff))
        return f"lost: {100 * ff[f]:.0f} % of finger {'AB'[f]}'s edge samples support the fit"
    if not (rms <= max_rms_px):
        return f"lost: edge residual {rms:.2f} px over {max_rms_px:.2f} px"
    # the TCP's sd scales with the residual: its limit holds at MAX_RMS_PX, and grows with the residual allowed
    if not (np.nanmax(tcp_sd) <= (tcp_lim := MAX_TCP_SD_MM * max(1.0, max_rms_px / MAX_RMS_PX))):
        return f"lost: TCP uncertain by {np.nanmax(tcp_sd):.3f} mm (over {tcp_lim:.3f} mm)"
    return None


def fit_silhouette(image, camera: CameraModel, C_H_G_pred, gripper: GripperSpec, gap_mm: float, *,
                   appearance: Appearance | None = None, rounds=ROUNDS, points=range(6),
                   frame: bool = False, max_rms_px: float = MAX_RMS_PX) -> SilhouetteFit:
    """Fit the fingers' silhouette to ``image`` from the pose ``C_H_G_pred`` (4, 4), jaw gap ``gap_mm``.

    ``appearance`` the faces' levels (else read at the prediction); ``rounds`` the search ranges [px], the first
    reaching the prediction's error; ``points`` those reported; ``frame``: a tracker's grey frame, unchecked;
    ``max_rms_px`` the residual limit (``rms_limit``; the TCP's sd limit grows alike). A failed fit: ``ok`` False."""
    img = _fit_image(image, camera, frame)
    H0 = np.asarray(C_H_G_pred, float)
    boxes = gripper.finger_boxes_G(gap_mm)
    p_G6 = gripper.points_G(gap=gap_mm)
    app = appearance.copy() if appearance is not None and appearance.levels else learn_appearance(
        img, camera, H0, gripper, gap_mm)

    def fail(reason, n_s, gf=0.0, ff=(0.0, 0.0), rms=math.nan, H_=None):
        return SilhouetteFit(H_, np.full((6, 2), np.nan), np.zeros(6, bool), False, reason, gf, np.asarray(ff, float),
                             rms, np.full(3, np.nan), n_s, app, [reason] * 6)

    H, es, s, last = _fit_rounds(img, camera, boxes, H0, app, rounds)
    n_s = len(s.edge)
    if last is None:
        return fail(f"too few edge samples in the picture ({n_s})", n_s)
    if not np.all(transform_points(H, p_G6)[:, 2] > 0.0):
        # a diverged solve (a picture unlike the prediction): no pose to start the next search from
        return fail("lost: the fit diverged (a fingertip point behind the camera)", n_s)
    lev, w, r, pick, JtWJ = last
    good = w > 0.5
    visible = _finger_visible(camera, es, H, s)
    fing = es.finger[s.edge]
    n_good = int(np.count_nonzero(good))
    gf = n_good / n_s
    # per finger, of those with enough samples in the picture (a finger may leave it)
    n_f = np.bincount(fing, minlength=2)
    ff = np.where(n_f >= MIN_FINGER_SAMPLES, np.bincount(fing[good], minlength=2) / np.maximum(n_f, 1), math.nan)
    rms = float(np.sqrt(np.mean(r[good] ** 2))) if n_good else math.nan
    cov, tcp_sd = _tcp_sd(H, JtWJ, w[good], r[good])
    uv6, found, reasons = _points_found(camera, H, p_G6, np.asarray(boxes, float).reshape(2, 2, 3), points)
    why = _lost_reason(gf, ff, rms, tcp_sd, n_s, max_rms_px)
    if why is not None:
        res = fail(why, n_s, gf, ff, rms, H)
        res.tcp_sd_mm, res.covariance, res.finger_visible = tcp_sd, cov, visible
        return res
    # the faces' levels for the next frame: the mean beside each edge's supporting samples
    new_app = app.copy()
    seen = lev[np.arange(n_s), pick]
    m = good & np.isfinite(seen)
    cnt = np.bincount(s.edge[m], minlength=len(es.faces))
    tot = np.bincount(s.edge[m], weights=seen[m], minlength=len(es.faces))
    for e in np.flatnonzero(cnt >= 5):
        new_app.levels[es.faces[e][0]] = float(tot[e] / cnt[e])
    return SilhouetteFit(H, np.where(found[:, None], uv6, np.nan), found, True, None, gf, ff, rms, tcp_sd, n_s,
                         new_app, reasons, cov, visible)
