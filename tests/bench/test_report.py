"""``selfview report``: the machinery that reruns the benchmarks and writes RESULTS.md, and the studies' own
pieces (the update limit written into a cell file, the limit found from a table, the grid symmetry)."""

from __future__ import annotations

import importlib.util
import json
import os
import re
import time
from pathlib import Path

import numpy as np
import pytest

from selfview.procedures.cli import main
from selfview.bench.report import (Bench, BenchRun, find_bench_dir, find_reference_dir, make_report, render_markdown,
                                        run_bench, willson_check)
from selfview.files.cell import default_cell_path, load_cell
from selfview.errors import ConfigError
from selfview.maths.geometry import R_from_rotvec, inv_H, make_H, rot_z

REPO = Path(__file__).resolve().parents[2]


def bench_module(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", REPO / "bench" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture
def fake_benches(tmp_path):
    d = tmp_path / "bench"
    d.mkdir()
    (d / "good.py").write_text('import json, sys\nprint("warming up")\nprint(json.dumps({"speed": {"solve_us": 12.345}, '
                               '"ok": True, "args": sys.argv[1:]}))\n')
    (d / "broken.py").write_text('import sys\nprint("no plate in the picture", file=sys.stderr)\nsys.exit(3)\n')
    (d / "chatty.py").write_text('print("done, but no JSON")\n')
    # sleeps, and so does a child it starts: both must be gone after the timeout
    (d / "slow.py").write_text(
        "import subprocess, sys, time\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])\n"
        f"open(r'{tmp_path / 'child.pid'}', 'w').write(str(child.pid))\n"
        "time.sleep(60)\n")
    return d


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie has exited; /proc tells
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().split()[2] == "Z")


def test_run_bench_records_every_outcome(fake_benches, tmp_path):
    res = tmp_path / "results"
    res.mkdir()
    ok = run_bench(Bench("good", "a good one", ("--out", "{out}"), ("--quick",)), fake_benches, res)
    assert ok.status == "ok" and ok.data["speed"]["solve_us"] == 12.345 and ok.data["args"] == ["--out", str(res)]
    assert json.loads((res / "good.json").read_text())["ok"] is True
    quick = run_bench(Bench("good", "a good one", ("--out", "{out}"), ("--quick",)), fake_benches, res, quick=True)
    assert quick.data["args"] == ["--quick"]
    bad = run_bench(Bench("broken", "fails"), fake_benches, res)
    assert bad.status == "failed" and "exit code 3" in bad.detail and "no plate in the picture" in bad.detail
    chatty = run_bench(Bench("chatty", "no JSON"), fake_benches, res)
    assert chatty.status == "no JSON" and "done, but no JSON" in chatty.detail
    missing = run_bench(Bench("absent", "not written yet"), fake_benches, res)
    assert missing.status == "not available" and "absent.py does not exist" in missing.detail
    assert run_bench(Bench("good", "x"), None, res).status == "not available"


