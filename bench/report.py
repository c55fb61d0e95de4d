"""One report of the project's evidence: every benchmark rerun, the experiment, Tsai on Willson's data.

``make_report`` runs each ``bench/`` script (``BENCHES``) as a subprocess with a timeout of its own and
collects the one JSON object it prints; a script that is missing, fails, times out or prints no JSON is
recorded as such, never dropped. In the same run it carries out the paper's experiment on the simulated
cell (``selfview.procedures.experiment.run_direct``, both series in parallel), Tsai's calibration on Willson's
reference points (``selfview.tsai``), and notes the machine. It writes ``RESULTS.md`` and, beside it in
``results/``, every JSON object, the studies' tables and the plots. Every figure in the report is read
from that run's results; none is typed in.
"""

from __future__ import annotations

import json
import os
import platform
import re
import signal
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from selfview.procedures.results import environment, plot_errors, write_json
from selfview.errors import ConfigError
from selfview.online import METHODS

__all__ = ["Bench", "BenchRun", "BENCHES", "find_bench_dir", "find_reference_dir", "run_bench", "machine",
           "run_experiment", "willson_check", "render_markdown", "make_report"]

_OUT = "{out}"  # replaced by the results folder in a bench's arguments
KEPT = "figures kept from the previous run"  # a benchmark not rerun by ``--keep``


@dataclass(frozen=True)
class Bench:
    """One benchmark script: its file under ``bench/``, what it measures, its arguments for the full
    and the quick run (``{out}`` stands for the results folder) and its time limit [s]."""

    name: str
    title: str
    args: tuple[str, ...] = ()
    quick_args: tuple[str, ...] = ()
    timeout_s: float = 300.0

    @property
    def script(self) -> str:
        return f"{self.name}.py"


BENCHES: tuple[Bench, ...] = (
    Bench("render", "simulated camera: one 768x576 frame", (), ("--repeat", "5"), 240.0),
    Bench("offline", "off-line calibration vs cv2.calibrateCamera", (), ("--quick",), 300.0),
    Bench("online", "on-line solves vs cv2.solvePnP, per-frame step", (), ("--repeat", "30", "--number", "5"), 180.0),
    Bench("robot", "VAL-II driver round trip over a pty", (), ("--n", "5"), 120.0),
    Bench("io", "gripper Modbus and frame sources", (), ("--strokes", "4", "--requests", "50", "--frames", "10"), 240.0),
    Bench("kinematics_vs_selfview", "AX=XB vs self-viewing as the robot wears", ("--out", _OUT),
          ("--quick", "--out", _OUT), 420.0),
    Bench("update_limit", "the update/recalibrate limit", ("--out", _OUT), ("--quick", "--out", _OUT), 420.0),
    Bench("error_budget", "a real cell's imperfections: the error budget of Tables 1 and 2", ("--out", _OUT),
          ("--quick", "--out", _OUT), 2400.0),
    Bench("intrinsics", "multi-view intrinsics vs cv2.calibrateCamera (and mrcal where installed)", (), ("--quick",),
          1200.0),
    Bench("clutter", "fingertips over real photographs: found / missed / wrong-but-marked-good", (),
          ("--trials", "1", "--steps", "2", "--disc", "3", "--occluded", "2"), 1200.0),
    Bench("faults", "fault campaign: corrupted links, hostile files and pictures, Ctrl-C", ("--faults", "10000"),
          ("--quick",), 900.0),
)


@dataclass
class BenchRun:
    """What one benchmark run gave: ``status`` 'ok', 'not available' (no script), 'failed' (non-zero
    exit), 'timed out' or 'no JSON'; ``data`` its JSON object (None unless ok); ``seconds``; ``command``;
    ``detail`` why it is not ok (the end of its stderr)."""

    name: str
    title: str
    status: str
    data: dict | None = None
    seconds: float = 0.0
    command: list[str] = field(default_factory=list)
    detail: str = ""


def find_bench_dir(start: Path | None = None) -> Path | None:
    """The benchmarks' folder: ``start`` if given, else the installed project's own (``selfview.bench``),
    wherever the command is started."""
    if start is not None:
        return Path(start) if Path(start).is_dir() else None
    import selfview.bench

    return Path(selfview.bench.__file__).resolve().parent


