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

    #: The operator's next step for this cause (the command line prints it after the error).
    what_to_do = "read the controller's message above and correct its cause before the next command"

    def __init__(self, text: str, command: str | None = None):
        where = f" after {command!r}" if command else " (asynchronous)"
        super().__init__(f"controller reported *{text}*{where}")
        self.text = text
        self.command = command


class ArmPowerOff(ControllerError):
    """Arm power is off (E-stop, power lost mid-move); press ARM POWER before moving again."""

    what_to_do = 'switch ARM POWER on at the controller (release the E-stop first) and run the command again'


class OutOfReach(ControllerError):
    """The controller found no joint solution for the target."""

    what_to_do = "choose a target inside the arm's reach (show a location with 'selfview robot --url URL point NAME')"


class NotCalibrated(ControllerError):
    """Motion refused before ``CAL``."""

    what_to_do = "calibrate the arm first: 'selfview robot --url URL calibrate' (the joints move a little), then run the command again"


class UndefinedLocation(ControllerError):
    """A named location is not defined in the controller."""

    what_to_do = "teach it first: 'selfview robot --url URL here NAME' (or 'define NAME X Y Z O A T')"


class Collision(ControllerError):
    """The arm stopped on contact beyond what the work cell allows."""

    what_to_do = 'clear the cell, check the arm and the gripper for damage, then move away at a low speed'


class MotionAborted(ControllerError):
    """The motion was stopped by ``ABORT`` before it reached its target."""

    what_to_do = 'the motion was stopped by ABORT: run the command again when the cell is clear'


class JointLimit(ControllerError):
    """A joint would pass its limit stop."""

    what_to_do = 'choose a target that keeps every joint inside its limit (the joint is named above)'


class InvalidArgument(ControllerError):
    """The controller refused a value (speed, joint number, ...)."""

    what_to_do = 'correct the value the controller refused (named above)'


class CommandRejected(ControllerError):
    """The controller did not understand the command line."""

    what_to_do = "the controller does not know this command line: check the controller's dialect file (--dialect)"


class ProgramRunning(DeviceError):
    """The controller prompts with its program prompt (``*``): a VAL program is running and the
    terminal's commands wait or are refused. Stop the program on the controller first."""

    what_to_do = "stop the VAL program on the controller's terminal, then run the command again"


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
