"""The cell description (``cell.yaml``) as typed, validated objects. Unknown, missing, mistyped or impossible values
raise ``ConfigError`` naming the key path, value and what was expected; keys beyond the reference file have defaults."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from selfview.maths.camera import CameraModel
from selfview.errors import ConfigError
from selfview.maths.geometry import check_rigid
from selfview.files.io_safe import MAX_YAML_BYTES, load_yaml, load_yaml_file, read_bounded, short_repr

__all__ = ["POINT_NAMES", "CameraSpec", "PlateSpec", "GripperSpec", "MonitorLimits", "Limit", "ImageSpec",
           "DisturbanceSpec", "SimulationSpec", "Cell", "load_cell", "parse_cell", "default_cell_path",
           "aruco_dictionary", "fingertip_points_G", "Section"]

#: The plate patterns ``selfview.measurement.plates.detect_plate`` measures.
PLATE_PATTERNS = ("discs", "chessboard", "charuco")
#: The six fingertip calibration points of CONVENTIONS.md, in their order.
POINT_NAMES: tuple[str, ...] = ("A-inner-front", "A-inner-back", "B-inner-front", "B-inner-back", "A-outer-front",
                                "B-outer-front")
#: The largest magnitude of any number of a cell file (mm, degrees, grey levels); a larger one is corrupted.
MAX_NUMBER = 1e9


class Section:
    """One YAML mapping, each key checked (``ConfigError`` naming its path); ``done()`` refuses keys not read."""

    def __init__(self, data: Any, path: str):
        if not isinstance(data, dict):
            raise ConfigError(f"{path or 'cell'}: expected a mapping, got {type(data).__name__} {short_repr(data)}")
        self.data = data
        self.path = path
        self.used: set[str] = set()

    def _key(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def has(self, key: str) -> bool:
        return key in self.data

    def raw(self, key: str, default: Any = ...) -> Any:
        self.used.add(key)
        if key not in self.data:
            if default is ...:
                raise ConfigError(f"{self._key(key)}: missing key")
            return default
        return self.data[key]

    def section(self, key: str, default: Any = ...) -> "Section":
        v = self.raw(key, default)
        return Section({} if v is None else v, self._key(key))

    def number(self, key: str, default: Any = ..., *, positive=False, lo=None, hi=None) -> float:
        v = self.raw(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ConfigError(f"{self._key(key)}: expected a number, got {short_repr(v)}")
        v = self._plausible(key, v)
        if positive and v <= 0:
            raise ConfigError(f"{self._key(key)}: expected a positive number, got {v!r}")
        if lo is not None and v < lo:
            raise ConfigError(f"{self._key(key)}: expected a number >= {lo}, got {v!r}")
        if hi is not None and v > hi:
            raise ConfigError(f"{self._key(key)}: expected a number <= {hi}, got {v!r}")
        return v

    def integer(self, key: str, default: Any = ..., *, positive=False) -> int:
        v = self.raw(key, default)
        if isinstance(v, bool) or not isinstance(v, int):
            raise ConfigError(f"{self._key(key)}: expected a whole number, got {v!r}")
        if positive and v <= 0:
            raise ConfigError(f"{self._key(key)}: expected a positive whole number, got {v!r}")
        if abs(v) > MAX_NUMBER:
            raise ConfigError(f"{self._key(key)}: the number {short_repr(v)} is not a plausible value "
                              f"(over {MAX_NUMBER:g})")
        return int(v)

    def string(self, key: str, default: Any = ..., choices=None) -> str:
        v = self.raw(key, default)
        if not isinstance(v, str):
            raise ConfigError(f"{self._key(key)}: expected text, got {v!r}")
        if choices is not None and v not in choices:
            raise ConfigError(f"{self._key(key)}: expected one of {', '.join(choices)}, got {v!r}")
        return v

    def vector(self, key: str, n: int, default: Any = ...) -> tuple[float, ...]:
        v = self.raw(key, default)
        if not isinstance(v, (list, tuple)) or len(v) != n or any(isinstance(x, bool) or not isinstance(x, (int, float))
                                                                  for x in v):
            raise ConfigError(f"{self._key(key)}: expected a list of {n} numbers, got {short_repr(v)}")
        return tuple(self._plausible(key, x) for x in v)

    def _plausible(self, key: str, v) -> float:
        """``v`` as a finite float of at most ``MAX_NUMBER`` (no value of a cell comes near); else ``ConfigError``."""
        try:
            v = float(v)
        except OverflowError:
            raise ConfigError(f"{self._key(key)}: the number {short_repr(v)} is too large") from None
        if not np.isfinite(v):
            raise ConfigError(f"{self._key(key)}: expected a finite number, got {v!r}")
        if abs(v) > MAX_NUMBER:
            raise ConfigError(f"{self._key(key)}: the number {v!r} is not a plausible value (over {MAX_NUMBER:g})")
        return v

    def transform(self, key: str, default: Any = ...) -> np.ndarray:
        v = self.raw(key, default)
        try:
            H = check_rigid(v, self._key(key))
        except OverflowError:
            raise ConfigError(f"{self._key(key)}: a number is too large for a transform") from None
        if np.max(np.abs(H[:3, 3])) > MAX_NUMBER:  # a rotation is bounded by being one; a translation is not
            raise ConfigError(f"{self._key(key)}: the translation {short_repr(H[:3, 3].tolist())} mm is not a "
                              f"plausible value (over {MAX_NUMBER:g})")
        return H

    def done(self) -> None:
        if unknown := sorted(set(self.data) - self.used):
            raise ConfigError(f"{self.path or 'cell'}: unknown key(s) {', '.join(map(str, unknown))}; "
                              f"expected only {', '.join(sorted(self.used))}")


@dataclass(frozen=True)
class CameraSpec:
    model: str
    width: int
    height: int
    principal_point: tuple[float, float]
    aspect: float
    focal_guess: float
    kappa_guess: float

    def guess(self) -> CameraModel:
        """Camera model from the guesses (a starting value; calibration measures f and kappa)."""
        return CameraModel(f=self.focal_guess, kappa=self.kappa_guess, cx=self.principal_point[0],
                           cy=self.principal_point[1], aspect=self.aspect, width=self.width, height=self.height)


@dataclass(frozen=True)
class PlateSpec:
    """The calibration plate: ``rows`` x ``cols`` plate points (disc centres; a board's inner corners) at ``pitch``
    mm, centred on W's origin; ``pattern`` one of ``PLATE_PATTERNS``; a board's ``squares`` (NX, NY) of ``pitch`` mm,
    its ArUco ``marker`` side [mm], ``dictionary`` and ``legacy_pattern``; ``disc_diameter`` [mm], 0 for a board."""
    rows: int
    cols: int
    pitch: float
    disc_diameter: float
    size: tuple[float, float]
    polarity: str
    pattern: str = "discs"
    squares: tuple[int, int] = (0, 0)
    marker: float = 0.0
    dictionary: str = ""
    legacy_pattern: bool = False

    def disc_centres_W(self) -> np.ndarray:
        """(rows*cols, 3) disc centres in W [mm], row-major (index = row * cols + col), grid centred on 0."""
        r, c = np.mgrid[0 : self.rows, 0 : self.cols]
        x = (c.ravel() - (self.cols - 1) / 2) * self.pitch
        y = (r.ravel() - (self.rows - 1) / 2) * self.pitch
        return np.column_stack([x, y, np.zeros_like(x)])


def fingertip_points_G(gap: float, width: float, thickness_A: float, thickness_B: float) -> np.ndarray:
    """(6, 3) fingertip points in G in ``POINT_NAMES`` order for a jaw ``gap``, finger ``width``, thicknesses [mm]."""
    g, w = gap, width
    return np.array([[g / 2, -w / 2, 0.0], [g / 2, w / 2, 0.0], [-g / 2, -w / 2, 0.0], [-g / 2, w / 2, 0.0],
                     [g / 2 + thickness_A, -w / 2, 0.0], [-g / 2 - thickness_B, -w / 2, 0.0]])


@dataclass(frozen=True)
class GripperSpec:
    finger_width: float
    finger_thickness: float
    finger_length: float
    states: dict[str, float]
    calibrate_in: str

    def gap(self, state: str) -> float:
        try:
            return self.states[state]
        except KeyError:
            raise ConfigError(f"gripper state {state!r}: expected one of {', '.join(self.states)}") from None

    def points_G(self, state: str | None = None, gap: float | None = None) -> np.ndarray:
        """(6, 3) nominal fingertip points in G [mm], in the order of ``POINT_NAMES``."""
        g = self.gap(state or self.calibrate_in) if gap is None else float(gap)
        return fingertip_points_G(g, self.finger_width, self.finger_thickness, self.finger_thickness)

    def finger_boxes_G(self, gap: float) -> list[tuple[np.ndarray, np.ndarray]]:
        """[(min corner, max corner)] of fingers A and B in G [mm] for a jaw gap."""
        g, w, t, L = gap, self.finger_width, self.finger_thickness, self.finger_length
        return [(np.array([g / 2, -w / 2, -L]), np.array([g / 2 + t, w / 2, 0.0])),
                (np.array([-g / 2 - t, -w / 2, -L]), np.array([-g / 2, w / 2, 0.0]))]


@dataclass(frozen=True)
class Limit:
    angle_deg: float
    shift_mm: float


@dataclass(frozen=True)
class MonitorLimits:
    update_limit: Limit
    alarm_limit: Limit
    max_rms_px: float = 1.5  # residual above which the model no longer fits (project default)
    max_missed_frames: int = 3  # frames in a row without the fingertips (not found, lost, no picture) before the alarm


@dataclass(frozen=True)
class ImageSpec:
    noise_gray: float
    blur_px: float
    paper: float
    ink: float
    foam: float
    finger: tuple[float, float, float]


@dataclass(frozen=True)
class DisturbanceSpec:
    name: str
    pivot_C: tuple[float, float, float]
    axis_C: tuple[float, float, float]
    axis_jitter_deg: float
    tcp_shift_mm: float
    tcp_shift_sd_mm: float


@dataclass(frozen=True)
class SimulationSpec:
    true_f: float
    true_kappa: float
    mount_error_angle_deg: float
    mount_error_shift_mm: float
    image: ImageSpec
    disturbances: dict[str, DisturbanceSpec]


@dataclass(frozen=True)
class RobotSpec:
    """The optional ``robot:`` section: the driver's settings files (relative to the cell file), ``max_speed`` [%]."""
    dialect: str | None = None
    limits: str | None = None
    kinematics: str | None = None
    max_speed: float | None = None


def _parse_robot(s: Section, source: str) -> RobotSpec:
    base = Path(source).parent if source and not source.startswith("<") else Path(".")

    def path(key):
        v = s.raw(key, None)
        if v is None:
            return None
        if not isinstance(v, str) or not v.strip():
            raise ConfigError(f"robot.{key}: expected a file name, got {short_repr(v)}")
        return str(base / v)

    spec = RobotSpec(dialect=path("dialect"), limits=path("limits"), kinematics=path("kinematics"),
                     max_speed=s.number("max_speed", None, lo=1.0, hi=100.0) if s.has("max_speed") else None)
    s.done()
    return spec


@dataclass(frozen=True)
class Cell:
    """The whole cell description. ``source`` is the file it came from, ``sha256`` its hash."""
    camera: CameraSpec
    plate: PlateSpec
    gripper: GripperSpec
    mount_guess_C_H_G: np.ndarray
    monitor: MonitorLimits
    simulation: SimulationSpec | None
    source: str = "<memory>"
    sha256: str = ""
    raw: dict = field(default_factory=dict, repr=False)
    robot: RobotSpec | None = None

    def camera_guess(self) -> CameraModel:
        return self.camera.guess()


def _parse_camera(s: Section) -> CameraSpec:
    spec = CameraSpec(model=str(s.raw("model", "")), width=s.integer("width", positive=True),
                      height=s.integer("height", positive=True), principal_point=s.vector("principal_point", 2),
                      aspect=s.number("aspect", 1.0, lo=0.5, hi=2.0),
                      focal_guess=s.number("focal_guess", lo=1.0, hi=1e5),
                      kappa_guess=s.number("kappa_guess", 0.0, lo=-1e-4, hi=1e-4))
    s.done()
    if spec.width > 16384 or spec.height > 16384:
        raise ConfigError(f"camera: {spec.width} x {spec.height} px is not a picture size (at most 16384 a side)")
    cx, cy = spec.principal_point
    if not (0 <= cx <= spec.width - 1 and 0 <= cy <= spec.height - 1):
        raise ConfigError(f"camera.principal_point: {list(spec.principal_point)} lies outside the "
                          f"{spec.width}x{spec.height} picture")
    return spec


def _parse_plate(s: Section) -> PlateSpec:
    pattern = s.string("pattern", "discs", choices=PLATE_PATTERNS)
    if pattern != "discs":
        return _parse_board(s, pattern)
    spec = PlateSpec(rows=s.integer("rows", positive=True), cols=s.integer("cols", positive=True),
                     pitch=s.number("pitch", positive=True), disc_diameter=s.number("disc_diameter", positive=True),
                     size=s.vector("size", 2),
                     polarity=s.string("polarity", "dark_on_light", choices=("dark_on_light", "light_on_dark")))
    s.done()
    if spec.rows * spec.cols < 5:
        raise ConfigError(f"plate: {spec.rows}x{spec.cols} discs; Tsai's coplanar method needs at least 5")
    if spec.disc_diameter >= spec.pitch:
        raise ConfigError(f"plate.disc_diameter: {spec.disc_diameter} mm; expected less than the pitch "
                          f"{spec.pitch} mm")
    need = ((spec.cols - 1) * spec.pitch + spec.disc_diameter, (spec.rows - 1) * spec.pitch + spec.disc_diameter)
    if spec.size[0] < need[0] or spec.size[1] < need[1]:
        raise ConfigError(f"plate.size: {list(spec.size)} mm is smaller than the disc grid {list(need)} mm")
    return spec


def _parse_board(s: Section, pattern: str) -> PlateSpec:
    """Chessboard or ChArUco plate: ``squares``, ``square``; ChArUco ``marker``, ``dictionary``, ``legacy_pattern``."""
    sq = s.raw("squares")
    if not (isinstance(sq, (list, tuple)) and len(sq) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) for v in sq)):
        raise ConfigError(f"plate.squares: expected [NX, NY], two whole numbers of squares, got {short_repr(sq)}")
    nx, ny = int(sq[0]), int(sq[1])
    if nx < 3 or ny < 3 or nx > 100 or ny > 100:
        raise ConfigError(f"plate.squares: {nx}x{ny}; expected 3 to 100 squares a side (a board's inner corners "
                          "must hold at least 2x2 points)")
    square = s.number("square", positive=True)
    marker, dictionary, legacy = 0.0, "", False
    if pattern == "charuco":
        marker = s.number("marker", positive=True)
        if marker >= square:
            raise ConfigError(f"plate.marker: {marker} mm; expected less than the square {square} mm")
        dictionary = s.string("dictionary")
        legacy = s.raw("legacy_pattern", False)
        if not isinstance(legacy, bool):
            raise ConfigError(f"plate.legacy_pattern: expected true or false, got {short_repr(legacy)}")
    board = (nx * square, ny * square)
    size = s.vector("size", 2, (board[0] + 2 * square, board[1] + 2 * square))
    if size[0] < board[0] or size[1] < board[1]:
        raise ConfigError(f"plate.size: {list(size)} mm is smaller than the board {list(board)} mm")
    s.done()
    spec = PlateSpec(rows=ny - 1, cols=nx - 1, pitch=square, disc_diameter=0.0, size=size, polarity="dark_on_light",
                     pattern=pattern, squares=(nx, ny), marker=marker, dictionary=dictionary, legacy_pattern=legacy)
    if pattern == "charuco":
        _check_dictionary(spec)
    return spec


