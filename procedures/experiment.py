"""The paper's experiment (section 5): park, calibrate, disturb the camera, re-measure.

One trial: with the gripper parked on the plate, calibrate off-line from a first picture; disturb the
camera on its mount; take a second picture; apply the on-line methods (NP-U, NP-I, NP-R) from the first
calibration and the fingertip corners of the second picture; run the off-line method on the second
picture as the reference; compare the TCP position per camera axis. In simulation the truth is known
too, and every estimate is also compared with it.

The trial logic is independent of how pictures are obtained: it takes a ``TrialRig`` (park, grab,
disturb, truth), which the engine implements with real or simulated devices, and which
``DirectSimRig`` implements straight on a ``SimWorld`` for benchmarks and tests.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from selfview.procedures.paper import PAPER_SERIES, PAPER_TABLES
from selfview.files.cell import Cell
from selfview.errors import CalibrationError, CellError
from selfview.measurement.fingers import find_fingertips
from selfview.maths.geometry import pose_difference
from selfview.estimation.offline import OfflineResult, calibrate_offline
from selfview.estimation.online import METHODS, estimate

__all__ = ["TrialRig", "DirectSimRig", "TrialRecord", "run_trial", "summarise", "tables_markdown", "METHODS"]


class TrialRig(Protocol):
    """What a trial needs from the cell."""

    def park(self) -> None: ...  # gripper parked on the plate, jaws in the calibration state, settled

    def grab(self) -> np.ndarray: ...  # a (H, W) uint8 picture taken after everything settled

    def disturb(self, series: str) -> dict: ...  # move the camera on its mount; what was done

    def truth(self) -> dict | None: ...  # the simulator's truth (C_H_G, f, kappa, ...) or None on a real cell

    def restore(self) -> None: ...  # undo the disturbance (simulation) or ask the operator to


@dataclass
class TrialRecord:
    """One trial's figures (plain types, JSON-ready)."""

    series: str
    index: int
    seed: int | None
    disturbance: dict
    offline_first: dict
    offline_reference: dict
    estimates: dict  # method -> {C_H_G, delta_deg, d_mm, rms_px, points_used, err_ref_mm [3], err_truth_mm [3]|None}
    errors: dict  # method -> reason, for methods that could not run (e.g. 5P with a point missing)
    reference_err_truth_mm: list | None
    first_err_truth_mm: list | None
    timings_ms: dict = field(default_factory=dict)


def _tcp_err(C_H_G_est, C_H_G_ref) -> list[float]:
    """Absolute TCP position error per camera axis (c_x, c_y, c_z) [mm], the paper's measure."""
    return [float(v) for v in np.abs(np.asarray(C_H_G_est)[:3, 3] - np.asarray(C_H_G_ref)[:3, 3])]


def run_trial(rig: TrialRig, cell: Cell, series: str, index: int, *, seed: int | None = None,
              state: str | None = None, methods=METHODS, camera=None) -> tuple[TrialRecord, dict]:
    """One trial of the paper's protocol. Returns the record and the pictures/results for annotation.

    ``camera`` a measured camera (``selfview.estimation.intrinsics``) whose principal point and aspect the off-line
    calibrations use; None: the cell's nominal ones."""
    state = state or cell.gripper.calibrate_in
    t0 = time.perf_counter()
    rig.park()
    img1 = rig.grab()
    first: OfflineResult = calibrate_offline(img1, cell, state=state, camera=camera)
    truth1 = rig.truth()
    cal = first.calibration
    disturbance = rig.disturb(series)
    img2 = rig.grab()
    truth2 = rig.truth()
    t1 = time.perf_counter()
    ft = find_fingertips(img2, cal.camera, cal.C_H_G, cell.gripper, cell.gripper.gap(state), model="auto")
    pG = cal.points_G[state]
    estimates, errors = {}, {}
    for m in methods:
        try:
            est = estimate(m, cal.C_H_G, pG, ft.uv, ft.found, cal.camera)
        except CalibrationError as exc:
            errors[m] = str(exc)
            continue
        estimates[m] = est
    t2 = time.perf_counter()
    ref: OfflineResult = calibrate_offline(img2, cell, state=state, C_H_G_guess=cal.C_H_G, camera=camera)
    C_ref = ref.calibration.C_H_G
    est_out = {}
    for m, est in estimates.items():
        est_out[m] = {
            "C_H_G": est.C_H_G.tolist(),
            "delta_deg": float(est.delta_deg),
            "d_mm": float(est.d_mm),
            "rms_px": float(est.rms_px),
            "points_used": list(est.points_used),
            "err_ref_mm": _tcp_err(est.C_H_G, C_ref),
            "err_truth_mm": _tcp_err(est.C_H_G, truth2["C_H_G"]) if truth2 else None,
            "rot_err_truth_deg": pose_difference(est.C_H_G, truth2["C_H_G"])[0] if truth2 else None,
        }
    rec = TrialRecord(
        series=series,
        index=index,
        seed=seed,
        disturbance=disturbance,
        offline_first=_offline_brief(first),
        offline_reference=_offline_brief(ref),
        estimates=est_out,
        errors=errors,
        reference_err_truth_mm=_tcp_err(C_ref, truth2["C_H_G"]) if truth2 else None,
        first_err_truth_mm=_tcp_err(cal.C_H_G, truth1["C_H_G"]) if truth1 else None,
        timings_ms={
            "offline_first_and_grabs": (t1 - t0) * 1e3,
            "online_all_methods": (t2 - t1) * 1e3,
            "offline_reference": (time.perf_counter() - t2) * 1e3,
        },
    )
    rig.restore()
    return rec, {"img1": img1, "img2": img2, "first": first, "reference": ref, "fingertips2": ft,
                 "estimates": estimates, "truth1": truth1, "truth2": truth2}


