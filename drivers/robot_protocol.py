"""The robot seam's types: what the engine and the procedures ask of a robot (``Robot``, ``RobotLimits``)
and what a robot answers (``Where``, ``AbortResult``). ``drivers/robot.py`` opens a robot by its URL."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from selfview.errors import LimitError

__all__ = ["Robot", "RobotLimits", "Where", "AbortResult", "check_speed_pct", "check_distance_mm"]


def check_speed_pct(pct, max_pct: float, what: str) -> float:
    """A speed in percent, finite and in ``0 < pct <= max_pct``, as a float; else ``LimitError`` naming
    ``what`` (nothing has been sent)."""
    try:
        v = float(pct)
    except (TypeError, ValueError):
        raise LimitError(f"{what}: speed {pct!r}; expected a number of percent; nothing was sent") from None
    if not np.isfinite(v) or not 0 < v <= max_pct:
        raise LimitError(f"{what}: speed {v:g} % is outside 0 < speed <= {max_pct:g} %; nothing was sent")
    return v


def check_distance_mm(d_mm, what: str) -> float:
    """An APPRO / DEPART distance, finite and >= 0 (a negative one would drive the tool beyond its location,
    into what it approaches), as a float; else ``LimitError`` naming ``what`` (nothing has been sent)."""
    try:
        d = float(d_mm)
    except (TypeError, ValueError):
        raise LimitError(f"{what}: distance {d_mm!r}; expected a number of mm; nothing was sent") from None
    if not np.isfinite(d) or d < 0:
        raise LimitError(f"{what}: distance {d:g} mm; expected a finite distance >= 0 mm along the tool's "
                         "approach side (a negative one passes beyond the location); nothing was sent")
    return d


@dataclass(frozen=True)
class Where:
    """The robot's pose as it reports it: ``pose`` in its own convention (VAL: x, y, z mm, o, a, t deg) of
    the tool point, ``joints`` (deg), ``base_H_T`` (4, 4) the tool point in the base frame [mm]."""

    pose: tuple[float, ...]
    joints: tuple[float, ...]
    base_H_T: np.ndarray

    @property
    def H(self) -> np.ndarray:
        """``base_H_T`` (4, 4): where a motion relative to the tool frame starts (``H @ T_delta``)."""
        return self.base_H_T

    def to_dict(self) -> dict:
        return {
            "pose": dict(zip(("x", "y", "z", "o", "a", "t"), self.pose)),
            "joints": list(self.joints),
            "base_H_T": np.round(self.base_H_T, 6).tolist(),
        }


@dataclass(frozen=True)
class AbortResult:
    """What ``abort()`` achieved: ``written`` ABORT went out; ``confirmed`` the controller answered it
    (``*Motion aborted*`` or its prompt: nothing moves); ``detail`` says how (or why not)."""

    written: bool
    confirmed: bool
    detail: str

    def __str__(self) -> str:
        if not self.written:
            return f"ABORT not written: {self.detail}"
        return f"ABORT sent and confirmed ({self.detail})" if self.confirmed else f"ABORT sent, NOT confirmed: {self.detail}"


@runtime_checkable
class RobotLimits(Protocol):
    """Client-side limits, checked before anything is sent; each raises ``LimitError`` naming ``what``."""

    def check_position(self, p_mm, what: str) -> None: ...
    def check_speed(self, pct: float, what: str) -> float: ...
    def check_distance(self, d_mm: float, what: str) -> float: ...


@runtime_checkable
class Robot(Protocol):
    """What the engine (``procedures/engine.py``) and the procedures use of a robot.

    ``knows_poses``: False for a robot that cannot say or reach a numeric pose (``manual://``): the
    engine then checks no planned position, and the robot refuses numeric targets, ``where`` and
    ``drive`` (``ConfigError``). Targets: a location name, a pose in the robot's convention or a (4, 4)
    ``base_H_T``. ``abort`` never raises; it stops whatever moves."""

    url: str | None
    limits: RobotLimits
    knows_poses: bool

    @property
    def connected(self) -> bool: ...
    def connect(self) -> Any: ...
    def close(self) -> None: ...
    def __enter__(self) -> Any: ...
    def __exit__(self, *exc) -> None: ...
    def where(self) -> Where: ...
    def pose_to_H(self, pose) -> np.ndarray: ...
    def ready_pose(self) -> np.ndarray | None: ...
    def location(self, name: str) -> tuple[float, ...]: ...
    def define(self, name: str, pose) -> None: ...
    def move(self, target) -> None: ...
    def moves(self, target) -> None: ...
    def appro(self, target, distance_mm: float) -> None: ...
    def depart(self, distance_mm: float) -> None: ...
    def drive(self, joint: int, delta_deg: float, speed_pct: float) -> None: ...
    def ready(self) -> None: ...
    def speed(self, pct: float) -> None: ...
    def abort(self) -> AbortResult: ...
