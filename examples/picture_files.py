"""Calibrate a picture file and track another, one call each, with their sigma and verdict.

    python examples/picture_files.py PARKED.png MOVED.png [--camera CAMERA.yaml] [--cell CELL.yaml]

PARKED.png shows the gripper parked on the plate, MOVED.png the fingertips after the camera may have moved
(on the simulated cell: ``selfview render --out parked.png`` and ``selfview render --out moved.png --disturb
cable``). The calibration is written to ``cal.yaml`` beside PARKED.png only when its verdict is go.
"""

import argparse
import sys
from pathlib import Path

import selfview

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("parked")
ap.add_argument("moved")
ap.add_argument("--camera", default=None, help="camera file from 'selfview intrinsics' (default: the cell's nominal)")
ap.add_argument("--cell", default=None, help="cell file (default: the reference cell)")
args = ap.parse_args()

try:
    cal = selfview.calibrate_picture(args.parked, cell=args.cell, camera=args.camera)
except selfview.CellError as exc:
    sys.exit(f"{args.parked}: {exc}")
print(f"calibration: {cal.verdict.upper()}: {cal.reason}")
tcp, sg = cal.C_H_G[:3, 3], cal.tcp_sigma_mm
print("  TCP in camera [mm]: " + "  ".join(f"{a} {v:+.3f} +- {s:.4f}" for a, v, s in zip("xyz", tcp, sg)))
for w in cal.warnings:
    print(f"  warning: {w}")
if not cal.go:
    sys.exit(1)
out = Path(args.parked).with_name("cal.yaml")
cal.save(out)
print(f"  saved to {out}")

moved = selfview.track(args.moved, out, method="auto", cell=args.cell)
print(f"tracking: {moved.decision} ({moved.reason})")
tcp = moved.C_H_G_orthonormal[:3, 3]
sig = moved.tcp_sigma_mm or [float("nan")] * 3
print("  TCP in camera [mm]: " + "  ".join(f"{a} {v:+.3f} +- {s:.4f}" for a, v, s in zip("xyz", tcp, sig)))
sys.exit(0 if moved.verdict == "go" else 6)