def aruco_dictionary(name: str, what: str = "plate.dictionary") -> int:
    """OpenCV's code of the predefined ArUco dictionary ``name`` ('DICT_4X4_50', ...); else ``ConfigError``."""
    import cv2

    code = getattr(cv2.aruco, name, None) if isinstance(name, str) and name.startswith("DICT_") else None
    if not isinstance(code, int):
        known = sorted(k for k in dir(cv2.aruco) if k.startswith("DICT_"))
        raise ConfigError(f"{what}: {name!r} is not an OpenCV predefined dictionary; expected one of "
                          f"{', '.join(known)}")
    return code


def _check_dictionary(spec: PlateSpec) -> None:
    """The ChArUco plate's dictionary is an OpenCV predefined one holding the board's markers."""
    import cv2

    name = spec.dictionary
    size = cv2.aruco.getPredefinedDictionary(aruco_dictionary(name)).bytesList.shape[0]
    need = spec.squares[0] * spec.squares[1] // 2
    if size < need:
        raise ConfigError(f"plate.dictionary: {name} holds {size} markers; a {spec.squares[0]}x{spec.squares[1]} "
                          f"ChArUco board needs {need}")


def parse_plate(data: Any) -> PlateSpec:
    """The ``plate:`` mapping of a cell or plate file, validated; raises ``ConfigError``."""
    return _parse_plate(Section(data, "plate"))


