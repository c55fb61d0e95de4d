"""Benchmark: multi-view intrinsics (f, kappa, principal point, aspect) against cv2.calibrateCamera and mrcal.

Study 1, the joint fit on the robot's planned views of simulated cameras (again per further ``--profile``
of a real cell's imperfections); 2, one parked picture calibrated with the measured camera; 3 and 4, how
often the camera check warns and how small an error it catches; 5, real dot-grid photographs. Each
study's function says what it measures. Prints one JSON object.

    python bench/intrinsics.py [--cameras 10] [--pictures 30] [--jobs 2] [--quick] [--profile ideal realistic ...]
    python bench/intrinsics.py --photos-only
    python bench/intrinsics.py --real-sets [--repeats 3]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

if not __package__ and (Path(__file__).resolve().parents[1] / "pyproject.toml").is_file():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from selfview.files.cell import default_cell_path, load_cell  # noqa: E402
from selfview.errors import CellError, ConfigError  # noqa: E402
from selfview.maths.geometry import inv_H  # noqa: E402
from selfview.estimation.intrinsics import (  # noqa: E402
    TARGET_ACROSS_MM, TARGET_ALONG_MM, calibrate_intrinsics, camera_check, detect_views, tcp_sigma,
)
from selfview.procedures.viewplan import plan_view_poses  # noqa: E402
from selfview.measurement.plates import plate_image_bias  # noqa: E402
from selfview.maths.geometry import trans, transform_points  # noqa: E402
from selfview.mocks.imperfections import PROFILES  # noqa: E402
from selfview.mocks.render import render as _project_render  # noqa: E402
from selfview.mocks.world import PLATE_BASE_POSE, SimWorld  # noqa: E402
from selfview.estimation.offline import calibrate_offline  # noqa: E402

try:  # the independent renderer lives beside the tests, in a source tree
    from tests import alt_render as _alt
except ImportError:  # pragma: no cover - an installed copy without the tests
    _alt = None

#: Where the robot's base lies from the reference simulated cell's plate (W's -x).
LEAN = (-1.0, 0.0)
CV_FLAGS = ("CALIB_USE_INTRINSIC_GUESS", "CALIB_ZERO_TANGENT_DIST", "CALIB_FIX_K2", "CALIB_FIX_K3")
#: The intrinsics targets: median centre error under 0.3 px, aspect and f errors under 0.05 %, the
#: errors' RMS within a factor 2 of the reported sigmas.
ISSUE = {"centre_px": 0.3, "aspect_pct": 0.05, "f_pct": 0.05, "sigma_factor": 2.0}
#: The robot's planned views per camera (12 by default; ``--views``).
VIEWS = 12


#: Real photograph sets under tests/data: (directory, picture pattern), each picture read with the cell file of
#: its size there.
PHOTO_SETS = (("visp-circles", "circles-0*.jpg"), ("visp-circles", "grid36-0*.png"))
PHOTO_DATA = Path(__file__).resolve().parents[1] / "tests" / "data"


def _render(world, C_H_W, seed):
    """The independent renderer's picture of the world's camera and gripper with the plate at ``C_H_W``."""
    return _alt.render(world.camera, world.C_H_G, C_H_W, world.jaw_gap_mm, world.cell, seed=seed).image


def _kappa_equivalent(K, dist, w, h, aspect):
    from selfview.bench.offline import kappa_equivalent

    return kappa_equivalent(K, dist, w, h, aspect)


def _cv2(dets, uvs, cam0, size):
    obj = [d.p_W.astype(np.float32) for d in dets]
    img = [u.astype(np.float32).reshape(-1, 1, 2) for u in uvs]
    K0 = np.array([[cam0.f, 0, cam0.cx], [0, cam0.f, cam0.cy], [0, 0, 1.0]])
    flags = 0
    for nm in CV_FLAGS:
        flags |= getattr(cv2, nm)
    t = time.perf_counter()
    rms, K, dist, _, _, sd_int, _, _ = cv2.calibrateCameraExtended(obj, img, size, K0, np.zeros(5), flags=flags)
    dt = time.perf_counter() - t
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    sd = np.ravel(sd_int)
    aspect = fy / fx
    return {
        "f": fy, "cx": cx, "cy": cy, "aspect": aspect,
        "kappa": _kappa_equivalent(K, dist.ravel(), size[0], size[1], aspect),
        "sigma": {"f": sd[1], "cx": sd[2], "cy": sd[3], "aspect": aspect * np.hypot(sd[0] / fx, sd[1] / fy)},
        "rms_px": rms, "seconds": dt,
    }


def _mrcal(dets, uvs, pitch, cam0, size):
    """mrcal's fit of the same views and detections (None: no interpreter has mrcal)."""
    from selfview.bench import _mrcal_peer

    if _MRCAL["python"] is None:
        return None
    m = _mrcal_peer.fit([d.p_W for d in dets], uvs, pitch, cam0, size, python=_MRCAL["python"])
    m["kappa"] = _kappa_equivalent(np.array(m["K"]), np.r_[m["dist"], 0.0], size[0], size[1], m["aspect"])
    return m


