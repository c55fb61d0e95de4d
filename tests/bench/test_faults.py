"""A short run of the fault campaign (``bench/faults.py``): its JSON, its counts, and the targets.

The campaign is run as a developer runs it (a process printing one JSON object), with a fixed seed, a
few hundred faults and a time budget. Targets (issue 18): no hang, no traceback, nothing unsafe, no
calibration file lost, and wrong values accepted only where no check can see them. The fault kinds
listed in ``KNOWN_DEFECTS`` still miss a target today (the defects that issue 18 names, which other
branches are fixing); every other kind the run injects must meet all of them. When a fix lands, its
kinds leave the list, and the test holds them to the targets from then on.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

OUTCOMES = ("clear_error", "no_effect", "hang", "traceback", "unsafe", "wrong_value", "lost_file")
TARGET_ZERO = ("hang", "traceback", "unsafe", "lost_file")

#: fault kind -> the issue 18 item that makes it miss a target today (remove a kind when its fix merges)
KNOWN_DEFECTS = {
    # the robot: a corrupted command runs before it is detected (item 3: APPRO 50 sent as 05, DEPART 20 as
    # 2, SPEED 16 as 61), and a stray line or a duplicated CR ends a motion early (item 2)
    "val.h2d.bitflip": "items 2, 3",
    "val.h2d.digit_swap": "item 3",
    "val.h2d.drop": "item 3",
    "val.h2d.dup": "items 2, 3",
    "val.h2d.error_line": "item 2",
    "val.h2d.stray_prompt": "items 2, 3",
    # WHERE and POINT replies with swapped digits or flipped bits accepted (item 4)
    "val.d2h.digit_swap": "item 4",
    "val.d2h.bitflip": "item 4",
    # the link cut during a motion: ABORT never reaches the controller, the arm goes on (item 1)
    "val.d2h.cutoff": "item 1",
    "val.h2d.cutoff": "item 1",
    # a stalled command line reaches the controller after the driver gave up, and runs (item 1)
    "val.h2d.stall": "item 1",
    # a reply stalled during WHERE: once in 230 the engine's run did not return within 15 s (not analysed;
    # the cleanup's ABORT goes through the resync of item 1)
    "val.d2h.stall": "item 1?",
    # the gripper: corrupted read replies accepted as a jaw state or valve outputs (item 9)
    "modbus.d2h.bitflip": "item 9 (also: pymodbus's struct.error escapes the driver as a traceback)",
    "modbus.d2h.dup": "item 9",
    "modbus.d2h.nonascii": "item 9",
    "modbus.d2h.stray_byte": "item 9 (also: struct.error escapes the driver)",
    "modbus.h2d.bitflip": "item 9 (also: a corrupted write's address energises a coil the driver never commands)",
    "modbus.h2d.nonascii": "item 9 (likewise)",
    # a stalled link: safe() fails in the cleanup and the valve stays energised until the watchdog (item 8)
    "modbus.d2h.stall": "item 8",
    "modbus.h2d.stall": "item 8",
    # files: alias bombs, deep nesting, huge numbers, NaN, wrong types (item 12)
    "calfile.alias_bomb": "item 12",
    "calfile.bitflip": "item 12",
    "calfile.deep_nesting": "item 12",
    "calfile.huge_number": "item 12",
    "calfile.nan": "item 12",
    "calfile.wrong_type": "item 12",
    "cellfile.alias_bomb": "item 12",
    "cellfile.deep_nesting": "item 12",
    "cellfile.bitflip": "not an issue-18 item: a cell file has no checksum, a changed name or structure is taken as written",
    "cellfile.garbled": "likewise",
    "cellfile.huge_number": "item 12",
    "cellfile.truncated": "likewise: a file cut at a line boundary loads, the missing keys take their defaults",
    "cellfile.wrong_type": "item 12",
    "cli.calfile.alias_bomb": "item 12",
    "cli.calfile.deep_nesting": "item 12",
    "cli.calfile.huge_number": "item 12",
    "cli.calfile.nan": "item 12",
    "cli.calfile.wrong_type": "item 12",
    "cli.cellfile.alias_bomb": "item 12",
    "cli.cellfile.deep_nesting": "item 12",
    "cli.cellfile.huge_number": "item 12",
    "cli.cellfile.truncated": "likewise",
    "cli.cellfile.wrong_type": "item 12",
    # pictures: a 0-byte file and a huge declared size raise cv2.error (item 14)
    "cli.picture.zero_bytes": "item 14",
    "cli.picture.huge_declared": "item 14",
    # Ctrl-C during park or the cell's calibrate exits 1 "this is a bug" instead of 130 (item 7)
    "sigint.park": "item 7",
    "sigint.calibrate": "item 7",
}


@pytest.fixture(scope="module")
def campaign():
    out = subprocess.run(
        [sys.executable, "-m", "selfview.bench.faults", "--quick", "--faults", "220", "--budget-s", "40", "--seed", "3"],
        capture_output=True, text=True, timeout=240,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    lines = [ln for ln in out.stdout.splitlines() if ln.strip()]
    assert len(lines) == 1, "the campaign prints exactly one JSON object"
    return json.loads(lines[0])


def test_the_json_has_the_documented_shape(campaign):
    for key in ("total", "totals", "kinds", "seconds", "seed", "examples", "invisible"):
        assert key in campaign, key
    assert campaign["seed"] == 3
    assert set(campaign["totals"]) == set(OUTCOMES)
    assert set(campaign["examples"]) >= {"unsafe", "wrong_value", "hang", "traceback"}
    for kind, counts in campaign["kinds"].items():
        assert set(counts) == set(OUTCOMES), kind
        assert all(isinstance(v, int) and v >= 0 for v in counts.values()), kind
    # every section injected faults
    sections = {k.split(".")[0] for k in campaign["kinds"]}
    assert sections >= {"val", "modbus", "calfile", "cellfile", "cli", "sigint"}, sections
    assert campaign["total"] >= 120


def test_the_counts_add_up(campaign):
    kinds = campaign["kinds"]
    assert sum(campaign["totals"].values()) == campaign["total"]
    assert sum(sum(c.values()) for c in kinds.values()) == campaign["total"]
    for o in OUTCOMES:
        assert sum(c[o] for c in kinds.values()) == campaign["totals"][o], o
    for kind, inv in campaign["invisible"].items():
        assert 0 < inv["wrong_value"] <= kinds[kind]["wrong_value"] and inv["why"], kind


def test_the_kinds_without_a_known_defect_meet_the_targets(campaign):
    misses = []
    for kind, counts in campaign["kinds"].items():
        if kind in KNOWN_DEFECTS:
            continue
        for o in TARGET_ZERO:
            if counts[o]:
                misses.append(f"{kind}: {o} {counts[o]}")
        invisible = campaign["invisible"].get(kind, {}).get("wrong_value", 0)
        if counts["wrong_value"] > invisible:
            misses.append(f"{kind}: wrong_value {counts['wrong_value']} (of which no check can see {invisible})")
    examples = [e for o in ("unsafe", "wrong_value", "hang", "traceback", "lost_file") for e in campaign["examples"][o]]
    assert not misses, f"{misses}\nexamples: {examples}"