def _bench_root(bench_dir: Path) -> Path:
    """The folder to put on the path so that ``selfview.bench`` is ``bench_dir``: site-packages for an
    installed project (``.../selfview/bench``), the repository for a source tree (``<repo>/bench``)."""
    bench_dir = Path(bench_dir).resolve()
    return bench_dir.parent.parent if bench_dir.parent.name == "selfview" else bench_dir.parent


def find_reference_dir(reference: Path | None = None) -> Path | None:
    """Willson's reference data: ``reference`` if given, else the copy shipped with the package
    (``selfview/data/reference/tsai-willson``); None if the folder does not hold it."""
    import selfview

    d = Path(reference) if reference else Path(selfview.__file__).resolve().parent / "data" / "reference" / "tsai-willson"
    return d if (d / "cc_cd.dat").is_file() else None


def _json_object(stdout: str) -> dict | None:
    """The JSON object a script printed: all of stdout, else its last line that is one."""
    text = stdout.strip()
    for cand in [text] + text.splitlines()[::-1]:
        try:
            obj = json.loads(cand)
        except ValueError:
            continue
        if isinstance(obj, dict):
            return obj
    return None


def run_bench(bench: Bench, bench_dir: Path | None, results_dir: Path, *, quick: bool = False,
              timeout_s: float | None = None, python: str = sys.executable, extra_args=()) -> BenchRun:
    """Run one benchmark script (with ``extra_args`` after its own) in its own process group; on
    timeout the whole group is killed. Its JSON is written to ``results_dir/<name>.json``."""
    script = None if bench_dir is None else Path(bench_dir) / bench.script
    if script is not None and not script.is_file() and (Path(bench_dir) / bench.name / "__main__.py").is_file():
        script = Path(bench_dir) / bench.name  # a campaign split into a package runs as its folder
    if script is None or not script.exists():
        where = "no bench/ folder found" if bench_dir is None else f"{script} does not exist"
        return BenchRun(bench.name, bench.title, "not available", detail=where)
    args = [a.replace(_OUT, str(results_dir)) for a in (bench.quick_args if quick else bench.args)] + list(extra_args)
    cmd = [python, str(script), *args]
    env = dict(os.environ)
    root = str(_bench_root(bench_dir))
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    limit = bench.timeout_s if timeout_s is None else timeout_s
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=root, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=limit)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the script's own worker processes too
        proc.communicate()
        return BenchRun(bench.name, bench.title, "timed out", seconds=time.monotonic() - t0, command=cmd,
                        detail=f"no result within {limit:g} s")
    dt = time.monotonic() - t0
    tail = "\n".join(err.strip().splitlines()[-5:])
    if proc.returncode != 0:
        return BenchRun(bench.name, bench.title, "failed", seconds=dt, command=cmd,
                        detail=f"exit code {proc.returncode}: {tail}")
    data = _json_object(out)
    if data is None:
        return BenchRun(bench.name, bench.title, "no JSON", seconds=dt, command=cmd,
                        detail=f"stdout held no JSON object: {out.strip()[-200:]!r}")
    write_json(Path(results_dir) / f"{bench.name}.json", data)
    return BenchRun(bench.name, bench.title, "ok", data, dt, cmd)


def machine() -> dict:
    """The machine and software the run used: CPU model, cores, Python, numpy, OpenCV and more."""
    cpu = platform.processor() or platform.machine()
    try:
        m = re.search(r"^model name\s*:\s*(.+)$", Path("/proc/cpuinfo").read_text(), re.M)
        cpu = m.group(1).strip() if m else cpu
    except OSError:
        pass
    env = environment()
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": cpu, "cores": os.cpu_count(), "usable_cores": usable, **env}


