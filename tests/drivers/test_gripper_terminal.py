"""The gripper driver against the simulated valve terminal: motions, faults, watchdog, reconnects.

The contract tests at the top run on the simulated terminal, or on a real valve when the environment
variable SELFVIEW_GRIPPER_URL names it (e.g. modbus-tcp://10.0.0.5:502?unit=1, default io map).
"""

from __future__ import annotations

import os
import time

import pytest

from selfview.drivers.pneumatic_gripper import ConnectionLost, GripperFault, IoMap, PneumaticGripper, Point
from selfview.mocks.valve_terminal import ValveTerminal
from selfview.mocks.world import SimWorld
from selfview.errors import DeviceTimeout

TRAVEL_S = 0.04


@pytest.fixture
def terminal():
    with ValveTerminal(travel_s=TRAVEL_S, watchdog_s=0.5) as t:
        yield t


@pytest.fixture
def contract_url(request):
    url = os.environ.get("SELFVIEW_GRIPPER_URL")
    if url:
        yield url
        return
    with ValveTerminal(travel_s=TRAVEL_S) as t:
        yield t.url


def wait_for(pred, timeout_s=2.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


# --- contract ---------------------------------------------------------------------------------------
def test_contract_open_close_state(contract_url):
    with PneumaticGripper(contract_url, timeout_s=1.0) as g:
        assert g.close_jaws() == "closed"
        assert g.state() == "closed" and g.valve_outputs["close"] is True
        assert g.open_jaws() == "open"
        assert g.state() == "open"
        assert g.close_jaws() == "closed"  # and back, a second stroke
        g.safe()


def test_contract_connect_and_close_twice(contract_url):
    g = PneumaticGripper(contract_url)
    g.connect()
    g.connect()
    assert g.last_state in ("open", "closed", "between")
    g.close()
    g.close()
    assert not g.connected and g.last_state is None


# --- simulated terminal -----------------------------------------------------------------------------
def test_motion_takes_the_travel_time_and_the_world_follows(cell):
    world = SimWorld(cell, seed=3)
    assert world.jaw_state == cell.gripper.calibrate_in == "open"
    with ValveTerminal(world, travel_s=TRAVEL_S) as t, PneumaticGripper(t.url) as g:
        v0 = world.version
        t0 = time.monotonic()
        assert g.close_jaws() == "closed"
        elapsed = time.monotonic() - t0
        assert elapsed >= TRAVEL_S  # the switch only comes on at the end of the stroke
        assert world.jaw_gap_mm == cell.gripper.states["closed"] and world.jaw_state == "closed"
        assert world.version > v0
        target, t_switch, t_arrive = t.strokes[-1]
        assert target == "closed" and t_arrive - t_switch == pytest.approx(TRAVEL_S, abs=1e-9)  # model time
        g.open_jaws()
        assert world.jaw_gap_mm == cell.gripper.states["open"] and world.jaw_state == "open"


def test_gap_is_between_while_travelling(cell):
    world = SimWorld(cell, seed=3)
    with ValveTerminal(world, travel_s=0.4) as t, PneumaticGripper(t.url, timeout_s=1.0) as g:
        g._write_outputs(g.io_map.drive("closed"))
        assert wait_for(lambda: g.state() == "between", 0.3)
        gap = world.jaw_gap_mm
        assert cell.gripper.states["closed"] < gap < cell.gripper.states["open"]
        assert g.close_jaws() == "closed"


def test_stuck_jaw_times_out(terminal):
    with PneumaticGripper(terminal.url, timeout_s=0.2) as g:
        terminal.stick_jaw()
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout, match="still 'open'"):
            g.close_jaws()
        assert 0.2 <= time.monotonic() - t0 < 2.0  # waited its timeout, and no more than that by far
        terminal.stick_jaw(False)
        assert g.close_jaws() == "closed"


def test_jaw_stuck_between_is_a_fault():
    with ValveTerminal(travel_s=1.0) as t, PneumaticGripper(t.url, timeout_s=0.3) as g:
        g._write_outputs(g.io_map.drive("closed"))
        assert wait_for(lambda: t.position < 1.0)
        t.stick_jaw()
        assert 0 < t.position < 1
        with pytest.raises(GripperFault, match="did not come on"):
            g.close_jaws()


