"""The paper's Tables 1 and 2 by its protocol, straight on simulated worlds (one world per trial).

Claims of the on-line calibration: measured as the paper measures it (against the off-line method run on
the second picture), 4P-U's mean TCP error is at most the paper's on every axis (Table 1: 0.02 / 0.00 / 0.04;
Table 2: 0.02 / 0.01 / 0.21 mm, 0.00 read as 0.01); against the simulator's truth, 4P-I's mean error is under
0.03 mm on every axis. The closing note reports the same over 40 trials per series (``selfview report``).
"""

import numpy as np
import pytest

from selfview.procedures.experiment import run_direct
from selfview.procedures.paper import PAPER_TABLES


@pytest.mark.slow
def test_tables_by_the_papers_protocol(cell):
    records, summary = run_direct(cell, trials=12, seed=500)
    assert len(summary["failures"]) <= 2, summary["failures"]
    for series in ("cable", "tilt"):
        ser = summary[series]
        paper_mean = np.maximum(PAPER_TABLES[series]["4P-U"][0], 0.01)
        ours = np.asarray(ser["methods"]["4P-U"]["reference"]["mean_mm"])
        assert np.all(ours <= paper_mean), (series, ours, paper_mean)
        truth = np.asarray(ser["methods"]["4P-I"]["truth"]["mean_mm"])
        assert np.all(truth < 0.03), (series, truth)
        assert ser["methods"]["4P-U"]["n"] >= 10
        # the disturbance is the paper's: about 1.5 mm along C x (cable), 4.5 mm along C y (tilt)
        shift = ser["tcp_shift_mm"]["mean"]
        assert shift == pytest.approx(1.5 if series == "cable" else 4.5, rel=0.2)
