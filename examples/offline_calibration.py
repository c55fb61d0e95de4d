"""Off-line calibration on the simulated cell, the way a lab script would do it on the real one.

    python examples/offline_calibration.py [calibration.yaml]

On a real cell replace ``CellSession.simulated(cell, seed=1)`` by
``CellSession.real(cell, robot="/dev/ttyS0", gripper="modbus-tcp://10.0.0.5:502?unit=1",
camera="v4l2:///dev/video0?input=1&std=pal")``.
"""

import sys

from selfview.procedures.runs import CellSession
from selfview.files.cell import default_cell_path, load_cell

out = sys.argv[1] if len(sys.argv) > 1 else "calibration.yaml"
cell = load_cell(default_cell_path())
with CellSession.simulated(cell, seed=1) as session:
    result = session.calibrate(out=out)  # park, grab, calibrate, save (atomically), depart

s = result.summary()
print(f"f = {s['f']:.2f} px, kappa = {s['kappa']:.3e} px^-2, residual {s['rms_px']:.3f} px on {s['discs_used']} discs")
print("TCP in the camera frame [mm]:", " ".join(f"{v:+.3f}" for v in result.calibration.C_H_G[:3, 3]))
print(f"saved to {out}")
