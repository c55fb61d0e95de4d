"""selfview: calibration toolkit for self-viewing eye-on-hand robot cells.

The numerical core: camera model (paper eq. 1-4), Tsai's coplanar calibration, the Plane Coincidence
Constraint (eq. 5-10), the on-line update (eq. 11-17), feature extraction and calibration files. It
imports nothing from ``drivers``, ``mocks`` or ``procedures``.
"""

from importlib import metadata as _metadata

try:
    __version__ = _metadata.version("selfview")
except _metadata.PackageNotFoundError:  # running from a source tree that was not installed
    __version__ = "0.0.0+unknown"

from selfview.errors import (  # noqa: E402
    AlarmError,
    CalibrationError,
    CalibrationFileError,
    CellError,
    ConfigError,
    DeviceError,
    DeviceTimeout,
    ImageError,
    LimitError,
    ProtocolError,
)

__all__ = [
    "__version__",
    "AlarmError",
    "CalibrationError",
    "CalibrationFileError",
    "CellError",
    "ConfigError",
    "DeviceError",
    "DeviceTimeout",
    "ImageError",
    "LimitError",
    "ProtocolError",
]
