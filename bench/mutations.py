"""Mutation check: can the test suite fail? Each mutation is a deliberate bug put into a temporary copy of
the repository; the tests that should catch it run there; it is caught when they fail.

A mutation is data (``MUTATIONS`` below): its name, the file it changes, the exact original text (which
must occur in that file exactly once), the replacement, and the pytest node ids or files that should
catch it. For each one the script copies the repository tree (with the compiled kernels built in place,
so the copy runs the same code; ``selfview/__init__.py`` resolves ``selfview.drivers`` and the others to
the copy's folders), applies the one mutation, and runs

    python -m pytest -x -q -p no:cacheprovider <tests>

with the copy as the working directory, under a timeout. Caught means the tests failed (a non-zero exit
other than "no tests collected" or a usage error). A mutation whose original text is not found, or found
more than once, is reported with an error ("no longer applies") and never counted as caught; a run that
times out counts as not caught, with its error.

Prints one JSON object: ``caught``, ``total``, ``errors`` (mutations that no longer apply or timed out),
and ``mutations``: a list of {name, file, caught, failed_tests, error, seconds}.

    python bench/mutations.py [--only NAME ...] [--list] [--timeout 600]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Mutation:
    """One deliberate bug: in ``file`` (relative to the repository), ``original`` becomes ``replacement``;
    ``tests`` (pytest node ids or files, relative to the repository) should then fail."""

    name: str
    file: str
    original: str
    replacement: str
    tests: tuple[str, ...]
    why: str = ""


MUTATIONS: tuple[Mutation, ...] = (
    Mutation(
        "val-echo-first-word",
        "drivers/puma_val_serial/driver.py",
        "            if not body or _norm(body) in echoes:\n",
        "            if not body or _norm(body).split()[0] in {e.split()[0] for e in echoes if e}:\n",
        ("tests/drivers/test_puma_transcript.py", "tests/drivers/test_puma_contract.py"),
        "the VAL echo matched on its first word only: a reply line starting with the command's word is dropped",
    ),
    Mutation(
        "calfile-written-in-place",
        "selfview/calfile.py",
        '    _atomic_write(p, text.encode("utf-8"))\n',
        '    p.write_bytes(text.encode("utf-8"))\n',
        ("tests/selfview/test_calfile_atomic.py",
         "tests/procedures/test_cli_calibrate_track.py::test_track_auto_follows_the_policy_and_apply_writes_atomically"),
        "the calibration writer writes the file in place (a failure midway leaves a torn file)",
    ),
    Mutation(
        "calfile-written-before-read-back",
        "selfview/calfile.py",
        '    Calibration.from_document(yaml.safe_load(text), source=str(p))\n    _atomic_write(p, text.encode("utf-8"))\n',
        '    _atomic_write(p, text.encode("utf-8"))\n    Calibration.from_document(yaml.safe_load(text), source=str(p))\n',
        ("tests/selfview/test_calfile_atomic.py",),
        "the file replaced before the check that it reads back",
    ),
    Mutation(
        "recalibration-alarm-limit-unchecked",
        "selfview/policy.py",
        '        if self.classify(delta_R, d_R) == "alarm":\n',
        "        if False:\n",
        ("tests/selfview/test_policy.py",),
        "a recalibration that itself measures more than the alarm limit is applied",
    ),
    Mutation(
        "abort-failure-escapes-cleanup",
        "procedures/engine.py",
        "        except Exception as exc:  # never let cleanup itself die\n",
        "        except ZeroDivisionError as exc:  # never let cleanup itself die\n",
        ("tests/procedures/test_engine.py",),
        "an ABORT that fails with anything but a CellError escapes the engine's cleanup",
    ),
    Mutation(
        "v4l2-std-range-unchecked",
        "drivers/frame_grabber_v4l2/url.py",
        '    if not 0 < v < 1 << 64:\n        raise ConfigError(f"{url}: std={text!r} is not a v4l2_std_id")\n',
        "",
        ("tests/drivers/test_grabber_v4l2.py",),
        "std=0 or a number beyond 64 bits accepted as a video standard",
    ),
    Mutation(
        "min-discs-60",
        "selfview/discs.py",
        "min_discs: int = 12) -> DiscDetections:",
        "min_discs: int = 60) -> DiscDetections:",
        ("tests/selfview/test_discs.py::test_the_minimum_disc_count", "tests/selfview/test_offline.py::test_robustness"),
        "the minimum disc count raised from 12 to 60: the standard pictures are refused",
    ),
    Mutation(
        "camera-half-pixel-shift",
        "selfview/camera.py",
        "out = np.column_stack([XY_hat[:, 0] / self.aspect + self.cx, XY_hat[:, 1] + self.cy])",
        "out = np.column_stack([XY_hat[:, 0] / self.aspect + self.cx + 0.5, XY_hat[:, 1] + self.cy])",
        ("tests/selfview/test_discs.py::test_alt_renderer_truth_is_self_consistent",
         "tests/selfview/test_fingertips.py::test_prediction_agrees_with_the_independent_renderer"),
        "the project's projection half a pixel off its convention (its own renderer follows it along)",
    ),
    Mutation(
        "disc-bias-correction-removed",
        "selfview/offline.py",
        "    uv_c = correct_disc_bias(det, ts.camera, ts.C_H_W, cell.plate)\n",
        "    uv_c = det.uv\n",
        ("tests/selfview/test_offline.py::test_accuracy_on_an_independent_renderer",
         "tests/selfview/test_offline.py::test_accuracy_over_30_seeds_on_the_project_renderer"),
        "the off-line calibration without its disc-bias correction",
    ),
)

_IGNORE = shutil.ignore_patterns(".git", "__pycache__", "*.egg-info", "build", ".pytest_cache", "*.pyc", ".ci-*")
# pytest's exit codes that do not mean "a test failed": interrupted, internal error, usage, no tests
_NOT_A_FAILURE = {2, 3, 4, 5}


def copy_tree(dest: Path, root: Path = ROOT) -> Path:
    """The repository's tree (kernels built in place included) copied to ``dest``; returns it."""
    shutil.copytree(root, dest, ignore=_IGNORE, symlinks=True)
    return dest


