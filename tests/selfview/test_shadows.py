"""Shadows on the plate (the fingers' own, a lamp's arm) and what the picture says about the plate's origin.

The renderer's ``Lamp`` casts the fingers' shadows; an occluder (a lamp's arm out of the picture) adds one
more. ``EDGE_LAMP`` puts the plate's outer column on the image's left in shadow (its top discs under the
arm's shadow edge, its bottom ones on the edge of finger A's shadow), while the column beyond the right
one lies outside the picture: were those discs dropped, nothing in the picture would say which seven of
the eight columns are seen. ``DEEP_LAMP`` hides that column in a deep shadow. Either the grid is indexed
right, or the result says that its origin is not known.
"""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from selfview.files.cell import load_cell
from selfview.measurement.discs import detect_discs
from selfview.errors import ConfigError, ImageError
from selfview.maths.geometry import pose_difference
from selfview.mocks.render import Lamp, render
from selfview.mocks.world import SimWorld
from selfview.estimation.offline import calibrate_offline
from selfview.mocks.render import disc_image_centroids
from selfview.procedures.cli import main
from tests.photo_variants import camera_turned, hazed, plate_tilted, shadowed, turn_matrix, turned

VISP = Path(__file__).resolve().parents[1] / "data" / "visp-circles"
PHOTOS = sorted(p.name for p in VISP.glob("*.*g"))

#: The lamp above the plate's +y side, and an arm whose shadow edge runs through the column at x = +31.5 mm
#: (the image's left column in this view).
EDGE_LAMP = Lamp(position_W=(36.0, 300.0, -150.0), occluders=(((31.0, 20.0, -12.0), (80.0, 90.0, -10.0)),))


def _world(cell):
    w = SimWorld(cell, seed=3)
    w.park()
    return w


