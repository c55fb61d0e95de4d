"""Study: visually guided grasping with C_H_G from the truth, self-viewing (off-line, on-line) and AX = XB.

The paper's application: the gripper servoed to an object (``selfview.procedures.grasp``: PBVS in the gripper
frame, the stand-off goal, a straight descent, the jaws closed) on the simulated cell, the world moved by a
PUMA 260 of each arm profile (``selfview.mocks.kinematic_errors.PROFILES``, each with its ISO 9283 repeatability
RP and its absolute accuracy AP measured here by ``arm_repeatability`` and written in the JSON's ``profiles``
and in every row: none, a perfect arm; worn, a worn PUMA as a lab has it, links within 1 mm and joint zeros
within 0.2 deg of the published kinematics (AP about 1 mm) repeating to RP 0.1 mm, twice the rated +-0.05 mm;
worn-noisy, the same geometry with 0.02 deg encoder noise, RP 0.6 mm, a sensitivity profile; half-worn on
request). Per profile one cell (``--seed``) and three calibrations: self-viewing off-line (the robot parks
the gripper on the plate, one picture), AX = XB (Tsai-Lenz, ``cv2.calibrateHandEye`` with
``CALIB_HAND_EYE_TSAI``, from ``--poses`` stations of the same robot, the flange poses its nominal kinematics
report at the joints read, the plate's pose per picture with the off-line calibration's f and kappa, ``C_H_G``
through the NOMINAL flange-to-TCP offset, which the simulated gripper truly has: AX=XB's best case there; the
stations turn the flange by tens of degrees about axes spread over all three directions, ``station_spread`` in
the JSON's ``axxb_stations``) and the truth. Each
condition servos from ``--starts`` starts: the block placed per start on the table, the gripper at a pre-grasp
pose 150-250 mm from the stand-off goal back along the camera's line of sight, turned up to 15 deg about the
target and shifted up to 50 mm (a start whose first picture does not show the target and the fingertips, or
that the arm cannot reach, is drawn again and counted); each start's arm draws encoder noise of its own, the
same for every calibration of that start (``start_arm``: the calibrations compared on the same landings).
Conditions also with the camera moved on its mount (1 deg about a random axis through the cable pivot, about
2 mm at the TCP) before the fourth frame, and a control where the goal is taught by a picture taken with the
gripper truly at the stand-off pose (every calibration should then agree). Prints one JSON object; ``--out DIR``
also writes the JSON, a markdown table and a PNG plot. ``--quick`` (5 starts, 18 conditions, 90 servo runs) took
499 s of CPU (user + sys, about 4 min on 2 idle cores; 33 min on a machine shared 8 ways); the full study
(20 starts) runs four times the servo runs: 830 s on 2 idle cores.

    python bench/positioning.py [--quick] [--seed N] [--starts 20] [--jobs 2] [--out DIR]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import faulthandler  # noqa: E402
import json  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

if not __package__ and (Path(__file__).resolve().parents[1] / "pyproject.toml").is_file():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from selfview.bench.handeye import plate_pose, relative_motions  # noqa: E402
from selfview.bench.kinematics_vs_selfview import F_H_G, errors, opencv_handeye, resolve_grid, stations  # noqa: E402
from selfview.files.cell import default_cell_path, load_cell  # noqa: E402
from selfview.errors import CellError, ConfigError, LimitError  # noqa: E402
from selfview.maths.geometry import inv_H, make_H, rot_z, rotation_angle, rotvec_from_R, trans  # noqa: E402
from selfview.files.io_safe import atomic_write  # noqa: E402
from selfview.mocks.imperfections import PROFILES as WORLDS  # noqa: E402
from selfview.mocks.kinematic_errors import PROFILES as ARMS, PerturbedPuma260, arm_profile, iso9283  # noqa: E402
from selfview.mocks.objects import draw_start, grasp_outcome, place_object  # noqa: E402
from selfview.mocks.puma260 import Unreachable  # noqa: E402
from selfview.mocks.render import render  # noqa: E402
from selfview.mocks.world import PLATE_BASE_POSE, SimWorld  # noqa: E402
from selfview.measurement.objects import load_object, object_pose  # noqa: E402
from selfview.estimation.offline import calibrate_offline  # noqa: E402
from selfview.procedures.engine import tool_step_size  # noqa: E402
from selfview.procedures.grasp import GraspResult, ServoSettings, pose_error, servo_grasp  # noqa: E402

#: The arm profiles the study knows (``selfview.mocks.kinematic_errors.PROFILES``), from perfect to worn.
PROFILES = tuple(ARMS)
DEFAULT_PROFILES = ("none", "worn", "worn-noisy")
#: The arm of the headline, the camera move and the control: the worn PUMA as a lab has it.
HEADLINE_PROFILE = "worn"
CALIBRATIONS = ("truth", "selfview-offline", "selfview-online", "axxb")
MOVE_DEG = 1.0
MOVE_BEFORE_FRAME = 3
MAX_DRAWS = 8
#: Landings per arm for its RP and AP in the JSON: ten times ISO 9283's 30 cycles (RP then within about 3 %, 1 sd).
LANDINGS = 300


class DirectRig:
    """A ``GraspRig`` straight on a ``SimWorld``: the arm a ``PerturbedPuma260`` (the controller's nominal
    kinematics, the world moved by the true ones), every step checked against its caps as the engine does."""

    def __init__(self, world, robot: PerturbedPuma260, seed: int):
        self.world, self.robot, self.seed = world, robot, seed
        self.q_read = None
        self.frames = 0

    def place(self, base_H_G) -> None:
        st = self.robot.move(np.asarray(base_H_G) @ inv_H(F_H_G), self.q_read)
        self.q_read = st.q_read
        self.world.set_tcp(st.base_H_F_true @ F_H_G)

    def where(self) -> np.ndarray:
        return self.robot.nominal.fk(self.q_read) @ F_H_G

    def grab(self) -> np.ndarray:
        self.frames += 1
        return render(self.world, seed=self.seed * 100_000 + self.frames).image

    def tool_step(self, delta, max_mm, max_deg) -> None:
        """The step, or ``LimitError`` (a ``CellError``, as the engine's limits refuse it; nothing moved) for a
        pose the arm cannot reach: ``Unreachable`` is a ``ValueError`` the study's runs did not catch, so one
        servo step out of reach ended the whole study and lost every run before it."""
        tool_step_size({"delta": delta, "max_mm": max_mm, "max_deg": max_deg}, "TOOL")
        target = self.where() @ delta
        try:
            self.place(target)
        except Unreachable as exc:
            raise LimitError(f"tool step to TCP ({', '.join(f'{v:.1f}' for v in target[:3, 3])}) mm out of the "
                             f"arm's reach: {exc}; nothing moved") from None

    def jaws(self, state: str) -> None:
        self.world.set_jaw(self.world.cell.gripper.gap(state), state)

    def truth(self) -> dict:
        return self.world.truth()

    def outcome(self) -> dict:
        return grasp_outcome(self.world, self.world.cell.gripper.gap("open"))


def stacks_on_sigusr1() -> None:
    """``kill -USR1 PID`` writes every thread's Python stack to stderr (the study's main process and each
    worker): the full run of 2026-12 waited 50 min with no condition reported while its workers went on."""
    if hasattr(signal, "SIGUSR1"):
        faulthandler.register(signal.SIGUSR1, all_threads=True)


def _calibrations(cell, seed: int, profile: str, n_poses: int, imperfections: str) -> tuple[dict, dict]:
    """({name: (C_H_G, camera) or {"failed": why}}, the AX=XB stations' spread (``station_spread``)) for one
    arm profile of one cell."""
    world = SimWorld(cell, seed=seed, imperfections=imperfections)
    robot = PerturbedPuma260(arm_profile(profile).errors, seed=seed)
    out = {"truth": (world.C_H_G.copy(), world.camera)}
    park = robot.move(PLATE_BASE_POSE @ trans(1.0, -1.5, 4.0) @ rot_z(np.radians(3.0)) @ inv_H(F_H_G))
    if world.set_tcp(park.base_H_F_true @ F_H_G) != "parked":
        return out | {k: {"failed": "parking on the plate failed"} for k in CALIBRATIONS[1:]}, {}
    off = calibrate_offline(render(world, seed=seed * 1000 + 7).image, cell).calibration
    out["selfview-offline"] = out["selfview-online"] = (off.C_H_G, off.camera)
    world.unpark()
    st, _ = stations(world, cell, seed, n_poses, 3 * n_poses + 10)
    base_H_F, C_H_W = [], []
    for base_H_G, det, _true in st:
        try:
            base_H_F.append(robot.observe(base_H_G @ inv_H(F_H_G)).base_H_F_nominal)
            C_H_W.append(plate_pose(det, off.camera, cell.plate))
        except (CellError, Unreachable):
            if len(base_H_F) > len(C_H_W):
                base_H_F.pop()
    C_H_W, _ = resolve_grid(C_H_W, base_H_F, F_H_G @ inv_H(cell.mount_guess_C_H_G))
    X = opencv_handeye(base_H_F, C_H_W, "CALIB_HAND_EYE_TSAI") if len(base_H_F) >= 3 else None
    out["axxb"] = (inv_H(X) @ F_H_G, off.camera) if X is not None else {"failed": f"{len(base_H_F)} stations"}
    return out, station_spread(base_H_F, C_H_W) if len(base_H_F) >= 2 else {"stations": len(base_H_F)}


def station_spread(base_H_F, C_H_W) -> dict:
    """How the AX=XB stations turn the flange (as the controller reports them): over every pair's motion
    (``relative_motions``) the rotation angle's median, minimum and maximum [deg], and the spread of the rotation
    axes, the second and third singular values of the unit axes stacked over the largest (both 0 for axes all
    parallel, the third 0 for axes in one plane, both 1 for axes spread evenly over every direction)."""
    A, _ = relative_motions(base_H_F, C_H_W)
    ang = np.degrees([rotation_angle(a) for a in A])
    axes = np.array([rotvec_from_R(a) for a in A])
    axes /= np.maximum(np.linalg.norm(axes, axis=1, keepdims=True), 1e-300)
    sv = np.linalg.svd(axes, compute_uv=False)
    return {"stations": len(base_H_F), "motions": len(A), "rotation_deg_median": float(np.median(ang)),
            "rotation_deg_min": float(np.min(ang)), "rotation_deg_max": float(np.max(ang)),
            "axis_spread": [float(v) for v in sv[1:] / sv[0]]}


def start_arm(seed: int, start: int, profile: str) -> PerturbedPuma260:
    """The cell's arm for one start: the same worn robot for every start of a cell (its link and zero errors
    from ``seed``), its encoder draws a stream of the start's own. (One stream for every start had each run
    land its k-th motion off by the same draw: the worn rows' final errors were one vector, 0.46 mm, for every
    start and every calibration, the taught goal's included.)"""
    return PerturbedPuma260(arm_profile(profile).errors, seed=seed, noise_seed=start)


