"""Following the fingertip corners from frame to frame (the on-line per-frame step).

``find_fingertips`` searches a picture from a predicted mount: a coarse template search, then two
passes of sub-pixel profiles per edge, some 100 ms. A wrist camera moves little between two frames
(40 ms apart), and what the search learnt about each edge still holds in the next frame: where its
line lies, where along it the edge showed (not where ink or another edge lay beside it), which way its
profiles run, the grey level of the finger's face beside it (and of the other face at a crease), its
blur and the slopes of its plateaus, whether the background is textured. ``FingertipTracker`` keeps
that and measures each new frame over all the tracked edges at once, in the same arrays:

1. where each edge lies now: on every fourth profile, reaching ``track_px`` either side of the last
   line, the strongest step that shows the face's grey level on its side; per edge, the median of
   their offsets;
2. every profile again within +-3 px of there, its step located exactly as the search's second pass
   locates it (``selfview.fingertips``: the area method with the edge's own transition width and
   plateau slopes, or the peak of the rise over a textured background; the same acceptance tests);
3. a robust line per edge (Tukey reweighting about the last line), and each corner the weighted
   intersection of its lines, as the search computes it.

A tracked frame is checked before it is believed: every edge must find again at least
``KEEP_FRACTION`` of the points the search found on it, turn less than ``MAX_TURN_DEG`` and stay
inside the profiles' reach; its points must come up to the corner (or the faces beside it must show
their grey level up to it, as over ink), their scatter about the lines stay below
``MAX_EDGE_RMS_PX``, and the corner stay in the picture. When a check fails (a jump of the camera
beyond ``track_px``, something covering a corner, a change of light beyond the levels' tolerance, a
new jaw gap) the frame goes to the full search from the caller's prediction, which also gives the
reasons for points it does not find, and the tracker starts again from its result. Profiles are
sampled by bilinear interpolation (single precision), as exact as the search's.

The numpy code here is the reference. When the C extension ``selfview._ctrack`` is built (see
``selfview._native``), steps 2-3 and the line fits run in it instead (``_passes_native``,
``_ctrack.lines``, ``_ctrack.line_stats``): the same operations in the same order and precision, the
same results bit for bit (``tests/selfview/test_native_track.py`` compares the two on every kind of
sequence). ``selfview._native.track`` is read at each frame; None runs the Python code.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from selfview import _native
from selfview.camera import CameraModel
from selfview.cell import POINT_NAMES, GripperSpec
from selfview.discs import as_gray
from selfview.errors import CalibrationError
from selfview.fingertips import (
    MAX_EDGE_RMS_PX,
    MIN_CONTRAST,
    PLATEAU_PX,
    _CTRACK_API,  # the interface of selfview._ctrack this module calls (its API), one for both modules
    FingertipResult,
    _faces_reach_corner,
    _Fit,
    _search,
    _step_estimates,
    checked_prediction,
)

__all__ = ["FingertipTracker", "SilhouetteTracker"]

MAX_TURN_DEG = 5.0  # an edge that turns more between two frames is searched for again
KEEP_FRACTION = 0.35  # of the points the search found on an edge, that a tracked frame must find again
CORNER_GAP_PX = 10.0  # edge points must come this close to the corner (beyond the first profile's)


class _Groups:
    """Groups ``gid`` (K,) in 0..n-1 of values that come in the order of their groups (sorted gid), for
    per-group medians at a few numpy calls each (the sort of all values at once)."""

    def __init__(self, gid: np.ndarray, n: int):
        self.gid = gid
        counts = np.bincount(gid, minlength=n)
        starts = np.cumsum(counts) - counts
        last = max(len(gid) - 1, 0)
        self.lo = np.minimum(starts + (counts - 1) // 2, last)
        self.hi = np.minimum(starts + counts // 2, last)
        self.empty = counts == 0
        self.base = np.arange(n, dtype=float)

    def median(self, values: np.ndarray) -> np.ndarray:
        """(n,) the median of ``values`` (K,) in each group, NaN for an empty one. (In C: ``trick_median``
        in ``_ctrack.c``, the same shifted values, so the same result to the bit.)"""
        if len(values) == 0:
            return np.full(len(self.base), np.nan)
        span = float(values.max() - values.min()) + 1.0  # groups' keys lie apart by more than any spread
        v = np.sort(values + self.gid * span)  # sorted within each group, the groups in their order
        med = 0.5 * (v[self.lo] + v[self.hi]) - self.base * span
        med[self.empty] = np.nan
        return med


def _group_median(values: np.ndarray, gid: np.ndarray, n: int) -> np.ndarray:
    """Median of ``values`` (K,) within each group ``gid`` (K,, sorted) in 0..n-1: (n,), NaN for an
    empty group."""
    return _Groups(gid, n).median(values)


class FingertipTracker:
    """The fingertip corners ``points`` (indices into ``POINT_NAMES``) of a sequence of pictures.

    ``camera`` the calibrated camera (it undistorts the edge points, as in ``find_fingertips``),
    ``gripper`` the cell's gripper, ``search_px`` the full search's range around its prediction,
    ``track_px`` how far [px] a tracked edge may move between two frames.

    ``find(image, C_H_G_pred, gap_mm)`` returns a ``FingertipResult`` like ``find_fingertips``: tracked
    from the previous frame when it can be (``result.tracked``), else searched from the prediction.
    The points the last search found are tracked; a wanted point it did not find is reported with its
    reason, and searched for again after ``refresh_frames`` tracked frames. ``searches`` and
    ``tracked_frames`` count the two kinds of frame, ``last_failure`` says why the last frame was
    searched for (None: not primed, or tracked). ``reset()`` forgets the last frame.
    """

    def __init__(
        self,
        camera: CameraModel,
        gripper: GripperSpec,
        *,
        points=range(4),
        search_px: float = 60.0,
        track_px: float = 12.0,
        refresh_frames: int = 25,
    ):
        if not isinstance(camera, CameraModel):
            raise TypeError(f"camera: expected a selfview.camera.CameraModel, got {type(camera).__name__}")
        want = sorted({int(k) for k in points})
        if not want or any(k < 0 or k > 5 for k in want):
            raise ValueError(f"points: expected indices 0..5 into POINT_NAMES, got {list(points)}")
        if not (track_px >= 4 and math.isfinite(track_px)):
            raise ValueError(f"track_px: expected a number of pixels of at least 4, got {track_px!r}")
        if int(refresh_frames) < 1:
            raise ValueError(f"refresh_frames: expected a positive number of frames, got {refresh_frames!r}")
        self.camera = camera
        self.gripper = gripper
        self.points = tuple(want)
        self.search_px = float(search_px)
        self.track_px = float(track_px)
        self.refresh_frames = int(refresh_frames)
        self.searches = 0
        self.tracked_frames = 0
        self.last_failure: str | None = None  # why the last frame was not tracked
        self.reset()

    # --- state ---------------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the last frame: the next one is searched for."""
        self._state = None

    @property
    def primed(self) -> bool:
        """Whether the next frame will be tracked (if its checks pass)."""
        return self._state is not None

    def _prime(self, result: FingertipResult, model, fits: dict, corner_keys: dict, gap_mm: float, img_shape) -> None:
        """Take over the edges of a full search at the points it found (none found: not primed)."""
        self._state = None
        tracked = [k for k in self.points if result.found[k]]
        if not tracked:
            return
        cam = self.camera
        keys = []
        for k in tracked:
            for key in corner_keys[k]:
                if key not in keys:
                    keys.append(key)
        E = len(keys)
        idx = {key: i for i, key in enumerate(keys)}
        anchor = [next(k for k in tracked if key in corner_keys[k]) for key in keys]
        q_corner = {k: cam.undistorted_pixels(result.uv[k][None, :])[0] for k in tracked}
        n = np.array([fits[key].n for key in keys])
        c = np.array([fits[key].c for key in keys])
        s_list, eid, n_ref = [], [], []
        for i, key in enumerate(keys):
            fit = fits[key]
            t = np.array([-n[i, 1], n[i, 0]])
            # profiles where the search found this edge (its inliers): not where it found ink, another
            # edge or nothing, which a longer profile might mistake for this edge
            s = (fit.q - q_corner[anchor[i]]) @ t
            if np.mean(s) < 0:  # the tangent points away from the anchor corner
                n[i], c[i] = -n[i], -c[i]
                s = -s
            s_list.append(np.sort(s))
            eid.append(np.full(len(s), i, dtype=np.int64))
            n_ref.append(len(fit.q))
        levels = np.array([fits[key].levels for key in keys], float)
        pdir = np.array([fits[key].pdir for key in keys], float)
        sh = [fits[key].shading for key in keys]
        cos = np.maximum(np.abs(np.sum(n * pdir, axis=1)), 0.5)  # the search samples no more obliquely
        # each edge's transition half-width along its profiles, from the blur the search measured
        sigma = np.array([x.sigma if x.sigma is not None else 1.6 / cc for x, cc in zip(sh, cos)])
        h = np.clip(np.ceil(3 * sigma + 1), 2, 12).astype(np.int64)
        sr1 = np.ceil(self.track_px / cos)
        s_all = np.concatenate(s_list)
        eid_all = np.concatenate(eid)
        # profile phases dithered along each edge, as the search does (golden-ratio sequence)
        phase = np.concatenate([(np.arange(len(s)) * 0.6180339887) % 1.0 - 0.5 for s in s_list])
        self._state = {
            "gap": float(gap_mm),
            "shape": img_shape,
            "keys": keys,
            "anchor": np.array(anchor),
            "n": n,
            "c": c,
            "s": s_all,
            "eid": eid_all,
            "phase": phase,
            "pdir": pdir,
            "pd": pdir[eid_all],  # each profile's direction (fixed while tracked)
            "levels": levels,
            "crease": np.array([model.edges[key].crease for key in keys]),
            "reach": np.array([fits[key].reach for key in keys], float),
            "textured": np.array([bool(fits[key].textured) for key in keys]),
            "g": np.array([(x.g_lo, x.g_hi) for x in sh], float),
            "h": h,
            "hmax": int(h.max()),
            "R": int(sr1.max()) + int(h.max()) + PLATEAU_PX + 1,
            "sr1": sr1[eid_all],
            "sr2": int(np.ceil(3.0 / cos).max()),
            "R2": int(np.ceil(3.0 / cos).max()) + int(h.max()) + PLATEAU_PX + 1,
            "sub": np.arange(0, len(eid_all), 4, dtype=np.int64),
            "n_ref": np.array(n_ref),
            "need": np.maximum(6, KEEP_FRACTION * np.array(n_ref)),  # of them, to be found again
            "bounds": np.searchsorted(eid_all, np.arange(E + 1)),
            "points": tracked,
            # the wanted points the search did not find, with its reasons, and the frames since
            "missing": {k: result.reasons[k] for k in self.points if not result.found[k]},
            "age": 0,
            "corner_lines": {k: [idx[key] for key in corner_keys[k]] for k in tracked},
            "pairs": _pair_rounds([(k, idx[key]) for k in tracked for key in corner_keys[k]]),
            "q_corner": q_corner,
            "uv": {k: result.uv[k].copy() for k in tracked},
        }
        q_st = _stations(self._state, q_corner, n)
        try:
            self._state["q_st"], self._state["pts"] = q_st, cam.distort_to_pixels(cam.pixel_to_sensor(q_st))
        except CalibrationError:  # an edge reaching beyond the lens's fold: search every frame
            self._state = None

    # --- the frame -----------------------------------------------------------------------------
    def find(self, image, C_H_G_pred, gap_mm: float) -> FingertipResult:
        """The corners in this frame: tracked from the last one, or searched from ``C_H_G_pred``
        (4, 4) with jaw gap ``gap_mm`` [mm] when there is none or the tracking does not hold.

        Raises ``ImageError`` for a picture that is not one, blank or of the wrong size (from the
        search), ``CalibrationError`` and ``ValueError`` as ``find_fingertips`` does (a bad prediction
        or jaw gap is refused before anything is tracked)."""
        C_H_G_pred, gap_mm = checked_prediction(C_H_G_pred, gap_mm)
        st = self._state
        why = None
        if st is not None:
            if abs(gap_mm - st["gap"]) > 1e-6:
                why = f"the jaw gap changed ({st['gap']:.2f} -> {float(gap_mm):.2f} mm)"
            elif st["missing"] and st["age"] >= self.refresh_frames:
                why = f"searching again for {', '.join(POINT_NAMES[k] for k in st['missing'])}"
            else:
                img = self._grey(image)
                if img.shape != st["shape"]:
                    why = f"the picture's size changed to {img.shape[1]}x{img.shape[0]}"
                else:
                    out = self._track(img)
                    if isinstance(out, FingertipResult):
                        self.tracked_frames += 1
                        self.last_failure = None
                        return out
                    why = out
        self.last_failure = why
        result, model, fits, corner_keys = _search(
            image, self.camera, C_H_G_pred, self.gripper, gap_mm, self.search_px, self.points
        )
        self.searches += 1
        shape = (int(self.camera.height), int(self.camera.width))
        self._prime(result, model, fits, corner_keys, gap_mm, shape)
        return result

    def _grey(self, image) -> np.ndarray:
        """A 2-D grey picture: a grey uint8 or float one as it is (no copy: the per-frame budget), a
        colour one converted; the full checks (size, blank) are the search's."""
        a = np.asarray(image)
        if a.ndim == 2 and (a.dtype == np.uint8 or a.dtype == np.float32 or a.dtype == np.float64):
            return np.ascontiguousarray(a)
        return as_gray(a, self.camera)

    def _track(self, img: np.ndarray):
        """The tracked result, or why the frame cannot be tracked (a string)."""
        st = self._state
        cam = self.camera
        H, W = img.shape
        E = len(st["keys"])
        n0, c0, eid = st["n"], st["c"], st["eid"]
        q_st = st["q_st"]
        # the compiled kernels (selfview._ctrack) when built, else the Python reference; both compute
        # the same, bit for bit (tests/selfview/test_native_track.py)
        nat = _native.track
        if nat is not None and getattr(nat, "API", None) != _CTRACK_API:  # a stale build
            nat = None
        # 1.-3. the edges' crossings in this frame (the stations are placed at the end of the last
        # frame: on each edge's line, at the same distances from its anchor corner as where the search
        # found the edge)
        second = _passes(st, img) if nat is None else _passes_native(nat, st, img)
        if isinstance(second, str):
            return second
        if np.any(np.bincount(second.eid, minlength=E) < 6):
            return "an edge shows fewer than 6 steps near where it was found"
        q2 = cam.undistorted_pixels(second.cross)
        if nat is None:
            n2, c2, w2 = _robust_lines(q2, second.eid, E, n0, c0)
            n_in, levels, ei, s_in, s_mean, s_ss, r_ss = _line_stats(q2, second, w2, n2, c2, E)
        else:
            n2, c2, w2 = np.empty((E, 2)), np.empty(E), np.empty(len(q2))
            nat.lines(q2, second.eid, n0, c0, n2, c2, w2)
            n_in, levels = np.empty(E, np.int64), np.empty((E, 2))
            s_mean, s_ss, r_ss = np.empty(E), np.empty(E), np.empty(E)
            s_in, ei = np.empty(len(q2)), np.empty(len(q2), np.int64)
            k_in = nat.line_stats(
                q2, second.eid, w2, n2, c2, second.Am, second.Bm, n_in, levels, s_mean, s_ss, r_ss, s_in, ei
            )
            s_in, ei = s_in[:k_in], ei[:k_in]
        anchor_q = np.array([st["q_corner"][k] for k in st["anchor"]])
        why = self._edge_checks(n_in, n0, n2, c2, anchor_q)
        if why:
            return why
        # 4. the corners: the search's weighted intersection of their lines
        t2 = np.column_stack([-n2[:, 1], n2[:, 0]])
        cnt = np.maximum(n_in, 1)
        corners = {}
        for kpt in st["points"]:
            qc = _intersect(n2, c2, t2, st["corner_lines"][kpt], s_mean, s_ss, r_ss, cnt)
            if qc is None:
                return f"the edges of {POINT_NAMES[kpt]} became nearly parallel"
            corners[kpt] = qc
        # the edge points must come up to each corner, as near as the profiles start, or the faces
        # beside the edge must show their level up to it (ink behind the edge), as in the search: per
        # (corner, edge) pair, the gap along the edge's line between the corner and its nearest point
        pairs = st["pairs"]  # (corner, edge) for each edge at each corner, in rounds of distinct edges
        b_in = np.searchsorted(ei, np.arange(E + 1))[:-1]
        s_st = np.sum(q_st * t2[eid], axis=1)
        for rnd in pairs:
            sc = np.zeros(E)
            for kpt, li in rnd:
                sc[li] = t2[li] @ corners[kpt]
            near_in = np.minimum.reduceat(np.abs(s_in - sc[ei]), b_in)
            near_st = np.minimum.reduceat(np.abs(s_st - sc[eid]), st["bounds"][:-1])
            for kpt, li in rnd:
                gap = float(near_in[li] - near_st[li])
                if gap > CORNER_GAP_PX:
                    a, b = np.searchsorted(ei, [li, li + 1])
                    qi = q2[w2 > 0]
                    fit = _Fit(n2[li], c2[li], qi[a:b], None, None, st["pdir"][li], levels[li], st["reach"][li])
                    if not _faces_reach_corner(img, cam, fit, bool(st["crease"][li]), corners[kpt], gap):
                        return f"no edge points within {gap:.0f} px of {POINT_NAMES[kpt]}"
        # the corners and the next frame's stations, distorted in one call
        q_next = _stations(st, corners, n2)
        try:
            both = cam.distort_to_pixels(cam.pixel_to_sensor(np.vstack([[corners[k] for k in st["points"]], q_next])))
        except CalibrationError as exc:  # beyond the lens's fold
            return f"the corners left the lens's field ({exc})"
        uv_c, pts_next = both[: len(corners)], both[len(corners) :]
        uv = np.full((6, 2), np.nan)
        found = np.zeros(6, bool)
        rms = np.full(6, np.nan)
        npts = np.zeros(6, int)
        n_in_l, r_ss_l = n_in.tolist(), r_ss.tolist()
        for kpt, p in zip(st["points"], uv_c.tolist()):
            if not (1.0 <= p[0] <= W - 2.0 and 1.0 <= p[1] <= H - 2.0):
                return f"{POINT_NAMES[kpt]} left the picture"
            if math.hypot(p[0] - st["uv"][kpt][0], p[1] - st["uv"][kpt][1]) > self.track_px:
                return f"{POINT_NAMES[kpt]} moved beyond {self.track_px:.0f} px"
            lines = st["corner_lines"][kpt]
            uv[kpt] = p
            found[kpt] = True
            ss = 0.0  # summed in order, as np.sum sums a few values
            for li in lines:
                ss += r_ss_l[li]
            npts[kpt] = sum(n_in_l[li] for li in lines)
            rms[kpt] = math.sqrt(ss / npts[kpt])
            if rms[kpt] > MAX_EDGE_RMS_PX:
                return f"the edge points of {POINT_NAMES[kpt]} scatter by {rms[kpt]:.2f} px about its lines"
        # 5. what the next frame starts from
        st["n"], st["c"], st["levels"] = n2, c2, levels
        st["q_corner"] = corners
        st["uv"] = {kpt: uv[kpt].copy() for kpt in st["points"]}
        st["age"] += 1
        st["q_st"], st["pts"] = q_next, pts_next
        reasons = [None if found[k] else "not requested" for k in range(6)]
        for k, why in st["missing"].items():
            reasons[k] = f"not found at the last search, {st['age']} frame(s) ago: {why}"
        return FingertipResult(
            uv=uv, found=found, reasons=reasons, edge_rms_px=rms, names=POINT_NAMES, n_edge_points=npts, tracked=True
        )

    def _edge_checks(self, n_in, n_old, n_new, c_new, anchor_q) -> str | None:
        """Why the edges found in this frame are not to be believed, or None."""
        st = self._state
        bad = np.flatnonzero(n_in < st["need"])
        if len(bad):
            i = int(bad[0])
            return f"edge {st['keys'][i]} kept {n_in[i]} of its {st['n_ref'][i]} points"
        turn = np.abs(n_new[:, 0] * n_old[:, 1] - n_new[:, 1] * n_old[:, 0])
        if np.any(turn > math.sin(math.radians(MAX_TURN_DEG))):
            return f"an edge turned by more than {MAX_TURN_DEG:g} degrees"
        shift = np.abs(np.sum(n_new * anchor_q, axis=1) - c_new)
        if np.any(shift > self.track_px - 3.0):
            return f"an edge moved {float(shift.max()):.1f} px, beyond the profiles' reach"
        return None