def apply(m: Mutation, tree: Path) -> str | None:
    """Put ``m`` into the tree; the reason it cannot be applied, or None."""
    path = tree / m.file
    if not path.is_file():
        return f"no longer applies: {m.file} does not exist"
    text = path.read_text(encoding="utf-8")
    n = text.count(m.original)
    if n != 1:
        where = "not found" if n == 0 else f"found {n} times"
        return f"no longer applies: the original text is {where} in {m.file}"
    path.write_text(text.replace(m.original, m.replacement), encoding="utf-8")
    return None


def _failed_tests(output: str) -> list[str]:
    return sorted(set(re.findall(r"^(?:FAILED|ERROR) (\S+)", output, flags=re.M)))


def run_one(m: Mutation, timeout_s: float, root: Path = ROOT) -> dict:
    """Apply ``m`` to a fresh copy of the tree, run its tests there, and say whether they caught it."""
    t0 = time.monotonic()
    rec = {"name": m.name, "file": m.file, "caught": False, "failed_tests": [], "error": None}
    with tempfile.TemporaryDirectory(prefix="selfview-mutation-") as tmp:
        tree = copy_tree(Path(tmp) / "tree", root)
        why = apply(m, tree)
        if why is not None:
            rec["error"] = why
        else:
            env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
            cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *m.tests]
            try:
                out = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=timeout_s)
            except subprocess.TimeoutExpired:
                rec["error"] = f"the tests did not finish within {timeout_s:g} s"
            else:
                text = out.stdout + out.stderr
                if out.returncode in _NOT_A_FAILURE:
                    tail = " | ".join(text.strip().splitlines()[-3:])
                    rec["error"] = f"pytest exit code {out.returncode} (no test failure): {tail}"
                else:
                    rec["caught"] = out.returncode != 0
                    rec["failed_tests"] = _failed_tests(text)
    rec["seconds"] = round(time.monotonic() - t0, 1)
    return rec


def main(argv=None, mutations: tuple[Mutation, ...] = MUTATIONS, root: Path = ROOT) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", action="append", metavar="NAME", help="run only this mutation (repeatable)")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds per mutation's test run (default 900)")
    args = ap.parse_args(argv)
    names = [m.name for m in mutations]
    if args.only:
        unknown = [n for n in args.only if n not in names]
        if unknown:
            ap.error(f"unknown mutation(s) {', '.join(unknown)}; known: {', '.join(names)}")
        chosen = [m for m in mutations if m.name in args.only]
    else:
        chosen = list(mutations)
    if args.list:
        print(json.dumps({"mutations": [{"name": m.name, "file": m.file, "tests": list(m.tests), "why": m.why}
                                        for m in chosen]}, indent=1))
        return 0
    results = []
    for m in chosen:
        print(f"mutation {m.name} ...", file=sys.stderr, flush=True)
        results.append(run_one(m, args.timeout, root))
    caught = sum(r["caught"] for r in results)
    print(json.dumps({"caught": caught, "total": len(results), "errors": sum(r["error"] is not None for r in results),
                      "mutations": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
