"""Calibration files: YAML (``format: selfview-calibration``, ``version: 1``) of a ``Calibration`` and a checksum over
all of it; writes are atomic and keep the previous file; a file not a calibration's is refused, never overwritten."""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import yaml

from selfview import __version__
from selfview.maths.camera import CameraModel
from selfview.files.cell import POINT_NAMES
from selfview.errors import CalibrationFileError, ConfigError
from selfview.maths.geometry import check_rigid
from selfview.files.io_safe import (MAX_YAML_BYTES, atomic_write, check_folder, file_lock, load_yaml, read_bounded,
                                    remove_leftovers, short_repr)
from selfview.estimation.tsai import MODES as TSAI_MODES

__all__ = ["Calibration", "save_calibration", "load_calibration", "history_dir", "FORMAT", "VERSION"]

FORMAT = "selfview-calibration"
VERSION = 1


@dataclass
class Calibration:
    """An off-line calibration and its on-line updates: ``camera``; ``C_H_W``, ``C_H_G`` (4, 4) [mm]; ``points_G``
    state -> (6, 3) points in G [mm] (POINT_NAMES order); ``state`` the picture's jaw state; ``residuals`` figures
    (rms_px, max_px, ...); ``image_sha256``, ``cell_sha256``; ``created`` ISO time; ``software`` version; ``updates``
    (method, time, delta_deg, d_mm); ``pictures`` role -> file name beside this file."""
    camera: CameraModel
    C_H_W: np.ndarray
    C_H_G: np.ndarray
    points_G: dict[str, np.ndarray]
    state: str
    residuals: dict[str, Any] = field(default_factory=dict)
    image_sha256: str = ""
    cell_sha256: str = ""
    created: str = ""
    software: str = __version__
    updates: list[dict[str, Any]] = field(default_factory=list)
    pictures: dict[str, str] = field(default_factory=dict)
    #: SHA-256 of the file read from ("" if none), what a save passing this as ``expected`` may replace; not a field.
    file_sha256: ClassVar[str] = ""

    def to_document(self) -> dict:
        points_G = {st: {nm: [float(v) for v in p] for nm, p in zip(POINT_NAMES, np.asarray(P, float))}
                    for st, P in self.points_G.items()}
        doc = {"format": FORMAT, "version": VERSION, "created": self.created or _now(),
               "software": f"selfview {self.software}", "cell_sha256": self.cell_sha256,
               "image_sha256": self.image_sha256, "camera": self.camera.to_dict(), "C_H_W": _mat(self.C_H_W),
               "C_H_G": _mat(self.C_H_G), "gripper": {"state": self.state, "points_G": points_G},
               "residuals": plain_data(self.residuals), "updates": plain_data(self.updates)}
        if self.pictures:
            doc["pictures"] = {str(k): str(v) for k, v in self.pictures.items()}
        doc["checksum"] = doc_checksum(doc)
        return doc

    @classmethod
    def from_document(cls, doc: Any, source: str = "<memory>") -> "Calibration":
        check_document(doc, FORMAT, VERSION, "calibration file", source, redo="recalibrate")
        try:
            _check_types(doc)
            camera = CameraModel.from_dict(doc["camera"])  # no skew: 0, the spec's model
            _plausible_camera(camera)
            pts = {}
            for st, d in doc["gripper"]["points_G"].items():
                pts[st] = np.array([d[nm] for nm in POINT_NAMES], dtype=float).reshape(6, 3)
                if not np.all(np.isfinite(pts[st])):
                    raise ValueError(f"gripper points_G {short_repr(st)} holds a non-finite number")
                if np.max(np.abs(pts[st])) > MAX_LENGTH_MM:
                    raise ValueError(f"gripper points_G {short_repr(st)} lie over {MAX_LENGTH_MM:g} mm from the TCP")
                _check_fingertip_shape(pts[st], f"gripper points_G {short_repr(st, 30)}")
            C_H_W = check_rigid(doc["C_H_W"], f"{source}: C_H_W")
            C_H_G = check_rigid(doc["C_H_G"], f"{source}: C_H_G")
            for name, H in (("C_H_W", C_H_W), ("C_H_G", C_H_G)):
                if np.linalg.norm(H[:3, 3]) > MAX_LENGTH_MM:
                    raise ValueError(f"{name} puts its origin over {MAX_LENGTH_MM:g} mm from the camera")
            _plausible_figures(doc.get("residuals") or {}, "residuals")  # types: _check_types
            return cls(camera=camera, C_H_W=C_H_W, C_H_G=C_H_G, points_G=pts, state=str(doc["gripper"]["state"]),
                       residuals=dict(doc.get("residuals") or {}), image_sha256=str(doc.get("image_sha256", "")),
                       cell_sha256=str(doc.get("cell_sha256", "")), created=str(doc.get("created", "")),
                       software=str(doc.get("software", "")).removeprefix("selfview "),
                       updates=list(doc.get("updates") or []),
                       pictures={str(k): str(v) for k, v in (doc.get("pictures") or {}).items()})
        except (KeyError, TypeError, ValueError, IndexError, AttributeError, OverflowError, ConfigError) as exc:
            what = f"missing key {exc}" if isinstance(exc, KeyError) else f"{type(exc).__name__}: {exc}"
            raise CalibrationFileError(f"{source}: malformed calibration file "
                                       f"({short_repr(what, 200)[1:-1]})") from None