def _passes(st: dict, img: np.ndarray):
    """Steps 1-3 of ``_track`` (the reference): the accepted crossings of the second pass
    (``_StepsFound``), or why the frame cannot be tracked (a string)."""
    H, W = img.shape
    E = len(st["keys"])
    eid = st["eid"]
    pts = st["pts"]
    pd = st["pd"]
    M = len(pts)
    R = st["R"]
    # profiles that would reach beyond the picture are sampled inside it and not used
    edge_lim = np.array([W - 1.0, H - 1.0])
    inside = np.all((pts - R - 1 >= 0) & (pts + R + 1 < edge_lim), axis=1)
    pts_in = np.clip(pts, R + 1, edge_lim - R - 1.001)
    rows = _Rows(st)
    # 2. first, where each edge lies now: on every fourth profile, the strongest allowed step
    # within track_px of the last line, and per edge the median of their offsets along the profiles
    sub = st["sub"]
    prof1 = _profiles_coarse(img, pts_in[sub], pd[sub], R)
    lim = R - st["hmax"] - PLATEAU_PX - 1
    at, peak, _, _, ok = _candidates(prof1, R, rows.subset(sub), -lim, 2 * lim)
    ok &= (np.abs(at + 0.5) <= st["sr1"][sub]) & (np.abs(peak) >= MIN_CONTRAST) & inside[sub]
    e1 = eid[sub]
    n_ok = np.bincount(e1[ok], minlength=E)
    n_sub = np.bincount(e1[inside[sub]], minlength=E)  # those whose profiles lie in the picture
    # an edge near the picture's border may have too few such profiles: it is looked for near its
    # last line only (the second pass and its checks tell whether it is still there)
    located = n_sub >= 3
    short = located & (n_ok < np.maximum(3, KEEP_FRACTION * n_sub))
    if short.any():
        i = int(np.flatnonzero(short)[0])
        return f"edge {st['keys'][i]} shows a step in only {n_ok[i]} of {n_sub[i]} profiles"
    offset = np.where(located, _group_median(at[ok] + 0.5, e1[ok], E), 0.0)
    # 3. then, as the search's second pass, every profile within +-3 px of there (its line), the
    # profiles moved to be centred on it: (M, 2 R2 + 1) grey levels and their running sums (the
    # plateaus' and the transition's sums for windows of any width)
    R2 = st["R2"]
    ph = st["phase"] + offset[eid]
    reach = R2 + np.abs(ph) + 1.0
    inside = np.all((pts - reach[:, None] >= 0) & (pts + reach[:, None] < edge_lim), axis=1)
    prof = _profiles(img, np.clip(pts, reach[:, None], edge_lim - reach[:, None] - 0.001), pd, ph, R2)
    cs = np.zeros((M, prof.shape[1] + 1))
    np.cumsum(prof, axis=1, dtype=np.float64, out=cs[:, 1:])
    return _steps(prof, cs, st, rows, pts, pd, ph, R2, st["sr2"], inside)


