"""The silhouette fit's compiled kernel (``selfview.measurement._csil``) against its numpy code.

Both must give the same measurement: on the same frames, both renderers, plain and over a photograph,
tracked and searched, the corners within CORNER_TOL_PX and the fitted pose's TCP within TCP_TOL_MM, the
same verdict (found or lost) and the same number of samples. The tolerances are tight enough to catch a
changed decision and loose enough for a reordered sum: the corners' own noise is ~0.02 px and the TCP's
~0.005 mm, so 0.01 px and 1e-4 mm lie far below anything physical, while a different candidate, weight
or step moves a corner by 0.05 px or more; the kernel's sums in another order differ by ~1e-9 px. The
kernel's sampling, candidates, IRLS and vote are also compared with their numpy code step by step.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

import selfview.measurement.silhouette as sil
from selfview.measurement import _native
from selfview.files.cell import default_cell_path, load_cell
from selfview.measurement.fingers import model_measurement
from selfview.maths.geometry import inv_H, make_H
from selfview.measurement.fingers import WIDE_ROUNDS, SilhouetteTracker
from tests import clutter_scenes as clutter

CORNER_TOL_PX = 0.01
TCP_TOL_MM = 1e-4
KERNEL = _native.sil
needs_kernel = pytest.mark.skipif(KERNEL is None, reason="the compiled kernel selfview.measurement._csil is not built")


@functools.lru_cache(maxsize=None)
def _cell():
    return load_cell(default_cell_path())


@functools.lru_cache(maxsize=None)
def _sequence(renderer: str, photo: str | None):
    return clutter.online_sequence(_cell(), renderer, photo, "cable", 131, 40.0, 1.5, steps=3)


def _run(seq, kernel, monkeypatch):
    """The tracker over the sequence, then searches of the last frame (the default rounds from the last
    frame's prediction, and the wide rounds from the mount before the disturbance)."""
    monkeypatch.setattr(_native, "sil", kernel)
    cell = _cell()
    tr = SilhouetteTracker(seq.camera, cell.gripper, points=range(4))
    out = []
    for fr in seq.frames:
        res = tr.find(fr.image, seq.C_H_G_pred, seq.gap)
        out.append((res, tr.last_fit))
    last = seq.frames[-1].image
    for rounds in (None, WIDE_ROUNDS):
        out.append(model_measurement(last, seq.camera, seq.C_H_G_pred, cell.gripper, seq.gap, range(4),
                                     rounds=rounds))
    return out, tr.tracked_frames


@needs_kernel
@pytest.mark.parametrize("renderer,photo", [("mocks", None), ("mocks", "gravel"), ("alt", None), ("alt", "coffee")])
def test_kernel_fit_matches_the_numpy_fit(renderer, photo, monkeypatch):
    seq = _sequence(renderer, photo)
    ref, tracked_ref = _run(seq, None, monkeypatch)
    fast, tracked_fast = _run(seq, KERNEL, monkeypatch)
    assert tracked_ref == tracked_fast and tracked_fast >= 2
    for (r0, f0), (r1, f1) in zip(ref, fast):
        assert (r0.lost is None) == (r1.lost is None)
        assert np.array_equal(r0.found, r1.found)
        assert f0.ok == f1.ok and f0.n_samples == f1.n_samples
        if r0.lost is None:
            assert np.all(np.linalg.norm(r0.uv[r0.found] - r1.uv[r1.found], axis=1) < CORNER_TOL_PX)
            assert np.all(np.abs(r0.C_H_G[:3, 3] - r1.C_H_G[:3, 3]) < TCP_TOL_MM)
            assert abs(f0.good_fraction - f1.good_fraction) <= 1.0 / f0.n_samples
            assert abs(f0.rms_px - f1.rms_px) < 1e-3


def test_an_8_bit_frame_fits_as_its_float_copy(monkeypatch):
    """A grabber's 8-bit frame skips the picture's checks on either path and gives the fit of its float32
    copy (the same grey levels)."""
    seq = _sequence("mocks", None)
    cell = _cell()
    fr = seq.frames[1]
    assert fr.image.dtype == np.uint8
    for kernel in (None, KERNEL):
        monkeypatch.setattr(_native, "sil", kernel)
        a = sil.fit_silhouette(fr.image, seq.camera, fr.C_H_G, cell.gripper, seq.gap, rounds=(8.0, 3.0), frame=True)
        b = sil.fit_silhouette(fr.image.astype(np.float32), seq.camera, fr.C_H_G, cell.gripper, seq.gap,
                               rounds=(8.0, 3.0))
        assert a.ok and b.ok and a.n_samples == b.n_samples
        assert np.abs(a.C_H_G[:3, 3] - b.C_H_G[:3, 3]).max() < TCP_TOL_MM


@needs_kernel
def test_kernel_steps_match_their_numpy_code_on_one_frame(monkeypatch):
    """Each kernel step on the same input as its numpy code: the candidates (offsets to 1e-4 px, the same
    ones missing), the vote (at most one vote apart per cell: n . d rounded otherwise), the IRLS (the
    pose's TCP to TCP_TOL_MM, the weights to 1e-6)."""
    cell = _cell()
    seq = _sequence("alt", "coffee")
    fr = seq.frames[2]
    img = fr.image.astype(np.float32)
    boxes = cell.gripper.finger_boxes_G(seq.gap)
    H0 = fr.C_H_G.copy()
    H0[:3, 3] += (0.3, -0.2, 0.5)  # a start some px off
    app = sil.learn_appearance(img, seq.camera, fr.C_H_G, cell.gripper, seq.gap)
    es = sil._visible_edges(boxes, H0)
    s = sil._sample(seq.camera, es, boxes, H0, margin=sil.BORDER_PX)
    assert len(s.edge) > 100
    for R, n in ((8.0, sil.CANDIDATES), (24.0, 8)):
        a = sil._candidates_np(img, s, R, app, n)
        b = sil._candidates(img, s, R, app, n)
        for x, y in zip(a, b):
            assert np.array_equal(np.isnan(x), np.isnan(y))
            assert np.nanmax(np.abs(x - y)) < 1e-4
        off = b[0]
        g = np.arange(-R, R + 1.0, 2.0)
        dx, dy = np.meshgrid(g, g)
        d = np.column_stack([dx.ravel(), dy.ravel()])
        votes = np.empty(len(d), np.int64)
        KERNEL.vote(off.astype(float), s.n, g, 1.5, votes)
        ref_votes = sil._votes_py(off, np.isfinite(off), s.n @ d.T, 1.5)
        assert np.abs(votes - ref_votes).max() <= 1 and votes.max() > 0.5 * len(off)
    off, _, _ = sil._candidates(img, s, 8.0, app)
    q = sil._undistorted(seq.camera, s, off)
    Hb, wb, rb, pb, Jb, sb = sil._solve(seq.camera, es, s, q, H0, 0.35, iters=6, start_floor=1.3)
    Hc, wc, rc, pc, Jc, sc = sil._solve_py(seq.camera, es, s, q, H0, 0.35, iters=6, start_floor=1.3)
    assert np.abs(Hb[:3, 3] - H0[:3, 3]).max() > 0.05  # the fit did move the pose
    assert np.abs(Hc[:3, 3] - Hb[:3, 3]).max() < TCP_TOL_MM and np.array_equal(pb, pc)
    assert np.abs(wb - wc).max() < 1e-6 and abs(sb - sc) < 1e-6
    assert np.allclose(Jb, Jc, rtol=1e-6, atol=1e-9 * np.abs(Jb).max())


@pytest.mark.skipif(_native.sil is None, reason="the compiled kernel selfview.measurement._csil is not built")
def test_the_kernel_refuses_bad_arguments_by_name():
    k = _native.sil
    S, C, E = 20, 3, 2
    q = np.zeros((S, C, 2))
    pos = np.zeros(S, np.int64)
    ab = np.ones((E, 3))
    H = np.eye(4)
    outs = (np.empty((4, 4)), np.empty(S), np.empty(S), np.empty(S, np.int64), np.empty((6, 6)))
    with pytest.raises(TypeError, match="pos: expected a int64 array"):
        k.solve(q, pos.astype(np.int32), ab, ab, H, 800.0, 0.35, 6, -1.0, *outs)
    with pytest.raises(ValueError, match="pos: sample 3 names edge 7"):
        bad = pos.copy()
        bad[3] = 7
        k.solve(q, bad, ab, ab, H, 800.0, 0.35, 6, -1.0, *outs)
    with pytest.raises(ValueError, match="w: dimension 0 is 19"):
        k.solve(q, pos, ab, ab, H, 800.0, 0.35, 6, -1.0, outs[0], np.empty(S - 1), *outs[2:])
    with pytest.raises(TypeError, match="q: expected a C-contiguous"):
        k.solve(q[:, ::-1], pos, ab, ab, H, 800.0, 0.35, 6, -1.0, *outs)
    with pytest.raises(ValueError, match="votes: dimension 0 is 8"):
        k.vote(np.zeros((S, C)), np.zeros((S, 2)), np.arange(3.0), 1.5, np.empty(8, np.int64))
    # no sample with a candidate: the reference's early return (weights zero), code 1
    code, sigma = k.solve(np.full((S, C, 2), np.nan), pos, ab, ab, H, 800.0, 0.35, 6, -1.0, *outs)
    assert code == 1 and not outs[1].any() and np.array_equal(outs[0], H)


# --- the kernel's sampling and candidates against their numpy code ------------------------------------------
# Tolerances with a physical meaning: positions to 1e-6 px (a millionth of a pixel: rounding of sums taken in
# another order, nothing a changed formula would stay within); normals to 1e-9 (their angle in rad); grey
# levels to 1e-3 (a thousandth of an 8-bit picture's step: the kernel reads the profile as cv2.remap does, at
# 1/32 px with single-precision weights); a candidate's offset to 1e-4 px (the parabola through those levels).
POS_TOL_PX = 1e-6
LEVEL_TOL_GREY = 1e-3
OFFSET_TOL_PX = 1e-4



def _poses(seq):
    """The sequence's true poses and, for each, one some px off (a start the fit corrects)."""
    out = []
    for k, fr in enumerate(seq.frames):
        H = fr.C_H_G.copy()
        out.append(H)
        H2 = sil._motion(np.array([0.004, -0.003, 0.002, 0.4, -0.3, 0.6]) * (1 + k)) @ H
        out.append(H2)
    return out


@needs_kernel
@pytest.mark.parametrize("kappa,skew", [(None, 0.0), (0.0, 0.0), (6e-7, 0.0), (-1.5e-7, 0.0), (None, 1e-3), (None, -8e-4)])
def test_kernel_samples_match_the_numpy_sampling(kappa, skew, monkeypatch):
    """The samples along the visible edges (which ones, where, their normals) from the kernel and from
    ``_sample_py``, on the poses of a disturbed sequence and poses some px off, with the cell's lens and
    with barrel, pincushion and no distortion, and with a grabber's shear (skew: 0.58 and 0.46 px over the
    picture's height): the kernel's own projection against camera.project."""
    cell = _cell()
    seq = _sequence("mocks", None)
    cam = (seq.camera if kappa is None else seq.camera.with_(kappa=kappa)).with_(skew=skew)
    boxes = cell.gripper.finger_boxes_G(seq.gap)
    checked = 0
    for H in _poses(seq):
        es = sil._visible_edges(boxes, H)
        a = sil._sample(cam, es, boxes, H, margin=sil.BORDER_PX)
        b = sil._sample_py(cam, es, boxes, H, margin=sil.BORDER_PX)
        assert np.array_equal(a.edge, b.edge) and len(a.edge) > 100
        assert np.abs(a.uv - b.uv).max() < POS_TOL_PX
        assert np.abs(a.p_G - b.p_G).max() < 1e-9  # mm
        assert np.abs(a.n - b.n).max() < 1e-9
        checked += len(a.edge)
    assert checked > 1000
    # one finger behind the other: the camera beside the gripper, looking along the jaws' axis
    for c_G in ((110.0, 3.0, -30.0), (120.0, 10.0, -50.0), (100.0, -8.0, -20.0)):
        H = _looking_at(c_G, (0.0, 0.0, -35.0))
        es = sil._visible_edges(boxes, H)
        a = sil._sample(cam, es, boxes, H, margin=sil.BORDER_PX)
        b = sil._sample_py(cam, es, boxes, H, margin=sil.BORDER_PX)
        assert np.array_equal(a.edge, b.edge) and len(a.edge) > 100
        assert np.abs(a.uv - b.uv).max() < POS_TOL_PX and np.abs(a.n - b.n).max() < 1e-9
        # the other finger hid some of them: fewer than the samples in the picture
        with monkeypatch.context() as m:
            m.setattr(sil, "_blocked", lambda o, d, lo, hi: np.zeros(len(d), bool))
            assert len(a.edge) < len(sil._sample_py(cam, es, boxes, H, margin=sil.BORDER_PX).edge) - 50


def _looking_at(c_G, target_G):
    """C_H_G of a camera at c_G (G, mm) looking at target_G, its y axis in G's z-up plane."""
    c = np.asarray(c_G, float)
    z = np.asarray(target_G, float) - c
    z /= np.linalg.norm(z)
    x = np.cross((0.0, 0.0, 1.0), z)
    x /= np.linalg.norm(x)
    return inv_H(make_H(np.column_stack([x, np.cross(z, x), z]), c))


@needs_kernel
def test_kernel_hands_points_it_does_not_project_to_the_python_code():
    """A lens whose field of view ends inside the picture (kappa < 0, the model's points beyond the fold):
    the kernel refuses (-1) and ``_sample`` raises what camera.project raises."""
    from selfview.errors import CalibrationError

    cell = _cell()
    seq = _sequence("mocks", None)
    cam = seq.camera.with_(kappa=-8e-6)
    boxes = cell.gripper.finger_boxes_G(seq.gap)
    H = seq.frames[0].C_H_G
    es = sil._visible_edges(boxes, H)
    n = len(es.a_G) * 400
    outs = (np.empty((n, 3)), np.empty(n, np.int64), np.empty((n, 2)), np.empty((n, 2)))
    assert _native.sil.sample(es.a_G, es.b_G, es.d_in, es.finger, es.box, H, sil._cam_params(cam), 3.0, 4.0,
                              *outs) == -1
    with pytest.raises(CalibrationError, match="beyond the lens's field of view"):
        sil._sample(cam, es, boxes, H, margin=sil.BORDER_PX)
    p_G6 = cell.gripper.points_G(gap=seq.gap)
    box = np.asarray(boxes, float)
    with pytest.raises(CalibrationError, match="beyond the lens's field of view"):
        sil._points_seen(cam, H, p_G6, box)


@needs_kernel
@pytest.mark.parametrize("renderer,photo,skew", [("mocks", None, 0.0), ("mocks", "gravel", 0.0), ("alt", None, 0.0),
                                                 ("alt", "coffee", 0.0), ("mocks", "gravel", 8e-4)])
def test_kernel_candidates_match_the_numpy_candidates(renderer, photo, skew):
    """The candidates along each sample's normal from the kernel (8-bit and float32 pictures) and from
    ``_candidates_np`` + ``camera.undistort_pixels``, on pictures of both renderers, plain and over a
    photograph, with learnt faces' levels and without, for the ranges of the tracker, of the fit's rounds
    and of the vote, and with a grabber's shear in the camera: the same candidates missing, offsets, levels
    and contrasts, undistorted coordinates."""
    cell = _cell()
    seq = _sequence(renderer, photo)
    if skew:
        seq = dataclasses.replace(seq, camera=seq.camera.with_(skew=skew))
    boxes = cell.gripper.finger_boxes_G(seq.gap)
    fr = seq.frames[-1]
    app = sil.learn_appearance(fr.image, seq.camera, fr.C_H_G, cell.gripper, seq.gap)
    assert app.levels
    found = 0
    for H in _poses(seq)[-2:]:
        es = sil._visible_edges(boxes, H)
        s = sil._sample(seq.camera, es, boxes, H, margin=sil.BORDER_PX)
        for R, n, a in ((3.0, sil.CANDIDATES, app), (8.0, sil.CANDIDATES, app), (24.0, 8, app),
                        (10.0, sil.CANDIDATES, sil.Appearance())):
            ref = sil._candidates_np(fr.image.astype(np.float32), s, R, a, n)
            q_ref = sil._undistorted(seq.camera, s, ref[0])
            for img in (fr.image, fr.image.astype(np.float32)):
                off, face, con, q = sil._candidates_q(img, s, R, a, seq.camera, n)
                assert off.shape == ref[0].shape
                assert np.array_equal(np.isnan(off), np.isnan(ref[0]))
                assert np.nanmax(np.abs(off - ref[0])) < OFFSET_TOL_PX
                assert np.nanmax(np.abs(face - ref[1])) < LEVEL_TOL_GREY
                assert np.nanmax(np.abs(con - ref[2])) < LEVEL_TOL_GREY
                assert np.array_equal(np.isnan(q), np.isnan(q_ref))
                assert np.nanmax(np.abs(q - q_ref)) < POS_TOL_PX
            found += int(np.isfinite(ref[0]).sum())
    assert found > 1000


@needs_kernel
def test_kernel_sampling_refuses_bad_arguments_by_name():
    k = _native.sil
    E, n = 4, 4 * 400
    ab = np.ones((E, 3))
    fin = np.zeros(E, np.int64)
    box = np.zeros((2, 2, 3))
    cam = np.array([962.0, 0.0, 383.5, 287.5, 1.0, 768.0, 576.0, 0.0])
    outs = (np.empty((n, 3)), np.empty(n, np.int64), np.empty((n, 2)), np.empty((n, 2)))
    with pytest.raises(ValueError, match="p: room for 1599 samples"):
        k.sample(ab, ab, ab, fin, box, np.eye(4), cam, 3.0, 4.0, np.empty((n - 1, 3)), np.empty(n - 1, np.int64),
                 np.empty((n - 1, 2)), np.empty((n - 1, 2)))
    with pytest.raises(ValueError, match="finger: edge 2 names finger 5"):
        bad = fin.copy()
        bad[2] = 5
        k.sample(ab, ab, ab, bad, box, np.eye(4), cam, 3.0, 4.0, *outs)
    with pytest.raises(ValueError, match="cam: expected f, aspect"):
        k.sample(ab, ab, ab, fin, box, np.eye(4), cam * np.r_[-1, np.ones(7)], 3.0, 4.0, *outs)
    with pytest.raises(ValueError, match="cam: dimension 0 is 7, expected 8"):  # a camera without its skew
        k.sample(ab, ab, ab, fin, box, np.eye(4), cam[:7].copy(), 3.0, 4.0, *outs)
    S, C = 10, 3
    args = (np.zeros((S, 2)), np.zeros((S, 2)), np.zeros(S), np.zeros(S), 8.0,
            np.array([3.0, 8.0, 0.18, 12.0]), cam)
    res = (np.empty((S, C)), np.empty((S, C)), np.empty((S, C)), np.empty((S, C, 2)))
    with pytest.raises(TypeError, match="img: expected a float32 array"):
        k.candidates(np.zeros((5, 5)), *args, *res)
    with pytest.raises(ValueError, match="q: dimension 1 is 2"):
        k.candidates(np.zeros((5, 5), np.float32), *args, *res[:3], np.empty((S, 2, 2)))
    with pytest.raises(ValueError, match="uv, nrm: sample 4 is not finite"):
        uv = np.zeros((S, 2))
        uv[4, 1] = np.nan
        k.candidates(np.zeros((5, 5), np.uint8), uv, *args[1:], *res)


def test_the_numpy_pieces_keep_their_definitions():
    """The numpy path's faster forms of three small pieces give what their plain definitions give: Tukey's
    scale is 1.4826 times ``np.median`` of |r| (odd and even counts), the step's rotation is
    ``geometry.R_from_rotvec``'s, and a ray blocked by a box is judged as the slab test's nan-aware form
    judges it (a ray along a face's plane included)."""
    from selfview.maths.geometry import R_from_rotvec
    from selfview.measurement.fingertips import tukey_weights

    rng = np.random.default_rng(5)
    for n in (1, 2, 7, 12, 518):
        r = rng.normal(scale=0.7, size=n)
        w, s = tukey_weights(r, 0.0)
        assert s == 1.4826 * float(np.median(np.abs(r)))
        u = r / (4.685 * s)
        assert np.array_equal(w, np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0))
    for v in ([1e-3, -2e-3, 5e-4], [0.0, 0.0, 0.0], [0.4, -1.1, 2.0]):
        assert np.allclose(sil._motion(np.r_[v, 1.0, 2.0, 3.0])[:3, :3], R_from_rotvec(v), atol=1e-15)
    lo, hi = np.zeros(3), np.ones(3)
    o = np.array([-1.0, 0.5, 0.5])
    d = np.array([[3.0, 0.0, 0.0],  # through the box
                  [0.5, 0.0, 0.0],  # stops before it
                  [3.0, 0.0, 0.5],  # through it, leaving by the top face
                  [3.0, 0.0, 0.0]])  # as the first, from a point in the plane y = 0 of a face (below)
    o4 = np.tile(o, (4, 1))
    o4[3] = (-1.0, 0.0, 0.5)  # along the face y = 0: 0 / 0 on y, bounded by x and z alone
    assert sil._blocked(o4, d, lo, hi).tolist() == [True, False, True, True]