def test_a_bench_that_overruns_is_killed_with_its_children(fake_benches, tmp_path):
    t0 = time.monotonic()
    r = run_bench(Bench("slow", "sleeps", timeout_s=1.5), fake_benches, tmp_path)
    assert r.status == "timed out" and "1.5 s" in r.detail
    assert time.monotonic() - t0 < 20
    pid = int((tmp_path / "child.pid").read_text())
    deadline = time.monotonic() + 5
    while _alive(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(pid)


def test_willson_check_reproduces_his_tsai_run():
    w = willson_check(find_reference_dir())
    tsai = next(r for r in w["runs"] if r["mode"] == "tsai")
    ours, his = tsai["ours"], tsai["willson"]
    assert ours["f"] == pytest.approx(his["f"], rel=1e-4) and ours["Tz"] == pytest.approx(his["Tz"], rel=1e-4)
    for k in ("Tx", "Ty", "Rx", "Ry", "Rz"):
        assert ours[k] == pytest.approx(his[k], abs=1e-4)
    assert ours["mean_px"] == pytest.approx(his["mean_px"], abs=1e-5)
    assert willson_check(None) is None


def test_make_report_writes_every_section_from_the_run(fake_benches, tmp_path):
    out = tmp_path / "docs" / "RESULTS.md"
    benches = (Bench("good", "fake speed figures"), Bench("broken", "fails"), Bench("offline", "not written yet"))
    said = []
    res = make_report(out, quick=True, benches=benches, bench_dir=fake_benches, trials=1, jobs=2,
                      progress=said.append, command="selfview report --test")
    assert res["runs"] == {"good": "ok", "broken": "failed", "offline": "not available"}
    text = out.read_text()
    files = {p.name for p in (tmp_path / "docs" / "results").iterdir()}
    assert {"good.json", "experiment.json", "experiment_errors.png", "willson.json", "machine.json"} <= files
    mach = json.loads((tmp_path / "docs" / "results" / "machine.json").read_text())
    assert mach["numpy"] == np.__version__ and mach["cores"] == os.cpu_count()
    assert f"numpy {np.__version__}" in text and "QUICK run" in text and "selfview report --test" in text
    assert "| `bench/good` | fake speed figures | ok |" in text and "[good.json](results/good.json)" in text
    assert "| `bench/broken` | fails | failed (exit code 3" in text
    assert "Not available: not available" in text  # the off-line accuracy without its benchmark
    exp = json.loads((tmp_path / "docs" / "results" / "experiment.json").read_text())
    assert exp["trials_per_series"] == 1 and "| 4P-U | " in text and "Table 1 (cable)" in text
    w = json.loads((tmp_path / "docs" / "results" / "willson.json").read_text())
    assert f"{w['runs'][0]['ours']['f']:.6f}" in text
    assert any("experiment" in s for s in said)


def test_make_report_passes_the_cell_to_write_to_the_limit_study_only(fake_benches, tmp_path):
    (fake_benches / "update_limit.py").write_text((fake_benches / "good.py").read_text())
    cell = tmp_path / "cell.yaml"
    res = make_report(tmp_path / "R.md", benches=(Bench("update_limit", "limit"), Bench("good", "other")),
                      bench_dir=fake_benches, trials=0, write_cell=cell)
    assert res["runs"] == {"update_limit": "ok", "good": "ok"}
    got = {n: json.loads((tmp_path / "results" / f"{n}.json").read_text())["args"] for n in ("update_limit", "good")}
    assert got == {"update_limit": ["--write-cell", "cell.yaml"], "good": []}  # relative to where the script runs
    # a study whose JSON lacks its figures gets a line saying so, not a crash
    assert "(section `limit` could not be written from these results: KeyError 'limit')" in (tmp_path / "R.md").read_text()


def test_render_markdown_reports_missing_studies():
    cell = load_cell(default_cell_path())
    mach = {"cpu": "test cpu", "cores": 2, "usable_cores": 2, "python": "3", "numpy": "2", "opencv": "4",
            "platform": "test", "selfview": "0"}
    runs = {"kinematics_vs_selfview": BenchRun("kinematics_vs_selfview", "AX=XB", "timed out", detail="no result within 420 s")}
    text = render_markdown(runs, mach, None, None, quick=False, seconds=1.0, command="c",
                           cell_limit=cell.monitor.update_limit, results_dir=Path("."))
    assert "Not available: timed out. no result within 420 s" in text
    assert "### The limit between updating and recalibrating ([update_limit.json](results/update_limit.json), table " \
           "[update_limit.md](results/update_limit.md))\n\nNot available: not run" in text
    assert "Willson's data (`reference/tsai-willson`) not found" in text


def test_report_command_refuses_bad_arguments(tmp_path, capsys):
    assert main(["report", "--only", "nonsense", "--out", str(tmp_path / "R.md")]) == 3
    assert "--only nonsense" in capsys.readouterr().err
    assert main(["report", "--only", "robot", "--out", str(tmp_path / "R.txt")]) == 3
    assert "expected a markdown file" in capsys.readouterr().err
    assert main(["report", "--render-only", "--only", "robot", "--out", str(tmp_path / "R.md")]) == 3
    assert "--render-only reruns nothing" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:  # a negative count on the command line: a usage error
        main(["report", "--trials", "-1", "--out", str(tmp_path / "R.md")])
    assert stop.value.code == 2


# --- the studies' pieces ----------------------------------------------------------------------------------
def test_write_cell_changes_only_the_update_limit(tmp_path, cell_path):
    ul = bench_module("update_limit")
    p = tmp_path / "cell.yaml"
    p.write_bytes(cell_path.read_bytes())
    before = p.read_text().splitlines()
    limit = {"angle_deg": 0.7712, "shift_mm": 0.3349}
    ul.write_cell(p, limit, "test evidence")
    ul.write_cell(p, limit, "test evidence, again")  # replaces its own note, never piles them up
    after = p.read_text().splitlines()
    changed = [ln for ln in after if ln not in before]
    assert changed == ["  # update_limit measured by bench/update_limit.py: test evidence, again",
                       "  update_limit: {angle_deg: 0.77, shift_mm: 2}"]  # the shift limit is the cell's own
    assert [ln for ln in before if ln not in after] == ["  update_limit: {angle_deg: 1.0, shift_mm: 2.0}"]
    assert len(after) == len(before) + 1
    lim = load_cell(p).monitor.update_limit
    assert (lim.angle_deg, lim.shift_mm) == (0.77, 2.0)
    q = tmp_path / "other.yaml"
    q.write_text("monitor: {}\n")
    with pytest.raises(ValueError, match="no line"):
        ul.write_cell(q, limit, "x")


def test_the_packaged_cell_carries_a_measured_update_limit():
    text = default_cell_path().read_text()
    assert "# update_limit measured by bench/update_limit.py" in text
    cell = load_cell(default_cell_path())
    assert cell.monitor.update_limit.angle_deg < cell.monitor.alarm_limit.angle_deg


def test_find_limit_on_a_quadratic_model_error():
    ul = bench_module("update_limit")
    angles = ul.angles_deg(12)
    tab = {"C z": [{"angle_deg": a, "model_tcp_mm": 0.02 * a**2, "model_rot_deg": 1e-4 * a**2,
                    "policy_d_mm": 0.26 * a, "tcp_shift_mm": 0.27 * a} for a in angles],
           "C x": [{"angle_deg": a, "model_tcp_mm": 1e-5 * a**2, "model_rot_deg": 1e-4 * a**2,
                    "policy_d_mm": 0.44 * a, "tcp_shift_mm": 2.3 * a} for a in angles]}
    floor = {"tcp_mm": 0.02, "rot_deg": 0.1, "n": 100}
    lim = ul.find_limit(tab, floor, 0.1)
    bound = np.sqrt(1.1**2 - 1) * 0.02
    assert lim["binding_axis"] == "C z" and lim["per_axis_deg"]["C x"] is None
    assert lim["angle_deg"] == pytest.approx(np.sqrt(bound / 0.02), rel=1e-6)  # exact: log-log of a power law
    assert lim["shift_mm"] == pytest.approx(0.44 * lim["angle_deg"], rel=1e-6)
    assert ul.cell_values(lim, 2.0) == (float(f"{lim['angle_deg']:.2g}"), 2.0)  # the cell keeps its shift limit
    none = ul.find_limit({"C x": tab["C x"]}, floor, 0.1)
    assert none["angle_deg"] is None and none["shift_mm"] is None


def test_resolve_grid_indexes_every_station_like_the_first(rng):
    kv = bench_module("kinematics_vs_selfview")
    F_H_C = make_H(R_from_rotvec([0.1, 3.0, 0.2]), (0.0, -58.0, -263.0))
    base_H_W = make_H(np.diag([1.0, -1.0, -1.0]), (350.0, 0.0, 20.0))
    F = [make_H(R_from_rotvec(rng.normal(size=3) * 0.3), rng.normal(size=3) * 30 + (350, 0, 300)) for _ in range(8)]
    true = [inv_H(F_H_C) @ inv_H(f) @ base_H_W for f in F]
    seen = [C @ rot_z(np.pi / 2 * k) for C, k in zip(true, rng.integers(0, 4, size=8))]
    guess = make_H(R_from_rotvec([0.1, 3.0, 0.2]) @ R_from_rotvec([0.02, -0.03, 0.01]), (3.0, -55.0, -260.0))
    fixed, turned = kv.resolve_grid(seen, F, guess)
    ref = inv_H(true[0]) @ fixed[0]
    for C, Ct in zip(fixed, true):
        np.testing.assert_allclose(inv_H(Ct) @ C, ref, atol=1e-9)
    assert 0 < turned < 8


@pytest.mark.slow
def test_quick_report_runs_the_studies_end_to_end(tmp_path):
    out = tmp_path / "RESULTS.md"
    code = main(["report", "--quick", "--only", "kinematics_vs_selfview", "update_limit", "--trials", "0",
                 "--out", str(out), "--bench-dir", str(REPO / "bench")])
    assert code == 0
    text = out.read_text()
    kv = json.loads((tmp_path / "results" / "kinematics_vs_selfview.json").read_text())
    ul = json.loads((tmp_path / "results" / "update_limit.json").read_text())
    h = kv["headline"]
    # the worn robot spoils AX=XB by far more than the self-viewing calibration's own error
    assert h["axxb_tcp_mm_at_max"] > 10 * h["selfview_tcp_mm_at_max"]
    assert h["selfview_tcp_mm_at_zero"] < 0.1 and h["axxb_tcp_mm_at_zero"] < 0.1
    assert f"{h['axxb_tcp_mm_at_max']:.4f} mm with the worn one" in text
    assert (tmp_path / "results" / "kinematics_vs_selfview.png").stat().st_size > 10_000
    assert (tmp_path / "results" / "update_limit.png").stat().st_size > 10_000
    assert ul["limit"]["noise_floor"]["n"] > 0 and "### The limit between updating and recalibrating" in text


def test_report_runs_the_installed_projects_own_benchmarks_wherever_started(tmp_path, monkeypatch):
    """Started from any folder (here one holding a bench/ of its own), the report runs selfview's benchmarks."""
    import selfview.bench

    (tmp_path / "bench").mkdir()
    (tmp_path / "bench" / "online.py").write_text("print('{}')\n")
    monkeypatch.chdir(tmp_path)
    d = find_bench_dir()
    assert d == Path(selfview.bench.__file__).resolve().parent
    assert (d / "online.py").read_text() != "print('{}')\n" and (d / "offline.py").is_file()
    assert find_reference_dir() is not None and (find_reference_dir() / "ccal.log").is_file()
    assert find_reference_dir(tmp_path) is None  # a folder without Willson's data is no reference


def test_keep_refreshes_one_benchmark_and_keeps_the_others_figures(fake_benches, tmp_path):
    """--keep: the benchmarks not rerun keep their stored JSON, marked as kept in the report."""
    out = tmp_path / "docs" / "RESULTS.md"
    (tmp_path / "docs" / "results").mkdir(parents=True)
    stored = {"speed": {"solve_us": 99.0}, "ok": True, "args": ["stored"]}
    (tmp_path / "docs" / "results" / "online.json").write_text(json.dumps(stored))
    benches = (Bench("good", "a good one", ("--out", "{out}")),)
    res = make_report(out, benches=benches, bench_dir=fake_benches, trials=0, keep=True, quick=True)
    assert res["runs"]["good"] == "ok" and res["runs"]["online"] == "ok"
    text = out.read_text()
    # the header names the one part refreshed at small sizes; the kept full-size part is not called quick
    assert "(run with --quick, small sizes: good; every other part at full size)" in text and "QUICK run" not in text
    assert ("| `bench/online` | on-line solves vs cv2.solvePnP, per-frame step | ok (kept: figures of an earlier run) | - "
            "| [online.json]") in text
    assert "The parts marked kept were not rerun by it: their figures are those of earlier runs." in text
    assert json.loads((tmp_path / "docs" / "results" / "online.json").read_text()) == stored


def test_render_only_writes_the_page_from_the_stored_json_alone(fake_benches, tmp_path):
    """--render-only reruns nothing: the page comes from results/*.json, and says what each run took."""
    out = tmp_path / "docs" / "RESULTS.md"
    make_report(out, benches=(Bench("good", "a good one"),), bench_dir=fake_benches, trials=0, command="first run")
    results = tmp_path / "docs" / "results"
    (results / "online.json").write_text(json.dumps({"frame_budget": {"frame_ms": 40.0, "step_ms_plain": 1.5,
                                                                       "step_ms_cluttered": 1.9, "search_ms": 17.6},
                                                      "median_us": {"4P-I": 30.0}}))
    (fake_benches / "good.py").write_text("raise SystemExit('must not run')\n")
    res = make_report(out, bench_dir=fake_benches, render_only=True)
    assert res["runs"] == {"online": "ok"}  # only what is stored (good is not one of the report's benchmarks)
    text = out.read_text()
    assert "Produced by `first run`" in text  # the command that made the figures, not the re-rendering
    assert "| per-frame step, photographed table (tracker + 4P-I) | 1.9 | 4.8 % |" in text
    assert "| full search (first frame, or after a lost one) | 17.6 | 44.0 % |" in text
    with pytest.raises(ConfigError, match="no results folder"):
        make_report(tmp_path / "elsewhere" / "R.md", render_only=True)


def test_the_published_page_is_short_and_every_figure_links_its_json():
    """docs/RESULTS.md: at most 300 lines; each section that shows a figure links a JSON file that exists."""
    page = REPO / "docs" / "RESULTS.md"
    text = page.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 300
    sections = re.split(r"^#{2,3} ", text, flags=re.M)[1:]
    assert len(sections) >= 8
    for sec in sections:
        title = sec.splitlines()[0]
        links = re.findall(r"\]\((results/[^)]+\.json)\)", sec)
        has_figure = re.search(r"\d\.\d", "\n".join(sec.splitlines()[1:]))
        if has_figure or title.startswith(("Speed", "The fault")):
            assert links, f"section '{title}' shows figures but links no JSON file"
        for ln in links:
            assert (page.parent / ln).is_file(), f"section '{title}' links {ln}, which does not exist"


def test_the_published_page_is_what_its_stored_results_render(tmp_path):
    """docs/RESULTS.md holds no figure typed in by hand: ``--render-only`` on a copy of docs/results/ writes
    the same page, line for line (a section or a table row edited by hand, or a JSON file changed without
    the page, shows here)."""
    import shutil

    docs = tmp_path / "docs"
    shutil.copytree(REPO / "docs" / "results", docs / "results")
    shutil.copyfile(REPO / "docs" / "RESULTS.md", docs / "RESULTS.md")
    make_report(docs / "RESULTS.md", render_only=True)
    published = (REPO / "docs" / "RESULTS.md").read_text(encoding="utf-8").splitlines()
    rendered = (docs / "RESULTS.md").read_text(encoding="utf-8").splitlines()
    assert rendered == published, [ln for ln in rendered if ln not in published] + [ln for ln in published if ln not in rendered]


def test_the_grasping_section_reads_its_run_size_and_landings_from_the_json():
    """The section types in no figure: the landings behind the arms' RP and AP and whether the run was quick come
    from positioning.json (a run that did not record its landings does not get a count made up)."""
    cell = load_cell(default_cell_path())
    mach = {"cpu": "test cpu", "cores": 2, "usable_cores": 2, "python": "3", "numpy": "2", "opencv": "4",
            "platform": "test", "selfview": "0"}
    data = json.loads((REPO / "docs" / "results" / "positioning.json").read_text())

    def section(d):
        runs = {"positioning": BenchRun("positioning", "grasping", "ok", data=d)}
        text = render_markdown(runs, mach, None, None, quick=False, seconds=1.0, command="c",
                               cell_limit=cell.monitor.update_limit, results_dir=Path("."))
        return text.split("### Visually guided grasping", 1)[1].split("\n### ", 1)[0]

    counted = dict(data, quick=False, profiles={k: v | {"landings": 17} for k, v in data["profiles"].items()})
    text = section(counted)
    assert "(ISO 9283 repeatability RP and accuracy AP over 17 landings)" in text and "--quick" not in text
    text = section(dict(data, quick=True, profiles={k: {kk: vv for kk, vv in v.items() if kk != "landings"}
                                                    for k, v in data["profiles"].items()}))
    assert "AP over their landings)" in text and "starts per condition (a --quick run)" in text
    assert "30 landings" not in text
