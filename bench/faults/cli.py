"""Hostile files and pictures through ``selfview track`` and ``selfview calibrate --image``."""

from __future__ import annotations

import shutil
import struct
import time
import zlib
from pathlib import Path

import numpy as np

from selfview.bench.faults.common import Tally, _cli_outcome, _draw, _file_state, _in_threads, _selfview
from selfview.bench.faults.files import CELL_FAULTS, FILE_FAULTS, FILE_WEIGHTS, FileFaults, LoaderWorker, file_outcome


# --- hostile pictures ---------------------------------------------------------------------------------
def _png(width: int, height: int, idat: bytes, depth: int = 8, colour: int = 0) -> bytes:
    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def _bomb_png(side: int) -> bytes:
    """A grey PNG of side x side black pixels: a few hundred kB that decode to side^2 bytes."""
    z = zlib.compressobj(9)
    row = b"\x00" * (side + 1)
    parts = [z.compress(row) for _ in range(side)]
    return _png(side, side, b"".join(parts) + z.flush())


PICTURE_FAULTS = ("zero_bytes", "garbage", "truncated_png", "huge_declared", "bomb", "wrong_size", "blank",
                  "noise", "deep_16bit", "text")


def make_picture(fault: str, fixtures: dict, rng) -> bytes:
    import cv2

    if fault == "zero_bytes":
        return b""
    if fault == "garbage":
        return rng.integers(0, 256, int(rng.integers(100, 50000))).astype(np.uint8).tobytes()
    if fault == "truncated_png":
        blob = Path(fixtures["picture"]).read_bytes()
        return blob[: int(rng.integers(8, len(blob)))]
    if fault == "huge_declared":
        side = int(rng.choice([40000, 65535, 100000]))
        return _png(side, side, zlib.compress(b"\x00" * 1000))
    if fault == "bomb":
        if "bomb" not in fixtures:
            fixtures["bomb"] = _bomb_png(20000)
        return fixtures["bomb"]
    if fault == "wrong_size":
        w, h = [(640, 480), (384, 288), (1536, 1152), (768, 575)][int(rng.integers(4))]
        return cv2.imencode(".png", cv2.resize(fixtures["image"], (w, h)))[1].tobytes()
    if fault == "blank":
        return cv2.imencode(".png", np.full((576, 768), int(rng.integers(0, 256)), np.uint8))[1].tobytes()
    if fault == "noise":
        return cv2.imencode(".png", rng.integers(0, 256, (576, 768)).astype(np.uint8))[1].tobytes()
    if fault == "deep_16bit":
        return cv2.imencode(".png", fixtures["image"].astype(np.uint16) * 257)[1].tobytes()
    if fault == "text":
        return b"this is not a picture\n" * int(rng.integers(1, 100))
    raise ValueError(fault)

def cli_case(kind: str, fault: str, fixtures: dict, rng, tally: Tally, workdir: Path, loader: LoaderWorker) -> None:
    """One hostile file or picture through the CLI."""
    workdir.mkdir(parents=True, exist_ok=True)
    guard = workdir / "cal.yaml"  # a good calibration file that a failing command must leave as it was
    shutil.copyfile(fixtures["cal"], guard)
    expect_same, why = None, None
    if kind == "picture":
        bad = workdir / "bad.png"
        bad.write_bytes(make_picture(fault, fixtures, rng))
        if rng.random() < 0.5:
            argv = ["calibrate", "--image", str(bad), "--out", str(guard), "--json"]
        else:
            argv = ["track", "--calibration", str(guard), "--image", str(bad), "--apply", "--json"]
        expect_same = False
    else:
        what = "calfile" if kind == "calfile" else "cellfile"
        blob = FileFaults(fixtures["cal_text"], fixtures["cell_text"]).make(what, fault, rng)
        if blob is None:
            return
        bad = workdir / f"bad-{what}.yaml"
        bad.write_bytes(blob)
        res = loader.load(what, str(bad))
        expect_same = res["status"] == "ok" and res["fp"] == fixtures["clean_fp"][what]
        why = file_outcome(res, fixtures["clean_fp"][what], what)[2] if res["status"] == "ok" else None
        if what == "calfile":
            argv = ["track", "--calibration", str(bad), "--image", fixtures["picture"], "--json"]
        else:
            argv = ["calibrate", "--cell", str(bad), "--image", fixtures["picture"], "--out", str(guard), "--json"]
    before = _file_state(guard)
    code, err = _selfview(argv, workdir)
    after = _file_state(guard)
    k = f"cli.{kind}.{fault}"
    what = f"selfview {argv[0]} ({bad.stat().st_size} bytes)"
    bad_exit, seen = _cli_outcome(code, err)
    if bad_exit:
        outcome, seen = bad_exit, f"{what}: {seen}"
    elif code != 0 and after != before:
        outcome, seen = "lost_file", f"{what}: exit {code} and the calibration file changed or a temp file was left"
    elif code != 0:
        msg = err.strip().splitlines()[0] if err.strip() else ""
        outcome, seen = ("clear_error", "") if msg and code in (2, 3, 4, 5) else ("traceback", f"{what}: exit {code}, stderr {err[-200:]!r}")
    elif expect_same:
        outcome = "no_effect"
    else:
        outcome, seen = "wrong_value", f"{what}: exit 0 on a hostile {'picture' if kind == 'picture' else 'file'} ({fault})"
    tally.add(k, outcome, seen, invisible=why if outcome == "wrong_value" else None)


def run_cli(n: int, seed: int, deadline: float, tally: Tally, fixtures: dict, workers: int = 2) -> None:
    def worker(share, seed_, index, deadline_, tally_):
        rng = np.random.default_rng([seed, 4, index])
        lw = LoaderWorker()
        try:
            for i in range(share):
                if time.monotonic() >= deadline:
                    break
                r = rng.random()
                if r < 0.5:
                    kind, fault = "picture", PICTURE_FAULTS[(index + 2 * i) % len(PICTURE_FAULTS)]
                else:
                    kind = "calfile" if r < 0.75 else "cellfile"
                    fault = _draw(FILE_FAULTS if kind == "calfile" else CELL_FAULTS, FILE_WEIGHTS, rng)
                cli_case(kind, fault, fixtures, rng, tally, Path(fixtures["dir"]) / f"cli{index}", lw)
        finally:
            lw.close()

    _in_threads(worker, n, seed, deadline, tally, workers)


