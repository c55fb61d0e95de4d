"""The compiled Gauss-Newton of NP-I and NP-R (``selfview._cnpu.np_i``) against the pure-Python
reference, ``online._gauss_newton`` reached through ``iterative_update`` and ``recalibrate``.

Every test runs the same call twice: with the kernel, and with ``selfview._native.npu`` set to None.
The kernel repeats the reference's iteration (the same linearisation, damping rule, Cholesky solve
and stopping rule), so when both take the same number of steps their estimates agree to the rounding
of the normal equations. Near the minimum the reference's damping rule reacts to cost changes at the
rounding level, so the two may now and then take a different number of steps; both have then stopped
within a tiny fraction of the pixel noise of the same minimum, which is what is asserted. A call the
kernel hands back gives the reference's estimate or error exactly.

Where the kernel is not built the module is skipped (or fails under ``SELFVIEW_REQUIRE_NATIVE=1``),
as ``test_native_npu``, whose scenes and helpers it shares.
"""

from __future__ import annotations

import math
import pickle
import sys
import tracemalloc

import numpy as np
import pytest

from selfview import _native, online
from selfview.cell import POINT_NAMES
from selfview.errors import CalibrationError
from selfview.geometry import transform_points
from selfview.online import MAX_CONDITION, MotionEstimate, differential_update, iterative_update, recalibrate
from tests.selfview.test_native_npu import (
    FIELDS,
    FORMS,
    NPU,
    _Camera,
    _RaisingCamera,
    _ref,
    assert_same_outcome,
    outcome,
    same_kind,
    scene,
)


class Spy:
    """Stands in for the kernel module: calls np_i and records whether it handled each call."""

    def __init__(self):
        self.handled: list[bool] = []

    def np_u(self, *args):
        return NPU.np_u(*args)

    def np_i(self, *args):
        out = NPU.np_i(*args)
        self.handled.append(out is not None)
        return out


def run_both(monkeypatch, solver, *args, **kwargs):
    """(outcome with the kernel, outcome of the pure-Python reference, [handled by the kernel?])."""
    spy = Spy()
    monkeypatch.setattr(_native, "npu", spy)
    native = outcome(solver, *args, **kwargs)
    monkeypatch.setattr(_native, "npu", None)
    reference = outcome(solver, *args, **kwargs)
    monkeypatch.setattr(_native, "npu", NPU)
    return native, reference, spy.handled


def gauss_newton_step_mm(H, P, uv, cam) -> float:
    """How far [mm] one more undamped Gauss-Newton step of the reference would move the points from
    the pose H: zero at the exact minimum (a check that needs neither path's own stopping rule)."""
    obs = online._undistort(cam, np.asarray(uv, float).tolist())
    pts, Jr = online._linearise(H[:3].tolist(), np.asarray(P, float).tolist(), obs, cam.f, "test")
    step = np.linalg.solve(Jr[:, :6].T @ Jr[:, :6], Jr[:, :6].T @ Jr[:, 6])
    return online._largest_move(pts, *step.tolist())