def _passes_native(nat, st: dict, img: np.ndarray):
    """``_passes`` by the compiled kernels ``nat`` (``selfview._ctrack``): the same result. The coarse
    profiles are still OpenCV's remap, the peaks' logarithms numpy's (its float32 log is not the C
    library's)."""
    H, W = img.shape
    eid, pts, pd, sub = st["eid"], st["pts"], st["pd"], st["sub"]
    M = len(pts)
    R = st["R"]
    levels = np.ascontiguousarray(st["levels"])
    # 2. the coarse pass: the maps of _profiles_coarse, OpenCV's remap, then in C _candidates, its tests,
    # the counts, and the median offsets (into the second pass's phases)
    mx = np.empty((len(sub), 2 * R + 1), np.float32)
    my = np.empty_like(mx)
    nat.coarse_maps(pts, pd, sub, R, W, H, mx, my)
    prof1 = cv2.remap(img, mx, my, cv2.INTER_LINEAR)
    lim = R - st["hmax"] - PLATEAU_PX - 1
    ph = np.empty(M)
    short = nat.coarse(
        prof1, sub, pts, eid, st["h"], levels, st["crease"], st["sr1"], st["phase"],
        W, H, R, lim, PLATEAU_PX, MIN_CONTRAST, KEEP_FRACTION, ph,
    )  # fmt: skip
    if short is not None:
        i, n_ok, n_sub = short
        return f"edge {st['keys'][i]} shows a step in only {n_ok} of {n_sub} profiles"
    # 3. the second pass: _profiles, the running sums, _steps up to the peaks' logarithms in C; np.log;
    # the peaks and the crossings in C
    cand = np.empty(M, np.int64)
    est = np.empty((M, 5))
    logarg = np.empty((M, 3), np.float64 if img.dtype == np.float64 else np.float32)
    G = nat.fine(
        img, pts, pd, ph, eid, st["h"], levels, st["crease"], st["g"], st["R2"], st["sr2"], PLATEAU_PX, MIN_CONTRAST,
        cand, est, logarg,
    )  # fmt: skip
    lg = np.log(logarg[:G])
    cross, eid2, Am, Bm = np.empty((G, 2)), np.empty(G, np.int64), np.empty(G), np.empty(G)
    K = nat.finish(cand[:G], est[:G], lg, pts, pd, ph, eid, st["textured"], cross, eid2, Am, Bm)
    return _StepsFound(cross[:K], eid2[:K], Am[:K], Bm[:K])


