"""The Plane Coincidence Constraint (paper, section 3, eq. 5-10), without robot kinematics: with the gripper parked on
the plate, G's x-y plane is W's, both z axes alike, so ``W_H_G`` is a turn about z and an x-y shift (eq. 7). The
fingertip pixels back-projected onto the plate (eq. 8) give (q1, q2, s_x, s_y) by least squares of eq. 10, and
``C_H_G = C_H_W W_H_G`` (eq. 6)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import POINT_NAMES, GripperSpec, fingertip_points_G
from selfview.errors import CalibrationError

__all__ = ["PCCResult", "solve_pcc", "measure_points_G", "points_G_for_state", "w_h_g_from_params", "jaw_gap_of"]


@dataclass(frozen=True)
class PCCResult:
    """Result of ``solve_pcc``: ``W_H_G``, ``C_H_G`` (4, 4); ``p_W`` (N, 3) back-projected points [mm], ``z_C`` (N,)
    their depths; ``residuals_mm`` (N, 2) of eq. 10, back-projected minus modelled; ``rms_mm``; ``q_norm`` |(q1, q2)|
    before normalisation (1 for a consistent gripper); ``names``, ``points_G`` (N, 3) of the points used."""

    W_H_G: np.ndarray
    C_H_G: np.ndarray
    p_W: np.ndarray
    z_C: np.ndarray
    residuals_mm: np.ndarray
    rms_mm: float
    q_norm: float
    names: tuple[str, ...]
    points_G: np.ndarray


def w_h_g_from_params(q1: float, q2: float, sx: float, sy: float) -> np.ndarray:
    """Eq. 7: (4, 4) ``W_H_G`` from (q1, q2) (normalised here) and (s_x, s_y) [mm]."""
    n = np.hypot(q1, q2)
    c, s = q1 / n, q2 / n
    return np.array([[c, -s, 0.0, sx], [s, c, 0.0, sy], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


def solve_pcc(uv, points_G, C_H_W, camera: CameraModel, names=None) -> PCCResult:
    """Eq. 8-10 for ``W_H_G`` from the fingertips' distorted pixels ``uv`` (N, 2) and G coordinates ``points_G`` (N, 3)
    [mm, z from the contact plane], and ``C_H_G = C_H_W W_H_G`` (eq. 6). Raises ``CalibrationError`` for fewer than
    two points, coincident points or non-finite input; ``ValueError`` for arrays of the wrong shape."""
    uv, pG, H = (np.asarray(a, dtype=float) for a in (uv, points_G, C_H_W))
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"PCC: uv: expected shape (N, 2), got {uv.shape}")
    if pG.ndim != 2 or pG.shape[1] != 3:
        raise ValueError(f"PCC: points_G: expected shape (N, 3), got {pG.shape}")
    if H.shape != (4, 4):
        raise ValueError(f"PCC: C_H_W: expected a (4, 4) transform, got shape {H.shape}")
    names = tuple(names) if names is not None else tuple(f"p{i + 1}" for i in range(len(uv)))
    if len(uv) != len(pG) or len(names) != len(uv):
        raise CalibrationError(f"PCC: {len(uv)} pixels for {len(pG)} gripper points and {len(names)} names")
    if len(uv) < 2:
        raise CalibrationError(f"PCC needs at least 2 fingertip points (eq. 10), got {len(uv)}")
    if not (np.all(np.isfinite(uv)) and np.all(np.isfinite(pG))):
        raise CalibrationError("PCC: fingertip pixels or gripper points contain NaN or infinity")
    if not np.all(np.isfinite(H)):
        raise CalibrationError("PCC: the plate pose C_H_W contains NaN or infinity")
    if np.ptp(pG[:, :2], axis=0).max() < 1e-6:
        raise CalibrationError("PCC: the gripper points coincide in the contact plane; their layout fixes no rotation")
    # eq. 8: back-projection onto the plane z_W = z_G (the planes coincide)
    p_W, z_C = camera.backproject_to_plane(uv, H, pG[:, 2])
    # eq. 10: two rows per point in (q1, q2, s_x, s_y)
    n = len(pG)
    A = np.zeros((2 * n, 4))
    A[0::2] = np.column_stack([pG[:, 0], -pG[:, 1], np.ones(n), np.zeros(n)])
    A[1::2] = np.column_stack([pG[:, 1], pG[:, 0], np.zeros(n), np.ones(n)])
    sol, *_ = np.linalg.lstsq(A, p_W[:, :2].reshape(-1), rcond=None)
    q_norm = float(np.hypot(sol[0], sol[1]))
    if q_norm < 1e-9:
        raise CalibrationError("PCC: the solve gave (q1, q2) = 0; the fingertip points do not fix a rotation")
    W_H_G = w_h_g_from_params(*sol)
    res = p_W[:, :2] - (pG[:, :2] @ W_H_G[:2, :2].T + W_H_G[:2, 3])
    return PCCResult(W_H_G=W_H_G, C_H_G=H @ W_H_G, p_W=p_W, z_C=z_C, residuals_mm=res,
                     rms_mm=float(np.sqrt(np.mean(np.sum(res**2, axis=1)))), q_norm=q_norm, names=names, points_G=pG)


def measure_points_G(p_W: np.ndarray, found: np.ndarray) -> dict[str, float]:
    """Gripper {'gap', 'width', 'thickness_A', 'thickness_B'} [mm] (thickness NaN if missing) from ``p_W`` (6, 3) in the
    contact plane (section 3: the inner four a rectangle on G's axes); ``CalibrationError`` without all four."""
    p = np.asarray(p_W, float)
    found = np.asarray(found, bool)
    if p.ndim != 2 or p.shape[0] != len(POINT_NAMES) or p.shape[1] not in (2, 3) or found.shape != (len(POINT_NAMES),):
        raise ValueError(f"measuring the gripper: expected p_W (6, 3) and found (6,), got {p.shape} and {found.shape}")
    p = p[:, :2]
    if not found[:4].all():
        missing = [POINT_NAMES[i] for i in range(4) if not found[i]]
        raise CalibrationError(f"measuring the gripper needs the four inner points; missing {', '.join(missing)}")
    gap = 0.5 * (np.linalg.norm(p[0] - p[2]) + np.linalg.norm(p[1] - p[3]))
    width = 0.5 * (np.linalg.norm(p[0] - p[1]) + np.linalg.norm(p[2] - p[3]))
    tA = float(np.linalg.norm(p[4] - p[0])) if found[4] else float("nan")
    tB = float(np.linalg.norm(p[5] - p[2])) if found[5] else float("nan")
    return {"gap": float(gap), "width": float(width), "thickness_A": tA, "thickness_B": tB}


def jaw_gap_of(points_G) -> float:
    """The jaw gap g [mm] of (6, 3) gripper points in POINT_NAMES order: the inner four lie at x = +-g/2."""
    return float(np.mean(np.abs(np.asarray(points_G, float)[:4, 0])) * 2)


def points_G_for_state(dims: dict[str, float], measured_state: str, gripper: GripperSpec) -> dict[str, np.ndarray]:
    """(6, 3) G coordinates per gripper state from ``dims`` measured in ``measured_state``: other gaps shifted by the
    nominal differences (the valve's end stops), a thickness not measured the cell's."""
    t_nom = gripper.finger_thickness
    tA = dims["thickness_A"] if np.isfinite(dims.get("thickness_A", np.nan)) else t_nom
    tB = dims["thickness_B"] if np.isfinite(dims.get("thickness_B", np.nan)) else t_nom
    g, g_meas = dims["gap"], gripper.gap(measured_state)
    return {state: fingertip_points_G(g + (g_nom - g_meas), dims["width"], tA, tB)
            for state, g_nom in gripper.states.items()}
