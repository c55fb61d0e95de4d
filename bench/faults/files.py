"""Hostile calibration and cell files through the loaders (a worker process with a memory limit), and the
clean fixtures the campaigns corrupt."""

from __future__ import annotations

import json
import math
import select
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from selfview.bench.faults.common import Tally, _draw, _in_threads, _limit_child


# --- hostile files through the loaders ------------------------------------------------------------------
#: the loader worker: reads "loader<TAB>path" lines, answers one JSON line each
_WORKER = r'''
import dataclasses, json, sys
import numpy as np
from selfview.files.calfile import load_calibration
from selfview.files.cell import load_cell
from selfview.errors import CellError

def fp(x, budget):
    budget[0] -= 1
    if budget[0] < 0:
        raise OverflowError("more than 100000 values")
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: fp(getattr(x, f.name), budget) for f in dataclasses.fields(x)
                if f.name not in ("source", "sha256", "created", "software")}
    if isinstance(x, dict):
        return {str(k): fp(v, budget) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [fp(v, budget) for v in x]
    if isinstance(x, np.ndarray):
        return fp(x.tolist(), budget)
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, float, np.integer, np.floating)):
        try:
            return repr(float(x))
        except OverflowError:
            return "int:" + str(len(str(int(x)))) + " digits"
    return repr(x) if not isinstance(x, str) else x

for line in sys.stdin:
    loader, path = line.rstrip("\n").split("\t", 1)
    try:
        obj = (load_calibration if loader == "calfile" else load_cell)(path)
        try:
            out = {"status": "ok", "fp": json.dumps(fp(obj, [100000]), sort_keys=True)}
        except OverflowError:
            out = {"status": "ok", "fp": "<a document of more than 100000 values>"}
    except CellError as exc:
        out = {"status": "error", "type": type(exc).__name__, "msg": str(exc)[:300], "clear": bool(str(exc).strip())}
    except BaseException as exc:
        out = {"status": "traceback", "type": type(exc).__name__, "msg": str(exc)[:300]}
    sys.stdout.write(json.dumps(out) + "\n")
    sys.stdout.flush()
'''