def _line_stats(q2, second: "_StepsFound", w2, n2, c2, E: int):
    """What the corners need of the lines' inliers (w2 > 0): their count per edge n_in (E,), the faces'
    median levels (E, 2), their edges ei and positions along the lines s_in (Kin,), the positions' mean
    and sum of squares about it, and the residuals' sum of squares per edge (E,) (the reference of
    ``_ctrack.line_stats``)."""
    inl = w2 > 0
    ei = second.eid[inl]
    n_in = np.bincount(ei, minlength=E)
    qi = q2[inl]
    levels = _group_median(np.concatenate([second.Am[inl], second.Bm[inl]]), np.concatenate([ei, ei + E]), 2 * E)
    levels = levels.reshape(2, E).T  # (E, 2): the low and high side's median grey level
    t2 = np.column_stack([-n2[:, 1], n2[:, 0]])
    s_in = np.sum(qi * t2[ei], axis=1)
    r_in = np.sum(qi * n2[ei], axis=1) - c2[ei]
    cnt = np.maximum(n_in, 1)
    s_mean = np.bincount(ei, s_in, E) / cnt
    s_ss = np.bincount(ei, (s_in - s_mean[ei]) ** 2, E)
    r_ss = np.bincount(ei, r_in * r_in, E)
    return n_in, levels, ei, s_in, s_mean, s_ss, r_ss


