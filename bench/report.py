"""One report of the project's evidence: every benchmark rerun, the experiment, Tsai on Willson's data.

``make_report`` runs each ``bench/`` script (``BENCHES``) as a subprocess with a timeout of its own and
collects the one JSON object it prints; a script that is missing, fails, times out or prints no JSON is
recorded as such, never dropped. In the same run it carries out the paper's experiment on the simulated
cell (``selfview.procedures.experiment.run_direct``, both series in parallel), Tsai's calibration on Willson's
reference points (``selfview.estimation.tsai``), and notes the machine. It writes ``RESULTS.md`` and, beside it in
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
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from selfview.procedures.results import environment, plot_errors, write_json
from selfview.errors import ConfigError
from selfview.estimation.online import METHODS

__all__ = ["Bench", "BenchRun", "BENCHES", "find_bench_dir", "find_reference_dir", "run_bench", "machine",
           "run_experiment", "willson_check", "render_markdown", "make_report"]

_OUT = "{out}"  # replaced by the results folder in a bench's arguments
KEPT = "kept: figures of an earlier run"  # a benchmark not rerun by ``--keep``


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
    # the --quick run (5 starts per condition) took 223 s on 2 idle cores, 1970 s at load 25; the full
    # run (20 starts) 830 s on 2 idle cores, 3796 s at nice 19 beside three CI runs, beyond the hour this limit was
    Bench("positioning", "visually guided grasping: the gripper servoed to an object, by calibration", ("--out", _OUT),
          ("--quick", "--out", _OUT), 9000.0),
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
    from selfview.files.cell import load_cell

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
    from selfview.files.cell import default_cell_path

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
    from selfview.estimation.tsai import parse_willson_log

    keep = ("f", "kappa1", "Tx", "Ty", "Tz", "Rx", "Ry", "Rz", "Cx", "Cy")
    out = {}
    for title, v in parse_willson_log(text).items():
        vals = {k: v[k] for k in keep if k in v}
        if "distorted_mean" in v:
            vals["mean_px"], vals["max_px"] = v["distorted_mean"], v["distorted_max"]
        out[title] = vals
    return out


def willson_check(ref_dir: Path | None) -> dict | None:
    """``selfview.estimation.tsai`` on Willson's coplanar points (``cc_cd.dat``) beside his published runs
    (``ccal.log``): mode 'tsai' with his fixed centre, mode 'full+centre' beside his full optimisation.
    Units converted with his sensor's pixel size from ``cc_cpcc.dat``. None without the data."""
    if ref_dir is None:
        return None
    from selfview.maths.geometry import rpy_from_R
    from selfview.estimation.tsai import calibrate_coplanar, load_willson_points

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


# --- the page ---------------------------------------------------------------------------------------------------
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


def _xyz(v, spec: str = ".3f") -> str:
    """A per-axis triple as 'x / y / z'."""
    return " / ".join(_f(a, spec) for a in v) if v else "-"


def _link(name: str) -> str:
    """A link to a file of the results folder, beside the page."""
    return f"[{name}](results/{name})"


def _unavailable(run: BenchRun | None) -> list[str]:
    """The lines of a section whose benchmark did not run or did not succeed."""
    return [f"Not available: {run.status + '. ' + run.detail if run else 'not run'}", ""]


def _ok(run: BenchRun | None) -> bool:
    return run is not None and run.status == "ok"


def _offline_accuracy(run: BenchRun | None) -> list[str]:
    lines = [f"### Off-line calibration from one picture ({_link('offline.json')})", ""]
    if not _ok(run):
        return lines + _unavailable(run)
    d = run.data
    acc = d["accuracy"]
    names = {"f_pct": "f [%]", "kappa_pct": "kappa [%]", "tcp_across_mm": "TCP across the optical axis [mm]",
             "tcp_along_mm": "TCP along the optical axis [mm]", "rot_deg": "rotation [deg]"}
    lines += [f"{d['seeds']} simulated cells, one picture each; error magnitudes, median / 95th percentile. OpenCV: "
              f"`cv2.calibrateCamera` ({d['opencv_flags']}) on the same disc centres, then the same PCC step.", "",
              "| error | target | selfview | cv2 | cv2, bias-corrected centres |", "|---|---|---|---|---|"]
    for k, nm in names.items():
        cells = []
        for label in ("selfview", "cv2", "cv2 bias-corrected"):
            e = acc.get(label, {}).get(k)
            cells.append("-" if not e else f"{_f(e['median'], '.3g')} / {_f(e['p95'], '.3g')}"
                         + ("" if e["p95_within"] else " (over)"))
        lines.append(f"| {nm} | {_f(d['targets'][k], 'g')} | " + " | ".join(cells) + " |")
    fails = ", ".join(f"{k} {v.get('failed')}" for k, v in acc.items())
    return lines + ["", f"Failed calibrations: {fails}.", ""]


