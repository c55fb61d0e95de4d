"""Calibration files: what an off-line calibration found, kept safe.

A calibration file is a YAML document (``format: selfview-calibration``, ``version: 1``) holding the
interior orientation (f, kappa, principal point, aspect), ``C_H_W`` and ``C_H_G`` (4x4, mm), the gripper
points per state, the residuals, the picture's SHA-256, the time, the software version, the cell file's
hash and a checksum over all of it.

Nothing is lost: a write goes to a temporary file in the same folder, is fsync'ed and renamed over the
old one (atomic on POSIX), and the previous file is first copied into ``<name>.history/``. A file that is
corrupt, altered, foreign or of an unknown version is refused with ``CalibrationFileError``, and is
never overwritten.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from selfview import __version__
from selfview.camera import CameraModel
from selfview.cell import POINT_NAMES
from selfview.errors import CalibrationFileError, ConfigError
from selfview.geometry import check_rigid

__all__ = ["Calibration", "save_calibration", "load_calibration", "history_dir", "FORMAT", "VERSION"]

FORMAT = "selfview-calibration"
VERSION = 1


@dataclass
class Calibration:
    """An off-line calibration and its later on-line updates.

    ``camera`` the interior orientation; ``C_H_W``, ``C_H_G`` (4, 4) [mm]; ``points_G`` state ->
    (6, 3) gripper points in G [mm] (POINT_NAMES order); ``state`` the gripper state of the picture;
    ``residuals`` a mapping of figures (rms_px, max_px, discs_used, ...); ``image_sha256`` of the picture;
    ``cell_sha256`` of the cell file; ``created`` ISO time; ``software`` version; ``updates`` the on-line
    changes applied since (method, time, delta_deg, d_mm).
    """

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

    def to_document(self) -> dict:
        doc = {
            "format": FORMAT,
            "version": VERSION,
            "created": self.created or _now(),
            "software": f"selfview {self.software}",
            "cell_sha256": self.cell_sha256,
            "image_sha256": self.image_sha256,
            "camera": self.camera.to_dict(),
            "C_H_W": _mat(self.C_H_W),
            "C_H_G": _mat(self.C_H_G),
            "gripper": {
                "state": self.state,
                "points_G": {
                    st: {nm: [float(v) for v in p] for nm, p in zip(POINT_NAMES, np.asarray(P, float))}
                    for st, P in self.points_G.items()
                },
            },
            "residuals": _plain(self.residuals),
            "updates": _plain(self.updates),
        }
        doc["checksum"] = _checksum(doc)
        return doc

    @classmethod
    def from_document(cls, doc: Any, source: str = "<memory>") -> "Calibration":
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise CalibrationFileError(f"{source}: not a selfview calibration file (no 'format: {FORMAT}')")
        if doc.get("version") != VERSION:
            raise CalibrationFileError(
                f"{source}: calibration file version {doc.get('version')!r}; this selfview reads version {VERSION}"
            )
        want = doc.get("checksum")
        body = {k: v for k, v in doc.items() if k != "checksum"}
        if want != _checksum(body):
            raise CalibrationFileError(
                f"{source}: checksum mismatch; the file was altered or corrupted (recalibrate, or restore a copy "
                f"from its .history folder)"
            )
        try:
            cam = doc["camera"]
            camera = CameraModel(
                f=float(cam["f"]),
                kappa=float(cam["kappa"]),
                cx=float(cam["principal_point"][0]),
                cy=float(cam["principal_point"][1]),
                aspect=float(cam["aspect"]),
                width=int(cam["width"]),
                height=int(cam["height"]),
            )
            pts = {}
            for st, d in doc["gripper"]["points_G"].items():
                pts[st] = np.array([d[nm] for nm in POINT_NAMES], dtype=float).reshape(6, 3)
            return cls(
                camera=camera,
                C_H_W=check_rigid(doc["C_H_W"], f"{source}: C_H_W"),
                C_H_G=check_rigid(doc["C_H_G"], f"{source}: C_H_G"),
                points_G=pts,
                state=str(doc["gripper"]["state"]),
                residuals=dict(doc.get("residuals") or {}),
                image_sha256=str(doc.get("image_sha256", "")),
                cell_sha256=str(doc.get("cell_sha256", "")),
                created=str(doc.get("created", "")),
                software=str(doc.get("software", "")).removeprefix("selfview "),
                updates=list(doc.get("updates") or []),
            )
        except (KeyError, TypeError, ValueError, IndexError, ConfigError) as exc:
            raise CalibrationFileError(f"{source}: malformed calibration file ({exc})") from exc


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def _mat(H) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(H, float)]


def _plain(x):
    """Convert numpy scalars/arrays in nested containers to plain Python for YAML/JSON."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, (np.floating, float)):
        return float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def _checksum(body: dict) -> str:
    # floats go through repr, which YAML round-trips exactly
    blob = json.dumps(body, sort_keys=True, separators=(",", ":"), default=str)
    return "sha256:" + hashlib.sha256(blob.encode()).hexdigest()


def history_dir(path) -> Path:
    """Folder where the previous versions of a calibration file are kept."""
    p = Path(path)
    return p.with_name(p.name + ".history")


def load_calibration(path) -> Calibration:
    """Read and verify a calibration file; raises ``CalibrationFileError`` naming the fault."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CalibrationFileError(f"{p}: no such calibration file (run 'selfview calibrate' first)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationFileError(f"{p}: cannot read the calibration file ({exc})") from exc
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationFileError(f"{p}: corrupt calibration file, not valid YAML ({exc})") from exc
    return Calibration.from_document(doc, source=str(p))


def save_calibration(cal: Calibration, path, *, keep_history: bool = True) -> Path:
    """Write ``cal`` to ``path`` atomically, keeping the previous file in ``<name>.history/``.

    Refuses (``CalibrationFileError``, nothing written) when the existing file is not a valid selfview
    calibration: it may be somebody else's file. Returns the path of the history copy, or None.
    """
    p = Path(path)
    kept = None
    if p.exists():
        load_calibration(p)  # refuse to replace a corrupt or foreign file
        if keep_history:
            hd = history_dir(p)
            hd.mkdir(exist_ok=True)
            blob = p.read_bytes()
            stamp = _dt.datetime.now(_dt.timezone.utc).strftime("%Y%m%dT%H%M%S.%fZ")
            kept = hd / f"{stamp}-{hashlib.sha256(blob).hexdigest()[:8]}{p.suffix or '.yaml'}"
            _atomic_write(kept, blob)
    text = yaml.safe_dump(cal.to_document(), sort_keys=False, default_flow_style=None, width=120)
    # check what we are about to write reads back, before it replaces anything
    Calibration.from_document(yaml.safe_load(text), source=str(p))
    _atomic_write(p, text.encode("utf-8"))
    return kept


def _atomic_write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    try:  # make the rename itself durable
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass
