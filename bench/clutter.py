"""Study: the fingertips over backgrounds the project did not make (real photographs), beside discs, and
partly covered.

The photographs shipped inside scikit-image (``skimage/data``: gravel, grass, brick, coffee, a motorcycle,
an astronaut, the cameraman, coins, ...; read with OpenCV from the installed package, nothing is
downloaded) are laid as a table ``distance_mm`` (15..80) beyond the plate's plane, where the fingertips
stand while parked, with a defocus blur, in both renderers: the project's (``selfview.mocks.render``,
``Backdrop``) and the independent one of the tests (``tests/alt_render.py``, ``table_image``; only when
run from a source tree). Three kinds of picture:

- ``online``: a sequence per trial. The gripper parked and its mount known (the true ``C_H_G`` before
  the disturbance is the prediction, so the study measures the measurement, not the off-line
  calibration), then the gripper lifted over the photograph and the camera moved by one draw of the
  paper's 'cable' or 'tilt' series in ``steps`` equal rotations, one picture each. Every disturbed
  picture is measured by the full search from the prediction (``search``) and by a
  ``FingertipTracker`` run over the sequence (``tracker``, primed by a search of the undisturbed
  picture), each followed by 4P-I;
- ``disc``: parked on the plate with a fingertip corner on or beside a printed disc (the parks drawn
  until one is), measured by the full search from the cell's mount guess; all six corners;
- ``occluded`` (independent renderer only): the online pictures with a cable (a thin box) across one finger.

Methods (``--methods``): ``search`` and ``tracker`` the corner search (``find_fingertips``) and the
corner tracker (``FingertipTracker``) as they were before the model; ``model-search``
(``find_fingertips(..., model=True)``) and ``model-tracker`` (``SilhouetteTracker``) the model-based
measurement, whose own pose is also scored as method E (``E_tcp_err_*``). The same frames for all four.

Each measured frame is one of: ``found`` (marked good and right), ``missed`` (not marked good: points
not found, 4P-I refused, or the measurement's own quality check said "not found"), ``wrong`` (marked
good but the pose more than ``WRONG_MM`` off in some axis of the TCP, or, for ``disc``, a found corner
more than 0.5 px off). Prints one JSON object: per renderer, kind, background family and photograph.

    python bench/clutter.py [--trials 2] [--steps 4] [--photos gravel,grass] [--quick]

``--quick``: one trial per photograph of the first four, 3 steps, 6 disc pictures and 2 occluded trials
per renderer (some 80 frames per method instead of some 330).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

if not __package__ and (Path(__file__).resolve().parents[1] / "pyproject.toml").is_file():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from selfview.cell import default_cell_path, load_cell  # noqa: E402
from selfview.errors import CalibrationError  # noqa: E402
from selfview.geometry import transform_points  # noqa: E402

#: background family of each photograph
FAMILIES = {
    "gravel": "texture", "grass": "texture", "brick": "texture", "rough-wall": "texture",
    "coffee": "objects", "motorcycle_left": "objects", "astronaut": "objects", "chelsea": "objects",
    "camera": "high-contrast", "coins": "high-contrast", "text": "high-contrast", "page": "high-contrast",
    "rocket": "objects", "hubble_deep_field": "texture", "moon": "texture", "horse": "high-contrast",
}
DEFAULT_PHOTOS = ("gravel", "grass", "brick", "coffee", "motorcycle_left", "astronaut", "camera", "coins")
#: (distance beyond the fingertips [mm], defocus sigma [px]) drawn in turn
SETTINGS = ((15.0, 0.6), (40.0, 1.5), (80.0, 3.0), (25.0, 0.0), (60.0, 2.2))
WRONG_MM = 0.1  # a pose marked good but further off than this (any TCP axis) is wrong
CORNER_PX = 0.5  # a corner further off than this is wrong (disc pictures)
ONLINE_POINTS = range(4)  # 4P-I's points
QUICK_PHOTOS = 4  # --quick: the first photographs of --photos


def photo_dir() -> Path:
    """The ``data`` folder of the installed scikit-image (its photographs), or a clear error."""
    spec = importlib.util.find_spec("skimage")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("the clutter study needs scikit-image's photographs: pip install -e '.[test]'")
    return Path(list(spec.submodule_search_locations)[0]) / "data"


def available_photos() -> list[str]:
    d = photo_dir()
    return [n for n in FAMILIES if (d / f"{n}.png").is_file() or (d / f"{n}.jpg").is_file()]


def load_photo(name: str) -> np.ndarray:
    """A photograph of ``skimage/data`` as a grey uint8 array (read with OpenCV)."""
    d = photo_dir()
    for ext in (".png", ".jpg"):
        p = d / f"{name}{ext}"
        if p.is_file():
            img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise RuntimeError(f"photograph {p.name}: OpenCV could not read it")
            return img
    raise RuntimeError(f"photograph {name!r}: not in scikit-image's data folder ({', '.join(available_photos())})")


def _alt():
    """``tests.alt_render`` when run from a source tree, else None."""
    root = Path(__file__).resolve().parents[1]
    if (root / "tests" / "alt_render.py").is_file():
        if str(root) not in sys.path:
            sys.path.insert(0, str(root))
        import tests.alt_render as alt

        return alt
    return None


@dataclass
class Frame:
    image: np.ndarray
    C_H_G: np.ndarray  # truth
    corner_uv: np.ndarray  # (6, 2) truth
    corner_visible: np.ndarray


@dataclass
class Sequence:
    """One trial: the undisturbed picture and the disturbed ones, the prediction and the truth."""

    renderer: str
    kind: str
    photo: str
    distance_mm: float
    defocus_px: float
    camera: object
    C_H_G_pred: np.ndarray
    gap: float
    p_G6: np.ndarray
    frames: list  # Frame, the first undisturbed


def _mm_per_px(photo: np.ndarray) -> float:
    """Scale so that the photograph spans about 180 mm (more than the view at these depths)."""
    return 180.0 / max(photo.shape)


def render_frame(renderer: str, world, photo, distance_mm, defocus_px, seed, occluder=None) -> Frame:
    """One picture of ``world`` over ``photo`` (None: the renderer's own plain background)."""
    from selfview.mocks.render import Backdrop, render

    cam = world.camera
    if renderer == "mocks":
        bd = None
        if photo is not None:
            bd = Backdrop(photo, mm_per_px=_mm_per_px(photo), distance_mm=distance_mm, defocus_px=defocus_px,
                          turn_deg=float(seed % 7) * 23.0)
        r = render(world, seed=seed, backdrop=bd)
        return Frame(r.image, world.C_H_G, r.corner_uv, r.corner_visible)
    alt = _alt()
    kw = {"seed": int(seed)}
    if photo is not None:
        from selfview.geometry import rot_z, trans

        # the same plane as the Backdrop's (distance beyond the plate's plane), its own blur model (mm on the table)
        C_H_T = world.C_H_W @ trans(0, 0, distance_mm) @ rot_z(np.radians(float(seed % 7) * 23.0))
        depth = float(C_H_T[2, 3])
        kw.update(table_image=photo, table_mm_per_px=_mm_per_px(photo), C_H_T=C_H_T,
                  table_defocus_mm=defocus_px * depth / cam.f)
    if occluder is not None:
        kw["occluders"] = (occluder,)
    pic = alt.render(cam, world.C_H_G, None, world.jaw_gap_mm, world.cell, **kw)
    return Frame(pic.image, world.C_H_G, pic.corner_uv, pic.corner_visible)


def _cable_across(world, finger: int, rng) -> tuple:
    """A dark cable 2 mm thick, straight across finger ``finger`` some 10..25 mm back from its tip, 6 mm
    in front of it (a box aligned with C: lo, hi, grey)."""
    cell = world.cell
    lo, hi = cell.gripper.finger_boxes_G(world.jaw_gap_mm)[finger]
    pts = transform_points(world.C_H_G, cell.gripper.points_G(gap=world.jaw_gap_mm))
    tip = pts[[0, 1] if finger == 0 else [2, 3]].mean(axis=0)
    back = tip.copy()
    # along the finger in C: from the tip towards the camera side the finger comes from
    axis = world.C_H_G[:3, :3] @ np.array([0.0, 0.0, -1.0])
    back = tip + axis * rng.uniform(10.0, 25.0)
    z = back[2] - 6.0
    c = back * (z / back[2])
    return (np.array([c[0] - 40.0, c[1] - 1.0, z - 1.0]), np.array([c[0] + 40.0, c[1] + 1.0, z + 1.0]), 40.0)


def online_sequence(cell, renderer: str, photo_name: str | None, series: str, seed: int, distance_mm: float,
                    defocus_px: float, steps: int = 4, occluded: bool = False) -> Sequence:
    """A trial of kind ``online`` (or ``occluded``): see the module's docstring."""
    from selfview.mocks.world import SimWorld

    world = SimWorld(cell, seed=seed)
    state = cell.gripper.calibrate_in
    world.set_jaw(cell.gripper.gap(state), state)
    world.park()
    pred = world.C_H_G
    world.unpark()
    photo = None if photo_name is None else load_photo(photo_name)
    rng = np.random.default_rng(seed + 17)
    occ = _cable_across(world, int(seed % 2), rng) if occluded else None
    frames = [render_frame(renderer, world, photo, distance_mm, defocus_px, seed * 10, occ)]
    d = world.disturb(series)
    world.reset_disturbance()
    pivot = cell.simulation.disturbances[series].pivot_C
    for k in range(steps):
        world.disturb_by_angle(d.axis_C, d.angle_deg / steps, pivot_C=pivot, series=series)
        frames.append(render_frame(renderer, world, photo, distance_mm, defocus_px, seed * 10 + 1 + k, occ))
    return Sequence(renderer, "occluded" if occluded else "online", photo_name or "plain", distance_mm, defocus_px,
                    world.camera, pred, world.jaw_gap_mm, world.points_G(), frames)


def disc_picture(cell, renderer: str, seed: int, on: bool) -> tuple[Sequence, float]:
    """A parked picture with a fingertip corner on a disc (``on``) or within 0.2..1.5 mm of a rim: parks
    drawn from ``seed`` until one is. Returns it and the corner's distance from the rim [mm] (negative: on)."""
    from selfview.mocks.world import SimWorld

    plate = cell.plate
    centres = plate.disc_centres_W()[:, :2]
    R = plate.disc_diameter / 2
    state = cell.gripper.calibrate_in
    for k in range(400):
        world = SimWorld(cell, seed=seed * 1000 + k)
        world.set_jaw(cell.gripper.gap(state), state)
        W_H_G = world.park(max_offset_mm=plate.pitch, max_turn_deg=20.0)
        p_W = transform_points(W_H_G, world.points_G())[:, :2]
        d = np.linalg.norm(p_W[:, None, :] - centres[None], axis=2).min(axis=1) - R
        # the tip corners (0..3) of the plate's side
        best = float(d[:4][np.argmin(np.abs(d[:4]))])
        if (on and -R * 0.8 < best < -0.3) or (not on and 0.2 < best < 1.5):
            if renderer == "mocks":
                from selfview.mocks.render import render

                r = render(world, seed=seed)
                fr = Frame(r.image, world.C_H_G, r.corner_uv, r.corner_visible)
            else:
                pic = _alt().render_world(world, seed=int(seed))
                fr = Frame(pic.image, world.C_H_G, pic.corner_uv, pic.corner_visible)
            return Sequence(renderer, "disc", "on disc" if on else "beside disc", 0.0, 0.0, world.camera,
                            cell.mount_guess_C_H_G, world.jaw_gap_mm, world.points_G(), [fr]), best
    raise RuntimeError("no park put a fingertip on/beside a disc")


# --- measuring ------------------------------------------------------------------------------------
def judge_pose(result, seq: Sequence, frame: Frame) -> dict:
    """found / missed / wrong for one on-line frame measured as ``result`` (a FingertipResult)."""
    from selfview.online import estimate

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


def measure_sequence(seq: Sequence, cell, methods=("search", "tracker")) -> dict:
    """Run each method over the sequence's disturbed frames; per method a list of per-frame verdicts."""
    from selfview.fingertips import find_fingertips
    from selfview.tracking import FingertipTracker, SilhouetteTracker

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
    if "tracker" in methods:
        out["tracker"] = _tracked(FingertipTracker(seq.camera, cell.gripper, points=ONLINE_POINTS), seq)
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
    """Generate the study's sequences (a generator, so that a caller measures as they come)."""
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
    ap.add_argument("--methods", default="search,tracker,model-search,model-tracker")
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
    renderers = [r for r in args.renderers.split(",") if r and (r != "alt" or _alt() is not None)]
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
