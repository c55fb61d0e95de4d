"""The robot seam: what the engine and the procedures ask of a robot (``Robot``), and ``open_robot``.

A robot is chosen by its URL: ``manual://`` is the operator's arm (``drivers/manual_robot.py``); any other
URL (a device path, ``serial://``, ``socket://``, ``rfc2217://``, ``loop://``) is a PUMA on a VAL-II
controller (``drivers/puma_val_serial``), the first implementation. A new robot: its driver module
implementing ``Robot`` (one that moves under software control also calls ``selfview.drivers.signals.watch`` at
connect, so that a termination signal ABORTs it: ``abort_now`` and ``wait_motion_end``), one entry in
``ROBOT_SCHEMES``, and ``tests/drivers/robot_contract.py`` run against it.

Poses: the tool point T in the robot's base frame B, ``base_H_T`` (4, 4) [mm]; a robot's own pose
convention (VAL's x y z o a t) goes through ``pose_to_H``. A motion relative to the tool frame is
``moves(where().H @ T_delta)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from selfview.drivers.robot_protocol import AbortResult, Robot, RobotLimits, Where
from selfview.errors import ConfigError

__all__ = ["Robot", "RobotLimits", "Where", "AbortResult", "ROBOT_SCHEMES", "open_robot", "robot_scheme"]


def _puma(url: str, cell, kw: dict) -> Robot:
    from dataclasses import replace

    from selfview.drivers.puma_val_serial import PumaKinematics, PumaVAL, ValLimits, load_dialect

    spec = getattr(cell, "robot", None)

    def setting(key):
        return kw.get(key) if kw.get(key) is not None else getattr(spec, key, None)

    dialect, limits, kinematics = setting("dialect"), setting("limits"), setting("kinematics")
    limits = ValLimits.load(limits) if limits else ValLimits()
    if setting("max_speed") is not None:
        try:
            max_speed = float(setting("max_speed"))
        except (TypeError, ValueError):
            raise ConfigError(f"robot max_speed {setting('max_speed')!r}: expected a number of percent") from None
        limits = replace(limits, max_speed_pct=max_speed)
    return PumaVAL(url, dialect=load_dialect(dialect) if dialect else None, limits=limits,
                   kinematics=PumaKinematics.load(kinematics) if kinematics else None,
                   timeout_s=2.0 if kw.get("timeout_s") is None else kw["timeout_s"],
                   baudrate=9600 if kw.get("baudrate") is None else kw["baudrate"])


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
