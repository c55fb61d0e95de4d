"""WHERE's pose against the kinematics of its own joint angles: no false alarm wherever
the arm can be, and a one-digit corruption caught.

The tolerance is the print rounding, derived, not chosen: VAL-II prints JT1..JT6, X Y Z and O A T with
2 decimals, so each printed joint is up to 0.005 deg off the angle the pose was computed from, each
coordinate up to 0.005 mm and each O/A/T angle up to 0.005 deg off the pose. Through the arm's lever arms
that allows at most 0.04-0.14 mm and 0.026-0.032 deg across the PUMA 260's workspace, and only in the
directions that rounding can move the pose (``PumaKinematics.where_fit``). The former flat 0.5 mm /
0.1 deg let a printed joint changed by 0.08 deg, or a coordinate changed by 0.1 mm, pass.

Replies here come from the simulator's kinematics (``selfview.mocks.puma260``) and O/A/T formatting,
never from the driver's, so the check is tested against an independent model of the controller.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from selfview.drivers.puma_val_serial import OAT_CONVENTIONS, PumaKinematics, PumaVAL, ValDialect
from selfview.errors import ConfigError, ProtocolError
from selfview.maths.geometry import inv_H, rotation_angle
from selfview.mocks.puma260 import READY_DEG, ArmConfig, Puma260, Unreachable, make_tool
from selfview.mocks.val_controller import TOOL_LENGTH_MM, ValController

VAL = ValDialect()
VPLUS = ValDialect(euler=OAT_CONVENTIONS["vplus"])
KIN = PumaKinematics()
TOOL = make_tool(TOOL_LENGTH_MM)
STEP = 0.005  # half the last printed digit (2 decimals): the most rounding moves a printed value

# the two configurations the full fault campaign refused (the tool straight down: A = 90, JT4 = -180)
CAMPAIGN_FALSE_ALARMS = ((20.84, -136.99, 25.6, -180.0, 68.61, 20.84), (20.84, -149.53, 24.9, -180.0, 55.37, 20.84))


def printed(values) -> tuple[float, ...]:
    """Values as the controller prints them (2 decimals)."""
    return tuple(float(f"{v:.2f}") for v in values)


def sim_pose(q, dialect=VAL) -> tuple[float, ...]:
    """The pose the simulated controller computes at joints ``q``, unrounded."""
    return dialect.H_to_pose(Puma260().fk(q) @ TOOL)


def _tool_vertical_and_level_configurations() -> list[tuple[float, ...]]:
    """Joints that put O/A/T at or near its singularity (A = +-90: the tool straight down or up) and
    at A = 0 / 180 (the tool level), in both wrist configurations, with JT4 / JT6 moved by whole turns
    to +-180 where the limits allow: the inverse kinematics of the simulator."""
    out = []
    for (x, y, z), (o, t), a, wrist in itertools.product(
        ((350.0, 0.0, 80.0), (350.0, 0.0, 140.0), (250.0, 150.0, 60.0), (300.0, -120.0, 200.0), (0.0, 350.0, 100.0)),
        ((-90.0, 0.0), (134.68, -141.0), (-180.0, 180.0), (30.0, 60.0)),
        (90.0, 89.996, 90.004, 89.99999, -90.0, -89.997, 0.0, 180.0, 0.004),
        ("noflip", "flip"),
    ):
        H = VAL.pose_to_H((x, y, z, o, a, t))
        try:
            q = Puma260(config=ArmConfig(wrist=wrist)).ik(H @ inv_H(TOOL), READY_DEG)
        except Unreachable:
            continue
        out.append(tuple(q))
        for j, turn in ((3, 360.0), (3, -360.0), (5, -360.0)):  # JT4 in -185..360, JT6 in -360..90
            q2 = np.array(q)
            q2[j] += turn
            if (j == 3 and -185.0 <= q2[j] <= 360.0) or (j == 5 and -360.0 <= q2[j] <= 90.0):
                out.append(tuple(q2))
    return out


def _joint_grid() -> list[tuple[float, ...]]:
    return [
        q for q in itertools.product(
            (-90.0, 20.84, 135.0), (-200.0, -136.99, -90.0), (-45.0, 25.6, 90.0),
            (-180.0, 0.0, 180.0, 270.0), (-90.0, 0.0, 68.61), (-180.0, 20.84, 90.0),
        )
    ]


CONFIGURATIONS = [*CAMPAIGN_FALSE_ALARMS, *_tool_vertical_and_level_configurations(), *_joint_grid()]


def test_the_sweep_covers_the_singularity_the_wrist_flips_and_the_wrap():
    poses = np.array([sim_pose(q) for q in CONFIGURATIONS])
    q = np.array(CONFIGURATIONS)
    assert len(CONFIGURATIONS) > 700
    assert np.sum(np.abs(np.abs(poses[:, 4]) - 90.0) < 0.01) > 100  # A at (or within 0.01 deg of) +-90
    assert np.sum(np.abs(np.abs(poses[:, 4]) - 90.0) < 1e-9) > 10  # exactly at the singularity
    assert np.any(np.abs(poses[:, 4]) < 0.01)  # the tool level (VAL's A stays in -90..90)
    vplus_a = np.array([sim_pose(c, VPLUS)[4] for c in CONFIGURATIONS])  # V+'s singularities: A = 0, 180
    assert np.sum(np.abs(vplus_a) < 0.01) > 10 and np.sum(np.abs(vplus_a - 180.0) < 0.01) > 10
    assert np.any(q[:, 4] < -1.0) and np.any(q[:, 4] > 1.0) and np.any(q[:, 4] == 0.0)  # both wrists, and singular
    assert np.any(q[:, 3] == -180.0) and np.any(q[:, 3] == 180.0) and np.any(np.abs(q[:, 5]) == 180.0)
    assert np.any(np.abs(np.abs(poses[:, 3:]) - 180.0) < 0.01)  # O or T at the wrap


@pytest.mark.parametrize("dialect", [VAL, VPLUS], ids=["val", "vplus"])
def test_no_false_alarm_anywhere_in_the_sweep(dialect):
    worst = 0.0
    for q in CONFIGURATIONS:
        fit = KIN.where_fit(printed(sim_pose(q, dialect)), printed(q), dialect.euler, 2)
        assert fit.consistent, (q, fit)
        worst = max(worst, fit.ratio)
    assert worst < 1.0


def test_no_false_alarm_with_rounding_at_its_worst_and_the_bound_is_reached():
    # the true joints at a corner of their rounding cells, the corner that moves the pose most: the
    # reply is still consistent, and such replies use up most of the bound (it is tight, not a margin)
    rng = np.random.default_rng(18)
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=6))) * (STEP - 1e-6)
    ratios = []
    for i in rng.choice(len(CONFIGURATIONS), 60, replace=False):
        q_print = np.array(printed(CONFIGURATIONS[i]))
        H0 = Puma260().fk(q_print) @ TOOL
        worst = max(corners, key=lambda s: np.linalg.norm((Puma260().fk(q_print + s) @ TOOL)[:3, 3] - H0[:3, 3]))
        fit = KIN.where_fit(printed(sim_pose(q_print + worst)), tuple(q_print), VAL.euler, 2)
        assert fit.consistent, (q_print, worst, fit)
        ratios.append(fit.ratio)
    assert max(ratios) > 0.7, max(ratios)


def test_the_bound_is_the_print_rounding_through_the_lever_arms():
    # with the tool down over the plate (the campaign's WHERE): 0.11 mm / 0.031 deg; nowhere near the
    # former 0.5 mm / 0.1 deg; and it scales with the printed precision
    q = printed(CAMPAIGN_FALSE_ALARMS[0])
    fit = KIN.where_fit(printed(sim_pose(q)), q, VAL.euler, 2)
    assert 0.09 < fit.bound_mm < 0.13 and 0.025 < fit.bound_deg < 0.035, fit
    # by hand: the six lever arms |z_i x (p - o_i)| times 0.005 deg, plus 0.005 mm on each coordinate,
    # bound the position from above; the worst corner cannot exceed that sum
    F = KIN.frames(q)
    p = (KIN.tool(q))[:3, 3]
    levers = [np.linalg.norm(np.cross(f[:3, 2], p - f[:3, 3])) for f in F[:6]]
    assert fit.bound_mm <= np.radians(STEP) * sum(levers) + np.sqrt(3) * STEP + 1e-9
    assert fit.bound_deg <= 9 * STEP + 1e-9  # six joints and three O/A/T angles
    fine = KIN.where_fit(tuple(round(v, 3) for v in sim_pose(q)), q, VAL.euler, 3)
    assert fine.bound_mm == pytest.approx(fit.bound_mm / 10) and fine.bound_deg == pytest.approx(fit.bound_deg / 10)


@pytest.mark.parametrize("what", ["joint 0.08 deg", "pose 0.1 mm"])
def test_a_one_digit_change_is_caught_everywhere_in_the_sweep(what):
    rng = np.random.default_rng(4)
    for i in rng.choice(len(CONFIGURATIONS), 40, replace=False):
        q = printed(CONFIGURATIONS[i])
        pose = printed(sim_pose(q))
        for k, sign in itertools.product(range(6 if what.startswith("joint") else 3), (-1.0, 1.0)):
            if what.startswith("joint"):
                bad_q, bad_pose = q[:k] + (round(q[k] + sign * 0.08, 2),) + q[k + 1:], pose
            else:
                bad_q, bad_pose = q, pose[:k] + (round(pose[k] + sign * 0.1, 2),) + pose[k + 1:]
            fit = KIN.where_fit(bad_pose, bad_q, VAL.euler, 2)
            assert not fit.consistent, (what, q, k, sign, fit)


def test_another_oat_convention_is_refused_at_the_singularity_too():
    # V+ angles read as VAL's do not fit, also with the tool straight down (both sets degenerate)
    named = 0
    for q in CONFIGURATIONS[:: 7]:
        pose = printed(sim_pose(q, VPLUS))
        turn = np.degrees(rotation_angle(VAL.pose_to_H(pose)[:3, :3].T @ VPLUS.pose_to_H(pose)[:3, :3]))
        if turn > 0.5:  # the two conventions give these numbers different rotations
            assert not KIN.where_fit(pose, printed(q), VAL.euler, 2).consistent, q
            assert KIN.where_fit(pose, printed(q), VPLUS.euler, 2).consistent, q
            named += 1
    assert named > 80


def test_a_known_model_difference_is_stated_not_hidden_in_the_rounding():
    # a controller whose TOOL is 0.3 mm longer than the driver's: refused, unless the site states it
    q = printed(CAMPAIGN_FALSE_ALARMS[0])
    pose = printed(VAL.H_to_pose(Puma260().fk(q) @ make_tool(TOOL_LENGTH_MM + 0.3)))
    assert not KIN.where_fit(pose, q, VAL.euler, 2).consistent
    assert PumaKinematics(where_model_mm=0.3).where_fit(pose, q, VAL.euler, 2).consistent
    with pytest.raises(ConfigError, match="where_model_deg"):
        PumaKinematics.from_dict({"where_model_deg": -1})


# --- through the simulated controller on its pseudo-terminal ----------------------------------------------
def changed(reply: str, line: int, col: int, by: float) -> str:
    """WHERE's reply with value ``col`` of its ``line``-th non-empty line (1: the pose, 3: the joints)
    moved by ``by`` in the printed digits, as a corrupted byte would."""
    rows = reply.split("\r\n")
    i = [n for n, r in enumerate(rows) if r.strip()][line]
    vals = [float(rows[i][k * 9:(k + 1) * 9]) for k in range(6)]
    vals[col] = round(vals[col] + by, 2)
    rows[i] = "".join(f"{v:9.2f}" for v in vals)
    return "\r\n".join(rows)


@pytest.fixture(scope="module")
def sim_and_robot():
    with ValController(seed=18, time_scale=0.0, calibrated=True) as sim:
        sim.start_pty()
        with PumaVAL(sim.url, timeout_s=1.0) as robot:
            yield sim, robot


def test_the_simulators_where_passes_the_drivers_check_at_the_singular_and_flipped_configurations(sim_and_robot):
    sim, robot = sim_and_robot
    some = [*CAMPAIGN_FALSE_ALARMS, *_tool_vertical_and_level_configurations()[::4]]
    assert len(some) > 40
    for q in some:
        sim._set_joints(q)  # noqa: SLF001 - puts the arm there without a motion
        w = robot.where()  # a false alarm would raise ProtocolError
        assert w.joints == printed(q)
    assert sum(1 for ln in sim.received if ln == "WHERE") == len(some)  # each read once: none refused


def test_the_campaigns_accepted_corruptions_are_now_read_again(sim_and_robot, monkeypatch):
    # the fault campaign's three accepted WHEREs (tool down over the plate): Y 0.00 -> 0.10, one joint
    # 0.08 / 0.09 deg off; each is refused and WHERE read again, the clean reply accepted
    sim, robot = sim_and_robot
    H = VAL.pose_to_H((350.0, 0.0, 80.0, -90.0, 90.0, 0.0))
    q = Puma260().ik(H @ inv_H(TOOL), READY_DEG)
    sim._set_joints(q)  # noqa: SLF001
    real = sim._cmd_where  # noqa: SLF001
    for line, old, new in ((1, 2, 0.1), (3, 4, 0.08), (3, 5, -0.09)):
        calls = []

        def corrupt_once(link, inp, head, line=line, col=old, by=new):
            reply = real(link, inp, head)
            if calls:
                return reply
            calls.append(1)
            return changed(reply, line, col, by)

        monkeypatch.setattr(sim, "_cmd_where", corrupt_once)
        n0 = sim.received.count("WHERE")
        w = robot.where()
        assert sim.received.count("WHERE") - n0 == 2, (line, old, new)
        assert w.joints == printed(q)


def test_a_where_that_stays_off_by_one_digit_is_refused_naming_the_rounding(sim_and_robot, monkeypatch):
    sim, robot = sim_and_robot
    sim._set_joints(CAMPAIGN_FALSE_ALARMS[0])  # noqa: SLF001
    real = sim._cmd_where  # noqa: SLF001

    monkeypatch.setattr(sim, "_cmd_where", lambda link, inp, head: changed(real(link, inp, head), 1, 1, 0.1))
    with pytest.raises(ProtocolError, match=r"times what printing both to 2 decimals can explain \(up to 0\.1"):
        robot.where()