# --- the experiment and Willson's data ----------------------------------------------------------------------
def _experiment_series(cell_path: str, series: str, trials: int, seed: int):
    """One series, trial by trial (world seeds ``seed + k``, as ``run_direct`` gives them): a trial that
    fails, even by a fault of a module under study, is listed as failed and the series goes on."""
    from selfview.procedures.experiment import run_direct
    from selfview.cell import load_cell

    cell = load_cell(cell_path)
    records, failures = [], []
    for k in range(trials):
        try:
            recs, summary = run_direct(cell, (series,), trials=1, seed=seed + k)
        except Exception as exc:  # noqa: BLE001 - recorded in the report, like the failures run_direct catches
            failures.append({"series": series, "index": k, "seed": seed + k, "error": f"{type(exc).__name__}: {exc}"})
            continue
        for r in recs:
            r.index = k
        records += recs
        failures += [{**f, "index": k} for f in summary["failures"]]
    return records, failures


def run_experiment(trials: int, *, jobs: int = 2, series=("cable", "tilt"), seed: int = 0) -> dict:
    """The paper's experiment on the reference cell, ``trials`` per series, the series in parallel
    (each with the seeds ``run_direct`` gives it in a joint run). Returns the summary, its tables
    (ours beside the paper's) and the time taken."""
    from selfview.procedures.experiment import summarise, tables_markdown
    from selfview.cell import default_cell_path

    t0 = time.monotonic()
    seeds = [seed + 10_000 * i for i in range(len(series))]
    args = ([str(default_cell_path())] * len(series), list(series), [trials] * len(series), seeds)
    if jobs > 1 and len(series) > 1:
        with ProcessPoolExecutor(min(jobs, len(series))) as ex:
            parts = list(ex.map(_experiment_series, *args))
    else:
        parts = [_experiment_series(*a) for a in zip(*args)]
    records = [r for p in parts for r in p[0]]
    summary = summarise(records)
    summary["failures"] = [f for p in parts for f in p[1]]
    return {"trials_per_series": trials, "series": list(series), "summary": summary,
            "tables_md": tables_markdown(summary), "seconds": time.monotonic() - t0}


def _willson_log(text: str) -> dict[str, dict[str, float]]:
    """Willson's calibration sections by title: f, kappa1, Tx, Ty, Tz, Rx, Ry, Rz, Cx, Cy and the
    distorted image-plane error's mean and max (as mean_px, max_px)."""
    from selfview.tsai import parse_willson_log

    keep = ("f", "kappa1", "Tx", "Ty", "Tz", "Rx", "Ry", "Rz", "Cx", "Cy")
    out = {}
    for title, v in parse_willson_log(text).items():
        vals = {k: v[k] for k in keep if k in v}
        if "distorted_mean" in v:
            vals["mean_px"], vals["max_px"] = v["distorted_mean"], v["distorted_max"]
        out[title] = vals
    return out


def willson_check(ref_dir: Path | None) -> dict | None:
    """``selfview.tsai`` on Willson's coplanar points (``cc_cd.dat``) beside his published runs
    (``ccal.log``): mode 'tsai' with his fixed centre, mode 'full+centre' beside his full optimisation.
    Units converted with his sensor's pixel size from ``cc_cpcc.dat``. None without the data."""
    if ref_dir is None:
        return None
    from selfview.geometry import rpy_from_R
    from selfview.tsai import calibrate_coplanar, load_willson_points

    p_W, uv = load_willson_points(ref_dir / "cc_cd.dat")
    dpy = float(np.loadtxt(ref_dir / "cc_cpcc.dat")[5])
    logs = _willson_log((ref_dir / "ccal.log").read_text())
    rows = []
    for mode, key in (("tsai", "Tz, f, kappa1 optimization"), ("full+centre", "full optimization")):
        pub = next((v for k, v in logs.items() if key in k), None)
        if pub is None:
            continue
        # his fixed (or starting) centre is the one his 'Tz, f, kappa1' run prints
        cx, cy = next(v for k, v in logs.items() if "Tz, f, kappa1" in k)["Cx"], next(
            v for k, v in logs.items() if "Tz, f, kappa1" in k)["Cy"]
        r = calibrate_coplanar(p_W, uv, cx=cx, cy=cy, mode=mode, width=576, height=384)
        rx, ry, rz = (float(np.degrees(a)) for a in rpy_from_R(r.C_H_W))
        t = r.C_H_W[:3, 3]
        ours = {"f": r.camera.f * dpy, "kappa1": r.camera.kappa / dpy**2, "Tx": t[0], "Ty": t[1], "Tz": t[2],
                "Rx": rx, "Ry": ry, "Rz": rz, "Cx": r.camera.cx, "Cy": r.camera.cy, "mean_px": r.mean_px,
                "max_px": r.max_px}
        rows.append({"mode": mode, "published": key, "ours": {k: float(v) for k, v in ours.items()},
                     "willson": pub})
    return {"points": int(len(p_W)), "pixel_mm": dpy, "runs": rows}


