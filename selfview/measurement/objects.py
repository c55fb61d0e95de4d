"""Objects to grasp: a block on the table with a printed ChArUco target on its top face, its description (YAML, the
target a ``plate:``-style section) and its pose ``C_H_O`` from one picture. Frame O: origin at the target's centre, x
and y along its squares, z into the block (as the plate's W, CONVENTIONS.md)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from selfview.maths.camera import CameraModel
from selfview.errors import CalibrationError, ConfigError
from selfview.maths.geometry import H_from_rotvec, R_from_rpy, inv_H, make_H
from selfview.files.cell import Section
from selfview.files.io_safe import load_yaml_file
from selfview.measurement.discs import gray_u8
from selfview.measurement.plates import make_charuco_board, warn_if_charuco_biased

__all__ = ["TargetSpec", "ObjectSpec", "TargetDetection", "ObjectPose", "load_object", "parse_object",
           "default_object_path", "detect_target", "object_pose", "target_board", "AMBIGUITY_RATIO", "MIN_CORNERS"]

#: IPPE's second solution must leave at least this many times the first's residual, else the pose is refused.
AMBIGUITY_RATIO = 3.0
#: A pose needs at least this many ChArUco corners (fewer cannot tell the flip apart).
MIN_CORNERS = 6
#: Where the simulation places the block by default: ranges of its centre ``x``, ``y`` [mm, base frame], ``yaw_deg``.
_PLACEMENT = {"x": (330.0, 370.0), "y": (150.0, 190.0), "yaw_deg": (-20.0, 20.0)}
_DICTIONARIES = ("DICT_4X4_50", "DICT_4X4_100", "DICT_5X5_50", "DICT_5X5_100", "DICT_6X6_50", "DICT_6X6_250")


@dataclass(frozen=True)
class TargetSpec:
    """A ChArUco patch: ``squares`` (NX, NY), ``square`` and ``marker`` side [mm], ``dictionary`` (cv2.aruco name)."""

    squares: tuple[int, int]
    square: float
    marker: float
    dictionary: str = "DICT_4X4_50"

    @property
    def size(self) -> tuple[float, float]:
        """(x, y) extent of the printed squares [mm]."""
        return (self.squares[0] * self.square, self.squares[1] * self.square)


@dataclass(frozen=True)
class ObjectSpec:
    """An object to grasp: ``block`` (x, y, height) [mm], x between the jaws; ``target``; ``O_H_Gstar`` (4, 4) the grasp
    frame in O; ``approach_mm`` the stand-off along G*'s z the servo aims at before the last descent; ``placement``
    (simulation) ranges of the block's centre ``x``, ``y`` [mm, base frame] and ``yaw_deg``; ``source`` where read."""

    name: str
    block: tuple[float, float, float]
    target: TargetSpec
    O_H_Gstar: np.ndarray
    approach_mm: float = 30.0
    placement: dict = field(default_factory=lambda: dict(_PLACEMENT))
    source: str = "<object>"

    @property
    def Gstar_H_O(self) -> np.ndarray:
        return inv_H(self.O_H_Gstar)

    @property
    def O_H_Gpre(self) -> np.ndarray:
        """The stand-off pose: G* backed off ``approach_mm`` along its own z."""
        return self.O_H_Gstar @ make_H(np.eye(3), (0.0, 0.0, -self.approach_mm))

    def jaw_clearance_mm(self, open_gap_mm: float) -> float:
        """How far the block may lie off centre between the open jaws (each side) [mm]."""
        return (float(open_gap_mm) - self.block[0]) / 2.0


def default_object_path() -> Path:
    return Path(__file__).resolve().parents[1] / "data" / "block.yaml"


def _in_range(values, key: str, lo: float, hi: float) -> tuple[float, ...]:
    if not all(lo <= v <= hi for v in values):
        raise ConfigError(f"{key}: expected numbers in {lo:g}..{hi:g}, got {list(values)}")
    return tuple(values)


def _parse_target(s: Section) -> TargetSpec:
    if s.string("pattern", "charuco") != "charuco":
        raise ConfigError(f"object.target.pattern {s.data['pattern']!r}: only 'charuco' targets are measured")
    sq = s.raw("squares")
    whole = isinstance(sq, list) and all(isinstance(n, int) and not isinstance(n, bool) and 3 <= n <= 20 for n in sq)
    if not whole or len(sq) != 2:
        raise ConfigError(f"object.target.squares: expected [NX, NY], whole numbers 3..20, got {sq!r}")
    square = s.number("square", lo=1.0, hi=200.0)
    marker = s.number("marker", lo=0.5, hi=200.0)
    if marker >= square:
        raise ConfigError(f"object.target.marker {marker:g} mm must be smaller than target.square {square:g} mm")
    d = s.string("dictionary", "DICT_4X4_50", choices=_DICTIONARIES)
    s.done()
    return TargetSpec((int(sq[0]), int(sq[1])), square, marker, d)


