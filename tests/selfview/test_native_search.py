"""The full search's compiled kernels (``selfview._ctrack``: ``clear``, ``search_profiles``,
``template_sums``) against the pure-Python reference (``selfview.fingertips``).

``find_fingertips`` runs twice on the same pictures, with the kernels and with ``selfview._native.track``
set to None (the Python code): the corners and their RMS within 1e-6 px, the point counts, the
found/not-found decisions and every reason the same (tolerances of the quantity, not bit identity: the
kernels and numpy round in another order, and which rounding each gets depends on the CPU). Pictures of both renderers (the project's and the
independent ``tests/alt_render.py``): parked and lifted, several seeds, blur, gain, light gradient, an
occluder, a picture without fingers, points outside the picture. Then the kernels one by one, against
the numpy code they replace, and bad arguments refused with an error naming them.

Skipped when the kernels are not built (or ``SELFVIEW_PURE_PYTHON=1``), except with
``SELFVIEW_REQUIRE_NATIVE=1`` in the environment (CI), where that fails.
"""

from __future__ import annotations

import numpy as np
import pytest

import selfview.fingertips as F
from selfview import _native
from selfview.fingertips import find_fingertips
from selfview.geometry import transform_points
from tests.alt_render import case, render_world
from tests.selfview.test_native_track import TOL_GREY, TOL_PX
from tests.selfview.test_native_track import nat  # noqa: F401  (the fixture)


def _both(monkeypatch, nat, image, camera, pred, gripper, gap, **kw):
    """find_fingertips with the kernels and with the Python code; asserts they agree (decisions, reasons
    and counts exactly; corners and edge RMS to a millionth of a pixel)."""
    monkeypatch.setattr(_native, "track", nat)
    a = find_fingertips(image, camera, pred, gripper, gap, **kw)
    monkeypatch.setattr(_native, "track", None)
    b = find_fingertips(image, camera, pred, gripper, gap, **kw)
    monkeypatch.setattr(_native, "track", nat)
    assert a.reasons == b.reasons
    assert np.array_equal(a.found, b.found)
    np.testing.assert_allclose(a.uv, b.uv, rtol=0, atol=TOL_PX, equal_nan=True)
    np.testing.assert_allclose(a.edge_rms_px, b.edge_rms_px, rtol=0, atol=TOL_PX, equal_nan=True)
    assert np.array_equal(a.n_edge_points, b.n_edge_points)
    return a


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5])
def test_alt_renderer_parked(nat, monkeypatch, cell_path, seed):
    c = case(str(cell_path), seed)
    res = _both(monkeypatch, nat, c.pic.image, c.world.camera, c.C_H_G_pred, c.cell.gripper, c.world.jaw_gap_mm)
    assert res.found.sum() >= 4


@pytest.mark.parametrize("seed,series", [(1, "cable"), (2, "tilt"), (3, "tilt"), (4, "cable")])
def test_alt_renderer_lifted(nat, monkeypatch, cell_path, seed, series):
    c = case(str(cell_path), seed, online=series)
    _both(monkeypatch, nat, c.pic.image, c.world.camera, c.C_H_G_pred, c.cell.gripper, c.world.jaw_gap_mm)


@pytest.mark.parametrize(
    "options",
    [
        (("blur_sigma", 1.5),),
        (("gain", 0.97),),
        (("gain", 1.03),),
        (("gradient", (0.4, -0.3)), ("vignetting", 0.3)),
        (("fingers", False),),
    ],
)
def test_alt_renderer_focus_light_and_no_fingers(nat, monkeypatch, cell_path, options):
    for seed in (2, 3):
        c = case(str(cell_path), seed, options=options)
        _both(monkeypatch, nat, c.pic.image, c.world.camera, c.C_H_G_pred, c.cell.gripper, c.world.jaw_gap_mm)


def test_occluded_and_outside(nat, monkeypatch, cell_path):
    c = case(str(cell_path), 3)
    w = c.world
    p = 0.8 * transform_points(w.C_H_G, w.points_G())[0]
    pic = render_world(w, seed=3, occluders=((p - [2.5, 2.5, 1.0], p + [2.5, 2.5, 1.0], 235.0),))
    res = _both(monkeypatch, nat, pic.image, w.camera, c.C_H_G_pred, c.cell.gripper, w.jaw_gap_mm)
    assert not res.found[0] and "occluded" in res.reasons[0]
    c = case(str(cell_path), 4)
    w2 = type(c.world)(c.cell, 4)
    w2.park()
    w2.disturb_by_angle((0.0, 1.0, 0.0), 3.0)
    pic = render_world(w2, seed=4)
    res = _both(monkeypatch, nat, pic.image, w2.camera, c.world.C_H_G, c.cell.gripper, w2.jaw_gap_mm, search_px=80.0)
    assert not res.found[4] and "outside the picture" in res.reasons[4]


@pytest.mark.parametrize("seed,online", [(0, None), (5, None), (9, None), (2, "tilt"), (3, "cable")])
def test_project_renderer(nat, monkeypatch, cell, seed, online):
    render_mod = pytest.importorskip("selfview.mocks.render")
    from selfview.mocks.world import SimWorld

    w = SimWorld(cell, seed)
    w.park()
    pred = cell.mount_guess_C_H_G
    if online:
        pred = w.C_H_G
        w.unpark()
        w.disturb(online)
    r = render_mod.render(w, seed=seed)
    _both(monkeypatch, nat, r.image, w.camera, pred, cell.gripper, w.jaw_gap_mm)
    _both(monkeypatch, nat, r.image.astype(np.float32), w.camera, pred, cell.gripper, w.jaw_gap_mm)


