"""The project's exceptions, mixed with builtins so callers can catch either; drivers translate vendor errors."""


class CellError(Exception):
    """Base of every error this project raises on purpose."""


class ConfigError(CellError, ValueError):
    """A cell description, URL or setting is malformed; the message names the key and the value."""


class DeviceError(CellError):
    """A device reported a fault or refused a command."""


class DeviceTimeout(CellError, TimeoutError):
    """A device did not answer within ``timeout_s``."""


class ProtocolError(CellError):
    """A reply did not follow the wire protocol (garbled, truncated, unexpected)."""


class LimitError(CellError, ValueError):
    """A command would break a configured limit; nothing was sent."""


class CalibrationError(CellError):
    """A calibration could not be computed; the message names the cause (too few points, collinear, ...)."""


class CalibrationFileError(CellError):
    """A calibration file is corrupt, foreign or of an unknown version; nothing was overwritten."""


class ImageError(CellError, ValueError):
    """A picture cannot be used (blank, saturated, wrong size, nothing found)."""


class PictureFileError(ImageError):
    """A picture file is missing, unreadable, not a picture or not 8- or 16-bit (a file fault, not the scene's)."""


class AlarmError(CellError):
    """The on-line monitor raised the alarm: the camera moved beyond the alarm limit."""
