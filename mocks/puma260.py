"""PUMA 260 kinematics: forward and closed-form inverse, from the published geometry.

Link lengths and joint offsets are parameters (``Puma260Geometry``), so a simulated robot can be given
kinematic errors. ``q`` are VAL's joint angles (JT1..JT6, degrees).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from selfview.drivers.puma_val_serial.limits import PUMA260_JOINT_LIMITS_DEG, PUMA260_JOINT_SPEED_DEG_S, VAL_READY_DEG
from selfview.maths.geometry import make_H, trans

__all__ = ["Puma260Geometry", "ArmConfig", "Puma260", "Unreachable", "READY_DEG", "make_tool"]

#: VAL's READY position: the arm straight up.
READY_DEG = VAL_READY_DEG
#: DH theta = VAL joint angle + this (degrees): the structure's zero, not a calibration error.
_VAL_ZERO_TO_DH_DEG = (0.0, 180.0, -180.0, 0.0, 0.0, 0.0)
_ALPHA_DEG = (90.0, 0.0, -90.0, 90.0, -90.0, 0.0)


def _dh(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    """Rot(z, theta) Trans(a, 0, d) Rot(x, alpha) of one standard DH link (radians, mm)."""
    ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


class Unreachable(ValueError):
    """A pose has no joint solution in the chosen configuration and the joint limits; ``reason`` says why."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


@dataclass(frozen=True)
class Puma260Geometry:
    """Link lengths (mm), joint offsets, limits and top speeds of a PUMA 260.

    Defaults are the published nominal geometry; change them to give a simulated robot kinematic errors.
    """

    shoulder_mm: float = 330.2
    upper_arm_mm: float = 198.1
    lateral_mm: float = 124.5
    elbow_drop_mm: float = 19.05
    forearm_mm: float = 203.2
    flange_mm: float = 63.5
    joint_offsets_deg: tuple[float, ...] = (0.0,) * 6
    joint_limits_deg: tuple[tuple[float, float], ...] = PUMA260_JOINT_LIMITS_DEG
    joint_speed_deg_s: tuple[float, ...] = PUMA260_JOINT_SPEED_DEG_S

    def __post_init__(self):
        for nm in ("shoulder_mm", "upper_arm_mm", "lateral_mm", "elbow_drop_mm", "forearm_mm", "flange_mm"):
            v = getattr(self, nm)
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"Puma260Geometry.{nm}: expected a finite length >= 0 mm, got {v!r}")
        if self.upper_arm_mm <= 0 or self.forearm_mm <= 0:
            raise ValueError("Puma260Geometry: upper arm and forearm must be longer than 0 mm")
        if len(self.joint_offsets_deg) != 6 or len(self.joint_limits_deg) != 6 or len(self.joint_speed_deg_s) != 6:
            raise ValueError("Puma260Geometry: joint offsets, limits and speeds need six entries each")
        for j, (lo, hi) in enumerate(self.joint_limits_deg, 1):
            if not lo < hi:
                raise ValueError(f"Puma260Geometry.joint_limits_deg: JT{j} range {lo}..{hi} is empty")
        if any(not v > 0 for v in self.joint_speed_deg_s):
            raise ValueError(f"Puma260Geometry.joint_speed_deg_s: expected positive speeds, got {self.joint_speed_deg_s}")

    def with_errors(self, **changes) -> "Puma260Geometry":
        """A copy with some lengths or offsets changed (a robot with kinematic errors)."""
        return replace(self, **changes)


@dataclass(frozen=True)
class ArmConfig:
    """Which of the (up to) eight solutions inverse kinematics returns: ``reach`` 'front' (the wrist
    centre in front of the shoulder, r > 0) or 'back', ``elbow`` 'above' or 'below' the shoulder-wrist
    line (seen from the side on which the wrist lies to the right), ``wrist`` 'noflip' (JT5 >= 0) or
    'flip'. Joint angles are wrapped by whole turns into the limits, nearest to a given joint state."""

    reach: str = "front"
    elbow: str = "above"
    wrist: str = "noflip"

    def __post_init__(self):
        for nm, ok in (("reach", ("front", "back")), ("elbow", ("above", "below")), ("wrist", ("noflip", "flip"))):
            if getattr(self, nm) not in ok:
                raise ValueError(f"ArmConfig.{nm}: expected one of {', '.join(ok)}, got {getattr(self, nm)!r}")


