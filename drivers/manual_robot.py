"""``manual://``: the operator's arm, for a lab whose robot has no driver here.

The operator positions the arm (pendant, hand guiding) and confirms at the terminal: a motion to a named
location ("the plate", "above the plate") is a request to the operator, answered by Enter. The robot knows
no pose and no kinematics, so it refuses what needs one (a numeric target, ``where``, ``drive``,
``define``) with ``ConfigError`` and nothing asked: self-viewing needs no kinematics, so the off-line
calibration, the intrinsics from pictures and the monitor work; a procedure that computes poses does not.
"""

from __future__ import annotations

import sys
from collections.abc import Callable

import numpy as np

from selfview.drivers.robot_protocol import AbortResult, Where, check_distance_mm, check_speed_pct
from selfview.errors import ConfigError, DeviceError

__all__ = ["ManualRobot", "ManualLimits"]


class ManualLimits:
    """The manual robot's limits: the operator's. Any speed up to 100 % and any distance >= 0 pass (the
    operator moves the arm; a non-finite or negative one is refused, ``LimitError``, before the operator is
    asked); a position cannot be checked (the robot knows none) and is refused."""

    def check_position(self, p_mm, what: str) -> None:
        raise ConfigError(f"{what}: manual:// knows no pose, so no position can be checked or reached")

    def check_speed(self, pct: float, what: str) -> float:
        return check_speed_pct(pct, 100.0, what)

    def check_distance(self, d_mm: float, what: str) -> float:
        return check_distance_mm(d_mm, what)


def _terminal_ask(prompt: str) -> str:
    """Ask at the terminal: the prompt on stderr, the answer a line of stdin (EOF: refused)."""
    print(prompt, file=sys.stderr, flush=True)
    line = sys.stdin.readline()
    if not line:
        raise DeviceError("manual://: no operator at the terminal (end of input) to confirm the arm's position")
    return line.rstrip("\n")


class ManualRobot:
    """The ``Robot`` an operator moves. ``ask(prompt) -> answer`` is the terminal (default: stderr and
    stdin); an answer starting with 'n' or 'q' ('no', 'quit') refuses the motion (``DeviceError``)."""

    knows_poses = False

    def __init__(self, url: str = "manual://", *, ask: Callable[[str], str] | None = None):
        if not isinstance(url, str) or not url.lower().startswith("manual://"):
            raise ConfigError(f"manual robot URL: expected manual://, got {url!r}")
        self.url = url
        self.limits = ManualLimits()
        self._ask = ask or _terminal_ask
        self._connected = False
        self.requests: list[str] = []  # what the operator was asked, in order

    def __repr__(self) -> str:
        return f"ManualRobot({self.url!r})"

    @property
    def connected(self) -> bool:
        return self._connected

    def connect(self, **_) -> "ManualRobot":
        self._connected = True
        return self

    def close(self) -> None:
        self._connected = False

    def __enter__(self) -> "ManualRobot":
        return self.connect()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- what it cannot do --------------------------------------------------------------------------
    def _cannot(self, what: str) -> ConfigError:
        return ConfigError(f"manual:// cannot {what}: it knows no pose (the operator moves the arm); use a robot "
                           "driver for procedures that compute poses")

    def where(self) -> Where:
        raise self._cannot("report where the arm is")

    def pose_to_H(self, pose) -> np.ndarray:
        raise self._cannot("convert a numeric pose")

    def ready_pose(self) -> None:
        return None

    def location(self, name: str) -> tuple[float, ...]:
        raise self._cannot(f"read the pose of location {name!r}")

    def define(self, name: str, pose) -> None:
        raise self._cannot(f"define location {name!r}")

    def drive(self, joint: int, delta_deg: float, speed_pct: float) -> None:
        raise self._cannot(f"drive joint {joint}")

    # --- what the operator does -------------------------------------------------------------------
    def _request(self, text: str) -> None:
        if not self._connected:
            raise DeviceError("manual://: not connected")
        self.requests.append(text)
        answer = self._ask(f"{text}, then press Enter (n: refuse)")
        if answer.strip().lower()[:1] in ("n", "q"):
            raise DeviceError(f"manual://: the operator refused: {text}")

    def _named(self, target, kind: str) -> str:
        if isinstance(target, str) and target.strip():
            return target.strip()
        raise self._cannot(f"{kind} to a numeric target (only to a location the operator knows by name)")

    def move(self, target) -> None:
        self._request(f"Bring the arm to {self._named(target, 'move')}")

    def moves(self, target) -> None:
        self._request(f"Bring the arm in a straight line to {self._named(target, 'move in a straight line')}")

    def appro(self, target, distance_mm: float) -> None:
        name = self._named(target, "approach")
        d = self.limits.check_distance(distance_mm, "APPRO")
        self._request(f"Bring the arm {d:g} mm above {name} (along the tool's z)")

    def depart(self, distance_mm: float) -> None:
        d = self.limits.check_distance(distance_mm, "DEPART")
        self._request(f"Lift the arm {d:g} mm back along the tool's z")

    def ready(self) -> None:
        self._request("Bring the arm to its ready position")

    def speed(self, pct: float) -> None:
        """Nothing to set: the operator moves the arm at the pace the pendant allows (a speed that is no
        percentage is still refused, ``LimitError``)."""
        self.limits.check_speed(pct, "SPEED")

    def abort(self) -> AbortResult:
        """The software moves nothing; the operator holds the arm (and its emergency stop)."""
        return AbortResult(False, True, "manual://: nothing moves under software control; the operator holds the arm")