# --- the markdown ---------------------------------------------------------------------------------------------
def _g(d, *keys, default=None):
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return default
        d = d[k]
    return d


def _f(v, spec: str = ".3g") -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, float, np.floating)):
        return format(float(v), spec)
    return str(v)


def _scalars(d, prefix: str = "", depth: int = 3) -> list[tuple[str, object]]:
    """(dotted key, value) of the numbers, booleans and short strings of a JSON object, ``depth`` deep."""
    out = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and depth > 1:
            out += _scalars(v, key + ".", depth - 1)
        elif isinstance(v, (int, float, bool)) or (isinstance(v, str) and len(v) <= 60):
            out.append((key, v))
    return out


def _bench_block(run: BenchRun) -> list[str]:
    if run.status != "ok":
        return [f"**{run.title}** (`bench/{run.name}.py`): **{run.status}**. {run.detail}".rstrip(), ""]
    rows = [f"| {k} | {_f(v, '.4g') if not isinstance(v, str) else v} |" for k, v in _scalars(run.data)
            if k not in ("benchmark",)]
    return [f"**{run.title}** (`bench/{run.name}.py`, {run.seconds:.0f} s, JSON: `results/{run.name}.json`)", "",
            "| figure | value |", "|---|---|", *rows, ""]


_STUDIES = ("kinematics_vs_selfview", "update_limit")


def _speed(runs: dict[str, BenchRun]) -> list[str]:
    lines = ["## Speed", "", "Each figure below was measured in this run; OpenCV's peers ran in the same process "
             "on the same data, and the ratios are theirs to ours.", ""]
    on, off = runs.get("online"), runs.get("offline")
    head = ["| what | ours | OpenCV peer | peer / ours |", "|---|---|---|---|"]
    rows = []
    if on and on.status == "ok":
        med = on.data.get("median_us", {})
        for ours in ("4P-U", "4P-I", "4P-R"):
            for peer in [k for k in med if k.startswith("cv2")]:
                if ours in med:
                    rows.append(f"| one {ours} solve [us] | {_f(med[ours])} | {peer}: {_f(med[peer])} | "
                                f"{_f(med[peer] / med[ours])} |")
        step = on.data.get("per_frame_step") or {}
        rows.append(f"| per-frame step: the fingertips tracked from the last frame + 4P-I [ms] (target "
                    f"{_f(on.data.get('target_step_ms'))}; {step.get('tracked_steps', '-')} of "
                    f"{step.get('steps', '-')} steps tracked) | {_f(on.data.get('per_frame_step_ms'))} | - | - |")
        rows.append(f"| a full search for the fingertips (the first frame, or when tracking does not hold) [ms] | "
                    f"{_f(step.get('full_search_ms'))} | - | - |")
        for bg in ("plain", "cluttered"):
            tr = on.data.get(f"trackers_{bg}") or {}
            model = tr.get("model") or {}
            if model.get("median_ms") is not None:
                corners = tr.get("corners") or {}
                rows.append(f"| per-frame step of the model (silhouette) tracker, {bg} background [ms] ({model.get('found', '-')} "
                            f"of {model.get('steps', '-')} found; over the corner tracker's step on the same frames, timed in "
                            f"turn: {_f(tr.get('model_to_corners_step'))}, the corner tracker holding "
                            f"{corners.get('tracked_steps', '-')} of {corners.get('steps', '-')}) | {_f(model['median_ms'])} "
                            "| - | - |")
    if off and off.status == "ok":
        sp = off.data.get("speed", {})
        rows.append(f"| camera calibration of one picture [ms] (calibrate_coplanar vs cv2.calibrateCamera) | "
                    f"{_f(sp.get('calibrate_coplanar_ms'))} | {_f(sp.get('cv2_calibrateCamera_ms'))} | "
                    f"{_f(sp.get('ratio_cv2_to_calibrate_coplanar'))} |")
        rows.append(f"| whole off-line calibration [ms] (target {_f(sp.get('target_ms'))}) | "
                    f"{_f(sp.get('calibrate_offline_ms'))} | - | - |")
        steps = sp.get("steps_median_ms", {})
        if steps:
            rows.append("| its steps [ms] | " + ", ".join(f"{k} {_f(v)}" for k, v in steps.items()) + " | - | - |")
    lines += (head + rows + [""]) if rows else ["No speed figures: the on-line and off-line benchmarks did not run.", ""]
    lines += ["All benchmark figures as printed:", ""]
    for name, r in runs.items():
        if name in _STUDIES:
            continue  # they have sections of their own
        if name == "offline" and r.status == "ok":  # its accuracy has a section of its own
            r = BenchRun(r.name, r.title, r.status, {"speed": r.data.get("speed", {})}, r.seconds, r.command)
        lines += _bench_block(r)
    return lines


