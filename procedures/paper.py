"""The paper's published figures (section 5, Tables 1 and 2), for side-by-side reports.

Mean and max TCP position error per camera axis (c_x, c_y, c_z) in mm over 20 measurements, the on-line
methods measured against the off-line method run on the second picture.
"""

from __future__ import annotations

PAPER_SERIES = {
    "cable": "Table 1: TCP c_x-displacement 1.5 mm (cable drawn to the right)",
    "tilt": "Table 2: TCP c_y-displacement 4.5 mm (attachment loosened, tilt changed)",
}

# method -> (mean c_x, c_y, c_z), (max c_x, c_y, c_z)
PAPER_TABLES: dict[str, dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]]] = {
    "cable": {
        "3P-U": ((0.23, 0.08, 0.38), (0.29, 0.09, 0.54)),
        "4P-U": ((0.02, 0.00, 0.04), (0.03, 0.01, 0.07)),
        "5P-U": ((0.02, 0.01, 0.05), (0.04, 0.02, 0.09)),
        "4P-R": ((0.07, 0.01, 0.15), (0.10, 0.01, 0.29)),
        "5P-R": ((0.07, 0.01, 0.17), (0.09, 0.02, 0.29)),
    },
    "tilt": {
        "3P-U": ((0.22, 0.08, 0.54), (0.26, 0.09, 0.64)),
        "4P-U": ((0.02, 0.01, 0.21), (0.03, 0.02, 0.27)),
        "5P-U": ((0.02, 0.01, 0.24), (0.04, 0.02, 0.31)),
        "4P-R": ((0.09, 0.02, 0.07), (0.13, 0.03, 0.13)),
        "5P-R": ((0.09, 0.02, 0.09), (0.10, 0.03, 0.17)),
    },
}
