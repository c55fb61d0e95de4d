"""A block to grasp in the simulated cell: where it lies, and whether a closing gripper holds it.

The block (``selfview.measurement.objects.ObjectSpec``) lies on the table (the base frame's z = 0 plane) at a pose drawn
per seed within the object file's ``placement``; the renderer draws it and its printed target
(``selfview.mocks.render``). ``grasp_outcome`` is the world's verdict when the jaws close: held when the
block lies between the open jaws within their clearance, the fingers' width on its faces, the fingertips
deep enough on its sides and above the table; otherwise why not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from selfview.errors import ConfigError
from selfview.maths.geometry import R_from_rotvec, inv_H, make_H, rot_z, rotation_angle, trans, transform_points
from selfview.measurement.objects import ObjectSpec

__all__ = ["SimObject", "place_object", "draw_start", "grasp_outcome", "MIN_GRIP_DEPTH_MM", "TABLE_MARGIN_MM"]

#: The fingertips must reach at least this far down the block's sides to hold it (mm).
MIN_GRIP_DEPTH_MM = 10.0
#: Fingertips closer than this to the table touch it (mm).
TABLE_MARGIN_MM = 0.0


@dataclass
class SimObject:
    """The block to grasp: its ``spec`` and its true pose ``base_H_O`` (4, 4)."""

    spec: ObjectSpec
    base_H_O: np.ndarray


def place_object(world, spec: ObjectSpec, seed: int | None = None) -> SimObject:
    """Put the block on ``world``'s table at a pose drawn from ``spec.placement`` (seeded by ``seed``,
    default the world's); returns it (also ``world.object``)."""
    if not isinstance(spec, ObjectSpec):
        raise ConfigError(f"place_object: expected an ObjectSpec, got {type(spec).__name__}")
    rng = np.random.default_rng([int(world.seed if seed is None else seed), 0x0B1EC7])
    pl = spec.placement
    x, y = rng.uniform(*pl["x"]), rng.uniform(*pl["y"])
    yaw = np.radians(rng.uniform(*pl["yaw_deg"]))
    # O: z down into the block, origin on its top face
    base_H_O = make_H(np.diag([1.0, -1.0, -1.0]), (x, y, spec.block[2])) @ rot_z(-yaw)
    obj = SimObject(spec, base_H_O)
    with world.lock:
        world.object = obj
        world.version += 1
    return obj


def draw_start(world, rng: np.random.Generator, reachable=None, draws: int = 8) -> np.ndarray:
    """A pre-grasp pose ``base_H_G`` for ``world.object``: its stand-off goal backed off 150-250 mm along the
    camera's line of sight (the mount guess's), turned up to 15 deg about a random axis through the target's
    centre (which keeps it in view) and shifted up to 50 mm in a random direction. ``reachable(base_H_G)``
    (optional) says whether the arm can take a pose: up to ``draws`` poses are drawn for one it can;
    ``ConfigError`` if none."""
    obj: SimObject = world.object
    if obj is None:
        raise ConfigError("draw_start: the simulated world has no object")
    if isinstance(draws, bool) or not isinstance(draws, (int, np.integer)) or draws < 1:
        raise ConfigError(f"draw_start draws: expected a whole number >= 1, got {draws!r}")
    base_H_pre = obj.base_H_O @ obj.spec.O_H_Gpre
    z_C = inv_H(world.cell.mount_guess_C_H_G)[:3, 2]  # the camera's axis in G
    for _ in range(draws):
        back = base_H_pre @ make_H(np.eye(3), -rng.uniform(150.0, 250.0) * z_C)
        axis = rng.normal(size=3)
        R = R_from_rotvec(axis / np.linalg.norm(axis) * np.radians(rng.uniform(0.0, 15.0)))
        turn = obj.base_H_O @ make_H(R) @ inv_H(obj.base_H_O)
        shift = rng.normal(size=3)
        shift *= rng.uniform(0.0, 50.0) / np.linalg.norm(shift)
        H = trans(*shift) @ turn @ back
        if reachable is None or reachable(H):
            return H
    raise ConfigError(f"no reachable pre-grasp pose in {draws} draws: the object lies out of the arm's reach")


def grasp_outcome(world, gap_open_mm: float) -> dict:
    """The world's verdict on closing the jaws now: ``held`` (bool), ``why`` (sentence), ``offset_mm`` (3,)
    the TCP's offset from the grasp frame G* in G* [mm], ``angle_deg`` the rotation between them,
    ``clearance_mm`` the jaws' clearance about the block."""
    obj: SimObject | None = world.object
    if obj is None:
        raise ConfigError("grasp_outcome: the simulated world has no object")
    if not (isinstance(gap_open_mm, (int, float, np.number)) and np.isfinite(gap_open_mm) and gap_open_mm > 0):
        raise ConfigError(f"grasp_outcome gap_open_mm: expected the open jaws' gap in mm (> 0), got {gap_open_mm!r}; "
                          "take it from the cell's gripper states (cell.gripper.gap('open'))")
    spec = obj.spec
    with world.lock:
        base_H_G = world.base_H_G.copy()
        pG = world.points_G()
    Gs_H_G = spec.Gstar_H_O @ inv_H(obj.base_H_O) @ base_H_G
    off = Gs_H_G[:3, 3]
    ang = float(np.degrees(rotation_angle(Gs_H_G[:3, :3])))
    bx, by, h = spec.block
    clearance = spec.jaw_clearance_mm(gap_open_mm)
    # the block's footprint across the jaws when turned by the yaw between G and G*
    yaw = abs(float(np.arctan2(Gs_H_G[1, 0], Gs_H_G[0, 0])))
    across = bx * np.cos(yaw) + by * np.sin(yaw)
    O_H_G = inv_H(obj.base_H_O) @ base_H_G
    tips_O = transform_points(O_H_G, pG)
    out = {"offset_mm": [float(v) for v in off], "angle_deg": ang, "clearance_mm": float(clearance)}
    reasons = []
    if np.max(tips_O[:, 2]) > h - TABLE_MARGIN_MM:
        reasons.append(f"a fingertip touches the table ({np.max(tips_O[:, 2]) - h:+.2f} mm into it)")
    if abs(O_H_G[0, 3]) + (across - bx) / 2 > clearance or across > gap_open_mm:
        reasons.append(f"the block lands on a jaw: {O_H_G[0, 3]:+.2f} mm across the jaws and "
                       f"{np.degrees(yaw):.2f} deg turned, {clearance:.2f} mm clearance")
    if abs(O_H_G[1, 3]) > (by - world.cell.gripper.finger_width) / 2:
        reasons.append(f"the fingers miss the block's faces ({O_H_G[1, 3]:+.2f} mm along them)")
    if np.min(tips_O[:, 2]) < MIN_GRIP_DEPTH_MM:
        reasons.append(f"the fingertips reach only {np.min(tips_O[:, 2]):.2f} mm down the block's sides "
                       f"(at least {MIN_GRIP_DEPTH_MM:g} needed)")
    out["held"] = not reasons
    out["why"] = "held" if not reasons else "; ".join(reasons)
    return out