def _pair_rounds(pairs: list) -> list[list]:
    """(corner, edge) pairs split into rounds in which no edge comes twice (an edge between two
    corners is checked against each in its own round)."""
    rounds: list[list] = []
    for k, li in pairs:
        for rnd in rounds:
            if all(lj != li for _, lj in rnd):
                rnd.append((k, li))
                break
        else:
            rounds.append([(k, li)])
    return rounds


def _stations(st: dict, corners: dict, n: np.ndarray) -> np.ndarray:
    """Where the profiles cross the edges (M, 2), undistorted px: on each edge's line ``n`` (E, 2), at
    the distances ``st['s']`` from its anchor corner (``corners``: point index -> (2,))."""
    anchor_q = np.array([corners[k] for k in st["anchor"]])
    eid = st["eid"]
    t = np.column_stack([-n[:, 1], n[:, 0]])  # each edge's tangent, gathered per profile
    return anchor_q[eid] + st["s"][:, None] * t[eid]


class _StepsFound:
    """The accepted steps of one pass: ``cross`` (K, 2) crossings [distorted px], ``eid`` (K,) their
    edges, ``Am``, ``Bm`` (K,) the grey levels before and after the step along the profile."""

    __slots__ = ("cross", "eid", "Am", "Bm")

    def __init__(self, cross, eid, Am, Bm):
        self.cross, self.eid, self.Am, self.Bm = cross, eid, Am, Bm


