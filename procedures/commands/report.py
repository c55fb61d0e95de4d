"""``selfview report``: rerun every benchmark, the experiment and Tsai on Willson's data; write one report."""

from __future__ import annotations

import sys

from selfview.procedures.commands._common import numeric, print_json


def register(sub):
    p = sub.add_parser(
        "report",
        help="rerun every benchmark and study and write docs/RESULTS.md with its JSON and plots",
        description=(
            "Reruns every bench/ script (render, offline, online, robot, io, kinematics_vs_selfview, update_limit, error_budget, "
            "intrinsics, clutter, faults, positioning) as a "
            "subprocess with a time limit each, the paper's experiment on the simulated cell (20 trials per series) and "
            "Tsai's method on Willson's reference data, and writes RESULTS.md with speed (OpenCV's peers timed in the same "
            "run), accuracy against the truth and the peers, the fault campaign and what to expect on a real cell, and "
            "beside it results/ with every JSON object, table and plot, which the page links. A missing or failing "
            "benchmark is reported as such. "
            "The grasping study alone took 223 s with --quick on 2 idle cores, 1970 s at load 25 (its full run, "
            "20 starts per condition, 830 s on 2 idle cores); --quick runs every part at small sizes."
        ),
    )
    p.add_argument("--out", default="docs/RESULTS.md", metavar="RESULTS.md", help="the report (default %(default)s)")
    p.add_argument("--quick", action="store_true", help="small sizes everywhere (a smoke test, not evidence)")
    p.add_argument("--only", metavar="NAME", nargs="+", help="run only these benchmarks (e.g. offline update_limit)")
    p.add_argument("--trials", type=numeric(integer=True, lo=0, hi=10_000, name="trials"), help="experiment trials per series (default 20, quick 2; 0 skips it)")
    p.add_argument("--bench-dir", metavar="DIR", help="a bench/ folder to run instead of the installed project's own")
    p.add_argument("--reference", metavar="DIR", help="the folder of Willson's data (default: the copy shipped with selfview)")
    p.add_argument("--jobs", type=numeric(integer=True, lo=1, hi=64, name="jobs"), default=2, help="processes for the experiment's two series (default 2)")
    p.add_argument("--write-cell", metavar="CELL.yaml",
                   help="also write the update limit measured in this run into that cell file (e.g. selfview/data/cell.yaml)")
    p.add_argument("--keep", action="store_true",
                   help="with --only (and --trials 0): keep the stored figures of every part not rerun (results/*.json "
                        "beside --out), so that one benchmark can be refreshed without rerunning the others")
    p.add_argument("--render-only", action="store_true",
                   help="rerun nothing: write the page again from the stored JSON (results/*.json beside --out)")
    p.add_argument("--json", action="store_true", help="print where everything went as one JSON object")
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from selfview.bench.report import BENCHES, make_report
    from selfview.errors import ConfigError

    benches = BENCHES
    if args.only:
        known = {b.name: b for b in BENCHES}
        unknown = [n for n in args.only if n not in known]
        if unknown:
            raise ConfigError(f"--only {' '.join(unknown)}: expected benchmark names among {', '.join(known)}")
        benches = tuple(known[n] for n in args.only)
    if args.render_only and (args.only or args.quick or args.trials or args.write_cell):
        raise ConfigError("--render-only reruns nothing: it takes no --only, --quick, --trials or --write-cell")
    if args.trials is not None and args.trials < 0:
        raise ConfigError(f"--trials: expected a number >= 0, got {args.trials}")

    def say(msg):
        if not args.json:
            print(f"report: {msg}", file=sys.stderr, flush=True)

    command = "selfview report " + " ".join(a for a in sys.argv[2:]) if sys.argv[1:2] == ["report"] else "selfview report"
    res = make_report(args.out, quick=args.quick, benches=benches, bench_dir=args.bench_dir, reference=args.reference,
                      trials=args.trials, jobs=args.jobs, progress=say, command=command.strip(),
                      write_cell=args.write_cell, keep=args.keep,
                      render_only=args.render_only)
    if args.json:
        print_json(res)
    else:
        print(f"wrote {res['markdown']} and {res['results']}/ in {res['seconds']:.0f} s: "
              + ", ".join(f"{k} {v}" for k, v in res["runs"].items()))
    bad = {k: v for k, v in res["runs"].items() if v != "ok"}
    if res.get("experiment_failed"):
        bad["experiment"] = f"failed ({res['experiment_failed']})"
    if not bad:
        return 0
    print("selfview report: error: " + ", ".join(f"{k} {v}" for k, v in bad.items()) + " (the report says so)\n"
          "  what to do: " + ("run it from a checkout, or give --bench-dir the checkout's bench/ folder"
                              if set(bad.values()) == {"not available"} else
                              "rerun the part named above alone (--only NAME) and read its error"), file=sys.stderr)
    # a part that is not there is a matter of files (3); one that ran and failed, of the program (1)
    return 3 if set(bad.values()) == {"not available"} else 1
