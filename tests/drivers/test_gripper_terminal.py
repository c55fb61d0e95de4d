"""The gripper driver against the simulated valve terminal: motions, faults, watchdog, reconnects.

The contract tests at the top run on the simulated terminal, or on a real valve when the environment
variable SELFVIEW_GRIPPER_URL names it (e.g. modbus-tcp://10.0.0.5:502?unit=1, default io map).
"""

from __future__ import annotations

import os
import time

import pytest

from selfview.drivers.pneumatic_gripper import (
    ConnectionLost,
    GripperFault,
    IoMap,
    ModbusExceptionReply,
    PneumaticGripper,
    Point,
)
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
        assert g.close_jaws() == "closed"
        assert world.jaw_gap_mm == cell.gripper.states["closed"] and world.jaw_state == "closed"
        assert world.version > v0
        target, t_switch, t_arrive = t.strokes[-1]
        assert target == "closed" and t_arrive - t_switch == pytest.approx(TRAVEL_S, abs=1e-9)  # model time
        # the switch only comes on at the end of the stroke: the confirming reading came after the arrival
        # (driver and terminal share the monotonic clock in this process)
        assert g.last_reading.time >= t_arrive
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
        with pytest.raises(DeviceTimeout, match="still 'open'") as e:
            g.close_jaws()
        assert time.monotonic() - t0 >= 0.2  # waited its whole timeout
        # the failed command made the driver give up: valve de-energised and read back
        assert "safe state confirmed" in str(e.value) and g.safe_report.confirmed
        assert terminal.valve_outputs == {"open": False, "close": False}
        terminal.stick_jaw(False)
        with pytest.raises(ConnectionLost, match="gave up"):
            g.close_jaws()  # nothing moves until the caller has re-read the valve
        g.connect()
        assert g.close_jaws() == "closed"


def test_jaw_stuck_between_is_a_fault():
    with ValveTerminal(travel_s=1.0) as t, PneumaticGripper(t.url, timeout_s=0.3) as g:
        g._write_outputs(g.io_map.drive("closed"))
        assert wait_for(lambda: t.position < 1.0)
        t.stick_jaw()
        assert 0 < t.position < 1
        with pytest.raises(GripperFault, match="did not come on"):
            g.close_jaws()
        assert t.valve_outputs == {"open": False, "close": False} and g.halted


def test_broken_switch_is_a_fault_and_a_shorted_one_too(terminal):
    with PneumaticGripper(terminal.url, timeout_s=0.2) as g:
        terminal.break_sensor("closed", reads=False)  # wire broken: never on
        with pytest.raises(GripperFault):
            g.close_jaws()
        assert terminal.position == 0.0  # the jaws did close; only the switch is silent
        terminal.break_sensor("closed", None)
        g.connect()
        assert g.state() == "closed"
        terminal.break_sensor("open", reads=True)  # short: always on
        with pytest.raises(GripperFault, match="both"):
            g.state()
        assert g.last_state is None


def test_exception_replies_on_demand(terminal):
    with PneumaticGripper(terminal.url) as g:
        terminal.fail_requests(6)
        with pytest.raises(ModbusExceptionReply) as e:
            g.open_jaws()
        assert e.value.code == 6 and "safe state NOT confirmed" in str(e.value)
        terminal.fail_requests(None)
        g.connect()
        assert g.open_jaws() == "open"


def test_silent_terminal_times_out_and_blocks_jaw_commands(terminal):
    with PneumaticGripper(terminal.url, request_timeout_s=0.15, retries=0, poll_s=0.05) as g:
        terminal.set_silent()
        n0 = terminal.requests
        with pytest.raises(DeviceTimeout, match="safe state NOT confirmed"):
            g.state()
        # one attempt each (not pymodbus's default of 4): the read, then the safe attempt's reconnection
        # (which reads the outputs first); the poller asks nothing after the loss
        assert terminal.requests - n0 == 2
        assert g.last_state is None and g.halted
        terminal.set_silent(False)
        with pytest.raises(ConnectionLost, match="connect"):
            g.close_jaws()  # the jaws do not move until the caller reconnects
        g.connect()
        assert g.last_state == "open" and g.close_jaws() == "closed"


def test_dropped_connection_then_reconnect(terminal):
    with PneumaticGripper(terminal.url, poll_s=None) as g:
        g.close_jaws()
        terminal.drop_connections()
        with pytest.raises(ConnectionLost, match="safe state confirmed"):
            g.state()
        assert g.last_state is None
        assert terminal.valve_outputs == {"open": False, "close": False}  # the safe attempt reconnected once
        with pytest.raises(ConnectionLost):
            g.open_jaws()
        g.connect()
        assert g.state() == "closed" and terminal.connections_total == 3


def test_drop_during_a_request(terminal):
    with PneumaticGripper(terminal.url, poll_s=None) as g:
        terminal.drop_on_next_request()
        with pytest.raises(ConnectionLost):
            g.close_jaws()
        assert terminal.position == 1.0  # the write never reached the valve


def test_poller_feeds_the_watchdog(terminal):
    with PneumaticGripper(terminal.url, poll_s=0.05) as g:
        g.close_jaws()
        n = g.polls
        assert wait_for(lambda: g.polls >= n + 25, 20.0)  # 25 polls of 0.05 s: over twice the 0.5 s watchdog
        assert terminal.watchdog_trips == 0 and terminal.valve_outputs["close"] is True
        assert g.last_state == "closed" and g.poll_error is None