def run_start(seed: int, start: int, profile: str, calib, online: bool, moved: bool, taught: bool,
              settings: ServoSettings, imperfections: str = "realistic") -> dict:
    """One servo run from one start; the figures of its end: the TCP against the grasp frame G* after the
    descent, or (not converged) against the stand-off goal where the servo stopped."""
    cv2.setNumThreads(1)
    cell = load_cell(default_cell_path())
    obj = load_object()
    world = SimWorld(cell, seed=seed, imperfections=imperfections)
    place_object(world, obj, seed=seed * 1000 + start)
    rig = DirectRig(world, start_arm(seed, start, profile), seed * 1000 + start)
    rng = np.random.default_rng([seed, start, 5])
    C_H_G, camera = calib
    rec = {"start": start, "draws": 0}
    rig.jaws(settings.state)
    for _ in range(MAX_DRAWS):
        rec["draws"] += 1
        try:
            rig.place(draw_start(world, rng, draws=1))
        except (Unreachable, CellError):
            continue
        r = render(world, seed=1)
        if r.corner_visible.sum() >= 5:
            try:
                object_pose(r.image, world.camera, obj)
                break
            except CellError:
                continue
    else:
        return rec | {"failed": f"no usable start in {MAX_DRAWS} draws"}
    taught_C_H_O = None
    if taught:  # the gripper truly at the stand-off pose, one picture: the goal in the camera frame
        here = world.base_H_G.copy()
        world.set_tcp(world.object.base_H_O @ obj.O_H_Gpre)
        taught_C_H_O = object_pose(render(world, seed=2).image, camera, obj).C_H_O
        world.set_tcp(here)
    axis = rng.normal(size=3)
    pivot = cell.simulation.disturbances["cable"].pivot_C

    def before(k):
        if moved and k == MOVE_BEFORE_FRAME:
            world.disturb_by_angle(axis, MOVE_DEG, pivot, series="moved")

    res = GraspResult()
    t0 = time.perf_counter()
    try:
        servo_grasp(rig, cell, obj, C_H_G, camera, cell.gripper.points_G(settings.state),
                    dataclasses.replace(settings, online=online), result=res, before_frame=before,
                    taught_C_H_O=taught_C_H_O)
    except CellError as exc:
        res.reason = f"{type(exc).__name__}: {exc}"
    t = res.true_error_mm
    if t is None:  # failed before the descent: the distance to the servo's goal where it stopped
        t, a = _final_truth(world, obj)
    else:
        a = res.true_error_deg
    ms = [r["processing_ms"] for r in res.iterations]
    cpu = [r["cpu_ms"] for r in res.iterations if r.get("cpu_ms") is not None]
    return rec | {"converged": res.converged, "held": bool(res.held), "iterations": len(res.iterations),
                  "reason": res.reason, "true_error_mm": t, "true_error_deg": a,
                  "processing_ms_median": float(np.median(ms)) if ms else None,
                  "processing_ms_max": float(np.max(ms)) if ms else None,
                  "cpu_ms_median": float(np.median(cpu)) if cpu else None,
                  "cpu_ms_max": float(np.max(cpu)) if cpu else None,
                  "seconds": time.perf_counter() - t0}