def _add_mrcal(out, dets, cell, cam0, truth, true_skew=0.0):
    """``out['mrcal']``: mrcal's fit on the raw disc centres with its errors, or what failed; nothing when
    no interpreter has mrcal."""
    try:
        m = _mrcal(dets, [d.uv for d in dets], cell.plate.pitch, cam0, (cam0.width, cam0.height))
        if m is not None:
            out["mrcal"] = {**m, **_errors(m, truth, true_skew)}
    except (RuntimeError, OSError, ValueError) as exc:  # mrcal ran and failed: said, not hidden
        out["mrcal"] = {"error": f"{type(exc).__name__}: {exc}"}


#: the interpreter that runs mrcal, found once by main() (workers inherit it)
_MRCAL: dict = {"python": None}


def _errors(est, truth, skew=0.0):
    """Errors against the true camera (``skew``: the true grabber's shear, px of u per px of v)."""
    extra = {}
    if "skew" in est:
        extra = {"skew_err": float(est["skew"] - skew)}
    return {
        **extra,
        "centre_px": float(np.hypot(est["cx"] - truth.cx, est["cy"] - truth.cy)),
        "d": {"f": est["f"] - truth.f, "cx": est["cx"] - truth.cx, "cy": est["cy"] - truth.cy,
              "aspect": est["aspect"] - truth.aspect, **({"skew": est["skew"] - skew} if "skew" in est else {})},
        "aspect_pct": float(100 * abs(est["aspect"] / truth.aspect - 1)),
        "f_pct": float(100 * abs(est["f"] / truth.f - 1)),
        "kappa_pct": float(100 * abs(est["kappa"] / truth.kappa - 1)),
    }


def one_camera(args) -> dict:
    """Studies 1 and 2 on one realistic simulated camera (principal point up to 15 px off, aspect 0.97-1.07).

    Study 1: the planned views (``plan_view_poses``) rendered by the independent test renderer
    (``tests/alt_render.py``), the discs detected once per view, and on those same detections:
      - ours: ``calibrate_intrinsics`` (bias-corrected centres, joint LM, covariance scaled by the
        residual), with the grabber's skew fitted;
      - ``cv2.calibrateCamera`` (extended, for its standard deviations): fx, fy, cx, cy free, one radial
        term (``CV_FLAGS``), started from the cell's guess, on the raw disc centres and on our
        bias-corrected ones; its f is fy, its aspect fy / fx (u = X^ / aspect + cx in ours), its kappa the
        paper's kappa closest to its k1 over the picture (``bench/offline.py``'s ``kappa_equivalent``);
      - mrcal (``bench/_mrcal_peer.py``) where an interpreter imports it: the plate as mrcal's board with
        its warp free, ``LENSMODEL_OPENCV4``, on the raw disc centres; skipped with a note otherwise.
    Per method (``table``): median centre error [px], aspect and f errors [%] against the truth, the RMS of
    the errors over the RMS of the reported sigmas per parameter (1 = honest sigmas), the median time.

    Study 2: one parked picture (the independent renderer): the TCP error of ``calibrate_offline`` with
    the measured camera and with the cell's nominal one, across and along the optical axis [mm], against
    0.02 and 0.08 mm; with the measured camera also ``tcp_sigma_mm``.
    """
    seed, views = args if isinstance(args, tuple) else (args, VIEWS)
    cell = load_cell(default_cell_path())
    w = SimWorld(cell, seed=seed, camera="realistic")
    cam0 = cell.camera.guess()
    plan = plan_view_poses(cell, views, lean_W=LEAN)
    imgs = [_render(w, w.C_H_G @ inv_H(v["W_H_G"]), 1000 * seed + i) for i, v in enumerate(plan)]
    dets, names, skipped = detect_views(imgs, cell.plate, cam0, skip_unusable=True)
    out = {"seed": seed, "truth": {"f": w.camera.f, "kappa": w.camera.kappa, "cx": w.camera.cx, "cy": w.camera.cy,
                                   "aspect": w.camera.aspect},
           "views_detected": len(dets), "views_skipped": skipped}
    try:
        t = time.perf_counter()
        r = calibrate_intrinsics(None, cell.plate, cam0, names, detections=dets)
        dt = time.perf_counter() - t
    except CellError as exc:
        out["error"] = f"{type(exc).__name__}: {exc}"
        return out
    c = r.camera
    ours = {"f": c.f, "cx": c.cx, "cy": c.cy, "aspect": c.aspect, "kappa": c.kappa, "skew": c.skew,
            "sigma": {k: r.sigma[k] for k in ("f", "cx", "cy", "aspect", "skew") if k in r.sigma}, "rms_px": r.rms_px, "seconds": dt,
            "stop_rule_met": r.stop_rule["met"], "cross_check_agree": r.cross_check.get("agree"),
            "views_used": r.views_used}
    out["selfview"] = {**ours, **_errors(ours, w.camera, 0.0)}
    size = (cam0.width, cam0.height)
    raw = _cv2(dets, [d.uv for d in dets], cam0, size)
    out["cv2_raw"] = {**raw, **_errors(raw, w.camera)}
    corrected = [d.uv - plate_image_bias(cell.plate, c, v.C_H_W, d.p_W) for d, v in zip(dets, r.views)]
    cor = _cv2(dets, corrected, cam0, size)
    out["cv2_bias_corrected"] = {**cor, **_errors(cor, w.camera)}
    _add_mrcal(out, dets, cell, cam0, w.camera)
    # study 2: one parked picture, calibrated with the measured camera and with the nominal one
    w.park()
    pic = _render(w, w.C_H_W, 1000 * seed + 999)
    truth = w.C_H_G[:3, 3]
    for key, camera in (("tcp_with_camera", c), ("tcp_nominal", None)):
        try:
            res = calibrate_offline(pic, cell, camera=camera)
            e = res.calibration.C_H_G[:3, 3] - truth
            out[key] = {"across_mm": float(np.hypot(e[0], e[1])), "along_mm": float(abs(e[2])),
                        "err_mm": [float(v) for v in e]}
            if camera is not None:
                out[key]["tcp_sigma_mm"] = tcp_sigma(res, cell, r.covariance[2:, 2:])["tcp_sigma_mm"]
            if camera is None:
                out[key]["warned"] = camera_check(res, cell)["warning"] is not None
        except CellError as exc:
            out[key] = {"error": f"{type(exc).__name__}: {exc}"}
    return out


