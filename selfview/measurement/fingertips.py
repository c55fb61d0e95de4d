"""The six fingertip corners of CONVENTIONS.md in a picture, searched from a predicted mount: a template of the
visible box edges slid over the gradient, profiles across each edge located by the area method (the rise's peak on
texture), a robust line per edge through its undistorted crossings, the corner their weighted intersection. A corner
outside the picture, hidden or with too few edge points is reported not found with the reason, never extrapolated."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import POINT_NAMES, GripperSpec
from selfview.measurement.discs import as_gray
from selfview.errors import CalibrationError
from selfview.maths.geometry import inv_H, transform_points

__all__ = ["FingertipResult", "PredictedFingers", "box_edges", "predict_fingertips", "search_corners", "visible_edges"]

FINGERS = ("A", "B")
POINT_FINGER = (0, 0, 1, 1, 0, 1)  # finger of each point, in POINT_NAMES order
COARSE_CANDIDATES = 4  # best shifts at a quarter resolution refined at full resolution
RIDGE_CANDIDATES = 8  # at most so many more, along ridges of the quarter-resolution score (_ridge_cells)
RIDGE_FRACTION = 0.75  # of the best score, that they reach
TEMPLATE_PX = 90.0  # how much of each edge, from its corner, the coarse template uses
FIT_PX = 90.0  # how much of each edge, from its corner, the fine stage scans
MIN_CONTRAST = 8.0  # grey levels between the two sides of an edge
BLUR_MARGIN = 4  # px a step's window keeps from any other edge
PLATEAU_PX = 3  # pixels on either side of an edge's transition that measure its grey levels
MAX_EDGE_RMS_PX = 0.5  # edge points of a corner scattering more about its lines (typically 0.1) mean a wrong edge
# fraction erf(1.5 / (sigma sqrt 2)) of a Gaussian step within +-1.5 px, per blur sigma (px), increasing for np.interp
_BLUR_SIGMA = np.linspace(4.0, 0.3, 38)
_BLUR_F = np.array([math.erf(1.5 / (s_ * math.sqrt(2))) for s_ in _BLUR_SIGMA])


@dataclass
class FingertipResult:
    """Fingertip corners in a picture, ``POINT_NAMES`` order (``names``): ``uv`` (6, 2) distorted px, NaN where not
    found; ``found`` (6,); ``reasons`` why not (None if found); ``edge_rms_px`` (6,) RMS of the edge points about
    their lines (undistorted px), NaN if not found; ``n_edge_points`` (6,) edge points used; ``tracked``: followed
    from the last frame. The model-based measurement also sets ``quality`` (``SilhouetteFit.quality``), ``lost`` why
    the frame is missed (None: not), ``C_H_G`` the fitted pose (None: none believed), ``left_out`` {name: why}."""

    uv: np.ndarray
    found: np.ndarray
    reasons: list
    edge_rms_px: np.ndarray
    names: tuple
    n_edge_points: np.ndarray | None = None
    tracked: bool = False
    quality: dict | None = None
    lost: str | None = None
    C_H_G: np.ndarray | None = None
    left_out: dict = field(default_factory=dict)

    @property
    def quality_ok(self) -> bool:
        """False when the measurement itself says the fingertips are lost (the frame is a missed one)."""
        return self.lost is None


@dataclass
class _Edge:
    key: tuple  # (finger, axis, side of the first other axis, side of the second)
    finger: int
    a_G: np.ndarray  # one end (3,) [mm]
    b_G: np.ndarray  # other end (3,)
    into: list  # unit directions (3,) from the edge into each of its faces that the camera sees
    faces: list  # those faces, as (finger, normal axis, side)

    @property
    def crease(self) -> bool:
        """Both faces seen: an edge between two lit faces rather than a silhouette."""
        return len(self.into) == 2


def box_edges(lo, hi, cam_G, finger: int) -> dict[tuple, _Edge]:
    """The visible edges of a box (lo, hi) seen from ``cam_G`` (3,), keyed by axis and sides."""
    edges = {}
    eye = np.eye(3)
    for axis in range(3):
        b, c = [k for k in range(3) if k != axis]
        for sb, sc in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
            into, faces = [], []
            # the face normal to b (side sb) spans the edge's axis and c; likewise for c
            for ax, side, other, oside in ((b, sb, c, sc), (c, sc, b, sb)):
                plane = hi[ax] if side > 0 else lo[ax]
                if side * (cam_G[ax] - plane) > 1e-9:
                    into.append(-oside * eye[other])
                    faces.append((finger, ax, side))
            if not into:
                continue
            a_G = np.where(np.arange(3) == axis, lo, 0.0)
            a_G[b] = hi[b] if sb > 0 else lo[b]
            a_G[c] = hi[c] if sc > 0 else lo[c]
            b_G = a_G.copy()
            b_G[axis] = hi[axis]
            key = (finger, axis, sb, sc)
            edges[key] = _Edge(key, finger, a_G, b_G, into, faces)
    return edges


def _corner_edges(p_G, lo, hi, finger, edges) -> list[tuple[_Edge, np.ndarray]]:
    """Visible edges meeting at box corner ``p_G`` with their far ends: [(edge, far end (3,))]."""
    out = []
    side = [(-1 if abs(p_G[k] - lo[k]) < abs(p_G[k] - hi[k]) else 1) for k in range(3)]
    for axis in range(3):
        b, c = [k for k in range(3) if k != axis]
        e = edges.get((finger, axis, side[b], side[c]))
        if e is not None:
            out.append((e, e.b_G if side[axis] < 0 else e.a_G))
    return out


def _hidden_by(p_C, boxes, C_H_G, skip: int) -> int | None:
    """Index of a finger box (other than ``skip``) that hides camera point ``p_C``, or None."""
    G_H_C = inv_H(C_H_G)
    o = G_H_C[:3, 3]
    d = G_H_C[:3, :3] @ p_C
    for k, (lo, hi) in enumerate(boxes):
        if k == skip:
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - o) / d, (hi - o) / d
        t_near = np.max(np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2)))
        t_far = np.min(np.where(np.isnan(t1), np.inf, np.maximum(t1, t2)))
        if t_near < min(t_far, 1.0) - 1e-9 and t_near > 0:
            return k
    return None


@dataclass(frozen=True, eq=False)
class PredictedFingers:
    """Where the fingers are expected in a picture: the ``camera``, the gripper in its frame ``C_H_G`` (4, 4), the
    ``gripper`` and its jaw gap ``gap_mm``. Raises ``ValueError`` for a transform of another shape or a jaw gap that
    is not a positive finite number, ``CalibrationError`` for a non-finite transform."""

    camera: CameraModel
    C_H_G: np.ndarray
    gripper: GripperSpec
    gap_mm: float

    def __post_init__(self):
        H = np.array(self.C_H_G, dtype=float)
        if H.shape != (4, 4):
            raise ValueError(f"C_H_G_pred: expected a (4, 4) transform, got shape {H.shape}")
        if not np.isfinite(H).all():
            raise CalibrationError("C_H_G_pred contains non-finite values: no prediction to search from")
        try:
            gap = float(self.gap_mm)
        except (TypeError, ValueError):
            gap = math.nan
        if not (math.isfinite(gap) and gap > 0.0):
            raise ValueError(f"gap_mm: expected the jaw gap as a positive number of mm, got {self.gap_mm!r}")
        H.flags.writeable = False
        object.__setattr__(self, "C_H_G", H)
        object.__setattr__(self, "gap_mm", gap)


class _Model:
    """The predicted finger geometry in the picture."""

    def __init__(self, pred: PredictedFingers):
        self.cam = pred.camera
        self.C_H_G = pred.C_H_G
        self.boxes = pred.gripper.finger_boxes_G(pred.gap_mm)
        self.points_G = pred.gripper.points_G(gap=pred.gap_mm)
        cam_G = inv_H(self.C_H_G)[:3, 3]
        self.edges: dict[tuple, _Edge] = {k: e for f, (lo, hi) in enumerate(self.boxes)
                                          for k, e in box_edges(lo, hi, cam_G, f).items()}
        pts_C = transform_points(self.C_H_G, self.points_G)
        if np.any(pts_C[:, 2] <= 0):
            raise CalibrationError("C_H_G puts fingertip points behind the camera")
        self.uv = self.cam.project(pts_C)
        self.corner_edges = [_corner_edges(p, *self.boxes[f], f, self.edges)
                             for p, f in zip(self.points_G, POINT_FINGER)]
        self.hidden = [_hidden_by(pts_C[k], self.boxes, self.C_H_G, POINT_FINGER[k]) for k in range(6)]

    def profile_dir(self, edge: _Edge, at_G) -> np.ndarray:
        """Unit image direction (2,) across ``edge`` near ``at_G``: into its seen face (steady shading) or a crease."""
        dirs = []
        for d in edge.into:
            uv = self.cam.project(transform_points(self.C_H_G, np.vstack([at_G, at_G + d])))
            v = uv[1] - uv[0]
            dirs.append(v / (np.linalg.norm(v) + 1e-12))
        out = dirs[0] - dirs[1] if len(dirs) == 2 else dirs[0]
        return out / (np.linalg.norm(out) + 1e-12)

    def polyline(self, start_G, end_G, max_px: float) -> np.ndarray:
        """(M, 2) distorted px ~1 px apart along the 3-D segment from ``start_G``, at most ``max_px`` long, in front."""
        ends_C = transform_points(self.C_H_G, np.vstack([start_G, end_G]))
        if ends_C[0, 2] <= 0:
            return np.zeros((0, 2))
        if ends_C[1, 2] <= 1.0:  # clip at 1 mm in front of the camera
            s = (ends_C[0, 2] - 1.0) / (ends_C[0, 2] - ends_C[1, 2])
            ends_C[1] = ends_C[0] + s * (ends_C[1] - ends_C[0])
        # how much of the segment spans max_px (perspective only, 10 % spare for the lens)
        t = np.linspace(0, 1, 33)[:, None]
        seg = ends_C[0] + t * (ends_C[1] - ends_C[0])
        run = _arc_length(self.cam.f * seg[:, :2] / seg[:, 2:])
        span = 1.1 * max_px + 2
        t_end = float(np.interp(span, run, t[:, 0])) if run[-1] > span else 1.0
        t = np.linspace(0, t_end, int(np.clip(min(run[-1], span) * 1.2, 4, 2000)))[:, None]
        uv = self.cam.project(ends_C[0] + t * (ends_C[1] - ends_C[0]))
        return uv[_arc_length(uv) <= max_px]


def _arc_length(p: np.ndarray) -> np.ndarray:
    """(M,) length along the polyline p (M, 2) from its first point."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def visible_edges(camera: CameraModel, C_H_G, gripper: GripperSpec, gap_mm: float) -> dict[str, list[str]]:
    """Which box edges show at each fingertip point (for reports): name -> ['x edge (silhouette)', ...]."""
    m = _Model(PredictedFingers(camera, C_H_G, gripper, gap_mm))
    return {name: [f"{'xyz'[e.key[1]]} edge ({'crease' if e.crease else 'silhouette'})" for e, _ in edges]
            for name, edges in zip(POINT_NAMES, m.corner_edges)}