def _final_truth(world, obj) -> tuple[list, float]:
    """The stand-off goal in the true gripper frame now: ([x, y, z] mm, deg)."""
    t, a = pose_error(inv_H(world.base_H_G) @ world.object.base_H_O @ obj.O_H_Gpre)
    return [float(v) for v in t], a


def arm_repeatability(seed: int, profile: str, moves: int = 30) -> dict:
    """How closely the arm of a profile (the cell's ``seed``) lands on one commanded pose over the block, each
    time from somewhere near (tool point, mm): ``iso9283`` of ``moves`` landings (ISO 9283's 30 cycles by default),
    its RP (``rp_mm``) and AP (``ap_mm``), with ``repeatability_mm`` the RMS distance from their barycentre and
    ``accuracy_mm`` the RMS distance from the command."""
    robot = PerturbedPuma260(arm_profile(profile).errors, seed=seed)
    target = make_H(np.diag([1.0, -1.0, -1.0]), (350.0, 170.0, 60.0))
    rng = np.random.default_rng([seed, 9])
    land = []
    for _ in range(moves):
        robot.move((trans(*rng.uniform(-20, 20, 3)) @ target) @ inv_H(F_H_G))  # from somewhere near
        land.append((robot.move(target @ inv_H(F_H_G)).base_H_F_true @ F_H_G)[:3, 3])
    iso = iso9283(land, target[:3, 3])
    return {"rp_mm": iso["rp_mm"], "ap_mm": iso["ap_mm"], "repeatability_mm": iso["rms_mm"],
            "accuracy_mm": float(np.sqrt(np.mean(np.sum((np.array(land) - target[:3, 3]) ** 2, axis=1)))),
            "landings": moves}