#: A length [mm] over this is a corrupted number: a wrist camera sees its fingertips from a few hundred mm.
MAX_LENGTH_MM = 10_000.0


def _plausible_camera(cam: CameraModel) -> None:
    """Refuse camera values no camera has (a corrupted number that still parses): ``ValueError`` naming it."""
    if not 0 < cam.width <= 16384 or not 0 < cam.height <= 16384:
        raise ValueError(f"camera size {cam.width} x {cam.height} px is not a picture size")
    if not 1.0 <= cam.f <= 1e5:
        raise ValueError(f"camera f = {cam.f} px is not a focal length (1 to 100000 px)")
    if abs(cam.kappa) * (cam.width ** 2 + cam.height ** 2) / 4 > 1.0:
        raise ValueError(f"camera kappa = {cam.kappa} px^-2 is not a lens distortion (it more than doubles the "
                         "corners' radius)")
    if not (-0.5 <= cam.cx <= cam.width - 0.5 and -0.5 <= cam.cy <= cam.height - 0.5):
        raise ValueError(f"camera principal point ({cam.cx}, {cam.cy}) lies outside the {cam.width} x {cam.height} "
                         "picture")
    if not 0.5 <= cam.aspect <= 2.0:
        raise ValueError(f"camera aspect = {cam.aspect} is not a pixel aspect (0.5 to 2)")


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _check_types(doc: dict) -> None:
    """``ValueError`` unless each field has its written type (a re-checksummed file may have changed one)."""
    cam = doc["camera"]
    for k in ("f", "kappa", "aspect") + (("skew",) if "skew" in cam else ()):
        if not _is_number(cam[k]):
            raise ValueError(f"camera {k} is {short_repr(cam[k], 40)}, not a number")
    pp = cam["principal_point"]
    if not (isinstance(pp, list) and len(pp) == 2 and all(_is_number(x) for x in pp)):
        raise ValueError(f"camera principal_point is {short_repr(pp, 60)}, not two numbers")
    for k in ("width", "height"):
        if not isinstance(cam[k], int) or isinstance(cam[k], bool):
            raise ValueError(f"camera {k} is {short_repr(cam[k], 40)}, not a whole number")
    for name in ("C_H_W", "C_H_G"):
        H = doc[name]
        if not (isinstance(H, list) and len(H) == 4 and all(isinstance(r, list) and len(r) == 4 and
                                                          all(_is_number(x) for x in r) for r in H)):
            raise ValueError(f"{name} is not a 4x4 matrix of numbers")
    grip = doc["gripper"]
    pts = grip["points_G"]
    if not isinstance(pts, dict) or not pts:
        raise ValueError("gripper points_G is not a table of jaw states")
    for st, table in pts.items():
        if not (isinstance(table, dict) and set(table) == set(POINT_NAMES) and all(
                isinstance(v, list) and len(v) == 3 and all(_is_number(x) for x in v) for v in table.values())):
            raise ValueError(f"gripper points_G {short_repr(st, 30)} is not the six named points of three numbers")
    if not isinstance(grip["state"], str) or grip["state"] not in pts:
        raise ValueError(f"gripper state {short_repr(grip['state'], 40)} is not one of the jaw states {sorted(pts)}")
    # provenance is never computed with, but a file whose hash or version changed type is not the file it was
    if type(doc.get("version")) is not int:  # True == 1 in Python
        raise ValueError(f"version is {short_repr(doc.get('version'), 40)}, not a whole number")
    for k in ("image_sha256", "cell_sha256"):
        v = doc.get(k, "")
        if not (isinstance(v, str) and (v == "" or (len(v) == 64 and all(c in "0123456789abcdef" for c in v)))):
            raise ValueError(f"{k} is {short_repr(v, 80)}, not a SHA-256 in hex (or empty)")
    for k in ("created", "software"):
        if k in doc and not isinstance(doc[k], str):
            raise ValueError(f"{k} is {short_repr(doc[k], 40)}, not text")
    ups = doc.get("updates", [])
    if not (isinstance(ups, list) and all(isinstance(u, dict) for u in ups)):
        raise ValueError(f"updates is {short_repr(ups, 60)}, not a list of records")
    _figure_types(doc.get("residuals", {}), "residuals")