def load_plate(path) -> PlateSpec:
    """The plate of a YAML file with a ``plate:`` section (a plate or cell file); ``ConfigError`` naming the file."""
    p = Path(path)
    data = load_yaml_file(p, error=ConfigError, what="plate file")
    if not isinstance(data, dict) or "plate" not in data:
        raise ConfigError(f"plate file {str(p)!r}: expected a mapping with a 'plate:' section")
    try:
        return parse_plate(data["plate"])
    except ConfigError as exc:
        raise ConfigError(f"{p.name}: {exc}") from None


def _parse_gripper(s: Section) -> GripperSpec:
    w = s.number("finger_width", positive=True)
    t = s.number("finger_thickness", positive=True)
    L = s.number("finger_length", positive=True)
    st = s.section("states")
    states = {str(name): st.number(name, positive=True) for name in list(st.data)}
    st.done()
    if not states:
        raise ConfigError("gripper.states: expected at least one state with its jaw gap")
    cal = s.string("calibrate_in", choices=tuple(states))
    s.done()
    return GripperSpec(finger_width=w, finger_thickness=t, finger_length=L, states=states, calibrate_in=cal)


def _parse_limit(s: Section) -> Limit:
    lim = Limit(angle_deg=s.number("angle_deg", positive=True), shift_mm=s.number("shift_mm", positive=True))
    s.done()
    return lim


