"""The PUMA 260's forward kinematics, as the driver needs them to check what ``WHERE`` prints.

VAL-II has no checksum, but ``WHERE`` prints the tool point's pose (X Y Z O A T) and the six joint
angles it came from: the pose must equal the forward kinematics of the joints through the controller's
TOOL, up to the rounding of the printed numbers. A digit swap in either line, or an O/A/T convention
that is not the controller's, breaks that equality. This module is the driver's own; the simulator
(``selfview.mocks.puma260``) has its own.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from selfview.drivers.puma_val_serial._config import check_keys, read_yaml
from selfview.errors import ConfigError
from selfview.maths.geometry import EulerConvention, rotvec_from_R

__all__ = ["PumaKinematics", "WhereFit"]

#: mm of arc per radian: how rotations are weighed against positions in the consistency test (the
#: test's verdict does not depend on it, only the size of its small second-order allowance)
_ARC_MM = 1000.0
#: the normals of Z's facets: every 5 of its 12 generators (6 joints, X Y Z, O A T); a normal to 5
#: vectors in 6 dimensions is their generalised cross product, signed 5x5 minors
_FACETS = np.array(list(itertools.combinations(range(12), 5)))
_MINOR_COLS = np.array([[c for c in range(6) if c != j] for j in range(6)])
_MINOR_SIGNS = (-1.0) ** np.arange(6)
#: corners of the rounding box, for the worst case reported beside a verdict
_CORNERS = np.array(list(itertools.product((-1.0, 1.0), repeat=9)))


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


def _axis_rot(axis: int, deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    u, v = (axis + 1) % 3, (axis + 2) % 3
    R = np.eye(3)
    R[u, u], R[u, v], R[v, u], R[v, v] = c, -s, s, c
    return R


def _euler_axes(conv: EulerConvention, angles_deg) -> np.ndarray:
    """(3, 3): column m is the base-frame axis about which angle m of ``conv`` turns the pose."""
    R = np.asarray(conv.base, dtype=float)
    cols = []
    for ax, a, s, o in zip(conv.sequence.lower(), angles_deg, conv.signs, conv.offsets_deg):
        i = "xyz".index(ax)
        cols.append(R[:, i] * abs(s))
        R = R @ _axis_rot(i, s * (float(a) + o))
    return np.array(cols).T


@dataclass(frozen=True)
class WhereFit:
    """WHERE's pose against the kinematics of its own joint angles.

    ``mm`` / ``deg``: the position difference and the angle of R_pose^T R_kin; ``ratio``: the largest
    facet violation, as a multiple of what the print rounding explains (<= 1: consistent);
    ``bound_mm`` / ``bound_deg``: the most the rounding can move the position / turn the pose at these
    joints (the radius of Z in each part, for messages).
    """

    mm: float
    deg: float
    ratio: float
    bound_mm: float
    bound_deg: float

    @property
    def consistent(self) -> bool:
        return self.ratio <= 1.0


@dataclass(frozen=True)
class PumaKinematics:
    """The arm the driver talks to: nominal PUMA 260 link lengths (mm), VAL's joint zero, the TOOL.

    ``where_model_mm`` / ``where_model_deg``: how far the controller's arm model may lie from this one,
    beyond the print rounding that ``where_fit`` derives; they widen its zonotope by a ball. 0 for a
    controller with the nominal PUMA 260 data and this TOOL; a controller whose link data or TOOL are
    known to differ states it here rather than in a looser rounding.
    """

    shoulder_mm: float = 330.2
    upper_arm_mm: float = 198.1
    lateral_mm: float = 124.5
    elbow_drop_mm: float = 19.05
    forearm_mm: float = 203.2
    flange_mm: float = 63.5
    tool_mm: tuple[float, float, float] = (0.0, 0.0, 170.0)
    where_model_mm: float = 0.0
    where_model_deg: float = 0.0

    def __post_init__(self):
        for nm in ("shoulder_mm", "upper_arm_mm", "lateral_mm", "elbow_drop_mm", "forearm_mm", "flange_mm"):
            v = getattr(self, nm)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                raise ConfigError(f"kinematics.{nm}: expected a length >= 0 mm, got {v!r}")
        t = self.tool_mm
        if not (isinstance(t, (tuple, list)) and len(t) == 3 and all(np.isfinite(float(v)) for v in t)):
            raise ConfigError(f"kinematics.tool_mm: expected three numbers (mm in the flange frame), got {t!r}")
        for nm in ("where_model_mm", "where_model_deg"):
            v = getattr(self, nm)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v >= 0):
                raise ConfigError(f"kinematics.{nm}: expected an allowance >= 0, got {v!r}")

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

    def frames(self, q_deg) -> list[np.ndarray]:
        """base_H_i (4, 4) for i = 0..6: the shoulder frame (joint 1's axis is its z), then each link's.

        Standard Denavit-Hartenberg, lengths in mm, angles in degrees, the shoulder ``shoulder_mm`` above
        the base reference B (z up, x forward):

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
        out = [H]
        for theta, d, a, alpha in chain:
            H = H @ _rz(theta) @ _t(a, 0.0, d) @ _rx(alpha)
            out.append(H)
        return out

    def flange(self, q_deg) -> np.ndarray:
        """base_H_flange (4, 4) at VAL joint angles ``q_deg`` (6,)."""
        return self.frames(q_deg)[-1]

    def tool(self, q_deg) -> np.ndarray:
        """base_H_T (4, 4): the tool point at joint angles ``q_deg``."""
        return self.flange(q_deg) @ _t(*self.tool_mm)

    def joints_reaching(self, goal_H: np.ndarray, q0, iters: int = 200) -> np.ndarray | None:
        """Joint angles (deg) near ``q0`` whose tool pose is ``goal_H`` (damped least squares on the joint
        axes, steps of at most 0.2 rad), to time a joint-interpolated motion; None if it does not converge
        to 0.1 mm / 0.05 deg."""
        q = np.asarray(q0, dtype=float).copy()
        w = np.array([1.0, 1.0, 1.0, 100.0, 100.0, 100.0])  # a radian weighed as 100 mm
        for _ in range(iters):
            F = self.frames(q)
            H = F[-1] @ _t(*self.tool_mm)
            dp = goal_H[:3, 3] - H[:3, 3]
            dr = rotvec_from_R(goal_H[:3, :3] @ H[:3, :3].T)
            if np.linalg.norm(dp) < 0.1 and np.degrees(np.linalg.norm(dr)) < 0.05:
                return q
            z = np.array([f[:3, 2] for f in F[:6]])
            J = np.vstack([np.cross(z, H[:3, 3] - np.array([f[:3, 3] for f in F[:6]])).T, z.T]) * w[:, None]
            step = np.linalg.solve(J.T @ J + 100.0 * np.eye(6), J.T @ (np.concatenate([dp, dr]) * w))
            q += np.degrees(step * min(1.0, 0.2 / max(float(np.abs(step).max()), 1e-12)))
        return None

    def where_fit(self, pose, joints, euler: EulerConvention, decimals: int) -> WhereFit:
        """Is the printed ``pose`` (x, y, z mm, o, a, t deg under ``euler``) the pose of the printed
        ``joints`` (deg), both printed with ``decimals`` decimals?

        The controller computes the pose from its unrounded joint angles and prints both rounded to d
        decimals (VAL-II: 2), so each printed joint is off its true value by up to h = 0.5e-d deg, each of X Y
        Z by up to h mm and each of O A T by up to h deg. The difference between the printed pose and the
        kinematics of the printed joints, as a 6-vector e = (position [mm], rotation vector of R_pose R_kin^T
        [rad]), is then, to first order,

            e = J dq + dx + E da,   |dq_i| <= h deg, |dx_i| <= h mm, |da_i| <= h deg,

        with J the arm's Jacobian at the printed joints (joint i moves the tool point by z_i x (p - o_i) and
        turns it about z_i: its lever arm) and E the axes of the O, A, T rotations at the printed angles.
        Those e form a zonotope Z (12 generators in 6 dimensions); a reading is consistent exactly when e lies
        in Z. The test is Z's facet inequalities: for the normal n of every 5 of the 12 generators, |n.e| <=
        sum_i |n.g_i| + the second-order remainder of the linearisation, 1/2 (6h + 3h)^2 in radians times (the
        arm's reach + 1 m), about 6e-4 mm at h = 0.005 (rotations are counted as mm of arc at 1 m). No round-
        number tolerance: at h = 0.005 the worst case over Z is 0.04-0.14 mm and 0.026-0.032 deg across the
        PUMA 260's workspace (0.11 mm / 0.031 deg with the tool down over the plate), and a difference along a
        direction in which rounding cannot move the pose is refused however small. So a printed joint changed
        by 0.08 deg (0.08 deg of tool rotation, whatever the joint), or X, Y or Z changed by 0.1 mm, is
        caught. Comparing rotations (not O/A/T triples) makes the test blind to the representation: wrapping
        at +-180 and the O/T degeneracy at A = +-90 change nothing.
        """
        h = 0.5 * 10.0 ** -decimals
        hr = np.radians(h)
        F = self.frames(joints)
        K = F[-1] @ _t(*self.tool_mm)
        p = K[:3, 3]
        z = np.array([f[:3, 2] for f in F[:6]]).T  # joint axes (base frame)
        o = np.array([f[:3, 3] for f in F[:6]]).T  # a point on each
        R_pose = euler.to_R(pose[3:])
        G = np.zeros((6, 12))
        G[:3, :6] = np.cross(z.T, (p[:, None] - o).T).T * hr
        G[3:, :6] = z * hr * _ARC_MM
        G[:3, 6:9] = np.eye(3) * h
        G[3:, 9:] = _euler_axes(euler, pose[3:]) * hr * _ARC_MM
        e = np.concatenate([np.asarray(pose[:3], dtype=float) - p, rotvec_from_R(R_pose @ K[:3, :3].T) * _ARC_MM])
        A = G.T[_FACETS]  # (792, 5, 6)
        N = np.linalg.det(np.moveaxis(A[:, :, _MINOR_COLS], 2, 1)) * _MINOR_SIGNS  # (792, 6)
        # unit normals (5 dependent generators give none: a zero row, no constraint)
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)
        reach = (self.upper_arm_mm + self.lateral_mm + self.elbow_drop_mm + self.forearm_mm + self.flange_mm
                 + float(np.linalg.norm(self.tool_mm)))
        second_order = 0.5 * (9 * hr) ** 2 * (reach + _ARC_MM)
        model = (self.where_model_mm * np.linalg.norm(N[:, :3], axis=1)
                 + np.radians(self.where_model_deg) * _ARC_MM * np.linalg.norm(N[:, 3:], axis=1))
        support = np.abs(N @ G).sum(axis=1)
        ratio = float(np.max((np.abs(N @ e) - second_order - model) / np.maximum(support, 1e-12)))
        # the worst case at a corner of the rounding box (O A T rounding does not move the position)
        bound_mm = float(np.linalg.norm(_CORNERS @ G[:3, :9].T, axis=1).max())
        rot = np.hstack([G[3:, :6], G[3:, 9:]])
        bound_deg = float(np.degrees(np.linalg.norm(_CORNERS @ rot.T, axis=1).max() / _ARC_MM))
        return WhereFit(
            mm=float(np.linalg.norm(e[:3])),
            deg=float(np.degrees(np.linalg.norm(e[3:]) / _ARC_MM)),
            ratio=max(ratio, 0.0),
            bound_mm=bound_mm,
            bound_deg=bound_deg,
        )
