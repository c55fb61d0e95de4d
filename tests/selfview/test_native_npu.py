"""The compiled NP-U kernel (``selfview._cnpu``) against the pure-Python reference of
``online.differential_update``.

Every test runs the same call twice: with the kernel, and with ``selfview._native.npu`` set to None
(the pure-Python code, the reference). A call the kernel handles must give the reference's estimate to
the rounding of the reference itself; a call it hands back, the reference's estimate or error exactly.

Where the kernel is not built the module is skipped, unless ``SELFVIEW_REQUIRE_NATIVE=1`` is set (and
``SELFVIEW_PURE_PYTHON`` is not): then it fails, so that a build that failed silently is caught.
"""

from __future__ import annotations

import importlib
import math
import os
import pickle
import sys
import tracemalloc

import numpy as np
import pytest

from selfview import _native, online
from selfview.camera import CameraModel
from selfview.cell import POINT_NAMES, default_cell_path, load_cell
from selfview.errors import CalibrationError
from selfview.geometry import delta_star, transform_points
from selfview.online import MAX_CONDITION, MotionEstimate, differential_update

NPU = _native.npu


def _flag(name: str) -> bool:
    return os.environ.get(name, "").strip() not in ("", "0")


if NPU is None:
    if _flag("SELFVIEW_REQUIRE_NATIVE") and not _flag(_native.PURE_PYTHON_ENV):
        try:  # to say why it is missing
            importlib.import_module("selfview._cnpu")
            why = "it imports, but selfview._native did not load it"
        except ImportError as exc:
            why = f"ImportError: {exc}"
        pytest.fail(f"SELFVIEW_REQUIRE_NATIVE=1, but the kernel selfview._cnpu is missing ({why})", pytrace=False)
    pytest.skip(
        "selfview._cnpu not built (or SELFVIEW_PURE_PYTHON=1): nothing to compare with the Python code",
        allow_module_level=True,
    )

from selfview.mocks.world import SimWorld  # noqa: E402

EPS = float(np.finfo(float).eps)
# Tolerances between the kernel and the Python reference where both compute the same quantity by their own
# code (not bit identity: the kernel's compiler may fuse multiply-adds, numpy's BLAS sums in its own order,
# and which rounding each gets depends on the CPU):
TOL_PX = 1e-6  # residuals and their rms: a millionth of a pixel (the fingertips' noise is ~0.05 px)
TOL_MM = 1e-6  # translations: a nanometre
TOL_DEG = 1e-6  # rotation angles (delta of eq. 14): 1.7e-8 rad, 2e-6 mm at the fingertips' ~100 mm
TOL_REL = 1e-9  # dimensionless or mixed-unit arrays (eq. 17's [A | b], covariances, condition numbers): relative
CELL = load_cell(default_cell_path())


# --- running both paths ------------------------------------------------------------------------------
class Spy:
    """Stands in for the kernel module: calls it and records whether it handled each call (or None)."""

    def __init__(self):
        self.handled: list[bool] = []

    def np_u(self, *args):
        out = NPU.np_u(*args)
        self.handled.append(out is not None)
        return out


def outcome(fn, *args, **kwargs):
    """fn's result, or ('raised', type, message)."""
    try:
        return fn(*args, **kwargs)
    except Exception as exc:  # noqa: BLE001 - any error must be the reference's
        return ("raised", type(exc), str(exc))


#: names=NAMES_GENERATOR: a new generator of names for each call
NAMES_GENERATOR = object()


def run_both(monkeypatch, *args, **kwargs):
    """(outcome with the kernel, outcome of the pure-Python reference, [handled by the kernel?])."""

    def fresh():
        if kwargs.get("names") is NAMES_GENERATOR:
            return {**kwargs, "names": (f"n{i}" for i in range(4))}
        return kwargs

    spy = Spy()
    monkeypatch.setattr(_native, "npu", spy)
    native = outcome(differential_update, *args, **fresh())
    monkeypatch.setattr(_native, "npu", None)
    reference = outcome(differential_update, *args, **fresh())
    monkeypatch.setattr(_native, "npu", NPU)
    return native, reference, spy.handled


