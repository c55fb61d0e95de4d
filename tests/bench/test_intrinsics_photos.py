"""bench/intrinsics.py's study of real photographs: ours beside findCirclesGrid and cv2.calibrateCamera."""

from __future__ import annotations

from selfview.bench.intrinsics import photo_study


def test_photo_study_finds_every_disc_and_agrees_with_opencv():
    out = photo_study()
    res = out["visp-circles"]
    assert res["none_refused"] and res["every_opencv_disc_found"]
    assert len(res["pictures"]) == 9 and all(r["ours"] == r["opencv"] == 36 for r in res["pictures"])
    assert all(r["centre_agreement_px"]["max"] < 0.5 for r in res["pictures"])
    cams = {tuple(c["size"]): c for c in res["cameras"]}
    assert set(cams) == {(320, 240), (640, 480)}
    for size, n in (((320, 240), 5), ((640, 480), 4)):
        cam = cams[size]
        assert cam["pictures"] == n
        assert cam["cv2_on_findCirclesGrid"]["discs"] == cam["cv2_on_our_discs"]["discs"] == 36 * n
        # every picture's discs reach the fit; the plate model may leave out a view it cannot tie to the
        # printed dot pattern, and says so
        assert cam["selfview_flat_plate"]["discs"] == 36 * n
        assert cam["selfview"]["discs"] + 36 * len(cam["selfview"]["views_left_out"]) == 36 * n
        assert cam["selfview"]["skew"] == 0.0
        for key in ("ours_minus_cv2_in_combined_sigmas", "flat_plate_minus_cv2_in_combined_sigmas"):
            assert all(abs(v) <= 3.0 for v in cam[key].values()), (size, key, cam[key])
        assert cam["within_3_sigmas"]