def _true_rc(det, pic, plate):
    """The true (row, col) of each detected disc: the nearest true disc image to its centre."""
    d = np.linalg.norm(det.uv[:, None, :] - pic.disc_uv[None, :, :], axis=2)
    k = np.argmin(d, axis=1)
    assert np.all(d[np.arange(len(k)), k] < 1.0)
    return np.column_stack([k // plate.cols, k % plate.cols])


def _indexed_right(det, true_rc, plate) -> bool:
    """Whether the detected indices are the true ones up to a symmetry of the square grid (which W's
    orientation convention picks), with no shift."""
    n = plate.rows - 1
    r, c = true_rc[:, 0], true_rc[:, 1]
    for rr, cc in ((r, c), (c, n - r), (n - r, n - c), (n - c, r)):
        for a, b in ((rr, cc), (rr, n - cc), (n - rr, cc), (cc, rr)):
            if np.array_equal(det.rc, np.column_stack([a, b])):
                return True
    return False


def test_the_lamp_darkens_the_shadowed_paper_only(cell):
    w = _world(cell)
    plain = render(w, seed=1, noise=False)
    lit = render(w, seed=1, noise=False, lamp=EDGE_LAMP)
    ratio = lit.image.astype(float) / np.maximum(plain.image.astype(float), 1.0)
    paper = plain.image > 180
    # in full shadow the paper keeps the ambient share, in the light all of it; the fingers are untouched
    assert np.percentile(ratio[paper], 1) == pytest.approx(EDGE_LAMP.ambient, abs=0.03)
    assert np.median(ratio[paper]) == pytest.approx(1.0, abs=0.01)
    shadowed = paper & (ratio < 0.6)
    assert 0.02 < shadowed.mean() < 0.3
    assert lit.truth["render"]["lamp"]["ambient"] == EDGE_LAMP.ambient
    with pytest.raises(ConfigError, match="position_W"):
        render(w, lamp=Lamp(position_W=(0.0, 0.0, 100.0)))
    with pytest.raises(ConfigError, match="occluder"):
        render(w, lamp=Lamp(occluders=(((0, 0, 0), (0, 1, 1)),)))


def test_without_shadows_the_same_view_pins_the_origin(cell):
    w = _world(cell)
    pic = render(w, seed=1)
    det = detect_discs(pic.image, cell.plate, camera=cell.camera.guess())
    assert det.origin_pinned and det.ambiguous == {}
    assert _indexed_right(det, _true_rc(det, pic, cell.plate), cell.plate)


def test_an_edge_column_in_shadow_is_indexed_right_or_named_ambiguous(cell):
    w = _world(cell)
    pic = render(w, seed=1, lamp=EDGE_LAMP)
    det = detect_discs(pic.image, cell.plate, camera=cell.camera.guess())
    right = _indexed_right(det, _true_rc(det, pic, cell.plate), cell.plate)
    assert right or not det.origin_pinned
    if not det.origin_pinned:
        assert set(det.ambiguous) == {"cols"}
        assert "0-6 up to 1-7" in det.ambiguous["cols"]


#: A lamp's arm in a deep shadow (5 % light) over the image's left column and all beyond it: its discs are
#: hardly seen, and the plate's end on the other side lies beyond the picture.
DEEP_LAMP = Lamp(position_W=(27.0, 0.0, -400.0), ambient=0.05, occluders=(((27.0, -80.0, -12.0), (90.0, 80.0, -10.0)),))
#: The same at 10 % light: the column is measured, but finger B's outer corner, in the shadow's edge, is not.
DIM_LAMP = Lamp(position_W=(26.0, 0.0, -400.0), ambient=0.1, occluders=(((26.0, -80.0, -12.0), (90.0, 80.0, -10.0)),))


def test_an_edge_column_in_shadow_gives_the_right_plate_pose(cell):
    """The edge column's discs on the shadow's edge are measured: the origin is pinned, and right."""
    w = _world(cell)
    res = calibrate_offline(render(w, seed=1, lamp=EDGE_LAMP).image, cell)
    assert res.discs.origin_pinned and res.summary()["C_H_W_known"] is True
    # the grid's centre is W's origin whatever the grid's turn: a pinned origin is the true one
    assert np.linalg.norm(res.calibration.C_H_W[:3, 3] - w.C_H_W[:3, 3]) < 0.05
    rot, dist = pose_difference(res.calibration.C_H_G, w.C_H_G)
    assert dist < 0.1 and rot < 0.1


def test_calibration_says_when_the_plate_pose_is_not_known(cell, tmp_path, capsys):
    """The edge column lost in a deep shadow: the plate pose is one pitch off, and the result says that it
    is not known (summary, residuals, the command line's warning); C_H_G holds, as it does not depend on it."""
    w = _world(cell)
    pic = render(w, seed=1, lamp=DEEP_LAMP)
    res = calibrate_offline(pic.image, cell)
    s = res.summary()
    rot, dist = pose_difference(res.calibration.C_H_G, w.C_H_G)
    assert dist < 0.1 and rot < 0.1
    assert np.linalg.norm(res.calibration.C_H_W[:3, 3] - w.C_H_W[:3, 3]) == pytest.approx(cell.plate.pitch, abs=0.1)
    assert s["C_H_W_known"] is False
    assert res.calibration.residuals["plate_origin"] == "ambiguous"
    assert any("C_H_W is not known" in m and "0-6 up to 1-7" in m for m in s["warnings"])
    path = tmp_path / "shadow.png"
    cv2.imwrite(str(path), pic.image)
    code = main(["calibrate", "--image", str(path), "--out", str(tmp_path / "cal.yaml"), "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "warning: the plate's origin is not pinned" in err
    doc = json.loads(out)
    assert doc["C_H_W_known"] is False and doc["warnings"]


def test_a_fingertip_corner_lost_in_a_shadow_is_no_silent_result(cell):
    """A corner mismeasured in a shadow's edge bends the fingertip rectangle: the gripper is then off by
    tenths of a millimetre (measured 0.34 mm, 0.54 deg), and the PCC residual says so (measured 25 times the
    picture's noise); a picture whose corners hold gives no warning. A corner the search does not find in the
    shadow's edge, or finds off the fingers' shape (more than 3 px from where the others put it), is left out,
    the silhouette fit measures the corners (measured: then 0.056 mm off) and the corner left out is named:
    the issue's bar is 0.05 mm or a warning."""
    w = _world(cell)
    res = calibrate_offline(render(w, seed=1, lamp=DIM_LAMP).image, cell)
    rot, dist = pose_difference(res.calibration.C_H_G, w.C_H_G)
    assert dist < 0.05 or any("PCC residual" in m or "B-outer-front was left out of the corner search" in m
                              for m in res.warnings)


def test_a_pcc_residual_far_above_the_pictures_noise_is_a_warning(cell):
    """The fingertip rectangle taken from a cell whose fingers are 0.3 mm wider than the pictured ones
    leaves a PCC residual many times what the picture's noise gives: a warning, not a silent result; the
    same picture with the pictured fingers' points gives none."""
    import dataclasses

    w = _world(cell)
    img = render(w, seed=1).image
    good = calibrate_offline(img, cell, points="cell")
    assert good.warnings == [] and good.pcc.rms_mm < 2 * good.calibration.residuals["pcc_noise_mm"]
    wide = dataclasses.replace(cell, gripper=dataclasses.replace(cell.gripper, finger_width=cell.gripper.finger_width + 0.3))
    bad = calibrate_offline(img, wide, points="cell")
    assert bad.pcc.rms_mm > 0.1
    assert len(bad.warnings) == 1 and "PCC residual" in bad.warnings[0]
    assert bad.calibration.residuals["warnings"] == bad.warnings
    assert bad.summary()["warnings"] == bad.warnings


def _photo(name):
    img = cv2.imread(str(VISP / name), cv2.IMREAD_GRAYSCALE)
    assert img is not None, f"missing test picture {name}"
    return img, load_cell(VISP / ("cell-640x480.yaml" if name.endswith(".png") else "cell.yaml")).plate


def _opencv(img, plate):
    ok, c = cv2.findCirclesGrid(img, (plate.cols, plate.rows), flags=cv2.CALIB_CB_SYMMETRIC_GRID | cv2.CALIB_CB_CLUSTERING)
    return c.reshape(-1, 2).astype(float) if ok else None


def test_discs_across_a_shadows_edge_are_measured_at_their_centre(cell):
    """A lamp's shadow (45 % light, edge 3 or 8 px soft) across the rendered plate: the discs it crosses
    are kept and measured against the truth as well as lit ones (measured: at most 0.046 px; before, the
    ring's plane was taken as the paper and they were 0.35 px off, up to 1.2 px, or dropped)."""
    errs = []
    for seed in range(2):
        w = SimWorld(cell, seed=seed)
        w.park()
        img = render(w, seed=seed).image
        truth = disc_image_centroids(w.camera, w.C_H_W, cell.plate)
        for soft in (3.0, 8.0):
            det = detect_discs(shadowed(img, soft_px=soft), cell.plate)
            h, wd = img.shape
            edge = 0.42 * wd + 0.25 * (det.uv[:, 1] - h / 2)
            across = np.abs(det.uv[:, 0] - edge) < 30
            assert across.sum() >= 4
            errs.append(np.linalg.norm(det.uv[across, None] - truth[None], axis=2).min(axis=1))
    errs = np.concatenate(errs)
    assert np.max(errs) < 0.1, np.round(errs, 3)


@pytest.mark.parametrize("name", PHOTOS)
def test_a_shadow_across_a_real_photograph_keeps_its_discs(name):
    """ViSP's photographs with a lamp's shadow across the grid: every disc of a soft-edged shadow and of a
    sharp one (3 px) is kept (before: 323 of the nine pictures' 324, the one lost where the edge crosses a disc
    beside a printed mark in circles-01; earlier 266), their centres a median 0.03 px from OpenCV's. The
    shadow is drawn, so the truth is each disc's centre in the photograph without it: ours move by at most
    0.157 px (that disc beside the mark; the others 0.123 px), OpenCV's by up to 0.82 px, which is why its
    centres are no truth here."""
    img, plate = _photo(name)
    assert len(detect_discs(shadowed(img, soft_px=8.0), plate)) == plate.rows * plate.cols
    sharp = shadowed(img)
    det = detect_discs(sharp, plate)
    assert len(det) == plate.rows * plate.cols, det.rejected
    moved = np.linalg.norm(det.uv[:, None] - detect_discs(img, plate).uv[None], axis=2).min(axis=1)
    assert moved.max() < 0.2, np.round(moved, 3)
    ref = _opencv(sharp, plate)
    if ref is not None:
        d = np.linalg.norm(ref[:, None, :] - det.uv[None], axis=2).min(axis=1)
        both = d[d < 3.0]
        assert np.median(both) < 0.25


@pytest.mark.parametrize("name", PHOTOS)
def test_glare_over_a_real_photograph_keeps_its_discs(name):
    """ViSP's photographs under glare (100 grey levels on ink and paper, the light at a fifth: the discs' contrast
    0.25, under the 0.3 threshold; before, no disc was found; OpenCV finds the grid in 7): every disc, measured with
    the pedestal off and said so, each where it is in the photograph (measured: at most 0.25 px after 8-bit
    rounding of a fifth of the light, median at most 0.008 px). An unchanged photograph has no pedestal."""
    img, plate = _photo(name)
    assert detect_discs(img, plate).pedestal == 0.0
    det = detect_discs(hazed(img), plate)
    assert len(det) == plate.rows * plate.cols, det.rejected
    assert det.pedestal > 50
    moved = np.linalg.norm(det.uv[:, None] - detect_discs(img, plate).uv[None], axis=2).min(axis=1)
    assert moved.max() < 0.3 and np.median(moved) < 0.02, np.round(moved, 3)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_parked_picture_under_glare_calibrates_as_a_clear_one(cell, seed):
    """The parked cell under glare (100 grey levels over a fifth of the light): the off-line calibration finds the
    plate with the pedestal off and says so in its residuals, and ``C_H_G`` is the clear picture's (measured: within
    0.006 deg and 0.006 mm; before, "no calibration plate in the picture")."""
    w = SimWorld(cell, seed=seed)
    w.park()
    img = render(w, seed=seed).image
    clear, faint = calibrate_offline(img, cell), calibrate_offline(hazed(img), cell)
    assert clear.calibration.residuals["disc_pedestal_grey"] == 0.0
    assert faint.calibration.residuals["disc_pedestal_grey"] > 50 and not faint.warnings
    deg, mm = pose_difference(faint.calibration.C_H_G, clear.calibration.C_H_G)
    assert deg < 0.03 and mm < 0.03, (deg, mm)


@pytest.mark.parametrize("name", PHOTOS[::2])
@pytest.mark.parametrize("deg", [30, 55, 80])
def test_a_plate_turned_in_the_picture(name, deg):
    """The plate turned by any angle in the picture: every disc, each where the turn puts the photograph's
    (measured: at most 0.096 px over the nine photographs turned 15-80 deg; OpenCV's own move by up to 0.66 px),
    and a median 0.03 px from OpenCV's (one disc of uneven ink in circles-05 lies 0.38-0.40 px from it)."""
    img, plate = _photo(name)
    pic = turned(img, deg)
    det = detect_discs(pic, plate)
    assert len(det) == plate.rows * plate.cols and det.origin_pinned
    M, _ = turn_matrix(img.shape, deg)
    truth = detect_discs(img, plate).uv @ M[:, :2].T + M[:, 2]
    moved = np.linalg.norm(det.uv[:, None] - truth[None], axis=2).min(axis=1)
    assert moved.max() < 0.15, np.round(moved, 3)
    ref = _opencv(pic, plate)
    assert ref is not None
    d = np.linalg.norm(ref[:, None, :] - det.uv[None], axis=2).min(axis=1)
    assert np.max(d) < 0.5 and np.median(d) < 0.1


@pytest.mark.parametrize("name, axis", [("circles-02.jpg", "x"), ("grid36-01.png", "y"), ("grid36-04.png", "x")])
def test_a_plate_seen_60_deg_off_square_on(name, axis):
    """ViSP's photographs warped to a view of their plate from 60 deg off square-on (``plate_tilted``):
    the discs are indexed as in the photograph, up to a symmetry of the grid and with no shift, the origin
    pinned; at most the near column's two outer discs lost to the picture's border. Before, 17 of the 18
    (picture, axis) views were refused as 'a lattice of 11 x 6' (a diagonal taken as a step) or indexed
    wrong with the origin 'pinned' (grid36-01, 25-26 discs)."""
    img, plate = _photo(name)
    cell = load_cell(VISP / ("cell-640x480.yaml" if name.endswith(".png") else "cell.yaml"))
    full = detect_discs(img, plate)
    f = cell.camera.guess().f
    pic, H = plate_tilted(img, full.p_W, full.uv, f, axis, 60)
    h, w = pic.shape
    for cam in (None, cell.camera.guess().with_(kappa=0.0, cx=(w - 1) / 2, cy=(h - 1) / 2)):
        det = detect_discs(pic, plate, camera=cam)
        assert len(det) >= plate.rows * plate.cols - 5 and det.origin_pinned, (len(det), det.index_basis)
        truth = cv2.perspectiveTransform(full.uv.reshape(-1, 1, 2), H).reshape(-1, 2)
        d = np.linalg.norm(det.uv[:, None, :] - truth[None], axis=2)
        k = np.argmin(d, axis=1)
        assert d.min(axis=1).max() < 3.0  # the warp moves a disc's centroid off its centre's image by up to 1 px
        assert _indexed_right(det, full.rc[k], plate)


def _cut(img, det, side):
    """``img`` cut between the two outer lines of discs of ``det`` on ``side``, and the cut's offset (u, v)."""
    u, v = np.sort(det.uv[:, 0]), np.sort(det.uv[:, 1])
    n = int(np.sqrt(len(det)))
    if side == "left":
        x0 = int((u[n - 1] + u[n]) / 2)
        return img[:, x0:], (x0, 0)
    if side == "right":
        return img[:, : int((u[-n] + u[-n - 1]) / 2)], (0, 0)
    if side == "top":
        y0 = int((v[n - 1] + v[n]) / 2)
        return img[y0:], (0, y0)
    return img[: int((v[-n] + v[-n - 1]) / 2)], (0, 0)


@pytest.mark.parametrize("name", ["grid36-01.png", "grid36-03.png", "circles-02.jpg", "circles-05.jpg"])
def test_a_partial_grid_is_indexed_by_what_is_seen(name):
    """A photograph cut through the grid (its outer line of discs gone on one side): the indices are the
    whole picture's wherever blank paper beyond the last line on the other side shows where the grid ends
    (indexed by what is seen, not centred), and the cut axis is named ambiguous unless the picture pins it:
    the next line beyond the cut lies outside the picture, so a picture with that side's line erased would
    look the same (measured: 7 of the 16 cuts indexed from the blank paper, all right, and named 'assumed';
    8 centred and named, 6 of them one line off; before, 6 were pinned on blank paper alone, all right)."""
    img, plate = _photo(name)
    full = detect_discs(img, plate)
    assert full.origin_pinned and len(full) == plate.rows * plate.cols
    for side in ("left", "right", "top", "bottom"):
        part, (du, dv) = _cut(img, full, side)
        det = detect_discs(part, plate)
        k = np.argmin(np.linalg.norm(det.uv[:, None, :] + (du, dv) - full.uv[None], axis=2), axis=1)
        right = np.array_equal(det.rc, full.rc[k])
        axis = "cols" if side in ("left", "right") else "rows"
        assert right or axis in det.ambiguous, (side, det.index_basis)
        assert right or det.index_basis[axis] == "centred", (side, det.index_basis)
        assert det.origin_pinned == (not det.ambiguous)


def _same_lattice(rc, ref) -> bool:
    """Whether indices ``rc`` are ``ref`` under one symmetry of the square grid and one shift."""
    for M in ([[1, 0], [0, 1]], [[0, 1], [1, 0]]):
        for sg in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            d = rc - ref @ (np.asarray(M) * np.asarray(sg)[:, None]).T
            if len({tuple(x) for x in d}) == 1:
                return True
    return False


@pytest.mark.parametrize("name, axis, deg", [("circles-03.jpg", "x", 45), ("circles-03.jpg", "y", 55),
                                             ("circles-01.jpg", "y", 45), ("grid36-02.png", "y", 45)])
def test_a_steep_view_is_indexed_right_or_refused(name, axis, deg):
    """The photograph as its camera would have taken it turned by 45-55 deg (the plate then seen up to about
    70 deg from square-on): the discs found are on the plate's lattice as in the straight picture, or the
    picture is refused; never a lattice taken along the grid's diagonal (before: on circles-03 turned 55 deg
    about y, 23 discs were indexed so, with both axes 'all seen')."""
    img, plate = _photo(name)
    cell = load_cell(VISP / ("cell-640x480.yaml" if name.endswith(".png") else "cell.yaml"))
    full = detect_discs(img, plate)
    pic, cam, H = camera_turned(img, cell.camera.guess(), axis, deg)
    try:
        det = detect_discs(pic, plate, camera=cam)
    except ImageError as e:
        assert "no square grid" in str(e) or "lattice" in str(e)
        return
    truth = cv2.perspectiveTransform(full.uv.reshape(-1, 1, 2).astype(np.float32), H).reshape(-1, 2)
    k = np.argmin(np.linalg.norm(det.uv[:, None, :] - truth[None], axis=2), axis=1)
    assert _same_lattice(det.rc, full.rc[k])


def _erased(pic, plate, line):
    """The picture with one outer line of discs ('row 0', 'row 7', 'col 0', 'col 7') painted over with the
    paper's grey: the discs gone as glare or a missing print would leave them."""
    img = pic.image.copy()
    uv = pic.disc_uv.reshape(plate.rows, plate.cols, 2)
    kind, k = line.split()
    sel = uv[int(k)] if kind == "row" else uv[:, int(k)]
    paper = int(np.median(img[img > np.percentile(img, 60)]))
    r = np.sqrt(np.median(detect_discs(pic.image, plate).area_px) / np.pi)
    for u, v in sel:
        cv2.circle(img, (int(round(u)), int(round(v))), int(np.ceil(1.8 * r)), paper, -1)
    return img


@pytest.mark.parametrize("line", ["row 0", "row 7", "col 0", "col 7"])
def test_an_erased_edge_line_gives_the_right_plate_pose_or_says_it_is_not_known(cell, line):
    """An outer line of discs erased from the parked picture: seven lines seen, blank paper where the eighth
    was. The plate pose is right or the result says it is not known, with a warning naming the indices;
    C_H_G holds either way. Before, erasing the bottom (row 0) or top (row 7) row gave C_H_W one pitch off,
    'known', no warning: blank paper beyond one end was taken as the grid's end while the other end was
    blank too (row 0) or beyond the picture (row 7)."""
    w = _world(cell)
    res = calibrate_offline(_erased(render(w, seed=1), cell.plate, line), cell)
    s = res.summary()
    rot, dist = pose_difference(res.calibration.C_H_G, w.C_H_G)
    assert dist < 0.1 and rot < 0.1
    off = np.linalg.norm(res.calibration.C_H_W[:3, 3] - w.C_H_W[:3, 3])
    assert off < 0.05 or s["C_H_W_known"] is False, (line, off, res.discs.index_basis)
    assert s["C_H_W_known"] == res.discs.origin_pinned
    if not s["C_H_W_known"]:
        axis = line.split()[0] + "s"
        assert set(res.discs.ambiguous) == {axis}
        assert any("C_H_W is not known" in m and "0-6 up to 1-7" in m for m in s["warnings"])


def test_the_command_says_when_an_erased_row_leaves_the_plate_pose_unknown(cell, tmp_path, capsys):
    """``selfview calibrate --image`` on the parked picture with its top row erased: exit 0 with the
    calibration written, a warning on stderr and ``C_H_W_known`` false with the warning in the JSON."""
    w = _world(cell)
    path = tmp_path / "erased.png"
    cv2.imwrite(str(path), _erased(render(w, seed=1), cell.plate, "row 7"))
    code = main(["calibrate", "--image", str(path), "--out", str(tmp_path / "cal.yaml"), "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "warning: the plate's origin is not pinned" in err and "lies beyond the picture" in err
    doc = json.loads(out)
    assert doc["C_H_W_known"] is False
    assert any("rows 0-6 up to 1-7" in m for m in doc["warnings"])
