"""``bench/discs_vs_opencv.py --floor``: where the disc detector's time goes, with stages made free in turn."""

import numpy as np

from selfview.bench.discs_vs_opencv import FREE_STAGES, floor_study, pictures
from selfview.measurement import discs


def test_the_floor_study_times_every_variant_and_leaves_the_detector_whole():
    """Each variant and findCirclesGrid timed on every picture; afterwards the detector measures again (its
    stages put back, also when a run fails): sub-pixel centres, not the free stages' box centres."""
    before = {name: getattr(discs, name) for v in FREE_STAGES.values() for name in v}
    out = floor_study(1, quick=True)
    assert out["pictures"] == len(list(pictures(True)))
    assert set(out["median_ms"]) == {*FREE_STAGES, "findCirclesGrid"}
    assert all(v > 0 for v in out["median_ms"].values())
    assert set(out["median_time_ratio_to_findCirclesGrid"]) == set(FREE_STAGES)
    assert {name: getattr(discs, name) for name in before} == before
    _, img, plate, _ = next(pictures(True))
    uv = discs.detect_discs(img, plate).uv
    assert np.abs(uv * 2 - np.rint(uv * 2)).max() > 0.01  # box centres are whole or half pixels