FIELDS = online._FIELDS


def same_kind(a, b, name):
    """The same type, and for arrays the same dtype, shape and memory layout."""
    assert type(a) is type(b), (name, type(a), type(b))
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, name
        for flag in ("C_CONTIGUOUS", "WRITEABLE", "OWNDATA"):
            assert a.flags[flag] == b.flags[flag], (name, flag)


def assert_identical(e1: MotionEstimate, e2: MotionEstimate):
    """Every field equal (NaN equal to NaN), of the same kind."""
    for name in FIELDS:
        a, b = getattr(e1, name), getattr(e2, name)
        same_kind(a, b, name)
        if isinstance(a, np.ndarray):
            assert np.array_equal(a, b, equal_nan=True), name
        elif isinstance(a, float) and math.isnan(b):
            assert math.isnan(a), name
        else:
            assert a == b, name


def assert_same_outcome(native, reference):
    if isinstance(reference, tuple):
        assert native == reference  # ('raised', type, message)
    else:
        assert isinstance(native, MotionEstimate), native
        assert_identical(native, reference)


def python_steps_at(x, H0, P, uv, cam):
    """The reference's steps around the solve, at the motion x (6,): ([A | b] of eq. 17, C'_H_G of
    eq. 13, the residuals of eq. 16 (N, 2), their rms, delta_deg, d_mm)."""
    obs = online._undistort(cam, uv.tolist())
    p_C = online._camera_points(H0.tolist(), P.tolist(), "test")
    Ab = online._eq17(p_C, obs, cam.f)
    dx, dy, dz, tx, ty, tz = x.tolist()
    H = np.dot(delta_star((dx, dy, dz), (tx, ty, tz)), H0)
    predicted = []
    for px, py, pz in p_C:  # eq. 16, as differential_update writes it
        xn, yn, zn = px - dz * py + dy * pz + tx, dz * px + py - dx * pz + ty, -dy * px + dx * py + pz + tz
        predicted.append((cam.f * xn / zn, cam.f * yn / zn))
    res, rms = online._pixel_residuals(cam, obs, predicted)
    e = online._estimate("", H, H, x, res, rms, None, None, (), 1, H0)
    return Ab, H, np.array(res), rms, e.delta_deg, e.d_mm


# --- scenes ------------------------------------------------------------------------------------------
def scene(rng, n):
    """(C_H_G before, p_G (n, 3), uv (n, 2), camera) of the reference cell, simulated: the camera turned
    by up to 6 degrees about a random axis through a random pivot, pixel noise up to 0.5 px; the points
    the first n fingertips, or n of them at random, sometimes moved off their plane."""
    world = SimWorld(CELL, seed=int(rng.integers(1 << 30)))
    before = world.C_H_G
    world.set_jaw(float(rng.uniform(20.0, 60.0)))
    world.disturb_by_angle(rng.normal(size=3), float(rng.uniform(0.0, 6.0)), pivot_C=rng.uniform(-40, 40, size=3))
    P6 = world.points_G()
    P = P6[:n] if rng.random() < 0.5 else P6[rng.choice(6, n, replace=False)]
    if rng.random() < 0.3:
        P = P + rng.normal(scale=3.0, size=P.shape)
    noise = float(rng.choice([0.0, 0.02, 0.1, 0.5]))
    uv = world.camera.project(transform_points(world.C_H_G, P)) + rng.normal(scale=noise, size=(n, 2))
    return before, P, uv, world.camera


FORMS = {
    "array": lambda a: a,
    "list": lambda a: a.tolist(),
    "float32": lambda a: a.astype(np.float32),
    "tuple": lambda a: tuple(map(tuple, a)),
}


