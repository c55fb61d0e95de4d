"""The PUMA 260's forward kinematics, as the driver needs them to check what ``WHERE`` prints.

VAL-II has no checksum, but ``WHERE`` prints the tool point's pose (X Y Z O A T) and the six joint
angles it came from: the pose must equal the forward kinematics of the joints through the controller's
TOOL. A digit swap in either line, or an O/A/T convention that is not the controller's, breaks that
equality. This module is the driver's own; the simulator (``selfview.mocks.puma260``) has its own.

The chain (standard Denavit-Hartenberg, lengths in mm, angles in degrees), the shoulder ``shoulder_mm``
above the base reference B (z up, x forward):

    link  theta         d          a            alpha
    1     q1            0          0            +90
    2     q2 + 180      0          upper_arm    0
    3     q3 - 180      lateral    elbow_drop   -90
    4     q4            forearm    0            +90
    5     q5            0          0            -90
    6     q6            flange     0            0

``q`` are VAL's joint angles (READY = 0, -90, 90, 0, 0, 0: the arm straight up). The TOOL is a
translation ``tool_mm`` in the flange frame (the cell's gripper: 170 mm along the flange z).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfview.drivers.puma_val_serial._config import check_keys, read_yaml
from selfview.errors import ConfigError

__all__ = ["PumaKinematics"]


def _rz(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    out = np.eye(4)
    out[0, 0], out[0, 1], out[1, 0], out[1, 1] = c, -s, s, c
    return out


def _rx(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    out = np.eye(4)
    out[1, 1], out[1, 2], out[2, 1], out[2, 2] = c, -s, s, c
    return out


def _t(x: float, y: float, z: float) -> np.ndarray:
    out = np.eye(4)
    out[:3, 3] = (x, y, z)
    return out


@dataclass(frozen=True)
class PumaKinematics:
    """The arm the driver talks to: nominal PUMA 260 link lengths (mm), VAL's joint zero, the TOOL.

    ``where_tol_mm`` / ``where_tol_deg``: how far WHERE's pose may lie from the kinematics of its own
    joint angles (both are printed with 2 decimals: 0.005 deg on six joints moves the tool point by up
    to ~0.2 mm; VAL-II documents no tolerance of its own, so this is the printing's, with margin).
    """

    shoulder_mm: float = 330.2
    upper_arm_mm: float = 198.1
    lateral_mm: float = 124.5
    elbow_drop_mm: float = 19.05
    forearm_mm: float = 203.2
    flange_mm: float = 63.5
    tool_mm: tuple[float, float, float] = (0.0, 0.0, 170.0)
    where_tol_mm: float = 0.5
    where_tol_deg: float = 0.1

    def __post_init__(self):
        for nm in ("shoulder_mm", "upper_arm_mm", "lateral_mm", "elbow_drop_mm", "forearm_mm", "flange_mm"):
            v = getattr(self, nm)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                raise ConfigError(f"kinematics.{nm}: expected a length >= 0 mm, got {v!r}")
        t = self.tool_mm
        if not (isinstance(t, (tuple, list)) and len(t) == 3 and all(np.isfinite(float(v)) for v in t)):
            raise ConfigError(f"kinematics.tool_mm: expected three numbers (mm in the flange frame), got {t!r}")
        for nm in ("where_tol_mm", "where_tol_deg"):
            if not getattr(self, nm) > 0:
                raise ConfigError(f"kinematics.{nm}: expected a positive tolerance, got {getattr(self, nm)!r}")

    @classmethod
    def from_dict(cls, data: dict) -> "PumaKinematics":
        kw = {}
        for k, v in check_keys(data, cls, "kinematics").items():
            try:
                kw[k] = tuple(float(x) for x in v) if k == "tool_mm" else float(v)
            except (TypeError, ValueError):
                raise ConfigError(f"kinematics.{k}: expected numbers, got {v!r}") from None
        return cls(**kw)

    @classmethod
    def load(cls, path) -> "PumaKinematics":
        return cls.from_dict(read_yaml(path, "kinematics"))

    def flange(self, q_deg) -> np.ndarray:
        """base_H_flange (4, 4) at VAL joint angles ``q_deg`` (6,)."""
        q = [float(v) for v in np.asarray(q_deg, dtype=float).reshape(6)]
        chain = [
            (q[0], 0.0, 0.0, 90.0),
            (q[1] + 180.0, 0.0, self.upper_arm_mm, 0.0),
            (q[2] - 180.0, self.lateral_mm, self.elbow_drop_mm, -90.0),
            (q[3], self.forearm_mm, 0.0, 90.0),
            (q[4], 0.0, 0.0, -90.0),
            (q[5], self.flange_mm, 0.0, 0.0),
        ]
        H = _t(0.0, 0.0, self.shoulder_mm)
        for theta, d, a, alpha in chain:
            H = H @ _rz(theta) @ _t(a, 0.0, d) @ _rx(alpha)
        return H

    def tool(self, q_deg) -> np.ndarray:
        """base_H_T (4, 4): the tool point at joint angles ``q_deg``."""
        return self.flange(q_deg) @ _t(*self.tool_mm)
