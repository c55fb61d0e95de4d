"""The tracker's compiled kernels (``selfview._ctrack``) against the pure-Python reference
(``selfview.tracking``).

Two trackers are fed the same pictures, one with the kernels and one with ``selfview._native.track``
set to None (the Python code): every decision (tracked or searched, and why) and every reason must be
the same, the corners and their edge RMS within 1e-6 px. Pictures of both
renderers (the project's and the independent ``tests/alt_render.py``), uint8 and float. Then the
kernels one by one: the same arrays as the Python functions they replace (integers and decisions exactly,
floats at a tolerance of their quantity: see the constants below), and bad arguments refused with an
error naming them, never a read outside a buffer.

Why tolerances and not bit identity: the kernels and numpy do the same arithmetic in another order
(numpy's pairwise sums and SIMD loops, the C compiler's fused multiply-adds, libm against numpy's
sin/cos/arctan2), and which rounding each gets depends on the CPU (vector width, FMA). The tolerances
are far below anything that matters to the tracker and far above double rounding.

Skipped when the kernels are not built (or ``SELFVIEW_PURE_PYTHON=1``), except with
``SELFVIEW_REQUIRE_NATIVE=1`` in the environment (CI), where that fails.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

import selfview.tracking as T
from selfview import _native
from selfview.fingertips import MIN_CONTRAST, PLATEAU_PX
from selfview.tracking import FingertipTracker
from tests.alt_render import render_world
from tests.selfview.test_tracking import _render, _world

REQUIRE_ENV = "SELFVIEW_REQUIRE_NATIVE"
# Tolerances between the kernels and the Python reference, by quantity:
TOL_PX = 1e-6  # picture positions, line offsets, edge RMS: a millionth of a pixel (the corners' noise is ~0.05 px)
TOL_GREY = 1e-4  # grey levels: a ten-thousandth of one 8-bit step (float32 profiles carry ~1e-5 at 120)
TOL_DIR = 1e-9  # unit line normals: 1e-9 rad of direction (1e-6 px of offset at 1000 px from the origin)
TOL_WEIGHT = 1e-9  # robust weights in [0, 1]: relative to a full weight
TOL_SS_REL = 1e-9  # sums of squares of positions/residuals (px^2): relative, they sum up to ~200 terms
NATIVE = _native.track  # as loaded (the tests set selfview._native.track to None for the reference)


@pytest.fixture
def nat():
    """The compiled module; skips (or fails with SELFVIEW_REQUIRE_NATIVE=1) when there is none."""
    required = os.environ.get(REQUIRE_ENV, "").strip() not in ("", "0")
    why = None
    if NATIVE is None:
        why = "selfview._ctrack is not built (or SELFVIEW_PURE_PYTHON=1): nothing to compare"
    elif getattr(NATIVE, "API", None) != T._CTRACK_API:
        why = f"selfview._ctrack is a stale build (API {getattr(NATIVE, 'API', None)}, expected {T._CTRACK_API})"
    if why:
        if required:
            pytest.fail(f"{REQUIRE_ENV}=1 but {why}")
        pytest.skip(why)
    return NATIVE


# --- two trackers on the same pictures ---------------------------------------------------------------
class _Pair:
    """A tracker with the kernels and one with the Python code, fed the same pictures; ``find``
    checks that they agree and returns the kernels' result."""

    TOL_PX = TOL_PX

    def __init__(self, nat, monkeypatch, camera, gripper, **kw):
        self.nat, self.mp = nat, monkeypatch
        self.c = FingertipTracker(camera, gripper, **kw)
        self.py = FingertipTracker(camera, gripper, **kw)
        self.worst = 0.0
        self.tracked = 0

    def find(self, image, C_H_G, gap):
        self.mp.setattr(_native, "track", self.nat)
        a = self.c.find(image, C_H_G, gap)
        self.mp.setattr(_native, "track", None)
        b = self.py.find(image, C_H_G, gap)
        self.mp.setattr(_native, "track", self.nat)
        assert (a.tracked, self.c.last_failure) == (b.tracked, self.py.last_failure)
        assert a.reasons == b.reasons
        np.testing.assert_array_equal(a.found, b.found)
        np.testing.assert_array_equal(a.n_edge_points, b.n_edge_points)
        np.testing.assert_array_equal(np.isnan(a.uv), np.isnan(b.uv))
        if a.found.any():
            d = float(np.max(np.abs(a.uv[a.found] - b.uv[b.found])))
            assert d <= self.TOL_PX, f"corners {d:.3g} px apart"
            self.worst = max(self.worst, d)
            # the edge RMS (px) decides nothing at this level: to a millionth of a pixel like the corners
            np.testing.assert_allclose(a.edge_rms_px[a.found], b.edge_rms_px[b.found], rtol=0, atol=TOL_PX)
        assert (self.c.searches, self.c.tracked_frames) == (self.py.searches, self.py.tracked_frames)
        assert self.c.primed == self.py.primed
        self.tracked += a.tracked
        return a