def check_agreement(native, reference, H0, P, uv, cam, prior_sigma_px):
    """The kernel's estimate against the reference's: the least-squares solution to the rounding of the
    normal equations, everything after the solve as the reference computes it from that solution."""
    n = len(P)
    x, xr = native.motion, reference.motion
    # 1. The solve. Both form N = A^T A and A^T b (BLAS, here sums in index order: each entry off by up to
    # gamma_2n = 2n eps relative to the sum of the magnitudes of its terms), then the same Cholesky: the
    # difference stays within 2 gamma_2n |N^-1| (|A|^T |b| + |A|^T |A| |x|), componentwise.
    Ab, H, res, rms, delta_deg, d_mm = python_steps_at(x, H0, P, uv, cam)
    A, b = np.abs(Ab[:, :6]), np.abs(Ab[:, 6])
    N_inv = np.linalg.inv(np.dot(Ab[:, :6].T, Ab[:, :6]))
    tol_x = 4 * n * EPS * np.dot(np.abs(N_inv), A.T @ b + (A.T @ A) @ np.abs(xr))
    assert np.all(np.abs(x - xr) <= tol_x), (x - xr, tol_x)
    # 2. Given the solution: what the reference computes from it, each at the tolerance of its quantity.
    H_k, x_k = np.empty((4, 4)), np.empty(6)
    rms_k, _, _, blob = NPU.np_u(H0, P, uv, cam, MAX_CONDITION, H_k, x_k)  # the kernel's own output
    # the kernel called again: the same code on the same input, bit for bit by construction
    assert np.array_equal(H_k, native.C_H_G) and np.array_equal(x_k, x) and rms_k == native.rms_px
    Ab_k = np.frombuffer(blob, float, 14 * n).reshape(2 * n, 7)
    # eq. 17's rows: products of a few terms each, relative to the largest entry of their column
    assert np.all(np.abs(Ab_k - Ab) <= TOL_REL * np.abs(Ab).max(axis=0)), Ab_k - Ab
    D = np.abs(delta_star(x[:3], x[3:]))
    # eq. 13's product, bounded by its own rounding (gamma_4 of |Delta*| |H0|, any order, fused or not)
    assert np.all(np.abs(native.C_H_G - H) <= 4 * EPS * np.dot(D, np.abs(H0))), native.C_H_G - H
    assert np.abs(native.residuals_px - res).max() <= TOL_PX
    assert abs(native.rms_px - rms) <= TOL_PX
    assert abs(native.delta_deg - delta_deg) <= TOL_DEG and abs(native.d_mm - d_mm) <= TOL_MM
    # the orthonormalised pose and the covariance are computed later, by the Python code, from the kernel's
    # own H and [A | b]: the same code on the same input (identity by construction)
    assert np.array_equal(native.C_H_G_orth, online._orthonormal(native.C_H_G))
    N_k = np.dot(Ab_k.T, Ab_k)[:6, :6]
    assert np.array_equal(native.covariance, online._ls_covariance(Ab_k, N_k, x, prior_sigma_px), equal_nan=True)
    # the condition number from the kernel's [A | b] against the reference's: relative
    assert native.condition == pytest.approx(reference.condition, rel=TOL_REL)
    # 3. End to end: the difference of the solutions carried through.
    dres = 2.0 * np.dot(np.abs(Ab[:, :6]), tol_x).reshape(n, 2) / np.array([cam.aspect, 1.0]) + 1e-12
    assert np.all(np.abs(native.residuals_px - reference.residuals_px) <= dres)
    assert abs(native.rms_px - reference.rms_px) <= 2.0 * dres.max()
    tol_delta = math.degrees(np.linalg.norm(tol_x[:3])) + 1e-15 * reference.delta_deg
    assert abs(native.delta_deg - reference.delta_deg) <= tol_delta
    assert abs(native.d_mm - reference.d_mm) <= np.linalg.norm(tol_x[3:]) + 1e-15 * reference.d_mm
    tol_H = np.dot(np.abs(delta_star(tol_x[:3], tol_x[3:]) - np.eye(4)), np.abs(H0)) + 8 * EPS * np.dot(D, np.abs(H0))
    assert np.all(np.abs(native.C_H_G - reference.C_H_G) <= tol_H)
    assert np.abs(native.C_H_G_orth - reference.C_H_G_orth).max() <= 4 * tol_H.max() + 1e-14
    if prior_sigma_px is not None or n == 3:
        # (prior_sigma_px^2 N^-1 or a NaN-free exact solve: relative, from [A | b]'s own agreement)
        scale = np.abs(reference.covariance).max() if np.isfinite(reference.covariance).all() else 0.0
        assert np.array_equal(np.isnan(native.covariance), np.isnan(reference.covariance))
        fin = np.isfinite(reference.covariance)
        assert np.all(np.abs(native.covariance[fin] - reference.covariance[fin]) <= TOL_REL * scale + 1e-300)
    else:
        r = np.dot(Ab[:, :6], xr) - Ab[:, 6]
        Adx = np.dot(np.abs(Ab[:, :6]), tol_x)
        tol_rss = 2 * np.linalg.norm(r) * np.linalg.norm(Adx) + np.dot(Adx, Adx) + 1e-300
        S = online._svd_inverse(np.dot(Ab.T, Ab)[:6, :6])
        dcov = np.abs(native.covariance - reference.covariance)
        assert np.all(dcov <= tol_rss / (2 * n - 6) * np.abs(S) + 4 * EPS * np.abs(reference.covariance))