def _imperfections(profile: str):
    """A profile name or PROFILE:PART -> ``Imperfections``."""
    name, _, part = profile.partition(":")
    if name not in PROFILES:
        raise ValueError(f"profile {profile!r}: expected one of {', '.join(PROFILES)} (or PROFILE:PART)")
    return PROFILES[name].only(part) if part else PROFILES[name]


def one_camera_profile(args) -> dict:
    """Study 1 on a cell with imperfections (a ``--profile``), rendered by the project's renderer.

    The independent renderer draws only the specified plate and no grabber. Ours is also run with the
    plate taken as specified (``selfview_flat_plate``, ``plate_model='flat'``) and without the skew
    (``selfview_no_skew``: the spec's camera model), and the fitted plate shape is listed;
    cv2.calibrateCamera holds K[0, 1] at 0, so it cannot model the grabber's shear. Then study 2 on that
    cell, with and without the skew (``tcp_with_camera``, ``tcp_with_camera_no_skew``), against the centre
    of the real fingers' inner corners.
    """
    seed, profile, views = args if len(args) == 3 else (*args, VIEWS)
    cell = load_cell(default_cell_path())
    w = SimWorld(cell, seed=seed, imperfections=_imperfections(profile), camera="realistic")
    cam0 = cell.camera.guess()
    plate = PLATE_BASE_POSE @ trans(0.0, 0.0, 4.0)
    lean = (inv_H(plate) @ np.array([0.0, 0.0, 0.0, 1.0]))[:2]
    imgs = []
    for i, v in enumerate(plan_view_poses(cell, views, lean_W=lean)):
        w.set_tcp(plate @ v["W_H_G"])
        imgs.append(_project_render(w, seed=1000 * seed + i).image)
    dets, names, skipped = detect_views(imgs, cell.plate, cam0, skip_unusable=True)
    out = {"seed": seed, "profile": profile,
           "truth": {"f": w.camera.f, "kappa": w.camera.kappa, "cx": w.camera.cx, "cy": w.camera.cy,
                     "aspect": w.camera.aspect},
           "views_detected": len(dets), "views_skipped": skipped}
    # the grabber's true shear as a skew: line v's content moved by pll_shear (v - (H-1)/2) / H
    true_skew = w.imperfect.shear_sign * w.imperfections.pll_shear_px / cam0.height
    out["truth"]["skew"] = true_skew
    flat = None
    measured = {}
    for key, model, skew in (("selfview", "bow+dots", True), ("selfview_no_skew", "bow+dots", False),
                             ("selfview_flat_plate", "flat", True)):
        try:
            t = time.perf_counter()
            r = calibrate_intrinsics(None, cell.plate, cam0, names, detections=dets, plate_model=model, skew=skew)
            dt = time.perf_counter() - t
        except CellError as exc:
            out[key] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        c = r.camera
        ours = {"f": c.f, "cx": c.cx, "cy": c.cy, "aspect": c.aspect, "kappa": c.kappa,
                "sigma": {k: r.sigma[k] for k in ("f", "cx", "cy", "aspect", "skew") if k in r.sigma},
                "rms_px": r.rms_px, "seconds": dt,
                "stop_rule_met": r.stop_rule["met"], "cross_check_agree": r.cross_check.get("agree"),
                "views_used": r.views_used, "plate_shape": r.plate_shape,
                "more_views": (r.stop_rule.get("more_views") or {}).get("views_needed")}
        if skew:
            ours["skew"] = c.skew
        out[key] = {**ours, **_errors(ours, w.camera, true_skew)}
        measured[key] = r
        if model == "flat":
            flat = r
    size = (cam0.width, cam0.height)
    raw = _cv2(dets, [d.uv for d in dets], cam0, size)
    out["cv2_raw"] = {**raw, **_errors(raw, w.camera)}
    if flat is not None:  # the flat fit's poses are on the detections' own grids
        corrected = [d.uv - plate_image_bias(cell.plate, flat.camera, v.C_H_W, d.p_W)
                     for d, v in zip(dets, flat.views)]
        cor = _cv2(dets, corrected, cam0, size)
        out["cv2_bias_corrected"] = {**cor, **_errors(cor, w.camera)}
    _add_mrcal(out, dets, cell, cam0, w.camera, true_skew)
    # study 2 on this cell: one parked picture calibrated with the measured camera (with and without its
    # skew); the true TCP is the centre of the real fingers' inner corners (the realistic fingers are off nominal)
    w.set_tcp(plate)
    w.park()
    pic = _project_render(w, seed=1000 * seed + 999).image
    truth = transform_points(w.C_H_G, w.points_G()[:4].mean(0, keepdims=True))[0]
    for key, mkey in (("tcp_with_camera", "selfview"), ("tcp_with_camera_no_skew", "selfview_no_skew")):
        if mkey not in measured:
            continue
        r = measured[mkey]
        try:
            res = calibrate_offline(pic, cell, camera=r.camera)
            e = res.calibration.C_H_G[:3, 3] - truth
            out[key] = {"across_mm": float(np.hypot(e[0], e[1])), "along_mm": float(abs(e[2])),
                        "err_mm": [float(v) for v in e],
                        "tcp_sigma_mm": tcp_sigma(res, cell, r.covariance[2:, 2:])["tcp_sigma_mm"]}
        except CellError as exc:
            out[key] = {"error": f"{type(exc).__name__}: {exc}"}
    return out


