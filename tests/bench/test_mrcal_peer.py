"""bench/_mrcal_peer.py: mrcal run as the intrinsics benchmark's peer in whichever interpreter has it.

Without mrcal the peer says so (None), never a figure. Where an interpreter with mrcal is found (Debian's
python3-mrcal), its fit of exact observations of a known pinhole camera must return that camera: the plumbing
(grid indices from the plate coordinates, pose seeds, units, the sigma recipe) is what is tested.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from selfview.bench import _mrcal_peer as P
from selfview.maths.camera import CameraModel
from selfview.maths.geometry import R_from_rpy, make_H


def test_without_mrcal_the_peer_says_none(monkeypatch):
    monkeypatch.setenv("SELFVIEW_MRCAL_PYTHON", sys.executable)
    try:
        import mrcal  # noqa: F401
        pytest.skip("this interpreter has mrcal")
    except ImportError:
        pass
    assert P.find_python() is None
    cam = CameraModel(f=950.0, kappa=0.0, cx=383.5, cy=287.5, aspect=1.0, width=768, height=576)
    assert P.fit([np.zeros((4, 3))], [np.zeros((4, 2))], 15.0, cam, (768, 576)) is None


def test_grid_indices_from_plate_coordinates():
    pitch = 15.0
    a = np.array([[30.0, 45.0, 0.0], [45.0, 45.0, 0.0]])
    b = np.array([[30.0 + 1e-3, 150.0, 0.0]])  # a bias-corrected centre a micrometre off still maps
    idx, W, H = P._grid([a, b], pitch)
    assert [i.tolist() for i in idx] == [[[0, 0], [1, 0]], [[0, 7]]]
    assert (W, H) == (2, 8)


def _pinhole_views(fx, fy, cx, cy, pitch=15.0, n=8):
    """Exact projections of an 8x8 grid seen from ``n`` tilted poses; the corner discs of each view
    dropped (as the fingers hide some)."""
    g = np.array([(i * pitch, j * pitch, 0.0) for j in range(8) for i in range(8)])
    rng = np.random.default_rng(5)
    p_W, uv = [], []
    for k in range(n):
        R = R_from_rpy(*np.deg2rad(rng.uniform(-30, 30, 3)))
        H = make_H(R, np.array([0, 0, 260.0]) - R @ np.array([52.5, 52.5, 0.0]))  # the grid's centre 260 mm ahead
        X = g @ H[:3, :3].T + H[:3, 3]
        u = np.column_stack([fx * X[:, 0] / X[:, 2] + cx, fy * X[:, 1] / X[:, 2] + cy])
        keep = np.ones(len(g), bool)
        keep[[0, 7, 56, 63][k % 4]] = False
        p_W.append(g[keep])
        uv.append(u[keep])
    return p_W, uv


def test_mrcal_recovers_a_known_pinhole_camera():
    python = P.find_python()
    if python is None:
        pytest.skip("no interpreter with mrcal (Debian's python3-mrcal)")
    fx, fy, cx, cy = 900.0, 945.0, 392.0, 281.0
    p_W, uv = _pinhole_views(fx, fy, cx, cy)
    guess = CameraModel(f=950.0, kappa=0.0, cx=383.5, cy=287.5, aspect=1.0, width=768, height=576)
    r = P.fit(p_W, uv, 15.0, guess, (768, 576), python=python)
    # exact observations: a hundredth of a pixel on the centre, 1e-4 relative on f and aspect
    assert abs(r["cx"] - cx) < 0.01 and abs(r["cy"] - cy) < 0.01
    assert abs(r["f"] / fy - 1) < 1e-4 and abs(r["aspect"] / (fy / fx) - 1) < 1e-4
    assert r["rms_px"] < 0.01 and all(np.isfinite(v) for v in r["sigma"].values())


def test_discs_off_the_pitch_grid_are_refused_by_view():
    pitch = 15.0
    a = np.array([[0.0, 0.0, 0.0], [15.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="view 1: a disc lies 0.40 pitch off"):
        P._grid([a, np.array([[6.0, 0.0, 0.0]])], pitch)
    with pytest.raises(ValueError, match="view 0: two discs at one grid place"):
        P._grid([np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])], pitch)
