"""The ``Robot`` contract (tests/drivers/robot_contract.py) on each implementation: the PUMA VAL-II driver
against the simulated controller over a real pseudo-terminal, and ``manual://`` with a scripted operator;
``open_robot`` picks each by its URL and honours the cell's robot settings."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from selfview.files.cell import default_cell_path, parse_cell
from selfview.drivers.manual_robot import ManualRobot
from selfview.drivers.puma_val_serial import PumaVAL
from selfview.drivers.robot import open_robot
from selfview.errors import ConfigError, LimitError
from selfview.mocks.val_controller import ValController
from selfview.mocks.world import SimWorld
from tests.drivers import robot_contract as contract


@pytest.fixture
def puma(cell):
    c = ValController(SimWorld(cell, seed=7), seed=3, time_scale=0.02)
    c.start_pty()
    r = open_robot(c.url, cell, timeout_s=0.5)
    r.connect()
    r.calibrate()
    r.speed(50)
    r.move("above")
    yield r
    r.close()
    c.stop()


@pytest.fixture
def operator():
    asked, answers = [], []

    def ask(prompt):
        asked.append(prompt)
        return answers.pop(0) if answers else ""

    return asked, answers, ask


@pytest.fixture
def manual(operator):
    asked, _, ask = operator
    with open_robot("manual://", None, ask=ask) as r:
        yield r


def test_puma_keeps_the_contract(puma):
    assert isinstance(puma, PumaVAL)
    contract.check_is_a_robot(puma)
    contract.check_where_and_the_pose_convention(puma)
    contract.check_tool_relative_straight_motion(puma)
    contract.check_a_plan_beyond_the_limits_moves_nothing(puma)
    contract.check_abort_when_idle(puma)


def test_manual_keeps_the_contract(manual, operator):
    asked, answers, _ = operator
    assert isinstance(manual, ManualRobot)
    contract.check_is_a_robot(manual)
    contract.check_refuses_what_needs_a_pose(manual, asked)
    contract.check_named_motions_go_through_the_operator(manual, asked)
    contract.check_abort_when_idle(manual)
    answers.append("no")
    contract.check_a_refused_request_is_an_error(manual)


def test_manual_refuses_a_distance_or_speed_that_is_none_before_asking(manual, operator):
    """A negative or non-finite APPRO / DEPART distance, or a speed that is no percentage, never reaches the
    operator as a request ('Lift the arm nan mm'): ``LimitError`` naming it, nobody asked."""
    asked, _, _ = operator
    for call in (lambda: manual.appro("plate", -10.0), lambda: manual.appro("plate", float("nan")),
                 lambda: manual.depart(float("inf")), lambda: manual.depart("up"), lambda: manual.speed(0),
                 lambda: manual.speed(float("nan"))):
        with pytest.raises(LimitError, match="nothing was sent"):
            call()
    assert asked == []
    manual.appro("plate", 10.0)
    assert asked == ["Bring the arm 10 mm above plate (along the tool's z), then press Enter (n: refuse)"]


def test_open_robot_honours_the_cell_robot_section(tmp_path):
    raw = yaml.safe_load(default_cell_path().read_text())
    (tmp_path / "limits.yaml").write_text("max_speed_pct: 40\n")
    raw["robot"] = {"limits": "limits.yaml", "max_speed": 25}
    path = tmp_path / "cell.yaml"
    path.write_text(yaml.safe_dump(raw))
    from selfview.files.cell import load_cell

    cell = load_cell(path)
    r = open_robot("loop://", cell)
    assert r.limits.max_speed_pct == 25
    assert open_robot("loop://", cell, max_speed=10).limits.max_speed_pct == 10
    raw["robot"] = {"limits": 5}
    with pytest.raises(ConfigError, match="robot.limits: expected a file name"):
        parse_cell(raw)
    with pytest.raises(ConfigError, match="robot URL"):
        open_robot("", cell)
    with pytest.raises(ConfigError, match="robot max_speed 'fast': expected a number"):
        open_robot("loop://", cell, max_speed="fast")
    with pytest.raises(ConfigError, match="timeout_s"):  # refused, not silently the default 2 s
        open_robot("loop://", cell, timeout_s=0)
    with pytest.raises(ConfigError, match="baudrate"):
        open_robot("loop://", cell, baudrate=0)
    assert open_robot("loop://", cell).timeout_s == 2.0 and open_robot("loop://", cell, timeout_s=0.5).timeout_s == 0.5


def test_the_puma_converts_only_six_finite_numbers_to_a_pose():
    """``pose_to_H`` (the seam's pose convention) names a wrong pose instead of unpacking it or returning NaN."""
    from selfview.drivers.puma_val_serial import ValLimits

    r = open_robot("loop://")
    for bad in ((300, 0, 50, 90, 90), (300, 0, 50, 90, 90, float("nan")), "above", None):
        with pytest.raises(ConfigError, match="pose: expected 6 finite numbers"):
            r.pose_to_H(bad)
    assert r.pose_to_H((300, 0, 50, 90, 90, 0))[:3, 3].tolist() == [300.0, 0.0, 50.0]
    for joint in (0, 7, True, 1.0):
        with pytest.raises(ConfigError, match="expected 1..6"):
            ValLimits().check_joint(joint, 0.0, "DRIVE")
    for p in ((300, 0), np.eye(4), "above"):
        with pytest.raises(ConfigError, match="MOVE: expected a tool point"):
            ValLimits().check_position(p, "MOVE")
    with pytest.raises(LimitError, match="x = nan mm is outside the workspace"):
        ValLimits().check_position((float("nan"), 0, 100), "MOVE")


def test_the_devices_table_names_the_operators_arm(cell):
    from selfview.procedures.commands.devices import _robot

    text, row = _robot("manual://", cell, 1.0)
    assert "operator's arm" in text and row == {"manual": True}