#: Study 4's cameras: offsets of the centre [px] (along u) and aspects.
SMALL = ([{"principal_point": [383.5 + d, 287.5]} for d in (0.5, 1.0, 2.0, 4.0)]
         + [{"aspect": a} for a in (1.001, 1.003, 1.01)])


def one_picture(args) -> dict:
    """Studies 3 and 4: the camera check (``camera_check``) on one parked picture calibrated with the
    nominal camera.

    Study 3 runs it on realistic cameras and on the nominal one: how often it warns, and on how many of
    the cameras whose nominal calibration misses the TCP targets. Study 4 (``SMALL``) on cameras a little
    off the nominal one (centre 0.5 to 4 px, aspect 0.1 to 1 %): one picture pins the centre only to a few
    tenths of a pixel, so small errors that still cost more than 0.02 mm may pass unwarned (the reason
    to run ``selfview intrinsics`` on every new camera).
    """
    seed, kind = args
    cell = load_cell(default_cell_path())
    w = SimWorld(cell, seed=seed, camera=kind)
    if isinstance(kind, dict):
        kind = "small: " + ", ".join(f"{k} {v}" for k, v in kind.items())
    w.park()
    pic = _render(w, w.C_H_W, 7 + seed)
    try:
        res = calibrate_offline(pic, cell)
    except CellError as exc:
        return {"seed": seed, "kind": kind, "error": f"{type(exc).__name__}: {exc}"}
    e = res.calibration.C_H_G[:3, 3] - w.C_H_G[:3, 3]
    chk = camera_check(res, cell)
    across, along = float(np.hypot(e[0], e[1])), float(abs(e[2]))
    return {"seed": seed, "kind": kind, "across_mm": across, "along_mm": along,
            "misses_targets": bool(across > TARGET_ACROSS_MM or along > TARGET_ALONG_MM),
            "warned": chk["warning"] is not None, "chi2": chk.get("chi2"),
            "offset_px": float(np.hypot(w.camera.cx - 383.5, w.camera.cy - 287.5)), "aspect": w.camera.aspect}


def _median(v):
    v = [x for x in v if x is not None and np.isfinite(x)]
    return float(statistics.median(v)) if v else None