def _as(image: np.ndarray, dtype) -> np.ndarray:
    """The picture as uint8, or as float32/float64 grey levels that are not whole numbers."""
    if dtype == np.uint8:
        return image
    return (image.astype(np.float64) * 0.93 + 7.3).astype(dtype)


_SEQUENCES: dict = {}


def _creeping(cell, renderer: str, seed: int, parked: bool, frames: int = 4):
    """(camera, gripper, jaw gap, [(picture, C_H_G)]) of a camera creeping about 1 px a frame (cached:
    rendering is the slow part)."""
    key = (renderer, seed, parked, frames)
    if key not in _SEQUENCES:
        w = _world(cell, seed, parked)
        rng = np.random.default_rng(seed)
        seq = [(_render(renderer, w, seed).image, w.C_H_G)]
        for i in range(frames):
            w.disturb_by_angle(rng.normal(size=3), 0.05)
            seq.append((_render(renderer, w, 100 + i).image, w.C_H_G))
        _SEQUENCES[key] = (w.camera, w.jaw_gap_mm, seq)
    return _SEQUENCES[key]


@pytest.mark.parametrize("dtype", [np.uint8, np.float32, np.float64])
@pytest.mark.parametrize("renderer", ["alt", "project"])
@pytest.mark.parametrize("seed,parked", [(0, True), (2, False), (6, False)])
def test_a_creeping_camera_is_tracked_alike(cell, nat, monkeypatch, renderer, seed, parked, dtype):
    camera, gap, seq = _creeping(cell, renderer, seed, parked)
    pair = _Pair(nat, monkeypatch, camera, cell.gripper)
    first = pair.find(_as(seq[0][0], dtype), seq[0][1], gap)
    assert not first.tracked and pair.c.primed
    # forth and back over the sequence, as the benchmark runs it
    for img, C_H_G in seq[1:] + seq[-2::-1]:
        pair.find(_as(img, dtype), C_H_G, gap)
    assert pair.tracked >= len(seq) - 1  # mostly tracked (a frame may be searched for, alike)


@pytest.mark.parametrize(
    "options",
    [
        (("gain", 0.97),),
        (("gain", 1.03),),
        (("gain", 0.85),),
        (("blur_sigma", 1.5),),
        (("gradient", (0.4, -0.3)), ("vignetting", 0.3)),
    ],
)
def test_a_change_of_light_or_focus_is_handled_alike(cell, nat, monkeypatch, options):
    w = _world(cell, 2, parked=True)
    pair = _Pair(nat, monkeypatch, w.camera, cell.gripper)
    pair.find(render_world(w, seed=2).image, w.C_H_G, w.jaw_gap_mm)
    for i in range(2):
        w.disturb_by_angle((1.0, 0.0, 0.0), 0.05)
        res = pair.find(render_world(w, seed=5 + i, **dict(options)).image, w.C_H_G, w.jaw_gap_mm)
        assert res.found[:4].all()