def _intrinsics(run: BenchRun | None) -> list[str]:
    lines = [f"### The camera's intrinsics from {_g(run.data, 'views_per_camera', default='-') if _ok(run) else '-'} "
             f"views ({_link('intrinsics.json')})", ""]
    if not _ok(run):
        return lines + _unavailable(run)
    d = run.data
    it = d["intrinsics"]
    peers = {"selfview": "selfview", "cv2_raw": "cv2.calibrateCamera", "cv2_bias_corrected": "cv2, bias-corrected centres",
             "mrcal": "mrcal"}
    t = d.get("issue_targets", {})
    lines += [f"Median errors against the truth over the simulated cameras (renderer: {d.get('renderer', '-')}).", "",
              "| method | centre [px] | aspect [%] | f [%] | kappa [%] | seconds |", "|---|---|---|---|---|---|",
              f"| target | {_f(t.get('centre_px'))} | {_f(t.get('aspect_pct'))} | {_f(t.get('f_pct'))} | - | - |"]
    for k, nm in peers.items():
        if k in it:
            r = it[k]
            lines.append(f"| {nm} | {_f(r['median_centre_err_px'])} | {_f(r['median_aspect_err_pct'])} | "
                         f"{_f(r['median_f_err_pct'])} | {_f(r['median_kappa_err_pct'])} | {_f(r['median_seconds'])} |")
    meets = it.get("selfview_meets_issue", {})
    lines += ["", "selfview within its targets: " + ", ".join(f"{k} {_f(v)}" for k, v in meets.items()) + ".", ""]
    for name, s in (d.get("real_photographs") or {}).items():
        if not isinstance(s, dict) or "pictures" not in s:
            continue  # a note beside the sets
        pics = s.get("pictures", [])
        found = sum(1 for r in pics if r.get("opencv") and r.get("opencv_found_by_ours") == r.get("opencv"))
        lines += [f"Real photographs of a printed dot grid (`tests/data/{name}`): every disc cv2.findCirclesGrid finds "
                  f"is found in {found} of {len(pics)} pictures, none refused: {'yes' if s.get('none_refused') else 'no'}. "
                  "Ours (the skew as `selfview intrinsics` decides it; the plate model the run fitted, as recorded) beside "
                  "cv2.calibrateCamera on the same pictures:", "",
                  "| camera | pictures | f | cx | cy | aspect | ours - cv2 [combined sigmas] f / cx / cy / aspect | skew "
                  "| plate model |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for c in s.get("cameras", []):
            ours, cv = c.get("selfview", {}), c.get("cv2_on_findCirclesGrid", {})
            if "f" not in ours:
                lines.append(f"| {c['size'][0]}x{c['size'][1]} | {c.get('pictures')} | {ours.get('error', '-')} | | | | | | |")
                continue
            z = c.get("ours_minus_cv2_in_combined_sigmas", {})
            lines.append(f"| {c['size'][0]}x{c['size'][1]} | {c.get('pictures')} | {_f(ours['f'], '.1f')} / {_f(cv.get('f'), '.1f')} | "
                         f"{_f(ours['cx'], '.1f')} / {_f(cv.get('cx'), '.1f')} | {_f(ours['cy'], '.1f')} / {_f(cv.get('cy'), '.1f')} | "
                         f"{_f(ours['aspect'], '.4f')} / {_f(cv.get('aspect'), '.4f')} | "
                         + " / ".join(_f(z.get(k), '.1f') for k in ("f", "cx", "cy", "aspect"))
                         + f" | {(ours.get('skew_fit') or {}).get('note', '-').split(':')[0]} | {ours.get('plate_model', '-')} |")
        lines.append("")
    return lines


def _experiment(exp: dict | None) -> list[str]:
    lines = [f"### On-line: the paper's Tables 1 and 2 on the simulated cell ({_link('experiment.json')})", ""]
    if not exp:
        return lines + ["Not run.", ""]
    if "failed" in exp:
        return lines + [f"Failed: {exp['failed']}", ""]
    from selfview.procedures.paper import PAPER_TABLES

    s = exp["summary"]
    series = [k for k in ("cable", "tilt") if k in s]
    lines += [f"{exp['trials_per_series']} trials per series; mean TCP error against the off-line reference (the "
              "paper's measure) per camera axis c_x / c_y / c_z [mm], beside the paper's. Plot: "
              f"{_link('experiment_errors.png')}.", "",
              "| method | " + " | ".join(f"Table {i + 1} ({k}) | paper" for i, k in enumerate(series)) + " |",
              "|---|" + "---|---|" * len(series)]
    for m in s[series[0]]["methods"]:
        cells = []
        for k in series:
            r = s[k]["methods"].get(m, {})
            cells += [_xyz(_g(r, "reference", "mean_mm")), _xyz(PAPER_TABLES.get(k, {}).get(m, (None,))[0], ".2f")]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    lines += ["", "The off-line reference against the simulator's truth, mean: "
              + "; ".join(f"{k} {_xyz(s[k]['offline_reference_vs_truth']['mean_mm'])} mm" for k in series)
              + f". Failed trials: {len(s.get('failures', []))}.", ""]
    return lines


def _clutter(run: BenchRun | None) -> list[str]:
    lines = [f"### The fingertips over real photographs ({_link('clutter.json')})", ""]
    if not _ok(run):
        return lines + _unavailable(run)
    d = run.data
    lines += [f"{len(d.get('photos', []))} photographed tables, {len(d.get('renderers', []))} renderers; 'wrong' is a "
              f"result off by more than {_f(d.get('wrong_mm'))} mm that was marked good.", "",
              "| measurement | frames | found [%] | missed | wrong | largest TCP error [mm] |", "|---|---|---|---|---|---|"]
    for k, r in d["table"].items():
        if k.startswith("all / "):
            lines.append(f"| {k[6:]} | {r['frames']} | {_f(r.get('found_pct'))} | {r['missed']} | {r['wrong']} | "
                         f"{_f(r.get('4P-I_tcp_err_max_mm'))} |")
    return lines + [""]


def _willson(w: dict | None) -> list[str]:
    lines = [f"### Tsai's method on Willson's reference data ({_link('willson.json')})", ""]
    if not w:
        return lines + ["Not available: Willson's data (`reference/tsai-willson`) not found; pass --reference.", ""]
    lines += [f"`selfview.estimation.tsai.calibrate_coplanar` on `cc_cd.dat` ({w['points']} points) beside his published runs.", "",
              "| mode | | f [mm] | kappa1 [mm^-2] | Tz [mm] | mean / max error [px] |", "|---|---|---|---|---|---|"]
    for r in w["runs"]:
        for who, v in (("ours", r["ours"]), ("Willson", r["willson"])):
            lines.append(f"| {r['mode']} | {who} | {_f(v.get('f'), '.6f')} | {_f(v.get('kappa1'), '.6e')} | "
                         f"{_f(v.get('Tz'), '.4f')} | {_f(v.get('mean_px'), '.6f')} / {_f(v.get('max_px'), '.6f')} |")
    return lines + [""]


def _handeye(run: BenchRun | None) -> list[str]:
    lines = [f"### Against classical hand/eye calibration, AX=XB ({_link('kinematics_vs_selfview.json')}, table "
             f"{_link('kinematics_vs_selfview.md')})", ""]
    if not _ok(run):
        return lines + _unavailable(run)
    d = run.data
    h, w = d["headline"], d["worn_robot"]
    return lines + [
        f"{d['seeds']} simulated cells; the worn robot has link lengths off by up to {w['link_mm']:g} mm, joint zeros by "
        f"up to {w['joint_offset_deg']:g} deg and {w['encoder_sd_deg']:g} deg encoder noise. Median TCP error:", "",
        f"- self-viewing: {_f(h['selfview_tcp_mm_at_zero'], '.4f')} mm with a perfect robot, "
        f"{_f(h['selfview_tcp_mm_at_max'], '.4f')} mm with the worn one;",
        f"- {h['axxb_method']}: {_f(h['axxb_tcp_mm_at_zero'], '.4f')} mm with a perfect robot, "
        f"{_f(h['axxb_tcp_mm_at_max'], '.4f')} mm with the worn one.", ""]


def _limit(run: BenchRun | None, cell_limit) -> list[str]:
    lines = [f"### The limit between updating and recalibrating ({_link('update_limit.json')}, table "
             f"{_link('update_limit.md')})", ""]
    if not _ok(run):
        return lines + _unavailable(run)
    lim, cv = run.data["limit"], run.data["cell_values"]
    if lim["angle_deg"] is None:
        return lines + ["No limit within the range swept: 4P-U stayed as good as 4P-R.", ""]
    same = (cv["angle_deg"], cv["shift_mm"]) == (cell_limit.angle_deg, cell_limit.shift_mm)
    return lines + [f"4P-U stays as good as 4P-R up to {_f(lim['angle_deg'], '.3f')} deg (binding axis "
                    f"{lim['binding_axis']}), a shift of {_f(lim['shift_mm'], '.3f')} mm. The packaged cell file holds "
                    f"{_f(cell_limit.angle_deg, 'g')} deg / {_f(cell_limit.shift_mm, 'g')} mm"
                    + (", the measured values." if same else ", NOT the values measured."), ""]


def _frame_budget(on: BenchRun | None, clutter: BenchRun | None) -> list[tuple]:
    """(what, median ms, share of the frame) rows of the per-frame work."""
    if not _ok(on):
        return []
    d = on.data
    frame = float(_g(d, "frame_budget", "frame_ms", default=d.get("frame_ms", 40.0)))
    fb = d.get("frame_budget")
    if fb:
        rows = [("per-frame step, plain table (tracker + 4P-I)", fb.get("step_ms_plain")),
                ("per-frame step, photographed table (tracker + 4P-I)", fb.get("step_ms_cluttered")),
                ("full search (first frame, or after a lost one)", fb.get("search_ms"))]
    else:
        rows = [("per-frame step (tracker + 4P-I)", d.get("per_frame_step_ms"))]
        for bg in ("plain", "cluttered"):
            rows.append((f"silhouette tracker's step, {bg} table", _g(d, f"trackers_{bg}", "model", "median_ms")))
        rows.append(("full search (first frame, or after a lost one)", _g(d, "per_frame_step", "full_search_ms")))
    if _ok(clutter) and _g(clutter.data, "table", "all / model-tracker", "step_ms_median") is not None:
        rows.append(("silhouette tracker over photographs (clutter.json)",
                     clutter.data["table"]["all / model-tracker"]["step_ms_median"]))
    return [(w, v, None if v is None else 100.0 * float(v) / frame) for w, v in rows], frame


def _speed(runs: dict[str, BenchRun]) -> list[str]:
    on, off = runs.get("online"), runs.get("offline")
    lines = [f"## Speed against the 40 ms frame budget ({_link('online.json')}, {_link('offline.json')})", ""]
    budget = _frame_budget(on, runs.get("clutter"))
    if budget:
        rows, frame = budget
        lines += [f"A CCIR frame is {_f(frame, 'g')} ms. Median times on this machine"
                  + (" (the numpy path)" if not _g(on.data, "compiled_kernels") else
                     f" (compiled kernels: {', '.join(on.data['compiled_kernels'])})") + ".", "",
                  "| per frame | median [ms] | of a frame |", "|---|---|---|"]
        lines += [f"| {w} | {_f(v)} | {_f(p, '.1f')} % |" for w, v, p in rows]
        med = on.data.get("median_us", {})
        lines += ["", "| one solve | ours [us] | cv2.solvePnP ITERATIVE [us] | IPPE [us] |", "|---|---|---|---|"]
        for m in ("4P-U", "4P-I", "4P-R"):
            if m in med:
                lines.append(f"| {m} | {_f(med[m])} | {_f(med.get('cv2.solvePnP ITERATIVE'))} | "
                             f"{_f(med.get('cv2.solvePnP IPPE'))} |")
        lines.append("")
    else:
        lines += _unavailable(on)
    if _ok(off):
        sp = off.data["speed"]
        lines += [f"Off-line calibration of one picture: {_f(sp.get('calibrate_offline_ms'))} ms (target "
                  f"{_f(sp.get('target_ms'))} ms); its camera step {_f(sp.get('calibrate_coplanar_ms'))} ms against "
                  f"cv2.calibrateCamera's {_f(sp.get('cv2_calibrateCamera_ms'))} ms."]
    rb, io, rd = runs.get("robot"), runs.get("io"), runs.get("render")
    if _ok(rb):
        lines.append(f"VAL-II WHERE at {rb.data['baud']} baud: {_f(rb.data['paced_median_s'] * 1000)} ms, "
                     f"{_f(rb.data['ratio_to_wire'])} x the wire time ({_link('robot.json')}).")
    if _ok(io):
        st = _g(io.data, "gripper_modbus_tcp", "minus_travel", "median_ms")
        rt = _g(io.data, "gripper_modbus_tcp", "request_round_trip", "median_ms")
        lines.append(f"Gripper over Modbus TCP: a stroke confirmed {_f(st)} ms after its travel, a request "
                     f"{_f(rt)} ms ({_link('io.json')}).")
    if _ok(rd):
        lines.append(f"The simulated camera renders a frame in {_f(rd.data['median_s'] * 1000)} ms ({_link('render.json')}).")
    return lines + [""]


def _family(kind: str) -> str:
    """The row of a fault kind in the campaign's table: its section, with what the section varies."""
    parts = kind.split(".")
    if parts[0] in ("signal", "files"):
        return f"{parts[0]}.{parts[-1]}"  # the signal (once or twice), the kind of hostile file
    if parts[0] == "fuzz":
        return "fuzz.long_name" if parts[-1] == "long_name" else "fuzz.numbers"
    if parts[0] in ("cli", "sigint", "devices", "stall", "epipe"):  # stall: the mode; epipe: the command
        return ".".join(parts[:2])
    return parts[0]


def _faults(run: BenchRun | None) -> list[str]:
    lines = [f"## The fault campaign ({_link('faults.json')})", ""]
    if not _ok(run):
        return lines + _unavailable(run)
    d = run.data
    bad = ("hang", "traceback", "unsafe", "wrong_value", "lost_file")
    fam: dict[str, Counter] = {}
    for kind, c in d["kinds"].items():
        fam.setdefault(_family(kind), Counter()).update(c)
    inv = Counter()
    for kind, v in d.get("invisible", {}).items():
        inv[_family(kind)] += v["wrong_value"]
    planned = sum(d.get("planned", {}).values())
    load = d.get("load_1min") or {}
    lines += [f"{d['total']} faults in {_f(d.get('seconds'), '.0f')} s (seed {d.get('seed')}"
              + (f"; machine load {_f(load.get('start'))} to {_f(load.get('end'))}" if load else "") + ")"
              + ("" if d.get("complete", True) else f", {planned - d['total']} short of the {planned} planned: a section's "
                 f"share of the {_f(d.get('budget_s'), 'g')} s budget ran out") + ". Each fault is judged from the simulators' side; 'wrong value' "
              "counts, in brackets, those no check can see.", "",
              "| family | faults | clear error | no effect | " + " | ".join(b.replace("_", " ") for b in bad) + " |",
              "|---|" + "---|" * (3 + len(bad))]
    for name in sorted(fam):
        c = fam[name]
        cells = [str(c[b]) if b != "wrong_value" or not inv[name] else f"{c[b]} ({inv[name]})" for b in bad]
        lines.append(f"| {name} | {sum(c.values())} | {c['clear_error']} | {c['no_effect']} | " + " | ".join(cells) + " |")
    t = d["totals"]
    lines.append(f"| **all** | **{d['total']}** | {t['clear_error']} | {t['no_effect']} | "
                 + " | ".join(str(t[b]) for b in bad) + " |")
    ex, shown = [], set()
    worst_first = ("unsafe", "lost_file", "hang", "traceback", "wrong_value")
    for e in (e for b in worst_first for e in d.get("examples", {}).get(b, [])):  # one per row of the table
        if _family(e["kind"]) not in shown and len(ex) < 8:
            shown.add(_family(e["kind"]))
            ex.append(e)
    if ex:
        lines += ["", "Examples of what the campaign found:", ""]
        lines += [f"- `{e['kind']}`: {e['seen'][:200]}" for e in ex]
    return lines + [""]


def _real_cell(run: BenchRun | None) -> list[str]:
    lines = [f"## What to expect on a real cell ({_link('error_budget.json')}, table {_link('error_budget.md')})", ""]
    if not _ok(run):
        return lines + _unavailable(run)
    d = run.data
    confs = d["configurations"]
    lines += [f"The paper's protocol on the simulated cell with each imperfection of a real one alone and all of them "
              f"together ('realistic'), {d['trials_per_series']} trials per series and configuration, the same worlds "
              "in each. Mean TCP error of 4P-U, c_x / c_y / c_z [mm], against the off-line reference and against the "
              "truth:", "",
              "| configuration | Table 1 vs reference | Table 1 vs truth | Table 2 vs reference | Table 2 vs truth |",
              "|---|---|---|---|---|"]
    for name, c in confs.items():
        cells = []
        for s in ("cable", "tilt"):
            m = _g(c, "series", s, "methods", "4P-U", default={})
            cells += [_xyz(m.get("reference_mean_mm")), _xyz(m.get("truth_mean_mm"))]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    failures = sum(len(c["failures"]) for c in confs.values())

    def worst(name, key):  # the largest per-axis mean of 4P-U over both series
        return max((max(_g(confs[name], "series", s, "methods", "4P-U", key, default=[0.0])) for s in ("cable", "tilt")),
                   default=None)

    lines.append("")
    if "realistic" in confs and "ideal" in confs:
        floor = worst("ideal", "truth_mean_mm")
        parts = [n for n in confs if n not in ("ideal", "realistic", "paper-like")
                 and worst(n, "truth_mean_mm") > 2.0 * floor]
        lines.append(f"On a cell with all of them, expect each on-line update within {_f(worst('realistic', 'reference_mean_mm'), '.2f')} "
                     f"mm (mean, per axis) of its off-line reference, and the tool centre within "
                     f"{_f(worst('realistic', 'truth_mean_mm'), '.2f')} mm of the truth, against {_f(floor, '.2f')} mm on the "
                     f"ideal cell: the off-line calibration's error carries into every update, and it comes from "
                     f"{', '.join(parts) or 'no single part'} (more than twice the ideal cell's error alone).")
    return lines + [f"Failed trials: {failures}.", ""]


def _positioning(run: BenchRun | None) -> list[str]:
    lines = [f"### Visually guided grasping ({_link('positioning.json')}, table {_link('positioning.md')}, plot "
             f"{_link('positioning.png')})", ""]
    if not _ok(run):
        return lines + _unavailable(run)
    from selfview.bench.positioning import table_markdown

    d, h = run.data, run.data["headline"]
    landings = {v.get("landings") for v in d["profiles"].values()}
    landings = f"{landings.pop()} landings" if len(landings) == 1 and None not in landings else "their landings"
    return lines + [
        f"The gripper servoed to a block's grasp frame (PBVS in the gripper frame, stop at {d['servo']['stop_mm']:g} mm "
        f"and {d['servo']['stop_deg']:g} deg, at most {d['servo']['max_iterations']} iterations), {d['starts']} starts per "
        f"condition{' (a --quick run)' if d.get('quick') else ''}, the '{d['world']}' cell of seed {d['seed']}; the final "
        "true TCP-to-goal distance:", "",
        table_markdown([c for c in d["conditions"] if "failed" not in c]), "",
        f"On the {h['profile']} arm: AX=XB / self-viewing on-line = {_f(h['axxb_over_online'])}; after the camera moved "
        f"mid-approach, on-line {_f(h['online_moved_over_unmoved'])} and off-line {_f(h['offline_moved_over_unmoved'])} "
        f"times their unmoved error; processing per iteration (picture to command) median {_f(h.get('processing_ms_median'))} "
        f"ms, at most {_f(h['processing_ms_max'])} ms by the wall clock, median {_f(h.get('cpu_ms_median'))} and at most "
        f"{_f(h.get('cpu_ms_max'))} ms of CPU time. A run that did not "
        "converge stopped before the descent: its distance is to the stand-off goal where it stopped. The arms (ISO 9283 "
        f"repeatability RP and accuracy AP over {landings}): " + ", ".join(
            f"{k} RP {_f(v.get('rp_mm'), '.3f')} mm, AP {_f(v.get('ap_mm'), '.3f')} mm" for k, v in d["profiles"].items())
        + ".", ""]


def _section(fn, *args) -> list[str]:
    """A section of the page; one whose results lack a figure it shows says so instead."""
    try:
        return fn(*args)
    except (KeyError, TypeError, IndexError, ValueError, AttributeError) as exc:
        return [f"(section `{fn.__name__.strip('_')}` could not be written from these results: "
                f"{type(exc).__name__} {exc})", ""]


def _quick_note(quick, runs: dict[str, BenchRun]) -> str:
    """The header's word on run sizes: ``quick`` True (every part small), False, or the names of the parts
    that ran with --quick (a --keep run refreshes some parts at small sizes beside full-size stored ones)."""
    if quick is True:
        return " (QUICK run: small sizes, for tests)"
    parts = [n for n in (quick or ()) if n in runs]
    return f" (run with --quick, small sizes: {', '.join(parts)}; every other part at full size)" if parts else ""


def render_markdown(runs: dict[str, BenchRun], mach: dict, exp: dict | None, willson: dict | None, *,
                    quick, seconds: float | None, command: str, cell_limit, results_dir: Path,
                    when: str | None = None) -> str:
    """The text of RESULTS.md from the results (``runs``: each benchmark's JSON as read or rerun)."""
    lines = ["# Results", "",
             f"Produced by `{command}`" + (f" in {seconds:.0f} s" if seconds is not None else "")
             + _quick_note(quick, runs)
             + f" on {when or time.strftime('%Y-%m-%d %H:%M %Z')}, on {mach['cpu']} ({mach['cores']} cores, "
             f"{mach['usable_cores']} usable), {mach['platform']}: Python {mach['python']}, numpy {mach['numpy']}, "
             f"OpenCV {mach['opencv']}, selfview {mach['selfview']} ({_link('machine.json')})."
             + (" The parts marked kept were not rerun by it: their figures are those of earlier runs."
                if any(r.detail == KEPT for r in runs.values()) else ""), "",
             "Every figure below is read from the JSON file its section links (`results/`). `selfview report "
             "--render-only` writes this page again from those files; `selfview report --only NAME --keep` reruns "
             "one benchmark and keeps the others' figures.", "",
             "| benchmark | what it measures | status | seconds | JSON |", "|---|---|---|---|---|"]
    for r in runs.values():
        status = r.status + (f" ({r.detail})" if r.detail and (r.status != "ok" or r.detail == KEPT) else "")
        lines.append(f"| `bench/{r.name}` | {r.title} | {status} | {'-' if r.detail == KEPT or r.seconds <= 0 else f'{r.seconds:.0f}'} | "
                     + (_link(f"{r.name}.json") if r.status == "ok" else "-") + " |")
    lines += ["", "## Accuracy against the truth and the peers", ""]
    lines += _section(_offline_accuracy, runs.get("offline"))
    lines += _section(_intrinsics, runs.get("intrinsics"))
    lines += _section(_experiment, exp)
    lines += _section(_clutter, runs.get("clutter"))
    lines += _section(_willson, willson)
    lines += _section(_handeye, runs.get("kinematics_vs_selfview"))
    lines += _section(_positioning, runs.get("positioning"))
    lines += _section(_limit, runs.get("update_limit"), cell_limit)
    lines += _section(_speed, runs)
    lines += _section(_faults, runs.get("faults"))
    lines += _section(_real_cell, runs.get("error_budget"))
    return "\n".join(lines).rstrip() + "\n"


def _stored(results: Path, name: str) -> dict | None:
    p = results / name
    return json.loads(p.read_text(encoding="utf-8")) if p.is_file() else None


def make_report(out: Path, *, quick: bool = False, benches=BENCHES, bench_dir: Path | None = None,
                reference: Path | None = None, trials: int | None = None, jobs: int = 2, progress=None,
                command: str = "selfview report", write_cell: Path | None = None, keep: bool = False,
                render_only: bool = False) -> dict:
    """Rerun the benchmarks, the experiment and Willson's check; write ``out`` (RESULTS.md) and
    ``out.parent/results/``. ``quick`` uses each benchmark's small arguments and 2 trials per series
    (``trials`` overrides). ``write_cell``: the update limit measured in this run is written into that
    cell file (``bench/update_limit.py --write-cell``) before the report reads the packaged one.
    ``keep``: the benchmarks not rerun keep their stored JSON. ``render_only``: nothing is rerun; the page
    is written from the stored JSON alone (``results/report.json`` keeps each run's status and time).
    Returns {'markdown': path, 'results': folder, 'runs': {name: status}, 'seconds'}.
    Raises ``ConfigError`` for an output path that is not a .md file, or nothing stored to render."""
    out = Path(out)
    if out.suffix.lower() != ".md":
        raise ConfigError(f"--out {out}: expected a markdown file such as docs/RESULTS.md")
    from selfview.files.cell import default_cell_path, load_cell

    say = progress or (lambda msg: None)
    t0 = time.monotonic()
    results = out.parent / "results"
    if render_only and not results.is_dir():
        raise ConfigError(f"--render-only: no results folder {results} to render from (run the report once first)")
    results.mkdir(parents=True, exist_ok=True)
    meta = (_stored(results, "report.json") or {}) if (keep or render_only) else {}
    past = meta.get("runs", {})
    bench_dir = Path(bench_dir) if bench_dir else find_bench_dir()
    runs = {}
    rerun = set() if render_only else {b.name for b in benches}
    if keep or render_only:  # every benchmark not rerun now keeps the figures stored by the last run, and says so
        for b in BENCHES:
            data = _stored(results, f"{b.name}.json")
            if b.name not in rerun and data is not None:
                runs[b.name] = BenchRun(b.name, b.title, "ok", data, float(_g(past, b.name, "seconds", default=0.0)),
                                        [], "" if render_only else KEPT)
    for b in benches if not render_only else ():
        say(f"bench/{b.script} ...")
        extra = ()
        if write_cell and b.name == "update_limit" and bench_dir is not None:
            # relative to the folder the script runs in, so that no path of this machine lands in its JSON
            extra = ("--write-cell", os.path.relpath(Path(write_cell).resolve(), _bench_root(bench_dir)))
        runs[b.name] = run_bench(b, bench_dir, results, quick=quick, extra_args=extra)
        say(f"bench/{b.script}: {runs[b.name].status} ({runs[b.name].seconds:.0f} s)")
    n = 0 if render_only else (trials if trials is not None else (2 if quick else 20))
    exp = None
    if (keep or render_only) and n == 0:
        exp = _stored(results, "experiment.json")
    if n > 0:
        say(f"experiment: {n} trials per series ...")
        try:
            exp = run_experiment(n, jobs=jobs)
        except Exception as exc:  # noqa: BLE001 - the report is still written, saying why this part is missing
            exp = {"failed": f"{type(exc).__name__}: {exc}"}
        write_json(results / "experiment.json", {k: v for k, v in exp.items() if k != "tables_md"})
        if "summary" in exp:
            plot_errors(exp["summary"], results / "experiment_errors.png", METHODS)
    if render_only:
        willson, mach = _stored(results, "willson.json"), _stored(results, "machine.json") or machine()
        if not runs and exp is None:
            raise ConfigError(f"--render-only: {results} holds no benchmark's JSON to render")
    else:
        willson = willson_check(find_reference_dir(reference))
        if willson:
            write_json(results / "willson.json", willson)
        mach = machine()
        write_json(results / "machine.json", mach)
    cell_limit = load_cell(default_cell_path()).monitor.update_limit
    seconds = time.monotonic() - t0
    if not render_only:
        meta = {"command": command, "when": time.strftime("%Y-%m-%d %H:%M %Z"), "seconds": round(seconds, 1),
                "quick": quick, "runs": {**past, **{k: {"status": r.status, "seconds": round(r.seconds, 1), "quick": quick}
                                                    for k, r in runs.items() if r.detail != KEPT}}}
        write_json(results / "report.json", meta)
    # which parts ran small: all of them in a plain --quick run, else those whose stored run says so
    parts = {k for k, v in meta.get("runs", {}).items() if isinstance(v, dict) and v.get("quick")}
    small = quick if not (keep or render_only) else (True if parts and parts >= set(runs) else sorted(parts))
    text = render_markdown(runs, mach, exp, willson, quick=small,
                           seconds=meta.get("seconds"), command=meta.get("command", command), cell_limit=cell_limit,
                           results_dir=results, when=meta.get("when"))
    from selfview.files.io_safe import atomic_write

    atomic_write(out, text.encode("utf-8"), what="report")
    return {"markdown": str(out), "results": str(results), "runs": {k: r.status for k, r in runs.items()},
            "experiment_failed": (exp or {}).get("failed"), "seconds": time.monotonic() - t0}