def test_no_watchdog_feed_after_a_failed_command():
    """After a failed command the poller must not keep the outputs energised."""
    with ValveTerminal(travel_s=TRAVEL_S, watchdog_s=0.3) as t, PneumaticGripper(t.url, poll_s=0.03) as g:
        assert g.close_jaws() == "closed"
        t.fail_requests(4)  # the device refuses every request: the open command fails, so does the safe attempt
        with pytest.raises(ModbusExceptionReply, match="safe state NOT confirmed") as e:
            g.open_jaws()
        report = e.value.safe_report
        assert report is g.safe_report and not report.written and not report.confirmed
        t.fail_requests(None)
        n = t.requests
        assert t.valve_outputs["close"] is True  # still energised: only the watchdog can drop it now ...
        assert wait_for(lambda: t.watchdog_trips == 1, 10.0)  # ... and it does, because nobody feeds it
        assert t.valve_outputs == {"open": False, "close": False}
        assert t.requests == n and g.halted and g.last_state is None
        g.connect()  # the caller resumes explicitly, and sees the reset
        assert g.outputs_reset and g.state() == "closed"  # a double valve held the jaws where they were


def test_link_drop_with_the_poller_running_leaves_the_valve_safe(terminal):
    """The poller sees the loss, does not reconnect to feed the watchdog, tries the safe state once."""
    with PneumaticGripper(terminal.url, poll_s=0.03) as g:
        assert g.close_jaws() == "closed"
        terminal.drop_connections()
        assert wait_for(lambda: g.safe_report is not None, 10.0)
        assert g.safe_report.confirmed and "poller lost the link" in g.safe_report.reason
        assert terminal.valve_outputs == {"open": False, "close": False}
        assert wait_for(lambda: not g.connected, 5.0)  # silent afterwards
        with pytest.raises(ConnectionLost, match="gave up"):
            g.open_jaws()
        g.connect()
        assert g.open_jaws() == "open"


def test_link_drop_while_the_safe_attempt_fails_too():
    """Nothing answers the safe attempt: the report says so, and the driver stays silent so that the
    terminal's watchdog drops the outputs."""
    with ValveTerminal(travel_s=TRAVEL_S, watchdog_s=0.3) as t, PneumaticGripper(
        t.url, poll_s=0.03, request_timeout_s=0.1
    ) as g:
        assert g.close_jaws() == "closed"
        t.set_silent()
        assert wait_for(lambda: g.safe_report is not None, 10.0)  # the poller timed out, then the attempt did
        assert not g.safe_report.confirmed and "DeviceTimeout" in g.safe_report.error
        t.set_silent(False)
        n = t.requests
        assert wait_for(lambda: t.watchdog_trips == 1, 10.0)
        assert t.requests == n and t.valve_outputs == {"open": False, "close": False}


def test_safe_returns_a_confirmed_report_or_raises(terminal):
    with PneumaticGripper(terminal.url, poll_s=None) as g:
        g.close_jaws()
        report = g.safe()
        assert report.confirmed and report.outputs == {"open": False, "close": False}
        assert not g.halted  # an explicit, confirmed safe() is no failure
        terminal.fail_requests(4)
        with pytest.raises(GripperFault, match="NOT confirmed"):
            g.safe()
        assert g.halted


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


def test_reads_are_tried_again_after_a_lost_reply_writes_never(terminal):
    from selfview.drivers.pneumatic_gripper.modbus import DEFAULT_READ_RETRIES, DEFAULT_TIMEOUT_S, ModbusLink

    assert DEFAULT_TIMEOUT_S >= 1.0 and DEFAULT_READ_RETRIES >= 1  # a busy PC's reply is late, not missing
    link = ModbusLink(terminal.url, timeout_s=0.15, retries=2)
    try:
        assert link.read("coil", 0, 2) == [False, False]
        n0, c0 = terminal.requests, link.connections
        terminal.set_silent(requests=2)  # two replies lost, the third answered
        assert link.read("discrete_input", 0, 2) == list(terminal.sensors)
        assert terminal.requests - n0 == 3 and link.connections == c0  # sent again on the same connection
        n0 = terminal.requests
        terminal.set_silent(requests=1)
        with pytest.raises(DeviceTimeout, match="x 1 attempt"):
            link.write_coil(0, True)  # a write that timed out may have been carried out: not sent again
        assert terminal.requests - n0 == 1
        n0 = terminal.requests
        terminal.set_silent()
        with pytest.raises(DeviceTimeout, match="x 3 attempt"):
            link.read("coil", 0, 2)
        assert terminal.requests - n0 == 3
    finally:
        terminal.set_silent(False)
        link.close()
    with PneumaticGripper(terminal.url, request_timeout_s=0.15, poll_s=None) as g:  # the default retries
        terminal.set_silent(requests=2)
        assert g.state() == "open" and g.halted is None and g.close_jaws() == "closed"


def test_rtu_reads_are_tried_again_like_tcp_writes_never():
    from selfview.drivers.pneumatic_gripper.modbus import ModbusLink

    with ValveTerminal(travel_s=TRAVEL_S, framing="rtu") as t:
        link = ModbusLink(t.url, timeout_s=0.15, retries=2)
        try:
            assert link.read("coil", 0, 2) == [False, False]
            n0, c0 = t.requests, link.connections
            t.set_silent(requests=2)  # two replies lost, the third answered
            assert link.read("discrete_input", 0, 2) == list(t.sensors)
            assert t.requests - n0 == 3 and link.connections == c0
            n0 = t.requests
            t.set_silent(requests=1)
            with pytest.raises(DeviceTimeout, match="x 1 attempt"):
                link.write_coil(0, True)
            assert t.requests - n0 == 1
        finally:
            t.set_silent(False)
            link.close()