def _parse_frame(s: Section) -> np.ndarray:
    p = _in_range(s.vector("xyz", 3, (0.0, 0.0, 0.0)), "object.grasp.xyz [mm]", -1000, 1000)
    a = _in_range(s.vector("rpy_deg", 3, (0.0, 0.0, 0.0)), "object.grasp.rpy_deg", -360, 360)
    s.done()
    return make_H(R_from_rpy(*np.radians(a)), p)


def parse_object(data, source: str = "<object>") -> ObjectSpec:
    """An ``ObjectSpec`` from the mapping of an object file; ``ConfigError`` naming ``source`` and what is wrong."""
    if not isinstance(data, dict) or not isinstance(data.get("object"), dict):
        raise ConfigError(f"{source}: expected a mapping with an 'object' section")
    try:
        return _parse_object(Section(data["object"], "object"), source)
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None


def _parse_object(o: Section, source: str) -> ObjectSpec:
    block = _in_range(o.vector("block", 3), "object.block [mm]", 1.0, 500.0)
    target = _parse_target(o.section("target"))
    if target.size[0] > block[0] or target.size[1] > block[1]:
        raise ConfigError(f"the target ({target.size[0]:g} x {target.size[1]:g} mm) does not fit on the "
                          f"block's top ({block[0]:g} x {block[1]:g} mm)")
    approach = o.number("approach_mm", 30.0, lo=0.0, hi=300.0)
    placement = dict(_PLACEMENT)
    ps = o.section("placement", None)
    for k, default in placement.items():
        lo, hi = _in_range(ps.vector(k, 2, default), f"object.placement.{k}", -2000, 2000)
        if lo > hi:
            raise ConfigError(f"object.placement.{k}: low {lo:g} above high {hi:g}")
        placement[k] = (lo, hi)
    ps.done()
    spec = ObjectSpec(str(o.raw("name", "object")), block, target, _parse_frame(o.section("grasp", None)),
                      approach, placement, source)
    o.done()
    return spec


def load_object(path=None) -> ObjectSpec:
    """Read an object file (default: the package's block); ``ConfigError`` naming what is wrong."""
    p = Path(path) if path is not None else default_object_path()
    return parse_object(load_yaml_file(p, what="object file"), f"object file {str(p)!r}")


def target_board(target: TargetSpec):
    """The ``cv2.aruco.CharucoBoard`` of ``target`` (board frame: origin at a corner, mm; shared, do not modify it)."""
    return make_charuco_board(tuple(target.squares), target.square, target.marker, target.dictionary,
                              what="target.dictionary")


@dataclass(frozen=True)
class TargetDetection:
    """The target's corners found in a picture: ``uv`` (N, 2) distorted pixels, ``p_O`` (N, 3) the same
    corners in O [mm], ``ids`` (N,) their ChArUco ids, ``markers`` how many markers were decoded."""

    uv: np.ndarray
    p_O: np.ndarray
    ids: np.ndarray
    markers: int


def detect_target(image: np.ndarray, target: TargetSpec) -> TargetDetection:
    """The ChArUco corners of ``target`` in a picture (as ``as_gray`` takes; OpenCV 4.10+ aruco). ``CalibrationError``
    when not seen (too few corners) or seen twice (a marker decoded twice); ``ImageError`` for no or a blank picture."""
    board = target_board(target)
    warn_if_charuco_biased()
    corners, ids, _, marker_ids = cv2.aruco.CharucoDetector(board).detectBoard(gray_u8(image, what="target picture"))
    n_markers = 0 if marker_ids is None else len(marker_ids)
    if marker_ids is not None and len(np.unique(marker_ids)) < n_markers:
        raise CalibrationError(f"target seen twice: {n_markers - len(np.unique(marker_ids))} marker id(s) decoded "
                               "more than once (two targets in view); refused")
    n = 0 if ids is None else len(ids)
    if n < MIN_CORNERS:
        raise CalibrationError(f"target not seen: {n} ChArUco corner(s) found ({n_markers} marker(s)), "
                               f"at least {MIN_CORNERS} needed")
    obj, imgp = board.matchImagePoints(corners, ids)
    half = np.array([target.size[0] / 2, target.size[1] / 2, 0.0])
    return TargetDetection(imgp.reshape(-1, 2).astype(float), obj.reshape(-1, 3).astype(float) - half,
                           ids.reshape(-1).astype(int), n_markers)


