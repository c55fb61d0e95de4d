"""Client-side limits of the PUMA 260 driver and its motion-time model.

Checked before a command is sent (``LimitError`` otherwise, nothing sent): the tool point must stay
in a workspace box of the base frame, joint motions within the joint limits, speeds at or below a
maximum. The same numbers bound how long the driver waits for a motion to finish.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfview.drivers.puma_val_serial._config import check_keys, read_yaml
from selfview.drivers.robot_protocol import check_distance_mm, check_speed_pct
from selfview.errors import ConfigError, LimitError

__all__ = ["ValLimits", "PUMA260_JOINT_LIMITS_DEG", "PUMA260_JOINT_SPEED_DEG_S", "VAL_READY_DEG"]

#: VAL's READY position (JT1..JT6, degrees): the arm straight up.
VAL_READY_DEG: tuple[float, ...] = (0.0, -90.0, 90.0, 0.0, 0.0, 0.0)

#: Published joint ranges of the PUMA 260 (JT1..JT6, degrees).
PUMA260_JOINT_LIMITS_DEG: tuple[tuple[float, float], ...] = (
    (-90.0, 200.0),
    (-240.0, 75.0),
    (-145.0, 145.0),
    (-185.0, 360.0),
    (-120.0, 120.0),
    (-360.0, 90.0),
)
#: Published top joint speeds (deg/s).
PUMA260_JOINT_SPEED_DEG_S: tuple[float, ...] = (119.0, 119.0, 164.0, 577.0, 431.0, 397.0)


@dataclass(frozen=True)
class ValLimits:
    """Limits the driver enforces, and the speeds it assumes to time motions.

    ``workspace_mm``: ((xmin, xmax), (ymin, ymax), (zmin, zmax)) of the tool point in the base frame.
    ``max_speed_pct``: the highest SPEED (and DRIVE speed) the driver sends.
    ``cart_speed_mm_s`` / ``rot_speed_deg_s``: the slowest tool speeds at SPEED 100 that a straight-line
    motion is assumed to reach (joint motions use ``joint_speed_deg_s``); with ``accel_s`` (the time a
    motion loses to speeding up and slowing down) they give its expected duration, and the wait for its
    prompt is ``timeout_factor`` times that plus ``timeout_margin_s``.
    ``assume_speed_pct``: the SPEED assumed before the driver has set one. ``calibrate_s``: CAL's duration.
    ``ready_joints_deg``: the joints of VAL's READY position (to time ``DO READY``).
    ``arrival_tol_mm`` / ``arrival_tol_deg`` / ``arrival_tol_joint_deg``: how close the WHERE after a
    motion must be to its target for the motion to count as complete (the prompt alone can be faked by
    one noise byte).
    """

    workspace_mm: tuple[tuple[float, float], ...] = ((-600.0, 600.0), (-600.0, 600.0), (0.0, 1000.0))
    joint_limits_deg: tuple[tuple[float, float], ...] = PUMA260_JOINT_LIMITS_DEG
    max_speed_pct: float = 50.0
    joint_speed_deg_s: tuple[float, ...] = PUMA260_JOINT_SPEED_DEG_S
    cart_speed_mm_s: float = 250.0
    rot_speed_deg_s: float = 90.0
    assume_speed_pct: float = 10.0
    accel_s: float = 0.5
    timeout_factor: float = 1.25
    timeout_margin_s: float = 3.0
    calibrate_s: float = 20.0
    ready_joints_deg: tuple[float, ...] = VAL_READY_DEG
    arrival_tol_mm: float = 1.0
    arrival_tol_deg: float = 0.5
    arrival_tol_joint_deg: float = 0.05

    def __post_init__(self):
        def pairs(name, n):
            v = getattr(self, name)
            try:
                ok = len(v) == n and all(len(p) == 2 and float(p[0]) < float(p[1]) for p in v)
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise ConfigError(f"limits.{name}: expected {n} [min, max] pairs with min < max, got {v!r}")

        pairs("workspace_mm", 3)
        pairs("joint_limits_deg", 6)
        if len(self.joint_speed_deg_s) != 6 or any(not float(v) > 0 for v in self.joint_speed_deg_s):
            raise ConfigError(f"limits.joint_speed_deg_s: expected six positive speeds, got {self.joint_speed_deg_s!r}")
        if not 0 < self.max_speed_pct <= 100:
            raise ConfigError(f"limits.max_speed_pct: expected 0 < pct <= 100, got {self.max_speed_pct!r}")
        if not 0 < self.assume_speed_pct <= 100:
            raise ConfigError(f"limits.assume_speed_pct: expected 0 < pct <= 100, got {self.assume_speed_pct!r}")
        for nm in ("cart_speed_mm_s", "rot_speed_deg_s", "timeout_factor", "calibrate_s", "arrival_tol_mm",
                   "arrival_tol_deg", "arrival_tol_joint_deg"):
            if not getattr(self, nm) > 0:
                raise ConfigError(f"limits.{nm}: expected a positive number, got {getattr(self, nm)!r}")
        for nm in ("timeout_margin_s", "accel_s"):
            if not getattr(self, nm) >= 0:
                raise ConfigError(f"limits.{nm}: expected >= 0, got {getattr(self, nm)!r}")
        for nm, v in vars(self).items():
            if any(not np.isfinite(float(x)) for x in np.ravel(np.asarray(v, dtype=float))):
                raise ConfigError(f"limits.{nm}: expected finite numbers, got {v!r}")

    @classmethod
    def from_dict(cls, data: dict) -> "ValLimits":
        """Limits from a mapping of field names (missing ones keep their defaults)."""
        kw = {}
        for k, v in check_keys(data, cls, "limits").items():
            try:
                kw[k] = tuple(tuple(float(x) for x in p) if isinstance(p, (list, tuple)) else float(p) for p in v) if isinstance(v, (list, tuple)) else float(v)
            except (TypeError, ValueError):
                raise ConfigError(f"limits.{k}: expected numbers, got {v!r}") from None
        return cls(**kw)

    @classmethod
    def load(cls, path) -> "ValLimits":
        """Limits from a YAML file of field names; raises ``ConfigError`` naming the problem."""
        return cls.from_dict(read_yaml(path, "limits"))

    # --- checks (raise LimitError; nothing has been sent) ---------------------------------------
    def check_position(self, p_mm, what: str) -> None:
        """The tool point ``p_mm`` (3,) must lie in the workspace box (``ConfigError`` for what is no point)."""
        try:
            p = np.asarray(p_mm, dtype=float).reshape(3)
        except (TypeError, ValueError):
            raise ConfigError(f"{what}: expected a tool point (x, y, z) in mm, got {p_mm!r}") from None
        for axis, v, (lo, hi) in zip("xyz", p, self.workspace_mm):
            if not lo <= v <= hi:
                raise LimitError(f"{what}: {axis} = {v:.2f} mm is outside the workspace {lo:g}..{hi:g} mm; nothing was sent")

    def check_speed(self, pct: float, what: str) -> float:
        """A SPEED (or DRIVE speed): finite, above 0 and at most ``max_speed_pct``. Returns it as a float."""
        return check_speed_pct(pct, self.max_speed_pct, what)

    def check_distance(self, d_mm: float, what: str) -> float:
        """An APPRO / DEPART distance (``check_distance_mm``). Returns it as a float."""
        return check_distance_mm(d_mm, what)

    def check_joint(self, joint: int, value_deg: float, what: str) -> None:
        """JT``joint`` (1..6; ``ConfigError`` otherwise) at ``value_deg`` must lie within its limits."""
        if isinstance(joint, bool) or not isinstance(joint, (int, np.integer)) or not 1 <= joint <= 6:
            raise ConfigError(f"{what}: joint {joint!r}; expected 1..6")
        lo, hi = self.joint_limits_deg[joint - 1]
        if not lo <= value_deg <= hi:
            raise LimitError(
                f"{what}: JT{joint} would reach {value_deg:.2f} deg, outside its limits {lo:g}..{hi:g} deg; nothing was sent"
            )

    # --- motion time -------------------------------------------------------------------------------
    def _bound(self, t_at_100: float, speed_pct: float | None) -> float:
        s = (speed_pct if speed_pct else self.assume_speed_pct) / 100.0
        return self.timeout_factor * (t_at_100 / s + self.accel_s) + self.timeout_margin_s

    def cartesian_timeout_s(self, distance_mm: float, angle_deg: float, speed_pct: float | None) -> float:
        """The wait (s) for a straight-line motion of the tool by ``distance_mm`` and ``angle_deg`` at
        SPEED ``speed_pct``: the slower of the two governs."""
        return self._bound(max(abs(distance_mm) / self.cart_speed_mm_s, abs(angle_deg) / self.rot_speed_deg_s), speed_pct)

    def joint_timeout_s(self, delta_deg, speed_pct: float | None, drive_pct: float = 100.0) -> float:
        """The wait (s) for a joint motion by ``delta_deg`` (6,) at SPEED ``speed_pct`` (and DRIVE speed):
        the slowest joint governs."""
        d = np.abs(np.asarray(delta_deg, dtype=float).reshape(6))
        t = float(np.max(d / np.asarray(self.joint_speed_deg_s))) * 100.0 / drive_pct
        return self._bound(t, speed_pct)