def _parse_monitor(s: Section) -> MonitorLimits:
    up = _parse_limit(s.section("update_limit"))
    al = _parse_limit(s.section("alarm_limit"))
    rms = s.number("max_rms_px", 1.5, positive=True)
    missed = s.integer("max_missed_frames", 3, positive=True)
    s.done()
    if al.angle_deg < up.angle_deg or al.shift_mm < up.shift_mm:
        raise ConfigError(f"monitor.alarm_limit: {al} must not be below monitor.update_limit {up}")
    return MonitorLimits(update_limit=up, alarm_limit=al, max_rms_px=rms, max_missed_frames=missed)


def _parse_simulation(s: Section) -> SimulationSpec:
    tc = s.section("true_camera")
    f = tc.number("f", positive=True)
    kappa = tc.number("kappa")
    tc.done()
    me = s.section("mount_error")
    me_a = me.number("angle_deg", lo=0)
    me_s = me.number("shift_mm", lo=0)
    me.done()
    im = s.section("image")
    image = ImageSpec(noise_gray=im.number("noise_gray", lo=0), blur_px=im.number("blur_px", lo=0),
                      paper=im.number("paper", lo=0, hi=255), ink=im.number("ink", lo=0, hi=255),
                      foam=im.number("foam", lo=0, hi=255), finger=im.vector("finger", 3))
    im.done()
    for i, v in enumerate(image.finger):
        if not 0 <= v <= 255:
            raise ConfigError(f"simulation.image.finger[{i}]: expected a grey level 0..255, got {v}")
    ds = s.section("disturbances")
    dists = {}
    for name in list(ds.data):
        d = ds.section(name)
        spec = DisturbanceSpec(name=str(name), pivot_C=d.vector("pivot_C", 3), axis_C=d.vector("axis_C", 3),
                               axis_jitter_deg=d.number("axis_jitter_deg", lo=0),
                               tcp_shift_mm=d.number("tcp_shift_mm", lo=0),
                               tcp_shift_sd_mm=d.number("tcp_shift_sd_mm", lo=0))
        d.done()
        if np.linalg.norm(spec.axis_C) == 0:
            raise ConfigError(f"simulation.disturbances.{name}.axis_C: expected a non-zero axis, "
                              f"got {list(spec.axis_C)}")
        dists[str(name)] = spec
    ds.done()
    s.done()
    return SimulationSpec(true_f=f, true_kappa=kappa, mount_error_angle_deg=me_a, mount_error_shift_mm=me_s,
                          image=image, disturbances=dists)


