"""Camera files (``CameraFile``, by ``selfview intrinsics``): checksummed YAML (``format: selfview-camera``,
``version: 1``), written and refused like calibration files; without ``skew`` (older): skew 0, a 5 x 5 covariance."""

from __future__ import annotations

import datetime as _dt
import hashlib
import platform
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import yaml

from selfview import __version__
from selfview.files.calfile import check_document, doc_checksum, plain_data, replace_keeping_history
from selfview.files.io_safe import MAX_YAML_BYTES, load_yaml, read_bounded
from selfview.maths.camera import CameraModel
from selfview.errors import CalibrationFileError, ConfigError

__all__ = ["CameraFile", "load_camera_file", "save_camera_file", "FORMAT", "VERSION", "INTRINSIC_NAMES"]

FORMAT = "selfview-camera"
VERSION = 1
INTRINSIC_NAMES = ("f", "kappa", "cx", "cy", "aspect", "skew")


@dataclass
class CameraFile:
    """A measured camera: ``camera``; ``sigma`` name -> 1-sigma (f, kappa, cx, cy, aspect[, skew]); ``covariance``
    (n, n) in that order (n = 6 with the skew measured, else 5); ``figures`` reported (rms_px, views_used, ...);
    ``provenance`` (pictures' SHA-256, created, software, Python/NumPy/OpenCV versions, the cell's hash)."""
    camera: CameraModel
    sigma: dict
    covariance: np.ndarray
    figures: dict = field(default_factory=dict)
    provenance: dict = field(default_factory=dict)
    file_sha256: ClassVar[str] = ""

    def to_document(self) -> dict:
        prov = dict(self.provenance)
        prov.setdefault("created", _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"))
        prov.setdefault("software", f"selfview {__version__}")
        prov.setdefault("versions", _versions())
        cov = np.asarray(self.covariance, float)
        n = self.n_intrinsics
        camera = self.camera.to_dict()
        if n == 6:
            camera["skew"] = float(self.camera.skew)
        doc = {"format": FORMAT, "version": VERSION, "camera": camera,
               "sigma": {k: float(self.sigma[k]) for k in INTRINSIC_NAMES[:n]},
               "covariance": [[float(v) for v in row] for row in cov], "figures": plain_data(self.figures),
               "provenance": plain_data(prov)}
        doc["checksum"] = doc_checksum(doc)
        return doc

    @classmethod
    def from_document(cls, doc: Any, source: str = "<memory>") -> "CameraFile":
        check_document(doc, FORMAT, VERSION, "camera file", source, redo="measure again with 'selfview intrinsics'",
                       hint="; write one with 'selfview intrinsics --out'")
        try:
            c = doc["camera"]
            n = 6 if "skew" in c else 5
            if n == 6 and (isinstance(c["skew"], bool) or not isinstance(c["skew"], (int, float))):
                raise ValueError(f"camera skew is {c['skew']!r}, not a number")
            camera = CameraModel.from_dict(c)
            sigma = {k: float(doc["sigma"][k]) for k in INTRINSIC_NAMES[:n]}
            cov = np.array(doc["covariance"], dtype=float).reshape(n, n)
            if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(list(sigma.values())))):
                raise ValueError("a sigma or the covariance holds a number that is not finite")
        except (KeyError, TypeError, ValueError, IndexError, ConfigError) as exc:
            raise CalibrationFileError(f"{source}: malformed camera file ({exc})") from exc
        return cls(camera, sigma, cov, dict(doc.get("figures") or {}), dict(doc.get("provenance") or {}))

    @property
    def n_intrinsics(self) -> int:
        """5 (f, kappa, cx, cy, aspect) or 6 (and the skew): the size of ``covariance``."""
        n = len(np.asarray(self.covariance))
        if n not in (5, 6) or np.shape(self.covariance) != (n, n):
            raise ConfigError(f"camera file covariance: expected 5 x 5 or 6 x 6, got {np.shape(self.covariance)}")
        if n == 5 and self.camera.skew:
            raise ConfigError("camera file: a camera with a skew needs its 6 x 6 covariance (the skew's too)")
        return n

    def centre_covariance(self) -> np.ndarray:
        """The covariance of (cx, cy, aspect[, skew]): (3, 3), or (4, 4) with the skew measured."""
        return np.asarray(self.covariance, float)[2:, 2:]

    def check_size(self, width: int, height: int, source: str = "camera file") -> None:
        """``ConfigError`` unless the file's picture size is ``width`` x ``height``."""
        self.camera.check_size(width, height, source)


def _versions() -> dict:
    import cv2

    return {"python": platform.python_version(), "numpy": np.__version__, "opencv": cv2.__version__}


def load_camera_file(path) -> CameraFile:
    """Read and verify a camera file; ``CalibrationFileError`` naming the fault. ``file_sha256``: of the bytes parsed
    (a provenance hash read again later could name a file replaced meanwhile)."""
    p = Path(path)
    blob = read_bounded(p, MAX_YAML_BYTES, error=CalibrationFileError, what="camera file",
                        missing=f"no such camera file (run 'selfview intrinsics --out {p.name}' first)")
    doc = load_yaml(blob, str(p), error=CalibrationFileError, what="camera file")
    cf = CameraFile.from_document(doc, source=str(p))
    cf.file_sha256 = hashlib.sha256(blob).hexdigest()
    return cf


def save_camera_file(cf: CameraFile, path, *, keep_history: bool = True) -> Path | None:
    """Write ``cf`` by ``replace_keeping_history`` (never over a file that is not a camera file); the history copy."""
    p = Path(path)
    text = yaml.safe_dump(cf.to_document(), sort_keys=False, default_flow_style=None, width=120)
    # what we are about to write must read back, before it replaces anything
    CameraFile.from_document(load_yaml(text, str(p), error=CalibrationFileError, what="camera file"), source=str(p))
    return replace_keeping_history(p, text, load_camera_file, what="camera file", keep_history=keep_history)