def predict_fingertips(camera: CameraModel, C_H_G, gripper: GripperSpec,
                       gap_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Predicted fingertip points: (uv (6, 2) distorted px, in_view (6,) bool: in the picture, not hidden, two or more
    of its edges shown), POINT_NAMES order. Raises ``CalibrationError`` if a point lies behind the camera."""
    m = _Model(PredictedFingers(camera, C_H_G, gripper, gap_mm))
    shown = [m.hidden[k] is None and len(m.corner_edges[k]) >= 2 for k in range(6)]
    return m.uv, camera.in_image(m.uv) & np.array(shown)


def _template_score(G: np.ndarray, pts: list[np.ndarray], normals: np.ndarray, groups: list, span: int):
    """Score (2 span + 1, 2 span + 1) of the shifts in [0, 2 span]^2 of integer template points ``pts`` (offset so
    that shift 0 is at index ``span``) over a gradient G (2, H, W): per edge the sum of its normal gradient."""
    n = 2 * span + 1
    sums = np.zeros((len(pts), n, n), np.float32)
    for e, q in enumerate(pts):
        Gn = normals[e, 0] * G[0] + normals[e, 1] * G[1]
        acc = sums[e]
        for qx, qy in q:
            acc += Gn[qy : qy + n, qx : qx + n]
    return _group_score(sums, groups)


def _group_score(sums: np.ndarray, groups: list) -> np.ndarray:
    """Per-edge sums (E, ...) -> score (...): signed sums within a group (one face's silhouette), magnitudes added."""
    score = np.zeros(sums.shape[1:], np.float32)
    for g in set(groups):
        score += np.abs(sum(sums[e] for e in range(len(sums)) if groups[e] == g))
    return score


def _padded_gradient(img: np.ndarray, lo: np.ndarray, hi: np.ndarray, s: int, smooth: float) -> np.ndarray:
    """(2, h, w) x and y gradient, blurred, at 1/s resolution over [lo, hi) in those units (zero beyond the picture)."""
    H, W = img.shape
    clo = np.maximum(lo * s, 0)
    chi = np.minimum(hi * s, (W, H))
    crop = img[clo[1] : chi[1], clo[0] : chi[0]]
    if s > 1:
        crop = cv2.resize(crop, ((chi[0] - clo[0]) // s, (chi[1] - clo[1]) // s), interpolation=cv2.INTER_AREA)
    crop = cv2.GaussianBlur(crop, (0, 0), smooth)
    G = np.zeros((2, hi[1] - lo[1], hi[0] - lo[0]), np.float32)
    off = clo // s - lo
    ch, cw = crop.shape
    G[0, off[1] : off[1] + ch, off[0] : off[0] + cw] = cv2.Sobel(crop, cv2.CV_32F, 1, 0) / 8
    G[1, off[1] : off[1] + ch, off[0] : off[0] + cw] = cv2.Sobel(crop, cv2.CV_32F, 0, 1) / 8
    return G


def _unique_rows(a: np.ndarray) -> np.ndarray:
    """``np.unique(a, axis=0)`` of integer points a (M, 2), faster."""
    if len(a) == 0:
        return np.unique(a, axis=0)
    mn = a.min(0)
    span = int(a[:, 1].max() - mn[1]) + 1
    u = np.unique((a[:, 0] - mn[0]) * span + (a[:, 1] - mn[1]))
    return np.column_stack([u // span + mn[0], u % span + mn[1]])


def _ridge_cells(score: np.ndarray, taken: np.ndarray) -> np.ndarray:
    """Cells (row, col) of the quarter-resolution score to refine: ``taken`` (K, 2) its best maxima, then, best first,
    up to ``RIDGE_CANDIDATES`` scoring ``RIDGE_FRACTION`` of the best, none next to one chosen (the +-6 px refinements
    overlap). Sliding along a finger's long sides keeps their score: a ridge, its maximum not always right."""
    flat = score.ravel()
    idx = np.nonzero(flat >= RIDGE_FRACTION * float(flat.max()))[0]
    idx = idx[np.argsort(flat[idx], kind="stable")[::-1]]
    rows, cols = np.divmod(idx, score.shape[1])
    out = [tuple(t) for t in np.asarray(taken, int)]
    n_taken = len(out)
    for y, x in zip(rows.tolist(), cols.tolist()):
        if len(out) - n_taken >= RIDGE_CANDIDATES:
            break
        if all(max(abs(y - ty), abs(x - tx)) >= 2 for ty, tx in out):
            out.append((y, x))
    return np.array(out, int).reshape(-1, 2)


def _coarse_shift(img: np.ndarray, polys: list[np.ndarray], search_px: float, into: np.ndarray, groups: list):
    """Best common shift (2,) px of the polylines over the gradient within +-search_px, and each one's sign of normal
    gradient there (+1: brighter to its left-hand normal); None if the template misses the picture. ``into`` (E, 2)
    image direction into each edge's face; ``groups`` (E,) the face whose silhouette (one polarity all round) it is."""
    H, W = img.shape
    pts = np.vstack(polys)
    left = np.array([_left_normal(p) for p in polys])
    flip = np.array([-1.0 if nrm @ d < 0 else 1.0 for nrm, d in zip(left, into)])  # every normal into its face
    normals = (left * flip[:, None]).astype(np.float32)
    s = 4  # quarter resolution over the whole range: scores of shifts 4 (i - span)
    span = int(np.ceil(search_px / s)) + 1
    lo = np.floor(pts.min(0) / s).astype(int) - span - 2
    hi = np.ceil(pts.max(0) / s).astype(int) + span + 3
    if np.any(np.minimum(hi * s, (W, H)) - np.maximum(lo * s, 0) < 4 * s):
        return None
    G = _padded_gradient(img, lo, hi, s, 1.0)
    tpl = [_unique_rows(np.rint(p / s).astype(int)) - lo - span for p in polys]
    score = _template_score(G, tpl, normals, groups, span)
    # it blurs the fingers' finer edges more than the rims of discs: refine its best few maxima and ridge
    peaks = (score == cv2.dilate(score, np.ones((5, 5), np.uint8))) & (score > 0)
    iy, ix = np.nonzero(peaks)
    order = np.argsort(-score[iy, ix], kind="stable")[:COARSE_CANDIDATES]
    if len(order) == 0:
        return None
    cells = _ridge_cells(score, np.column_stack([iy[order], ix[order]]))
    centres = 4.0 * np.column_stack([cells[:, 1] - span, cells[:, 0] - span])
    r = 6  # full resolution, +-r px around each: one gradient image over every candidate's reach
    lo = np.floor(pts.min(0) + centres.min(0)).astype(int) - r - 2
    hi = np.ceil(pts.max(0) + centres.max(0)).astype(int) + r + 3
    G = _padded_gradient(img, lo, hi, 1, 1.5)
    dv, du = np.mgrid[-r : r + 1, -r : r + 1]
    shifts = np.column_stack([du.ravel(), dv.ravel()])
    Gn = [(normals[e, 0] * G[0] + normals[e, 1] * G[1]).ravel() for e in range(len(polys))]
    gw = G.shape[2]
    flat_shifts = shifts[:, 1] * gw + shifts[:, 0]
    best = None
    for centre in centres:
        sums = np.zeros((len(polys), len(shifts)), np.float32)
        for e, poly in enumerate(polys):
            q = _unique_rows(np.rint(poly + centre).astype(int)) - lo
            sums[e] = Gn[e][(q[:, 1] * gw + q[:, 0])[None, :] + flat_shifts[:, None]].sum(1)
        score = _group_score(sums, groups)
        # the shifts within +-search_px only (a candidate cell's neighbourhood reaches beyond it)
        score = np.where(np.all(np.abs(centre + shifts) <= search_px, axis=1), score, -np.inf)
        i = int(np.argmax(score))
        if np.isfinite(score[i]) and (best is None or score[i] > best[0]):
            best = (score[i], centre + shifts[i], sums[:, i])
    if best is None:
        return None
    _, shift, sums = best
    signs = np.sign(sums) * flip  # back to each polyline's own left-hand normal
    return shift, np.where(signs == 0, 1.0, signs)


def _left_normal(poly: np.ndarray) -> np.ndarray:
    """Unit normal (2,) to the left of the chord of the polyline poly (M, 2)."""
    t = poly[-1] - poly[0]
    return np.array([-t[1], t[0]]) / (np.linalg.norm(t) + 1e-12)


@dataclass
class _Shading:
    """An edge's blur and the slopes of its two plateaus along its profiles (from a first pass)."""

    sigma: float | None = None  # blur along the profile (samples); None: not known, assume 1.6 px
    g_lo: float = 0.0  # grey levels per profile step, on the profile's low side
    g_hi: float = 0.0  # on its high side
    contrast: float = 0.0  # typical grey-level step of the edge
    expect: tuple = (None, None)  # grey levels the low and high side must show (a face's), or None
    tol: float = np.inf  # how far from them


@dataclass
class _Steps:
    pts: np.ndarray  # (E, 2) sub-pixel crossings, distorted pixels
    levels: np.ndarray  # (E, 2) grey levels before and after the step along the profile
    win_val: np.ndarray  # (E, L) each crossing's window of samples along its profile
    win_x: np.ndarray  # (E, L) the samples' coordinates along the profile
    plateau: int  # samples at either end of a window that measure the plateaus
    stations: np.ndarray  # (S, 2) where profiles were scanned (not skipped), on the predicted edge
    pdir: np.ndarray  # (2,) the profiles' direction
    peaks: np.ndarray  # (E, 2) the crossings by the steepest rise instead of the area

    @property
    def scanned(self) -> int:
        return len(self.stations)

    def subset(self, keep: np.ndarray) -> "_Steps":
        return _Steps(self.pts[keep], self.levels[keep], self.win_val[keep], self.win_x[keep], self.plateau,
                      self.stations, self.pdir, self.peaks[keep])

    def blur(self) -> float:
        """Median blur sigma (samples) from the step's share in the rise's middle four samples; only sizes windows."""
        m = self.win_val.shape[1] // 2  # the step lies between samples m - 1 and m
        span = (self.win_val[:, m + 1] - self.win_val[:, m - 2]) / (self.levels[:, 1] - self.levels[:, 0])
        f = float(np.clip(np.median(span), 0.05, 0.999))
        return float(np.interp(f, _BLUR_F, _BLUR_SIGMA))

    def slopes(self) -> tuple[float, float]:
        """Median over the crossings of each plateau's least-squares slope (grey levels per step)."""
        out = []
        for sl in (slice(0, self.plateau), slice(-self.plateau, None)):
            x, v = self.win_x[:, sl], self.win_val[:, sl]
            x = x - x.mean(1, keepdims=True)
            out.append(float(np.median((x * (v - v.mean(1, keepdims=True))).sum(1) / (x * x).sum(1))))
        return out[0], out[1]


def _bilinear(img: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Bilinear grey levels at positions p (..., 2) px, which must lie within [0, W-1) x [0, H-1)."""
    x, y = p[..., 0], p[..., 1]
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    fx, fy = x - x0, y - y0
    v00, v01 = img[y0, x0], img[y0, x0 + 1]
    v10, v11 = img[y0 + 1, x0], img[y0 + 1, x0 + 1]
    return (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy


def _edge_steps(img, poly, pdir, sign, others, search, shading: _Shading, both_signs=False, P=PLATEAU_PX) -> _Steps:
    """Where the edge along ``poly`` (M, 2) crosses profiles along ``pdir`` (2,), one per px. ``sign`` +1/-1: grey
    level grows to the left-hand normal (``both_signs``: either way, as over ink); ``others`` (K, 2) other edges'
    points, whose profiles are skipped; steps ``search`` px either side, showing ``shading.expect`` where given."""
    n = _left_normal(poly)
    cos = float(n @ pdir)
    if abs(cos) < 0.5:  # a face seen too obliquely: sample straight across instead, towards the same side
        pdir = n if cos >= 0 else -n
        cos = float(n @ pdir)
    step_sign = np.sign(cos) * sign  # sign of the grey level's change along the profile
    cos = abs(cos)
    sigma = shading.sigma if shading.sigma is not None else 1.6 / cos  # along the profile
    h = int(np.clip(np.ceil(3 * sigma + 1), 2, 12))  # transition half-width (samples)
    sr = int(np.ceil(search / cos))
    R = sr + h + P + 1
    st = _stations(img.shape, poly, pdir, R, others)
    if len(st) == 0:
        none, no_win = np.zeros((0, 2)), np.zeros((0, 2 * (h + P)))
        return _Steps(none, none, no_win, no_win, P, none, pdir, none)
    j = np.arange(-R, R + 1)
    # dithered sample phase (golden-ratio sequence): a phase's bias averages out instead of repeating on every profile
    ph = (np.arange(len(st)) * 0.6180339887) % 1.0 - 0.5
    pos = st[:, None, :] + (j[None, :] + ph[:, None])[..., None] * pdir[None, None, :]
    prof = _bilinear(img, pos)
    mid = slice(R - sr, R + sr + 1)
    diff = prof[:, mid][:, 1:] - prof[:, mid][:, :-1]
    score = np.abs(diff) if both_signs else diff * step_sign
    # where a face must show on a side, only steps with its grey level there (the plateaus' middles) count
    i = np.arange(diff.shape[1]) + (R - sr)
    for side, off in ((0, -h - P // 2), (1, h + 1 + P // 2)):
        if shading.expect[side] is not None:
            score = np.where(np.abs(prof[:, i + off] - shading.expect[side]) <= shading.tol, score, -np.inf)
    k = np.argmax(score, axis=1)
    rows = np.arange(len(k))
    peak = diff[rows, k]
    sgn = np.sign(peak) if both_signs else np.full(len(k), step_sign)
    at = k - sr  # the step lies between samples at and at + 1 (profile coordinates)
    wi = (at + R)[:, None] + np.arange(-h - P + 1, h + P + 1)[None, :]
    win = prof[rows[:, None], wi].astype(np.float64)
    Am, Bm, e, e_peak = _step_estimates(win, at, h, P, shading, diff, k, sgn)
    good = _plausible(win, Am, Bm, at, e, e_peak, peak, sgn, shading, P)
    return _Steps(st[good] + (e + ph)[good, None] * pdir[None, :], np.column_stack([Am, Bm])[good], win[good],
                  (wi - R)[good].astype(float), P, st, pdir, st[good] + (e_peak + ph)[good, None] * pdir[None, :])


def _stations(shape: tuple, poly: np.ndarray, pdir: np.ndarray, R: int, others: np.ndarray) -> np.ndarray:
    """(S, 2) points 1 px apart along ``poly`` (M, 2) whose +-R sample profiles along ``pdir`` lie in the picture
    (H, W) and pass no point of ``others`` (K, 2) within ``BLUR_MARGIN``."""
    H, W = shape
    run = _arc_length(poly)
    if run[-1] < 2:
        return np.zeros((0, 2))
    s = np.arange(0.5, run[-1], 1.0)
    st = np.column_stack([np.interp(s, run, poly[:, 0]), np.interp(s, run, poly[:, 1])])
    # the whole profile in the picture (only along its direction: an edge may run close to the border)
    reach = (R + 1) * np.abs(pdir)  # the dither adds up to 0.5 sample
    ok = np.all((st - reach >= 0) & (st + reach < (W - 1, H - 1)), axis=1)
    if len(others):
        lo, hi = st.min(0) - R - BLUR_MARGIN, st.max(0) + R + BLUR_MARGIN
        o = others[np.all((others > lo) & (others < hi), axis=1)]
        if len(o):
            rel = o[None, :, :] - st[:, None, :]
            tt = np.clip(rel @ pdir, -R, R)
            ok &= np.min(np.sum((rel - tt[..., None] * pdir) ** 2, axis=2), axis=1) >= BLUR_MARGIN**2
    return st[ok]


def _step_estimates(win, at, h: int, P: int, shading: _Shading, diff, k, sgn):
    """Plateau levels (Am, Bm) and crossings (e, e_peak), profile coordinates, of the step between samples ``at``,
    ``at + 1`` in windows ``win`` (M, 2 (h + P)). e (area): the ideal step between the plateaus sloped by ``shading``
    (grey levels/sample) holding the transition's sum (Newton). e_peak: a Gaussian through the three differences
    ``diff`` (M, D) around ``k`` (M,) of sign ``sgn`` (robust to texture), NaN where they make no peak."""
    g_lo, g_hi = shading.g_lo, shading.g_hi
    Am = win[:, :P].mean(1)
    Bm = win[:, -P:].mean(1)
    x_lo, x_hi = at - h + 0.5, at + h + 0.5  # the transition
    x_A, x_B = x_lo - P / 2, x_hi + P / 2  # where the plateau means lie
    S = win[:, P:-P].sum(1)
    e = at + 0.5
    rows = np.arange(len(k))
    with np.errstate(divide="ignore", invalid="ignore"):
        for _ in range(3):
            Ae = Am - g_lo * (x_A - e)
            Be = Bm - g_hi * (x_B - e)
            F = Ae * (e - x_lo) - g_lo * (e - x_lo) ** 2 / 2 + Be * (x_hi - e) + g_hi * (x_hi - e) ** 2 / 2 - S
            e = e - F / (Ae - Be)
        kk = np.clip(k, 1, diff.shape[1] - 2)
        lm, l0, lp = (np.log(np.maximum(diff[rows, kk + i] * sgn, 1e-3)) for i in (-1, 0, 1))
        den = lm - 2 * l0 + lp
        e_peak = at + (kk - k) + 0.5 + np.where(den < 0, 0.5 * (lm - lp) / den, np.nan)
    return Am, Bm, e, e_peak


def _plausible(win, Am, Bm, at, e, e_peak, peak, sgn, shading: _Shading, P: int) -> np.ndarray:
    """(M,) whether each window holds one clean step of polarity ``sgn``, with enough contrast, the sides' levels
    ``shading`` expects and estimates near the chosen step."""
    contrast = np.abs(Bm - Am)
    rough = np.maximum(np.ptp(win[:, :P], axis=1), np.ptp(win[:, -P:], axis=1))
    slope_allow = (abs(shading.g_lo) + abs(shading.g_hi)) * P
    return (((Bm - Am) * sgn >= max(MIN_CONTRAST, 0.35 * shading.contrast))
            & (np.abs(Am - (shading.expect[0] if shading.expect[0] is not None else Am)) <= shading.tol)
            & (np.abs(Bm - (shading.expect[1] if shading.expect[1] is not None else Bm)) <= shading.tol)
            & (rough <= 0.08 * contrast + 8 + slope_allow)
            & (np.ptp(win, axis=1) <= 1.15 * contrast + 10 + slope_allow)  # one step only: no ink or other edge
            & (np.abs(e - (at + 0.5)) < 1.5) & (np.abs(e_peak - (at + 0.5)) < 1.0) & (peak * sgn > 0))


def _line_tls(q: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float]:
    """Weighted total-least-squares line through q (N, 2): unit normal n and c with n.q = c."""
    m = (w[:, None] * q).sum(0) / w.sum()
    d = q - m
    sxx, syy, sxy = (w * d[:, 0] ** 2).sum(), (w * d[:, 1] ** 2).sum(), (w * d[:, 0] * d[:, 1]).sum()
    ang = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # direction of the largest spread
    n = np.array([-np.sin(ang), np.cos(ang)])
    return n, float(n @ m)


def tukey_weights(r: np.ndarray, floor: float) -> tuple[np.ndarray, float]:
    """Tukey's biweights of residuals r (N,) and their robust scale: 1.4826 median |r|, at least ``floor``; a
    residual beyond 4.685 scales weighs 0."""
    # np.median's value by partition: 7-9 us against 17 us, called per edge and reweighting step of every frame
    a, k = np.abs(r), len(r) // 2
    med = float(np.partition(a, k)[k] if len(a) % 2 else np.mean(np.partition(a, (k - 1, k))[k - 1:k + 1]))
    s = max(1.4826 * med, floor)
    u = r / (4.685 * s)
    return np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0), s


@functools.lru_cache(maxsize=4096)
def _pair_draws(N: int) -> tuple[np.ndarray, np.ndarray]:
    """The 40 index pairs (i, j) ``_fit_line`` tries for N points; seeded with N, so cached (read-only)."""
    rng = np.random.default_rng(N)
    ij = (rng.integers(0, N, 40), rng.integers(0, N, 40))
    for a in ij:
        a.flags.writeable = False
    return ij


def _fit_line(q: np.ndarray, t_pred: np.ndarray, iters: int = 3):
    """Robust line n.q = c through q (N, 2) near direction ``t_pred`` (2,): the point pair (within 10 degrees) with
    most points within 0.25 px, then Tukey reweighting (scale >= 0.05 px). Returns (n, c, inlier mask)."""
    N = len(q)
    t_pred = t_pred / np.linalg.norm(t_pred)
    i, j = _pair_draws(N)
    d = q[j] - q[i]
    ln = np.linalg.norm(d, axis=1)
    ok = (ln > 5.0) & (np.abs(d @ t_pred) > np.cos(np.radians(10)) * ln)
    if np.any(ok):
        nrm = np.column_stack([-d[ok, 1], d[ok, 0]]) / ln[ok, None]
        res = q @ nrm.T - np.sum(nrm * q[i[ok]], axis=1)[None, :]
        best = int(np.argmax(np.sum(np.abs(res) < 0.25, axis=0)))
        w = (np.abs(res[:, best]) < 0.25).astype(float)
    else:
        w = np.ones(N)
    for _ in range(iters):
        n, c = _line_tls(q, w)
        w = tukey_weights(q @ n - c, 0.05)[0]
        if w.sum() < 2:
            break
    return n, c, w > 0


@dataclass
class _Fit:
    n: np.ndarray  # unit normal of the line n.q = c, undistorted pixels
    c: float
    q: np.ndarray  # the inlier crossings, undistorted pixels
    shading: _Shading
    scanned_q: np.ndarray  # (S, 2) where profiles were scanned, undistorted pixels
    pdir: np.ndarray  # (2,) the profiles' direction
    levels: np.ndarray  # (2,) median grey levels on the profiles' low and high side
    reach: float  # how far from the edge (px along pdir) the plateaus were measured


def _fit_edge(img, cam, poly, pdir, sign, others, shading: _Shading, first: bool, both: bool, crease: bool):
    """Crossings of one edge and a robust line through them (undistorted px): (_Fit, None) or (None, the reason). The
    first pass searches wide and measures the second's shading; ``both``: either polarity (ink reverses it)."""
    search, plateau = (8.0, 5) if first else (3.0, PLATEAU_PX)
    st = _edge_steps(img, poly, pdir, sign, others, search, shading, both, plateau)
    need = max(6, int((0.15 if first else 0.3) * st.scanned))  # the first pass sees one polarity only
    if len(st.pts) < need:
        return None, f"too few edge points ({len(st.pts)} of {st.scanned} crossings)"
    pred_q = cam.undistorted_pixels(poly[[0, -1]])
    t = pred_q[1] - pred_q[0]
    # areas are exact on flat plateaus, peaks hold on texture: does the background (low side) wander beyond noise?
    textured = first
    if not first and not crease and len(st.levels) >= 12:
        wander = np.median(np.abs(st.levels[6:] - st.levels[:-6]), axis=0) * 1.4826 / np.sqrt(2)
        textured = bool(wander[0] > max(1.2, 1.5 * min(wander[1], 1.0)))
    q = cam.undistorted_pixels(st.peaks if textured else st.pts)
    n, c, inl = _fit_line(q, t)
    if inl.sum() < need:
        return None, f"too few edge points on a line ({int(inl.sum())} of {st.scanned} crossings)"
    if abs(n @ t) / np.linalg.norm(t) > np.sin(np.radians(10)):
        return None, "edge direction differs from the prediction by more than 10 degrees"
    if first:
        good = st.subset(inl)
        contrast = float(np.median(np.abs(good.levels[:, 1] - good.levels[:, 0])))
        shading = _Shading(good.blur(), *good.slopes(), contrast, shading.expect, shading.tol)
    h_reach = st.win_x.shape[1] / 2 - st.plateau / 2 if len(st.win_x) else 0.0
    levels = np.median(st.levels[inl], axis=0)
    return _Fit(n, c, q[inl], shading, cam.undistorted_pixels(st.stations), st.pdir, levels, h_reach), None


def _move_poly(cam, poly, fit: _Fit) -> np.ndarray:
    """The polyline projected onto a fitted line (undistorted) and distorted back."""
    q = cam.undistorted_pixels(poly)
    q = q - ((q @ fit.n) - fit.c)[:, None] * fit.n[None, :]
    return cam.distort_to_pixels(cam.pixel_to_sensor(q))


def search_corners(image, pred: PredictedFingers, search_px, points):
    """The corner search of ``find_fingertips``: a ``FingertipResult``. Raises ``ValueError`` for a ``search_px``
    that is not a positive number of px or ``points`` outside 0..5."""
    if isinstance(search_px, bool) or not isinstance(search_px, (int, float, np.number)) \
            or not (math.isfinite(search_px) and search_px > 0):
        raise ValueError(f"search_px: expected a positive number of pixels, got {search_px!r}")
    camera = pred.camera
    img = as_gray(image, camera)
    model = _Model(pred)
    want = sorted({int(k) for k in points})
    if any(k < 0 or k > 5 for k in want):
        raise ValueError(f"points: expected indices 0..5 into POINT_NAMES, got {list(points)}")
    res = FingertipResult(uv=np.full((6, 2), np.nan), found=np.zeros(6, bool),
                          reasons=[None if k in want else "not requested" for k in range(6)],
                          edge_rms_px=np.full(6, np.nan), names=POINT_NAMES, n_edge_points=np.zeros(6, int))
    H, W = img.shape
    for f in (0, 1):
        todo = []
        for k in (k for k in want if POINT_FINGER[k] == f):
            pu, pv = model.uv[k]
            if pu < -search_px or pv < -search_px or pu > W - 1 + search_px or pv > H - 1 + search_px:
                res.reasons[k] = f"outside the picture (predicted at {pu:.0f}, {pv:.0f})"
            elif model.hidden[k] is not None:
                res.reasons[k] = f"occluded by finger {FINGERS[model.hidden[k]]}"
            elif len(model.corner_edges[k]) < 2:
                res.reasons[k] = "fewer than two of its edges face the camera"
            else:
                todo.append(k)
        located = _locate_edges(img, camera, model, f, todo, search_px)
        if located is None:
            for k in todo:
                res.reasons[k] = "outside the picture"
            continue
        fits, fails, shift = located
        for k in todo:
            corner = _corner(img, camera, model, k, fits, fails, search_px, model.uv[k] + shift)
            if isinstance(corner, str):
                res.reasons[k] = corner
            else:
                res.uv[k], res.edge_rms_px[k], res.n_edge_points[k] = corner
                res.found[k] = True
    return res


def _locate_edges(img, camera, model: _Model, f: int, todo: list[int], search_px: float):
    """Fit the visible edges of finger ``f`` at the corners ``todo``: coarse alignment, then two passes. Returns
    ({edge key: _Fit}, {edge key: why it failed}, coarse shift (2,)) or None (nothing to search, or out of view)."""
    polys: dict[tuple, np.ndarray] = {}
    pdirs: dict[tuple, np.ndarray] = {}
    for k in todo:
        for e, far in model.corner_edges[k]:
            if e.key not in polys:
                poly = model.polyline(model.points_G[k], far, TEMPLATE_PX)
                if len(poly) >= 4:
                    polys[e.key] = poly
                    pdirs[e.key] = model.profile_dir(e, model.points_G[k])
    keys = list(polys)
    groups = [("crease", k) if model.edges[k].crease else model.edges[k].faces[0] for k in keys]
    if not keys:
        return None
    coarse = _coarse_shift(img, [polys[e] for e in keys], search_px, np.array([pdirs[e] for e in keys]), groups)
    if coarse is None:
        return None
    shift, signs = coarse
    cur = {e: polys[e] + shift for e in keys}
    sign = dict(zip(keys, signs))
    # every visible edge of the finger that reaches the tip plane, from there as far as the scans go
    reach = TEMPLATE_PX + 2 * search_px + 20
    all_other = {e.key: model.polyline(*((e.b_G, e.a_G) if e.b_G[2] > e.a_G[2] else (e.a_G, e.b_G)), reach) + shift
                 for e in model.edges.values() if e.finger == f and max(e.a_G[2], e.b_G[2]) > -1e-9}
    fits: dict[tuple, _Fit] = {}
    fails: dict[tuple, str | None] = {}  # read only for edges not in fits

    def run(key, first: bool, shading: _Shading, both: bool):
        poly = cur[key][: max(4, int(len(cur[key]) * FIT_PX / TEMPLATE_PX))]
        others = np.vstack([p for kk, p in all_other.items() if kk != key] or [np.zeros((0, 2))])
        crease = model.edges[key].crease
        fit, fails[key] = _fit_edge(img, camera, poly, pdirs[key], sign[key], others, shading, first, both, crease)
        fits.pop(key, None)
        if fit is not None:
            fits[key] = fit

    for key in keys:
        run(key, True, _Shading(), False)
    # an edge whose face level the face's other edges contradict found ink, one not found may lie over it: look again
    expect = _face_levels(model, fits)
    for key in keys:
        exp, tol = _expected_sides(model.edges[key], expect, fits.get(key))
        if key not in fits or any(x is not None and abs(lv - x) > tol for x, lv in zip(exp, fits[key].levels)):
            if any(x is not None for x in exp):
                run(key, True, _Shading(expect=exp, tol=tol), True)
    expect = _face_levels(model, fits)
    for key, fit in fits.items():  # centre the second pass on the first's lines
        cur[key] = _move_poly(camera, cur[key], fit)
        if key in all_other:
            all_other[key] = _move_poly(camera, all_other[key], fit)
    for key in keys:
        if key in fits:
            exp, tol = _expected_sides(model.edges[key], expect, fits[key])
            run(key, False, replace(fits[key].shading, expect=exp, tol=tol), True)
    return fits, fails, shift


def _face_levels(model: _Model, fits: dict) -> dict[tuple, list[tuple]]:
    """Grey levels each face shows beside its fitted edges: {face: [(edge key, level, crossings)]}."""
    out: dict[tuple, list[tuple]] = {}
    for key, fit in fits.items():
        e = model.edges[key]
        # the profiles run into the first face; a crease's second face lies on their low side
        for face, level in zip(e.faces, (fit.levels[1], fit.levels[0])):
            out.setdefault(face, []).append((key, float(level), len(fit.q)))
    return out


def _expected_sides(edge: _Edge, levels: dict, fit: _Fit | None) -> tuple[tuple, float]:
    """Grey levels the low and high side of an edge's profiles should show (the face's other edges' median,
    weighted by crossings), and the tolerance from the contrast."""
    exp = [None, None]
    for face, side in zip(edge.faces, (1, 0)):
        others = sorted((lv, n) for k, lv, n in levels.get(face, []) if k != edge.key and lv == lv)
        if others:
            lv = np.array([o[0] for o in others])
            cw = np.cumsum([o[1] for o in others])
            exp[side] = float(lv[np.searchsorted(cw, cw[-1] / 2)])
    if fit is not None and exp[1] is not None:
        contrast = abs(exp[1] - float(fit.levels[0])) if exp[0] is None else abs(exp[1] - exp[0])
    elif fit is not None:
        contrast = abs(float(fit.levels[1] - fit.levels[0]))
    else:
        contrast = max((abs(a - b) for a in exp if a is not None for b in exp if b is not None), default=0.0)
    tol = max(15.0, 0.3 * contrast)
    return (exp[0], exp[1]), tol


def _faces_reach_corner(img, camera, fit: _Fit, crease: bool, q_corner, gap: float) -> bool:
    """Whether the face(s) beside an edge keep their grey level up to the corner where no edge points were found
    (ink behind the edge, not something in front). ``crease``: check both sides, else the profiles' high side."""
    t = np.array([-fit.n[1], fit.n[0]])
    if (fit.q.mean(0) - q_corner) @ t < 0:
        t = -t
    along = q_corner[None, :] + np.arange(6.0, 6.0 + gap)[:, None] * t[None, :]
    base = camera.distort_to_pixels(camera.pixel_to_sensor(along))
    sides = [(+1, fit.levels[1])] + ([(-1, fit.levels[0])] if crease else [])
    H, W = img.shape
    for sgn, level in sides:
        p = base + sgn * fit.reach * fit.pdir[None, :]
        inside = np.all((p >= 0) & (p < (W - 1, H - 1)), axis=1)
        if inside.sum() < 0.7 * len(p):
            return False
        v = _bilinear(img, p[inside])
        tol = max(10.0, 0.25 * abs(fit.levels[1] - fit.levels[0]))
        if np.mean(np.abs(v - level) <= tol) < 0.7:
            return False
    return True


def _corner(img, camera, model, k, fits, fails, search_px, aligned):
    """Intersect the fitted edges at corner k: (uv (2,) px, rms, n points) or why not; ``aligned`` (2,) coarse guess."""
    H, W = img.shape
    lines = [(fits[e.key], e) for e, _ in model.corner_edges[k] if e.key in fits]
    if len(lines) < 2:
        if not (2.0 <= aligned[0] <= W - 3.0 and 2.0 <= aligned[1] <= H - 3.0):
            return f"outside the picture (at about {aligned[0]:.0f}, {aligned[1]:.0f})"
        bad = [fails.get(e.key, "not scanned") for e, _ in model.corner_edges[k] if e.key not in fits]
        return "edges not found: " + "; ".join(bad)
    N = np.array([ln.n for ln, _ in lines])
    c = np.array([ln.c for ln, _ in lines])
    sin = min(abs(N[i, 0] * N[j, 1] - N[i, 1] * N[j, 0]) for i in range(len(N)) for j in range(i + 1, len(N)))
    if sin < np.sin(np.radians(10)):
        return "its edges are nearly parallel in the picture"
    q = np.linalg.lstsq(N, c, rcond=None)[0]
    if len(lines) > 2:  # weigh each line by its uncertainty at the corner: scatter, count, lever arm
        wts = []
        for ln, _ in lines:
            t = np.array([-ln.n[1], ln.n[0]])
            s = ln.q @ t
            r = ln.q @ ln.n - ln.c
            lever = (q @ t - s.mean()) ** 2 / max(np.sum((s - s.mean()) ** 2), 1e-9)
            var = max(float(np.mean(r**2)), 0.03**2) * (1 / len(s) + lever)
            wts.append(1 / np.sqrt(var))
        wts = np.array(wts)
        q = np.linalg.lstsq(N * wts[:, None], c * wts, rcond=None)[0]
    p = camera.distort_to_pixels(camera.pixel_to_sensor(q))
    if not (1.0 <= p[0] <= W - 2.0 and 1.0 <= p[1] <= H - 2.0):
        return f"outside the picture (at {p[0]:.0f}, {p[1]:.0f})"
    if np.linalg.norm(p - model.uv[k]) > search_px * 1.5:
        return f"found {np.linalg.norm(p - model.uv[k]):.0f} px from its prediction, beyond the search range"
    # the edges must be seen up to near the corner, or the finger's faces must: otherwise it is hidden
    for ln, e in lines:
        gap = np.min(np.linalg.norm(ln.q - q, axis=1)) - np.min(np.linalg.norm(ln.scanned_q - q, axis=1))
        if gap > 10.0 and not _faces_reach_corner(img, camera, ln, e.crease, q, gap):
            return f"occluded: no edge points within {gap:.0f} px of it"
    r = np.concatenate([ln.q @ ln.n - ln.c for ln, _ in lines])
    rms = float(np.sqrt(np.mean(r**2)))
    if rms > MAX_EDGE_RMS_PX:  # the lines rest on something else than straight edges (a rim of ink)
        return f"its edge points scatter by {rms:.2f} px about their lines: not the finger's edges"
    return p, rms, len(r)