def test_a_covered_corner_is_handled_alike(cell, nat, monkeypatch):
    from selfview.geometry import transform_points

    w = _world(cell, 3, parked=True)
    pair = _Pair(nat, monkeypatch, w.camera, cell.gripper)
    pair.find(render_world(w, seed=3).image, w.C_H_G, w.jaw_gap_mm)
    p = 0.8 * transform_points(w.C_H_G, w.points_G())[0]  # on the line of sight to A-inner-front
    occluder = (p - [2.5, 2.5, 1.0], p + [2.5, 2.5, 1.0], 235.0)
    res = pair.find(render_world(w, seed=4, occluders=(occluder,)).image, w.C_H_G, w.jaw_gap_mm)
    assert not res.tracked and pair.c.last_failure and not res.found[0]


def test_a_jump_is_searched_for_alike(cell, nat, monkeypatch):
    w = _world(cell, 1, parked=False)
    before = w.C_H_G
    pair = _Pair(nat, monkeypatch, w.camera, cell.gripper, track_px=8.0)
    pair.find(render_world(w, seed=1).image, before, w.jaw_gap_mm)
    w.disturb("cable")  # the fingertips move some 10-20 px in the picture
    res = pair.find(render_world(w, seed=2).image, before, w.jaw_gap_mm)
    assert not res.tracked and pair.c.last_failure
    for i in range(2):  # and followed again from there
        w.disturb_by_angle((0.0, 0.0, 1.0), 0.05)
        res = pair.find(render_world(w, seed=3 + i).image, before, w.jaw_gap_mm)
        assert res.tracked, pair.c.last_failure


def test_missing_points_and_the_border_are_handled_alike(cell, nat, monkeypatch):
    w = _world(cell, 4, parked=True)
    before = w.C_H_G
    w.disturb_by_angle((0.0, 1.0, 0.0), 3.0)  # A's outer point leaves the picture
    pair = _Pair(nat, monkeypatch, w.camera, cell.gripper, points=range(6), search_px=80.0, refresh_frames=2)
    pair.find(render_world(w, seed=4).image, before, w.jaw_gap_mm)
    for i in range(4):
        pair.find(render_world(w, seed=10 + i).image, before, w.jaw_gap_mm)
    assert pair.c.searches == 2 and pair.tracked == 3


