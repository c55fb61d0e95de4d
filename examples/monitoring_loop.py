"""A monitoring loop: calibrate, then keep C_H_G true frame by frame while the camera creeps on its mount.

    python examples/monitoring_loop.py [frames]

Each frame the fingertips are found where the current C_H_G predicts them; the policy of the cell's
``monitor`` limits updates C_H_G (4P-U), recalibrates (4P-R / 5P-R) or raises the alarm, which stops
the robot. In simulation the camera is turned 0.3 degrees per frame about the cable axis.
"""

import sys
import tempfile
from pathlib import Path

from selfview.procedures.runs import CellSession
from selfview.files.cell import default_cell_path, load_cell
from selfview.errors import AlarmError

frames = int(sys.argv[1]) if len(sys.argv) > 1 else 8
cell = load_cell(default_cell_path())
cal_file = Path(tempfile.mkdtemp()) / "calibration.yaml"
cable = cell.simulation.disturbances["cable"]

with CellSession.simulated(cell, seed=2) as session:
    session.calibrate(out=cal_file)
    world = session.sim.world

    def creep(k):  # simulation only: the camera turns a little on its mount before each frame
        world.disturb_by_angle(cable.axis_C, 0.3, cable.pivot_C, series="creep")

    def show(rec):
        print(f"frame {rec['frame']}: {rec['action']} - {rec['reason']}")

    try:
        session.monitor(cal_file, frames=frames, disturb=creep, on_decision=show)
    except AlarmError as exc:
        print(f"alarm, robot stopped: {exc}")
