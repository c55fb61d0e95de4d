"""The plate seam: one ``detect_plate`` for every printed pattern, and what its points need afterwards.

A plate (``cell.PlateSpec``) is a ``rows x cols`` lattice of plate points at ``pitch`` mm centred on W's
origin (x along the columns, y along the rows, z into the plate; CONVENTIONS.md), printed as one of
``PLATE_PATTERNS``:

- ``discs``: dark discs whose centres are the points (``discs.detect_discs``); a disc's image centroid is
  not the image of its centre, ``plate_image_bias`` gives the difference for a pose;
- ``chessboard``: NX x NY squares, the (NX-1) x (NY-1) inner corners the points (OpenCV's
  ``findChessboardCornersSB``); square (0, 0), on W's -x -y corner, is dark; a board with NX + NY even
  looks the same turned by a half turn, so its orientation is ambiguous and refused;
- ``charuco``: a chessboard with ArUco markers in its light squares (``cv2.aruco.CharucoDetector``), the
  inner corners numbered by OpenCV's ids (row-major), so a partial view (fingers over it) is indexed.

A corner has no perspective bias (zero). ``board_ink`` and ``board_edges_W`` draw a board for the
simulated camera (``mocks/render.py``). A new pattern: its detector and drawing here, its keys in
``cell._parse_board``.
"""

from __future__ import annotations

import functools
import warnings

import cv2
import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import PLATE_PATTERNS, PlateSpec, aruco_dictionary
from selfview.measurement.discs import DiscDetections, as_gray, detect_discs, disc_image_bias
from selfview.errors import ConfigError, ImageError

__all__ = ["PLATE_PATTERNS", "PlateDetections", "detect_plate", "plate_image_bias", "correct_plate_bias",
           "charuco_board", "make_charuco_board", "board_ink", "board_edges_W", "charuco_biased",
           "warn_if_charuco_biased", "CHARUCO_BIASED_BEFORE"]

#: The points of one picture: ``DiscDetections`` (uv, rc, p_W, ...) whatever the pattern; for a board
#: ``area_px`` is 0, ``n_blobs`` the markers (ChArUco) or corners (chessboard) the detector reported.
PlateDetections = DiscDetections