def _profiles(img: np.ndarray, pts: np.ndarray, pd: np.ndarray, phase: np.ndarray, R: int) -> np.ndarray:
    """Bilinear grey levels (M, 2R + 1) at pts + (j + phase) pd, j = -R..R (inside the picture).
    (In C: ``sample_row`` of ``_ctrack.fine`` and ``_ctrack.profiles``, the same operations.)"""
    W = img.shape[1]
    off = np.arange(-R, R + 1, dtype=np.float64)[None, :] + phase[:, None]
    x = pts[:, 0:1] + off * pd[:, 0:1]
    y = pts[:, 1:2] + off * pd[:, 1:2]
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = x - x0
    fy = y - y0
    i00 = (y0 * W + x0).astype(np.intp)
    flat = img.ravel()
    # single precision for the interpolation (the weights' rounding is below 1e-4 grey levels)
    fx = fx.astype(np.float32)
    fy = fy.astype(np.float32)
    v00 = flat[i00].astype(np.float32)
    v01 = flat[i00 + 1]
    v10 = flat[i00 + W].astype(np.float32)
    v11 = flat[i00 + (W + 1)]
    top = v00 + (v01 - v00) * fx
    return top + ((v10 + (v11 - v10) * fx) - top) * fy


def _profiles_coarse(img: np.ndarray, pts: np.ndarray, pd: np.ndarray, R: int) -> np.ndarray:
    """Grey levels (M, 2R + 1) at pts + j pd, j = -R..R, by OpenCV's bilinear remap: its positions are
    rounded to 1/32 px, which does not matter where the profiles only find the step to a pixel."""
    off = np.arange(-R, R + 1, dtype=np.float32)[None, :]
    mx = pts[:, 0:1].astype(np.float32) + off * pd[:, 0:1].astype(np.float32)
    my = pts[:, 1:2].astype(np.float32) + off * pd[:, 1:2].astype(np.float32)
    return cv2.remap(img, mx, my, cv2.INTER_LINEAR).astype(np.float32)


class _Rows:
    """Per-profile constants of one frame: each row's edge parameters, gathered once."""

    def __init__(self, st: dict):
        eid = st["eid"]
        levels = st["levels"]
        self.h = st["h"][eid]
        self.exp_hi = levels[eid, 1]
        self.exp_lo = np.where(st["crease"], levels[:, 0], np.nan)[eid]
        self.any_lo = bool(st["crease"].any())
        self.contrast0 = np.abs(levels[:, 1] - levels[:, 0])[eid]
        self.tol = np.maximum(15.0, 0.3 * self.contrast0)
        self.g_lo, self.g_hi = st["g"][eid, 0], st["g"][eid, 1]
        self.textured = st["textured"][eid]

    def subset(self, idx: np.ndarray) -> "_Rows":
        out = object.__new__(_Rows)
        for k, v in self.__dict__.items():
            out.__dict__[k] = v[idx] if isinstance(v, np.ndarray) else v
        return out