def headline_profile(profiles) -> str:
    """The profile of the headline, the camera move and the control among ``profiles``: ``HEADLINE_PROFILE``
    when run, else the last of them in the order of ``PROFILES`` (whatever the order they are named in).
    Raises ``ConfigError`` (a ``ValueError``) for no profile or one not in ``PROFILES``."""
    if isinstance(profiles, str) or not profiles:
        raise ConfigError(f"profiles: expected one or more of {', '.join(PROFILES)}, got {profiles!r}")
    for p in profiles:
        arm_profile(p)
    return HEADLINE_PROFILE if HEADLINE_PROFILE in profiles else max(profiles, key=PROFILES.index)


def conditions(profiles=DEFAULT_PROFILES) -> list[dict]:
    """Every condition of the study: (calibration, profile, camera moved, taught goal). The camera move and
    the taught goal (the control) on the headline profile (``headline_profile``), with the three measured
    calibrations. Raises ``ConfigError`` (a ``ValueError``) for no profile or one not in ``PROFILES``."""
    last = headline_profile(profiles)
    out = [{"calibration": c, "profile": p, "camera_moved": False, "taught_goal": False}
           for p in profiles for c in CALIBRATIONS]
    out += [{"calibration": c, "profile": last, "camera_moved": True, "taught_goal": False} for c in CALIBRATIONS[1:]]
    out += [{"calibration": c, "profile": last, "camera_moved": False, "taught_goal": True} for c in CALIBRATIONS[1:]]
    return out