def _offline_brief(r: OfflineResult) -> dict:
    s = r.summary()
    return {k: s[k] for k in ("f", "kappa", "C_H_G", "C_H_W", "rms_px", "discs_used", "corners_found", "pcc_rms_mm")}


def summarise(records: list[TrialRecord], methods=METHODS) -> dict:
    """Per series and method: mean and max TCP error per axis against the reference and the truth."""
    out: dict = {}
    for series in sorted({r.series for r in records}):
        rs = [r for r in records if r.series == series]
        ser: dict = {"trials": len(rs), "methods": {}}
        for m in methods:
            ref = np.array([r.estimates[m]["err_ref_mm"] for r in rs if m in r.estimates])
            tru = [r.estimates[m]["err_truth_mm"] for r in rs if m in r.estimates and r.estimates[m]["err_truth_mm"]]
            entry = {"n": int(len(ref)), "failed": int(sum(m in r.errors for r in rs))}
            if len(ref):
                entry["reference"] = {"mean_mm": ref.mean(0).round(4).tolist(), "max_mm": ref.max(0).round(4).tolist()}
            if tru:
                t = np.array(tru)
                entry["truth"] = {"mean_mm": t.mean(0).round(4).tolist(), "max_mm": t.max(0).round(4).tolist()}
            ser["methods"][m] = entry
        ref_tr = [r.reference_err_truth_mm for r in rs if r.reference_err_truth_mm]
        if ref_tr:
            t = np.array(ref_tr)
            ser["offline_reference_vs_truth"] = {"mean_mm": t.mean(0).round(4).tolist(), "max_mm": t.max(0).round(4).tolist()}
        shifts = [np.linalg.norm(r.disturbance.get("tcp_shift_C", [np.nan] * 3)) for r in rs]
        ser["tcp_shift_mm"] = {"mean": float(np.nanmean(shifts)), "sd": float(np.nanstd(shifts))}
        out[series] = ser
    return out


def tables_markdown(summary: dict, methods=METHODS) -> str:
    """Tables 1 and 2 in the paper's layout, ours beside the paper's."""
    lines = []

    def fmt(v, nd=3):  # ours to the micrometre; the paper printed two decimals
        return " | ".join(f"{x:.{nd}f}" for x in v)

    for series, ser in summary.items():
        if not isinstance(ser, dict) or "methods" not in ser:
            continue  # failures and other run facts, not a series
        title = PAPER_SERIES.get(series, series)
        sh = ser.get("tcp_shift_mm", {})
        lines += [f"## {title}", "",
                  f"{ser['trials']} trials; simulated TCP shift {sh.get('mean', float('nan')):.2f} "
                  f"+- {sh.get('sd', float('nan')):.2f} mm.", ""]
        for against in ("reference", "truth"):
            head = ("against the off-line reference (the paper's measure)" if against == "reference"
                    else "against the simulator's truth (which the paper could not have)")
            # the paper measured against its off-line reference only: its figures stand beside that table
            paper_cols = against == "reference"
            head_cols = "| method | mean c_x | mean c_y | mean c_z | max c_x | max c_y | max c_z |"
            if paper_cols:
                head_cols += " paper mean c_x | c_y | c_z | paper max c_x | c_y | c_z |"
            lines += [f"### Errors {head}", "", head_cols, "|---" * (13 if paper_cols else 7) + "|"]
            for m in methods:
                e = ser["methods"].get(m, {})
                if against not in e:
                    continue
                paper = PAPER_TABLES.get(series, {}).get(m)
                p = (f" {fmt(paper[0], 2)} | {fmt(paper[1], 2)} |" if paper else " - | - | - | - | - | - |") if paper_cols else ""
                fail = f" ({e['failed']} failed)" if e.get("failed") else ""
                lines.append(f"| {m}{fail} | {fmt(e[against]['mean_mm'])} | {fmt(e[against]['max_mm'])} |{p}")
            lines.append("")
        if "offline_reference_vs_truth" in ser:
            o = ser["offline_reference_vs_truth"]
            lines += [f"Off-line reference against the truth: mean {fmt(o['mean_mm'])}, max {fmt(o['max_mm'])} mm.", ""]
    for f in summary.get("failures", []):
        lines.append(f"- trial {f['index']} of series {f['series']} (seed {f['seed']}) failed: {f['error']}")
    return "\n".join(lines)


