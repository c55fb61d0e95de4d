"""The simulated cell's true state, shared by every simulated device.

One ``SimWorld`` owns what a real cell would hold physically: the true camera (f, kappa, and the
principal point and aspect, which a real camera and grabber pair do not keep at their nominal values:
``camera='ideal'`` keeps the cell's nominal ones, ``'realistic'`` draws them, see ``draw_camera``), the true
mount ``C_H_G`` (drawn within ``simulation.mount_error`` of the mount guess), disturbances of the camera
on its mount, the jaw gap, the robot's TCP pose in its base frame, and the plate lying on foam. Devices
simulated elsewhere (the VAL-II controller, the valve terminal, the camera) read and change it under its
lock. It owns its random generator (seeded); there are no module globals.

Frames: B is the robot base (z up); W the plate (CONVENTIONS.md: z into the plate, so pointing down on
a table); G the gripper (z the approach direction); C the camera.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from selfview.mocks.imperfections import realise as realise_imperfections
from selfview.mocks.imperfections import resolve as resolve_imperfections
from selfview.maths.camera import CameraModel
from selfview.files.cell import Cell
from selfview.errors import ConfigError
from selfview.maths.geometry import (
    R_from_rotvec,
    inv_H,
    trans,
    make_H,
    rot_axis,
    rot_z,
    transform_points,
)

__all__ = ["SimWorld", "Disturbance", "random_small_rotation", "draw_camera", "CAMERA_KINDS", "PLATE_BASE_POSE",
           "REALISTIC_OFFSET_PX", "REALISTIC_ASPECT"]

#: Where the plate's centre lies in the robot base frame when nobody presses on it (mm): on foam
#: on the table in front of the robot, W's z pointing down into the plate.
PLATE_BASE_POSE = make_H(np.diag([1.0, -1.0, -1.0]), (350.0, 0.0, 20.0))
#: How far the foam lets the plate sink and tilt before the gripper hits the table (mm, degrees).
FOAM_TRAVEL_MM = 15.0
FOAM_TILT_DEG = 12.0

#: The simulated camera's kinds: 'ideal' (the cell's nominal principal point and aspect) or 'realistic'.
CAMERA_KINDS = ("ideal", "realistic")
#: A realistic camera's principal point lies up to this far from the nominal one (px, uniform over the
#: disc), and its aspect is uniform in this range: CCIR camera and grabber pairs are that far from
#: nominal (Willson's calibrations list centres 8 to 30 px off and sx from 1.028 to 1.108).
REALISTIC_OFFSET_PX = 15.0
REALISTIC_ASPECT = (0.97, 1.07)


def draw_camera(nominal: CameraModel, kind="ideal", seed: int = 0) -> CameraModel:
    """The true camera of a simulated cell: ``nominal`` (f, kappa already the true ones) with its
    principal point and aspect as ``kind`` says.

    ``kind``: 'ideal' (``nominal`` unchanged), 'realistic' (offset uniform over a disc of radius
    ``REALISTIC_OFFSET_PX``, aspect uniform in ``REALISTIC_ASPECT``, drawn from their own generator
    seeded by ``seed``, so the world's other draws do not change), or a mapping with
    ``principal_point`` [cx, cy] and/or ``aspect`` (explicit values), or a ``CameraModel``.
    Raises ``ConfigError`` for anything else.
    """
    if isinstance(kind, CameraModel):
        return kind
    if isinstance(kind, dict):
        unknown = set(kind) - {"principal_point", "aspect"}
        if unknown:
            raise ConfigError(f"simulated camera: unknown key(s) {', '.join(sorted(unknown))}; "
                              "expected principal_point, aspect")
        cx, cy = kind.get("principal_point", nominal.principal_point)
        return nominal.with_(cx=float(cx), cy=float(cy), aspect=float(kind.get("aspect", nominal.aspect)))
    if kind == "ideal":
        return nominal
    if kind == "realistic":
        rng = np.random.default_rng([int(seed), 15_015])
        r = REALISTIC_OFFSET_PX * np.sqrt(rng.uniform())
        a = rng.uniform(0, 2 * np.pi)
        return nominal.with_(cx=nominal.cx + r * np.cos(a), cy=nominal.cy + r * np.sin(a),
                             aspect=float(rng.uniform(*REALISTIC_ASPECT)))
    raise ConfigError(f"simulated camera {kind!r}: expected one of {', '.join(CAMERA_KINDS)}, "
                      "a mapping {principal_point, aspect} or a CameraModel")


def random_small_rotation(rng: np.random.Generator, max_angle_rad: float) -> np.ndarray:
    """(3, 3) rotation about a uniformly random axis by an angle uniform in [0, max_angle_rad]."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return R_from_rotvec(axis * rng.uniform(0.0, max_angle_rad))


@dataclass(frozen=True)
class Disturbance:
    """One applied camera disturbance: the motion of the camera on its mount.

    ``C_H_Cnew`` (4, 4) is the new camera frame in the old one; ``tcp_shift_C`` (3,) how far the TCP moved
    in camera coordinates [mm]; ``angle_deg`` the rotation.
    """

    series: str
    C_H_Cnew: np.ndarray
    angle_deg: float
    axis_C: np.ndarray
    tcp_shift_C: np.ndarray


class SimWorld:
    """The true state of a simulated self-viewing cell.

    ``cell`` must have a ``simulation`` section. ``seed`` fixes every random draw (mount, parking
    offsets, disturbances, the camera). ``camera``: the true camera's principal point and aspect
    (``draw_camera``; default 'ideal', the cell's nominal ones). Thread-safe: devices call it from their
    server threads.
    """

    def __init__(self, cell: Cell, seed: int = 0, imperfections=None, *, camera="ideal"):
        if cell.simulation is None:
            raise ConfigError(f"{cell.source}: the simulated cell needs a 'simulation' section")
        self.cell = cell
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)
        self.lock = threading.RLock()
        sim = cell.simulation
        self.camera: CameraModel = draw_camera(cell.camera.guess().with_(f=sim.true_f, kappa=sim.true_kappa),
                                               camera, self.seed)
        # The true mount: the guess moved by a random rotation and shift within the configured error.
        R_err = random_small_rotation(self.rng, np.radians(sim.mount_error_angle_deg))
        shift = self.rng.normal(size=3)
        shift *= self.rng.uniform(0, sim.mount_error_shift_mm) / np.linalg.norm(shift)
        G = cell.mount_guess_C_H_G
        self.mount_C_H_G: np.ndarray = make_H(R_err @ G[:3, :3], G[:3, 3] + shift)
        self._C_H_Ccur = np.eye(4)  # accumulated disturbance: current camera frame in the mount's
        self.disturbances: list[Disturbance] = []
        self.jaw_gap_mm: float = cell.gripper.gap(cell.gripper.calibrate_in)
        self.jaw_state: str = cell.gripper.calibrate_in
        self.base_H_G: np.ndarray = make_H(np.diag([1.0, -1.0, -1.0]), (350.0, 0.0, 200.0))
        self.base_H_plate0: np.ndarray = PLATE_BASE_POSE.copy()
        self.W_H_G: np.ndarray | None = None  # set while parked on the plate
        self.object = None  # a block to grasp on the table (selfview.mocks.objects.SimObject) or None
        self.version = 0  # bumped on every change, so a camera can tell a new scene
        # a real cell's imperfections (mocks/imperfections.py; None or 'ideal': none), drawn from their
        # own generator so that they change nothing else in the world
        self.imperfections = resolve_imperfections(imperfections)
        self.imperfect = realise_imperfections(self.imperfections, cell, self.seed)

    # --- camera and mount -----------------------------------------------------------------------
    @property
    def C_H_G(self) -> np.ndarray:
        """The true gripper-to-camera transform now (mount and every disturbance applied)."""
        with self.lock:
            return inv_H(self._C_H_Ccur) @ self.mount_C_H_G

    def disturb(self, series: str, shift_mm: float | None = None) -> Disturbance:
        """Move the camera on its mount as ``simulation.disturbances[series]`` describes.

        A rotation about an axis through the configured pivot (camera coordinates), the axis jittered
        within ``axis_jitter_deg``, by the angle that moves the TCP by ``shift_mm`` (default: drawn
        from N(tcp_shift_mm, tcp_shift_sd_mm)). Accumulates onto earlier disturbances.
        """
        sim = self.cell.simulation
        try:
            spec = sim.disturbances[series]
        except KeyError:
            raise ConfigError(
                f"disturbance {series!r}: expected one of {', '.join(sim.disturbances)}"
            ) from None
        with self.lock:
            axis = np.asarray(spec.axis_C, dtype=float)
            axis /= np.linalg.norm(axis)
            # jitter: tilt the axis by a random angle up to axis_jitter_deg in a random direction
            perp = np.cross(axis, self.rng.normal(size=3))
            perp /= np.linalg.norm(perp)
            jit = self.rng.uniform(0, np.radians(spec.axis_jitter_deg))
            axis = R_from_rotvec(perp * jit) @ axis
            target = spec.tcp_shift_mm + spec.tcp_shift_sd_mm * self.rng.normal() if shift_mm is None else shift_mm
            target = abs(float(target))
            imp = self.imperfections
            if imp.pivot_sd_mm or imp.slip_sd_mm or imp.roll_deg_per_mm2:
                pivot, slip, roll = self.imperfect.disturbance(spec.pivot_C)
                rot = self._apply_rotation(series, axis, pivot, target)
                self._C_H_Ccur = self._C_H_Ccur @ inv_H(rot.C_H_Cnew)  # one disturbance: rotation, roll, slip
                self.disturbances.pop()
                twist = rot_axis(np.array([0.0, 0.0, 1.0]), np.radians(roll * target**2), (0.0, 0.0, 0.0))
                return self._commit(series, rot.C_H_Cnew @ twist @ trans(*slip), axis)
            return self._apply_rotation(series, axis, np.asarray(spec.pivot_C, float), target)

    def disturb_by_angle(self, axis_C, angle_deg: float, pivot_C=(0.0, -15.0, -20.0), series: str = "custom") -> Disturbance:
        """Rotate the camera by ``angle_deg`` about ``axis_C`` through ``pivot_C`` (current camera frame)."""
        with self.lock:
            axis = np.asarray(axis_C, float)
            axis /= np.linalg.norm(axis)
            return self._commit(series, rot_axis(axis, np.radians(angle_deg), pivot_C), axis)

    def _apply_rotation(self, series, axis, pivot, target_shift) -> Disturbance:
        tcp_C = self.C_H_G[:3, 3]

        def shift(theta):
            M = rot_axis(axis, theta, pivot)
            return transform_points(inv_H(M), tcp_C) - tcp_C

        if target_shift == 0:
            return self._commit(series, np.eye(4), axis)
        # the TCP moves along the dominant component positively: pick the sign of the angle for that
        lin = shift(1e-4)
        k = int(np.argmax(np.abs(lin)))
        sign = 1.0 if lin[k] > 0 else -1.0
        lo, hi = 0.0, 1e-3
        while np.linalg.norm(shift(sign * hi)) < target_shift:
            hi *= 2
            if hi > np.pi / 2:
                raise ConfigError(f"disturbance {series!r}: no rotation about the pivot moves the TCP {target_shift} mm")
        for _ in range(80):
            mid = (lo + hi) / 2
            if np.linalg.norm(shift(sign * mid)) < target_shift:
                lo = mid
            else:
                hi = mid
        return self._commit(series, rot_axis(axis, sign * (lo + hi) / 2, pivot), axis)

    def _commit(self, series, M, axis) -> Disturbance:
        tcp_before = self.C_H_G[:3, 3]
        self._C_H_Ccur = self._C_H_Ccur @ M
        tcp_after = self.C_H_G[:3, 3]
        ang = float(np.degrees(np.arccos(np.clip((np.trace(M[:3, :3]) - 1) / 2, -1, 1))))
        d = Disturbance(series, M, ang, np.asarray(axis, float), tcp_after - tcp_before)
        self.disturbances.append(d)
        self.version += 1
        return d

    def reset_disturbance(self) -> None:
        """Put the camera back to its true mount."""
        with self.lock:
            self._C_H_Ccur = np.eye(4)
            self.disturbances.clear()
            self.version += 1

    # --- gripper --------------------------------------------------------------------------------
    def set_jaw(self, gap_mm: float, state: str | None = None) -> None:
        """Set the jaw gap (the valve terminal's gripper model calls this as the jaws travel)."""
        with self.lock:
            self.jaw_gap_mm = float(gap_mm)
            if state is not None:
                self.jaw_state = state
            self.version += 1

    # --- robot and plate ------------------------------------------------------------------------
    @property
    def parked(self) -> bool:
        return self.W_H_G is not None

    def park(self, max_offset_mm: float = 3.0, max_turn_deg: float = 8.0, turn_deg: float | None = None) -> np.ndarray:
        """Park the gripper on the plate: the fingertip plane coincides with the plate (eq. 5-7) at a
        random in-plane offset (within ``max_offset_mm``) and turn (within ``max_turn_deg``, or exactly
        ``turn_deg``). Returns the true ``W_H_G``."""
        with self.lock:
            s = self.rng.uniform(-max_offset_mm, max_offset_mm, size=2)
            q = np.radians(turn_deg) if turn_deg is not None else self.rng.uniform(-1, 1) * np.radians(max_turn_deg)
            W_H_G = rot_z(q)
            W_H_G[:2, 3] = s
            self.W_H_G = W_H_G
            # the TCP sits where the plate is (the robot brought it there)
            self.base_H_G = self.base_H_plate0 @ W_H_G
            self.version += 1
            return W_H_G.copy()

    def unpark(self) -> None:
        with self.lock:
            self.W_H_G = None
            self.version += 1

    def set_tcp(self, base_H_G: np.ndarray) -> str:
        """Move the TCP (the robot simulator calls this). Returns 'free', 'parked' or 'collision'.

        Pressing the fingertips onto the plate (within the foam's travel and tilt) parks the gripper:
        the plate tilts until its plane coincides with the fingertip plane (the paper's Fig. 3).
        """
        with self.lock:
            self.base_H_G = np.asarray(base_H_G, float).copy()
            state = self.contact(self.base_H_G)
            if state == "parked":
                P = inv_H(self.base_H_plate0) @ self.base_H_G  # gripper in the resting plate frame
                q = np.arctan2(P[1, 0], P[0, 0])
                W_H_G = rot_z(q)
                W_H_G[:2, 3] = P[:2, 3]
                self.W_H_G = W_H_G
            else:
                self.W_H_G = None
            self.version += 1
            return state

    def contact(self, base_H_G: np.ndarray) -> str:
        """'free' (above the plate), 'parked' (pressing it within the foam's give) or 'collision'."""
        P = inv_H(self.base_H_plate0) @ np.asarray(base_H_G, float)
        depth = P[2, 3]  # W's z points into the plate: positive = pressed below the resting surface
        half = np.asarray(self.cell.plate.size) / 2
        over_plate = abs(P[0, 3]) < half[0] and abs(P[1, 3]) < half[1]
        if depth < 0 or not over_plate:
            return "free"
        tilt = np.degrees(np.arccos(np.clip(P[2, 2], -1, 1)))
        if depth <= FOAM_TRAVEL_MM and tilt <= FOAM_TILT_DEG:
            return "parked"
        return "collision"

    @property
    def base_H_W(self) -> np.ndarray:
        """The plate's pose in the base frame now (tilted into coincidence while parked)."""
        with self.lock:
            if self.W_H_G is not None:
                return self.base_H_G @ inv_H(self.W_H_G)
            return self.base_H_plate0.copy()

    @property
    def C_H_W(self) -> np.ndarray:
        """The true plate pose in the camera frame now."""
        with self.lock:
            if self.W_H_G is not None:
                return self.C_H_G @ inv_H(self.W_H_G)
            return self.C_H_G @ inv_H(self.base_H_G) @ self.base_H_plate0

    @property
    def C_H_B(self) -> np.ndarray:
        """The robot base in the camera frame (for rendering the table under a free gripper)."""
        with self.lock:
            return self.C_H_G @ inv_H(self.base_H_G)

    def points_G(self) -> np.ndarray:
        """(6, 3) true fingertip points in G for the current jaw gap."""
        return self.imperfect.points_G(self.cell.gripper, self.jaw_gap_mm)

    def finger_boxes_G(self, gap: float | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """The true fingers' boxes [(lo, hi)] in G [mm] for a jaw gap (default: the current one)."""
        return self.imperfect.finger_boxes_G(self.cell.gripper, self.jaw_gap_mm if gap is None else gap)

    @property
    def C_H_O(self) -> np.ndarray | None:
        """The true pose of the object to grasp in the camera frame now (None: no object)."""
        with self.lock:
            if self.object is None:
                return None
            return self.C_H_B @ self.object.base_H_O

    def truth(self) -> dict:
        """The ground truth a test or a report compares against (plain lists, mm, px)."""
        with self.lock:
            extra = {} if self.object is None else {"C_H_O": self.C_H_O.tolist(),
                                                    "base_H_O": self.object.base_H_O.tolist()}
            return extra | {
                "f": self.camera.f,
                "kappa": self.camera.kappa,
                "principal_point": [self.camera.cx, self.camera.cy],
                "aspect": self.camera.aspect,
                "C_H_G": self.C_H_G.tolist(),
                "C_H_W": self.C_H_W.tolist(),
                "W_H_G": None if self.W_H_G is None else self.W_H_G.tolist(),
                "jaw_gap_mm": self.jaw_gap_mm,
                "parked": self.parked,
                "seed": self.seed,
            }