@pytest.mark.parametrize("n", [3, 4, 5, 6])
def test_agrees_with_the_python_code(monkeypatch, n):
    rng = np.random.default_rng(100 + n)
    handled = 0
    cases = 150
    for i in range(cases):
        H0, P, uv, cam = scene(rng, n)
        form = list(FORMS)[i % len(FORMS)]
        to = FORMS[form]
        names = None if rng.random() < 0.7 else [f"p{j}" for j in range(n)]
        prior = None if rng.random() < 0.8 else 0.05
        native, reference, used = run_both(monkeypatch, to(H0), to(P), to(uv), cam, names, prior_sigma_px=prior)
        if used != [True]:  # a configuration the kernel hands back (the bound does not settle it, ...)
            assert used == [False]
            assert_same_outcome(native, reference)
            continue
        handled += 1
        for name in FIELDS:
            same_kind(getattr(native, name), getattr(reference, name), name)
        assert native.method == reference.method == f"{n}P-U"
        assert native.points_used == reference.points_used == (POINT_NAMES[:n] if names is None else tuple(names))
        assert native.iterations == reference.iterations == 1
        assert np.array_equal(native.C_H_G_prior, reference.C_H_G_prior)
        if form == "array":
            assert native.C_H_G_prior is H0 and reference.C_H_G_prior is H0
        # what both computed from: the input as float64 (float32 converted exactly)
        H0d, Pd, uvd = (np.asarray(to(a), dtype=float) for a in (H0, P, uv))
        check_agreement(native, reference, H0d, Pd, uvd, cam, prior)
    assert handled >= 0.8 * cases  # three of the six fingertips at random: some nearly collinear


def test_agrees_for_many_points(monkeypatch):
    """More points than the kernel keeps on its stack."""
    rng = np.random.default_rng(5)
    H0, _, _, cam = scene(rng, 4)
    P = np.column_stack([rng.uniform(-30, 30, size=(40, 2)), rng.uniform(-5, 5, size=40)])
    uv = cam.project(transform_points(H0, P)) + rng.normal(scale=0.3, size=(40, 2))
    native, reference, used = run_both(monkeypatch, H0, P, uv, cam)
    assert used == [True] and reference.points_used == tuple(f"point-{i + 1}" for i in range(40))
    check_agreement(native, reference, H0, P, uv, cam, None)
    assert native.points_used == reference.points_used and native.method == "40P-U"


