"""Disc detection on the calibration plate (the off-line calibration's first step, paper section 3): a ``rows x cols``
array of dark discs at ``pitch`` mm on a light sheet (CONVENTIONS.md). ``detect_discs`` measures and indexes the whole
discs of a picture; ``correct_disc_bias`` removes their centres' perspective and lens bias for a pose of the plate."""

from __future__ import annotations

import contextlib
import itertools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import PlateSpec
from selfview.files.io_safe import uint16_gain
from selfview.errors import ImageError
from selfview.maths.geometry import transform_points

__all__ = ["DiscDetections", "detect_discs", "correct_disc_bias", "disc_image_bias", "as_gray", "gray_u8"]

#: A pixel belongs to a disc candidate when it is this much darker than the paper around it (relative).
DARK_FRACTION = 0.3
#: Outlines: the contrast smoothed by a Gaussian of at least this sigma [px], more where pixel noise stays above this.
OUTLINE_BLUR_PX, OUTLINE_NOISE = 0.7, 0.01
#: Round test: a blob's area over its convex hull's at least this.
SOLIDITY = 0.9
#: Ring test: a ring pixel deviating from the fitted paper plane by more than this (relative) is not paper.
RING_TOLERANCE = 0.12
#: Ring test: paper off one plane by more than this rms (relative; pixel noise taken out) lies across a shadow's edge.
SLOPE_RMS = 0.025
#: ... or when a quadratic leaves less than this share of the plane's mean square residual there.
CURVED_SHARE = 0.6
#: Pixel noise: a ring pixel's tolerance at least this many sigmas of it; it is taken out of the rms SLOPE_RMS judges.
NOISE_SIGMAS = 4.0
#: Centre weight: the share of a disc's own ink contrast where a pixel's weight starts (0) and saturates (1).
INK_RAMP = (0.1, 0.9)
#: Shadow's edge: the halving steps [deg], two to a fit, that refine the best of ``_edge_level``'s 15 deg steps.
REFINE_STEPS_DEG = ((8, 4), (2, 1))
#: Size test: a disc's area over its lattice cell's, relative to the plate's pi/4 (d/pitch)^2, lies in this range.
DISC_SHARE = (0.5, 2.0)
#: Square test: the plate's axes as seen within this cosine of a right angle, their lengths within this share.
SQUARE_TOLERANCE = 0.3
#: Lattice test: a disc off the midpoint of its two neighbours on a line by more than this (of a step).
LATTICE_TOLERANCE = 0.15
#: Faint discs (their centres' median contrast under this): measured again with a grey pedestal taken off, glare's
#: (haze, a raised black level: the plate's 1st-percentile ink ``INK_CONTRAST`` below its paper), then a defocus's
#: (its ink spread: the discs' contrast falls, not the paper's) at ``DEFOCUS_PEDESTAL`` of the paper's level.
FAINT, INK_CONTRAST, DEFOCUS_PEDESTAL = 0.5, 0.6, 0.5


@dataclass
class DiscDetections:
    """Discs found in one picture, sorted by (row, col): ``uv`` (N, 2) sub-pixel centres [px, distorted: each disc
    image's centroid]; ``rc`` (N, 2) int (row, col), 0-based; ``p_W`` (N, 3) centres in W [mm], z = 0, origin at the
    grid centre; ``area_px`` (N,) pixels above the darkness threshold; ``n_blobs`` candidate blobs; ``rejected`` the
    dropped ones by reason; ``index_basis`` how each axis was anchored (``_anchor``); ``ambiguous`` per axis nothing
    pins, the indices it may take (while not empty, the grid's origin, so ``p_W`` and any ``C_H_W``, is a guess);
    ``pedestal`` the grey level taken off a faint picture before measuring it (``FAINT``), 0 for none."""

    uv: np.ndarray
    rc: np.ndarray
    p_W: np.ndarray
    area_px: np.ndarray
    n_blobs: int
    rejected: dict[str, int]
    index_basis: dict[str, str] = field(default_factory=dict)
    ambiguous: dict[str, str] = field(default_factory=dict)
    pedestal: float = 0.0

    @property
    def origin_pinned(self) -> bool:
        """Whether the picture fixes the grid's origin (every axis's index anchored by what is seen)."""
        return not self.ambiguous

    def __len__(self) -> int:
        return len(self.uv)


