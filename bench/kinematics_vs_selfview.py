"""Study: classical hand/eye calibration (AX = XB) against the self-viewing method as the robot wears.

Per seed, one simulated cell and one worn PUMA 260 (``selfview.mocks.kinematic_errors``) whose errors
scale ``WORN_PUMA`` (link lengths +-1 mm, joint zeros +-0.2 deg, encoder noise 0.0033 deg sd: RP 0.1 mm) by each
``--levels`` value; both methods' ``C_H_G`` against the true mount (``run_seed``). Prints one JSON object;
with ``--out DIR`` also writes ``kinematics_vs_selfview.json``, ``.md`` (table) and ``.png`` (plot) there.

    python bench/kinematics_vs_selfview.py [--seeds 6] [--levels 0,0.25,0.5,0.75,1] [--jobs 2] [--out DIR] [--quick]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

if not __package__ and (Path(__file__).resolve().parents[1] / "pyproject.toml").is_file():
    # run as a file in a source tree: import the tree it lies in (installed, selfview is on the path)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from selfview.mocks.kinematic_errors import WORN_PUMA, PerturbedPuma260  # noqa: E402
from selfview.mocks.puma260 import Unreachable, make_tool  # noqa: E402
from selfview.mocks.render import render  # noqa: E402
from selfview.mocks.val_controller import TOOL_LENGTH_MM  # noqa: E402
from selfview.mocks.world import PLATE_BASE_POSE, SimWorld  # noqa: E402
from selfview.files.cell import default_cell_path, load_cell  # noqa: E402
from selfview.measurement.plates import detect_plate  # noqa: E402
from selfview.errors import CellError  # noqa: E402
from selfview.maths.geometry import (  # noqa: E402
    R_from_rotvec, inv_H, make_H, pose_difference, rot_z, rotation_angle, trans, transform_points,
)
from selfview.bench.handeye import calibrate_handeye, plate_pose  # noqa: E402
from selfview.estimation.offline import calibrate_offline  # noqa: E402

MIN_DISCS = 20
MIN_CLEARANCE_MM = 10.0  # fingertips at least this far above the plate at a station
OPENCV_METHODS = {"cv2 TSAI": "CALIB_HAND_EYE_TSAI", "cv2 PARK": "CALIB_HAND_EYE_PARK"}
OURS = {"Tsai-Lenz": "tsai-lenz", "Park-Martin": "park-martin"}
F_H_G = make_tool(TOOL_LENGTH_MM)


# --- stations ----------------------------------------------------------------------------------------
def candidate_pose(cell, rng) -> np.ndarray:
    """A true gripper pose base_H_G over the resting plate that aims the (guessed) camera at its centre."""
    h = rng.uniform(60.0, 120.0)
    tilt_axis = np.array([*(lambda a: (np.cos(a), np.sin(a)))(rng.uniform(0, 2 * np.pi)), 0.0])
    R = R_from_rotvec(tilt_axis * np.radians(rng.uniform(15.0, 25.0))) @ rot_z(np.radians(rng.uniform(-40, 40)))[:3, :3]
    W_H_G = make_H(R, (0.0, 0.0, -h))  # W's z points into the plate: above it is negative z
    G_H_C = inv_H(cell.mount_guess_C_H_G)
    o, d = (W_H_G @ G_H_C)[:3, 3], (W_H_G @ G_H_C)[:3, 2]
    hit = o - o[2] / d[2] * d  # where the optical axis meets the plate
    W_H_G[:2, 3] -= hit[:2] + rng.uniform(-10.0, 10.0, size=2)
    return PLATE_BASE_POSE @ W_H_G


def stations(world, cell, seed: int, n: int, max_tries: int) -> tuple[list, dict]:
    """``n`` stations (true base_H_G, disc detections) whose pictures show enough of the plate.

    60-120 mm over the plate, tilted 15-25 deg about a random horizontal axis, turned up to 40 deg about
    the vertical, aimed so the camera sees the plate; a picture is kept if it shows >= ``MIN_DISCS``
    whole discs with every row and column seen."""
    rng = np.random.default_rng([seed, 2])
    plate, guess = cell.plate, cell.camera.guess()
    nominal = PerturbedPuma260(seed=seed).nominal
    out, skipped = [], {"unreachable": 0, "not free": 0, "too few discs": 0, "grid not all seen": 0, "no plate": 0}
    for k in range(max_tries):
        if len(out) == n:
            break
        base_H_G = candidate_pose(cell, rng)
        try:
            nominal.ik(base_H_G @ inv_H(F_H_G))
        except Unreachable:
            skipped["unreachable"] += 1
            continue
        tips_W = transform_points(inv_H(PLATE_BASE_POSE) @ base_H_G, world.points_G())
        if tips_W[:, 2].max() > -MIN_CLEARANCE_MM or world.set_tcp(base_H_G) != "free":
            skipped["not free"] += 1
            continue
        img = render(world, seed=seed * 1000 + k).image
        try:
            det = detect_plate(img, plate, camera=guess)
        except Exception:  # a fault in a module under study is this trial's result, not the end of the study
            skipped["no plate"] += 1
            continue
        if len(det) < MIN_DISCS:
            skipped["too few discs"] += 1
            continue
        if set(det.index_basis.values()) != {"all seen"}:
            skipped["grid not all seen"] += 1
            continue
        out.append((base_H_G, det, world.C_H_W.copy()))
    return out, skipped


_GRID_TURNS = [rot_z(k * np.pi / 2) for k in range(4)]


def resolve_grid(C_H_W_list, base_H_F_list, F_H_C_guess) -> tuple[list[np.ndarray], int]:
    """Index every station's plate frame like the first one's: of the grid's four quarter turns about
    its centre (``detect_plate`` orients W by the picture), take the one whose plate orientation in the
    base frame (robot pose times the mount guess) agrees best with station 0's. Returns the poses and
    how many were turned."""
    ref = None
    out, turned = [], 0
    for C_H_W, base_H_F in zip(C_H_W_list, base_H_F_list):
        best = None
        for k, S in enumerate(_GRID_TURNS):
            R = (base_H_F @ F_H_C_guess @ C_H_W @ S)[:3, :3]
            ang = 0.0 if ref is None else rotation_angle(R @ ref.T)
            if best is None or ang < best[0]:
                best = (ang, k, R)
        if ref is None:
            ref = best[2]
        turned += best[1] != 0
        out.append(C_H_W @ _GRID_TURNS[best[1]])
    return out, turned


def opencv_handeye(base_H_F, C_H_W, flag_name: str) -> np.ndarray | None:
    """F_H_C from cv2.calibrateHandEye (gripper = flange, target = plate), or None if unavailable."""
    if not hasattr(cv2, "calibrateHandEye") or not hasattr(cv2, flag_name):
        return None
    R, t = cv2.calibrateHandEye(
        [H[:3, :3] for H in base_H_F], [H[:3, 3] for H in base_H_F],
        [H[:3, :3] for H in C_H_W], [H[:3, 3] for H in C_H_W], method=getattr(cv2, flag_name),
    )
    return make_H(R, t.ravel())


def errors(C_H_G_est, C_H_G_true) -> dict:
    rot, tcp = pose_difference(C_H_G_est, C_H_G_true)
    return {"tcp_mm": tcp, "rot_deg": rot}


# --- one seed ----------------------------------------------------------------------------------------
def run_seed(seed: int, levels: list[float], n_list: list[int], max_tries: int) -> dict:
    """Both methods on one simulated cell at every wear level.

    AX = XB: ``C_H_W`` from each station's picture (``plate_pose``: the discs' exterior orientation with
    f and kappa FIXED at this level's off-line calibration, so that both methods share one interior
    orientation and the comparison is about the kinematics); the flange pose from the controller's
    NOMINAL kinematics at the joints its encoders read, while the arm truly stands where the TRUE
    geometry puts the true joints (``PerturbedPuma260.observe``: the stations' true poses are the same
    at every level, so each picture is rendered once per seed). The grid's four-fold symmetry is
    resolved per station (``resolve_grid``). Solved with the first 5, 10 and 20 stations by
    ``selfview.bench.handeye`` (Tsai-Lenz, Park-Martin) and OpenCV's ``calibrateHandEye`` (TSAI, PARK);
    ``C_H_G = X^-1 F_H_G`` through the tool transform. Self-viewing: the robot (commanded through the
    same worn kinematics) parks the gripper on the plate; one picture; ``calibrate_offline``.
    """
    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    cell = load_cell(default_cell_path())
    world = SimWorld(cell, seed=seed)
    truth = world.C_H_G.copy()
    st, skipped = stations(world, cell, seed, max(n_list), max_tries)
    F_H_C_guess = F_H_G @ inv_H(cell.mount_guess_C_H_G)
    rng = np.random.default_rng([seed, 3])
    park_offset = (rng.uniform(-3, 3), rng.uniform(-3, 3), np.radians(rng.uniform(-8, 8)))
    out = {"seed": seed, "stations": len(st), "skipped": skipped, "levels": []}
    for level in levels:
        robot = PerturbedPuma260(WORN_PUMA.scaled(level), seed=seed)
        entry = {"level": level, "errors": robot.summary()}
        # self-viewing: the worn robot parks the gripper, one picture, off-line calibration
        target = PLATE_BASE_POSE @ trans(park_offset[0], park_offset[1], 4.0) @ rot_z(park_offset[2])
        park = robot.move(target @ inv_H(F_H_G))
        state = world.set_tcp(park.base_H_F_true @ F_H_G)
        if state != "parked":
            entry["selfview"] = {"failed": f"parking gave {state}"}
            out["levels"].append(entry)
            continue
        try:
            off = calibrate_offline(render(world, seed=seed * 1000 + 900 + len(out["levels"])).image, cell)
        except Exception as exc:  # a fault in a module under study is this trial's result, not the end of the study
            entry["selfview"] = {"failed": f"{type(exc).__name__}: {exc}"}
            out["levels"].append(entry)
            continue
        camera = off.calibration.camera
        entry["selfview"] = errors(off.calibration.C_H_G, truth)
        entry["parked_pose_error"] = dict(zip(("rot_deg", "mm"), pose_difference(park.base_H_F_true, target @ inv_H(F_H_G))))
        # AX = XB from the stations: nominal flange poses, camera poses with the fixed interior orientation
        base_H_F, C_H_W, true_C_H_W, kin_err, cam_err = [], [], [], [], []
        for base_H_G, det, C_H_W_true in st:
            try:
                s = robot.observe(base_H_G @ inv_H(F_H_G))
                C = plate_pose(det, camera, cell.plate)
            except Exception:  # a fault in a module under study is this trial's result, not the end of the study
                continue
            base_H_F.append(s.base_H_F_nominal)
            C_H_W.append(C)
            true_C_H_W.append(C_H_W_true)
            kin_err.append(pose_difference(s.base_H_F_nominal, s.base_H_F_true))
            cam_err.append(min(pose_difference(C @ S, C_H_W_true) for S in _GRID_TURNS))
        C_H_W, turned = resolve_grid(C_H_W, base_H_F, F_H_C_guess)
        # check against the truth: every station's plate frame must be the same quarter turn of the true one
        turns = [min(range(4), key=lambda k: rotation_angle(C[:3, :3].T @ (Ct @ _GRID_TURNS[k])[:3, :3]))
                 for C, Ct in zip(C_H_W, true_C_H_W)]
        entry["grid_mismatches"] = int(sum(k != turns[0] for k in turns))
        ke, ce = np.array(kin_err), np.array(cam_err)
        entry["stations_used"] = len(base_H_F)
        entry["grid_turned"] = int(turned)
        entry["kinematics_pose_error"] = {"median_mm": float(np.median(ke[:, 1])), "median_deg": float(np.median(ke[:, 0]))}
        entry["camera_pose_error"] = {"median_mm": float(np.median(ce[:, 1])), "median_deg": float(np.median(ce[:, 0]))}
        handeye = {}
        for n in n_list:
            if n > len(base_H_F):
                continue
            res = {}
            for label, m in OURS.items():
                try:
                    he = calibrate_handeye(base_H_F[:n], C_H_W[:n], m)
                    res[label] = {**errors(he.C_H_G(F_H_G), truth), "plate_spread_mm": he.plate_spread_mm}
                except CellError as exc:
                    res[label] = {"failed": str(exc)}
            for label, flag in OPENCV_METHODS.items():
                X = opencv_handeye(base_H_F[:n], C_H_W[:n], flag)
                if X is not None:
                    res[label] = errors(inv_H(X) @ F_H_G, truth)
            handeye[str(n)] = res
        entry["handeye"] = handeye
        out["levels"].append(entry)
    out["seconds"] = time.perf_counter() - t0
    return out


# --- summary, table, plot ----------------------------------------------------------------------------
def _stat(values) -> dict | None:
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if not len(v):
        return None
    return {"median": float(np.median(v)), "mean": float(v.mean()), "max": float(v.max()), "n": int(len(v))}


def summarise(per_seed: list[dict], levels, n_list) -> list[dict]:
    """Per level: the statistics over seeds of each method's TCP and rotation errors."""
    rows = []
    for i, level in enumerate(levels):
        entries = [s["levels"][i] for s in per_seed if i < len(s["levels"])]
        row = {"level": level, "link_mm": WORN_PUMA.link_mm * level, "joint_offset_deg": WORN_PUMA.joint_offset_deg * level,
               "encoder_sd_deg": WORN_PUMA.encoder_sd_deg * level, "methods": {}}
        row["methods"]["self-viewing"] = {
            "tcp_mm": _stat(e.get("selfview", {}).get("tcp_mm") for e in entries),
            "rot_deg": _stat(e.get("selfview", {}).get("rot_deg") for e in entries),
        }
        for n in n_list:
            for label in (*OURS, *OPENCV_METHODS):
                vals = [e.get("handeye", {}).get(str(n), {}).get(label, {}) for e in entries]
                if not any("tcp_mm" in v for v in vals):
                    continue
                row["methods"][f"AX=XB {label} N={n}"] = {
                    "tcp_mm": _stat(v.get("tcp_mm") for v in vals), "rot_deg": _stat(v.get("rot_deg") for v in vals)}
        row["kinematics_pose_error_mm"] = _stat(e.get("kinematics_pose_error", {}).get("median_mm") for e in entries)
        row["camera_pose_error_mm"] = _stat(e.get("camera_pose_error", {}).get("median_mm") for e in entries)
        rows.append(row)
    return rows