def test_deferred_diagnostics_pickle_and_repr(monkeypatch):
    rng = np.random.default_rng(9)
    H0, P, uv, cam = scene(rng, 4)
    native, reference, used = run_both(monkeypatch, H0, P, uv, cam)
    assert used == [True]
    for name in ("C_H_G_orth", "residuals_px", "covariance"):
        assert getattr(native, name) is getattr(native, name)
    copy = pickle.loads(pickle.dumps(native))
    assert_identical(copy, native)
    assert repr(native).startswith("MotionEstimate(method='4P-U'")
    assert native.to_dict().keys() == reference.to_dict().keys()


# --- every unusual case: the reference's outcome exactly ----------------------------------------------
def _ref():
    cam = CELL.camera.guess().with_(f=962.0, kappa=1.9e-7)
    return CELL.mount_guess_C_H_G, CELL.gripper.points_G("open"), cam


def _bad_cases():
    H0, P6, cam = _ref()
    P = P6[:4]
    uv = cam.project(transform_points(H0, P))
    cases = {}

    def add(name, *args, **kwargs):
        cases[name] = (args, kwargs)

    add("normal", H0, P, uv, cam)
    add("2 points", H0, P[:2], uv[:2], cam)
    add("1 point", H0, P[:1], uv[:1], cam)
    add("0 points", H0, P[:0], uv[:0], cam)
    line = np.array([[28.0, -6.0, 0.0], [0.0, -6.0, 0.0], [-28.0, -6.0, 0.0], [14.0, -6.0, 0.0]])
    add("collinear", H0, line, cam.project(transform_points(H0, line)), cam)
    near = line + [[0, 0, 0], [0, 0.01, 0], [0, 0, 0], [0, 0, 0]]
    add("nearly collinear", H0, near, cam.project(transform_points(H0, near)), cam)
    same = np.repeat(P[:1], 4, axis=0)
    add("coincident", H0, same, cam.project(transform_points(H0, same)), cam)
    for what, arr_i in (("uv", 2), ("p_G", 1), ("C_H_G", 0)):
        for value in (np.nan, np.inf, -np.inf):
            args = [H0.copy(), P.copy(), uv.copy()]
            args[arr_i][1, 1] = value
            add(f"{value} in {what}", *args, cam)
    nan3 = uv.copy()
    nan3[2] = np.nan
    add("NaN in uv, names given", H0, P, nan3, cam, names=list("abcd"))
    behind = H0.copy()
    behind[2, 3] = -110.0
    add("behind the camera", behind, P, uv, cam)
    flat = cam.with_(kappa=0.0)
    far = [[-1134.08, -289.95], [186.83, -2080.78], [416.87, -912.59], [-110.77, -300.01]]
    add("the update moves a point behind", H0, P, np.array(far), flat)
    add("uv (3, 2) for 4 points", H0, P, uv[:3], cam)
    add("p_G (4, 2)", H0, P[:, :2], uv, cam)
    add("p_G (12,)", H0, P.ravel(), uv, cam)
    add("C_H_G (3, 4)", H0[:3], P, uv, cam)
    add("C_H_G (16,)", H0.ravel(), P, uv, cam)
    add("C_H_G 3-d", H0[None], P, uv, cam)
    add("ragged p_G", H0, [[1.0, 2.0, 3.0], [1.0, 2.0]], uv, cam)
    add("p_G of strings", H0, [["a", "b", "c"]] * 4, uv, cam)
    add("camera None", H0, P, uv, None)
    add("camera a dict", H0, P, uv, {"f": 962.0, "kappa": 0.0, "cx": 383.5, "cy": 287.5, "aspect": 1.0})
    add("names too few", H0, P, uv, cam, names=["a", "b"])
    add("names too many", H0, P, uv, cam, names="abcde")
    add("names not iterable", H0, P, uv, cam, names=5)
    add("names of numbers", H0, P, uv, cam, names=range(4))
    add("names a generator", H0, P, uv, cam, names=NAMES_GENERATOR)
    # the conditioning: refused; bound not settling it but the exact check passing (Python decides)
    far_away = H0.copy()
    far_away[2, 3] = 1e5  # 100 m: a 56 mm patch cannot fix the camera's pose
    add("far-away patch", far_away, P, cam.project(transform_points(far_away, P)), cam)
    thin = np.array([[28.0, -6.0, 0.0], [0.0, -5.0, 0.0], [-28.0, -6.0, 0.0], [14.0, -7.0, 0.0]])
    add("ill-conditioned, accepted", H0, thin, cam.project(transform_points(H0, thin)), cam)
    add("huge p_G", H0, P * 1e200, uv, cam)
    add("huge uv", H0, P, uv * 1e300, cam)
    big = H0.copy()
    big[:3, 3] = 1e300
    add("huge C_H_G", big, P, uv, cam)
    add("tiny p_G", H0, P * 1e-300, uv, cam)
    # the Newton inversion of the residuals not converging: distort() decides, or raises
    off = uv.copy()
    off[0] += 150.0
    add("Newton fails, distort succeeds", H0, P, off, cam.with_(kappa=-2e-6))
    add("Newton fails, distort raises", H0, P, off, cam.with_(kappa=-3e-6))
    # layouts and types the kernel leaves to Python
    add("Fortran-order C_H_G", np.asfortranarray(H0), P, uv, cam)
    add("strided p_G", H0, np.repeat(P, 2, axis=0)[::2], uv, cam)
    add("big-endian uv", H0, P, uv.astype(">f8"), cam)
    add("int C_H_G", np.round(H0).astype(int).tolist(), P, uv, cam)
    add("float32 kappa", H0, P, uv, cam.with_(kappa=np.float32(1.9e-7)))
    add("int camera", H0, P, uv, CameraModel(f=962, kappa=0, cx=384, cy=288, aspect=1))
    add("numpy float64 camera", H0, P, uv, cam.with_(f=np.float64(962.0), cx=np.float64(383.5)))
    return cases