def parse_cell(data: Any, source: str = "<memory>", sha256: str = "") -> Cell:
    """Build a ``Cell`` from an already parsed YAML mapping; raises ``ConfigError``."""
    top = Section(data, "")
    camera = _parse_camera(top.section("camera"))
    plate = _parse_plate(top.section("plate"))
    gripper = _parse_gripper(top.section("gripper"))
    mg = top.section("mount_guess")
    C_H_G = mg.transform("C_H_G")
    mg.done()
    if C_H_G[2, 3] <= 0:
        raise ConfigError(f"mount_guess.C_H_G: the TCP must lie in front of the camera (z > 0), got z={C_H_G[2, 3]}")
    monitor = _parse_monitor(top.section("monitor"))
    sim = _parse_simulation(top.section("simulation")) if top.has("simulation") else None
    robot = _parse_robot(top.section("robot"), source) if top.has("robot") else None
    top.done()
    return Cell(camera=camera, plate=plate, gripper=gripper, mount_guess_C_H_G=C_H_G, monitor=monitor,
                simulation=sim, robot=robot, source=source, sha256=sha256, raw=data)


def load_cell(path) -> Cell:
    """Read and validate a cell description file; raises ``ConfigError`` naming what is wrong."""
    p = Path(path)
    src = f"cell description {str(p)!r}"
    blob = read_bounded(p, MAX_YAML_BYTES, error=ConfigError, what="cell description", source=src)
    data = load_yaml(blob, src, error=ConfigError, what="file")
    if data is None:
        raise ConfigError(f"{src}: the file is empty")
    try:
        return parse_cell(data, source=str(p), sha256=hashlib.sha256(blob).hexdigest())
    except ConfigError as exc:
        raise ConfigError(f"{p.name}: {exc}") from None


def default_cell_path() -> Path:
    """The reference cell that ships with the package (a copy of the shared ``cell.yaml``)."""
    return Path(__file__).resolve().parents[1] / "data" / "cell.yaml"
