"""The gripper driver against a Modbus server written elsewhere: pyModbusTCP's (not pymodbus).

The test plays the pneumatics: a DataBank whose solenoid writes set the reed-switch inputs at once.
"""

from __future__ import annotations

import pytest

pyModbusTCP_server = pytest.importorskip("pyModbusTCP.server", reason="test extra pyModbusTCP not installed")

from selfview.drivers.pneumatic_gripper import IoMap, ModbusExceptionReply, PneumaticGripper, Point  # noqa: E402


class GripperBank(pyModbusTCP_server.DataBank):
    """Coils 0 (open) / 1 (close) drive discrete inputs 0 (open) / 1 (closed); holding register 5
    bits 0 / 1 drive input register 6 bits 0 / 1 the same way."""

    def __init__(self):
        super().__init__(coils_size=16, d_inputs_size=16, h_regs_size=16, i_regs_size=16)
        self.set_discrete_inputs(0, [True, False])
        self.set_input_registers(6, [0b01])

    def on_coils_change(self, address, from_value, to_value, srv_info):
        o, c = self.get_coils(0, 2)
        if o != c:
            self.set_discrete_inputs(0, [o, c])

    def on_holding_registers_change(self, address, from_value, to_value, srv_info):
        (word,) = self.get_holding_registers(5, 1)
        o, c = word & 1, (word >> 1) & 1
        if o != c:
            self.set_input_registers(6, [0b01 if o else 0b10])


@pytest.fixture
def server():
    bank = GripperBank()
    srv = pyModbusTCP_server.ModbusServer(host="127.0.0.1", port=0, no_block=True, data_bank=bank)
    srv.start()
    port = srv._service.server_address[1]  # pyModbusTCP has no public accessor for a port-0 bind
    yield bank, f"modbus-tcp://127.0.0.1:{port}?unit=1"
    srv.stop()


def test_coil_map_against_pymodbustcp(server):
    bank, url = server
    with PneumaticGripper(url, timeout_s=0.5) as g:
        assert g.state() == "open"
        assert g.close_jaws() == "closed"
        assert bank.get_coils(0, 2) == [False, True]
        assert g.open_jaws() == "open"
        assert bank.get_coils(0, 2) == [True, False]
        g.safe()
        assert bank.get_coils(0, 2) == [False, False]
        assert g.state() == "open"  # a double valve holds its position


def test_register_bits_read_modify_write_against_pymodbustcp(server):
    bank, url = server
    bank.set_holding_registers(5, [0xA000])  # other valves' bits, which must survive
    m = IoMap(open_valve=Point.parse("hr:5.0"), close_valve=Point.parse("hr:5.1"),
              open_sensor=Point.parse("ir:6.0"), closed_sensor=Point.parse("ir:6.1"))
    with PneumaticGripper(url, io_map=m) as g:
        assert g.close_jaws() == "closed"
        assert bank.get_holding_registers(5, 1) == [0xA002]
        assert g.open_jaws() == "open"
        assert bank.get_holding_registers(5, 1) == [0xA001]


def test_mask_write_refused_by_a_server_without_fc22(server):
    # pyModbusTCP does not implement Mask Write Register: the exception reply must surface as such
    bank, url = server
    m = IoMap(open_valve=Point.parse("hr:5.0"), close_valve=Point.parse("hr:5.1"),
              open_sensor=Point.parse("ir:6.0"), closed_sensor=Point.parse("ir:6.1"), register_write="mask")
    with PneumaticGripper(url, io_map=m) as g:
        with pytest.raises(ModbusExceptionReply) as e:
            g.close_jaws()
        assert e.value.function == 22 and e.value.code == 1  # illegal function
        assert bank.get_holding_registers(5, 1) == [0]