BAD = _bad_cases()


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # the reference's, on huge input
@pytest.mark.parametrize("name", list(BAD))
def test_unusual_input_gives_the_reference_outcome(monkeypatch, name):
    args, kwargs = BAD[name]
    native, reference, used = run_both(monkeypatch, *args, **kwargs)
    if used == [True] and not isinstance(reference, tuple):  # handled: agreement as for the scenes
        H0, P, uv = (np.asarray(a, dtype=float) for a in args[:3])
        check_agreement(native, reference, H0, P, uv, args[3], None)
    else:  # handed back, or an error (the names' are raised after the kernel): the reference's exactly
        assert_same_outcome(native, reference)


@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")  # the reference's, on huge input
def test_the_unusual_cases_cover_both_paths(monkeypatch):
    """The cases above include errors, hand-backs that succeed, and cases the kernel handles."""
    kinds = {}
    for name, (args, kwargs) in BAD.items():
        native, reference, used = run_both(monkeypatch, *args, **kwargs)
        kinds[name] = "error" if isinstance(reference, tuple) else "kernel" if used == [True] else "python"
    expected = {
        "normal": "kernel",
        "ill-conditioned, accepted": "python",
        "Newton fails, distort succeeds": "python",
        "Newton fails, distort raises": "error",
        "the update moves a point behind": "error",
        "far-away patch": "error",
        "collinear": "error",
        "nearly collinear": "error",
        "coincident": "error",
        "int camera": "kernel",
        "numpy float64 camera": "kernel",
        "float32 kappa": "python",
        "Fortran-order C_H_G": "python",
        "camera None": "error",
        "names too few": "error",
    }
    assert {k: kinds[k] for k in expected} == expected