def check_agreement(native: MotionEstimate, reference: MotionEstimate, P, uv, cam, prior=None, tol=1e-9):
    for name in FIELDS:
        same_kind(getattr(native, name), getattr(reference, name), name)
    assert native.method == reference.method and native.points_used == reference.points_used
    assert native.C_H_G_orth is native.C_H_G
    assert np.array_equal(native.C_H_G_prior, reference.C_H_G_prior)
    if native.iterations == reference.iterations:
        # the same steps: agreement far below the data's noise but not at one CPU's rounding (the kernel may
        # fuse multiply-adds, numpy's BLAS sums in its own order): the pose's rotation entries to 1e-9
        # (1e-9 rad) and its translation to 1e-9 mm, the motion (rad, mm) likewise, pixels to 1e-6 px,
        # the condition number and covariance relative 1e-6
        tol_H, tol_motion, tol_px, tol_rel = 1e-9, 1e-9, 1e-6, 1e-6
    else:  # stopped elsewhere within the tolerance of the same minimum
        tol_H, tol_motion, tol_px, tol_rel = 1e-7, 1e-5, 1e-5, 1e-5
    assert np.abs(native.C_H_G - reference.C_H_G).max() <= tol_H
    assert np.abs(native.motion - reference.motion).max() <= tol_motion
    assert abs(native.delta_deg - reference.delta_deg) <= math.degrees(tol_motion) * 2
    assert abs(native.d_mm - reference.d_mm) <= tol_motion * 2
    assert np.abs(native.residuals_px - reference.residuals_px).max() <= tol_px
    assert abs(native.rms_px - reference.rms_px) <= tol_px
    assert native.condition == pytest.approx(reference.condition, rel=tol_rel)
    if math.isnan(reference.covariance[0, 0]):
        assert np.isnan(native.covariance).all()
    elif reference.rms_px < 1e-6 and prior is None:  # exact data: both covariances are rounding noise, and tiny
        assert np.abs(native.covariance).max() < 1e-12 and np.abs(reference.covariance).max() < 1e-12
    else:
        scale = np.abs(reference.covariance).max()
        assert np.abs(native.covariance - reference.covariance).max() <= tol_rel * scale
    # the kernel's pose is the minimum: one more full step would move no point by a nanometre
    assert gauss_newton_step_mm(native.C_H_G, P, uv, cam) < max(1e-6, 10.0 * tol)
    R = native.C_H_G[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12 and np.array_equal(native.C_H_G[3], [0, 0, 0, 1])


@pytest.mark.parametrize("n", [3, 4, 5, 6])
def test_np_i_agrees_with_the_python_code(monkeypatch, n):
    rng = np.random.default_rng(200 + n)
    handled = same_steps = 0
    cases = 80
    for i in range(cases):
        H0, P, uv, cam = scene(rng, n)
        to = FORMS[list(FORMS)[i % len(FORMS)]]
        names = None if rng.random() < 0.7 else [f"p{j}" for j in range(n)]
        prior = None if rng.random() < 0.8 else 0.05
        native, reference, used = run_both(monkeypatch, iterative_update, to(H0), to(P), to(uv), cam, names,
                                           prior_sigma_px=prior)
        if used != [True]:
            assert used in ([False], [])
            assert_same_outcome(native, reference)
            continue
        handled += 1
        same_steps += native.iterations == reference.iterations
        assert native.method == f"{n}P-I"
        assert native.points_used == (POINT_NAMES[:n] if names is None else tuple(names))
        check_agreement(native, reference, np.asarray(to(P), float), np.asarray(to(uv), float), cam, prior)
    assert handled >= 0.8 * cases
    assert same_steps >= 0.8 * handled


@pytest.mark.parametrize("n", [4, 5, 6])
def test_np_r_refinement_agrees_with_the_python_code(monkeypatch, n):
    """NP-R: the same IPPE (or SQPnP for points off their plane) start, then the kernel's iteration."""
    rng = np.random.default_rng(300 + n)
    handled = 0
    cases = 60
    for i in range(cases):
        H0, P, uv, cam = scene(rng, n)
        to = FORMS[list(FORMS)[i % len(FORMS)]]
        native, reference, used = run_both(monkeypatch, recalibrate, to(H0), to(P), to(uv), cam)
        if used != [True]:
            assert_same_outcome(native, reference)
            continue
        handled += 1
        assert native.method == f"{n}P-R"
        check_agreement(native, reference, np.asarray(to(P), float), np.asarray(to(uv), float), cam)
    assert handled >= 0.8 * cases


def test_np_i_from_a_non_orthogonal_prior(monkeypatch):
    """After an NP-U update (eq. 13 leaves the rotation non-orthogonal) the kernel starts from its
    nearest rotation, as the reference does, and measures the motion from the non-orthogonal prior."""
    rng = np.random.default_rng(7)
    handled = 0
    for _ in range(20):
        H0, P, uv, cam = scene(rng, 4)
        try:
            H_u = differential_update(H0, P, uv, cam).C_H_G
        except CalibrationError:
            continue
        assert np.abs(H_u[:3, :3].T @ H_u[:3, :3] - np.eye(3)).max() > 1e-9
        native, reference, used = run_both(monkeypatch, iterative_update, H_u, P, uv, cam)
        if used == [True]:
            check_agreement(native, reference, P, uv, cam)
            handled += 1
        else:
            assert_same_outcome(native, reference)
    assert handled >= 10  # the kernel took most of them: the test is not vacuous


def test_exact_data_recovers_the_disturbance(monkeypatch):
    """Noise-free points of a camera turned by up to 10 degrees: the kernel finds the truth to 1e-9 mm."""
    rng = np.random.default_rng(11)
    from selfview.mocks.world import SimWorld
    from tests.selfview.test_native_npu import CELL

    for k in range(10):
        world = SimWorld(CELL, seed=400 + k)
        before = world.C_H_G
        world.disturb_by_angle(rng.normal(size=3), float(rng.uniform(0.5, 10.0)), pivot_C=[0.0, -15.0, -20.0])
        P = world.points_G()[:4]
        uv = world.camera.project(transform_points(world.C_H_G, P))
        spy = Spy()
        monkeypatch.setattr(_native, "npu", spy)
        est = iterative_update(before, P, uv, world.camera)
        assert spy.handled == [True]
        assert np.abs(transform_points(est.C_H_G, P) - transform_points(world.C_H_G, P)).max() < 1e-9
        assert est.rms_px < 1e-9


# --- unusual input: the reference's outcome ------------------------------------------------------------
def _cases():
    H0, P6, cam = _ref()
    P = P6[:4]
    uv = cam.project(transform_points(H0, P))
    cases = {}

    def add(name, solver, *args, **kwargs):
        cases[name] = (solver, args, kwargs)

    for solver, tag in ((iterative_update, "I"), (recalibrate, "R")):
        add(f"{tag} normal", solver, H0, P, uv, cam)
        add(f"{tag} 2 points", solver, H0, P[:2], uv[:2], cam)
        line = np.array([[28.0, -6.0, 0.0], [0.0, -6.0, 0.0], [-28.0, -6.0, 0.0], [14.0, -6.0, 0.0]])
        add(f"{tag} collinear", solver, H0, line, cam.project(transform_points(H0, line)), cam)
        bad_uv = uv.copy()
        bad_uv[1, 1] = np.nan
        add(f"{tag} NaN in uv", solver, H0, P, bad_uv, cam)
        add(f"{tag} no convergence in 1 step", solver, H0, P, uv + 3.0, cam, max_iter=1)
        add(f"{tag} names too few", solver, H0, P, uv, cam, names=["a"])
        add(f"{tag} list input", solver, H0.tolist(), P.tolist(), uv.tolist(), cam)
        far_away = H0.copy()
        far_away[2, 3] = 1e5
        add(f"{tag} far-away patch", solver, far_away, P, cam.project(transform_points(far_away, P)), cam)
    add("I 3 points", iterative_update, H0, P[:3], uv[:3], cam)
    add("R 3 points", recalibrate, H0, P[:3], uv[:3], cam)
    behind = H0.copy()
    behind[2, 3] = -110.0
    add("I behind the camera", iterative_update, behind, P, uv, cam)
    add("I max_iter 0", iterative_update, H0, P, uv, cam, max_iter=0)
    add("I max_iter a float", iterative_update, H0, P, uv, cam, max_iter=5.0)
    add("I tol an int", iterative_update, H0, P, uv + 1.0, cam, tol=1)
    add("I tol 0", iterative_update, H0, P, uv + 1.0, cam, tol=0.0)
    add("I tol a string", iterative_update, H0, P, uv, cam, tol="1e-9")
    last_row = H0.copy()
    last_row[3] = (0.0, 0.0, 0.0, 2.0)
    add("I last row not 0 0 0 1", iterative_update, last_row, P, uv, cam)
    mirrored = H0.copy()
    mirrored[:3, 0] *= -1.0
    add("I mirrored prior", iterative_update, mirrored, P, uv, cam)
    add("I camera None", iterative_update, H0, P, uv, None)
    add("I float32 kappa", iterative_update, H0, P, uv, cam.with_(kappa=np.float32(1.9e-7)))
    return cases


CASES = _cases()


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
@pytest.mark.parametrize("name", list(CASES))
def test_unusual_input_gives_the_reference_outcome(monkeypatch, name):
    solver, args, kwargs = CASES[name]
    native, reference, used = run_both(monkeypatch, solver, *args, **kwargs)
    if used == [True] and not isinstance(reference, tuple):
        check_agreement(native, reference, np.asarray(args[1], float), np.asarray(args[2], float), args[3],
                        tol=kwargs.get("tol", 1e-9))
    else:
        assert_same_outcome(native, reference)


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_the_unusual_cases_cover_both_paths(monkeypatch):
    kinds = {}
    for name, (solver, args, kwargs) in CASES.items():
        native, reference, used = run_both(monkeypatch, solver, *args, **kwargs)
        kinds[name] = "error" if isinstance(reference, tuple) else "kernel" if used == [True] else "python"
    expected = {
        "I normal": "kernel",
        "R normal": "kernel",
        "I list input": "kernel",
        "R list input": "kernel",
        "I collinear": "error",
        "R collinear": "error",
        "I 2 points": "error",
        "R 3 points": "error",
        "I NaN in uv": "error",
        "I no convergence in 1 step": "error",
        "R no convergence in 1 step": "error",
        "I far-away patch": "error",
        "I behind the camera": "error",
        "I max_iter 0": "error",
        "I max_iter a float": "error",
        "I tol 0": "error",
        "I tol an int": "kernel",
        "I last row not 0 0 0 1": "python",
        "I mirrored prior": "error",
        "I float32 kappa": "python",
        "I camera None": "error",
        "I names too few": "error",
    }
    assert {k: kinds[k] for k in expected} == expected


def test_a_mirrored_prior_is_refused_by_name(monkeypatch):
    solver, args, kwargs = CASES["I mirrored prior"]
    native, reference, used = run_both(monkeypatch, solver, *args, **kwargs)
    assert used == [False] and native == reference and reference[1] is CalibrationError
    assert "no rigid motion" in reference[2] and "determinant -1" in reference[2]
    H0, P6, cam = _ref()
    with pytest.raises(CalibrationError, match="no rigid motion"):
        recalibrate(args[0], P6[:4], args[2], cam)


def test_no_convergence_message_is_the_reference_one(monkeypatch):
    H0, P6, cam = _ref()
    uv = cam.project(transform_points(H0, P6[:4])) + 3.0
    native, reference, used = run_both(monkeypatch, iterative_update, H0, P6[:4], uv, cam, max_iter=2)
    assert used == [False] and native == reference
    assert reference[1] is CalibrationError and "no convergence in 2 iterations" in reference[2]


def test_deferred_diagnostics_pickle_and_repr(monkeypatch):
    H0, P, uv, cam = scene(np.random.default_rng(9), 5)
    native, reference, used = run_both(monkeypatch, iterative_update, H0, P, uv, cam)
    assert used == [True]
    for name in ("residuals_px", "covariance"):
        assert getattr(native, name) is getattr(native, name)
    copy = pickle.loads(pickle.dumps(native))
    for name in FIELDS:
        a, b = getattr(copy, name), getattr(native, name)
        assert np.array_equal(a, b, equal_nan=True) if isinstance(a, np.ndarray) else a == b or a != a
    assert repr(native).startswith("MotionEstimate(method='5P-I'")
    assert native.to_dict().keys() == reference.to_dict().keys()


# --- the kernel called directly ------------------------------------------------------------------------
def _direct_args():
    H0, P6, cam = _ref()
    P = np.ascontiguousarray(P6[:4])
    uv = cam.project(transform_points(H0, P)) + [[0.3, -0.2], [0.1, 0.4], [-0.3, 0.2], [0.2, 0.1]]
    return [H0, None, P, uv, cam, MAX_CONDITION, 1e-9, 50, np.empty((4, 4)), np.empty(6)]


def test_kernel_direct_call_fills_the_outputs():
    args = _direct_args()
    rms, delta_deg, d_mm, iterations, blob = NPU.np_i(*args)
    assert type(rms) is float and type(iterations) is int and type(blob) is bytes
    assert len(blob) == (36 + 4 * 4) * 8 and 1 <= iterations <= 50
    saved = _native.npu
    _native.npu = None
    try:
        reference = iterative_update(args[0], args[2], args[3], args[4])
    finally:
        _native.npu = saved
    # the same minimum: rotation entries to 1e-9 rad, translation and motion to 1e-9 (mm, rad), rms to 1e-6 px
    assert np.allclose(args[8], reference.C_H_G, rtol=0, atol=1e-9)
    assert np.allclose(args[9], reference.motion, rtol=0, atol=1e-9)
    assert rms == pytest.approx(reference.rms_px, abs=1e-6)
    # a start given: the same minimum
    H_s = np.empty((4, 4))
    assert NPU.np_i(args[0], reference.C_H_G, *args[2:8], H_s, np.empty(6)) is not None
    assert np.abs(H_s - reference.C_H_G).max() < 1e-9  # the same minimum: 1e-9 rad, 1e-9 mm


def _fallback_variants():
    H0, _, P, uv = _direct_args()[:4]
    return {
        "list C_H_G": (0, H0.tolist()),
        "float32 start": (1, H0.astype(np.float32)),
        "(3, 4) start": (1, H0[:3].copy()),
        "int64 p_G": (2, P.astype(np.int64)),
        "(3, 2) uv": (3, uv[:3].copy()),
        "non-contiguous p_G": (2, np.asfortranarray(P)),
        "camera None": (4, None),
        "camera with NaN": (4, _Camera(cx=math.nan)),
        "camera raising": (4, _RaisingCamera()),
        "tol a string": (6, "1e-9"),
        "tol a huge int": (6, 10**400),
        "max_iter a float": (7, 50.0),
        "max_iter 0": (7, 0),
        "max_iter huge": (7, 10**30),
        "max_condition NaN": (5, math.nan),
    }


FALLBACK = _fallback_variants()


@pytest.mark.parametrize("name", list(FALLBACK))
def test_kernel_hands_back_what_it_does_not_handle(name):
    args = _direct_args()
    i, value = FALLBACK[name]
    args[i] = value
    H_out, x_out = args[8].copy(), args[9].copy()
    assert NPU.np_i(*args) is None
    assert np.array_equal(args[8], H_out, equal_nan=True) and np.array_equal(args[9], x_out, equal_nan=True)


@pytest.mark.parametrize(
    "change,error",
    [
        (lambda a: a[:9], TypeError),
        (lambda a: a + [None], TypeError),
        (lambda a: a[:5] + ["1e8"] + a[6:], TypeError),
        (lambda a: a[:8] + [np.empty((4, 3))] + a[9:], ValueError),
        (lambda a: a[:9] + [np.empty(7)], ValueError),
        (lambda a: a[:9] + [[0.0] * 6], TypeError),
    ],
)
def test_kernel_rejects_wrong_arguments(change, error):
    with pytest.raises(error):
        NPU.np_i(*change(_direct_args()))


def test_kernel_leaks_no_references_nor_memory():
    args = _direct_args()
    started = _direct_args()
    started[1] = args[0].copy()
    bad = _direct_args()
    bad[3] = bad[3].copy()
    bad[3][0, 0] = math.nan
    many = _direct_args()  # more points than the kernel keeps on its stack
    rng = np.random.default_rng(3)
    many[2] = np.column_stack([rng.uniform(-30, 30, size=(40, 2)), np.zeros(40)])
    many[3] = many[4].project(transform_points(many[0], many[2])) + rng.normal(scale=0.2, size=(40, 2))
    objects = [args[0], args[2], args[3], args[8], started[1], bad[3], many[2], many[3]]
    before = [sys.getrefcount(o) for o in objects]
    for _ in range(500):
        NPU.np_i(*args)
        NPU.np_i(*started)
        NPU.np_i(*bad)
        assert NPU.np_i(*many) is not None
    tracemalloc.start()
    try:
        start = tracemalloc.get_traced_memory()[0]
        for _ in range(5000):
            NPU.np_i(*args)
            NPU.np_i(*started)
            NPU.np_i(*bad)
            NPU.np_i(*many)
            try:
                NPU.np_i(*args[:8], np.empty(3), args[9])
            except ValueError:
                pass
        grown = tracemalloc.get_traced_memory()[0] - start
    finally:
        tracemalloc.stop()
    assert [sys.getrefcount(o) for o in objects] == before
    assert grown < 20000