def _summary(cond: dict, runs: list[dict]) -> dict:
    ok = [r for r in runs if "failed" not in r]
    mm = np.array([np.linalg.norm(r["true_error_mm"]) for r in ok]) if ok else np.array([np.nan])
    deg = np.array([r["true_error_deg"] for r in ok]) if ok else np.array([np.nan])
    xyz = np.array([np.abs(r["true_error_mm"]) for r in ok]) if ok else np.full((1, 3), np.nan)
    conv = [r for r in ok if r["converged"]]
    ms = [r["processing_ms_median"] for r in ok if r.get("processing_ms_median") is not None]
    msmax = [r["processing_ms_max"] for r in ok if r.get("processing_ms_max") is not None]
    return cond | {
        "starts": len(runs),
        "median_mm": float(np.median(mm)), "p95_mm": float(np.percentile(mm, 95)), "max_mm": float(np.max(mm)),
        "median_mm_xyz": [float(v) for v in np.median(xyz, axis=0)],
        "median_deg": float(np.median(deg)), "p95_deg": float(np.percentile(deg, 95)),
        "converged": len(conv), "held": sum(bool(r["held"]) for r in ok),
        "iterations_median": float(np.median([r["iterations"] for r in conv])) if conv else None,
        "repeatability_mm": [float(v) for v in np.std([r["true_error_mm"] for r in conv], axis=0)] if len(conv) > 1 else None,
        "processing_ms_median": float(np.median(ms)) if ms else None,
        "processing_ms_max": float(np.max(msmax)) if msmax else None,
        "cpu_ms_median": _median_of(ok, "cpu_ms_median"),
        "cpu_ms_max": max((r.get("cpu_ms_max") or 0) for r in ok) if ok else None,
        "failures": sorted({r.get("reason", r.get("failed", "")) for r in runs if not r.get("converged")})[:5],
    }


