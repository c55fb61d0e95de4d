"""Study: the fingertips measured over real photographs laid as the table, beside discs and partly covered.

The photographs shipped inside scikit-image (gravel, grass, brick, coffee, ...; read from the installed
package, nothing is downloaded) lie ``distance_mm`` (15..80) beyond the plate's plane, blurred, in both
renderers. Each frame measured by each method (``--methods``) is found, missed or wrong (``judge_pose``,
``judge_corners``). Prints one JSON object: per renderer, kind, background family and photograph.

    python bench/clutter.py [--trials 2] [--steps 4] [--photos gravel,grass] [--quick]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

if not __package__ and (Path(__file__).resolve().parents[1] / "pyproject.toml").is_file():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from selfview.files.cell import default_cell_path, load_cell  # noqa: E402
from selfview.errors import CalibrationError  # noqa: E402

if str(Path(__file__).resolve().parents[1]) not in sys.path:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the scenes live beside the tests

from tests.clutter_scenes import (  # noqa: E402,F401  (the scenes, shared with the tests)
    DEFAULT_PHOTOS,
    FAMILIES,
    SETTINGS,
    Frame,
    Sequence,
    available_photos,
    disc_picture,
    load_photo,
    online_sequence,
)

WRONG_MM = 0.1  # a pose marked good but further off than this (any TCP axis) is wrong
CORNER_PX = 0.5  # a corner further off than this is wrong (disc pictures)
ONLINE_POINTS = range(4)  # 4P-I's points
QUICK_PHOTOS = 4  # --quick: the first photographs of --photos


# --- measuring ------------------------------------------------------------------------------------
def judge_pose(result, seq: Sequence, frame: Frame) -> dict:
    """found / missed / wrong for one on-line frame measured as ``result`` (a FingertipResult).

    ``found``: marked good and right; ``missed``: not marked good (points not found, 4P-I refused, or the
    measurement's own quality check said "not found"); ``wrong``: marked good but the pose more than
    ``WRONG_MM`` off in some axis of the TCP."""
    from selfview.estimation.online import estimate

    quality_ok = getattr(result, "quality_ok", True)
    need = list(ONLINE_POINTS)
    ok = bool(np.all(result.found[need])) and quality_ok
    out = {"verdict": "missed", "err_mm": None, "corner_px": None}
    fin = result.found[need] & frame.corner_visible[need]
    if np.any(fin):
        out["corner_px"] = float(np.max(np.linalg.norm(result.uv[need][fin] - frame.corner_uv[need][fin], axis=1)))
    if not ok:
        out["why"] = getattr(result, "lost_reason", None) or "; ".join(
            f"{k}: {r}" for k, r in enumerate(result.reasons) if k in need and r)
        return out
    try:
        est = estimate("4P-I", seq.C_H_G_pred, seq.p_G6, result.uv, result.found, seq.camera)
    except CalibrationError as exc:
        out["why"] = str(exc)
        return out
    err = np.abs(est.C_H_G[:3, 3] - frame.C_H_G[:3, 3])
    out["err_mm"] = err.tolist()
    if getattr(result, "C_H_G", None) is not None:  # method E: the model's own pose
        out["err_E_mm"] = np.abs(np.asarray(result.C_H_G)[:3, 3] - frame.C_H_G[:3, 3]).tolist()
    out["verdict"] = "wrong" if float(err.max()) > WRONG_MM else "found"
    return out


def judge_corners(result, frame: Frame) -> dict:
    """found / missed / wrong for a parked picture: all six corners within CORNER_PX."""
    vis = frame.corner_visible
    err = np.linalg.norm(result.uv - frame.corner_uv, axis=1)
    quality_ok = getattr(result, "quality_ok", True)
    good = result.found & vis & quality_ok
    if np.any(good & ~(err <= CORNER_PX)):
        v = "wrong"
    elif np.all(result.found[vis]) and quality_ok:
        v = "found"
    else:
        v = "missed"
    return {"verdict": v, "corner_px": None if not np.any(good) else float(np.nanmax(err[good])),
            "n_found": int(np.sum(good))}


def measure_sequence(seq: Sequence, cell, methods=("search", "model-tracker")) -> dict:
    """Run each method over the sequence's disturbed frames; per method a list of per-frame verdicts.

    ``search``: the corner search (``find_fingertips``); ``model-search`` (``find_fingertips(...,
    model=True)``) and ``model-tracker`` (a ``SilhouetteTracker`` run over the sequence, primed by a search
    of the undisturbed picture) the model-based measurement, whose own pose is also scored as method E
    (``E_tcp_err_*``). The same frames for all; each followed by 4P-I."""
    from selfview.measurement.fingers import find_fingertips
    from selfview.measurement.fingers import SilhouetteTracker

    out = {}
    if seq.kind == "disc":
        fr = seq.frames[0]
        for m, model in (("search", False), ("model-search", True)):
            if m in methods:
                res = find_fingertips(fr.image, seq.camera, seq.C_H_G_pred, cell.gripper, seq.gap, model=model)
                out[m] = [judge_corners(res, fr)]
        return out
    if "model-search" in methods:
        out["model-search"] = [
            judge_pose(find_fingertips(fr.image, seq.camera, seq.C_H_G_pred, cell.gripper, seq.gap,
                                       points=ONLINE_POINTS, model=True), seq, fr)
            for fr in seq.frames[1:]
        ]
    if "model-tracker" in methods:
        out["model-tracker"] = _tracked(SilhouetteTracker(seq.camera, cell.gripper, points=ONLINE_POINTS), seq,
                                        timed=True)
    if "search" in methods:
        out["search"] = [
            judge_pose(find_fingertips(fr.image, seq.camera, seq.C_H_G_pred, cell.gripper, seq.gap,
                                       points=ONLINE_POINTS), seq, fr)
            for fr in seq.frames[1:]
        ]
    return out


def _tracked(tr, seq: Sequence, *, timed: bool = False) -> list[dict]:
    """A tracker primed on the sequence's first frame, then judged on each later one (``timed``: each
    step's time in ``ms``)."""
    tr.find(seq.frames[0].image, seq.C_H_G_pred, seq.gap)
    verdicts = []
    for fr in seq.frames[1:]:
        t0 = time.perf_counter()
        res = tr.find(fr.image, seq.C_H_G_pred, seq.gap)
        v = judge_pose(res, seq, fr)
        v["tracked"] = bool(res.tracked)
        if timed:
            v["ms"] = (time.perf_counter() - t0) * 1e3
        verdicts.append(v)
    return verdicts


def build(cell, renderers, photos, trials: int, steps: int, series=("cable", "tilt"), disc_trials: int = 0,
          occluded_trials: int = 0, plain: bool = True):
    """Generate the study's sequences (a generator, so that a caller measures as they come).

    Renderers: the project's (``selfview.mocks.render``, ``Backdrop``) and the independent one of the
    tests (``tests/alt_render.py``, ``table_image``; only from a source tree); the scenes are built by
    ``tests/clutter_scenes.py``. Kinds:
    - ``online``: a sequence per trial. The gripper parked and its mount known (the true ``C_H_G`` before
      the disturbance is the prediction, so the study measures the measurement, not the off-line
      calibration), then lifted over the photograph and the camera moved by one draw of the paper's
      'cable' or 'tilt' series in ``steps`` equal rotations, one picture each;
    - ``disc``: parked on the plate with a fingertip corner on or beside a printed disc (the parks drawn
      until one is), measured by the full search from the cell's mount guess; all six corners;
    - ``occluded`` (independent renderer only): the online pictures with a cable (a thin box) across one
      finger.
    """
    k = 0
    for renderer in renderers:
        names = ([None] if plain else []) + list(photos)
        for name in names:
            for t in range(trials):
                for s_i, series_name in enumerate(series):
                    dist, blur = SETTINGS[(k + s_i) % len(SETTINGS)]
                    seed = 101 + 7 * k + s_i
                    yield online_sequence(cell, renderer, name, series_name, seed, dist, blur, steps)
                k += 1
        if renderer == "alt":
            for t in range(occluded_trials):
                name = photos[t % len(photos)]
                dist, blur = SETTINGS[t % len(SETTINGS)]
                yield online_sequence(cell, renderer, name, ("cable", "tilt")[t % 2], 501 + t, dist, blur, steps,
                                      occluded=True)
        for t in range(disc_trials):
            yield disc_picture(cell, renderer, 900 + t, on=bool(t % 2))[0]


def family(seq: Sequence) -> str:
    if seq.kind == "disc":
        return seq.photo
    if seq.kind == "occluded":
        return "occluded"
    return "plain" if seq.photo == "plain" else FAMILIES.get(seq.photo, "other")


def tabulate(rows: list[dict]) -> dict:
    """rows: {renderer, kind, family, photo, method, verdict, err_mm, ...} -> counts and accuracy."""
    table: dict = {}
    for r in rows:
        for key in (("all", r["method"]), (r["renderer"], r["family"], r["method"]), ("family", r["family"], r["method"])):
            t = table.setdefault(" / ".join(key), {"frames": 0, "found": 0, "missed": 0, "wrong": 0, "_err": [],
                                                   "_errE": [], "_ms": []})
            t["frames"] += 1
            t[r["verdict"]] += 1
            if r["verdict"] != "missed" and r.get("err_mm") is not None:
                t["_err"].append(r["err_mm"])
            if r["verdict"] != "missed" and r.get("err_E_mm") is not None:
                t["_errE"].append(r["err_E_mm"])
            if r.get("ms") is not None:
                t["_ms"].append(r["ms"])
    for t in table.values():
        e = t.pop("_err")
        e = np.array(e) if e else None
        eE, ms = t.pop("_errE"), t.pop("_ms")
        if eE:
            t["E_tcp_err_mean_mm"] = [round(float(v), 4) for v in np.mean(eE, axis=0)]
            t["E_tcp_err_max_mm"] = round(float(np.max(eE)), 4)
        if ms:
            t["step_ms_median"] = round(float(np.median(ms)), 2)
        t["found_pct"] = round(100.0 * t["found"] / max(t["frames"], 1), 2)
        if e is not None and e.ndim == 2:
            t["4P-I_tcp_err_mean_mm"] = [round(float(v), 4) for v in e.mean(axis=0)]
            t["4P-I_tcp_err_max_mm"] = round(float(e.max()), 4)
    return dict(sorted(table.items()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=2, help="trials per photograph and series")
    ap.add_argument("--steps", type=int, default=4, help="disturbed frames per trial")
    ap.add_argument("--photos", default=",".join(DEFAULT_PHOTOS))
    ap.add_argument("--renderers", default="mocks,alt")
    ap.add_argument("--disc", type=int, default=10, help="parked pictures beside/on a disc per renderer")
    ap.add_argument("--occluded", type=int, default=6, help="trials with a cable across a finger (alt renderer)")
    ap.add_argument("--methods", default="search,model-search,model-tracker")
    ap.add_argument("--frames-out", default=None, help="also write every frame's verdict to this JSON file")
    ap.add_argument("--quick", action="store_true",
                    help=f"a small run: one trial of {QUICK_PHOTOS} photographs, 3 steps, 6 disc pictures and 2 "
                         "occluded trials per renderer")
    args = ap.parse_args(argv)
    if args.quick:
        args.trials, args.steps, args.disc, args.occluded = 1, 3, 6, 2
        args.photos = ",".join(args.photos.split(",")[:QUICK_PHOTOS])
    cv2.setNumThreads(1)
    cell = load_cell(default_cell_path())
    renderers = [r for r in args.renderers.split(",") if r]
    photos = [p for p in args.photos.split(",") if p]
    methods = tuple(args.methods.split(","))
    rows = []
    t0 = time.perf_counter()
    for seq in build(cell, renderers, photos, args.trials, args.steps, disc_trials=args.disc,
                     occluded_trials=args.occluded):
        res = measure_sequence(seq, cell, methods)
        for method, verdicts in res.items():
            for i, v in enumerate(verdicts):
                rows.append({"renderer": seq.renderer, "kind": seq.kind, "family": family(seq), "photo": seq.photo,
                             "distance_mm": seq.distance_mm, "defocus_px": seq.defocus_px, "method": method,
                             "frame": i, **v})
    out = {
        "benchmark": "clutter",
        "renderers": renderers,
        "photos": photos,
        "trials": args.trials,
        "steps": args.steps,
        "wrong_mm": WRONG_MM,
        "corner_px": CORNER_PX,
        "table": tabulate(rows),
        "seconds": round(time.perf_counter() - t0, 1),
    }
    if args.frames_out:
        Path(args.frames_out).write_text(json.dumps(rows))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