def table(per_camera):
    ok = [p for p in per_camera if "selfview" in p and "error" not in p["selfview"]]
    out = {}
    for m in ("selfview", "selfview_no_skew", "selfview_flat_plate", "cv2_raw", "cv2_bias_corrected", "mrcal"):
        rows = [p[m] for p in ok if m in p and "error" not in p[m]]
        if not rows:
            continue
        entry = {
            "median_centre_err_px": _median([r["centre_px"] for r in rows]),
            "median_aspect_err_pct": _median([r["aspect_pct"] for r in rows]),
            "median_f_err_pct": _median([r["f_pct"] for r in rows]),
            "median_kappa_err_pct": _median([r["kappa_pct"] for r in rows]),
            "median_seconds": _median([r["seconds"] for r in rows]),
            # the fit's time over cv2.calibrateCamera's on the same detections, the same run (issue 31: <= 10)
            "median_seconds_over_cv2": _median([p[m]["seconds"] / p["cv2_raw"]["seconds"] for p in ok
                                                if m in p and "error" not in p[m] and "cv2_raw" in p]),
            "median_sigma": {k: _median([r["sigma"][k] for r in rows]) for k in ("f", "cx", "cy", "aspect")},
        }
        # observed spread (RMS of the errors) over the RMS of the reported sigmas, per parameter
        entry["spread_over_sigma"] = {
            k: float(np.sqrt(np.mean([r["d"][k] ** 2 for r in rows])) / np.sqrt(np.mean([r["sigma"][k] ** 2 for r in rows])))
            for k in ("f", "cx", "cy", "aspect")
        }
        if all("skew" in r["sigma"] and "skew" in r["d"] for r in rows):
            entry["median_skew_err"] = _median([abs(r["d"]["skew"]) for r in rows])
            entry["median_sigma"]["skew"] = _median([r["sigma"]["skew"] for r in rows])
            entry["spread_over_sigma"]["skew"] = float(np.sqrt(np.mean([r["d"]["skew"] ** 2 for r in rows]))
                                                       / np.sqrt(np.mean([r["sigma"]["skew"] ** 2 for r in rows])))
        out[m] = entry
    s = out.get("selfview")
    if s:
        out["selfview_meets_issue"] = {
            "centre": s["median_centre_err_px"] < ISSUE["centre_px"],
            "aspect": s["median_aspect_err_pct"] < ISSUE["aspect_pct"],
            "f": s["median_f_err_pct"] < ISSUE["f_pct"],
            "sigmas_within_factor_2": all(1 / ISSUE["sigma_factor"] <= v <= ISSUE["sigma_factor"]
                                          for v in s["spread_over_sigma"].values()),
        }
    for key in ("tcp_with_camera", "tcp_with_camera_no_skew", "tcp_nominal"):
        rows = [p[key] for p in ok if key in p and "error" not in p[key]]
        if rows:
            out[key] = {"median_across_mm": _median([r["across_mm"] for r in rows]),
                        "median_along_mm": _median([r["along_mm"] for r in rows]),
                        "max_across_mm": max(r["across_mm"] for r in rows),
                        "max_along_mm": max(r["along_mm"] for r in rows), "n": len(rows)}
            if key.startswith("tcp_with_camera"):
                # the TCP errors' RMS per camera axis over the RMS of the reported tcp_sigma_mm (1 = honest)
                e = np.array([r["err_mm"] for r in rows])
                sg = np.array([r["tcp_sigma_mm"] for r in rows])
                out[key]["spread_over_tcp_sigma"] = [float(v) for v in np.sqrt((e**2).mean(0)) / np.sqrt((sg**2).mean(0))]
                out[key]["median_tcp_sigma_mm"] = [float(v) for v in np.median(sg, axis=0)]
    return out


def rates(pics):
    out = {}
    for kind in ("ideal", "realistic"):
        rows = [p for p in pics if p["kind"] == kind and "error" not in p]
        costly = [p for p in rows if p["misses_targets"]]
        out[kind] = {
            "pictures": len(rows), "failed": sum(1 for p in pics if p["kind"] == kind and "error" in p),
            "warned": sum(p["warned"] for p in rows),
            "warning_rate": (sum(p["warned"] for p in rows) / len(rows)) if rows else None,
            "miss_targets": len(costly),
            "warned_when_missing_targets": (sum(p["warned"] for p in costly) / len(costly)) if costly else None,
            "max_chi2": max((p["chi2"] or 0.0) for p in rows) if rows else None,
        }
    return out


def _photo_cells(folder: Path) -> dict:
    """{(width, height): cell} of the cell files in ``folder``."""
    cells = {}
    for f in sorted(folder.glob("cell*.yaml")):
        c = load_cell(f)
        cells[(c.camera.width, c.camera.height)] = c
    return cells


def _in_sigmas(ours, theirs) -> dict:
    return {k: float((ours[k] - theirs[k]) / np.hypot(ours["sigma"][k], theirs["sigma"][k]))
            for k in ("f", "cx", "cy", "aspect")}


