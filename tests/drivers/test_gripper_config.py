"""Modbus URLs, I/O points, the address convention and the io map: what is accepted, what is refused."""

from __future__ import annotations

import pytest

from selfview.drivers.pneumatic_gripper import IoMap, JawReading, Point, from_reference, parse_modbus_url, to_reference
from selfview.drivers.pneumatic_gripper.gripper import GripperFault, PneumaticGripper
from selfview.errors import ConfigError


def test_tcp_url():
    u = parse_modbus_url("modbus-tcp://127.0.0.1:5020?unit=3")
    assert (u.transport, u.host, u.port, u.unit, u.framing) == ("tcp", "127.0.0.1", 5020, 3, "mbap")
    u = parse_modbus_url("modbus-tcp://plc.local")
    assert (u.port, u.unit) == (502, 1)


def test_rtu_urls():
    u = parse_modbus_url("modbus-rtu:///dev/ttyUSB0?baud=9600&parity=N&stopbits=2")
    assert (u.transport, u.device, u.baud, u.parity, u.stopbits, u.bytesize, u.framing) == (
        "rtu", "/dev/ttyUSB0", 9600, "N", 2, 8, "rtu")
    u = parse_modbus_url("modbus-rtu:///dev/ttyS1")
    assert (u.baud, u.parity, u.stopbits) == (19200, "E", 1)  # the Modbus standard's default
    u = parse_modbus_url("modbus-rtu+socket://10.0.0.7:4001?unit=17")
    assert (u.transport, u.host, u.port, u.unit, u.framing) == ("rtu-socket", "10.0.0.7", 4001, 17, "rtu")


@pytest.mark.parametrize(
    "url, match",
    [
        ("tcp://127.0.0.1:502", "unknown scheme"),
        ("127.0.0.1:502", "expected modbus-tcp"),
        ("modbus-tcp://127.0.0.1:502?unit=300", "unit=300: out of range"),
        ("modbus-tcp://127.0.0.1:502?slave=1", "unknown parameter"),
        ("modbus-tcp://127.0.0.1:0", "port 0"),
        ("modbus-tcp://127.0.0.1:99999", "bad port"),
        ("modbus-tcp://:502", "missing host"),
        ("modbus-tcp://127.0.0.1:502/x", "no path"),
        ("modbus-rtu://dev/ttyUSB0", "three slashes"),
        ("modbus-rtu:///dev/ttyUSB0?parity=X", "parity"),
        ("modbus-rtu:///dev/ttyUSB0?baud=fast", "not a whole number"),
        ("modbus-rtu:///dev/ttyUSB0?baud=19_200", "not a whole number in ASCII digits"),
        ("modbus-tcp://127.0.0.1:502?unit=\uff11", "not a whole number in ASCII digits"),  # a full-width 1
        ("modbus-rtu+socket://10.0.0.7", "no standard port"),
    ],
)
def test_bad_urls_name_the_problem(url, match):
    with pytest.raises(ConfigError, match=match):
        parse_modbus_url(url)
    with pytest.raises(ConfigError):
        PneumaticGripper(url)  # the driver refuses it at construction, before any I/O


def test_points_and_modicon_references():
    assert Point.parse("coil:0") == Point("coil", 0)
    assert Point.parse("di:12") == Point("discrete_input", 12)
    assert Point.parse("hr:0.3") == Point("holding_register", 0, 3)
    assert Point.parse("ir:2.15") == Point("input_register", 2, 15)
    # 1-based references -> 0-based wire addresses
    assert Point.parse("40001.3") == Point("holding_register", 0, 3)
    assert Point.parse("400010.0") == Point("holding_register", 9, 0)
    assert Point.parse("00001") == Point("coil", 0)
    assert Point.parse("10002") == Point("discrete_input", 1)
    assert Point.parse("30017.1") == Point("input_register", 16, 1)
    assert from_reference("465536", 0) == Point("holding_register", 65535, 0)
    assert to_reference(Point("holding_register", 0, 3)) == "400001.3"
    assert to_reference(Point("discrete_input", 4)) == "100005"
    for p in ("coil:5", "hr:7.2", "di:0", "ir:1.0"):
        assert str(Point.parse(p)) == p