#: Tolerance [mm] on CONVENTIONS' fingertip shape: measured fingers differ by tenths of a mm, a replaced number by mm.
SHAPE_TOLERANCE_MM = 2.0


def _check_fingertip_shape(table: np.ndarray, where: str) -> None:
    """``ValueError`` naming what is off unless the (6, 3) points of one jaw state have that shape."""
    aif, aib, bif, bib, aof, bof = P = np.asarray(table, dtype=float).reshape(6, 3)
    checks = (("the points out of the tip plane z = 0", float(np.max(np.abs(P[:, 2])))),
              ("the rectangle of points 1-4 off the TCP", float(np.linalg.norm((aif + aib + bif + bib)[:2] / 4))),
              ("the fingers' widths unequal", abs(np.linalg.norm(aib - aif) - np.linalg.norm(bib - bif))),
              ("the gap unequal at front and back", abs(np.linalg.norm(bif - aif) - np.linalg.norm(bib - aib))),
              ("the fingers' thicknesses unequal", abs(np.linalg.norm(aof - aif) - np.linalg.norm(bof - bif))),
              ("finger A not on the +x side", max(0.0, -min(aif[0], aib[0], aof[0] - aif[0]))))
    for what, off in checks:
        if not off <= SHAPE_TOLERANCE_MM:
            raise ValueError(f"{where}: {what} by {off:.2f} mm (more than {SHAPE_TOLERANCE_MM:g} mm: not a fingertip "
                             "shape; see CONVENTIONS' fingertip points)")


def _figure_types(res: dict, where: str) -> None:
    """``ValueError`` unless the figures the calibration writes have their types (others are only shown)."""
    if not isinstance(res, dict):
        raise ValueError(f"{where} is not a table of figures")
    names = set(POINT_NAMES)
    checks = {
        "rms_px": _is_number, "max_px": _is_number, "pcc_rms_mm": _is_number, "pcc_q_norm": _is_number,
        "discs_used": lambda v: isinstance(v, int) and not isinstance(v, bool), "tsai_mode": lambda v: v in TSAI_MODES,
        "points_from": lambda v: v in ("picture", "cell"), "corners_measured_by": lambda v: v in ("corners", "model"),
        "corners_found": lambda v: isinstance(v, list) and all(isinstance(x, str) and x in names for x in v),
        "corner_edge_rms_px": lambda v: isinstance(v, dict) and all(k in names and _is_number(x) for k, x in v.items()),
        "camera_file": lambda v: isinstance(v, dict) and all(isinstance(v.get(k), str) for k in ("path", "sha256"))}
    for key, ok in checks.items():
        if key in res and not ok(res[key]):
            raise ValueError(f"{where}.{key} is {short_repr(res[key], 60)}, not what the calibration writes there")


def _plausible_figures(x, where: str) -> None:
    """Every number in a nested figure (residuals: px, mm, counts) finite and under 1e6."""
    if isinstance(x, dict):
        for k, v in x.items():
            _plausible_figures(v, f"{where}.{k}")
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            _plausible_figures(v, f"{where}[{i}]")
    elif _is_number(x) and not (math.isfinite(x) and abs(x) < 1e6):
        raise ValueError(f"{short_repr(where, 80)} is {short_repr(x, 40)}, not a plausible figure")


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _mat(H) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(H, float)]


