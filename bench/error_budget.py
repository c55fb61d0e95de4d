"""Study: the error budget of the paper's experiment on an imperfect simulated cell.

The paper's protocol (section 5, Tables 1 and 2; ``selfview.procedures.experiment.run_direct``) run with
each part of a real cell's imperfections alone at its realistic magnitude, with all, with none and with
the ``paper-like`` profile (``configurations``), on the same seeds so that only the imperfections differ;
``paper_check`` compares ``paper-like`` with the paper. Prints one JSON object; ``--out DIR`` also writes
``error_budget.json`` and ``error_budget.md``.

    python bench/error_budget.py [--trials 10] [--jobs 2] [--configs ideal plate ... paper-like] [--quick] [--out DIR]
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

from selfview.files.cell import default_cell_path, load_cell  # noqa: E402
from selfview.mocks.imperfections import PARTS, PROFILES, Imperfections  # noqa: E402
from selfview.procedures.paper import PAPER_TABLES  # noqa: E402

BUDGET_METHODS = ("3P-U", "4P-U", "5P-U", "4P-I", "4P-R", "5P-R")
PAPER_METHODS = ("3P-U", "4P-U", "5P-U", "4P-R", "5P-R")
SERIES = ("cable", "tilt")
AXES = ("c_x", "c_y", "c_z")


def configurations(names=None) -> dict[str, Imperfections]:
    """'ideal', each part of ``realistic`` alone, 'realistic' (all parts) and 'paper-like' (or ``names``)."""
    real = PROFILES["realistic"]
    out = {"ideal": PROFILES["ideal"]}
    out.update({part: real.only(part) for part in PARTS if not real.only(part).ideal})
    out["realistic"] = real
    out["paper-like"] = PROFILES["paper-like"]
    if names:
        unknown = [n for n in names if n not in out]
        if unknown:
            raise SystemExit(f"--configs: unknown {', '.join(unknown)}; expected some of {', '.join(out)}")
        out = {n: out[n] for n in names}
    return out


def _run(name: str, imp: Imperfections, series: str, trials: int, seed: int) -> tuple[str, str, dict, list]:
    """One configuration and series: park, calibrate off-line, disturb the camera, re-measure with each
    method (3P-U, 4P-U, 5P-U, 4P-I, 4P-R, 5P-R); the mean absolute TCP error per camera axis [mm] against
    the simulator's truth and against the off-line method on the second picture (the paper's measure),
    and the failed trials with their reasons (a miss, never a result)."""
    from selfview.procedures.experiment import run_direct

    cell = load_cell(default_cell_path())
    t0 = time.perf_counter()
    _, summary = run_direct(cell, (series,), trials=trials, seed=seed + (10_000 if series == "tilt" else 0),
                            profile=imp)
    ser = summary.get(series, {"trials": 0, "methods": {}})
    methods = {}
    for m in BUDGET_METHODS:
        e = ser["methods"].get(m, {})
        methods[m] = {
            "n": e.get("n", 0),
            "failed": e.get("failed", 0),
            "reference_mean_mm": e.get("reference", {}).get("mean_mm"),
            "reference_max_mm": e.get("reference", {}).get("max_mm"),
            "truth_mean_mm": e.get("truth", {}).get("mean_mm"),
        }
    out = {
        "trials": ser.get("trials", 0),
        "methods": methods,
        "offline_reference_vs_truth_mean_mm": ser.get("offline_reference_vs_truth", {}).get("mean_mm"),
        "tcp_shift_mm": ser.get("tcp_shift_mm"),
        "seconds": round(time.perf_counter() - t0, 1),
    }
    return name, series, out, summary.get("failures", [])


def paper_check(conf: dict) -> dict:
    """How ``conf`` (one configuration's results) compares with the paper's Tables 1 and 2.

    Per series, method (3P-U, 4P-U, 5P-U, 4P-R, 5P-R) and axis where the paper's mean is at least 0.05 mm,
    the ratio of ours to the paper's against the reference (within a factor of 2: 0.5..2); and the
    pattern: 3P-U's mean error, summed over the axes, at least three times 4P-U's in both tables;
    Table 2's 4P-U c_z above 4P-R's."""
    ratios, misses = [], []
    for series in SERIES:
        for m in PAPER_METHODS:
            ours = conf["series"][series]["methods"][m]["reference_mean_mm"]
            paper = PAPER_TABLES[series][m][0]
            for k, ax in enumerate(AXES):
                if paper[k] < 0.05:
                    continue
                r = None if ours is None else ours[k] / paper[k]
                item = {"series": series, "method": m, "axis": ax, "paper_mm": paper[k],
                        "ours_mm": None if ours is None else ours[k], "ratio": None if r is None else round(r, 3)}
                ratios.append(item)
                if r is None or not 0.5 <= r <= 2.0:
                    misses.append(item)

    def total(series, m):
        v = conf["series"][series]["methods"][m]["reference_mean_mm"]
        return None if v is None else sum(v)

    pattern = {}
    for series in SERIES:
        t3, t4 = total(series, "3P-U"), total(series, "4P-U")
        pattern[f"{series}_3P-U_over_4P-U"] = None if not (t3 and t4) else round(t3 / t4, 2)
    tu = conf["series"]["tilt"]["methods"]["4P-U"]["reference_mean_mm"]
    tr = conf["series"]["tilt"]["methods"]["4P-R"]["reference_mean_mm"]
    pattern["tilt_4P-U_cz_over_4P-R_cz"] = None if not (tu and tr and tr[2]) else round(tu[2] / tr[2], 2)
    pattern_ok = (all(v is not None and v >= 3 for k, v in pattern.items() if k.endswith("over_4P-U"))
                  and (pattern["tilt_4P-U_cz_over_4P-R_cz"] or 0) > 1)
    return {"within_factor_2": len(ratios) - len(misses), "checked": len(ratios), "misses": misses,
            "ratios": ratios, "pattern": pattern, "pattern_ok": bool(pattern_ok),
            "reproduces": bool(pattern_ok and not misses)}


def budget_markdown(out: dict) -> str:
    """The error-budget tables: per series, configuration and method, the mean error against the
    reference (the paper's measure) and against the truth; the paper's figures beside them."""
    lines = []
    for series in SERIES:
        lines += [f"#### {'Table 1 (cable, 1.5 mm)' if series == 'cable' else 'Table 2 (tilt, 4.5 mm)'}: "
                  "mean TCP error [mm] c_x / c_y / c_z", "",
                  "| configuration | " + " | ".join(f"{m} vs reference" for m in BUDGET_METHODS)
                  + " | 4P-U vs truth | 4P-R vs truth | reference vs truth | failed |",
                  "|---" * (len(BUDGET_METHODS) + 5) + "|"]

        def f3(v):
            return "-" if v is None else " / ".join(f"{x:.3f}" for x in v)

        for name, conf in out["configurations"].items():
            s = conf["series"][series]
            ms = s["methods"]
            failed = sum(ms[m]["failed"] for m in BUDGET_METHODS) + len([f for f in conf["failures"] if f["series"] == series])
            lines.append(f"| {name} | " + " | ".join(f3(ms[m]["reference_mean_mm"]) for m in BUDGET_METHODS)
                         + f" | {f3(ms['4P-U']['truth_mean_mm'])} | {f3(ms['4P-R']['truth_mean_mm'])}"
                         + f" | {f3(s['offline_reference_vs_truth_mean_mm'])} | {failed} |")
        paper = PAPER_TABLES[series]
        lines.append("| the paper | " + " | ".join(
            (" / ".join(f"{x:.2f}" for x in paper[m][0]) if m in paper else "-") for m in BUDGET_METHODS) + " | - | - | - | - |")
        lines.append("")
    chk = out.get("paper_check")
    if chk:
        p = chk["pattern"]
        lines += [f"paper-like against the paper: {chk['within_factor_2']} of {chk['checked']} means (axes where the "
                  f"paper's is >= 0.05 mm) within a factor of 2; 3P-U / 4P-U (sum over the axes) "
                  f"{p['cable_3P-U_over_4P-U']} (Table 1), {p['tilt_3P-U_over_4P-U']} (Table 2), the paper 11.2 and 5.0; "
                  f"Table 2's 4P-U c_z / 4P-R c_z {p['tilt_4P-U_cz_over_4P-R_cz']}, the paper 3.0.", ""]
        for mm in chk["misses"]:
            lines.append(f"- outside a factor of 2: {mm['series']} {mm['method']} {mm['axis']}: ours {mm['ours_mm']} mm, "
                         f"the paper {mm['paper_mm']} mm (ratio {mm['ratio']})")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10, help="trials per series and configuration (default 10)")
    ap.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes (default 2)")
    ap.add_argument("--configs", nargs="+", help="configurations to run (default: all)")
    ap.add_argument("--seed", type=int, default=0, help="first world seed (default 0)")
    ap.add_argument("--quick", action="store_true", help="a small run: 2 trials per series")
    ap.add_argument("--out", metavar="DIR", help="also write error_budget.json and error_budget.md here")
    args = ap.parse_args(argv)
    trials = 2 if args.quick else args.trials
    if trials < 1:
        raise SystemExit("--trials: expected at least 1")
    confs = configurations(args.configs)
    t0 = time.perf_counter()
    tasks = [(name, imp, series, trials, args.seed) for name, imp in confs.items() for series in SERIES]
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as ex:
            results = list(ex.map(_run, *zip(*tasks)))
    else:
        results = [_run(*t) for t in tasks]
    out: dict = {"trials_per_series": trials, "seed": args.seed, "methods": list(BUDGET_METHODS),
                 "configurations": {}}
    for name, imp in confs.items():
        out["configurations"][name] = {"imperfections": imp.as_dict(), "series": {}, "failures": []}
    for name, series, res, failures in results:
        out["configurations"][name]["series"][series] = res
        out["configurations"][name]["failures"] += failures
    out["paper"] = {s: {m: {"mean_mm": list(v[0]), "max_mm": list(v[1])} for m, v in t.items()} for s, t in PAPER_TABLES.items()}
    if "paper-like" in out["configurations"]:
        out["paper_check"] = paper_check(out["configurations"]["paper-like"])
    out["seconds"] = round(time.perf_counter() - t0, 1)
    if args.out:
        d = Path(args.out)
        d.mkdir(parents=True, exist_ok=True)
        (d / "error_budget.json").write_text(json.dumps(out, indent=1))
        (d / "error_budget.md").write_text(budget_markdown(out))
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