def table_markdown(rows: list[dict]) -> str:
    """The conditions' table; with each arm's ISO 9283 RP and AP (mm) where the rows carry them (a run that did
    not measure them gets no columns made up)."""
    arm = any("arm_rp_mm" in r for r in rows)
    cols = ["calibration", "profile"] + (["arm RP mm", "arm AP mm"] if arm else []) + [
        "camera moved", "taught goal", "starts", "median mm", "p95 mm", "max mm", "median deg", "converged", "held",
        "iterations", "ms/iteration"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        f = (lambda v, d=3: "-" if v is None or not np.isfinite(v) else f"{v:.{d}f}")
        cells = [r["calibration"], r["profile"]] + ([f(r.get("arm_rp_mm")), f(r.get("arm_ap_mm"))] if arm else []) + [
            "yes" if r["camera_moved"] else "no", "yes" if r["taught_goal"] else "no", str(r["starts"]),
            f(r["median_mm"]), f(r["p95_mm"]), f(r["max_mm"]), f(r["median_deg"]), str(r["converged"]), str(r["held"]),
            f(r["iterations_median"], 1), f(r["processing_ms_median"], 1)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 4))
    plain = [r for r in rows if not r["camera_moved"] and not r["taught_goal"]]
    profs = list(dict.fromkeys(r["profile"] for r in plain))
    for c in CALIBRATIONS:
        pts = [(profs.index(r["profile"]), r["median_mm"], r["p95_mm"]) for r in plain if r["calibration"] == c]
        if pts:
            x, m, p = zip(*pts)
            ax.errorbar(x, m, yerr=[np.zeros(len(m)), np.array(p) - np.array(m)], marker="o", capsize=3, label=c)
    ax.set_xticks(range(len(profs)), profs)
    ax.set_yscale("log")
    ax.set_xlabel("kinematic error profile")
    ax.set_ylabel("final TCP to goal [mm] (median, bar to p95)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _headline(rows: list[dict], prof_last: str) -> dict:
    """The issue's ratios on the arm ``prof_last``: AX=XB over on-line (and over off-line and the truth, the
    stand-ins while the on-line drifts), each calibration's median after the camera move over its unmoved one."""

    def get(cal, prof=None, moved=False, taught=False):
        prof = prof or prof_last
        for r in rows:
            if (r["calibration"], r["profile"], r["camera_moved"], r["taught_goal"]) == (cal, prof, moved, taught):
                return r
        return None

    def ratio(a, b):
        return a["median_mm"] / b["median_mm"] if a and b and b["median_mm"] > 0 else None

    on, ax_, off, tru = get("selfview-online"), get("axxb"), get("selfview-offline"), get("truth")
    return {
        "profile": prof_last,
        "axxb_over_online": ratio(ax_, on), "axxb_over_offline": ratio(ax_, off), "axxb_over_truth": ratio(ax_, tru),
        "online_moved_over_unmoved": ratio(get("selfview-online", moved=True), on),
        "offline_moved_over_unmoved": ratio(get("selfview-offline", moved=True), off),
        "processing_ms_max": max((r["processing_ms_max"] or 0) for r in rows),
        # wall clock counts the time other processes took from this one; CPU time is the work itself
        "processing_ms_median": _median_of(rows, "processing_ms_median"),
        "cpu_ms_median": _median_of(rows, "cpu_ms_median"),
        "cpu_ms_max": max((r.get("cpu_ms_max") or 0) for r in rows),
    }


def _median_of(rows: list[dict], key: str) -> float | None:
    v = [r[key] for r in rows if r.get(key) is not None]
    return float(np.median(v)) if v else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1, help="the simulated cell (default 1)")
    ap.add_argument("--profiles", default=",".join(DEFAULT_PROFILES),
                    help=f"arm profiles (selfview.mocks.kinematic_errors.PROFILES), of {', '.join(PROFILES)} "
                    "(default %(default)s)")
    ap.add_argument("--starts", type=int, default=20, help="starts per condition (default 20)")
    ap.add_argument("--poses", type=int, default=10, help="stations for AX=XB (default 10)")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    ap.add_argument("--out", metavar="DIR", help="also write positioning.json, .md and .png there")
    ap.add_argument("--world", default="realistic", choices=sorted(WORLDS),
                    help="the simulated cell's imperfections (default %(default)s)")
    ap.add_argument("--quick", action="store_true", help="every condition with 5 starts")
    args = ap.parse_args(argv)
    if args.quick:
        args.starts = 5
    profiles = tuple(p for p in args.profiles.split(",") if p)
    if args.starts < 1 or args.poses < 3 or args.jobs < 1 or not profiles or set(profiles) - set(PROFILES):
        ap.error(f"expected --starts >= 1, --poses >= 3, --jobs >= 1, --profiles of {', '.join(PROFILES)}")
    t0 = time.perf_counter()
    cell = load_cell(default_cell_path())
    settings = ServoSettings()
    stacks_on_sigusr1()
    ex = ProcessPoolExecutor(args.jobs, initializer=stacks_on_sigusr1)
    try:
        n = len(profiles)
        made = dict(zip(profiles, ex.map(_calibrations, [cell] * n, [args.seed] * n, profiles, [args.poses] * n,
                                         [args.world] * n)))
        cals = {p: m[0] for p, m in made.items()}
        arms = {p: ARMS[p].to_dict() | arm_repeatability(args.seed, p, moves=LANDINGS) for p in profiles}
        conds = [c | {"arm_rp_mm": arms[c["profile"]]["rp_mm"], "arm_ap_mm": arms[c["profile"]]["ap_mm"]}
                 for c in conditions(profiles)]
        futs = []
        for c in conds:
            cal = cals[c["profile"]][c["calibration"]]
            if isinstance(cal, dict):
                futs.append(None)
                continue
            futs.append([ex.submit(run_start, args.seed, s, c["profile"], cal,
                                   c["calibration"] == "selfview-online", c["camera_moved"], c["taught_goal"], settings,
                                   args.world)
                         for s in range(args.starts)])
        rows, runs = [], []
        for c, fl in zip(conds, futs):
            if fl is None:
                rows.append(c | {"starts": 0, "failed": cals[c["profile"]][c["calibration"]]["failed"]})
                continue
            rr = [f.result() for f in fl]
            runs.append(c | {"runs": rr})
            rows.append(_summary(c, rr))
            r = rows[-1]
            print(f"[{time.perf_counter() - t0:6.0f} s] {c['calibration']} {c['profile']}"
                  f"{' moved' if c['camera_moved'] else ''}{' taught' if c['taught_goal'] else ''}: median "
                  f"{r['median_mm']:.3f} / p95 {r['p95_mm']:.3f} / max {r['max_mm']:.3f} mm, median "
                  f"{r['median_deg']:.3f} deg, converged {r['converged']}/{r['starts']}, held {r['held']}, iterations "
                  f"{r['iterations_median']}",
                  file=sys.stderr, flush=True)
    except BaseException:
        # a run's error or Ctrl-C: the runs not yet started are dropped, not waited for
        ex.shutdown(wait=False, cancel_futures=True)
        raise
    ex.shutdown()
    out = {
        "benchmark": "visually guided grasping: final TCP-to-goal error by calibration, kinematic profile, camera move",
        "seed": args.seed, "starts": args.starts, "quick": args.quick, "world": args.world,
        "servo": dataclasses.asdict(settings), "object": load_object().name,
        "profiles": arms,
        "calibration_errors": {p: {k: _cal_error(v, c["truth"][0]) for k, v in c.items()} for p, c in cals.items()},
        "axxb_stations": {p: m[1] for p, m in made.items()},
        "conditions": [r for r in rows],
        "headline": _headline([r for r in rows if "failed" not in r], headline_profile(profiles)),
        "runs": runs,
        "seconds": round(time.perf_counter() - t0, 1),
        "jobs": args.jobs,
        "versions": {"numpy": np.__version__, "opencv": cv2.__version__, "python": sys.version.split()[0]},
    }
    if args.out:
        d = Path(args.out)
        d.mkdir(parents=True, exist_ok=True)
        atomic_write(d / "positioning.json", json.dumps(out, indent=1).encode(), what="results")
        atomic_write(d / "positioning.md", (table_markdown([r for r in rows if "failed" not in r]) + "\n").encode(),
                     what="results")
        plot([r for r in rows if "failed" not in r], d / "positioning.png")
    print(json.dumps(out))
    return 0


def _cal_error(cal, truth) -> dict:
    """A calibration's ``C_H_G`` against the truth (``errors``), or the reason it failed."""
    return cal if isinstance(cal, dict) else errors(cal[0], truth)


if __name__ == "__main__":
    raise SystemExit(main())
