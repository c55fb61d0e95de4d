"""Pneumatic parallel-jaw gripper on a Modbus valve: driver, I/O map and URLs.

Only ``selfview.drivers.pneumatic_gripper.modbus`` imports pymodbus (3.11 to the newest 3.x; see pyproject.toml).
"""

from selfview.drivers.pneumatic_gripper.gripper import GripperFault, JawReading, PneumaticGripper, SafeReport
from selfview.drivers.pneumatic_gripper.iomap import JAW_STATES, IoMap, Point, from_reference, to_reference
from selfview.drivers.pneumatic_gripper.modbus import (
    ConnectionFailed,
    ConnectionLost,
    ModbusExceptionReply,
    ModbusLink,
)
from selfview.drivers.pneumatic_gripper.url import ModbusUrl, parse_modbus_url

__all__ = [
    "PneumaticGripper",
    "GripperFault",
    "JawReading",
    "SafeReport",
    "IoMap",
    "Point",
    "JAW_STATES",
    "from_reference",
    "to_reference",
    "ModbusLink",
    "ModbusExceptionReply",
    "ConnectionFailed",
    "ConnectionLost",
    "ModbusUrl",
    "parse_modbus_url",
]
