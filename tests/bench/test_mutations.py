"""bench/mutations.py: its machinery on one cheap mutation (applied to a copy, caught by its tests), and a
mutation whose text is gone reported as such, never counted as caught."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from selfview.bench import mutations as M

ROOT = Path(__file__).resolve().parents[2]
CHEAP = "recalibration-alarm-limit-unchecked"  # caught by tests/selfview/test_policy.py in a few seconds


def test_every_mutation_applies_to_this_tree_once(tmp_path):
    names = [m.name for m in M.MUTATIONS]
    assert len(set(names)) == len(names)
    for m in M.MUTATIONS:
        text = (ROOT / m.file).read_text(encoding="utf-8")
        assert text.count(m.original) == 1, f"{m.name}: its original text no longer occurs once in {m.file}"
        assert m.original != m.replacement and m.tests
        for t in m.tests:
            path, _, test = t.partition("::")
            assert (ROOT / path).is_file(), f"{m.name}: {t} does not exist"
            if test:  # a renamed test leaves the mutation with nothing to run (pytest: "not found")
                assert re.search(rf"^def {re.escape(test.split('[')[0])}\(", (ROOT / path).read_text(encoding="utf-8"),
                                 re.M), f"{m.name}: {path} has no test {test}"


def test_one_mutation_is_applied_to_a_copy_and_caught():
    before = (ROOT / "selfview" / "estimation" / "policy.py").read_bytes()
    out = subprocess.run([sys.executable, str(ROOT / "bench" / "mutations.py"), "--only", CHEAP, "--timeout", "300"],
                         cwd=ROOT, capture_output=True, text=True, timeout=400)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert set(res) == {"caught", "total", "errors", "mutations"}
    assert (res["caught"], res["total"], res["errors"]) == (1, 1, 0), res
    (m,) = res["mutations"]
    assert {"name", "file", "caught", "failed_tests", "error"} <= set(m)
    assert m["name"] == CHEAP and m["file"] == "selfview/estimation/policy.py" and m["caught"] is True and m["error"] is None
    assert any("test_a_recalibration_beyond_the_alarm_limit_raises_the_alarm" in t for t in m["failed_tests"]), m
    assert (ROOT / "selfview" / "estimation" / "policy.py").read_bytes() == before  # the repository itself is untouched


def test_a_mutation_that_no_longer_applies_is_reported_not_counted(capsys):
    gone = M.Mutation("gone", "selfview/estimation/policy.py", "text that is not in the file\n", "x\n",
                      ("tests/selfview/test_policy.py",))
    twice = M.Mutation("twice", "selfview/estimation/policy.py", "import", "imp0rt", ("tests/selfview/test_policy.py",))
    missing = M.Mutation("missing", "selfview/no_such_file.py", "a", "b", ("tests/selfview/test_policy.py",))
    assert M.main(["--timeout", "60"], mutations=(gone, twice, missing)) == 0
    res = json.loads(capsys.readouterr().out)
    assert (res["caught"], res["total"], res["errors"]) == (0, 3, 3)
    errors = {m["name"]: m["error"] for m in res["mutations"]}
    assert "no longer applies: the original text is not found" in errors["gone"]
    assert "no longer applies: the original text is found" in errors["twice"] and "times" in errors["twice"]
    assert "no longer applies" in errors["missing"] and "does not exist" in errors["missing"]
    assert not any(m["caught"] for m in res["mutations"])


def test_list_and_unknown_names(capsys):
    assert M.main(["--list"]) == 0
    listed = json.loads(capsys.readouterr().out)["mutations"]
    assert [m["name"] for m in listed] == [m.name for m in M.MUTATIONS]
    with pytest.raises(SystemExit):
        M.main(["--only", "no-such-mutation"])
    assert "unknown mutation" in capsys.readouterr().err


#: the safety rules a realistic one-place bug can break: each mutation must make its named test fail
SAFETY = ("engine-closes-stop-at-first-failure", "engine-cancel-unchecked-between-steps",
          "engine-cleanup-only-for-project-errors", "motion-arrival-ignores-orientation",
          "valve-safe-confirmed-without-read-back", "register-write-echo-unchecked",
          "calfile-without-checksum-accepted", "camfile-nan-covariance-accepted")


def _test_exists(node: str) -> bool:
    path, _, name = node.partition("::")
    return re.search(rf"^def {re.escape(name)}\(", (ROOT / path).read_text(encoding="utf-8"), flags=re.M) is not None


@pytest.mark.slow
@pytest.mark.parametrize("name", SAFETY)
def test_each_safety_mutation_is_caught_by_its_named_test(name, capsys):
    (m,) = [m for m in M.MUTATIONS if m.name == name]
    assert all("::" in t for t in m.tests), f"{name}: name the one test that catches it"
    missing = [t for t in m.tests if not _test_exists(t)]
    if missing:
        pytest.skip(f"the test that catches {name} is not in this tree yet: {missing}")
    assert M.main(["--only", name, "--timeout", "300"]) == 0
    (res,) = json.loads(capsys.readouterr().out)["mutations"]
    assert res["error"] is None and res["caught"], res
    assert set(res["failed_tests"]) & set(m.tests), f"{name} was caught, but not by its named test: {res}"
