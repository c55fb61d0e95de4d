"""The plate seam: one ``detect_plate`` for every pattern of ``PLATE_PATTERNS`` (a new one: its detector and drawing
here, its keys in ``cell._parse_board``). A plate is a ``rows x cols`` lattice of points at ``pitch`` mm centred on W's
origin (x along columns, y along rows, z into the plate; CONVENTIONS.md): disc centres, or a board's inner corners
(chessboard: square (0, 0), on W's -x -y corner, dark, NX + NY odd; ChArUco: OpenCV's ids, row-major). Only discs
have an image bias (``plate_image_bias``). ``board_ink`` and ``board_edges_W`` draw a board for ``mocks/render.py``."""

from __future__ import annotations

import functools
import warnings

import cv2
import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import PLATE_PATTERNS, PlateSpec, aruco_dictionary
from selfview.measurement.discs import DiscDetections, detect_discs, disc_image_bias, gray_u8
from selfview.errors import ConfigError, ImageError

__all__ = ["PLATE_PATTERNS", "PlateDetections", "detect_plate", "plate_image_bias", "correct_plate_bias",
           "charuco_board", "make_charuco_board", "board_ink", "board_edges_W", "charuco_biased",
           "warn_if_charuco_biased", "CHARUCO_BIASED_BEFORE"]

#: The points of one picture: ``DiscDetections`` (uv, rc, p_W, ...) whatever the pattern; for a board
#: ``area_px`` is 0, ``n_blobs`` the markers (ChArUco) or corners (chessboard) the detector reported.
PlateDetections = DiscDetections


