"""A short run of the fault campaign (``bench/faults/``): its JSON, its counts, and the targets.

The campaign is run as a developer runs it (a process printing one JSON object), with a fixed seed, a
few hundred faults and a time budget. Targets: no hang, no traceback, nothing unsafe, no calibration
file lost, and wrong values accepted only where no check can see them. The fault kinds listed in
``KNOWN_DEFECTS`` may miss a target for a reason no software check can remove (said beside each); every
other kind the run injects (termination signals, a second process, killed saves, endless files, numbers at
the command line included) must meet all of them.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

OUTCOMES = ("clear_error", "no_effect", "hang", "traceback", "unsafe", "wrong_value", "lost_file")
TARGET_ZERO = ("hang", "traceback", "unsafe", "lost_file")

#: fault kind -> why it may still miss a target: what no software check on this side of the link can see
#: or prevent (every defect the first campaign found is fixed and held to the targets here)
KNOWN_DEFECTS = {
    # the serial link cut during a motion: no ABORT can be written any more; the controller's own stop
    # (its E-stop chain, a lost-host watchdog where configured) is what remains
    "val.d2h.cutoff": "a cut link: ABORT cannot reach the controller",
    "val.h2d.cutoff": "likewise",
    # a cell file has no checksum: a changed name or structure, or a file cut at a line boundary (missing
    # keys take their defaults), loads as written
    "cellfile.bitflip": "a cell file has no checksum",
    "cellfile.garbled": "likewise",
    "cellfile.truncated": "likewise",
    "cli.cellfile.garbled": "likewise",
    "cli.cellfile.truncated": "likewise",
    # a re-checksummed calibration file whose informational fields (residual figures, provenance text)
    # changed is taken as written: every field that is computed with is type- and range-checked
    "calfile.wrong_type": "informational fields of a re-checksummed file",
    "cli.calfile.wrong_type": "likewise",
}


@pytest.fixture(scope="module")
def campaign():
    out = subprocess.run(
        [sys.executable, "-m", "selfview.bench.faults", "--quick", "--faults", "220", "--budget-s", "80", "--seed", "3"],
        capture_output=True, text=True, timeout=300,
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
    # the families that start a process per fault: each ran, within its small share
    for name in ("signals", "devices", "stalls", "epipe", "saves", "paths"):
        assert 0 < campaign["sections"][name]["faults"] <= campaign["planned"][name], (name, campaign["sections"])
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


def test_the_json_names_no_path_of_this_machine(campaign):
    text = json.dumps(campaign)
    assert "selfview-faults-" not in text and "/tmp/" not in text


def test_a_second_process_counts_as_unsafe_only_if_park_drove_the_arm_after_it():
    """The scoring of ``devices.robot``: park closes the port before it exits, and a second process that
    starts slowly (a loaded machine) may come after that; it drove a robot park owned only if park's
    lines follow its SPEED at the controller."""
    from selfview.bench.faults.devices import _park_went_on

    assert not _park_went_on(["", "SPEED (20)", "STATUS", "DO APPRO PLATE, (50)", "", "SPEED (45)", "STATUS"], 45)
    assert not _park_went_on(["SPEED (45)", "", "STATUS", ""], 45)
    assert _park_went_on(["", "SPEED (45)", "STATUS", "WHERE", "DO MOVES (PRESS)"], 45)
    assert _park_went_on(["SPEED 45", "DO DEPART (50)", "STATUS"], 45)  # the bare form is the same command
