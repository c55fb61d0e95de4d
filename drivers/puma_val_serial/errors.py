"""Typed errors for the texts a VAL-II controller prints between asterisks.

The dialect's error table maps a controller text to one of these class names, so a real controller's
wording is configured, not coded. Each carries the controller's own text and the command it answered.
"""

from __future__ import annotations

from selfview.errors import DeviceError

__all__ = [
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
    "ProgramRunning",
    "ERROR_CLASSES",
]


class ControllerError(DeviceError):
    """The controller printed an error line (``*text*``); ``text`` is its wording, ``command`` the line
    it answered (None for an asynchronous message)."""

    def __init__(self, text: str, command: str | None = None):
        where = f" after {command!r}" if command else " (asynchronous)"
        super().__init__(f"controller reported *{text}*{where}")
        self.text = text
        self.command = command


class ArmPowerOff(ControllerError):
    """Arm power is off (E-stop, power lost mid-move); press ARM POWER before moving again."""


class OutOfReach(ControllerError):
    """The controller found no joint solution for the target."""


class NotCalibrated(ControllerError):
    """Motion refused before ``CAL``."""


class UndefinedLocation(ControllerError):
    """A named location is not defined in the controller."""


class Collision(ControllerError):
    """The arm stopped on contact beyond what the work cell allows."""


class MotionAborted(ControllerError):
    """The motion was stopped by ``ABORT`` before it reached its target."""


class JointLimit(ControllerError):
    """A joint would pass its limit stop."""


class InvalidArgument(ControllerError):
    """The controller refused a value (speed, joint number, ...)."""


class CommandRejected(ControllerError):
    """The controller did not understand the command line."""


class ProgramRunning(DeviceError):
    """The controller prompts with its program prompt (``*``): a VAL program is running and the
    terminal's commands wait or are refused. Stop the program on the controller first."""


#: Class names usable in a dialect's error table.
ERROR_CLASSES: dict[str, type[ControllerError]] = {
    c.__name__: c
    for c in (
        ControllerError,
        ArmPowerOff,
        OutOfReach,
        NotCalibrated,
        UndefinedLocation,
        Collision,
        MotionAborted,
        JointLimit,
        InvalidArgument,
        CommandRejected,
    )
}