def photo_study() -> dict:
    """Study 5: ours beside findCirclesGrid and cv2.calibrateCamera on real photographs.

    Each set of printed dot-grid photographs the project did not make (``PHOTO_SETS``, in ``tests/data``,
    each with a cell file per picture size). Per picture the discs ``detect_plate`` finds beside
    ``cv2.findCirclesGrid``'s (symmetric grid) and the distance between the centres both found [px]; per
    camera (pictures of one size, at least 4) ``calibrate_intrinsics`` run as ``selfview intrinsics`` runs
    it (the skew fitted only when the views pin it, ``skew_fit`` says which and why; the skew always fitted
    is listed apart) beside ``cv2.calibrateCamera`` (``CV_FLAGS``) on findCirclesGrid's centres and on ours,
    each difference in units of the combined sigmas sqrt(s_ours^2 + s_cv2^2) for f, cx, cy and the aspect.
    Each fit's ``seconds`` on the detections (detection not counted); ``fit_seconds_over_cv2_on_our_discs``
    the first one's (with the halves' cross-check, as the command runs it) over cv2's on the same discs.
    """
    from types import SimpleNamespace

    from selfview.measurement.plates import detect_plate

    out = {}
    for folder, pattern in PHOTO_SETS:
        cells = _photo_cells(PHOTO_DATA / folder)
        files = sorted((PHOTO_DATA / folder).glob(pattern))
        rows, groups = [], {}
        for f in files:
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            cell = cells[(img.shape[1], img.shape[0])]
            pl = cell.plate
            ok, ref = cv2.findCirclesGrid(img, (pl.cols, pl.rows), flags=cv2.CALIB_CB_SYMMETRIC_GRID)
            row = {"picture": f.name, "size": [img.shape[1], img.shape[0]], "opencv": len(ref) if ok else 0}
            try:
                det = detect_plate(img, pl, camera=cell.camera_guess())
            except CellError as exc:
                row.update(ours=0, refused=str(exc))
                rows.append(row)
                continue
            row.update(ours=len(det), rejected=det.rejected)
            if ok:
                ref = ref.reshape(-1, 2).astype(float)
                d = np.linalg.norm(det.uv[:, None, :] - ref[None], axis=2)
                near = d.min(0)  # per OpenCV disc, the nearest of ours
                row["opencv_found_by_ours"] = int(np.sum(near < 1.0))
                both = near[near < 1.0]
                row["centre_agreement_px"] = {"median": float(np.median(both)), "max": float(both.max())}
                k = np.arange(len(ref))
                p = np.column_stack([k % pl.cols, k // pl.cols, np.zeros(len(k))]) * pl.pitch
                groups.setdefault((img.shape[1], img.shape[0]), []).append((det, SimpleNamespace(p_W=p), ref, f.name))
            rows.append(row)
        cams = []
        for size, views in groups.items():
            if len(views) < 4:
                continue
            cell = cells[size]
            cam0 = cell.camera_guess()
            dets = [v[0] for v in views]
            entry = {"size": list(size), "pictures": len(views)}
            try:
                fits = {}
                variants = (("selfview", "auto", "auto"), ("selfview_bent_plate", "auto", "bow+dots"),
                            ("selfview_skew_fitted", True, "auto"), ("selfview_flat_plate", "auto", "flat"),
                            ("selfview_flat_no_skew", False, "flat"))
                for key, skew, plate_model in variants:
                    t = time.perf_counter()
                    r = calibrate_intrinsics(None, cell.plate, cam0, [v[3] for v in views], detections=dets,
                                             skew=skew, cross_check=key == "selfview", plate_model=plate_model)
                    dt = time.perf_counter() - t
                    c = r.camera
                    fits[key] = {"views_used": r.views_used, "f": c.f, "cx": c.cx, "cy": c.cy, "aspect": c.aspect,
                                 "kappa": c.kappa,
                                 "skew": c.skew, "rms_px": r.rms_px, "discs": int(sum(v.discs for v in r.views)),
                                 "views_left_out": [list(x) if isinstance(x, tuple) else x for x in r.skipped],
                                 "plate_model": r.plate_shape.get("model", plate_model),
                                 "plate_model_why": r.plate_shape.get("why"),
                                 "sigma": {k: r.sigma[k] for k in ("f", "cx", "cy", "aspect", "skew") if k in r.sigma},
                                 "skew_fit": r.skew_fit, "seconds": dt}
                entry.update(fits)
                entry["selfview"]["skew_note"] = fits["selfview"]["skew_fit"]["note"] + " (selfview_skew_fitted has it free)"
                entry["selfview_flat_plate"]["note"] = "the plate taken as specified, as cv2.calibrateCamera takes it"
            except CellError as exc:
                entry["selfview"] = {"error": f"{type(exc).__name__}: {exc}"}
            cvd = _cv2([v[1] for v in views], [v[2] for v in views], cam0, size)
            cvd["discs"] = int(sum(len(v[2]) for v in views))
            entry["cv2_on_findCirclesGrid"] = cvd
            entry["cv2_on_our_discs"] = {**_cv2(dets, [d.uv for d in dets], cam0, size),
                                         "discs": int(sum(len(d) for d in dets))}
            if "seconds" in entry.get("selfview", {}):
                # as `selfview intrinsics` fits (with the halves' cross-check), over cv2 on the same discs
                entry["fit_seconds_over_cv2_on_our_discs"] = (entry["selfview"]["seconds"]
                                                              / entry["cv2_on_our_discs"]["seconds"])
            if "error" not in entry.get("selfview", {"error": 1}):
                entry["ours_minus_cv2_in_combined_sigmas"] = _in_sigmas(entry["selfview"], cvd)
                entry["ours_minus_cv2_on_our_discs_in_combined_sigmas"] = _in_sigmas(
                    entry["selfview"], entry["cv2_on_our_discs"])
                entry["flat_plate_minus_cv2_in_combined_sigmas"] = _in_sigmas(entry["selfview_flat_plate"], cvd)
                entry["skew_fitted_minus_cv2_in_combined_sigmas"] = _in_sigmas(entry["selfview_skew_fitted"], cvd)
                entry["bent_plate_minus_cv2_in_combined_sigmas"] = _in_sigmas(entry["selfview_bent_plate"], cvd)
                entry["flat_no_skew_minus_cv2_in_combined_sigmas"] = _in_sigmas(entry["selfview_flat_no_skew"], cvd)
                entry["within_3_sigmas"] = all(abs(v) <= 3 for v in entry["ours_minus_cv2_in_combined_sigmas"].values())
            cams.append(entry)
        out.setdefault(folder, {"pictures": [], "cameras": []})
        out[folder]["pictures"] += rows
        out[folder]["cameras"] += cams
    for res in out.values():
        pics = [r for r in res["pictures"] if r.get("opencv")]
        res["every_opencv_disc_found"] = all(r.get("opencv_found_by_ours") == r["opencv"] for r in pics)
        res["none_refused"] = not any("refused" in r for r in res["pictures"])
    out["notes"] = ("cv2's aspect sigma is fy / fx with the sigmas of fx and fy taken as independent (its "
                    "extended calibration gives no covariance), so it overstates the aspect's uncertainty")
    return out


#: Every real set under tests/data with several views of one camera: (name, directory, picture pattern, cell
#: file or None: the directory's plate.yaml with a camera guessed from the views, as ``selfview intrinsics
#: --plate`` does). NiftyCal's dots are one view per camera and cannot give a joint fit.
REAL_SETS = (("visp-stills", "visp-circles", "circles-0*.jpg", "cell.yaml"),
             ("visp-640x480", "visp-circles", "grid36-0*.png", "cell-640x480.yaml"),
             ("boofcv-stills", "boofcv-circles", "image0000*.jpg", None),
             ("boofcv-video", "boofcv-circles-video", "frame*.jpg", None),
             ("charuco", "charuco-basler", "basler-*.jpg", None),
             ("chessboard", "opencv-chessboard", "left*.jpg", None))


def _counting_fits():
    """A context that counts the joint fits (``fit_views``) and LM runs a calibration makes: {fits, lm} (the
    halves' cross-check makes none: it is to first order)."""
    import contextlib

    from selfview.estimation.intrinsics import calibrate as cal_mod, fit as fit_mod

    @contextlib.contextmanager
    def ctx():
        n = {"fits": 0, "lm": 0}
        saved = (cal_mod.fit_views, fit_mod.levenberg_marquardt)

        def fits(*a, **k):
            n["fits"] += 1
            return saved[0](*a, **k)

        def lm(*a, **k):
            n["lm"] += 1
            return saved[1](*a, **k)

        cal_mod.fit_views = fits
        fit_mod.levenberg_marquardt = lm
        try:
            yield n
        finally:
            cal_mod.fit_views, fit_mod.levenberg_marquardt = saved
    return ctx()


def real_sets_study(repeats: int = 3) -> dict:
    """Study 6: ``calibrate_intrinsics`` as ``selfview intrinsics`` runs it (its defaults: plate model and
    skew by evidence, the halves' cross-check) beside cv2.calibrateCamera (``CV_FLAGS``) on the same
    detections of every real set (``REAL_SETS``), timed interleaved ``repeats`` times in this run (median
    seconds, their ratio: issue 31 asks at most 10), the joint fits and LM runs per result, the plate model
    chosen and why, and f, cx, cy minus OpenCV's in combined sigmas (issue 31: within 2)."""
    from selfview.estimation.intrinsics import guess_camera
    from selfview.files.cell import load_plate

    out = {}
    for name, folder, pattern, cell_file in REAL_SETS:
        files = sorted((PHOTO_DATA / folder).glob(pattern))
        imgs = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files]
        size = (imgs[0].shape[1], imgs[0].shape[0])
        if cell_file:
            cell = load_cell(PHOTO_DATA / folder / cell_file)
            plate, cam0 = cell.plate, cell.camera.guess()
            dets, names, _ = detect_views(imgs, plate, cam0, [f.name for f in files], skip_unusable=True)
        else:
            plate = load_plate(PHOTO_DATA / folder / "plate.yaml")
            dets, names, _ = detect_views(imgs, plate, None, [f.name for f in files], skip_unusable=True)
            cam0 = guess_camera(dets, *size)
        ours, theirs = [], []
        for _ in range(repeats):
            with _counting_fits() as n:
                t = time.perf_counter()
                r = calibrate_intrinsics(None, plate, cam0, names, detections=dets)
                ours.append(time.perf_counter() - t)
            cvd = _cv2(dets, [d.uv for d in dets], cam0, size)
            theirs.append(cvd["seconds"])
        c = r.camera
        mine = {"f": c.f, "cx": c.cx, "cy": c.cy, "aspect": c.aspect, "sigma": r.sigma}
        z = _in_sigmas(mine, cvd)
        out[name] = {"views": len(dets), "views_used": r.views_used, "joint_fits": n["fits"], "lm_runs": n["lm"],
                     "plate_model": r.plate_shape["model"], "plate_model_why": r.plate_shape["why"],
                     "skew_note": r.skew_fit.get("note"), "seconds": _median(ours), "cv2_seconds": _median(theirs),
                     "seconds_over_cv2": _median(ours) / _median(theirs),
                     "minus_cv2_in_combined_sigmas": {k: z[k] for k in ("f", "cx", "cy")},
                     "within_2_sigmas": all(abs(z[k]) <= 2 for k in ("f", "cx", "cy"))}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cameras", type=int, default=10, help="simulated cameras for the intrinsics table (default 10)")
    ap.add_argument("--pictures", type=int, default=30, help="parked pictures per kind for the warning rates (default 30)")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    ap.add_argument("--views", type=int, default=VIEWS, help=f"planned views per camera (default {VIEWS})")
    ap.add_argument("--quick", action="store_true", help="a small run: 2 cameras, 4 pictures per kind")
    ap.add_argument("--profile", nargs="+", default=["ideal", "realistic"],
                    help="simulated cells for study 1: 'ideal' (the independent renderer, and studies 2-4) and "
                         "imperfection profiles or PROFILE:PART, e.g. realistic:plate (default: ideal realistic)")
    ap.add_argument("--no-mrcal", action="store_true", help="do not look for mrcal (the peer is then skipped)")
    ap.add_argument("--photos-only", action="store_true", help="only study 5, the real photographs")
    ap.add_argument("--real-sets", action="store_true",
                    help="only study 6: every real set's fit against cv2.calibrateCamera, time and agreement")
    ap.add_argument("--repeats", type=int, default=3, help="timings per set in study 6 (default 3)")
    args = ap.parse_args(argv)
    if args.real_sets:
        print(json.dumps({"benchmark": "intrinsics on every real set vs cv2.calibrateCamera (same detections)",
                          "opencv_flags": " | ".join(CV_FLAGS) + " (fx, fy, cx, cy free)",
                          "real_sets": real_sets_study(max(1, args.repeats))}, default=float))
        return 0
    if args.photos_only:
        print(json.dumps({"benchmark": "intrinsics on real photographs vs cv2.findCirclesGrid and cv2.calibrateCamera",
                          "opencv_flags": " | ".join(CV_FLAGS) + " (fx, fy, cx, cy free)",
                          "real_photographs": photo_study()}, default=float))
        return 0
    for prof in args.profile:
        if prof != "ideal":
            try:
                _imperfections(prof)
            except (ValueError, ConfigError) as exc:  # an unknown profile or part
                ap.error(str(exc))
    if args.quick:
        args.cameras, args.pictures = 2, 4
    if args.cameras < 1 or args.pictures < 1 or args.views < 4:
        ap.error("expected --cameras >= 1, --pictures >= 1 and --views >= 4")
    if _alt is None:
        print(json.dumps({"benchmark": "intrinsics", "skipped": "the independent renderer (tests/alt_render.py) is "
                                                                 "not beside this copy: run from a source tree"}))
        return 0
    t0 = time.perf_counter()
    if not args.no_mrcal:
        from selfview.bench import _mrcal_peer

        _MRCAL["python"] = _mrcal_peer.find_python()  # before the workers start: they inherit it
    seeds = [(s, args.views) for s in range(args.cameras)]
    ideal = "ideal" in args.profile
    work = [(100 + s, k) for k in ("ideal", "realistic") for s in range(args.pictures)] if ideal else []
    work += [(200 + i, k) for i, k in enumerate(SMALL)] if ideal else []
    others = [p for p in dict.fromkeys(args.profile) if p != "ideal"]
    pwork = [(s, p, v) for p in others for s, v in seeds]
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as ex:
            per_camera = list(ex.map(one_camera, seeds)) if ideal else []
            pics = list(ex.map(one_picture, work))
            per_profile = list(ex.map(one_camera_profile, pwork))
    else:
        per_camera = [one_camera(s) for s in seeds] if ideal else []
        pics = [one_picture(a) for a in work]
        per_profile = [one_camera_profile(a) for a in pwork]
    profiles = {}
    for p in others:
        rows = [r for r in per_profile if r["profile"] == p]
        shapes = [r["selfview"]["plate_shape"] for r in rows if "selfview" in r and "plate_shape" in r["selfview"]]
        profiles[p] = {
            "renderer": "selfview.mocks.render (the project's: the independent one has no imperfections)",
            "intrinsics": table(rows),
            "plate_models_fitted": {m: sum(1 for sh in shapes if sh.get("model") == m) for m in ("bow+dots", "bow", "flat")},
            "per_camera": rows,
        }
    if _MRCAL["python"] is not None:
        from selfview.bench import _mrcal_peer

        mrcal_note = (f"mrcal {_mrcal_peer.mrcal_version(_MRCAL['python']) or '(version not reported)'} run in its own interpreter "
                      f"({Path(_MRCAL['python']).name}): {_mrcal_peer.LENSMODEL}, the plate's warp free, outlier "
                      "rejection on, on the raw disc centres (study 1 and each profile; no skew term: mrcal's "
                      "models have none)")
    else:
        mrcal_note = "no interpreter imports mrcal (Debian's python3-mrcal, or SELFVIEW_MRCAL_PYTHON): skipped"
    out = {
        "benchmark": "multi-view intrinsics vs cv2.calibrateCamera (and mrcal)",
        "renderer": "tests/alt_render.py (independent)",
        "views_per_camera": args.views,
        "intrinsics": table(per_camera) if ideal else None,
        "profiles": profiles,
        "issue_targets": ISSUE,
        "tcp_targets_mm": {"across": TARGET_ACROSS_MM, "along": TARGET_ALONG_MM},
        "camera_check": rates(pics),
        "camera_check_small_errors": [
            {k: p.get(k) for k in ("kind", "across_mm", "along_mm", "misses_targets", "warned", "chi2", "error")}
            for p in pics if str(p["kind"]).startswith("small")],
        "mrcal": mrcal_note,
        "opencv_flags": " | ".join(CV_FLAGS) + " (fx, fy, cx, cy free)",
        "opencv_skew": "cv2.calibrateCamera has no skew parameter (K[0, 1] is held at 0; only cv2.fisheye has "
                       "CALIB_FIX_SKEW): it cannot model a grabber's shear",
        "real_photographs": photo_study(),
        "real_sets": real_sets_study(1),
        "per_camera": per_camera,
        "pictures": pics,
        "seconds": round(time.perf_counter() - t0, 1),
        "versions": {"numpy": np.__version__, "opencv": cv2.__version__, "python": sys.version.split()[0]},
    }
    print(json.dumps(out, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