def detect_plate(image, plate: PlateSpec, *, camera: CameraModel | None = None,
                 min_points: int = 12) -> PlateDetections:
    """The plate points seen in ``image`` (any picture ``as_gray`` takes), sorted by (row, col): pixels (distorted, as
    measured), grid indices and W points [mm]. Raises ``ImageError`` (no plate, fewer than ``min_points`` points, a
    chessboard of ambiguous orientation, another board's markers), ``ConfigError`` (an unknown pattern or dictionary)
    or ``ValueError`` (``min_points`` not a whole number >= 1)."""
    if isinstance(min_points, bool) or not isinstance(min_points, (int, np.integer)) or min_points < 1:
        raise ValueError(f"min_points: expected a whole number of plate points >= 1, got {min_points!r}")
    if plate.pattern == "discs":
        return detect_discs(image, plate, camera=camera, min_discs=min_points)
    u8 = gray_u8(image, camera)
    basis, ambiguous = {"x": "board", "y": "board"}, {}
    if plate.pattern == "chessboard":
        uv, ids, n_raw, basis, ambiguous = _chessboard(u8, plate)
    elif plate.pattern == "charuco":
        uv, ids, n_raw = _charuco(u8, plate, min_points)
    else:
        raise ConfigError(f"plate.pattern: {plate.pattern!r}; expected one of {', '.join(PLATE_PATTERNS)}")
    if len(ids) < min_points:
        raise ImageError(f"only {len(ids)} {plate.pattern} corner(s) seen; at least {min_points} are needed")
    order = np.argsort(ids)
    ids = ids[order]
    rc = np.column_stack([ids // plate.cols, ids % plate.cols]).astype(int)
    return DiscDetections(uv=uv[order].astype(float), rc=rc, p_W=plate.disc_centres_W()[ids],
                          area_px=np.zeros(len(ids)), n_blobs=int(n_raw), rejected={}, index_basis=basis,
                          ambiguous=ambiguous)


def plate_image_bias(plate: PlateSpec, camera: CameraModel, C_H_W, p_W) -> np.ndarray:
    """(N, 2) [px] the measured image of each plate point minus the image of the point, for the pose
    ``C_H_W`` (4, 4): a disc's perspective and lens bias; zero for a board's corners."""
    p_W = np.atleast_2d(np.asarray(p_W, float))
    if plate.pattern != "discs" or len(p_W) == 0:
        return np.zeros((len(p_W), 2))
    return disc_image_bias(camera, C_H_W, p_W, plate.disc_diameter / 2)


def correct_plate_bias(det: PlateDetections, camera: CameraModel, C_H_W, plate: PlateSpec) -> np.ndarray:
    """(N, 2) the detections' pixels with ``plate_image_bias`` removed (distorted pixels)."""
    return det.uv - plate_image_bias(plate, camera, C_H_W, det.p_W)


#: A corner's dark cells, and its light ones, agree within this share of their contrast, which needs X_MIN_CONTRAST.
X_AGREE = 0.3
X_MIN_CONTRAST = 40.0


def _chessboard(u8: np.ndarray, plate: PlateSpec) -> tuple[np.ndarray, np.ndarray, int, dict, dict]:
    """(uv, ids, corners found, index basis, ambiguous) of the board's inner corners: the whole board's, else (fingers,
    the picture's edge) a lattice grown from 2 x 2 alternating squares and placed on the plate."""
    nx, ny = plate.squares
    if (nx + ny) % 2 == 0:
        raise ImageError(f"a {nx}x{ny}-square chessboard looks the same turned by a half turn: its orientation in the "
                         "picture is ambiguous; use a board with one odd and one even number of squares (or ChArUco)")
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCornersSB(u8, (nx - 1, ny - 1), flags=flags)
    if ok and corners is not None:
        g = corners.reshape(ny - 1, nx - 1, 2).astype(float)
        a, b = g[0, 1] - g[0, 0], g[1, 0] - g[0, 0]
        if a[0] * b[1] - a[1] * b[0] < 0:  # W's x, y, z (into the plate) right-handed: x to y turns clockwise on screen
            g = g[:, ::-1]
        if _cell_level(u8, g, 0, 0) >= _cell_level(u8, g, 0, 1):  # the inner cell at (0, 0) is dark, as square (0, 0)
            g = g[::-1, ::-1]
        r, c = np.mgrid[0 : g.shape[0], 0 : g.shape[1]]
        keep = _alternating(u8, g)  # OpenCV places a corner under a finger where the lattice puts it
        return (g[keep], (r * (nx - 1) + c)[keep], g.shape[0] * g.shape[1], {"x": "board", "y": "board"}, {})
    ok, corners, meta = cv2.findChessboardCornersSBWithMeta(u8, (3, 3), flags | cv2.CALIB_CB_LARGER)
    if not ok or corners is None:
        raise ImageError(f"no {nx}x{ny}-square chessboard ({nx - 1}x{ny - 1} inner corners) found in the picture")
    found = _grow_lattice(u8, corners.reshape(meta.shape[0], meta.shape[1], 2).astype(float))
    return _place_lattice(u8, found, plate)


def _alternating(u8: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(R, C) bool: the corners of the whole board's grid g (R, C, 2) whose cells alternate with the board's parity."""
    G = np.pad(g, ((1, 1), (1, 1), (0, 0)))
    G[0, 1:-1], G[-1, 1:-1] = 2 * g[0] - g[1], 2 * g[-1] - g[-2]
    G[:, 0], G[:, -1] = 2 * G[:, 1] - G[:, 2], 2 * G[:, -2] - G[:, -3]
    R, C = g.shape[:2]
    return np.array([[_x_corner(u8, G[r : r + 3, c : c + 3]) == (r + c) % 2 for c in range(C)] for r in range(R)])


def _seed_block(u8: np.ndarray, g: np.ndarray) -> np.ndarray:
    """(3, 3, 2) corners of the grid g (R, C, 2) whose four cells alternate (``_x_corner``), the block nearest
    the grid's middle first; ``ImageError`` when none does (OpenCV's partial grid may skip rows or columns)."""
    R, C = g.shape[:2]
    blocks = sorted(((r, c) for r in range(R - 2) for c in range(C - 2)),
                    key=lambda rc: (rc[0] + 1 - (R - 1) / 2) ** 2 + (rc[1] + 1 - (C - 1) / 2) ** 2)
    for r, c in blocks:
        if _x_corner(u8, g[r : r + 3, c : c + 3]) is not None:
            return g[r : r + 3, c : c + 3]
    # every corner OpenCV gave is the board's: a block around one, along its nearest neighbours' steps, refined
    pool = g.reshape(-1, 2)
    for p in pool[np.argsort(np.linalg.norm(pool - pool.mean(0), axis=1))]:
        d = pool - p
        n = np.linalg.norm(d, axis=1)
        order = [k for k in np.argsort(n) if n[k] > 3.0]
        if not order:
            continue
        a = d[order[0]]
        b = next((d[k] for k in order[1:] if abs(a[0] * d[k][1] - a[1] * d[k][0]) > 0.7 * n[order[0]] * n[k]), None)
        if b is None:
            continue
        for fa, fb in ((1, 1), (1, 2), (2, 1), (2, 2)):  # OpenCV's grid may skip every other row or column
            sub = _refined_block(u8, p, a / fa, b / fb)
            if sub is not None and _x_corner(u8, sub) is not None:
                return sub
    raise ImageError("no part of the chessboard found is a grid of alternating squares: fingers or the picture's "
                     "edge cut the board too much")


def _refined_block(u8: np.ndarray, p, a, b) -> np.ndarray | None:
    """(3, 3, 2) the corners p + i a + j b (i, j in -1..1), refined; None when they reach beyond the picture."""
    j, i = np.mgrid[-1:2, -1:2]
    sub = p + i[..., None] * a + j[..., None] * b
    return _subpix(u8, sub, int(np.clip(min(np.linalg.norm(a), np.linalg.norm(b)) / 4, 2, 15)))


def _subpix(u8: np.ndarray, pts: np.ndarray, win: int) -> np.ndarray | None:
    """Corners ``pts`` (..., 2) [px] refined in a (2 win + 1) px window; None when one is within 2 px of the border."""
    h, w = u8.shape
    if not np.all((pts >= win + 2) & (pts < (w - win - 2, h - win - 2))):
        return None
    q = cv2.cornerSubPix(u8, pts.reshape(-1, 1, 2).astype(np.float32), (win, win), (-1, -1),
                         (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 30, 0.01))
    return q.reshape(pts.shape).astype(float)


def _x_corner(u8: np.ndarray, sub: np.ndarray, levels=None) -> int | None:
    """The dark cells' parity (0: the block's cell (0, 0) dark, 1: light) of a 3 x 3 block of corners (3, 3, 2) whose
    four cells alternate, else None; ``levels`` (dark, light) the grey levels they must show (within ``X_AGREE``).
    Read in the middles and near the middle corner (a finger at a square's outer corner may darken its middle only)."""
    near = sub[1, 1] + 0.4 * (sub - sub[1, 1])
    parities = {_x_cells(u8, sub, levels), _x_cells(u8, near, levels)}
    return parities.pop() if len(parities) == 1 else None


def _x_cells(u8: np.ndarray, sub: np.ndarray, levels) -> int | None:
    """``_x_corner`` for the cells of one 3 x 3 block read in their middles."""
    lv = np.array([[_cell_level(u8, sub, r, c) for c in range(2)] for r in range(2)])
    d1, d2 = (lv[0, 0] + lv[1, 1]) / 2, (lv[0, 1] + lv[1, 0]) / 2
    contrast = abs(d1 - d2)
    if contrast < X_MIN_CONTRAST or max(abs(lv[0, 0] - lv[1, 1]), abs(lv[0, 1] - lv[1, 0])) > X_AGREE * contrast:
        return None
    parity = 0 if d1 < d2 else 1
    if levels is not None:
        dark, light = levels
        want = np.where((np.add.outer(np.arange(2), np.arange(2)) + parity) % 2 == 0, dark, light)
        if np.max(np.abs(lv - want)) > X_AGREE * (light - dark):
            return None
    return parity


def _block_levels(u8: np.ndarray, sub: np.ndarray) -> tuple[float, float]:
    """(dark, light) grey levels of an alternating 3 x 3 block's cells."""
    lv = np.sort([_cell_level(u8, sub, r, c) for r in range(2) for c in range(2)])
    return float(lv[:2].mean()), float(lv[2:].mean())


def _lattice_H(found: dict) -> np.ndarray:
    """The homography from lattice (c, r) to pixels of the corners found."""
    rc = np.array(list(found), float)
    uv = np.array(list(found.values()), float)
    H, _ = cv2.findHomography(rc[:, ::-1], uv, 0)
    if H is None:
        raise ImageError("the chessboard corners found do not form a lattice")
    return H


def _at(H: np.ndarray, c, r) -> np.ndarray:
    p = H @ np.vstack([np.ravel(c), np.ravel(r), np.ones(np.size(c))])
    return (p[:2] / p[2]).T


def _grow_lattice(u8: np.ndarray, g: np.ndarray) -> dict:
    """{(r, c): uv} the board's corners grown from a seed block of ``g``: each predicted by the homography of the
    nearest corners, refined, and taken within a quarter square of the prediction when its four cells alternate with the
    seed's parity (a corner under a finger or beyond the board does not)."""
    seed = _seed_block(u8, g)
    found = {(i, j): seed[i, j] for i in range(3) for j in range(3)}
    parity, levels = _x_corner(u8, seed), _block_levels(u8, seed)
    tried = set(found)
    grew = True
    while grew:
        grew = False
        H = _lattice_H(found)
        todo = sorted({(r + dr, c + dc) for r, c in found for dr, dc in ((0, 1), (1, 0), (0, -1), (-1, 0))} - tried)
        for r, c in todo:
            tried.add((r, c))
            near = sorted(found, key=lambda k: (k[0] - r) ** 2 + (k[1] - c) ** 2)[:16]
            Hn = _lattice_H({k: found[k] for k in near}) if len(near) >= 6 else H
            quad = _at(Hn, [c - 1, c + 1, c + 1, c - 1, c], [r - 1, r - 1, r + 1, r + 1, r])
            p = quad[4]
            side = float(np.min(np.linalg.norm(quad[:4] - p, axis=1))) / np.sqrt(2)  # about a square [px]
            win = int(np.clip(side / 4, 2, 15))
            q = _subpix(u8, p, win) if side >= 8 else None
            if q is None or np.linalg.norm(q - p) > side / 4:
                continue
            block = _at(Hn, np.tile([c - 1, c, c + 1], 3), np.repeat([r - 1, r, r + 1], 3)).reshape(3, 3, 2)
            block[1, 1] = q
            px = _x_corner(u8, block, levels)
            if px is None or px != (parity + r - 1 + c - 1) % 2:
                continue
            found[(r, c)] = q
            grew = True
    return found


def _end_seen(u8: np.ndarray, H: np.ndarray, rows, cols, light: float, dark: float) -> bool:
    """Whether the board's border shows beyond lattice line ``rows`` (or ``cols``): cells all in view, 80 % light."""
    rr, cc = np.broadcast_arrays(np.asarray(rows, float), np.asarray(cols, float))
    h, w = u8.shape
    lv = []
    for r, c in zip(rr.ravel(), cc.ravel()):
        quad = _at(H, [c - 0.5, c + 0.5, c + 0.5, c - 0.5], [r - 0.5, r - 0.5, r + 0.5, r + 0.5])
        if not np.all((quad >= 0) & (quad < (w - 1, h - 1))):
            return False
        lv.append(_quad_level(u8, quad))
    return bool(np.mean(np.array(lv) > light - 0.3 * (light - dark)) >= 0.8)


def _place_lattice(u8: np.ndarray, found: dict, plate: PlateSpec) -> tuple[np.ndarray, np.ndarray, int, dict, dict]:
    """(uv, ids, corners found, basis per axis, ambiguous per axis) of the grown lattice ``found`` {(r, c): uv} on the
    plate: turned so W's x, y, z are right-handed, placed by the board's border beyond it and the squares' colours
    (square (0, 0) dark); of several placements, the most central, its origin said ambiguous."""
    nx, ny = plate.squares
    H = _lattice_H(found)
    a, b = _at(H, [1, 0], [0, 1]) - _at(H, [0], [0])
    mirror = a[0] * b[1] - a[1] * b[0] < 0
    rc = np.array(list(found), int)
    uv = np.array(list(found.values()), float)
    cells = [(r, c) for r, c in found if {(r + 1, c), (r, c + 1), (r + 1, c + 1)} <= found.keys()]
    lv = np.array([_cell_level(u8, found, r, c) for r, c in cells])
    if len(lv) < 2:
        raise ImageError(f"only {len(found)} chessboard corner(s) found around the seed: too little of the board in "
                         "view")
    dark_lv, light_lv = np.percentile(lv, [10, 90])
    dark = lv < (dark_lv + light_lv) / 2
    rmin, rmax, cmin, cmax = rc[:, 0].min(), rc[:, 0].max(), rc[:, 1].min(), rc[:, 1].max()
    ends = {  # the border seen beyond the lattice's last line, per direction (dr, dc) in its own indices
        (-1, 0): _end_seen(u8, H, rmin - 1.5, np.arange(cmin, cmax) + 0.5, light_lv, dark_lv),
        (1, 0): _end_seen(u8, H, rmax + 1.5, np.arange(cmin, cmax) + 0.5, light_lv, dark_lv),
        (0, -1): _end_seen(u8, H, np.arange(rmin, rmax) + 0.5, cmin - 1.5, light_lv, dark_lv),
        (0, 1): _end_seen(u8, H, np.arange(rmin, rmax) + 0.5, cmax + 1.5, light_lv, dark_lv),
    }
    cand = []
    m = np.array([[1, 0], [0, -1]]) if mirror else np.eye(2, dtype=int)
    for quarter in range(4):  # the lattice turned by quarter turns on the board
        t = np.linalg.matrix_power(np.array([[0, -1], [1, 0]]), quarter) @ m
        R, C = (rc @ t.T).T
        seen = {tuple(t @ d): v for d, v in ends.items()}  # the ends in the board's directions
        e_r, e_c = (seen[(-1, 0)], seen[(1, 0)]), (seen[(0, -1)], seen[(0, 1)])
        r_opts = _offsets(R.min(), R.max(), ny - 2, *e_r)
        c_opts = _offsets(C.min(), C.max(), nx - 2, *e_c)
        # a cell's top-left corner on the board, and the colour it must have there
        tl = np.array([(np.array([[r, c], [r + 1, c], [r, c + 1], [r + 1, c + 1]]) @ t.T).min(0) for r, c in cells])
        for r0 in r_opts:
            for c0 in c_opts:
                if np.mean(dark == ((tl[:, 0] + r0 + tl[:, 1] + c0) % 2 == 0)) >= 0.9:
                    cand.append((R + r0, C + c0, *e_r, *e_c))
    if not cand:
        raise ImageError(f"the {len(found)} chessboard corners seen ({rmax - rmin + 1} x {cmax - cmin + 1}) cannot be "
                         f"placed on the plate's {nx}x{ny}-square board: another board, or the plate file's squares "
                         "are wrong")
    mid = np.array([(ny - 2) / 2, (nx - 2) / 2])
    best = min(cand, key=lambda k: float(np.sum((np.array([k[0].mean(), k[1].mean()]) - mid) ** 2)))
    R, C, r_lo, r_hi, c_lo, c_hi = best
    basis = {"x": _basis(c_lo, c_hi), "y": _basis(r_lo, r_hi)}
    ambiguous = {}
    for axis, k in (("x", 1), ("y", 0)):
        if any(not np.array_equal(cc[k], best[k]) for cc in cand):
            ambiguous[axis] = (f"the {len(found)} chessboard corners seen fit {len(cand)} places (or turns) on the "
                               "board; neither its border nor its squares' colours tell which")
            basis[axis] = "centred"
    return uv, R * (nx - 1) + C, len(found), basis, ambiguous


def _offsets(lo: int, hi: int, top: int, lo_seen: bool, hi_seen: bool) -> list[int]:
    """The shifts k that put lattice indices lo..hi on the board's 0..top: pinned by an end seen."""
    return [k for k in range(-lo, top - hi + 1) if (not lo_seen or lo + k == 0) and (not hi_seen or hi + k == top)]


def _basis(lo_seen: bool, hi_seen: bool) -> str:
    return {(True, True): "all seen", (True, False): "low end seen", (False, True): "high end seen"}.get(
        (lo_seen, hi_seen), "centred")


def _cell_level(u8: np.ndarray, g: np.ndarray | dict, r: int, c: int) -> float:
    """Mean grey in the middle of cell (r, c)..(r + 1, c + 1) of the grid g ((R, C, 2) array or {(r, c): uv} dict)."""
    return _quad_level(u8, np.array([g[r, c], g[r, c + 1], g[r + 1, c + 1], g[r + 1, c]]))


def _quad_level(u8: np.ndarray, quad: np.ndarray) -> float:
    """Mean grey level in the middle of the cell whose corners are ``quad`` (4, 2) [px] in order around it."""
    h, w = u8.shape
    mid = quad.mean(0)
    pts = np.rint(mid + 0.3 * (quad - mid)).astype(np.int32)  # a small quadrilateral in the cell's middle
    lo = np.clip(pts.min(0), 0, (w - 1, h - 1))
    hi = np.clip(pts.max(0) + 1, lo + 1, (w, h))
    mask = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)  # over the quadrilateral's bounding box only
    cv2.fillConvexPoly(mask, pts - lo, 1)
    if not mask.any():
        return float(u8[int(np.clip(round(mid[1]), 0, h - 1)), int(np.clip(round(mid[0]), 0, w - 1))])
    return float(u8[lo[1] : hi[1], lo[0] : hi[0]][mask > 0].mean())


#: OpenCV before this: ChArUco corners 0.5 px off (4.10, 4.11; 4.14, 5.1 within 0.1 px; 4.12, 4.13 not measured).
CHARUCO_BIASED_BEFORE = (4, 12)


def charuco_biased() -> bool:
    """Whether this OpenCV's ChArUco corners carry the half-pixel bias above."""
    return tuple(int(x) for x in cv2.__version__.split(".")[:2]) < CHARUCO_BIASED_BEFORE


def warn_if_charuco_biased() -> None:
    """A ``UserWarning`` on an OpenCV whose ChArUco corners carry the half-pixel bias above."""
    if charuco_biased():
        warnings.warn(f"OpenCV {cv2.__version__} places ChArUco corners about 0.5 px off (measured); the poses "
                      "from a ChArUco board carry it: use OpenCV 4.14 or newer for ChArUco", stacklevel=3)


@functools.lru_cache(maxsize=8)
def make_charuco_board(squares: tuple[int, int], square: float, marker: float, dictionary: str,
                       legacy: bool = False, what: str = "plate.dictionary"):
    """A shared, cached ``cv2.aruco.CharucoBoard`` (do not modify it): ``squares`` (NX, NY) of ``square`` mm, ``marker``
    mm markers of the predefined ``dictionary``. ``ConfigError`` naming ``what`` for an unknown dictionary."""
    board = cv2.aruco.CharucoBoard(tuple(int(v) for v in squares), float(square), float(marker),
                                   cv2.aruco.getPredefinedDictionary(aruco_dictionary(dictionary, what)))
    board.setLegacyPattern(bool(legacy))
    return board


def charuco_board(plate: PlateSpec):
    """The plate's ``cv2.aruco.CharucoBoard`` (board coordinates: origin at the board's corner, mm)."""
    return make_charuco_board(tuple(plate.squares), plate.pitch, plate.marker, plate.dictionary, plate.legacy_pattern)


def _charuco(u8: np.ndarray, plate: PlateSpec, min_points: int) -> tuple[np.ndarray, np.ndarray, int]:
    board = charuco_board(plate)
    warn_if_charuco_biased()
    corners, ids, _, marker_ids = cv2.aruco.CharucoDetector(board).detectBoard(u8)
    n_markers = 0 if marker_ids is None else len(marker_ids)
    n = 0 if ids is None else len(ids)
    if n < min_points:
        if n_markers == 0:
            found = cv2.aruco.ArucoDetector(board.getDictionary()).detectMarkers(u8)[1]
            seen = sorted(int(i) for i in np.ravel(found)) if found is not None else []
            if seen:
                raise ImageError(f"the {plate.dictionary} markers seen (ids {seen[:12]}) are not this board's "
                                 f"(ids 0..{len(board.getIds()) - 1}): another board, or the plate file's board size "
                                 "or legacy_pattern is wrong")
            raise ImageError(f"no {plate.dictionary} marker found in the picture: no ChArUco plate in view, or the "
                             "plate file names another dictionary than the printed one")
        raise ImageError(f"only {n} ChArUco corner(s) seen ({n_markers} markers); at least {min_points} are needed")
    return corners.reshape(-1, 2), np.ravel(ids).astype(int), n_markers


def _require_board(plate: PlateSpec) -> None:
    if plate.pattern not in ("chessboard", "charuco"):
        raise ConfigError(f"plate.pattern: {plate.pattern!r} is not a board; a board's print is drawn for "
                          "'chessboard' or 'charuco' plates only")


@functools.lru_cache(maxsize=8)
def _charuco_print(squares, square, marker, dictionary, legacy) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(NY, NX) marker index per square (-1: none), (M, 2) marker top-left corners [mm, board], (M, k, k)
    marker cells (True: dark), k = marker bits + 2 (the black border)."""
    board = make_charuco_board(squares, square, marker, dictionary, legacy)
    nx, ny = squares
    k = board.getDictionary().markerSize + 2
    where = np.full((ny, nx), -1, int)
    tl, cells = [], []
    for m, (obj, mid) in enumerate(zip(board.getObjPoints(), np.ravel(board.getIds()))):
        lo = np.asarray(obj, float).reshape(-1, 3)[:, :2].min(0)
        where[int((lo[1] + marker / 2) // square), int((lo[0] + marker / 2) // square)] = m
        tl.append(lo)
        cells.append(cv2.aruco.generateImageMarker(board.getDictionary(), int(mid), k) < 128)
    return where, np.array(tl), np.array(cells)


def board_ink(plate: PlateSpec, xw: np.ndarray, yw: np.ndarray) -> np.ndarray:
    """Whether plate points (x_W, y_W) [mm] (any shape) lie on the board's dark print; ``ConfigError`` for no board."""
    _require_board(plate)
    nx, ny = plate.squares
    sq = plate.pitch
    bx, by = np.asarray(xw) + nx * sq / 2, np.asarray(yw) + ny * sq / 2
    inside = (bx >= 0) & (bx < nx * sq) & (by >= 0) & (by < ny * sq)
    i = np.clip(np.floor(bx / sq), 0, nx - 1).astype(np.intp)
    j = np.clip(np.floor(by / sq), 0, ny - 1).astype(np.intp)
    if plate.pattern == "chessboard":
        return inside & ((i + j) % 2 == 0)
    where, tl, cells = _charuco_print(tuple(plate.squares), sq, plate.marker, plate.dictionary, plate.legacy_pattern)
    m = where[j, i]
    ink = inside & (m < 0)
    has = inside & (m >= 0)
    k = cells.shape[1]
    mm = m[has]
    cu = np.floor((bx[has] - tl[mm, 0]) / plate.marker * k).astype(np.intp)
    cv = np.floor((by[has] - tl[mm, 1]) / plate.marker * k).astype(np.intp)
    on = (cu >= 0) & (cu < k) & (cv >= 0) & (cv < k)
    dark = np.zeros(mm.shape, bool)
    dark[on] = cells[mm[on], cv[on], cu[on]]
    ink[has] = dark
    return ink


def board_edges_W(plate: PlateSpec) -> list[tuple[np.ndarray, np.ndarray]]:
    """Segments (p0, p1) in W [mm] holding every edge of the board's print; ``ConfigError`` if the plate is no board."""
    _require_board(plate)
    nx, ny = plate.squares
    sq = plate.pitch
    xs = [i * sq for i in range(nx + 1)]
    ys = [j * sq for j in range(ny + 1)]
    if plate.pattern == "charuco":
        _, tl, cells = _charuco_print(tuple(plate.squares), sq, plate.marker, plate.dictionary, plate.legacy_pattern)
        k = cells.shape[1]
        steps = np.arange(k + 1) * plate.marker / k
        xs += sorted({round(float(x), 9) for x in (tl[:, 0:1] + steps).ravel()})
        ys += sorted({round(float(y), 9) for y in (tl[:, 1:2] + steps).ravel()})
    ox, oy = nx * sq / 2, ny * sq / 2
    segs = [(np.array([x - ox, -oy, 0.0]), np.array([x - ox, oy, 0.0])) for x in xs]
    segs += [(np.array([-ox, y - oy, 0.0]), np.array([ox, y - oy, 0.0])) for y in ys]
    return segs
