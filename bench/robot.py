"""Benchmark: the round trip of WHERE between the PUMA VAL-II driver and the simulator over a real pty.

Prints one JSON object: the median round trip with the simulator pacing its bytes at 9600 baud (8N1,
10 bits a byte), the time the reply's bytes alone need at that rate, their ratio (target < 1.1: the
driver adds little beyond the wire), and the median round trip without pacing. The round trip
includes the typed line's echo, compared before the CR that executes it. Also the time a motion's
checks cost at that rate (an instant motion on the simulator: POINT, WHERE, the motion's prompt, a
CR answered, a WHERE at the target), which the driver adds to every motion.

    python bench/robot.py [--n 30] [--baud 9600]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

from selfview.drivers.puma_val_serial import PumaVAL, ValDialect
from selfview.mocks.val_controller import ValController


def round_trips(pace_baud: int | None, n: int) -> tuple[list[float], int]:
    """``n`` WHERE round trips (s) and the bytes of one reply."""
    sim = ValController(None, seed=0, time_scale=0.0, pace_baud=pace_baud)
    try:
        path = sim.start_pty()
        with PumaVAL(path, timeout_s=5.0) as robot:
            robot.where()  # warm up
            times = []
            for _ in range(n):
                t0 = time.perf_counter()
                robot.where()
                times.append(time.perf_counter() - t0)
            return times, robot.last_rx_bytes
    finally:
        sim.stop()


def motion_overhead(pace_baud: int, n: int) -> list[float]:
    """``n`` instant motions (time_scale 0) between two taught locations, each with its checks (s)."""
    sim = ValController(None, seed=0, time_scale=0.0, pace_baud=pace_baud, calibrated=True)
    try:
        path = sim.start_pty()
        with PumaVAL(path, timeout_s=5.0) as robot:
            robot.speed(50)
            times = []
            for k in range(n):
                t0 = time.perf_counter()
                robot.move(("above", "plate")[k % 2])
                times.append(time.perf_counter() - t0)
            return times
    finally:
        sim.stop()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=30, help="round trips per setting (default 30)")
    ap.add_argument("--baud", type=int, default=9600)
    args = ap.parse_args(argv)
    paced, nbytes = round_trips(args.baud, args.n)
    free, _ = round_trips(None, args.n)
    moves = motion_overhead(args.baud, max(3, args.n // 3))
    wire_s = nbytes * 10.0 / args.baud
    med = statistics.median(paced)
    print(
        json.dumps(
            {
                "benchmark": "robot WHERE round trip over a pty",
                "n": args.n,
                "baud": args.baud,
                "reply_bytes": nbytes,
                "wire_time_s": round(wire_s, 5),
                "paced_median_s": round(med, 5),
                "paced_max_s": round(max(paced), 5),
                "ratio_to_wire": round(med / wire_s, 4),
                "target_ratio": 1.1,
                "unpaced_median_s": round(statistics.median(free), 5),
                "unpaced_max_s": round(max(free), 5),
                "prompt_silence_s": ValDialect().prompt_silence_s,
                "paced_checked_motion_median_s": round(statistics.median(moves), 4),
                "paced_checked_motion_max_s": round(max(moves), 4),
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