def plain_data(x):
    """Convert numpy scalars/arrays in nested containers to plain Python for YAML/JSON."""
    if isinstance(x, dict):
        return {str(k): plain_data(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [plain_data(v) for v in x]
    return x.tolist() if isinstance(x, (np.ndarray, np.generic)) else x  # plain Python numbers, nested lists


def check_document(doc, fmt: str, version: int, kind: str, source: str, *, redo: str, hint: str = "") -> None:
    """``CalibrationFileError`` naming ``source`` unless ``doc`` is a mapping of format ``fmt`` and ``version``
    whose checksum holds; ``kind`` names the file, ``redo`` how to make a new one, ``hint`` how to write one."""
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        raise CalibrationFileError(f"{source}: not a selfview {kind} (no 'format: {fmt}'{hint})")
    if doc.get("version") != version:
        raise CalibrationFileError(f"{source}: {kind} version {short_repr(doc.get('version'))}; this selfview reads "
                                   f"version {version}")
    want = doc.get("checksum")
    body = {k: v for k, v in doc.items() if k != "checksum"}
    if want != doc_checksum(body):
        raise CalibrationFileError(f"{source}: checksum mismatch; the {kind} was altered or corrupted ({redo}, or "
                                   "restore a copy from its .history folder)")


def doc_checksum(body: dict) -> str:
    # floats go through repr, which YAML round-trips exactly
    blob = json.dumps(body, sort_keys=True, separators=(",", ":"), default=str)
    return "sha256:" + hashlib.sha256(blob.encode()).hexdigest()


def history_dir(path) -> Path:
    """Folder where the previous versions of a calibration file are kept."""
    p = Path(path)
    return p.with_name(p.name + ".history")


def load_calibration(path) -> Calibration:
    """Read and verify a calibration file; ``CalibrationFileError`` if corrupt, altered, foreign, of another version,
    hostile (YAML aliases, deep nesting, huge numbers) or holding non-finite numbers."""
    p = Path(path)
    blob = read_bounded(p, MAX_YAML_BYTES, error=CalibrationFileError, what="calibration file",
                        missing="no such calibration file (run 'selfview calibrate' first)")
    cal = Calibration.from_document(load_yaml(blob, str(p), error=CalibrationFileError, what="calibration file"),
                                    source=str(p))
    cal.file_sha256 = hashlib.sha256(blob).hexdigest()
    return cal


def save_calibration(cal: Calibration, path, *, keep_history: bool = True,
                     expected: "Calibration | str | None" = None) -> Path:
    """Write ``cal`` by ``replace_keeping_history`` once it reads back; with ``expected`` (the loaded Calibration or its
    file's SHA-256) only over that version (a recalibration saved meanwhile stays). Returns the history copy or None."""
    p = Path(path)
    text = yaml.safe_dump(cal.to_document(), sort_keys=False, default_flow_style=None, width=120)
    # check what we are about to write reads back, before it replaces anything
    Calibration.from_document(load_yaml(text, str(p), error=CalibrationFileError), source=str(p))
    want = expected.file_sha256 if isinstance(expected, Calibration) else expected
    if isinstance(expected, Calibration) and not want:
        raise CalibrationFileError(f"{p}: the expected calibration was not read from a file: nothing to compare with")
    return replace_keeping_history(p, text, load_calibration, what="calibration file", keep_history=keep_history,
                                   expected_sha256=want)


def replace_keeping_history(p: Path, text: str, load_existing, *, what: str, keep_history: bool = True,
                            expected_sha256: str | None = None) -> Path | None:
    """Replace ``p`` with ``text`` atomically under ``file_lock``, the previous file first checked by ``load_existing``
    (it raises for a corrupt or foreign file: it may be somebody else's), kept in ``<name>.history/`` and, with
    ``expected_sha256``, still of that hash. ``CalibrationFileError`` naming the path and cause, ``p`` unchanged."""
    p = Path(os.path.realpath(p)) if Path(p).is_symlink() else Path(p)
    check_folder(p, error=CalibrationFileError, what=what)
    with file_lock(p, error=CalibrationFileError, what=what):
        if expected_sha256 is not None:
            _check_version(p, expected_sha256, what)
        kept = None
        if p.exists():
            load_existing(p)  # refuse to replace a corrupt or foreign file
            kept = _keep_previous(p, what) if keep_history else None
        atomic_write(p, text.encode("utf-8"), error=CalibrationFileError, what=what)
        return kept


def _keep_previous(p: Path, what: str) -> Path:
    """A copy of ``p`` in ``history_dir(p)``, named by its time (UTC) and hash; ``CalibrationFileError``."""
    hd = history_dir(p)
    try:
        hd.mkdir(exist_ok=True)
    except FileExistsError:
        raise CalibrationFileError(f"{hd}: cannot keep the previous {what}: a file of that name exists where its "
                                   f"history folder belongs; {p} is unchanged") from None
    except OSError as exc:
        raise CalibrationFileError(f"{hd}: cannot create the history folder ({exc.strerror or exc}); {p} is "
                                   "unchanged") from None
    remove_leftovers(hd)  # history copies of saves killed half-way
    blob = read_bounded(p, MAX_YAML_BYTES, error=CalibrationFileError, what=f"previous {what}")
    stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
    kept = hd / f"{stamp}-{hashlib.sha256(blob).hexdigest()[:8]}{p.suffix or '.yaml'}"
    atomic_write(kept, blob, error=CalibrationFileError, what=f"history copy of the {what}",
                 mode=stat.S_IMODE(p.stat().st_mode))
    return kept


def _check_version(p: Path, expected_sha256: str, what: str) -> None:
    """``CalibrationFileError`` naming both versions unless ``p`` still hashes to ``expected_sha256``."""
    now = hashlib.sha256(read_bounded(p, MAX_YAML_BYTES, error=CalibrationFileError, what=what)).hexdigest()
    if now != expected_sha256:
        raise CalibrationFileError(f"{p}: changed since it was read: this update derives from version sha256 "
                                   f"{expected_sha256[:12]}, but the file now holds version sha256 {now[:12]} "
                                   "(a recalibration saved meanwhile?); nothing written: run again from the new "
                                   "calibration")