def test_broken_switch_is_a_fault_and_a_shorted_one_too(terminal):
    with PneumaticGripper(terminal.url, timeout_s=0.2) as g:
        terminal.break_sensor("closed", reads=False)  # wire broken: never on
        with pytest.raises(GripperFault):
            g.close_jaws()
        assert terminal.position == 0.0  # the jaws did close; only the switch is silent
        terminal.break_sensor("closed", None)
        assert g.state() == "closed"
        terminal.break_sensor("open", reads=True)  # short: always on
        with pytest.raises(GripperFault, match="both"):
            g.state()
        assert g.last_state is None


def test_exception_replies_on_demand(terminal):
    from selfview.drivers.pneumatic_gripper import ModbusExceptionReply

    with PneumaticGripper(terminal.url) as g:
        terminal.fail_requests(6)
        with pytest.raises(ModbusExceptionReply) as e:
            g.open_jaws()
        assert e.value.code == 6
        terminal.fail_requests(None)
        assert g.open_jaws() == "open"


def test_silent_terminal_times_out_and_blocks_jaw_commands(terminal):
    with PneumaticGripper(terminal.url, request_timeout_s=0.15, poll_s=0.05) as g:
        terminal.set_silent()
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout):
            g.state()
        assert time.monotonic() - t0 < 2.0  # 0.15 s, not pymodbus's default 3 s x 4 attempts
        assert g.last_state is None
        terminal.set_silent(False)
        assert wait_for(lambda: g.poll_error is None)  # the poller reconnected ...
        assert g.last_state is None  # ... but the state stays unknown ...
        with pytest.raises(ConnectionLost, match="connect"):
            g.close_jaws()  # ... and the jaws do not move until the caller reconnects
        g.connect()
        assert g.last_state == "open" and g.close_jaws() == "closed"


def test_dropped_connection_then_reconnect(terminal):
    with PneumaticGripper(terminal.url, poll_s=None) as g:
        g.close_jaws()
        terminal.drop_connections()
        with pytest.raises(ConnectionLost):
            g.state()
        assert g.last_state is None
        with pytest.raises(ConnectionLost):
            g.open_jaws()
        g.connect()
        assert g.state() == "closed" and terminal.connections_total == 2


def test_drop_during_a_request(terminal):
    with PneumaticGripper(terminal.url, poll_s=None) as g:
        terminal.drop_on_next_request()
        with pytest.raises(ConnectionLost):
            g.close_jaws()
        assert terminal.position == 1.0  # the write never reached the valve


def test_poller_feeds_the_watchdog(terminal):
    with PneumaticGripper(terminal.url, poll_s=0.1) as g:
        g.close_jaws()
        time.sleep(1.0)  # twice the watchdog
        assert terminal.watchdog_trips == 0 and terminal.valve_outputs["close"] is True
        assert g.polls >= 5 and g.last_state == "closed"


def test_watchdog_resets_outputs_and_the_driver_sees_it_after_reconnect():
    # single solenoid, spring return to open: the watchdog's reset opens the jaws
    m = IoMap(open_valve=None, close_valve=Point.parse("40001.0"), open_sensor=Point.parse("30001.0"),
              closed_sensor=Point.parse("30001.1"))
    with ValveTerminal(io_map=m, travel_s=TRAVEL_S, watchdog_s=0.2) as t:
        with PneumaticGripper(t.url, io_map=m, poll_s=None) as g:
            assert g.close_jaws() == "closed"
            assert wait_for(lambda: t.watchdog_trips == 1, 1.0)
            assert t.valve_outputs == {"close": False}
            assert wait_for(lambda: t.sensors == (True, False), 1.0)  # sprung open
            t.drop_connections()  # the terminal also hangs up
            with pytest.raises(ConnectionLost):
                g.state()
            g.connect()  # re-reads the outputs
            assert g.valve_outputs == {"close": False} and g.outputs_reset
            assert g.state() == "open"


def test_rtu_over_tcp_terminal():
    with ValveTerminal(travel_s=TRAVEL_S, framing="rtu") as t:
        assert t.url.startswith("modbus-rtu+socket://127.0.0.1:")
        with PneumaticGripper(t.url) as g:
            assert g.close_jaws() == "closed" and g.open_jaws() == "open"


def test_safe_state_closed():
    m = IoMap(safe_state="closed")
    with ValveTerminal(io_map=m, travel_s=TRAVEL_S) as t, PneumaticGripper(t.url, io_map=m) as g:
        g.safe()
        assert t.valve_outputs == {"open": False, "close": True}
        assert wait_for(lambda: t.position == 0.0)