def detect_plate(image, plate: PlateSpec, *, camera: CameraModel | None = None, min_points: int = 12) -> PlateDetections:
    """The plate points seen in ``image`` (any picture ``discs.as_gray`` takes), indexed on the plate's
    lattice and sorted by (row, col): pixels (distorted, as measured), grid indices and W points [mm].

    Raises ``ImageError`` (no plate, fewer than ``min_points`` points, a chessboard of ambiguous
    orientation, markers of another board), ``ConfigError`` (an unknown pattern or dictionary) or
    ``ValueError`` (``min_points`` not a whole number >= 1)."""
    if isinstance(min_points, bool) or not isinstance(min_points, (int, np.integer)) or min_points < 1:
        raise ValueError(f"min_points: expected a whole number of plate points >= 1, got {min_points!r}")
    if plate.pattern == "discs":
        return detect_discs(image, plate, camera=camera, min_discs=min_points)
    gray = as_gray(image, camera)
    u8 = np.clip(np.rint(gray), 0, 255).astype(np.uint8)
    basis = "board"
    if plate.pattern == "chessboard":
        uv, ids, n_raw, basis = _chessboard(u8, plate)
    elif plate.pattern == "charuco":
        uv, ids, n_raw = _charuco(u8, plate, min_points)
    else:
        raise ConfigError(f"plate.pattern: {plate.pattern!r}; expected one of {', '.join(PLATE_PATTERNS)}")
    if len(ids) < min_points:
        raise ImageError(f"only {len(ids)} {plate.pattern} corner(s) seen; at least {min_points} are needed")
    order = np.argsort(ids)
    ids = ids[order]
    rc = np.column_stack([ids // plate.cols, ids % plate.cols]).astype(int)
    return DiscDetections(uv=uv[order].astype(float), rc=rc, p_W=plate.disc_centres_W()[ids], area_px=np.zeros(len(ids)),
                          n_blobs=int(n_raw), rejected={}, index_basis={"x": basis, "y": basis})


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


# --- chessboard -------------------------------------------------------------------------------------
def _chessboard(u8: np.ndarray, plate: PlateSpec) -> tuple[np.ndarray, np.ndarray, int, str]:
    """The board's inner corners: the whole board, else (fingers over it, its edge out of the picture) the
    largest part of it OpenCV finds, placed in the middle of the plate's grid (its position on the plate
    is not known: ``index_basis`` 'partial view'; one picture's pose is then shifted along the plate,
    which the off-line calibration does not use)."""
    nx, ny = plate.squares
    if (nx + ny) % 2 == 0:
        raise ImageError(f"a {nx}x{ny}-square chessboard looks the same turned by a half turn: its orientation in the "
                         "picture is ambiguous; use a board with one odd and one even number of squares (or ChArUco)")
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCornersSB(u8, (nx - 1, ny - 1), flags=flags)
    basis = "board"
    if ok and corners is not None:
        g = corners.reshape(ny - 1, nx - 1, 2).astype(float)
    else:
        ok, corners, meta = cv2.findChessboardCornersSBWithMeta(u8, (3, 3), flags | cv2.CALIB_CB_LARGER)
        if not ok or corners is None:
            raise ImageError(f"no {nx}x{ny}-square chessboard ({nx - 1}x{ny - 1} inner corners) found in the picture")
        g = corners.reshape(meta.shape[0], meta.shape[1], 2).astype(float)
        if g.shape[0] > ny - 1 or g.shape[1] > nx - 1:
            g = g.transpose(1, 0, 2)
        if g.shape[0] > ny - 1 or g.shape[1] > nx - 1:
            raise ImageError(f"the chessboard seen has {meta.shape[1]}x{meta.shape[0]} inner corners, more than the "
                             f"plate's {nx - 1}x{ny - 1}: the plate file describes another board")
        basis = "partial view"
    if basis != "board":
        _check_alternation(u8, g)
    a, b = g[0, 1] - g[0, 0], g[1, 0] - g[0, 0]
    if a[0] * b[1] - a[1] * b[0] < 0:  # W's x, y, z (into the plate) right-handed: x to y turns clockwise on screen
        g = g[:, ::-1]
    dark0 = _cell_level(u8, g, 0, 0) < _cell_level(u8, g, 0, 1)
    if basis == "board" and not dark0:  # the inner cell at (0, 0) is dark, as square (0, 0)
        g = g[::-1, ::-1]
    r, c = np.mgrid[0 : g.shape[0], 0 : g.shape[1]]
    if basis != "board":  # centred on the plate (W's origin among the points seen), on a dark first cell's parity
        r0, c0 = (ny - 1 - g.shape[0]) // 2, (nx - 1 - g.shape[1]) // 2
        if (r0 + c0) % 2 != (0 if dark0 else 1):
            r0, c0 = (r0, c0 + 1) if c0 + g.shape[1] < nx - 1 else (r0, c0 - 1) if c0 > 0 else (r0 + 1 if r0 + g.shape[0] < ny - 1 else r0 - 1, c0)
        r, c = r + r0, c + c0
        if r.min() < 0 or c.min() < 0 or r.max() >= ny - 1 or c.max() >= nx - 1:
            raise ImageError("the part of the chessboard seen cannot be placed on the plate's grid")
    return g.reshape(-1, 2), (r * (nx - 1) + c).ravel(), g.shape[0] * g.shape[1], basis


def _check_alternation(u8: np.ndarray, g: np.ndarray) -> None:
    """A partial grid's cells must alternate dark and light like the squares (OpenCV may return every
    other corner of a board as a grid of its own): ``ImageError`` otherwise."""
    lv = np.array([[_cell_level(u8, g, r, c) for c in range(g.shape[1] - 1)] for r in range(g.shape[0] - 1)])
    dark = lv < np.median(lv)
    parity = (np.add.outer(np.arange(lv.shape[0]), np.arange(lv.shape[1])) % 2) == 0
    agree = max(np.mean(dark == parity), np.mean(dark != parity))
    if agree < 0.9:
        raise ImageError(f"the part of the chessboard found is not a grid of alternating squares ({agree:.0%} of its "
                         "cells alternate): fingers or the picture's edge cut the board too much; use a ChArUco plate")


def _cell_level(u8: np.ndarray, g: np.ndarray, r: int, c: int) -> float:
    """Mean grey level in the middle of the cell between corners (r, c) and (r + 1, c + 1) of the grid g."""
    quad = np.array([g[r, c], g[r, c + 1], g[r + 1, c + 1], g[r + 1, c]])
    mid = quad.mean(0)
    pts = np.rint(mid + 0.3 * (quad - mid)).astype(np.int32)  # a small quadrilateral in the cell's middle
    mask = np.zeros(u8.shape, np.uint8)
    cv2.fillConvexPoly(mask, pts, 1)
    if not mask.any():
        return float(u8[int(np.clip(round(mid[1]), 0, u8.shape[0] - 1)), int(np.clip(round(mid[0]), 0, u8.shape[1] - 1))])
    return float(u8[mask > 0].mean())


# --- ChArUco ----------------------------------------------------------------------------------------
#: OpenCV releases whose ChArUco corners were measured about 0.5 px off in u and v against the simulated
#: cell's truth (4.10, 4.11; 4.14 and 5.1 within 0.1 px); 4.12 and 4.13 were not measured.
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
    """A ``cv2.aruco.CharucoBoard`` of ``squares`` (NX, NY) of ``square`` mm with ``marker`` mm markers of
    the predefined ``dictionary`` (shared, cached: do not modify it). ``ConfigError`` naming ``what`` for
    an unknown dictionary."""
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


# --- drawing (the simulated camera) -----------------------------------------------------------------
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
    """Whether plate points (x_W, y_W) [mm] (any shape) lie on the board's dark print. ``ConfigError`` for
    a plate that is no board."""
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
    """Segments (p0, p1) in W [mm] holding every edge of the board's print (lines across the whole board:
    square sides, and for ChArUco every marker cell's sides). ``ConfigError`` for a plate that is no board."""
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