class LoaderWorker:
    """A child process running the public loaders on files, with a memory limit and a timeout per file
    (a hang is killed and the worker restarted)."""

    def __init__(self, timeout_s: float = 3.0):
        self.timeout_s = timeout_s
        self.proc = None

    def _start(self):
        self.proc = subprocess.Popen([sys.executable, "-c", _WORKER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True, bufsize=1, preexec_fn=_limit_child)

    def load(self, loader: str, path: str, timeout_s: float | None = None) -> dict:
        if self.proc is None or self.proc.poll() is not None:
            self._start()
            first = True
        else:
            first = False
        self.proc.stdin.write(f"{loader}\t{path}\n")
        self.proc.stdin.flush()
        wait = (timeout_s or self.timeout_s) + (20.0 if first else 0.0)  # the first answer includes the imports
        r, _, _ = select.select([self.proc.stdout], [], [], wait)
        line = self.proc.stdout.readline() if r else ""
        if not line:
            died = self.proc.poll()
            self.close()
            if died is not None and died < 0:
                return {"status": "traceback", "type": f"killed by signal {-died}", "msg": "the loader's process died"}
            return {"status": "hang", "msg": f"no answer within {wait:g} s"}
        return json.loads(line)

    def close(self):
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.kill()
            self.proc.wait()
            try:
                self.proc.stdin.close()
                self.proc.stdout.close()
            except OSError:
                pass
            self.proc = None


FILE_FAULTS = ("truncated", "garbled", "bitflip", "non_utf8", "empty", "binary", "alias_bomb", "deep_nesting",
               "huge_number", "nan", "wrong_type", "wrong_checksum", "digit_change")
CELL_FAULTS = tuple(f for f in FILE_FAULTS if f != "wrong_checksum")  # a cell file has no checksum
#: faults that hang today's loaders for the whole per-file timeout are drawn less often (they cost seconds)
FILE_WEIGHTS = {"alias_bomb": 0.1, "deep_nesting": 0.15}
INVISIBLE = {
    "calfile": "a plausible number changed and the checksum recomputed: nothing tells it from a real calibration",
    "cellfile": "a cell file has no checksum: a plausible number changed (a digit, a bit) is taken as written",
    "cellfile.text": "a cell file has no checksum: a free-text field (the camera's model name) changed is taken as "
                     "written; nothing is computed with it",
    "calfile.residuals": "the residual figures (shown, never computed with) replaced by another well-typed table and "
                         "the checksum recomputed: the loader checks their types, not their history",
}


def _differs_only_in(a, b, leaf_ok) -> bool:
    """True if fingerprint ``b`` has ``a``'s structure and every leaf that differs passes ``leaf_ok(x, y)``."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_differs_only_in(a[k], b[k], leaf_ok) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_differs_only_in(x, y, leaf_ok) for x, y in zip(a, b))
    return a == b or leaf_ok(a, b)


def _as_number(v) -> float | None:
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def _plausible_number(a, b) -> bool:
    x, y = _as_number(a), _as_number(b)
    if x is None or y is None or not (math.isfinite(x) and math.isfinite(y)) or x * y < 0:
        return False
    return x == 0 == y or (x != 0 and y != 0 and 0.1 <= y / x <= 10)


def _plausible_change(a, b) -> bool:
    """True if fingerprint ``b`` differs from ``a`` only in finite numbers within a factor 10 of the
    truth, of the same sign (what no range check can tell from a real value)."""
    return _differs_only_in(a, b, _plausible_number)


def _text_change_only(a, b) -> bool:
    """True if fingerprint ``b`` differs from ``a`` only in leaves that are text, not numbers, on both sides."""
    return _differs_only_in(a, b, lambda x, y: isinstance(x, str) and isinstance(y, str)
                            and _as_number(x) is None and _as_number(y) is None)


def _leaves(doc, path=()):
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _leaves(v, path + (k,))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from _leaves(v, path + (i,))
    else:
        yield path, doc


def _set(doc, path, value):
    for k in path[:-1]:
        doc = doc[k]
    doc[path[-1]] = value


def _alias_bomb(levels: int) -> str:
    parts = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, levels):
        parts.append(f"a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 9) + "]")
    return "{" + ", ".join(parts) + "}"


class FileFaults:
    """Hostile variants of a clean calibration file and of the clean cell file."""

    def __init__(self, cal_text: str, cell_text: str):
        import yaml

        self.clean = {"calfile": cal_text, "cellfile": cell_text}
        self.docs = {k: yaml.safe_load(v) for k, v in self.clean.items()}

    def make(self, what: str, fault: str, rng) -> bytes | None:
        """The bytes of one hostile file (None: this fault does not apply to this file)."""
        import copy

        import yaml

        from selfview.files.calfile import doc_checksum

        text = self.clean[what]
        raw = text.encode()
        signed = what == "calfile"

        def dump(doc):
            if signed:
                doc["checksum"] = doc_checksum({k: v for k, v in doc.items() if k != "checksum"})
            return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120).encode()

        def top_key_line():
            keys = [i for i, ln in enumerate(text.splitlines()) if ln and not ln[0].isspace() and not ln.startswith("#") and ":" in ln]
            return int(rng.choice(keys))

        if fault == "truncated":
            return raw[: int(rng.integers(0, len(raw)))]
        if fault == "garbled":
            b = bytearray(raw)
            for _ in range(int(rng.integers(1, 4))):
                b[int(rng.integers(len(b)))] = int(rng.integers(0x20, 0x7F))
            return bytes(b)
        if fault == "bitflip":
            b = bytearray(raw)
            b[int(rng.integers(len(b)))] ^= 1 << int(rng.integers(8))
            return bytes(b)
        if fault == "non_utf8":
            i = int(rng.integers(len(raw)))
            return raw[:i] + bytes([0xFF, 0xFE, 0x80 | int(rng.integers(0x80))]) + raw[i:]
        if fault == "empty":
            return b"" if rng.random() < 0.5 else b"   \n# nothing\n"
        if fault == "binary":
            return rng.integers(0, 256, int(rng.integers(16, 2048))).astype(np.uint8).tobytes()
        if fault in ("alias_bomb", "deep_nesting"):
            lines = text.splitlines()
            i = top_key_line()
            key = lines[i].split(":", 1)[0]
            j = i + 1
            while j < len(lines) and (not lines[j] or lines[j][0].isspace() or lines[j].startswith("#")):
                j += 1
            if fault == "alias_bomb":
                value = _alias_bomb(int(rng.integers(6, 10)))
            else:
                n = int(rng.choice([200, 2000, 20000, 100000]))
                value = "[" * n + "]" * n if rng.random() < 0.5 else "{a: " * n + "1" + "}" * n
            return "\n".join(lines[:i] + [f"{key}: {value}"] + lines[j:]).encode() + b"\n"
        doc = copy.deepcopy(self.docs[what])
        leaves = [(p, v) for p, v in _leaves(doc) if p[-1] != "checksum"]
        numeric = [(p, v) for p, v in leaves if isinstance(v, (int, float)) and not isinstance(v, bool)]
        if fault == "huge_number":
            p, _ = numeric[int(rng.integers(len(numeric)))]
            _set(doc, p, [10 ** int(rng.integers(20, 400)), -(10 ** 309), 1e308 * 10, 2 ** 64][int(rng.integers(4))])
            return dump(doc)
        if fault == "nan":
            p, _ = numeric[int(rng.integers(len(numeric)))]
            _set(doc, p, [float("nan"), float("inf"), float("-inf")][int(rng.integers(3))])
            return dump(doc)
        if fault == "wrong_type":
            p, _ = leaves[int(rng.integers(len(leaves)))]
            if rng.random() < 0.3 and len(p) > 1:
                p = p[:-1]  # a whole section or list replaced
            _set(doc, p, ["a string", [1, 2, 3], {"x": 1}, None, True, [], {}][int(rng.integers(7))])
            return dump(doc)
        if fault == "wrong_checksum":
            if not signed:
                return None
            c = doc["checksum"]
            i = len("sha256:") + int(rng.integers(64))
            doc["checksum"] = c[:i] + ("0" if c[i] != "0" else "1") + c[i + 1:]
            return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120).encode()
        if fault == "digit_change":
            cands = [(p, v) for p, v in numeric if isinstance(v, float) and v != 0]
            p, v = cands[int(rng.integers(len(cands)))]
            _set(doc, p, float(v) * float(rng.choice([1.001, 0.999, 1.01, 0.99, 1.1, 0.9])))
            return dump(doc)
        raise ValueError(fault)

def file_outcome(res: dict, clean_fp: str, kind: str) -> tuple[str, str, str | None]:
    """(outcome, what was seen, invisible reason) of one loader result."""
    st = res["status"]
    if st == "hang":
        return "hang", res.get("msg", ""), None
    if st == "traceback":
        return "traceback", f"{res.get('type')}: {res.get('msg', '')}", None
    if st == "error":
        return ("clear_error", "", None) if res.get("clear") else ("traceback", f"{res['type']} with no message", None)
    if res["fp"] == clean_fp:
        return "no_effect", "", None
    try:
        clean, got = json.loads(clean_fp), json.loads(res["fp"])
        plausible = _plausible_change(clean, got)
    except ValueError:
        clean = got = None
        plausible = False
    why = INVISIBLE[kind.split(".")[0]] if plausible else None
    if (why is None and kind.split(".")[0] == "calfile" and isinstance(clean, dict) and isinstance(got, dict)
            and clean.keys() == got.keys() and all(clean[k] == got[k] for k in clean if k != "residuals")):
        why = INVISIBLE["calfile.residuals"]
    if why is None and kind.split(".")[0] == "cellfile" and clean is not None and _text_change_only(clean, got):
        why = INVISIBLE["cellfile.text"]
    return "wrong_value", f"loaded a content that differs from the file's truth ({res['fp'][:160]}...)", why


def run_files(n: int, seed: int, deadline: float, tally: Tally, fixtures: dict, workers: int = 2) -> None:
    ff = FileFaults(fixtures["cal_text"], fixtures["cell_text"])
    clean_fp = {}
    w = LoaderWorker()
    try:
        for what, path in (("calfile", fixtures["cal"]), ("cellfile", fixtures["cell"])):
            res = w.load(what, str(path))
            if res["status"] != "ok":
                raise RuntimeError(f"the clean {what} does not load: {res}")
            clean_fp[what] = res["fp"]
    finally:
        w.close()
    fixtures["clean_fp"] = clean_fp

    def worker(share, seed_, index, deadline_, tally_):
        rng = np.random.default_rng([seed, 3, index])
        lw = LoaderWorker()
        d = Path(fixtures["dir"]) / f"files{index}"
        d.mkdir(exist_ok=True)
        try:
            done = 0
            while done < share and time.monotonic() < deadline:
                what = str(rng.choice(["calfile", "cellfile"]))
                fault = _draw(FILE_FAULTS if what == "calfile" else CELL_FAULTS, FILE_WEIGHTS, rng)
                blob = ff.make(what, fault, rng)
                if blob is None:
                    continue
                path = d / f"{what}.yaml"
                path.write_bytes(blob)
                res = lw.load(what, str(path))
                kind = f"{what}.{fault}"
                outcome, seen, why = file_outcome(res, clean_fp[what], kind)
                tally.add(kind, outcome, f"{len(blob)}-byte file: {seen}", invisible=why)
                done += 1
        finally:
            lw.close()

    _in_threads(worker, n, seed, deadline, tally, workers)


# --- fixtures: a parked picture, its calibration, the cell --------------------------------------------
def make_fixtures(folder: Path, seed: int) -> dict:
    """The clean files the campaign corrupts: a rendered picture of the gripper parked on the plate, the
    calibration ``selfview calibrate`` makes from it, the reference cell file."""
    import cv2

    from selfview.files.calfile import save_calibration
    from selfview.files.cell import default_cell_path, load_cell
    from selfview.mocks.render import render
    from selfview.mocks.world import SimWorld
    from selfview.estimation.offline import calibrate_offline

    cell_path = default_cell_path()
    cell = load_cell(cell_path)
    w = SimWorld(cell, seed=seed)
    w.park()
    img = render(w, seed=seed).image
    png = folder / "parked.png"
    cv2.imwrite(str(png), img)
    res = calibrate_offline(img, cell)
    cal = folder / "cal.yaml"
    save_calibration(res.calibration, cal)
    return {"dir": str(folder), "picture": str(png), "image": img, "cal": str(cal), "cal_text": cal.read_text(),
            "cell": str(cell_path), "cell_text": Path(cell_path).read_text()}