def as_gray(image, camera: CameraModel | None = None, what: str = "picture") -> np.ndarray:
    """The picture as a (H, W) float32 grey image (0..255) from (H, W), (H, W, 1), BGR or BGRA uint8, uint16
    (``uint16_gain``) or float. ``ImageError`` for no image, the wrong size for ``camera``, or blank (span < 12)."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (1, 3, 4):
        a = a[..., 0] if a.shape[2] == 1 else a[..., :3]
    gain = uint16_gain(a) if a.dtype == np.uint16 and a.size else 1.0
    if a.ndim == 3 and a.shape[2] == 3:
        a = a.astype(np.float32) @ np.array([0.114, 0.587, 0.299], np.float32)  # BGR weights
    if a.ndim != 2 or a.size == 0:
        raise ImageError(f"{what}: expected a grey or BGR image, got an array of shape {np.shape(image)}")
    if a.dtype.kind not in "iuf" or (a.dtype.kind in "iu" and a.dtype not in (np.uint8, np.uint16)
                                     and not 0 <= a.min() <= a.max() <= 255):  # not bool, object, or a wider scale
        raise ImageError(f"{what}: expected uint8, uint16, float or 0..255 integer pixels, got dtype {a.dtype}")
    h, w = a.shape
    if camera is not None and (h, w) != (int(camera.height), int(camera.width)):
        raise ImageError(f"{what} is {w}x{h} px but the camera model expects {int(camera.width)}x{int(camera.height)}")
    g = np.multiply(a, gain, dtype=np.float32)
    if a.dtype.kind == "f" and not np.all(np.isfinite(g)):
        raise ImageError(f"{what}: contains NaN or infinite pixels")
    lo, hi = np.percentile(a[::3, ::3] if a.dtype == np.uint8 else g[::3, ::3], [1, 99])
    if hi - lo < 12:
        raise ImageError(f"blank {what}: its grey levels span only {lo:.0f}..{hi:.0f}")
    return g


def gray_u8(image, camera: CameraModel | None = None, what: str = "picture") -> np.ndarray:
    """``as_gray``'s picture rounded to uint8, for OpenCV's board and marker detectors."""
    return np.clip(np.rint(as_gray(image, camera, what)), 0, 255).astype(np.uint8)


def _paper_level(work: np.ndarray) -> np.ndarray:
    """Local level (H, W) of the light background: a grey closing wider than a disc, at quarter resolution, smoothed but
    never below it (the smoothing would darken the paper by the sheet's edge, and the discs beside it)."""
    h, w = work.shape
    small = cv2.resize(work, (max(8, w // 4), max(8, h // 4)), interpolation=cv2.INTER_AREA)
    k = max(5, (max(small.shape) // 6) | 1)
    closed = cv2.morphologyEx(small, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_RECT, (k, k)))
    closed = cv2.max(closed, cv2.blur(closed, (k // 3 | 1, k // 3 | 1)))
    return cv2.resize(closed, (w, h), interpolation=cv2.INTER_LINEAR)


def _ellipse_misfit(blob: np.ndarray) -> tuple[float, float]:
    """(solidity, max distance [px] of the outline from its fitted ellipse) of a blob mask."""
    contours, _ = cv2.findContours(blob.view(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    c = max(contours, key=len)
    if len(c) < 6:
        return 0.0, np.inf
    hull = cv2.contourArea(cv2.convexHull(c))
    solidity = np.count_nonzero(blob) / max(hull + len(c) / 2.0, 1.0)  # contour runs through pixel centres
    if solidity < SOLIDITY:  # not round whatever the ellipse: no fit needed
        return solidity, np.inf
    (ex, ey), (da, db), ang = cv2.fitEllipse(c)
    if min(da, db) <= 0:
        return solidity, np.inf
    ct, st = math.cos(math.radians(ang)), math.sin(math.radians(ang))
    dx, dy = c[:, 0, 0] - ex, c[:, 0, 1] - ey  # by hand: a (n, 2) @ (2, 2) costs more in numpy's calls
    rho = np.hypot((dx * ct + dy * st) / (da / 2), (dy * ct - dx * st) / (db / 2))
    return solidity, float(np.abs(rho - 1).max()) * (da + db) / 4


def _round_blobs(labels, stats, reject, smooth) -> tuple[list[int], np.ndarray]:
    """(labels of the elliptical blobs clear of the picture's border, ``stats`` with the cores split off blobs that
    are not: ``_split``), the others ``reject``ed by reason; ``labels`` gets the split cores' labels in place."""
    H, W = labels.shape
    x, y, w, h, area = stats[1:].T
    speck = area < 20
    edge = ~speck & ((x == 0) | (y == 0) | (x + w == W) | (y + h == H))
    reject("speck", np.count_nonzero(speck))
    reject("picture edge", np.count_nonzero(edge))
    round_, todo, split = [], list(np.flatnonzero(~(speck | edge)) + 1), set()
    while todo:
        k = todo.pop(0)
        x, y, w, h, area = stats[k].tolist()
        solidity, misfit = (0.0, np.inf) if area > 0.05 * H * W else _ellipse_misfit(labels[y : y + h, x : x + w] == k)
        if solidity >= SOLIDITY and misfit <= max(1.6, 0.035 * np.sqrt(area)):
            round_.append(k)
            continue
        cores = [] if k in split else _split(smooth, labels, k, (x, y, w, h), len(stats))
        if cores:
            new = range(len(stats), len(stats) + len(cores))
            split.update(new)
            todo += [j for j in new if cores[j - new[0]][4] >= 20]
            stats = np.vstack([stats, cores])
        else:
            reject("too large" if area > 0.05 * H * W else "not elliptical")
    return round_, stats


def _split(smooth, labels, k, bbox, first: int) -> list:
    """Stats rows of the cores of blob ``k`` (discs merged with a shadow's edge by the threshold) darker than midway
    from ``DARK_FRACTION`` to its ink (95th percentile), labelled from ``first`` in ``labels``; the rest of ``k``
    becomes paper (``_centroid``'s ring sees the shadow). Empty when no core is distinctly darker than the rest."""
    x, y, w, h = bbox
    sub, lab = smooth[y : y + h, x : x + w], labels[y : y + h, x : x + w]
    own = lab == k
    t = (DARK_FRACTION + float(np.percentile(sub[own], 95))) / 2
    if t < 1.5 * DARK_FRACTION:
        return []
    n, cl, st, _ = cv2.connectedComponentsWithStats((own & (sub > t)).view(np.uint8), connectivity=8)
    if n < 2:
        return []
    lab[own] = 0
    for j in range(1, n):
        lab[cl == j] = first + j - 1
    return [[x + a, y + b, c, d, e] for a, b, c, d, e in st[1:]]


def _measure_discs(work, labels, stats, round_: list[int], reject, noise: float) -> tuple[list, list]:
    """(centres, areas [px]) of round blobs of the plate's disc size (``_typical_area``), the others ``reject``ed."""
    typical = _typical_area(stats[round_, cv2.CC_STAT_AREA]) if round_ else 0.0
    small = stats[:, cv2.CC_STAT_AREA] < 0.25 * typical
    uv, areas = [], []
    for k in round_:
        x, y, w, h, area = stats[k].tolist()
        if area < 0.25 * typical or area > 4 * typical:
            reject("speck" if area < 0.25 * typical else "too large")
            continue
        why, c = _centroid(work, labels, k, (x, y, w, h), area, small, noise)
        if why:
            reject(why)
            continue
        uv.append(c)
        areas.append(area)
    return uv, areas


def _centroid(work, labels, k, bbox, area, small, noise) -> tuple[str | None, np.ndarray | None]:
    """(None, sub-pixel centre (2,) [px]) of blob ``k``, or (why it is no whole, clean disc, None): the centroid of
    ink (``_weighted_centre``) over a support around the blob, against paper I_paper a plane fitted to the ring beyond
    it (``_edge_level`` across a shadow's edge). A symmetric blur keeps ink's first moment (edge-based ellipse fits
    shift); it is the distorted image's centroid, ``correct_disc_bias`` removes the difference."""
    x, y, w, h = bbox
    H, W = work.shape
    d = 2 * math.sqrt(area / math.pi)
    m_in = min(max(round(0.2 * d), 3), 10)
    m_ring = min(max(round(0.15 * d), 2), 8)
    m = m_in + m_ring
    if x < 2 or y < 2 or x + w > W - 2 or y + h > H - 2:
        return "picture edge", None
    x0, y0, x1, y1 = max(x - m, 0), max(y - m, 0), min(x + w + m, W), min(y + h + m, H)
    masks = _support_and_ring(labels[y0:y1, x0:x1], k, area, small, m_in, m)
    if masks is None:
        return "crowded", None
    dist, support, ring, halo = masks
    crop, cu, cv_ = work[y0:y1, x0:x1], (x1 - x0 - 1) / 2, (y1 - y0 - 1) / 2
    gu, gv = np.repeat([np.arange(x1 - x0) - cu], y1 - y0, 0), np.repeat(np.arange(y1 - y0)[:, None] - cv_, x1 - x0, 1)
    z, u, v = crop[ring].astype(np.float64), gu[ring], gv[ring]
    A = np.array([np.ones(len(z)), u, v, u * u, u * v, v * v])  # a quadratic's rows; the plane's the first three
    N, b = A @ A.T, A @ z
    coef = _least_squares(N[:3, :3], b[:3])
    if coef is None:  # ring pixels on one line: no paper around the disc
        return "crowded", None
    r_ring = z - coef @ A[:3]
    # the pixel noise widens a ring pixel's tolerance, starts the centre's weights above it, and is taken out of the rms
    floor = NOISE_SIGMAS * noise / coef[0] if coef[0] > 0 else 0.0
    tol, slope = max(RING_TOLERANCE, floor), math.hypot(SLOPE_RMS * coef[0], noise)
    off = np.abs(r_ring) > tol * coef[0]
    share_off = np.count_nonzero(off) / len(off)
    if coef[0] > 0 and (share_off > 0.01 or _curved(A, z, r_ring, slope, (N, b))):
        # a shadow's edge across the disc changes the paper's level along one direction only; a mark does not
        level = _edge_level(A[1], A[2], z, np.arctan2(coef[2], coef[1]), tol)
        if level is not None:
            return _weighted_centre(crop, support, level, (gu, gv), (x0 + cu, y0 + cv_), area, floor)
    level = None
    if coef[0] > 0 and share_off > 0.01:
        # a mark or the sheet's edge in the ring: refit on the paper, or a shadow's edge without the mark (the second
        # try); the disc is kept if the thing is clear of it
        coef = np.linalg.lstsq(A[:3, ~off].T, z[~off], rcond=None)[0]
        for again in (False, True):
            level = again and _edge_level(A[1], A[2], z, np.arctan2(coef[2], coef[1]), tol, marks=True)
            if again and not level:
                return "occluded", None
            paper = level(gu, gv) if level else coef[0] + coef[1] * gu + coef[2] * gv
            resid = cv2.blur((crop.astype(np.float64) - paper).astype(np.float32), (3, 3))  # noise-proof
            foreign = (np.abs(resid) > tol * coef[0]) & (dist > 2)
            _, flab, fst, _ = cv2.connectedComponentsWithStats(foreign.astype(np.uint8), connectivity=8)
            # a thing touching the disc hides part of it, unless it is another blob's halo or a pixel or two of noise
            near = set(np.unique(flab[foreign & (dist <= 3)])) - set(np.unique(flab[foreign & halo])) - {0}
            if not {j for j in near if fst[j, cv2.CC_STAT_AREA] > 3}:
                break
        share_off = np.count_nonzero(foreign[ring]) / len(z)
        support &= ~foreign
    if coef[0] <= 0 or share_off >= 0.3:
        return "occluded", None
    level = level or (lambda u, v: coef[0] + coef[1] * u + coef[2] * v)
    return _weighted_centre(crop, support, level, (gu, gv), (x0 + cu, y0 + cv_), area, floor)


def _support_and_ring(lab, k, area, small, m_in, m):
    """(distance from blob ``k`` [px], support, ring, halo of other blobs) in the label crop ``lab``; pixels nearer or
    beside another blob are in neither. None when crowded (a blob larger than a mark beside it, too little its own)."""
    not_k = lab != k
    dist = cv2.distanceTransform(not_k.view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)
    other = not_k & (lab > 0)
    if other.any():
        d_other = cv2.distanceTransform((~other).view(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_5)
        if not small[lab[other & (dist <= 2.0)]].all():
            return None
        mine = d_other > np.maximum(dist, 2.0)  # nearer this blob, and not beside another
        clear = mine & (d_other > 2.5)  # ... and not within the blur of another
        halo = d_other <= 2.5
    else:  # no other blob in reach (about half the discs): every pixel is this blob's
        mine, clear, halo = True, True, False
    in_sup = dist <= m_in
    band = (dist <= m) ^ in_sup
    support = in_sup & mine
    ring = band & clear
    n_ring = np.count_nonzero(ring)
    fr_ring = n_ring / max(np.count_nonzero(band), 1)
    fr_sup = np.count_nonzero(support & not_k) / max(np.count_nonzero(in_sup) - area, 1)
    return None if fr_ring < 0.05 or n_ring < 12 or fr_sup < 0.5 else (dist, support, ring, halo)


def _weighted_centre(crop, support, level, grid, centre, area, floor) -> tuple[str | None, np.ndarray | None]:
    """``_centroid``'s answer, or "occluded": centroid [px] of ``support`` weighted by the ink share of contrast
    ``c = 1 - grey / level(u, v)``, a ramp from 0 at ``INK_RAMP[0]`` (or ``floor``, pixel noise's reach) to 1 at
    ``INK_RAMP[1]`` of the disc's own contrast (the mean c of its dark pixels): a symmetric blur keeps the ramp's first
    moment; a shadow or glare misread in ``level`` shifts only the edge, not the ink inside nor the paper outside."""
    su, sv = grid[0][support], grid[1][support]  # [px from the crop's centre, ``centre`` in the picture]
    c = 1.0 - crop[support] / level(su, sv)
    ink = c[c > DARK_FRACTION]
    if c.sum() <= 0.25 * area * DARK_FRACTION or not ink.size:
        return "occluded", None
    full = INK_RAMP[1] * (ink.sum() / ink.size)
    start = min(max(INK_RAMP[0] / INK_RAMP[1] * full, floor), full / 2)  # paper's noise gets no weight: it is clipped
    wgt = c * (1.0 / (full - start))
    wgt -= start / (full - start)
    s = np.minimum(np.maximum(wgt, 0.0, out=wgt), 1.0, out=wgt).sum()  # in place: the clip costs more than the sums
    return None, np.array([float(wgt @ su) / s + centre[0], float(wgt @ sv) / s + centre[1]])


def _noise_sigma(a: np.ndarray, on: np.ndarray, step: int) -> float:
    """The pixel noise's sigma in ``a`` over the pixels ``on`` (a mask of ``a[::step, ::step]``): their median absolute
    response to Immerkaer's kernel, blind to planes (noise of sigma s: 6 s rms), which a shadow's or a disc's edge
    moves at a few pixels, not at the median."""
    r = cv2.filter2D(a, cv2.CV_32F, np.float32([[1, -2, 1], [-2, 4, -2], [1, -2, 1]]))[::step, ::step][on]
    return float(np.median(np.abs(r))) * (1.4826 / 6) if r.size else 0.0


def _least_squares(N: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """Least squares from their normal equations ``N x = b`` (cheaper per call than numpy's); None when singular."""
    ok, x = cv2.solve(N, b[:, None], flags=cv2.DECOMP_LU)
    return x[:, 0] if ok else None


def _curved(A, z, r, limit, normal) -> bool:
    """Whether ring paper ``z`` (``A``: rows 1, x, y, x^2, xy, y^2, ``normal`` its normal equations; ``r`` its plane's
    residuals) is off its plane by > ``limit`` rms, or curved."""
    mse = float(r @ r) / len(z)
    if mse > limit**2:
        return True
    q = _least_squares(*normal)
    if q is None:  # a ring too small to tell
        return False
    r = z - q @ A
    return float(r @ r) / len(z) < CURVED_SHARE * mse


def _edge_level(x, y, z, angle, tol: float, marks: bool = False):
    """The paper's level across a disc varying along one direction only (a shadow's edge, a slope): a 1 px-binned
    profile of the ring's grey ``z`` at (``x``, ``y``) [px from the crop's centre] along the best-fitting normal (15 deg
    steps from ``angle``, refined to 1 deg); with ``marks``, fitted again without the ring's pixels off it by more than
    ``tol`` of it (a mark, up to 30 %). Returns level(x, y), or None when the ring is not such paper."""

    def fit(angles):
        """(mse per angle, ``detail(i)``) of all ``angles`` in one ``np.interp``, each angle's bins apart."""
        a = np.asarray(angles, float)
        c, s = np.cos(a), np.sin(a)
        u = np.multiply.outer(c, x)  # in place from here: each temporary costs as much as the arithmetic
        u += np.multiply.outer(s, y)
        t0 = u.min(1)
        u -= t0[:, None]
        b = u.astype(np.intp)  # floor: u >= 0, and every angle's first bin is filled
        nb = int(b.max()) + 1
        rows = np.arange(len(a))[:, None]
        b += nb * rows
        flat = b.ravel()
        cnt = np.bincount(flat, minlength=nb * len(a)).reshape(len(a), nb)
        tot = np.bincount(flat, np.broadcast_to(z, u.shape).ravel(), minlength=nb * len(a)).reshape(len(a), nb)
        have = cnt > 0
        centres = np.arange(nb) + 0.5
        prof = np.divide(tot, cnt, out=np.zeros_like(tot), where=have)
        hi = centres[nb - 1 - np.argmax(have[:, ::-1], axis=1)]
        gap = nb + 2.0
        xp = (centres + gap * rows)[have]
        np.maximum(u, 0.5, out=u)
        np.minimum(u, hi[:, None], out=u)
        u += gap * rows
        lev = np.interp(u.ravel(), xp, prof[have]).reshape(u.shape)
        r = z - lev
        mse = np.einsum("ij,ij->i", r, r) / len(z)

        def detail(i):
            return np.abs(r[i]) > tol * lev[i], c[i], s[i], centres[have[i]] + t0[i], prof[i, have[i]]

        return mse, detail

    coarse = angle + np.radians(np.arange(0, 180, 15))
    mse, detail = fit(coarse)
    i = int(np.argmin(mse))  # the first of equals
    # halving the step about the best (8, 4, 2, 1 deg), two steps to one fit of every offset [deg] they may reach
    off, best, chosen = 0, float(mse[i]), (detail, i)
    for steps in REFINE_STEPS_DEG:
        reach = sorted({off + sum(p) for p in itertools.product(*[(-d, 0, d) for d in steps])} - {off})
        fine, fine_detail = fit(coarse[i] + np.radians(reach))
        got = dict(zip(reach, fine))
        for d in steps:
            j = min((off - d, off + d), key=got.get)
            if got[j] < best:
                off, best, chosen = j, float(got[j]), (fine_detail, reach.index(j))
    off, c, s, at, prof = chosen[0](chosen[1])
    if np.mean(off) > 0.01:
        return _edge_level(x[~off], y[~off], z[~off], np.arctan2(s, c), tol) if marks and np.mean(off) < 0.3 else None
    return lambda u, v: np.interp(u * c + v * s, at, prof)


def _seed(P: np.ndarray, dist: np.ndarray) -> tuple[int, np.ndarray, np.ndarray] | None:
    """A disc near the middle whose neighbours confirm two lattice steps (a, b) both ways."""
    order = np.argsort(np.linalg.norm(P - np.median(P, axis=0), axis=1), kind="stable")
    for s in order:
        nb = np.argsort(dist[s], kind="stable")[1:9]
        a = P[nb[0]] - P[s]
        la = np.linalg.norm(a)
        if not np.any(np.linalg.norm(P[nb] - (P[s] - a), axis=1) < 0.25 * la):
            continue
        for j in nb[1:]:
            b = P[j] - P[s]
            lb = np.linalg.norm(b)
            # a reduced basis (no diagonal): neither a + b nor a - b shorter than the longer step
            if abs(a @ b) > 0.6 * min(la, lb) ** 2 or not 0.5 < lb / la < 2.0:
                continue
            if np.any(np.linalg.norm(P[nb] - (P[s] - b), axis=1) < 0.25 * lb):
                return int(s), a, b
    return None


def _propagate(P: np.ndarray) -> dict[int, tuple[int, int]]:
    """Lattice index (i, j) of points P (N, 2) reachable from a seed, local steps following perspective and lens."""
    dist = np.linalg.norm(P[:, None, :] - P[None, :, :], axis=2)
    seed = _seed(P, dist)
    if seed is None:
        return {}
    s, a, b = seed
    index, at = {s: (0, 0)}, {(0, 0): s}
    steps, queue = {s: (a, b)}, [s]
    while queue:
        p = queue.pop(0)
        i, j = index[p]
        for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            for jump in (1, 2):
                key = (i + di * jump, j + dj * jump)
                if key in at:
                    break
                back = at.get((i - di, j - dj))
                step = P[p] - P[back] if back is not None else _parallel_step(P, at, (i, j), (di, dj))
                if step is None:
                    step = steps[p][0] * di + steps[p][1] * dj
                off = P - (P[p] + jump * step)
                dd = np.einsum("ij,ij->i", off, off)  # squared distances to the prediction
                q = int(np.argmin(dd))
                if dd[q] >= 0.09 * float(step @ step) or q in index:  # 0.3 steps
                    continue
                index[q], at[key] = key, q
                sa, sb = steps[p]
                meas = (P[q] - P[p]) / jump
                steps[q] = (meas * di if di else sa, meas * dj if dj else sb)
                queue.append(q)
                break
    return index


def _parallel_step(P, at, ij, d) -> np.ndarray | None:
    """The step ``d`` (di, dj) at ``ij`` as the neighbouring lines measure it (perspective shrinks steps across lines):
    their mean, or one line's extrapolated by the next's; None when no neighbouring line has it."""
    (i, j), (di, dj) = ij, d
    side = []
    for s in (1, -1):
        got = []
        for n in (1, 2):
            lo, hi = at.get((i + s * n * dj, j + s * n * di)), at.get((i + s * n * dj + di, j + s * n * di + dj))
            if lo is None or hi is None:
                break
            got.append(P[hi] - P[lo])
        if got:
            side.append(got)
    if len(side) == 2:
        return (side[0][0] + side[1][0]) / 2
    if side:
        return 2 * side[0][0] - side[0][1] if len(side[0]) == 2 else side[0][0]
    return None


def _lattice_outliers(P, index) -> set[int]:
    """Points off the midpoint of their two lattice neighbours on a line by > ``LATTICE_TOLERANCE`` steps."""
    at = {v: k for k, v in index.items()}
    k, lo, hi = np.array([(k, at[i - di, j - dj], at[i + di, j + dj]) for k, (i, j) in index.items()
                          for di, dj in ((1, 0), (0, 1)) if (i - di, j - dj) in at and (i + di, j + dj) in at],
                         int).reshape(-1, 3).T  # a point with both neighbours on a line, once per line
    step = np.linalg.norm(P[hi] - P[lo], axis=1) / 2
    return set(k[np.linalg.norm(P[k] - (P[lo] + P[hi]) / 2, axis=1) > LATTICE_TOLERANCE * step].tolist())


def _cell_share(P, index, areas) -> dict[int, float]:
    """Per point with neighbours on both axes: its blob's area over its cell's |a x b|, locally pi/4 (d/pitch)^2."""
    at = {v: k for k, v in index.items()}
    share = {}
    for k, (i, j) in index.items():
        steps = []
        for di, dj in ((1, 0), (0, 1)):
            hi, lo = at.get((i + di, j + dj)), at.get((i - di, j - dj))
            step = P[hi] - P[k] if hi is not None else (P[k] - P[lo] if lo is not None else None)
            steps.append(step)
        if steps[0] is not None and steps[1] is not None:
            share[k] = float(areas[k] / max(abs(steps[0][0] * steps[1][1] - steps[0][1] * steps[1][0]), 1e-9))
    return share


def _off_size(P, index, areas, plate: PlateSpec) -> set[int]:
    """Lattice points whose blob is far off the plate's disc size there (labels, marks); ``ImageError`` if most are."""
    share = _cell_share(P, index, areas)
    if not share:
        return set()
    expect = np.pi / 4 * (plate.disc_diameter / plate.pitch) ** 2
    bad = {k for k, v in share.items() if not DISC_SHARE[0] < v / expect < DISC_SHARE[1]}
    if len(bad) > len(share) / 2:
        raise ImageError(f"the discs cover {np.median(list(share.values())):.2f} of their lattice cell where the "
                         f"plate's {plate.disc_diameter:g} mm discs at {plate.pitch:g} mm pitch would cover "
                         f"{expect:.2f}: check plate.disc_diameter and plate.pitch in the cell file")
    return bad


#: Changes of lattice basis tried for the plate's axes: integer 2 x 2, entries within +-2, determinant +-1.
_BASES = np.array([m for m in itertools.product(range(-2, 3), repeat=4)
                   if abs(m[0] * m[3] - m[1] * m[2]) == 1]).reshape(-1, 2, 2)
#: ``_BASES``' distinct rows, and which each of their rows is: a box's extent per row, not per basis (16, not 208).
_ROWS, _ROW_OF = np.unique(_BASES.reshape(-1, 2), axis=0, return_inverse=True)


def _plate_axes(P, index) -> dict[int, tuple[int, int]]:
    """``index`` in the lattice's own axes: the basis giving the smallest box (a seed on a foreshortened diagonal
    indexes a sheared lattice: 10 x 8 as 17 x 10); of ties, the first whose image steps are nearest a right angle."""
    ids = list(index)
    keys = np.array([index[k] for k in ids])
    along = _ROWS @ keys.T  # (rows, N)
    ext = (along.max(1) - along.min(1) + 1)[_ROW_OF].reshape(-1, 2)  # (bases, 2)
    area = ext[:, 0] * ext[:, 1]
    own = (keys.max(0) - keys.min(0) + 1).prod()
    if area.min() == own:
        return index
    best, best_cos = None, None
    for m in np.flatnonzero(area == area.min()):
        trial = dict(zip(ids, map(tuple, (keys @ _BASES[m].T).tolist())))
        a, b = _mean_step(P, trial, 0), _mean_step(P, trial, 1)
        cos = abs(a @ b) / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12)
        if best_cos is None or cos < best_cos - 1e-9:
            best, best_cos = trial, cos
    return best


def _plate_window(index, plate: PlateSpec) -> dict[int, tuple[int, int]]:
    """``index`` cut to the plate-sized window holding the most points if larger (blobs beyond the sheet); tie: all."""
    keys = np.array(list(index.values()))
    lo, ext = keys.min(0), keys.max(0) - keys.min(0) + 1
    shapes = {(plate.cols, plate.rows), (plate.rows, plate.cols)}
    if any(ext[0] <= a and ext[1] <= b for a, b in shapes):
        return index
    counts = {}
    for a, b in shapes:
        for i0 in range(lo[0], max(lo[0], lo[0] + ext[0] - a) + 1):
            for j0 in range(lo[1], max(lo[1], lo[1] + ext[1] - b) + 1):
                inside = frozenset(k for k, (i, j) in index.items() if i0 <= i < i0 + a and j0 <= j < j0 + b)
                counts[inside] = len(inside)
    ranked = sorted(counts.values(), reverse=True)
    if len(ranked) > 1 and ranked[0] == ranked[1]:
        return index  # no one window is the plate: refused when oriented
    best = max(counts, key=counts.get)
    return {k: index[k] for k in best}


def _mean_step(P, index, axis: int) -> np.ndarray:
    """The mean image step (2,) from a lattice point to the next along index ``axis``; zero when none has one."""
    at = {v: k for k, v in index.items()}
    di, dj = (1, 0) if axis == 0 else (0, 1)
    steps = [P[at[(i + di, j + dj)]] - P[k] for k, (i, j) in index.items() if (i + di, j + dj) in at]
    return np.mean(steps, axis=0) if steps else np.zeros(2)


def _orient(P, index, plate: PlateSpec) -> np.ndarray:
    """(N, 2) (col, row) lattice coordinates as W: x to growing u, z away from the camera, extents fitting the plate."""
    keys = np.array([index[k] for k in sorted(index)])
    A, B = _mean_step(P, index, 0), _mean_step(P, index, 1)
    choices = [(0, A, 1, B), (1, B, 0, A)]
    if abs(B[0]) / (np.linalg.norm(B) + 1e-9) > abs(A[0]) / (np.linalg.norm(A) + 1e-9):
        choices.reverse()
    for ci, cvec, ri, rvec in choices:
        csign = 1 if cvec[0] >= 0 else -1
        rsign = 1 if csign * (cvec[0] * rvec[1] - cvec[1] * rvec[0]) > 0 else -1
        cr = np.column_stack([keys[:, ci] * csign, keys[:, ri] * rsign])
        ext = cr.max(0) - cr.min(0) + 1
        if ext[0] <= plate.cols and ext[1] <= plate.rows:
            return cr - cr.min(0)
    raise ImageError(f"the discs form a lattice of {ext[0]} x {ext[1]}, larger than the plate's {plate.cols} x "
                     f"{plate.rows}")


def _check_square(xy: np.ndarray, cr: np.ndarray) -> None:
    """``ImageError`` unless indices ``cr`` (N, 2) (col, row) and rays ``xy`` (N, 2) (undistorted, over f) form a square
    grid: the homography's axes square and equal within ``SQUARE_TOLERANCE`` (indexed along a diagonal: 45 deg)."""
    Hm, _ = cv2.findHomography(cr.astype(np.float64), xy.astype(np.float64))
    if Hm is None:
        return
    a, b = Hm[:, 0], Hm[:, 1]
    cos = abs(a @ b) / (np.linalg.norm(a) * np.linalg.norm(b))
    ratio = np.linalg.norm(a) / np.linalg.norm(b)
    if cos > SQUARE_TOLERANCE or not 1 - SQUARE_TOLERANCE < ratio < 1 / (1 - SQUARE_TOLERANCE):
        raise ImageError(f"the discs' lattice is no square grid as the camera sees it (its axes "
                         f"{np.degrees(np.arccos(cos)):.0f} deg apart, their lengths {ratio:.2f} to 1): the plate is "
                         "seen too obliquely to index it (or the camera guess is far off)")


def _grid_end(P_img, cr, axis, side, dark, r_px) -> str | None:
    """What lies one step beyond the last column/row (``axis`` 0/1, ``side`` -1 low, +1 high): 'disc' (a dark spot
    ringed by paper), 'blank' (blank paper at two or more places, nothing dark), else None (out of the picture, a
    finger, a shadow). A place the border cuts counts when a third of a disc is in the picture."""
    at = {tuple(k): n for n, k in enumerate(cr)}
    edge = cr[:, axis].min() if side < 0 else cr[:, axis].max()
    H, W = dark.shape
    rr = int(np.ceil(1.5 * r_px))
    empty, covered = 0, False
    for n in np.nonzero(cr[:, axis] == edge)[0]:
        q = at.get(tuple(cr[n] - side * (np.arange(2) == axis)))  # its neighbour inside
        if q is None:
            continue
        pred = 2 * P_img[n] - P_img[q]
        u, v = int(round(pred[0])), int(round(pred[1]))
        u0, u1, v0, v1 = max(u - rr, 0), min(u + rr + 1, W), max(v - rr, 0), min(v + rr + 1, H)
        if u1 - u0 < 5 or v1 - v0 < 5:
            continue
        vv, uu = np.mgrid[v0:v1, u0:u1]
        d2 = (uu - u) ** 2 + (vv - v) ** 2
        if np.count_nonzero(d2 <= r_px**2) < np.pi * r_px**2 / 3:
            continue
        patch = cv2.blur(dark[v0:v1, u0:u1], (5, 5))  # 5x5 means: noise-proof
        if np.max(patch) <= DARK_FRACTION / 2:
            empty += 1
            continue
        ring = patch[d2 >= (1.3 * r_px) ** 2]
        if ring.size and np.median(ring) <= DARK_FRACTION / 2:
            return "disc"
        covered = True
    return "blank" if empty >= 2 and not covered else None


def _typical_area(area: np.ndarray) -> float:
    """The plate's disc area [px]: the median of the factor-4 band of blob areas holding the most ink (not marks)."""
    la = np.log(np.asarray(area, float))
    band = (la[None, :] >= la[:, None] - np.log(2)) & (la[None, :] <= la[:, None] + np.log(2))  # row: one band
    ink = band @ np.asarray(area)
    c = la[int(np.argmax(ink))]
    inside = (la >= c - np.log(2)) & (la <= c + np.log(2))
    return float(np.exp(np.median(la[inside])))


def detect_discs(image, plate: PlateSpec, *, camera: CameraModel | None = None, min_discs: int = 12) -> DiscDetections:
    """Find, measure and index the whole discs of the calibration plate in ``image`` ((H, W) grey or BGR); ``camera``
    (optional) checks its size and straightens the lattice (kappa) for indexing. Returns ``DiscDetections`` (distorted
    pixels, not yet bias-corrected: ``correct_disc_bias``). Raises ``ImageError`` for a blank picture, one of the wrong
    size, with fewer than ``min_discs`` whole discs or whose discs form no lattice. Faint discs are measured again with
    a grey pedestal off (``FAINT``; ``DiscDetections.pedestal``): glare's, a defocus's. An origin nothing pins
    (``DiscDetections.ambiguous``) does not change the hand/eye result: it cancels in ``C_H_G = C_H_W W_H_G``."""
    img = as_gray(image, camera)
    work = img if plate.polarity == "dark_on_light" else (float(img.max()) - img)
    try:
        det, contrast = _detect(work, plate, camera, min_discs)
    except ImageError as e:
        det, contrast, error = None, 0.0, e
    if contrast < FAINT:  # glare or haze adds a grey level to ink and paper alike: off, the ink has the print's contrast
        level = _paper_level(work)
        lit = level >= 0.5 * float(level.max())  # the plate's paper, not a dark bench beside it
        paper = float(np.median(level[lit]))
        ink = (float(np.percentile(work[lit], 1)) - (1 - INK_CONTRAST) * paper) / INK_CONTRAST
        for pedestal in (ink, DEFOCUS_PEDESTAL * paper):  # the one that finds most discs, until one finds all
            if pedestal > 0.05 * paper and (det is None or len(det) < plate.rows * plate.cols):
                with contextlib.suppress(ImageError):
                    again = _detect(work - pedestal, plate, camera, min_discs)[0]
                    if det is None or len(again) > len(det):
                        det, again.pedestal = again, pedestal
    if det is None:
        raise error
    return det


def _detect(work, plate: PlateSpec, camera: CameraModel | None, min_discs: int) -> tuple[DiscDetections, float]:
    """``detect_discs``'s one pass on ``work`` (H, W) float32, dark on light: (detections, the median contrast at
    their centres)."""
    paper = _paper_level(work)
    dark = cv2.divide(work, cv2.max(paper, 1.0))  # compiled: a third of numpy's time
    np.subtract(1.0, dark, out=dark)
    # the blobs' outlines from a smoothed contrast, so pixel noise neither frays them nor joins specks to them
    lit = paper[::3, ::3]
    on = (lit >= 0.5 * float(lit.max())) & (np.abs(dark[::3, ::3]) < DARK_FRACTION / 2)  # the plate's bare paper
    noise = _noise_sigma(work, on, 3)  # [grey levels]
    rel = noise / float(np.median(lit[on])) if on.any() else 0.0
    blur = max(OUTLINE_BLUR_PX, rel / (2 * math.sqrt(math.pi) * OUTLINE_NOISE))  # a Gaussian's gain on white noise
    smooth = cv2.GaussianBlur(dark, (0, 0), blur)
    mask = cv2.compare(smooth, DARK_FRACTION, cv2.CMP_GT)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    rejected: dict[str, int] = {}

    def reject(reason: str, count: int = 1) -> None:
        if count:
            rejected[reason] = rejected.get(reason, 0) + count

    round_, stats = _round_blobs(labels, stats, reject, smooth)
    uv, areas = _measure_discs(work, labels, stats, round_, reject, noise)
    if len(uv) < min_discs:
        why = ", ".join(f"{v} {k}" for k, v in sorted(rejected.items())) or "none"
        raise ImageError(f"no calibration plate in the picture: {len(uv)} whole disc(s) found, at least {min_discs} "
                         f"needed ({n - 1} dark blobs; rejected: {why})")
    uv, areas = np.array(uv), np.array(areas)
    P = camera.undistorted_pixels(uv) if camera is not None else uv
    index = _propagate(P)
    for k in _lattice_outliers(P, index):
        del index[k]
    if index:
        index = _plate_axes(P, index)
    if len(index) >= min_discs:
        for k in _off_size(P, index, areas, plate):
            del index[k]
        index = _plate_window(index, plate)
    if len(index) < min_discs:
        raise ImageError(f"the discs do not form a lattice: {len(index)} of {len(uv)} whole discs fit one "
                         f"(at least {min_discs} needed)")
    reject("off lattice", len(uv) - len(index))
    ids = np.array(sorted(index))
    cr = _orient(P[ids], {n_: index[k] for n_, k in enumerate(ids)}, plate)
    if camera is not None:
        _check_square(camera.undistort_pixels(uv[ids]) / camera.f, cr)
    basis, ambiguous = _anchor(cr, uv[ids], plate, dark, float(np.sqrt(np.median(areas) / np.pi)))
    order = np.lexsort((cr[:, 0], cr[:, 1]))
    rc, ids = cr[order, ::-1].astype(int), ids[order]
    p_W = plate.disc_centres_W()[rc[:, 0] * plate.cols + rc[:, 1]]
    at = np.clip(np.rint(uv[ids]).astype(int), 0, np.array(dark.shape[::-1]) - 1)
    return (DiscDetections(uv=uv[ids], rc=rc, p_W=p_W, area_px=areas[ids].astype(float), n_blobs=n - 1,
                           rejected=rejected, index_basis=basis, ambiguous=ambiguous),
            float(np.median(dark[at[:, 1], at[:, 0]])))


def _anchor(cr, uv, plate: PlateSpec, dark, r_px: float) -> tuple[dict, dict]:
    """Shift the (col, row) indices ``cr`` (in place) onto the plate's grid; returns (basis per axis, per unpinned axis
    the indices it may take). An axis is pinned when all its lines are seen, or by blank paper a pitch beyond one end
    with the grid going on beyond the other ('low/high end seen'); with the other end out of the picture it is only
    'assumed' (the blank line's discs may be missing); blank at both ends or neither leaves it 'centred'."""
    basis, ambiguous = {}, {}
    for axis, name, count in ((0, "cols", plate.cols), (1, "rows", plate.rows)):
        ext = cr[:, axis].max() + 1
        if ext == count:
            basis[name] = "all seen"
            continue
        low, high = (_grid_end(uv, cr, axis, side, dark, r_px) for side in (-1, +1))
        word = "columns" if name == "cols" else "rows"
        if (low == "blank") != (high == "blank"):  # the grid ends at the blank side
            end, seen = ("low" if low == "blank" else "high"), "disc" in (low, high)
            basis[name] = f"{end} end {'seen' if seen else 'assumed'}"
            shift = 0 if low == "blank" else count - ext
            why = None if seen else (f"blank paper one pitch beyond the outer {word} on the {end} side only, while "
                                     "the next line on the other side lies beyond the picture: the grid may end at the "
                                     "blank paper or run out of the picture with that line's discs missing (erased by "
                                     "glare, hidden)")
        else:
            basis[name] = "centred"
            shift = (count - ext) // 2
            why = (f"blank paper one pitch beyond the outer {word} on both sides, so a line of discs is missing "
                   "from the picture (erased by glare, hidden or not found)" if low == high == "blank" else
                   f"no end of the grid (one pitch beyond the outer {word} on either side lies outside the picture "
                   "or is not blank paper)")
        cr[:, axis] += shift
        if why:
            ambiguous[name] = (f"{ext} of the plate's {count} {word} seen and {why}: they may be {word} "
                               f"{_span(0, ext)} up to {_span(count - ext, ext)}, taken as {_span(shift, ext)}")
    return basis, ambiguous


def _span(first: int, n: int) -> str:
    return f"{first}-{first + n - 1}"


def disc_image_bias(camera: CameraModel, C_H_W, p_W, radius_mm: float, n_boundary: int = 64) -> np.ndarray:
    """(N, 2) [px] centroid of each disc's distorted image minus the image of its centre ``p_W`` (N, 3) [mm], radius
    ``radius_mm``, pose ``C_H_W`` (4, 4): the shoelace centroid of ``n_boundary`` projected boundary points on a
    polygon of the disc's area (at 64: 4e-5 px from 4096 points' value, a quarter of 256 inscribed points' time).
    ``CalibrationError`` (the camera model's) for discs behind the camera."""
    p_W = np.atleast_2d(np.asarray(p_W, float))
    t = np.arange(n_boundary) * (2 * np.pi / n_boundary)
    ring = np.column_stack([np.cos(t), np.sin(t), np.zeros_like(t)]) * (radius_mm * math.sqrt(t[1] / math.sin(t[1])))
    pts = (p_W[:, None, :] + ring[None, :, :]).reshape(-1, 3)
    poly = camera.project(transform_points(C_H_W, pts)).reshape(len(p_W), n_boundary, 2)
    x, y = poly[..., 0], poly[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * y1 - x1 * y
    a = cross.sum(1) / 2
    cx, cy = ((x + x1) * cross).sum(1) / (6 * a), ((y + y1) * cross).sum(1) / (6 * a)
    return np.column_stack([cx, cy]) - camera.project(transform_points(C_H_W, p_W))


def correct_disc_bias(det: DiscDetections, camera: CameraModel, C_H_W, plate: PlateSpec) -> np.ndarray:
    """(N, 2) [px, distorted] ``det.uv`` minus ``disc_image_bias`` for a pose ``C_H_W`` (4, 4) and ``camera``."""
    if len(det.uv) == 0:
        return det.uv.copy()
    return det.uv - disc_image_bias(camera, C_H_W, det.p_W, plate.disc_diameter / 2)