# --- the kernels one by one --------------------------------------------------------------------------
def _img(seed=0, H=60, W=80):
    return np.random.default_rng(seed).uniform(0, 255, (H, W)).astype(np.float32)


def test_search_profiles_is_bilinear(nat):
    rng = np.random.default_rng(1)
    img = _img()
    R = 7
    st = np.column_stack([rng.uniform(10, 68, 50), rng.uniform(10, 48, 50)])
    st[:5] = np.rint(st[:5])  # samples on whole pixels too
    for pdir in (np.array([0.6, 0.8]), np.array([1.0, 0.0]), np.array([-0.28, 0.96])):
        ph = (np.arange(len(st)) * 0.6180339887) % 1.0 - 0.5
        out = np.empty((len(st), 2 * R + 1))
        nat.search_profiles(img, st, pdir, ph, R, out)
        j = np.arange(-R, R + 1)
        pos = st[:, None, :] + (j[None, :] + ph[:, None])[..., None] * pdir[None, None, :]
        # bilinear grey levels: to a ten-thousandth of an 8-bit step
        np.testing.assert_allclose(out, F._bilinear(img, pos), rtol=0, atol=TOL_GREY)
    with pytest.raises(ValueError, match="outside"):
        nat.search_profiles(img, np.array([[2.0, 30.0]]), np.array([1.0, 0.0]), np.zeros(1), R, np.empty((1, 15)))
    with pytest.raises(TypeError, match="img"):
        nat.search_profiles(img.astype(np.float64), st, pdir, ph, R, np.empty((len(st), 15)))
    with pytest.raises(ValueError, match="out"):
        nat.search_profiles(img, st, pdir, ph, R, np.empty((len(st), 14)))
    with pytest.raises(ValueError, match="ph"):
        nat.search_profiles(img, st, pdir, ph[:-1], R, np.empty((len(st), 15)))


def test_clear_against_numpy(nat):
    rng = np.random.default_rng(2)
    st = np.column_stack([rng.uniform(0, 100, 200), rng.uniform(0, 100, 200)])
    o = np.column_stack([rng.uniform(0, 100, 300), rng.uniform(0, 100, 300)])
    pdir = np.array([0.6, -0.8])
    R = 9
    ok = np.empty(len(st), np.uint8)
    nat.clear(st, o, pdir, float(R), float(F.BLUR_MARGIN), ok)
    ref = F._clear_of(st, o, pdir, R)
    sure = ok != 2
    assert sure.sum() > 150 and np.array_equal(ok[sure] == 1, ref[sure])
    # a point exactly at the margin from a profile: left to numpy
    st1 = np.array([[50.0, 50.0]])
    o1 = np.array([[50.0 + 4.0 * 0.8, 50.0 + 4.0 * 0.6]])  # 4 px off the profile's line, beside its middle
    nat.clear(st1, o1, pdir, float(R), 4.0, ok[:1])
    assert ok[0] == 2
    # the search's use: unsure rows decided by numpy
    st2 = np.vstack([st, st1])
    o2 = np.vstack([o, o1])
    clear = np.empty(len(st2), np.uint8)
    nat.clear(st2, o2, pdir, float(R), 4.0, clear)
    unsure = clear == 2
    clear[unsure] = F._clear_of(st2[unsure], o2, pdir, R)
    assert np.array_equal(clear == 1, F._clear_of(st2, o2, pdir, R))
    with pytest.raises(ValueError, match="ok"):
        nat.clear(st, o, pdir, float(R), 4.0, np.empty(3, np.uint8))
    with pytest.raises(ValueError, match="R, margin"):
        nat.clear(st, o, pdir, -1.0, 4.0, ok)
    with pytest.raises(ValueError, match="others"):
        nat.clear(st, o[:, :1].copy(), pdir, float(R), 4.0, ok)


def test_template_sums_in_order(nat, monkeypatch):
    rng = np.random.default_rng(3)
    G = rng.normal(0, 30, (2, 70, 90)).astype(np.float32)
    normals = np.array([[0.6, 0.8], [-1.0, 0.0], [0.28, -0.96]], np.float32)
    span = 12
    pts = [np.column_stack([rng.integers(0, 90 - 2 * span - 1, 40), rng.integers(0, 70 - 2 * span - 1, 40)])
           for _ in range(3)]
    groups = [0, 0, 1]
    monkeypatch.setattr(_native, "track", nat)
    a = F._template_score(G, pts, normals, groups, span)
    monkeypatch.setattr(_native, "track", None)
    b = F._template_score(G, pts, normals, groups, span)
    # exactly: element-wise float32 additions in the same order (nothing to fuse or reorder), by construction
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    out = np.zeros((25, 25), np.float32)
    with pytest.raises(ValueError, match="q: point"):
        nat.template_sums(G[0], np.array([[80, 0]], np.int64), 25, out)
    with pytest.raises(ValueError, match="q: point"):
        nat.template_sums(G[0], np.array([[-1, 0]], np.int64), 25, out)
    with pytest.raises(TypeError, match="q"):
        nat.template_sums(G[0], np.array([[1, 0]], np.int32), 25, out)


def test_unique_rows_is_numpys():
    rng = np.random.default_rng(4)
    for a in (rng.integers(-50, 50, (300, 2)), rng.integers(0, 3, (40, 2)), np.zeros((0, 2), int),
              np.array([[5, -7]])):
        assert np.array_equal(F._unique_rows(a), np.unique(a, axis=0))
