"""selfview: calibration toolkit for self-viewing eye-on-hand robot cells.

The numerical core: camera model (paper eq. 1-4), Tsai's coplanar calibration, the Plane Coincidence Constraint
(eq. 5-10), the on-line update (eq. 11-17), feature extraction and calibration files. It imports nothing from
``drivers``, ``mocks`` or ``procedures``.
"""

from importlib import metadata as _metadata
from pathlib import Path as _Path

# The repository keeps drivers/, mocks/, procedures/ and bench/ beside selfview/ (a layout its users fixed); an
# install maps them to selfview.drivers, .mocks, .procedures and .bench (pyproject.toml, [tool.setuptools.package-dir]).
# From a source tree (a checkout or a copy, installed or not) the same names resolve to the folders beside this one,
# so that a copy of the tree runs its own code.
_TREE = _Path(__file__).resolve().parent.parent
if not (_Path(__file__).resolve().parent / "drivers").is_dir() and (_TREE / "pyproject.toml").is_file() \
        and (_TREE / "drivers" / "__init__.py").is_file():
    __path__.append(str(_TREE))  # noqa: F821 (a package's __path__)

try:
    __version__ = _metadata.version("selfview")
except _metadata.PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"

from selfview.errors import (  # noqa: E402
    AlarmError, CalibrationError, CalibrationFileError, CellError, ConfigError, DeviceError, DeviceTimeout, ImageError,
    LimitError, PictureFileError, ProtocolError,
)

__all__ = ["__version__", "PictureCalibration", "TrackResult", "calibrate_picture", "track", "AlarmError",
           "CalibrationError", "CalibrationFileError", "CellError", "ConfigError", "DeviceError", "DeviceTimeout",
           "ImageError", "LimitError", "PictureFileError", "ProtocolError"]

_API = ("PictureCalibration", "TrackResult", "calibrate_picture", "track")


def __getattr__(name):
    """The one-call API (``selfview.api``), imported when first used: ``import selfview`` stays light."""
    if name in _API:
        from selfview import api

        return getattr(api, name)
    raise AttributeError(f"module 'selfview' has no attribute {name!r}")