@pytest.mark.parametrize(
    "text, match",
    [
        ("coil:0.1", "has no bit"),
        ("hr:3", "needs a bit"),
        ("hr:3.16", "needs a bit 0..15"),
        ("xx:1", "unknown table"),
        ("40001.3.1", "expected"),
        ("20001", "leading digit 2"),
        ("40000", "count from 1"),
        ("4001", "expected"),
        ("coil:70000", "0..65535"),
        ("coil:\uff11", "expected"),  # a full-width digit: re's \d would take it
        ("\uff14" + "0001", "expected"),
    ],
)
def test_bad_points(text, match):
    with pytest.raises(ConfigError, match=match):
        Point.parse(text)


def test_io_map_from_dict_and_back():
    m = IoMap.from_dict(
        {"open_valve": None, "close_valve": "40001.0", "open_sensor": "30001.0", "closed_sensor": "ir:0.1",
         "safe_state": "open", "register_write": "mask", "stray_coils": "switch-off"}
    )
    assert m.solenoid == "single" and m.valves == {"close": Point("holding_register", 0, 0)}
    assert m.to_dict() == {"open_valve": None, "close_valve": "hr:0.0", "open_sensor": "ir:0.0",
                           "closed_sensor": "ir:0.1", "safe_state": "open", "register_write": "mask",
                           "stray_coils": "switch-off"}
    assert IoMap.from_dict(m.to_dict()) == m
    assert IoMap().solenoid == "double"


@pytest.mark.parametrize(
    "data, match",
    [
        ({"open_valve": None, "close_valve": None}, "needs open_valve"),
        ({"open_valve": "di:0"}, "read-only"),
        ({"close_valve": "coil:0"}, "same point"),
        ({"closed_sensor": "di:0"}, "same point"),
        ({"open_sensor": "coil:1"}, "shares its point"),
        ({"safe_state": "off"}, "safe_state"),
        ({"register_write": "fc22"}, "register_write"),
        ({"stray_coils": "ignore"}, "stray_coils"),
        ({"valve": "coil:0"}, "unknown key"),
        ({"open_valve": "coil"}, "open_valve"),
    ],
)
def test_bad_io_maps(data, match):
    with pytest.raises(ConfigError, match=match):
        IoMap.from_dict(data)


def test_drive_and_direction_single_and_double():
    double = IoMap()
    assert double.drive("open") == {"open": True, "close": False}
    assert double.drive("closed") == {"open": False, "close": True}
    assert double.drive("all-off") == {"open": False, "close": False}
    assert double.direction({"open": True, "close": True}) is None  # a bistable valve holds
    assert double.direction({"open": False, "close": False}) is None
    spring_open = IoMap(open_valve=None)  # only a close solenoid: de-energised = open
    assert spring_open.drive("closed") == {"close": True}
    assert spring_open.direction({"close": False}) == "open"
    spring_closed = IoMap(close_valve=None)
    assert spring_closed.direction({"open": False}) == "closed"
    with pytest.raises(ConfigError):
        double.drive("half")


def test_reading_states():
    assert JawReading(True, False, 0.0).state == "open"
    assert JawReading(False, True, 0.0).state == "closed"
    assert JawReading(False, False, 0.0).state == "between"
    with pytest.raises(GripperFault):
        JawReading(True, True, 0.0).state


@pytest.mark.parametrize("kw", [{"timeout_s": 0}, {"poll_s": -1}, {"request_timeout_s": 0}, {"retries": 9},
                                {"io_map": {"open_valve": "coil:0"}}])
def test_bad_driver_settings(kw):
    with pytest.raises(ConfigError):
        PneumaticGripper("modbus-tcp://127.0.0.1:502", **kw)


def test_reads_are_grouped_within_modbus_limits():
    from selfview.drivers.pneumatic_gripper.gripper import _span_reads

    pts = [Point.parse(t) for t in ("di:1", "di:0", "ir:3.1", "ir:3.2", "ir:200.0", "di:2500", "coil:4")]
    assert _span_reads(pts) == [
        ("coil", 4, 1),
        ("discrete_input", 0, 2),
        ("discrete_input", 2500, 1),  # 2501 bits would exceed the 2000 one read may ask for
        ("input_register", 3, 1),  # two bits of one register: one register read
        ("input_register", 200, 1),
    ]


@pytest.mark.parametrize("timeout_s", [float("inf"), float("nan"), 1e10, 0.0, -1.0])
def test_request_timeouts_are_finite_and_bounded(timeout_s):
    from selfview.drivers.pneumatic_gripper.modbus import ModbusLink

    with pytest.raises(ConfigError, match="timeout_s"):
        ModbusLink("modbus-tcp://127.0.0.1:502?unit=1", timeout_s=timeout_s)  # inf would wait forever