def _offline_accuracy(run: BenchRun | None) -> list[str]:
    lines = ["### Off-line calibration against the simulator's truth", ""]
    if not run or run.status != "ok":
        return lines + _unavailable(run)
    acc = run.data["accuracy"]
    names = {"f_pct": "f error [%]", "kappa_pct": "kappa error [%]", "tcp_across_mm": "TCP across the optical axis [mm]",
             "tcp_along_mm": "TCP along the optical axis [mm]", "rot_deg": "rotation [deg]"}
    lines += [f"{run.data['seeds']} simulated cells (seeds 0-{run.data['seeds'] - 1}), one picture each; magnitudes, "
              f"median / 95th percentile. OpenCV: `cv2.calibrateCamera` ({run.data['opencv_flags']}) on the same "
              f"detected disc centres, then the same PCC step; its kappa: {run.data['kappa_from_k1']}.", "",
              "| error | target | self-viewing (ours) | cv2 on the detected centres | cv2 on bias-corrected centres |",
              "|---|---|---|---|---|"]
    for k, nm in names.items():
        cells = []
        for label in ("selfview", "cv2", "cv2 bias-corrected"):
            e = acc.get(label, {}).get(k)
            cells.append("-" if not e else f"{_f(e['median'], '.4g')} / {_f(e['p95'], '.4g')}"
                         + ("" if e["p95_within"] else (" (p95 over)" if e["median_within"] else " (over)")))
        lines.append(f"| {nm} | {_f(run.data['targets'][k], 'g')} | " + " | ".join(cells) + " |")
    fails = {label: acc.get(label, {}).get("failed") for label in acc}
    lines += ["", f"Failed calibrations per method: {', '.join(f'{k} {v}' for k, v in fails.items())}.", ""]
    return lines


def _demote(md: str, levels: int) -> str:
    """Markdown with its headings moved ``levels`` deeper (to nest a generated section)."""
    return re.sub(r"^(#+) ", lambda m: "#" * (len(m.group(1)) + levels) + " ", md, flags=re.M)


def _experiment(exp: dict | None) -> list[str]:
    lines = ["### On-line: the paper's experiment (Tables 1 and 2) on the simulated cell", ""]
    if not exp:
        return lines + ["Not run.", ""]
    if "failed" in exp:
        return lines + [f"Failed: {exp['failed']}", ""]
    s = exp["summary"]
    lines += [f"`selfview.procedures.experiment.run_direct`, {exp['trials_per_series']} trials per series, in "
              f"{exp['seconds']:.0f} s; errors per camera axis (c_x, c_y, c_z) in mm. "
              f"Plot: `results/experiment_errors.png`.", "", _demote(exp["tables_md"], 2), ""]
    if not s.get("failures"):
        lines += ["No trial failed.", ""]
    return lines