def test_frames_that_cannot_be_tracked_fail_alike(cell, nat, monkeypatch):
    """A picture moved by many pixels, one of another jaw gap's fingers, a blank stretch: each frame
    fails in the coarse pass, the second pass or the checks, for the same reason both ways."""
    camera, gap, seq = _creeping(cell, "project", 0, True)
    img0, C_H_G = seq[0]
    reasons = set()
    for shift in [(0, 3), (0, 9), (14, 0), (0, 40), (-25, 25)]:
        pair = _Pair(nat, monkeypatch, camera, cell.gripper)
        pair.find(img0, C_H_G, gap)
        res = pair.find(np.roll(seq[1][0], shift, axis=(0, 1)), C_H_G, gap)
        reasons.add(pair.c.last_failure if not res.tracked else None)
    pair = _Pair(nat, monkeypatch, camera, cell.gripper)
    pair.find(img0, C_H_G, gap)
    img = seq[1][0].copy()
    img[:, : img.shape[1] // 2] = 90  # half the picture blank
    res = pair.find(img, C_H_G, gap)
    reasons.add(pair.c.last_failure if not res.tracked else None)
    assert len(reasons - {None}) >= 2, reasons  # more than one kind of failure was compared


# --- the kernels one by one -------------------------------------------------------------------------
@pytest.fixture(scope="module")
def primed(cell):
    """A tracker primed on the first picture of a sequence, and the next picture."""
    camera, gap, seq = _creeping(cell, "project", 2, False)
    tr = FingertipTracker(camera, cell.gripper)
    tr.find(seq[0][0], seq[0][1], gap)
    assert tr.primed
    return tr, seq[1][0]


@pytest.mark.parametrize("dtype", [np.uint8, np.float32, np.float64])
def test_the_passes_agree(nat, primed, dtype):
    tr, img = primed
    img = _as(img, dtype)
    a = T._passes(tr._state, img)
    b = T._passes_native(nat, tr._state, img)
    assert len(a.eid) > 100
    np.testing.assert_array_equal(a.eid, b.eid)  # which edge each step belongs to: integers, exactly
    np.testing.assert_allclose(b.cross, a.cross, rtol=0, atol=TOL_PX)  # edge crossings, px
    np.testing.assert_allclose(b.Am, a.Am, rtol=0, atol=TOL_GREY)  # the faces' grey levels
    np.testing.assert_allclose(b.Bm, a.Bm, rtol=0, atol=TOL_GREY)


def test_a_failing_coarse_pass_says_the_same(nat, primed):
    tr, img = primed
    img = np.roll(img, 40, axis=1)
    a, b = T._passes(tr._state, img), T._passes_native(nat, tr._state, img)
    assert isinstance(a, str) and a == b


def _picture(H=48, W=64, dtype=np.float64, guard=0):
    """A smooth picture (H, W) with grey levels 20..120, inside a buffer with ``guard`` elements before
    and after it of NaN (float) or 255 (uint8): a kernel that reads outside the picture reads those."""
    v, u = np.mgrid[0:H, 0:W]
    pic = 70 + 50 * np.sin(u / 7.0) * np.cos(v / 5.0)
    buf = np.full(H * W + 2 * guard, 255 if dtype == np.uint8 else np.nan, dtype)
    img = buf[guard : guard + H * W].reshape(H, W)
    img[:] = pic.astype(dtype) if dtype != np.uint8 else np.round(pic).astype(np.uint8)
    return img


@pytest.mark.parametrize("dtype", [np.uint8, np.float32, np.float64])
def test_profiles_are_numpys_and_stay_inside(nat, dtype):
    H, W, R = 48, 64, 6
    img = _picture(H, W, dtype, guard=4 * W)
    rng = np.random.default_rng(1)
    ang = rng.uniform(0, 2 * np.pi, 200)
    pd = np.column_stack([np.cos(ang), np.sin(ang)])
    ph = rng.uniform(-0.5, 0.5, 200)
    reach = R + np.abs(ph)
    # the samples reach from the picture's first pixel to just short of its last (x < W - 1)
    lo, hi = reach[:, None] * np.abs(pd), np.array([W - 1.0, H - 1.0]) - reach[:, None] * np.abs(pd) - 1e-9
    pts = lo + rng.uniform(0, 1, (200, 2)) * (hi - lo)
    pts[:20] = lo[:20]  # at the very border
    pts[20:40] = hi[20:40]
    out = np.empty((200, 2 * R + 1), np.float64 if dtype == np.float64 else np.float32)
    nat.profiles(img, pts, pd, ph, R, out)
    ref = T._profiles(img, pts, pd, ph, R)
    assert ref.dtype == out.dtype
    # bilinear grey levels: a ten-thousandth of an 8-bit step (the interpolation's products may be fused)
    np.testing.assert_allclose(out, ref, rtol=0, atol=TOL_GREY)
    assert np.all(np.isfinite(out)) and out.max() <= 121  # nothing of the guard band was read
    # a sample beyond the picture, on any side, or NaN: refused (x < W - 1: its four pixels inside)
    right, down = [1.0, 0.0], [0.0, 1.0]
    for p, d in [
        ([R - 1e-9, 10.0], right),
        ([W - 1.0 - R, 10.0], right),
        ([10.0, R - 0.25], down),
        ([10.0, H - 1.0 - R], down),
        ([np.nan, 10.0], right),
        ([10.0, np.inf], down),
        ([10.0, 10.0], [np.nan, 0.0]),
    ]:
        with pytest.raises(ValueError, match="outside the 64x48 picture"):
            nat.profiles(img, np.array([p]), np.array([d]), np.zeros(1), R, out[:1])


@pytest.mark.parametrize("dtype", [np.uint8, np.float32, np.float64])
def test_the_second_pass_never_reads_outside_the_picture(nat, dtype):
    """Positions anywhere (far outside, NaN) are clipped into the picture as the Python clips them; a
    direction that would still carry the samples outside is refused."""
    H, W, R, half, E = 48, 64, 14, 3, 2
    img = _picture(H, W, dtype, guard=4 * W)
    M = 40
    rng = np.random.default_rng(2)
    pts = rng.uniform(-100, 200, (M, 2))
    pd = np.tile([0.6, 0.8], (M, 1))
    eid = np.repeat(np.arange(E, dtype=np.int64), M // E)
    h = np.array([4, 6], np.int64)
    levels = np.array([[20.0, 120.0], [120.0, 20.0]])
    crease = np.array([False, True])
    g = np.zeros((E, 2))
    ph = rng.uniform(-0.5, 0.5, M)
    cand, est = np.empty(M, np.int64), np.empty((M, 5))
    logarg = np.empty((M, 3), np.float64 if dtype == np.float64 else np.float32)
    args = (img, pts, pd, ph, eid, h, levels, crease, g, R, half, PLATEAU_PX, MIN_CONTRAST)
    G = nat.fine(*args, cand, est, logarg)
    assert 0 <= G <= M
    assert np.all(np.isfinite(est[:G])) and np.all(np.isfinite(logarg[:G]))
    with pytest.raises(ValueError, match="outside the 64x48 picture"):
        nat.fine(img, pts, pd * 3.0, *args[3:], cand, est, logarg)  # steps of 3 px carry it outside
    p = pts.copy()
    p[5] = [10.0, np.inf]  # clipped to the border, as np.clip does
    assert 0 <= nat.fine(img, p, *args[2:], cand, est, logarg) <= M
    p[5] = [np.nan, 10.0]  # no place at all
    with pytest.raises(ValueError, match="outside the 64x48 picture"):
        nat.fine(img, p, *args[2:], cand, est, logarg)


def test_robust_lines_and_their_stats_are_pythons(nat):
    rng = np.random.default_rng(3)
    for trial in range(20):
        E = int(rng.integers(1, 9))
        counts = rng.integers(6, 200, E)
        gid = np.repeat(np.arange(E, dtype=np.int64), counts)
        K = len(gid)
        ang = rng.uniform(0, np.pi, E)
        n_true = np.column_stack([np.cos(ang), np.sin(ang)])
        c_true = rng.uniform(-300, 300, E)
        s = rng.uniform(-80, 80, K)
        q = (n_true[gid] * c_true[gid, None] + s[:, None] * np.column_stack([-n_true[gid, 1], n_true[gid, 0]])
             + n_true[gid] * rng.normal(0, 0.1, K)[:, None])  # fmt: skip
        out = rng.random(K) < 0.1
        q[out] += rng.normal(0, 5, (int(out.sum()), 2))  # outliers
        n_prev = n_true + rng.normal(0, 0.02, (E, 2))
        c_prev = c_true + rng.normal(0, 0.5, E)
        n_ref, c_ref, w_ref = T._robust_lines(q, gid, E, n_prev, c_prev)
        n, c, w = np.empty((E, 2)), np.empty(E), np.empty(K)
        nat.lines(q, gid, n_prev, c_prev, n, c, w)
        np.testing.assert_array_equal(w > 0, w_ref > 0)  # which points are inliers: a decision, exactly
        # the same operations in another order (libm's arctan2/sin/cos against numpy's, fused multiply-adds):
        # normals as directions to 1e-9 rad, offsets to 1e-6 px, weights (0..1) to 1e-9 of a full weight
        np.testing.assert_allclose(n, n_ref, rtol=0, atol=TOL_DIR)
        np.testing.assert_allclose(c, c_ref, rtol=0, atol=TOL_PX)
        np.testing.assert_allclose(w, w_ref, rtol=0, atol=TOL_WEIGHT)
        Am, Bm = rng.normal(60, 5, K), rng.normal(150, 5, K)

        class _S:
            eid, Am, Bm = gid, None, None

        steps = _S()
        steps.Am, steps.Bm = Am, Bm
        ref = T._line_stats(q, steps, w_ref, n_ref, c_ref, E)
        n_in, levels = np.empty(E, np.int64), np.empty((E, 2))
        s_mean, s_ss, r_ss = np.empty(E), np.empty(E), np.empty(E)
        s_in, ei = np.empty(K), np.empty(K, np.int64)
        k_in = nat.line_stats(q, gid, w_ref, n_ref, c_ref, Am, Bm, n_in, levels, s_mean, s_ss, r_ss, s_in, ei)
        r_n_in, r_levels, r_ei, r_s_in, r_s_mean, r_s_ss, r_r_ss = ref
        np.testing.assert_array_equal(n_in, r_n_in)  # counts and edge indices: integers, exactly
        np.testing.assert_array_equal(ei[:k_in], r_ei)
        np.testing.assert_allclose(levels, r_levels, rtol=0, atol=TOL_GREY)  # median grey levels
        np.testing.assert_allclose(s_in[:k_in], r_s_in, rtol=0, atol=TOL_PX)  # positions along the lines, px
        np.testing.assert_allclose(s_mean, r_s_mean, rtol=0, atol=TOL_PX)
        # sums of squares (px^2) of up to ~200 terms of up to ~1e4 px^2: relative
        np.testing.assert_allclose(s_ss, r_s_ss, rtol=TOL_SS_REL, atol=TOL_PX**2)
        np.testing.assert_allclose(r_ss, r_r_ss, rtol=TOL_SS_REL, atol=TOL_PX**2)


def test_group_medians_are_pythons(nat):
    rng = np.random.default_rng(4)
    for trial in range(50):
        n = int(rng.integers(1, 12))
        gid = np.sort(rng.integers(0, n, int(rng.integers(0, 120)))).astype(np.int64)  # some groups empty
        values = rng.normal(0, 10 ** rng.uniform(-3, 3), len(gid))
        if trial % 5 == 0:
            values = np.round(values)  # ties
        out = np.empty(n)
        nat.group_median(values, gid, n, out)
        # exactly: a median is one of the values (or the mean of two, one IEEE addition and halving)
        np.testing.assert_array_equal(out, T._group_median(values, gid, n))


# --- bad arguments ----------------------------------------------------------------------------------
def _fine_args(M=12, E=2, R=16, dtype=np.uint8):
    img = _picture(64, 80, dtype)
    pts = np.tile([40.0, 32.0], (M, 1))
    pd = np.tile([1.0, 0.0], (M, 1))
    eid = np.repeat(np.arange(E, dtype=np.int64), M // E)
    return dict(
        img=img, pts=pts, pd=pd, ph=np.zeros(M), eid=eid, h=np.full(E, 4, np.int64),
        levels=np.tile([20.0, 120.0], (E, 1)), crease=np.zeros(E, bool), g=np.zeros((E, 2)), R=R, half=6,
        P=PLATEAU_PX, min_contrast=MIN_CONTRAST, cand=np.empty(M, np.int64), est=np.empty((M, 5)),
        logarg=np.empty((M, 3), np.float64 if dtype == np.float64 else np.float32),
    )  # fmt: skip


@pytest.mark.parametrize(
    "change, error, match",
    [
        (dict(img=np.zeros((64, 80), np.int16)), TypeError, "img: expected a uint8, float32 or float64"),
        (dict(img=np.zeros((64, 80, 1), np.uint8)), ValueError, "img: expected a 2-D"),
        (dict(img=np.zeros((80, 64), np.uint8).T), TypeError, "img: expected a C-contiguous"),
        (dict(img=[[1, 2], [3, 4]]), TypeError, "img: expected .* got list"),
        (dict(pts=np.zeros((12, 2), np.float32)), TypeError, "pts: expected a float64"),
        (dict(pts=np.zeros((12, 3))), ValueError, r"pts: expected shape \(any, 2\)"),
        (dict(pd=np.zeros((11, 2))), ValueError, r"pd: expected shape \(12, 2\)"),
        (dict(ph=np.zeros(13)), ValueError, r"ph: expected shape \(12,\)"),
        (dict(eid=np.zeros(12, np.int32)), TypeError, "eid: expected a int64"),
        (dict(eid=np.full(12, 2, np.int64)), ValueError, "eid: index 2 .* not within 0..1"),
        (dict(eid=np.full(12, -1, np.int64)), ValueError, "eid: index -1"),
        (dict(levels=np.zeros((3, 2))), ValueError, r"levels: expected shape \(2, 2\)"),
        (dict(crease=np.zeros(2, np.uint8)), TypeError, "crease: expected a bool"),
        (dict(h=np.array([4, 12], np.int64)), ValueError, "h: profiles of 2R.1 = 33 samples are too short for edge 1"),
        (dict(h=np.array([4, -1], np.int64)), ValueError, "h: profiles .* too short for edge 1"),
        (dict(half=1), ValueError, "half >= 2"),
        (dict(cand=np.empty(11, np.int64)), ValueError, r"cand: expected shape \(12,\) \(first dimension at least\)"),
        (dict(est=np.empty((12, 4))), ValueError, r"est: expected shape \(12, 5\)"),
        (dict(logarg=np.empty((12, 3))), TypeError, "logarg: expected a float32"),
    ],
)
def test_fine_refuses_bad_arguments(nat, change, error, match):
    args = _fine_args()
    assert 0 <= nat.fine(*args.values()) <= 12
    args.update(change)
    with pytest.raises(error, match=match):
        nat.fine(*args.values())


def test_outputs_must_be_writable_and_sizes_positive(nat):
    args = _fine_args()
    ro = np.empty((12, 5))
    ro.flags.writeable = False
    with pytest.raises(TypeError, match="est: expected a C-contiguous, writable float64"):
        nat.fine(*{**args, "est": ro}.values())
    with pytest.raises(TypeError, match="expected a C-contiguous, writable float64"):
        nat.lines(np.zeros((6, 2)), np.zeros(6, np.int64), np.zeros((1, 2)), np.zeros(1), np.zeros((1, 2)), np.zeros(1),
                  ro[0, :0])  # fmt: skip
    with pytest.raises(ValueError, match="R, half, P"):
        nat.fine(*{**args, "R": 0}.values())
    mx = np.empty((3, 33), np.float32)
    with pytest.raises(ValueError, match="sub: index 12"):
        nat.coarse_maps(args["pts"], args["pd"], np.array([0, 4, 12], np.int64), 16, 80, 64, mx, mx.copy())
    with pytest.raises(ValueError, match=r"my: expected shape \(3, 33\)"):
        nat.coarse_maps(args["pts"], args["pd"], np.array([0, 4, 8], np.int64), 16, 80, 64, mx,
                        np.empty((3, 31), np.float32))  # fmt: skip
    with pytest.raises(TypeError, match="mx: expected a float32"):
        nat.coarse_maps(args["pts"], args["pd"], np.array([0, 4, 8], np.int64), 16, 80, 64, mx.astype(float), mx)


def test_coarse_finish_lines_refuse_bad_arguments(nat):
    a = _fine_args()
    M, E, R = 12, 2, 16
    sub = np.array([0, 4, 8], np.int64)
    prof1 = np.zeros((3, 2 * R + 1), np.uint8)
    ok = dict(prof1=prof1, sub=sub, pts=a["pts"], eid=a["eid"], h=a["h"], levels=a["levels"], crease=a["crease"],
              sr1=np.full(M, 10.0), phase=np.zeros(M), W=80, H=64, R=R, lim=R - 4 - PLATEAU_PX - 1, P=PLATEAU_PX,
              min_contrast=MIN_CONTRAST, keep_fraction=0.35, ph=np.empty(M))  # fmt: skip
    assert nat.coarse(*ok.values()) is None  # a flat picture: no edge located, none too short
    for change, error, match in [
        (dict(prof1=np.zeros((3, 2 * R), np.uint8)), ValueError, r"prof1: expected shape \(any, 33\)"),
        (dict(sub=np.array([0, 8, 4], np.int64)), ValueError, "sub: expected increasing"),
        (dict(sub=np.array([0, 4], np.int64)), ValueError, r"sub: expected shape \(3,\)"),
        (dict(eid=a["eid"][::-1].copy()), ValueError, "eid: expected sorted group indices"),
        (dict(lim=R), ValueError, "h: profiles .* too short"),
        (dict(sr1=np.zeros(M + 1)), ValueError, "sr1"),
        (dict(ph=np.empty(M, np.float32)), TypeError, "ph: expected a float64"),
    ]:
        with pytest.raises(error, match=match):
            nat.coarse(*{**ok, **change}.values())
    G = 3
    fin = dict(cand=np.array([0, 5, 11], np.int64), est=np.zeros((G, 5)), lg=np.zeros((G, 3), np.float32),
               pts=a["pts"], pd=a["pd"], ph=np.zeros(M), eid=a["eid"], textured=np.zeros(E, bool),
               cross=np.empty((G, 2)), eid_out=np.empty(G, np.int64), Am=np.empty(G), Bm=np.empty(G))  # fmt: skip
    assert nat.finish(*fin.values()) == 0  # lg = 0: no peak
    for change, error, match in [
        (dict(cand=np.array([0, 5, 12], np.int64)), ValueError, "cand: index 12"),
        (dict(lg=np.zeros((G, 2), np.float32)), ValueError, r"lg: expected shape \(3, 3\)"),
        (dict(lg=np.zeros((G, 3), np.float16)), TypeError, "lg: expected a float32 or float64"),
        (dict(textured=np.zeros(1, bool)), ValueError, "eid: index 1"),
        (dict(Bm=np.empty(2)), ValueError, "Bm"),
    ]:
        with pytest.raises(error, match=match):
            nat.finish(*{**fin, **change}.values())
    q, gid = np.random.default_rng(0).normal(size=(12, 2)), np.repeat(np.arange(2, dtype=np.int64), 6)
    n, c, w = np.empty((2, 2)), np.empty(2), np.empty(12)
    nat.lines(q, gid, np.tile([0.0, 1.0], (2, 1)), np.zeros(2), n, c, w)
    for args, error, match in [
        ((q, gid[::-1].copy()), ValueError, "gid: expected sorted"),
        ((q, np.repeat(np.array([0, 2], np.int64), 6)), ValueError, "gid: group index 2"),
        ((q, np.zeros(12, np.int64)), ValueError, "gid: group 1 has no points"),
        ((q[:11], gid), ValueError, r"gid: expected shape \(11,\)"),
    ]:
        with pytest.raises(error, match=match):
            nat.lines(*args, np.tile([0.0, 1.0], (2, 1)), np.zeros(2), n, c, w[: len(args[0])])
    with pytest.raises(ValueError, match="n: expected a number of groups"):
        nat.group_median(np.zeros(3), np.zeros(3, np.int64), -1, np.empty(0))
