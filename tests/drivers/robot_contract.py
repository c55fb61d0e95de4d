"""The ``Robot`` contract (drivers/robot.py), reusable for the next robot: each ``check_*`` takes a connected
robot ready to move (calibrated, at a safe speed) and what it needs; ``test_robot_contract.py`` runs them
against every implementation. A new robot's tests call them with its own mock or hardware."""

from __future__ import annotations

import numpy as np
import pytest

from selfview.drivers.robot import AbortResult, Robot, Where
from selfview.errors import CellError, ConfigError, LimitError
from selfview.maths.geometry import check_rigid, pose_difference, trans
from selfview.procedures.engine import CellDevices, Engine, Step


def check_is_a_robot(robot) -> None:
    """It has every member the engine and the procedures use, and its limits check what it is sent."""
    assert isinstance(robot, Robot)
    assert robot.connected
    assert isinstance(robot.knows_poses, bool)
    assert robot.limits.check_distance(10.0, "contract") == 10.0
    assert robot.limits.check_speed(20.0, "contract") == 20.0
    for bad in (-1.0, float("nan"), float("inf"), "ten"):
        with pytest.raises(LimitError, match="contract: distance"):
            robot.limits.check_distance(bad, "contract")
    for bad in (0.0, -5.0, float("nan"), 101.0, "fast"):
        with pytest.raises(LimitError, match="contract: speed"):
            robot.limits.check_speed(bad, "contract")


def check_abort_when_idle(robot) -> None:
    """``abort`` never raises and reports whether nothing moves."""
    res = robot.abort()
    assert isinstance(res, AbortResult) and res.confirmed, res


def check_where_and_the_pose_convention(robot) -> None:
    """``where`` reports a rigid ``base_H_T`` (also ``.H``) that its own pose convention reproduces."""
    w = robot.where()
    assert isinstance(w, Where)
    check_rigid(w.H, "where")
    ang, dist = pose_difference(robot.pose_to_H(w.pose), w.H)
    assert dist < 0.02 and ang < 0.02


def check_tool_relative_straight_motion(robot, T_delta=None, tol_mm=0.02, tol_deg=0.03) -> None:
    """``moves(where().H @ T_delta)`` ends at that pose: a motion relative to the tool frame."""
    T_delta = trans(5.0, -3.0, -10.0) if T_delta is None else T_delta
    goal = robot.where().H @ T_delta
    robot.moves(goal)
    ang, dist = pose_difference(robot.where().H, goal)
    assert dist < tol_mm and ang < tol_deg, (dist, ang)


def check_a_plan_beyond_the_limits_moves_nothing(robot) -> None:
    """The engine checks a plan against the robot's limits before its first motion."""
    start = robot.where().H
    far = start @ trans(0.0, 0.0, -1e5)
    steps = [Step("moves", {"target": far})]
    with pytest.raises(LimitError):
        Engine(CellDevices(robot=robot)).check_plan(steps)
    ang, dist = pose_difference(robot.where().H, start)
    assert dist < 0.02 and ang < 0.02


def check_refuses_what_needs_a_pose(robot, asked: list) -> None:
    """A robot that knows no pose refuses numeric targets, ``where``, ``drive`` and ``define`` with
    ``ConfigError`` and asks nobody; the engine refuses such a plan before anything moves."""
    assert robot.knows_poses is False
    n = len(asked)
    for call in (robot.where, lambda: robot.moves(np.eye(4)), lambda: robot.move((300, 0, 50, 90, 90, 0)),
                 lambda: robot.appro(np.eye(4), 10.0), lambda: robot.drive(1, 5.0, 10.0),
                 lambda: robot.define("p", (300, 0, 50, 90, 90, 0)), lambda: robot.location("plate")):
        with pytest.raises(ConfigError, match="knows no pose"):
            call()
    with pytest.raises(ConfigError, match="plan refused before anything moved"):
        Engine(CellDevices(robot=robot)).check_plan([Step("move", {"target": "above"}), Step("moves", {"target": np.eye(4)})])
    assert len(asked) == n


def check_named_motions_go_through_the_operator(robot, asked: list) -> None:
    """Motions to named locations run through the engine as requests the operator confirms."""
    engine = Engine(CellDevices(robot=robot))
    steps = [Step("speed", {"pct": 20}), Step("move", {"target": "above the plate"}), Step("moves", {"target": "plate"}),
             Step("depart", {"distance_mm": 30.0})]
    engine.run(lambda e: [e.execute(s) for s in steps], steps)
    assert len(asked) == 3 and "plate" in asked[1] and "30 mm" in asked[2]


def check_a_refused_request_is_an_error(robot) -> None:
    with pytest.raises(CellError, match="refused"):
        robot.move("plate")