def _willson(w: dict | None) -> list[str]:
    lines = ["### Tsai's method on Willson's reference data", ""]
    if not w:
        return lines + ["Not available: Willson's data (`reference/tsai-willson`) not found; pass --reference.", ""]
    lines += [f"`selfview.tsai.calibrate_coplanar` on `cc_cd.dat` ({w['points']} coplanar points) beside the runs "
              f"published in `ccal.log`; f in mm and kappa1 in mm^-2 through his pixel size {w['pixel_mm']:g} mm.", "",
              "| mode (published run) | | f [mm] | kappa1 [mm^-2] | Tx | Ty | Tz [mm] | Rx | Ry | Rz [deg] | Cx | Cy | mean / max error [px] |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in w["runs"]:
        for who, v in (("ours", r["ours"]), ("Willson", r["willson"])):
            lines.append(f"| {r['mode']} ({r['published']}) | {who} | {_f(v.get('f'), '.6f')} | {_f(v.get('kappa1'), '.6e')} | "
                         + " | ".join(_f(v.get(k), ".4f") for k in ("Tx", "Ty", "Tz", "Rx", "Ry", "Rz", "Cx", "Cy"))
                         + f" | {_f(v.get('mean_px'), '.6f')} / {_f(v.get('max_px'), '.6f')} |")
    return lines + [""]


def _table_file(results_dir: Path, name: str) -> list[str]:
    """The table a study wrote beside its JSON in this run."""
    p = results_dir / name
    return [p.read_text(encoding="utf-8").rstrip(), ""] if p.is_file() else [f"(its table `{name}` was not written)", ""]


def _unavailable(run: BenchRun | None) -> list[str]:
    """The lines of a section whose benchmark did not run or did not succeed."""
    return [f"Not available: {run.status + '. ' + run.detail if run else 'not run'}", ""]


def _handeye(run: BenchRun | None, results_dir: Path) -> list[str]:
    lines = ["## Kinematics-free? Classical hand/eye calibration (AX=XB) against self-viewing", ""]
    if not run or run.status != "ok":
        return lines + _unavailable(run)
    d = run.data
    h = d["headline"]
    w = d["worn_robot"]
    lines += [f"{d['seeds']} simulated cells; the worn robot (level 1) has link lengths off by up to {w['link_mm']:g} mm, "
              f"joint zeros by up to {w['joint_offset_deg']:g} deg and {w['encoder_sd_deg']:g} deg encoder noise; levels "
              f"{', '.join(_f(v, 'g') for v in d['levels'])} scale it. AX=XB from {', '.join(map(str, d['poses']))} stations; "
              f"camera: {d['camera']}. `bench/kinematics_vs_selfview.py` ({run.seconds:.0f} s); plot "
              "`results/kinematics_vs_selfview.png`.", ""]
    lines += [f"- Self-viewing, median TCP error: {_f(h['selfview_tcp_mm_at_zero'], '.4f')} mm with a perfect robot, "
              f"{_f(h['selfview_tcp_mm_at_max'], '.4f')} mm with the worn one.",
              f"- {h['axxb_method']}, median TCP error: {_f(h['axxb_tcp_mm_at_zero'], '.4f')} mm with a perfect robot, "
              f"{_f(h['axxb_tcp_mm_at_max'], '.4f')} mm with the worn one.", ""]
    return lines + _table_file(results_dir, "kinematics_vs_selfview.md")


def _limit(run: BenchRun | None, cell_limit, results_dir: Path) -> list[str]:
    lines = ["## The limit between updating and recalibrating", ""]
    if not run or run.status != "ok":
        return lines + _unavailable(run)
    d = run.data
    lim = d["limit"]
    if lim["angle_deg"] is None:
        lines += ["No limit within the range swept: 4P-U stayed as good as 4P-R up to 10 deg.", ""]
    else:
        cv = d["cell_values"]
        tcp = ", ".join(f"{a} {_f(v, '.2f')} mm" for a, v in lim["tcp_shift_mm_per_axis"].items())
        lines += [f"Measured: **{_f(lim['angle_deg'], '.3f')} deg** (binding axis: {lim['binding_axis']}), matching "
                  f"shift (the policy's d, eq. 14, largest over the axes) **{_f(lim['shift_mm'], '.3f')} mm**; TCP shift at "
                  f"that angle {tcp}. "
                  f"As a cell value: update_limit angle_deg {_f(cv['angle_deg'], 'g')}, shift_mm {_f(cv['shift_mm'], 'g')}.",
                  f"The packaged cell description (`selfview/data/cell.yaml`) holds update_limit "
                  f"{_f(cell_limit.angle_deg, 'g')} deg / {_f(cell_limit.shift_mm, 'g')} mm, which the policy uses"
                  + (": the measured values." if (cv["angle_deg"], cv["shift_mm"]) == (cell_limit.angle_deg, cell_limit.shift_mm)
                     else ": NOT the value measured in this run."), ""]
    lines += [f"{d['seeds']} seeds, angles {', '.join(_f(a, 'g') for a in d['angles_deg'])} deg about C x, C y, C z and a "
              f"random axis per seed through the pivot {d['pivot_C']} mm; `bench/update_limit.py` ({run.seconds:.0f} s); "
              "plot `results/update_limit.png`. The criterion is in the script's docstring.", ""]
    return lines + _table_file(results_dir, "update_limit.md")


def _error_budget(run: BenchRun | None, results_dir: Path) -> list[str]:
    lines = ["## A real cell's imperfections: the error budget of Tables 1 and 2", ""]
    if not run or run.status != "ok":
        return lines + _unavailable(run)
    d = run.data
    confs = d["configurations"]
    lines += [f"The paper's protocol (`run_direct`), {d['trials_per_series']} trials per series and configuration, the same "
              "worlds in every configuration: none of the imperfections (ideal), each part alone at its realistic "
              "magnitude (`selfview.mocks.imperfections`, where each magnitude's source is written), all of them "
              "(realistic) and the paper-like profile. Mean absolute TCP error per camera axis, c_x / c_y / c_z [mm]; "
              f"`bench/error_budget.py` ({run.seconds:.0f} s).", ""]
    for name in ("realistic", "paper-like"):
        if name in confs:
            imp = {k: v for k, v in confs[name]["imperfections"].items() if v}
            lines.append(f"- {name}: " + ", ".join(f"{k} {_f(v, 'g')}" for k, v in imp.items()))
    lines.append("")
    failures = [f for c in confs.values() for f in c["failures"]]
    misses = {(n, s): sum(m["failed"] for m in c["series"][s]["methods"].values())
              for n, c in confs.items() for s in c["series"]}
    lines += [f"Failed trials: {len(failures)}; methods that could not run on a trial (reported as misses with their "
              f"reason, never as results): {sum(misses.values())} over all configurations.", ""]
    return lines + _table_file(results_dir, "error_budget.md")


def _section(fn, *args) -> list[str]:
    """A section of the report; one whose results lack a figure it shows says so instead."""
    try:
        return fn(*args)
    except (KeyError, TypeError, IndexError, ValueError) as exc:
        return [f"(section `{fn.__name__.strip('_')}` could not be written from this run's results: "
                f"{type(exc).__name__} {exc})", ""]


def render_markdown(runs: dict[str, BenchRun], mach: dict, exp: dict | None, willson: dict | None, *,
                    quick: bool, seconds: float, command: str, cell_limit, results_dir: Path) -> str:
    """The text of RESULTS.md from one run's results."""
    lines = ["# Results", "",
             f"Produced by `{command}` in {seconds:.0f} s" + (" (QUICK run: small sizes, for tests)" if quick else "")
             + f" on {time.strftime('%Y-%m-%d %H:%M %Z')}. Every figure below comes from that run; the JSON of every "
             "benchmark is in `results/`.", "",
             "## Machine", "",
             f"{mach['cpu']}, {mach['cores']} cores ({mach['usable_cores']} usable); Python {mach['python']}, numpy "
             f"{mach['numpy']}, OpenCV {mach['opencv']}, matplotlib {mach.get('matplotlib')}; {mach['platform']}; "
             f"selfview {mach['selfview']}.", "",
             "| benchmark | status | seconds |", "|---|---|---|"]
    lines += [f"| `bench/{r.name}.py` | {r.status}{' (' + KEPT + ')' if r.detail == KEPT else ''} | "
              f"{'-' if r.detail == KEPT else f'{r.seconds:.1f}'} |" for r in runs.values()]
    lines += [""]
    lines += _section(_speed, runs)
    lines += ["## Accuracy", ""]
    lines += _section(_offline_accuracy, runs.get("offline"))
    lines += _section(_experiment, exp)
    lines += _section(_willson, willson)
    lines += _section(_handeye, runs.get("kinematics_vs_selfview"), results_dir)
    lines += _section(_limit, runs.get("update_limit"), cell_limit, results_dir)
    lines += _section(_error_budget, runs.get("error_budget"), results_dir)
    return "\n".join(lines).rstrip() + "\n"


def make_report(out: Path, *, quick: bool = False, benches=BENCHES, bench_dir: Path | None = None,
                reference: Path | None = None, trials: int | None = None, jobs: int = 2, progress=None,
                command: str = "selfview report", write_cell: Path | None = None, keep: bool = False) -> dict:
    """Rerun the benchmarks, the experiment and Willson's check; write ``out`` (RESULTS.md) and
    ``out.parent/results/``. ``quick`` uses each benchmark's small arguments and 2 trials per series
    (``trials`` overrides). ``write_cell``: the update limit measured in this run is written into that
    cell file (``bench/update_limit.py --write-cell``) before the report reads the packaged one.
    Returns {'markdown': path, 'results': folder, 'runs': {name: status}, 'seconds'}.
    Raises ``ConfigError`` for an output path that is not a .md file."""
    out = Path(out)
    if out.suffix.lower() != ".md":
        raise ConfigError(f"--out {out}: expected a markdown file such as docs/RESULTS.md")
    from selfview.cell import default_cell_path, load_cell

    say = progress or (lambda msg: None)
    t0 = time.monotonic()
    results = out.parent / "results"
    results.mkdir(parents=True, exist_ok=True)
    bench_dir = Path(bench_dir) if bench_dir else find_bench_dir()
    runs = {}
    rerun = {b.name for b in benches}
    if keep:  # every benchmark not rerun now keeps the figures stored by the last run, and says so
        for b in BENCHES:
            stored = results / f"{b.name}.json"
            if b.name not in rerun and stored.is_file():
                runs[b.name] = BenchRun(b.name, b.title, "ok", json.loads(stored.read_text(encoding="utf-8")),
                                        0.0, [], KEPT)
    for b in benches:
        say(f"bench/{b.script} ...")
        extra = ()
        if write_cell and b.name == "update_limit" and bench_dir is not None:
            # relative to the folder the script runs in, so that no path of this machine lands in its JSON
            extra = ("--write-cell", os.path.relpath(Path(write_cell).resolve(), _bench_root(bench_dir)))
        runs[b.name] = run_bench(b, bench_dir, results, quick=quick, extra_args=extra)
        say(f"bench/{b.script}: {runs[b.name].status} ({runs[b.name].seconds:.0f} s)")
    n = trials if trials is not None else (2 if quick else 20)
    exp = None
    if keep and n == 0 and (results / "experiment.json").is_file():
        from selfview.procedures.experiment import tables_markdown

        exp = json.loads((results / "experiment.json").read_text(encoding="utf-8"))
        if "summary" in exp:
            exp["tables_md"] = tables_markdown(exp["summary"])
    if n > 0:
        say(f"experiment: {n} trials per series ...")
        try:
            exp = run_experiment(n, jobs=jobs)
        except Exception as exc:  # noqa: BLE001 - the report is still written, saying why this part is missing
            exp = {"failed": f"{type(exc).__name__}: {exc}"}
        write_json(results / "experiment.json", {k: v for k, v in exp.items() if k != "tables_md"})
        if "summary" in exp:
            plot_errors(exp["summary"], results / "experiment_errors.png", METHODS)
    willson = willson_check(find_reference_dir(reference))
    if willson:
        write_json(results / "willson.json", willson)
    mach = machine()
    write_json(results / "machine.json", mach)
    cell_limit = load_cell(default_cell_path()).monitor.update_limit
    text = render_markdown(runs, mach, exp, willson, quick=quick, seconds=time.monotonic() - t0, command=command,
                           cell_limit=cell_limit, results_dir=results)
    tmp = out.with_suffix(".md.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(out)
    return {"markdown": str(out), "results": str(results), "runs": {k: r.status for k, r in runs.items()},
            "seconds": time.monotonic() - t0}
