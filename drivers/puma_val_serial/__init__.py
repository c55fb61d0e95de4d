"""PUMA 260 on a VAL-II controller, over the controller's terminal port (serial, pty or TCP).

``PumaVAL`` is the driver; ``ValDialect`` the controller's terminal dialect as data; ``ValLimits`` the
client-side limits checked before anything is sent; the ``ControllerError`` family the typed errors of
the controller's ``*text*`` lines.
"""

from selfview.drivers.puma_val_serial.dialect import DEFAULT_COMMANDS, DEFAULT_ERRORS, OAT_CONVENTIONS, ValDialect, load_dialect
from selfview.drivers.puma_val_serial.driver import AbortResult, PumaVAL, Where
from selfview.drivers.puma_val_serial.kinematics import PumaKinematics
from selfview.drivers.puma_val_serial.errors import (
    ArmPowerOff,
    Collision,
    CommandRejected,
    ControllerError,
    InvalidArgument,
    JointLimit,
    MotionAborted,
    NotCalibrated,
    OutOfReach,
    ProgramRunning,
    UndefinedLocation,
)
from selfview.drivers.puma_val_serial.limits import ValLimits

__all__ = [
    "PumaVAL",
    "Where",
    "AbortResult",
    "PumaKinematics",
    "OAT_CONVENTIONS",
    "ProgramRunning",
    "ValDialect",
    "ValLimits",
    "load_dialect",
    "DEFAULT_COMMANDS",
    "DEFAULT_ERRORS",
    "ControllerError",
    "ArmPowerOff",
    "OutOfReach",
    "NotCalibrated",
    "UndefinedLocation",
    "Collision",
    "MotionAborted",
    "JointLimit",
    "InvalidArgument",
    "CommandRejected",
]