def _candidates(prof, R: int, rows: _Rows, start: int, width: int):
    """The strongest step of either polarity per profile among ``width`` consecutive step positions
    from ``start`` (profile coordinate of the sample before the step), keeping only steps that
    show the face's grey level on its side (and a crease's other face on the other).
    Returns (at (M,), the step's grey-level difference (M,), the differences (M, width), the column
    index (M,) of the chosen one among them, whether the profile has any allowed step (M,)).
    (In C: ``candidates`` in ``_ctrack.c``, for ``_ctrack.coarse`` and ``_ctrack.fine``.)"""
    P = PLATEAU_PX
    flat = prof.ravel()
    L = prof.shape[1]
    c0 = start + R  # flat index of the sample before each step
    cols = (np.arange(len(prof)) * L + c0)[:, None] + np.arange(width)[None, :]
    diff = prof[:, c0 + 1 : c0 + width + 1] - prof[:, c0 : c0 + width]
    hi_side = flat[cols + (rows.h + 1 + P // 2)[:, None]]
    allowed = np.abs(hi_side - rows.exp_hi[:, None]) <= rows.tol[:, None]
    if rows.any_lo:
        lo_side = flat[cols - (rows.h + P // 2)[:, None]]
        allowed &= ~(np.abs(lo_side - rows.exp_lo[:, None]) > rows.tol[:, None])  # NaN: no expectation
    score = np.where(allowed, np.abs(diff), -1.0)
    k = np.argmax(score, axis=1)
    idx = np.arange(len(prof))
    return start + k, diff[idx, k], diff, k, score[idx, k] >= 0.0


def _steps(prof, cs, st: dict, rows: "_Rows", pts, pd, phase, R: int, half: int, use: np.ndarray) -> _StepsFound:
    """The step in each profile (sampled at pts + (j + phase) pd, j = -R..R; stations ``pts`` (M, 2),
    directions ``pd`` (M, 2)) within ``half`` samples of its middle, located as the second pass of
    ``fingertips._edge_steps`` locates it: the strongest step of either polarity that shows the face's grey level on its
    side (and a crease's other face on the other), its crossing by the area method (sloped plateaus,
    each edge's own transition width) or, over a textured background, by the peak of the rise; the
    search's acceptance tests. ``cs`` the running sums of ``prof``; ``use`` (M,) the profiles to use.
    (In C: ``_ctrack.fine`` up to the peaks' logarithms, ``_ctrack.finish`` after them.)"""
    P = PLATEAU_PX
    start = -half
    at, peak, diff, k, ok = _candidates(prof, R, rows, start, 2 * half)
    M = len(prof)
    idx = np.arange(M)
    h = rows.h
    sgn = np.sign(peak)
    ws = at + R - h - P + 1  # the window: P plateau samples, 2h over the transition, P plateau samples
    Am = (cs[idx, ws + P] - cs[idx, ws]) / P
    S = cs[idx, ws + P + 2 * h] - cs[idx, ws + P]
    Bm = (cs[idx, ws + 2 * h + 2 * P] - cs[idx, ws + 2 * h + P]) / P
    x_lo, x_hi = at - h + 0.5, at + h + 0.5
    x_A, x_B = x_lo - P / 2, x_hi + P / 2
    g_lo, g_hi = rows.g_lo, rows.g_hi
    e, e_peak = _step_estimates(at, x_lo, x_hi, x_A, x_B, Am, Bm, S, g_lo, g_hi, diff, k, sgn)
    # the plateaus' and the whole window's spread (a window shorter than the longest repeats its end)
    plat = np.arange(P)[None, :]
    flat = prof.ravel()
    ws_flat = (idx * prof.shape[1] + ws)[:, None]
    lo_win = flat[ws_flat + plat]
    hi_win = flat[ws_flat + (2 * h + P)[:, None] + plat]
    whole = flat[ws_flat + np.minimum(np.arange(2 * (st["hmax"] + P))[None, :], (2 * (h + P) - 1)[:, None])]
    contrast = np.abs(Bm - Am)
    rough = np.maximum(np.ptp(lo_win, axis=1), np.ptp(hi_win, axis=1))
    slope_allow = (np.abs(g_lo) + np.abs(g_hi)) * P
    good = (
        ok
        & use
        & ((Bm - Am) * sgn >= np.maximum(MIN_CONTRAST, 0.35 * rows.contrast0))
        & (np.abs(Bm - rows.exp_hi) <= rows.tol)
        & ~(np.abs(Am - rows.exp_lo) > rows.tol)  # NaN (no expectation) passes
        & (rough <= 0.08 * contrast + 8 + slope_allow)
        & (np.ptp(whole, axis=1) <= 1.15 * contrast + 10 + slope_allow)  # one step only
        & (np.abs(e - (at + 0.5)) < 1.5)
        & (np.abs(e_peak - (at + 0.5)) < 1.0)
        & (peak * sgn > 0)
    )
    g = np.flatnonzero(good)
    along = np.where(rows.textured[g], e_peak[g], e[g]) + phase[g]
    return _StepsFound(pts[g] + along[:, None] * pd[g], st["eid"][g], Am[g], Bm[g])


def _robust_lines(q: np.ndarray, gid: np.ndarray, E: int, n_prev: np.ndarray, c_prev: np.ndarray):
    """A robust line per edge through its crossings q (K, 2) (undistorted px; ``gid`` (K,) their edges,
    sorted), from the lines (n_prev, c_prev) near which they were looked for: Tukey weights about the
    median offset from those, then three rounds of weighted total least squares and Tukey reweighting
    (scale >= 0.05 px), as the search's ``_fit_line`` ends. Returns (n (E, 2), c (E,), weights (K,):
    > 0 for the inliers). (In C: ``_ctrack.lines``.)"""
    groups = _Groups(gid, E)
    starts = np.searchsorted(gid, np.arange(E))
    r = np.sum(q * n_prev[gid], axis=1) - c_prev[gid]
    w = _tukey(r - groups.median(r)[gid], groups, 0.05)
    n = n_prev
    for _ in range(3):
        n, c = _lines_tls(q, w, starts, n)
        w = _tukey(np.sum(q * n[gid], axis=1) - c[gid], groups, 0.05)
    return n, c, w


def _intersect(n, c, t, lines, s_mean, s_ss, r_ss, cnt):
    """The corner (2,) where ``lines`` (indices of n (E, 2), c (E,)) meet, or None when two of them are
    within 10 degrees of parallel. Two lines: their intersection; three: least squares weighted by each
    line's uncertainty at the corner (scatter, count, lever arm), as the search's ``_corner`` weighs them."""
    N = [n[i].tolist() for i in lines]
    sin = min(abs(N[a][0] * N[b][1] - N[a][1] * N[b][0]) for a in range(len(N)) for b in range(a + 1, len(N)))
    if sin < math.sin(math.radians(10)):
        return None

    def solve(wts):
        a11 = a12 = a22 = b1 = b2 = 0.0
        for (nx, ny), ci, wi in zip(N, (float(c[i]) for i in lines), wts):
            w2 = wi * wi
            a11 += w2 * nx * nx
            a12 += w2 * nx * ny
            a22 += w2 * ny * ny
            b1 += w2 * nx * ci
            b2 += w2 * ny * ci
        det = a11 * a22 - a12 * a12
        return np.array([(a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det])

    q = solve([1.0] * len(N))
    if len(N) > 2:
        wts = []
        for i in lines:
            lever = (float(t[i] @ q) - s_mean[i]) ** 2 / max(s_ss[i], 1e-9)
            var = max(r_ss[i] / cnt[i], 0.03**2) * (1.0 / cnt[i] + lever)
            wts.append(1.0 / math.sqrt(var))
        q = solve(wts)
    return q


def _tukey(r: np.ndarray, groups: _Groups, floor: float) -> np.ndarray:
    """Tukey biweights of residuals r (K,) with a scale per group: 1.4826 MAD, at least ``floor``."""
    s = np.maximum(1.4826 * groups.median(np.abs(r)), floor)
    u = r / (4.685 * s[groups.gid])
    return np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)


def _lines_tls(q: np.ndarray, w: np.ndarray, starts: np.ndarray, n_prev: np.ndarray):
    """Weighted total-least-squares line per group of consecutive points (group g from ``starts[g]``,
    every group present): normals (n, 2), turned like ``n_prev``, and c. The six weighted moments of
    all groups in one reduction."""
    A = np.empty((len(q), 6))
    A[:, 0] = w
    np.multiply(w, q[:, 0], out=A[:, 1])
    np.multiply(w, q[:, 1], out=A[:, 2])
    np.multiply(A[:, 1], q[:, 0], out=A[:, 3])
    np.multiply(A[:, 2], q[:, 1], out=A[:, 4])
    np.multiply(A[:, 1], q[:, 1], out=A[:, 5])
    sw, sx, sy, sxx, syy, sxy = np.add.reduceat(A, starts, axis=0).T
    sw = np.maximum(sw, 1e-300)
    mx, my = sx / sw, sy / sw
    cxx, cyy, cxy = sxx - sx * mx, syy - sy * my, sxy - sx * my
    ang = 0.5 * np.arctan2(2 * cxy, cxx - cyy)  # direction of the largest spread
    nrm = np.column_stack([-np.sin(ang), np.cos(ang)])
    flip = np.sum(nrm * n_prev, axis=1) < 0
    nrm[flip] = -nrm[flip]
    return nrm, nrm[:, 0] * mx + nrm[:, 1] * my


WIDE_ROUNDS = (60.0, 24.0, 10.0, 5.0, 3.0)  # a search's fit from a start that may be far off [px]


class SilhouetteTracker:
    """The fingertips of a sequence of pictures by the model-based measurement (``selfview.silhouette``).

    Like ``FingertipTracker`` (``find(image, C_H_G_pred, gap_mm)`` returns a ``FingertipResult``;
    ``searches``, ``tracked_frames``, ``last_failure``, ``reset()``, ``primed``), but every frame fits the
    whole silhouette of both fingers: from the last fitted pose with the short ranges ``track_rounds``
    [px] (the camera moves little between frames), with the faces' grey levels of the last fit; once more
    within 3 px of the new pose when the fingertips moved more than ``refine_px`` [px]. When
    that fit is not believed (its quality under the thresholds: the reason is ``last_failure``), the frame
    is searched: fits with the full ranges from the last pose and from ``C_H_G_pred``, then from the
    pose the corner search (``selfview.fingertips``) gives. A frame where none holds reports every point
    as not found, with the reason in ``result.lost``: a missed frame, never a pose. Every result carries
    the fit's ``quality``. The fit's sampling, candidates, IRLS and vote run in the compiled kernel
    ``selfview._csil`` when built (``selfview.silhouette``: its numpy code the reference).
    """

    def __init__(self, camera: CameraModel, gripper: GripperSpec, *, points=range(4), search_px: float = 60.0,
                 track_rounds=(8.0,), refine_px: float = 2.0, appearance=None):
        if not isinstance(camera, CameraModel):
            raise TypeError(f"camera: expected a selfview.camera.CameraModel, got {type(camera).__name__}")
        want = sorted({int(k) for k in points})
        if not want or any(k < 0 or k > 5 for k in want):
            raise ValueError(f"points: expected indices 0..5 into POINT_NAMES, got {list(points)}")
        rounds = tuple(float(r) for r in track_rounds)
        if not rounds or any(not (1.0 <= r <= 60.0) for r in rounds):
            raise ValueError(f"track_rounds: expected search ranges of 1..60 px, got {track_rounds!r}")
        self.camera = camera
        self.gripper = gripper
        self.points = tuple(want)
        self.search_px = float(search_px)
        self.track_rounds = rounds
        self.refine_px = float(refine_px)
        self.searches = 0
        self.tracked_frames = 0
        self.lost_frames = 0
        self.last_failure: str | None = None
        self.last_fit = None
        self._app0 = appearance
        self.reset()

    def reset(self) -> None:
        """Forget the last pose: the next frame is searched for."""
        self._H = None
        self._gap = None
        self._app = self._app0

    @property
    def primed(self) -> bool:
        return self._H is not None

    def find(self, image, C_H_G_pred, gap_mm: float) -> FingertipResult:
        from selfview.fingertips import _fit_result, model_measurement
        from selfview.silhouette import fit_silhouette

        C_H_G_pred, gap_mm = checked_prediction(C_H_G_pred, gap_mm)
        a = np.asarray(image)
        if a.dtype == np.uint8 and a.shape == (int(self.camera.height), int(self.camera.width)):
            img = a  # a grabber's frame: no other check needed per frame (float32 where the search needs it)
        else:
            img = as_gray(image, self.camera)  # float32, checked
        why = None
        if self._H is not None and self._gap is not None and abs(gap_mm - self._gap) > 1e-6:
            why = f"the jaw gap changed ({self._gap:.2f} -> {gap_mm:.2f} mm)"
            self.reset()
        if self._H is not None:
            fit = fit_silhouette(img, self.camera, self._H, self.gripper, gap_mm, appearance=self._app,
                                 rounds=self.track_rounds, points=self.points, frame=True)
            if fit.C_H_G is not None and self._moved_px(fit.C_H_G, gap_mm) > self.refine_px:
                # a larger step than usual: once more with a short range around the new pose
                again = fit_silhouette(img, self.camera, fit.C_H_G, self.gripper, gap_mm, appearance=fit.appearance,
                                       rounds=(min(self.track_rounds[-1], 3.0),), points=self.points, frame=True)
                fit = again if again.ok or not fit.ok else fit
            if fit.ok:
                self._take(fit, gap_mm)
                self.tracked_frames += 1
                self.last_failure = None
                res = _fit_result(fit, None, self.points)
                res.tracked = True
                return res
            why = fit.reason
        self.last_failure = why
        img = img.astype(np.float32, copy=False)
        starts = ([self._H] if self._H is not None else []) + [C_H_G_pred]
        res, fit = model_measurement(img, self.camera, C_H_G_pred, self.gripper, gap_mm, self.points,
                                     appearance=self._app, starts=starts)
        if not fit.ok:
            # the corner search's pose (three corners or more), and fits reaching as far as it searches
            searched = _search(img, self.camera, C_H_G_pred, self.gripper, gap_mm, self.search_px, range(6))[0]
            res2, fit2 = model_measurement(img, self.camera, C_H_G_pred, self.gripper, gap_mm, self.points,
                                           searched=searched, appearance=self._app, starts=[],
                                           rounds=WIDE_ROUNDS)
            if fit2.ok:
                res, fit = res2, fit2
        self.searches += 1
        if fit.ok:
            self._take(fit, gap_mm)
        else:
            self.lost_frames += 1
        return res

    def _moved_px(self, H, gap_mm: float) -> float:
        """How far [px] the fingertip points moved in the picture from the last pose to ``H``."""
        from selfview.geometry import transform_points

        p = self.gripper.points_G(gap=gap_mm)
        a = self.camera.project_undistorted(transform_points(self._H, p))
        b = self.camera.project_undistorted(transform_points(H, p))
        return float(np.max(np.linalg.norm(a - b, axis=1)))

    def _take(self, fit, gap_mm: float) -> None:
        self._H = fit.C_H_G.copy()
        self._gap = float(gap_mm)
        self._app = fit.appearance
        self.last_fit = fit