def test_the_conditioning_limit_is_read_at_call_time(monkeypatch):
    """MAX_CONDITION goes to the kernel at each call: lowered, the bound no longer settles the normal
    configuration, and the Python code refuses it with its message."""
    H0, P6, cam = _ref()
    uv = cam.project(transform_points(H0, P6[:4]))
    monkeypatch.setattr(online, "MAX_CONDITION", 1e3)
    native, reference, used = run_both(monkeypatch, H0, P6[:4], uv, cam)
    assert used == [False] and native == reference and reference[1] is CalibrationError
    assert "exceeds 1e+03" in reference[2]


def test_condition_sweep_both_ways_to_accept(monkeypatch):
    """Four points off a line by a varying amount (test_online's sweep): the kernel takes the ones the
    bound settles, hands back the others, and the outcomes are the reference's."""
    H0, _, cam = _ref()
    kinds = set()
    for off_mm in np.geomspace(0.05, 20.0, 25):
        Q = np.array([[28.0, -6.0, 0.0], [0.0, -6.0 + off_mm, 0.0], [-28.0, -6.0, 0.0], [14.0, -6.0 - off_mm, 0.0]])
        uv = cam.project(transform_points(H0, Q))
        native, reference, used = run_both(monkeypatch, H0, Q, uv, cam)
        if used == [True]:
            check_agreement(native, reference, H0, Q, uv, cam, None)
            kinds.add("kernel")
        else:
            assert_same_outcome(native, reference)
            kinds.add("error" if isinstance(reference, tuple) else "python")
    assert kinds == {"kernel", "python", "error"}


# --- the kernel called directly ------------------------------------------------------------------------
def _direct_args():
    H0, P6, cam = _ref()
    P = np.ascontiguousarray(P6[:4])
    return [H0, P, cam.project(transform_points(H0, P)), cam, MAX_CONDITION, np.empty((4, 4)), np.empty(6)]


def test_kernel_direct_call_fills_the_outputs():
    args = _direct_args()
    out = NPU.np_u(*args)
    rms, delta_deg, d_mm, blob = out
    assert type(rms) is float and type(delta_deg) is float and type(d_mm) is float and type(blob) is bytes
    assert len(blob) == 16 * 4 * 8
    reference = _reference_call(*args[:4])
    # the pose to 1e-9 (rotation entries: 1e-9 rad; translation: a picometre) and the motion (rad, mm) alike
    assert np.allclose(args[5], reference.C_H_G, rtol=0, atol=1e-9)
    assert np.allclose(args[6], reference.motion, rtol=0, atol=1e-9)
    # any buffer of doubles of the right shape will do, e.g. a memoryview
    mv = [memoryview(np.ascontiguousarray(a)) for a in args[:3]]
    assert NPU.np_u(*mv, *args[3:]) is not None


def _reference_call(H0, P, uv, cam):
    saved = _native.npu
    _native.npu = None
    try:
        return differential_update(H0, P, uv, cam)
    finally:
        _native.npu = saved


class _Camera:
    def __init__(self, **kw):
        self.__dict__.update(dict(f=962.0, kappa=0.0, cx=383.5, cy=287.5, aspect=1.0) | kw)


class _RaisingCamera(_Camera):
    @property
    def kappa(self):
        raise RuntimeError("kappa unavailable")


