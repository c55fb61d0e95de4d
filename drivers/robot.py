"""The robot seam: what the engine and the procedures ask of a robot (``Robot``), and ``open_robot``.

A robot is chosen by its URL: ``manual://`` is the operator's arm (``drivers/manual_robot.py``); any other
URL (a device path, ``serial://``, ``socket://``, ``rfc2217://``, ``loop://``) is a PUMA on a VAL-II
controller (``drivers/puma_val_serial``), the first implementation. A new robot: its driver module
implementing ``Robot``, one entry in ``ROBOT_SCHEMES``, and ``tests/drivers/robot_contract.py`` run
against it.

Poses: the tool point T in the robot's base frame B, ``base_H_T`` (4, 4) [mm]; a robot's own pose
convention (VAL's x y z o a t) goes through ``pose_to_H``. A motion relative to the tool frame is
``moves(where().H @ T_delta)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from selfview.errors import ConfigError

__all__ = ["Robot", "RobotLimits", "Where", "AbortResult", "ROBOT_SCHEMES", "open_robot", "robot_scheme"]


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


def _puma(url: str, cell, kw: dict) -> Robot:
    from dataclasses import replace

    from selfview.drivers.puma_val_serial import PumaKinematics, PumaVAL, ValLimits, load_dialect

    spec = getattr(cell, "robot", None)

    def setting(key):
        return kw.get(key) if kw.get(key) is not None else getattr(spec, key, None)

    dialect, limits, kinematics = setting("dialect"), setting("limits"), setting("kinematics")
    limits = ValLimits.load(limits) if limits else ValLimits()
    if setting("max_speed") is not None:
        limits = replace(limits, max_speed_pct=float(setting("max_speed")))
    return PumaVAL(url, dialect=load_dialect(dialect) if dialect else None, limits=limits,
                   kinematics=PumaKinematics.load(kinematics) if kinematics else None,
                   timeout_s=kw.get("timeout_s") or 2.0, baudrate=kw.get("baudrate") or 9600)


def _manual(url: str, cell, kw: dict) -> Robot:
    from selfview.drivers.manual_robot import ManualRobot

    return ManualRobot(url, ask=kw.get("ask"))


#: URL scheme -> factory(url, cell, settings); None stands for every URL no other scheme claims.
ROBOT_SCHEMES: dict[str | None, Callable[[str, Any, dict], Robot]] = {"manual": _manual, None: _puma}


def robot_scheme(url: str) -> str | None:
    """The ``ROBOT_SCHEMES`` key of a robot URL."""
    if not isinstance(url, str) or not url.strip():
        raise ConfigError(f"robot URL: expected a device path or URL such as socket://127.0.0.1:5000 or manual://, got {url!r}")
    scheme = url.split("://", 1)[0].lower() if "://" in url else None
    return scheme if scheme in ROBOT_SCHEMES else None


def open_robot(url: str, cell=None, *, dialect=None, limits=None, kinematics=None, max_speed=None,
               timeout_s: float | None = None, baudrate: int | None = None, ask=None) -> Robot:
    """The robot a URL names, not connected. ``cell``'s optional ``robot:`` section (dialect, limits and
    kinematics files, max_speed) sets the PUMA driver up; the keyword arguments override it (a
    command line's --dialect ...). ``ask`` (prompt -> answer) is the operator's terminal for
    ``manual://``. Raises ``ConfigError`` (a bad URL or settings file)."""
    kw = {"dialect": dialect, "limits": limits, "kinematics": kinematics, "max_speed": max_speed,
          "timeout_s": timeout_s, "baudrate": baudrate, "ask": ask}
    return ROBOT_SCHEMES[robot_scheme(url)](url, cell, kw)