@dataclass(frozen=True)
class ObjectPose:
    """``C_H_O`` (4, 4); ``sigma_mm``, ``sigma_deg`` (3,) standard deviations of translation and rotation (camera axes);
    ``rms_px``, ``rms_px_other`` residuals of the chosen and IPPE's flipped pose; ``corners``, ``detection`` used."""

    C_H_O: np.ndarray
    sigma_mm: np.ndarray
    sigma_deg: np.ndarray
    rms_px: float
    rms_px_other: float
    corners: int
    detection: TargetDetection | None = None


def _residual_px(rv, tv, p_O, xy, f: float) -> float:
    proj, _ = cv2.projectPoints(p_O, rv, tv, np.eye(3), None)
    return float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - xy) ** 2, axis=1)))) * f


def _check_detection(det: TargetDetection) -> None:
    """A detection the pose can rest on: (N, 2) pixels, (N, 3) points, finite, ``MIN_CORNERS`` or more, no line."""
    uv, p = np.asarray(det.uv, float), np.asarray(det.p_O, float)
    if uv.ndim != 2 or uv.shape[1] != 2 or p.shape != (len(uv), 3):
        raise ValueError(f"target detection: expected uv (N, 2) and p_O (N, 3), got {uv.shape} and {p.shape}")
    if len(uv) < MIN_CORNERS:
        raise CalibrationError(f"target pose: {len(uv)} corner(s), at least {MIN_CORNERS} needed")
    if not (np.all(np.isfinite(uv)) and np.all(np.isfinite(p))):
        raise CalibrationError("target pose: a corner's pixel or target point is not finite")
    s = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    if not s[1] > 1e-2 * s[0]:
        raise CalibrationError("target pose: the corners lie on one line; they do not fix the pose")


def object_pose(image: np.ndarray, camera: CameraModel, obj: ObjectSpec | TargetSpec,
                detection: TargetDetection | None = None) -> ObjectPose:
    """``C_H_O`` (4, 4) of the object's target in ``image`` (eq. 3-4: corners undistorted by ``camera``, IPPE on the
    normalised rays, Levenberg-Marquardt refinement). Raises ``CalibrationError``: target not seen or seen twice, a
    ``detection`` of fewer than ``MIN_CORNERS``, non-finite or collinear corners, or ambiguous (IPPE's flip fits within
    ``AMBIGUITY_RATIO`` times the chosen residual); ``ValueError`` for ``detection`` arrays not (N, 2) and (N, 3)."""
    target = obj.target if isinstance(obj, ObjectSpec) else obj
    det = detection if detection is not None else detect_target(image, target)
    _check_detection(det)
    f = float(camera.f)
    p = np.ascontiguousarray(det.p_O, np.float64)
    q = np.ascontiguousarray(camera.undistort_pixels(det.uv) / f, np.float64)  # distortion-free rays (X / f, Y / f)
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(p, q, np.eye(3), None, flags=cv2.SOLVEPNP_IPPE)
    if n < 1:
        raise CalibrationError("target seen but no pose fits its corners")
    sols = []
    for rv, tv in zip(rvecs, tvecs):
        rv, tv = cv2.solvePnPRefineLM(p, q, np.eye(3), None, rv.copy(), tv.copy())
        if tv[2, 0] > 0:
            sols.append((_residual_px(rv, tv, p, q, f), rv, tv))
    if not sols:
        raise CalibrationError("target seen but every pose fitting it lies behind the camera")
    sols.sort(key=lambda s: s[0])
    rms, rv, tv = sols[0]
    other = sols[1][0] if len(sols) > 1 else float("inf")
    if other < AMBIGUITY_RATIO * max(rms, 0.02):
        raise CalibrationError(f"target pose ambiguous: the flipped solution fits with {other:.3f} px against "
                               f"{rms:.3f} px (needs {AMBIGUITY_RATIO:g} times more); seen too small or too frontal")
    _, J = cv2.projectPoints(p, rv, tv, np.eye(3), None)
    J = J[:, :6] * f
    s2 = (rms ** 2) * 2 * len(p) / max(2 * len(p) - 6, 1)  # per degree of freedom
    try:
        cov = np.linalg.inv(J.T @ J) * s2
    except np.linalg.LinAlgError:
        raise CalibrationError("target pose: its corners do not fix the pose (degenerate)") from None
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    C_H_O = H_from_rotvec(rv.reshape(3), tv.reshape(3))
    return ObjectPose(C_H_O, sd[3:], np.degrees(sd[:3]), rms, float(other), len(p), det)