def _fallback_variants():
    """Arguments the kernel must hand back (None), by position."""
    H0, P, uv = _direct_args()[:3]
    return {
        "list C_H_G": (0, H0.tolist()),
        "float32 C_H_G": (0, H0.astype(np.float32)),
        "int64 p_G": (1, P.astype(np.int64)),
        "complex uv": (2, uv.astype(complex)),
        "bytes uv": (2, b"\0" * 64),
        "bytearray p_G": (1, bytearray(96)),
        "memoryview of bytes, format B": (1, memoryview(bytearray(96)).cast("B", (4, 24))),
        "None": (0, None),
        "(3, 4) C_H_G": (0, H0[:3].copy()),
        "(4, 2) p_G": (1, P[:, :2].copy()),
        "(4, 3, 1) p_G": (1, P[:, :, None].copy()),
        "(12,) p_G": (1, P.ravel().copy()),
        "(3, 2) uv": (2, uv[:3].copy()),
        "(4, 3) uv": (2, np.zeros((4, 3))),
        "non-contiguous p_G": (1, np.asfortranarray(P)),
        "big-endian C_H_G": (0, H0.astype(">f8")),
        "camera None": (3, None),
        "camera without kappa": (3, type("Cam", (), {"f": 962.0, "cx": 0.0, "cy": 0.0, "aspect": 1.0})()),
        "camera with a string": (3, _Camera(f="962")),
        "camera with a float32": (3, _Camera(kappa=np.float32(0.0))),
        "camera with NaN": (3, _Camera(cx=math.nan)),
        "camera with inf": (3, _Camera(f=math.inf)),
        "camera with a huge int": (3, _Camera(f=10**400)),
        "camera raising": (3, _RaisingCamera()),
        "max_condition NaN": (4, math.nan),
        "max_condition 0": (4, 0.0),
    }


FALLBACK = _fallback_variants()


@pytest.mark.parametrize("name", list(FALLBACK))
def test_kernel_hands_back_what_it_does_not_handle(name):
    args = _direct_args()
    i, value = FALLBACK[name]
    args[i] = value
    H_out, x_out = args[5].copy(), args[6].copy()
    assert NPU.np_u(*args) is None
    assert np.array_equal(args[5], H_out, equal_nan=True) and np.array_equal(args[6], x_out, equal_nan=True)


@pytest.mark.parametrize(
    "change,error",
    [
        (lambda a: a[:6], TypeError),
        (lambda a: a + [None], TypeError),
        (lambda a: [], TypeError),
        (lambda a: a[:4] + ["1e8"] + a[5:], TypeError),
        (lambda a: a[:4] + [None] + a[5:], TypeError),
        (lambda a: a[:5] + [np.empty((4, 3))] + a[6:], ValueError),
        (lambda a: a[:6] + [np.empty(7)], ValueError),
        (lambda a: a[:5] + [np.empty((4, 4), np.float32)] + a[6:], TypeError),
        (lambda a: a[:5] + [np.empty((4, 4)).T] + a[6:], TypeError),
        (lambda a: a[:5] + [_read_only((4, 4))] + a[6:], TypeError),
        (lambda a: a[:6] + [[0.0] * 6], TypeError),
        (lambda a: a[:6] + [b"\0" * 48], TypeError),
        (lambda a: a[:6] + [None], TypeError),
    ],
)
def test_kernel_rejects_wrong_arguments(change, error):
    with pytest.raises(error):
        NPU.np_u(*change(_direct_args()))


def _read_only(shape):
    a = np.zeros(shape)
    a.flags.writeable = False
    return a


def test_kernel_keyboard_interrupt_from_the_camera_propagates():
    class Interrupting(_Camera):
        @property
        def f(self):
            raise KeyboardInterrupt

    args = _direct_args()
    args[3] = Interrupting()
    with pytest.raises(KeyboardInterrupt):
        NPU.np_u(*args)


def test_kernel_leaks_no_references_nor_memory():
    args = _direct_args()
    bad = _direct_args()
    bad[2] = bad[2].copy()
    bad[2][0, 0] = math.nan
    objects = args[:4] + args[5:] + bad[:3]
    before = [sys.getrefcount(o) for o in objects]
    for _ in range(2000):  # warm up
        NPU.np_u(*args)
        NPU.np_u(*bad)
    tracemalloc.start()
    try:
        start = tracemalloc.get_traced_memory()[0]
        for _ in range(20000):
            NPU.np_u(*args)
            NPU.np_u(*bad)
            try:
                NPU.np_u(*args[:5], np.empty(3), args[6])
            except ValueError:
                pass
        grown = tracemalloc.get_traced_memory()[0] - start
    finally:
        tracemalloc.stop()
    assert [sys.getrefcount(o) for o in objects] == before
    assert grown < 20000  # bytes: nothing kept per call