@dataclass
class Puma260:
    """Forward and inverse kinematics of the flange in the base frame B (mm, degrees)."""

    geometry: Puma260Geometry = field(default_factory=Puma260Geometry)
    config: ArmConfig = field(default_factory=ArmConfig)

    # --- forward ----------------------------------------------------------------------------------
    def _theta(self, q_deg) -> np.ndarray:
        q = np.asarray(q_deg, dtype=float).reshape(6)
        return np.radians(q + np.asarray(_VAL_ZERO_TO_DH_DEG) + np.asarray(self.geometry.joint_offsets_deg))

    def _links(self):
        g = self.geometry
        d = (0.0, 0.0, g.lateral_mm, g.forearm_mm, 0.0, g.flange_mm)
        a = (0.0, g.upper_arm_mm, g.elbow_drop_mm, 0.0, 0.0, 0.0)
        return d, a

    def frames(self, q_deg) -> list[np.ndarray]:
        """The (4, 4) poses in B of DH frames 0..6 (frame 0 at the shoulder, 6 at the flange)."""
        # Standard Denavit-Hartenberg in the usual PUMA structure (shoulder and upper arm in one plane, a
        # lateral offset between upper arm and forearm, a small elbow drop, a spherical wrist), the
        # shoulder frame ``shoulder`` mm above the base reference (B: z up, x forward):
        #     link  theta      d         a           alpha
        #     1     q1 + z1    0         0           +90
        #     2     q2 + z2    0         upper_arm   0
        #     3     q3 + z3    lateral   elbow_drop  -90
        #     4     q4 + z4    forearm   0           +90
        #     5     q5 + z5    0         0           -90
        #     6     q6 + z6    flange    0           0
        # ``z`` maps VAL's zero to the DH zero so that VAL's READY (0, -90, 90, 0, 0, 0) holds the arm
        # straight up.
        d, a = self._links()
        H = trans(0.0, 0.0, self.geometry.shoulder_mm)
        out = [H]
        for th, di, ai, al in zip(self._theta(q_deg), d, a, np.radians(_ALPHA_DEG)):
            H = H @ _dh(th, di, ai, al)
            out.append(H)
        return out

    def fk(self, q_deg) -> np.ndarray:
        """base_H_flange (4, 4) for VAL joint angles ``q_deg`` (6,)."""
        return self.frames(q_deg)[-1]

    # --- inverse ----------------------------------------------------------------------------------
    def ik(self, base_H_flange, q_near_deg=None) -> np.ndarray:
        """VAL joint angles (6,) in degrees that put the flange at ``base_H_flange`` (4, 4).

        ``q_near_deg`` (the current joints) picks among whole-turn equivalents and fixes JT4 at the
        wrist singularity (JT5 = 0). Raises ``Unreachable`` naming the cause.
        """
        g = self.geometry
        H = np.asarray(base_H_flange, dtype=float)
        if H.shape != (4, 4) or not np.all(np.isfinite(H)):
            raise Unreachable(f"target: expected a finite 4x4 transform, got shape {H.shape}")
        q_near = np.asarray(READY_DEG if q_near_deg is None else q_near_deg, dtype=float).reshape(6)
        R = H[:3, :3]
        pw = H[:3, 3] - g.flange_mm * R[:, 2] - np.array([0.0, 0.0, g.shoulder_mm])
        px, py, pz = pw
        d3, a2, a3, d4 = g.lateral_mm, g.upper_arm_mm, g.elbow_drop_mm, g.forearm_mm
        rho2 = px * px + py * py - d3 * d3
        if rho2 < 0:
            raise Unreachable(
                f"wrist centre ({px:.1f}, {py:.1f}) mm lies within the lateral offset {d3} mm of the base axis"
            )
        r = (1.0 if self.config.reach == "front" else -1.0) * np.sqrt(rho2)
        th1 = np.arctan2(py, px) - np.arctan2(-d3, r)
        L = np.hypot(a3, d4)
        K = (r * r + pz * pz - a2 * a2 - a3 * a3 - d4 * d4) / (2.0 * a2)
        if abs(K) > L * (1 + 1e-12):
            dist = float(np.hypot(r, pz))
            raise Unreachable(
                f"wrist centre {dist:.1f} mm from the shoulder; the arm reaches "
                f"{abs(a2 - L):.1f}..{a2 + L:.1f} mm"
            )
        beta = np.arctan2(d4, a3)
        acos = np.arccos(np.clip(K / L, -1.0, 1.0))
        best = None
        for th3 in (-beta + acos, -beta - acos):
            u = a3 * np.cos(th3) - d4 * np.sin(th3)
            w = a3 * np.sin(th3) + d4 * np.cos(th3)
            th2 = np.arctan2(pz, r) - np.arctan2(w, a2 + u)
            # elbow above the shoulder-wrist line, seen with the wrist to the right
            cross = np.sign(r if r != 0 else 1.0) * (r * a2 * np.sin(th2) - pz * a2 * np.cos(th2))
            above = cross > 0
            if above == (self.config.elbow == "above"):
                best = (th2, th3)
        if best is None:  # stretched straight: both solutions coincide
            best = (th2, th3)
        th2, th3 = best
        # wrist: R_3^6 = Rz(th4) Ry(-th5) Rz(th6) (alpha4 = +90, alpha5 = -90)
        zero = np.radians(np.asarray(_VAL_ZERO_TO_DH_DEG) + np.asarray(g.joint_offsets_deg))
        q123 = np.degrees(np.array([th1, th2, th3]) - zero[:3])
        R03 = self.frames(np.concatenate([q123, np.zeros(3)]))[3][:3, :3]
        M = R03.T @ R
        sb = np.hypot(M[0, 2], M[1, 2])
        if sb < 1e-9:
            if M[2, 2] < 0:
                raise Unreachable("the flange would have to fold back onto the forearm (JT5 = 180 deg)")
            # wrist singularity: only th4 + th6 is defined; keep JT4 where it is
            th4 = np.radians(q_near[3]) + zero[3]
            th5 = 0.0
            th6 = np.arctan2(M[1, 0], M[0, 0]) - th4
        else:
            a = np.arctan2(M[1, 2], M[0, 2])
            b = np.arctan2(sb, M[2, 2])
            c = np.arctan2(M[2, 1], -M[2, 0])
            th4, th5, th6 = a, -b, c
            q5 = np.degrees(th5 - zero[4])
            if (q5 >= 0) != (self.config.wrist == "noflip"):
                th4, th5, th6 = a + np.pi, b, c + np.pi
        q = np.degrees(np.array([th1, th2, th3, th4, th5, th6]) - zero)
        q = self._wrap_into_limits(q, q_near)
        err = np.abs(self.fk(q) - H)[:3].max()
        if err > 1e-6 * max(1.0, np.abs(H[:3, 3]).max()):
            raise Unreachable(f"no exact solution (residual {err:.2e}); the pose is singular for this arm")
        return q

    def _wrap_into_limits(self, q, q_near) -> np.ndarray:
        out = np.empty(6)
        for j in range(6):
            lo, hi = self.geometry.joint_limits_deg[j]
            base = (q[j] + 180.0) % 360.0 - 180.0
            cands = [base + 360.0 * k for k in range(-2, 3) if lo - 1e-9 <= base + 360.0 * k <= hi + 1e-9]
            if not cands:
                raise Unreachable(f"JT{j + 1} would be {base:.2f} deg, outside its limits {lo:g}..{hi:g} deg")
            out[j] = min(cands, key=lambda v: abs(v - q_near[j]))
        return out

    def within_limits(self, q_deg) -> int | None:
        """The number (1..6) of the first joint outside its limits, or None."""
        for j, (v, (lo, hi)) in enumerate(zip(np.asarray(q_deg, float).reshape(6), self.geometry.joint_limits_deg), 1):
            if not lo - 1e-9 <= v <= hi + 1e-9:
                return j
        return None


def make_tool(length_mm: float) -> np.ndarray:
    """flange_H_T (4, 4): the tool point straight out along the flange z by ``length_mm``."""
    return make_H(np.eye(3), (0.0, 0.0, float(length_mm)))