def _median_max(s: dict | None, digits: int) -> str:
    return "-" if s is None else f"{s['median']:.{digits}f} ({s['max']:.{digits}f})"


def table_markdown(rows: list[dict]) -> str:
    """Median (max) TCP error [mm] and median (max) rotation error [deg] over seeds, per level and method;
    and how far the controller's flange poses and the pictures' plate poses were from the truth."""
    head = "| method | " + " | ".join(
        f"level {r['level']:g}: {r['link_mm']:.2f} mm, {r['joint_offset_deg']:.2f} deg, {r['encoder_sd_deg']:.3f} deg sd"
        for r in rows) + " |"
    rule = "|---" * (len(rows) + 1) + "|"
    lines = []
    for key, title, digits in (("tcp_mm", "TCP position error [mm]", 3), ("rot_deg", "Rotation error [deg]", 4)):
        lines += [f"{title}, median (max) over seeds:", "", head, rule]
        for m in rows[0]["methods"]:
            cells = [_median_max(r["methods"].get(m, {}).get(key), digits) for r in rows]
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        lines.append("")
    for key, what in (("kinematics_pose_error_mm", "the controller's flange pose (nominal kinematics) from the true one"),
                      ("camera_pose_error_mm", "the plate pose from each picture from the true one")):
        vals = [r.get(key) for r in rows]
        lines.append(f"Median distance of {what} [mm], per level: "
                     + ", ".join("-" if v is None else f"{v['median']:.3f}" for v in vals) + ".")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path, n_list) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [r["link_mm"] for r in rows]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, unit in ((axes[0], "tcp_mm", "TCP position error [mm]"), (axes[1], "rot_deg", "rotation error [deg]")):
        sv = [r["methods"]["self-viewing"][key] for r in rows]
        ax.plot(x, [s["median"] if s else np.nan for s in sv], "k-o", lw=2, label="self-viewing (off-line, PCC)")
        for n, style in zip(n_list, ("--", "-.", "-")):
            for label, colour in (("Tsai-Lenz", "tab:blue"), ("Park-Martin", "tab:orange")):
                s = [r["methods"].get(f"AX=XB {label} N={n}", {}).get(key) for r in rows]
                ax.plot(x, [v["median"] if v else np.nan for v in s], style, color=colour, marker=".",
                        label=f"AX=XB {label}, N={n}")
        ax.set_xlabel(f"kinematic error: link lengths +- [mm]\n(joint zeros +- {WORN_PUMA.joint_offset_deg:g} deg and encoder "
                      f"{WORN_PUMA.encoder_sd_deg:g} deg sd at {WORN_PUMA.link_mm:g} mm)")
        ax.set_ylabel(unit + ", median over seeds")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("Hand/eye calibration as the robot wears: AX=XB through the kinematics vs self-viewing")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=6, help="simulated cells (default 6)")
    ap.add_argument("--levels", default="0,0.25,0.5,0.75,1", help="kinematic error levels, fractions of the worn robot")
    ap.add_argument("--poses", default="5,10,20", help="numbers of stations for AX=XB")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    ap.add_argument("--out", metavar="DIR", help="also write the JSON, a markdown table and a PNG plot here")
    ap.add_argument("--quick", action="store_true", help="a small run: 1 seed, levels 0 and 1, 5 stations")
    args = ap.parse_args(argv)
    try:
        levels = [float(v) for v in args.levels.split(",")]
        n_list = sorted(int(v) for v in args.poses.split(","))
    except ValueError:
        ap.error("--levels and --poses: expected comma-separated numbers")
    if args.quick:
        args.seeds, levels, n_list = 1, [0.0, 1.0], [5]
    if args.seeds < 1 or min(n_list) < 3 or min(levels) < 0:
        ap.error("expected --seeds >= 1, --poses >= 3, --levels >= 0")
    t0 = time.perf_counter()
    seeds = list(range(args.seeds))
    jobs = max(1, min(args.jobs, len(seeds)))
    work = (seeds, [levels] * len(seeds), [n_list] * len(seeds), [3 * max(n_list) + 10] * len(seeds))
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as ex:
            per_seed = list(ex.map(run_seed, *work))
    else:
        per_seed = [run_seed(*a) for a in zip(*work)]
    rows = summarise(per_seed, levels, n_list)
    first, last = rows[0]["methods"], rows[-1]["methods"]
    key = f"AX=XB Tsai-Lenz N={max(n_list)}"
    out = {
        "benchmark": "AX=XB vs self-viewing as the kinematic error grows",
        "worn_robot": WORN_PUMA.to_dict(),
        "levels": levels,
        "poses": n_list,
        "seeds": args.seeds,
        "camera": "f and kappa fixed at each level's off-line calibration; pose per picture from the discs",
        "opencv_handeye": hasattr(cv2, "calibrateHandEye"),
        "summary": rows,
        "headline": {
            "selfview_tcp_mm_at_zero": first["self-viewing"]["tcp_mm"]["median"] if first["self-viewing"]["tcp_mm"] else None,
            "selfview_tcp_mm_at_max": last["self-viewing"]["tcp_mm"]["median"] if last["self-viewing"]["tcp_mm"] else None,
            "axxb_tcp_mm_at_zero": first.get(key, {}).get("tcp_mm", {}).get("median"),
            "axxb_tcp_mm_at_max": last.get(key, {}).get("tcp_mm", {}).get("median"),
            "axxb_method": key,
        },
        "per_seed": per_seed,
        "seconds": round(time.perf_counter() - t0, 1),
        "jobs": jobs,
        "versions": {"numpy": np.__version__, "opencv": cv2.__version__, "python": sys.version.split()[0]},
    }
    if args.out:
        d = Path(args.out)
        d.mkdir(parents=True, exist_ok=True)
        (d / "kinematics_vs_selfview.json").write_text(json.dumps(out, indent=1))
        (d / "kinematics_vs_selfview.md").write_text(table_markdown(rows) + "\n")
        plot(rows, d / "kinematics_vs_selfview.png", n_list)
        out["files"] = [str(d / f"kinematics_vs_selfview.{e}") for e in ("json", "md", "png")]
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
