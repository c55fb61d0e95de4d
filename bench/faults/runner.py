"""The campaign: faults per section, each section's share of the time budget, one JSON object."""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from selfview.bench import faults as campaign_doc
from selfview.bench.faults import common
from selfview.bench.faults.common import Tally, _quiet_logs, _thread_deaths
from selfview.bench.faults.val import run_val
from selfview.bench.faults.modbus import run_modbus
from selfview.bench.faults.files import make_fixtures, run_files
from selfview.bench.faults.cli import run_cli
from selfview.bench.faults.devices import run_devices
from selfview.bench.faults.paths import run_paths
from selfview.bench.faults.saves import run_saves
from selfview.bench.faults.signals import run_sigint
from selfview.bench.faults.stalls import run_stalls
from selfview.bench.faults.epipe import run_epipe


#: rough seconds of budget per fault, per section, on 2 cores (the ones that start a process cost most)
COST_S = {"signals": 1.2, "devices": 3.5, "stalls": 3.0, "epipe": 1.4, "saves": 0.8, "paths": 1.6, "cli": 1.25,
          "files": 0.045, "modbus": 0.026, "val": 0.042}
ORDER = ("signals", "devices", "stalls", "epipe", "saves", "paths", "cli", "files", "modbus", "val")
#: the sections that start a process per fault: a fixed number each (quick, full)
FIXED = {"signals": (3, 48), "devices": (1, 12), "stalls": (2, 40), "epipe": (2, 32), "saves": (3, 36), "paths": (4, 36),
         "cli": (8, 80)}


def plan_counts(faults: int, quick: bool) -> dict:
    """Faults per section: the ones that start a process are a fixed small share, the rest is split."""
    fixed = {k: v[0 if quick else 1] for k, v in FIXED.items()}
    rest = max(0, faults - sum(fixed.values()))
    val = int(rest * 0.35)
    modbus = int(rest * 0.25)
    return {"val": val, "modbus": modbus, "files": rest - val - modbus, **fixed}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=campaign_doc.__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--faults", type=int, default=None, help="faults to inject (default 10000; --quick 300)")
    ap.add_argument("--budget-s", type=float, default=None,
                    help="stop injecting after this many seconds (default 600; --quick 50); the JSON says how many were injected")
    ap.add_argument("--quick", action="store_true", help="a few hundred faults in well under a minute")
    args = ap.parse_args(argv)
    faults = args.faults if args.faults is not None else (300 if args.quick else 10000)
    budget = args.budget_s if args.budget_s is not None else (50.0 if args.quick else 600.0)
    counts = plan_counts(faults, args.quick)
    tally = Tally()
    common.set_notes(tally)
    _thread_deaths(tally)
    _quiet_logs()
    t0 = time.monotonic()
    load0 = round(os.getloadavg()[0], 2)
    # each section's deadline: its share of the budget by its estimated cost, cumulative (a section
    # that ends early leaves its time to the next ones)
    cost = {k: counts[k] * COST_S[k] for k in ORDER}
    total_cost = sum(cost.values()) or 1.0
    shares, acc = {}, 0.0
    for k in ORDER:
        acc += cost[k] / total_cost
        shares[k] = min(1.0, acc)
    with tempfile.TemporaryDirectory(prefix="selfview-faults-") as tmp:
        # the campaign's own lock folder: a record a killed case leaves (a motion, an energised valve) is
        # seen by the campaign's later cases only, never by a program outside it
        locks = Path(tmp) / "locks"
        locks.mkdir(mode=0o700)
        os.environ["SELFVIEW_LOCK_DIR"] = str(locks)
        fixtures = make_fixtures(Path(tmp), args.seed)
        run_files(0, args.seed, t0 + budget, tally, fixtures)  # the clean files' fingerprints
        sections = {}
        runs = {"signals": lambda d: run_sigint(counts["signals"], args.seed, d, tally, fixtures),
                "devices": lambda d: run_devices(counts["devices"], args.seed, d, tally, fixtures),
                "stalls": lambda d: run_stalls(counts["stalls"], args.seed, d, tally, fixtures),
                "epipe": lambda d: run_epipe(counts["epipe"], args.seed, d, tally, fixtures),
                "saves": lambda d: run_saves(counts["saves"], args.seed, d, tally, fixtures),
                "paths": lambda d: run_paths(counts["paths"], args.seed, d, tally, fixtures),
                "cli": lambda d: run_cli(counts["cli"], args.seed, d, tally, fixtures),
                "files": lambda d: run_files(counts["files"], args.seed, d, tally, fixtures),
                "modbus": lambda d: run_modbus(counts["modbus"], args.seed, d, tally),
                "val": lambda d: run_val(counts["val"], args.seed, d, tally)}
        for name in ORDER:
            n0, s0 = tally.total, time.monotonic()
            # a section late behind an overrunning one still gets time for a case or two, and each of the
            # small sections that start a process per fault time for all of its cases
            least = counts[name] if name in FIXED else 3
            runs[name](max(t0 + budget * shares[name], time.monotonic() + 1.0 + least * COST_S[name]))
            sections[name] = {"planned": counts[name], "faults": tally.total - n0, "seconds": round(time.monotonic() - s0, 1)}
    out = {"benchmark": "fault campaign", "seed": args.seed, "planned": counts, "budget_s": budget,
           "sections": sections}
    out.update(tally.to_json())
    out["seconds"] = round(time.monotonic() - t0, 1)
    out["complete"] = out["total"] >= sum(counts.values())
    out["load_1min"] = {"start": load0, "end": round(os.getloadavg()[0], 2)}  # other work on the machine slows the cases
    out["blind_spots"] = [
        "calibration files: the fields 'created' and 'software' are not compared (nothing uses them)",
        "robot: a motion that ends at its target by another path is not seen, unless the controller "
        "received a motion line other than the checked one (that is seen, and unsafe)",
        "robot: the controller's locations other than the one a case defines or reads, and its "
        "settings other than SPEED and CAL, are not compared after a case",
        "gripper: every coil is read after a case (one the driver never commands, energised, is unsafe); the registers are not",
        "CLI: a command that exits 0 on a hostile picture counts as wrong_value; its output is not checked",
        "signals: a run that ended before the signal counts as no_effect; its results are not checked",
        "a second process: the robot's port and the valve terminal; the grabber is not (the simulated cell's camera is "
        "frames://, which has no owner)",
        "host stalls: the robot commands only (ready, depart); a Ctrl-Z's stop is carried out because each child runs "
        "in its own process group of the campaign's session (in an orphaned group the kernel discards it: ABORT only)",
        "closed standard output: robot and park write only once their devices are closed, so their cases check the exit "
        "and its message; monitor's (0 to 2 lines read) check the stop of a running cell",
        "a read-only folder is made with chattr +i (or permissions, which root ignores): where neither holds, its "
        "cases do not run and the notes say so",
    ]
    out["outcomes"] = {
        "clear_error": "refused or failed with a project error and a message; the cell as it should be",
        "no_effect": "succeeded and returned or did the truth",
        "invisible": "wrong values (counted in wrong_value) that no check can see, per kind, with the reason",
        "not_fired": "faults armed whose byte never passed (not counted in total)",
    }
    print(json.dumps(out).replace(tmp, "<work>"))  # no path of this machine in the JSON
    return 0


if __name__ == "__main__":
    sys.exit(main())

