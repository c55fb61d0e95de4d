"""selfview: calibration toolkit for self-viewing eye-on-hand robot cells. Its numerical core (camera model, eq. 1-4;
Tsai; PCC, eq. 5-10; on-line update, eq. 11-17; features; files) imports nothing from drivers, mocks or procedures."""

from importlib import metadata as _metadata
from pathlib import Path as _Path

# the folders beside selfview/ (drivers/, mocks/, ...) are selfview.drivers etc.: a copy of the tree runs its own code
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
    """``selfview.api``'s names, imported when first used so that ``import selfview`` stays light."""
    if name in _API:
        from selfview import api

        return getattr(api, name)
    raise AttributeError(f"module 'selfview' has no attribute {name!r}")