class DirectSimRig:
    """A trial rig straight on a simulated world and its renderer, without device channels.

    For benchmarks and numerical tests; the engine's rig runs the same trial through the drivers.
    """

    def __init__(self, world, *, render_seed: int = 0):
        from selfview.mocks.render import render

        self._render = render
        self.world = world
        self._frame = render_seed * 1000

    def park(self) -> None:
        w = self.world
        w.set_jaw(w.cell.gripper.gap(w.cell.gripper.calibrate_in), w.cell.gripper.calibrate_in)
        w.park()

    def grab(self) -> np.ndarray:
        self._frame += 1
        return self._render(self.world, seed=self._frame).image

    def disturb(self, series: str) -> dict:
        d = self.world.disturb(series)
        return {"series": series, "angle_deg": d.angle_deg, "axis_C": d.axis_C.tolist(),
                "tcp_shift_C": d.tcp_shift_C.tolist()}

    def truth(self) -> dict:
        return self.world.truth()

    def restore(self) -> None:
        self.world.reset_disturbance()


def measure_intrinsics_direct(world, views: int = 12, render_seed: int = 0):
    """``selfview.estimation.intrinsics`` on a simulated world without device channels: the gripper through the
    planned views above the plate (``plan_view_poses``, from the plate's taught pressing pose), a picture
    at each by the project's renderer. The world is left unparked. Returns the ``IntrinsicsResult``."""
    from selfview.maths.geometry import inv_H, trans
    from selfview.estimation.intrinsics import calibrate_intrinsics
    from selfview.procedures.viewplan import plan_view_poses
    from selfview.mocks.render import render
    from selfview.mocks.world import PLATE_BASE_POSE

    cell = world.cell
    plate = PLATE_BASE_POSE @ trans(0.0, 0.0, 4.0)
    lean = (inv_H(plate) @ np.array([0.0, 0.0, 0.0, 1.0]))[:2]
    imgs = []
    for i, v in enumerate(plan_view_poses(cell, views, lean_W=lean)):
        world.set_tcp(plate @ v["W_H_G"])
        imgs.append(render(world, seed=render_seed * 100 + i).image)
    world.unpark()
    return calibrate_intrinsics(imgs, cell.plate, cell.camera.guess(), skip_unusable=True)


def run_direct(cell: Cell, series_list=("cable", "tilt"), trials: int = 20, seed: int = 0,
               progress=None, profile=None, camera="ideal") -> tuple[list[TrialRecord], dict]:
    """The experiment straight on simulated worlds (one world per trial, seeded ``seed + k``).

    ``profile``: the simulated cell's imperfections (``selfview.mocks.imperfections``: a profile name
    such as 'ideal' or 'paper-like', or an ``Imperfections``; None: ideal). ``camera`` the simulated
    camera (``selfview.mocks.world.draw_camera``): 'ideal' (the cell's nominal one), or 'realistic': one
    camera drawn for the run (seed ``seed``), measured once by ``measure_intrinsics_direct`` as a lab
    would with a new camera, every trial's world with that camera and its calibrations with the
    measured one (``summary['camera']``).
    Returns the records and the summary; trials that failed are listed in ``summary['failures']``."""
    from selfview.mocks.world import SimWorld

    true_cam, measured, cam_info = "ideal", None, None
    if camera != "ideal":
        w0 = SimWorld(cell, seed=seed, imperfections=profile, camera=camera)
        true_cam = w0.camera
        intr = measure_intrinsics_direct(w0, render_seed=seed)
        measured = intr.camera
        cam_info = {"truth": true_cam.to_dict(), "measured": measured.to_dict(), "sigma": intr.sigma,
                    "views_used": intr.views_used, "stop_rule_met": intr.stop_rule["met"]}
    records, failures = [], []
    for series in series_list:
        for k in range(trials):
            s = seed + k + 10_000 * list(series_list).index(series)  # seeds never repeat across series
            world = SimWorld(cell, seed=s, imperfections=profile, camera=true_cam)
            try:
                rec, _ = run_trial(DirectSimRig(world, render_seed=s), cell, series, k, seed=s, camera=measured)
            except CellError as exc:
                failures.append({"series": series, "index": k, "seed": s, "error": f"{type(exc).__name__}: {exc}"})
                if progress:
                    progress(series, k, trials, f"failed: {exc}")
                continue
            records.append(rec)
            if progress:
                progress(series, k, trials, None)
    summary = summarise(records)
    summary["failures"] = failures
    if cam_info is not None:
        summary["camera"] = cam_info
    return records, summary
