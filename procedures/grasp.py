"""Visually guided grasping: position-based visual servoing in the gripper frame (the paper's application).

Each frame measures the object in the gripper frame, ``G_H_O = inv(C_H_G) C_H_O``: ``C_H_O`` from the
object's printed target (``selfview.measurement.objects.object_pose``), ``C_H_G`` kept current by the on-line update
from the fingertips of the same picture (``SilhouetteTracker`` and the monitor policy, as ``selfview track``
and ``monitor`` do; off-line: the calibration's, the fingertips still watched for the alarm). The error is
the stand-off goal ``Gpre`` (the grasp frame G* backed off ``approach_mm`` along its z) in the current
gripper frame, ``G_H_Gpre = G_H_O O_H_Gpre``: its translation and theta-u drive a bounded straight motion
of the tool frame by ``gain`` times the error, capped per step, through the engine's ``tool`` step (limits
checked before anything is sent). The loop stops when |t| < ``stop_mm`` and theta < ``stop_deg``; it fails
(``GraspFailed``, the engine then stops the robot and leaves the valve safe) after ``max_iterations``, when
the target or the fingertips leave the picture (not measured in the monitor's ``max_missed_frames`` pictures in a
row: one picture's noise may spoil a small, distant target's decoding, and the next is taken), when the error keeps growing, or when a step would bring
the fingertips to the table (as this picture's fingertips and target place them, whichever C_H_G drives). Then a straight descent of ``approach_mm`` along the tool z
and the jaws close.

The loop takes a ``GraspRig`` (grab, tool step, jaws, truth): ``EngineRig`` drives the engine's devices (a
real or simulated cell); the study ``bench/positioning.py`` drives a ``SimWorld`` directly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import Cell
from selfview.errors import AlarmError, CalibrationError, ConfigError, ImageError
from selfview.maths.geometry import H_from_rotvec, check_rigid, inv_H, rotation_angle, rotvec_from_R, transform_points
from selfview.measurement.objects import ObjectSpec, TargetDetection, detect_target, object_pose
from selfview.estimation.policy import TRACKER_NOISE_PX, Monitor
from selfview.procedures.engine import Step
from selfview.measurement.fingers import SilhouetteTracker

__all__ = ["ServoSettings", "GraspRig", "EngineRig", "GraspFailed", "GraspResult", "servo_grasp", "run_grasp",
           "draw_servo", "pose_error", "TABLE_MARGIN_MM"]

#: A commanded pose whose fingertips (as measured) come closer than this to the table is refused (mm).
TABLE_MARGIN_MM = 2.0
#: Iterations in a row in which the measured error grew before the loop gives up.
GROWING_ITERATIONS = 3
#: Pictures taken at the grasp pose after the descent (the target in view, the fingertips hidden by the block):
#: each measures the TCP against G* and corrects by a bounded step; the last one only measures.
GRASP_PICTURES = 3
#: A correction at the grasp pose larger than this (mm, deg) is refused: the fingers straddle the block there.
GRASP_CORRECTION_MM, GRASP_CORRECTION_DEG = 3.0, 2.0
#: The target is searched for in a window around where the last pose and the step since put it: this much of
#: the target's projected size around it, and ``WINDOW_MARGIN_PX`` more.
WINDOW_MARGIN, WINDOW_MARGIN_PX = 0.25, 16


class GraspFailed(CalibrationError):
    """The servo could not bring the gripper to the object; the message says why (nothing more is moved)."""


@dataclass(frozen=True)
class ServoSettings:
    """``gain`` fraction of the error corrected per step; ``max_step_mm``, ``max_step_deg`` the cap of each
    step; ``stop_mm``, ``stop_deg`` convergence; ``max_iterations``; ``online`` keep ``C_H_G`` current from the
    fingertips (else the calibration's, the fingertips watched for the alarm only); ``method`` the update
    method; ``state`` the jaws' state while approaching and ``grip_state`` to hold."""

    gain: float = 0.8
    max_step_mm: float = 40.0
    max_step_deg: float = 8.0
    stop_mm: float = 0.1
    stop_deg: float = 0.1
    max_iterations: int = 20
    online: bool = True
    method: str = "4P-U"
    state: str = "open"
    grip_state: str = "closed"

    def check(self) -> "ServoSettings":
        for nm, lo, hi in (("gain", 0.05, 1.0), ("max_step_mm", 0.1, 100.0), ("max_step_deg", 0.05, 30.0),
                           ("stop_mm", 0.001, 10.0), ("stop_deg", 0.001, 10.0)):
            v = getattr(self, nm)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and np.isfinite(v) and lo <= v <= hi):
                raise ConfigError(f"servo {nm}: expected {lo:g}..{hi:g}, got {v!r}")
        if isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, int) or not 1 <= self.max_iterations <= 1000:
            raise ConfigError(f"servo max_iterations: expected 1..1000, got {self.max_iterations!r}")
        return self


class GraspRig(Protocol):
    """What the servo needs from the cell."""

    def grab(self) -> np.ndarray: ...  # a (H, W) uint8 picture taken now

    def tool_step(self, delta: np.ndarray, max_mm: float, max_deg: float) -> None: ...  # straight, in the tool frame

    def jaws(self, state: str) -> None: ...  # move the jaws to a state and wait

    def truth(self) -> dict | None: ...  # the simulator's truth (C_H_G, C_H_O, ...) or None

    def outcome(self) -> dict | None: ...  # the simulated world's verdict on the grasp, or None on a real cell


@dataclass
class GraspResult:
    """The run's figures (plain types, JSON-ready). ``iterations`` records, one per frame: measured error
    ``error_mm`` [x, y, z] (the stand-off goal in the gripper frame) and ``error_deg``, in simulation the
    ``true_error_mm``/``true_error_deg``, ``processing_ms`` (picture to command, wall clock) and ``cpu_ms`` (the
    same, this process's CPU time: what it costs without the machine's other load), what the fingertips said,
    ``target_missed`` why the target was not measured in the pictures taken before (none: the first was used).
    ``at_grasp`` the same records of the pictures taken after the descent (the error against G*, C_H_G the
    servo's last: the block hides the fingertips there), ``grasp_error_mm``/``grasp_error_deg`` the last
    one's measured error (None when the target was not measured there: ``grasp_note`` says why)."""

    converged: bool = False
    held: bool | None = None
    reason: str = ""
    iterations: list = field(default_factory=list)
    true_error_mm: list | None = None
    true_error_deg: float | None = None
    outcome: dict | None = None
    C_H_G: list | None = None
    at_grasp: list = field(default_factory=list)
    grasp_error_mm: list | None = None
    grasp_error_deg: float | None = None
    grasp_note: str = ""

    def to_dict(self) -> dict:
        return {"converged": self.converged, "held": self.held, "iterations": len(self.iterations),
                "reason": self.reason, "true_error_mm": self.true_error_mm, "true_error_deg": self.true_error_deg,
                "grasp_error_mm": self.grasp_error_mm, "grasp_error_deg": self.grasp_error_deg,
                "grasp_note": self.grasp_note, "outcome": self.outcome, "C_H_G": self.C_H_G,
                "records": self.iterations, "at_grasp": self.at_grasp}


def pose_error(A_H_B) -> tuple[np.ndarray, float]:
    """(translation (3,) [mm], rotation angle [deg]) of a transform."""
    H = np.asarray(A_H_B, float)
    return H[:3, 3].copy(), float(np.degrees(rotation_angle(H[:3, :3])))


class _TargetWindow:
    """The object's pose frame after frame (``object_pose``), its target searched for first in the part of the
    picture where the last pose, moved by the tool step since (the camera rides on the gripper), puts it: the
    ChArUco detection, most of an iteration's time, scales with the pixels it scans. The first picture, and any
    whose window does not show the target, is searched whole (a second target anywhere is refused there)."""

    def __init__(self, camera: CameraModel, obj: ObjectSpec):
        self.camera, self.obj = camera, obj
        w, h = obj.target.size
        self.outline = np.array([[-w / 2, -h / 2, 0], [w / 2, -h / 2, 0], [w / 2, h / 2, 0], [-w / 2, h / 2, 0]], float)
        self.C_H_O: np.ndarray | None = None
        self.windowed = 0

    def moved(self, C_H_G, delta) -> None:
        """The tool moved by ``delta`` (4, 4, in G): where the object now is in the camera, as ``C_H_G`` says."""
        if self.C_H_O is not None:
            C = np.asarray(C_H_G, float)
            self.C_H_O = C @ inv_H(delta) @ inv_H(C) @ self.C_H_O

    def _window(self, shape) -> tuple[int, int, int, int] | None:
        if self.C_H_O is None:
            return None
        p = transform_points(self.C_H_O, self.outline)
        if not np.all(p[:, 2] > 1.0):
            return None
        uv = self.camera.project(p)
        if not np.isfinite(uv).all():
            return None
        lo, hi = uv.min(axis=0), uv.max(axis=0)
        m = WINDOW_MARGIN * (hi - lo) + WINDOW_MARGIN_PX
        x0, y0 = np.maximum(np.floor(lo - m), 0).astype(int)
        x1, y1 = np.minimum(np.ceil(hi + m), (shape[1], shape[0])).astype(int)
        return (x0, y0, x1, y1) if x1 - x0 > 16 and y1 - y0 > 16 else None

    def pose(self, img: np.ndarray):
        """The object's ``ObjectPose`` in ``img``; raises as ``object_pose`` does."""
        box = self._window(np.shape(img))
        pose = None
        if box is not None:
            x0, y0, x1, y1 = box
            try:
                det = detect_target(np.asarray(img)[y0:y1, x0:x1], self.obj.target)
                pose = object_pose(img, self.camera, self.obj, TargetDetection(det.uv + (x0, y0), det.p_O, det.ids,
                                                                               det.markers))
                self.windowed += 1
            except (CalibrationError, ImageError):
                pose = None  # not (wholly) in the window (or the window blank): the whole picture
        if pose is None:
            pose = object_pose(img, self.camera, self.obj)
        self.C_H_O = pose.C_H_O
        return pose


def _true_errors(truth: dict | None, obj: ObjectSpec, O_H_goal) -> tuple[list | None, float | None]:
    """The goal's true pose in the gripper frame now: ([x, y, z] mm, deg), from the simulator's truth."""
    if not truth or truth.get("C_H_O") is None:
        return None, None
    G_H_O = inv_H(np.asarray(truth["C_H_G"])) @ np.asarray(truth["C_H_O"])
    t, a = pose_error(G_H_O @ O_H_goal)
    return [float(v) for v in t], a


def _step_towards(G_H_goal: np.ndarray, s: ServoSettings) -> np.ndarray:
    """The tool motion: ``gain`` times the error (translation and theta-u), scaled down into the caps."""
    t = s.gain * G_H_goal[:3, 3]
    u = s.gain * rotvec_from_R(G_H_goal[:3, :3])
    k = min(1.0, 0.999 * s.max_step_mm / max(np.linalg.norm(t), 1e-12),
            0.999 * np.radians(s.max_step_deg) / max(np.linalg.norm(u), 1e-12))  # within the caps after rounding
    return H_from_rotvec(k * u, k * t)


def _table_check(G_H_O: np.ndarray, delta: np.ndarray, obj: ObjectSpec, p_G: np.ndarray, what: str) -> None:
    """Refuse a motion after which a fingertip (as measured) would come within ``TABLE_MARGIN_MM`` of the table
    (the plane the block stands on: z_O = its height)."""
    tips_O = transform_points(inv_H(G_H_O) @ delta, p_G)
    low = float(np.max(tips_O[:, 2]))
    if low > obj.block[2] - TABLE_MARGIN_MM:
        raise GraspFailed(f"{what} would bring a fingertip {obj.block[2] - low:.1f} mm from the table (as measured; "
                          f"{TABLE_MARGIN_MM:g} mm kept): refused, nothing sent")


class _Growth:
    """Gives up when the measured error grew ``GROWING_ITERATIONS`` times in a row by more than noise."""

    def __init__(self):
        self.history: list[float] = []

    def check(self, err_mm: float, err_deg: float) -> None:
        e = err_mm + err_deg  # 1 deg weighs as 1 mm
        self.history.append(e)
        h = self.history[-(GROWING_ITERATIONS + 1):]
        if len(h) == GROWING_ITERATIONS + 1 and all(b > a for a, b in zip(h, h[1:])) and h[-1] > h[0] + 0.5:
            raise GraspFailed(f"the error grows: {h[0]:.2f} to {h[-1]:.2f} (mm + deg) over the last "
                              f"{GROWING_ITERATIONS} iterations; stopped")


def _check_inputs(C_H_G, camera, p_G6, taught_C_H_O=None) -> None:
    """``ConfigError`` naming the input at fault, before anything moves: ``C_H_G`` (and ``taught_C_H_O``) a
    finite rigid (4, 4) transform, ``camera`` a ``CameraModel``, ``p_G6`` (6, 3) finite fingertip points."""
    check_rigid(C_H_G, "the calibration's C_H_G")
    if taught_C_H_O is not None:
        check_rigid(taught_C_H_O, "taught_C_H_O")
    if not isinstance(camera, CameraModel):
        raise ConfigError(f"camera: expected a selfview.maths.camera.CameraModel, got {type(camera).__name__}")
    try:
        p = np.asarray(p_G6, float)
    except (TypeError, ValueError):
        p = np.full(1, np.nan)
    if p.shape != (6, 3) or not np.isfinite(p).all():
        raise ConfigError(f"fingertip points p_G6: expected (6, 3) finite points in G [mm], got shape {p.shape}")


def servo_grasp(rig: GraspRig, cell: Cell, obj: ObjectSpec, C_H_G, camera: CameraModel, p_G6,
                settings: ServoSettings = ServoSettings(), *, result: GraspResult | None = None,
                on_iteration: Callable[[dict, np.ndarray, object], None] | None = None,
                before_frame: Callable[[int], None] | None = None, taught_C_H_O=None) -> GraspResult:
    """Servo the gripper to ``obj``'s grasp frame, descend and close the jaws (module docstring).

    ``C_H_G`` (4, 4) the calibration's; ``camera`` its interior orientation; ``p_G6`` (6, 3) the fingertip
    points [mm] of ``settings.state``; ``result`` filled as the loop goes (so a caller still has the
    iterations when it raises); ``on_iteration(record, picture, object pose)`` sees each frame;
    ``before_frame(k)`` (simulation) may disturb the camera before frame k; ``taught_C_H_O`` (4, 4): the
    stand-off goal taught by a picture taken there (the object's pose in the camera frame then), instead of
    the object file's grasp frame: ``C_H_G`` then cancels out of the goal. Raises ``GraspFailed`` (not
    converged, target or fingertips lost, error growing, the table too near), ``AlarmError`` (the
    fingertips say the calibration is off beyond the alarm limit)."""
    s = settings.check()
    _check_inputs(C_H_G, camera, p_G6, taught_C_H_O)
    res = result if result is not None else GraspResult()
    gap = cell.gripper.gap(s.state)
    cell.gripper.gap(s.grip_state)  # an unknown holding state is named now, not after the descent
    C0 = np.asarray(C_H_G, float)
    mon = Monitor(C0, camera, p_G6, cell.monitor, update_method=s.method, noise_px=TRACKER_NOISE_PX, learn_view=True)
    tracker = SilhouetteTracker(camera, cell.gripper, points=range(6))
    target = _TargetWindow(camera, obj)
    O_H_pre = obj.O_H_Gpre
    growth = _Growth()
    rig.jaws(s.state)
    for k in range(s.max_iterations + 1):
        if before_frame is not None:
            before_frame(k)
        img, d, pose, missed, (t0, c0) = _picture(rig, tracker, mon, target, gap, k)
        C_now = mon.C_H_G if s.online else C0
        if taught_C_H_O is not None:
            O_H_pre = inv_H(taught_C_H_O) @ C_now
        G_H_O = inv_H(C_now) @ pose.C_H_O
        G_H_pre = G_H_O @ O_H_pre
        # the table's clearance from the fingertips as measured in this picture, whichever C_H_G drives
        G_H_O_seen = inv_H(mon.C_H_G) @ pose.C_H_O
        e_t, e_deg = pose_error(G_H_pre)
        done = float(np.linalg.norm(e_t)) < s.stop_mm and e_deg < s.stop_deg
        delta = None if done else _step_towards(G_H_pre, s)
        if delta is not None:
            _table_check(G_H_O_seen, delta, obj, p_G6, f"iteration {k + 1}'s step")
        ms, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
        true_t, true_deg = _true_errors(rig.truth(), obj, O_H_pre)
        rec = {"iteration": k + 1, "error_mm": [float(v) for v in e_t], "error_deg": e_deg,
               "true_error_mm": true_t, "true_error_deg": true_deg, "processing_ms": ms, "cpu_ms": cpu,
               "fingertips": d.action, "target_rms_px": pose.rms_px, "target_sigma_mm": [float(v) for v in pose.sigma_mm],
               "target_missed": missed}
        res.iterations.append(rec)
        if on_iteration is not None:
            on_iteration(rec, img, pose)
        if done:
            res.converged = True
            break
        if k == s.max_iterations:
            raise GraspFailed(f"not converged after {s.max_iterations} iterations: still {np.linalg.norm(e_t):.3f} mm "
                              f"and {e_deg:.3f} deg from the stand-off (stops at {s.stop_mm:g} mm, {s.stop_deg:g} deg)")
        growth.check(float(np.linalg.norm(e_t)), e_deg)
        rig.tool_step(delta, s.max_step_mm, s.max_step_deg)
        target.moved(mon.C_H_G, delta)
    _descend(rig, obj, target, C_now, mon.C_H_G, G_H_O_seen, p_G6, s, res, taught=taught_C_H_O is not None)
    truth = rig.truth()
    res.true_error_mm, res.true_error_deg = _true_errors(truth, obj, obj.O_H_Gstar)  # the TCP against G*
    res.outcome = rig.outcome()
    rig.jaws(s.grip_state)
    res.held = None if res.outcome is None else bool(res.outcome["held"])
    res.C_H_G = np.asarray(C_now).tolist()
    res.reason = "converged" + ("" if res.held is None else ("; held" if res.held else f"; not held: {res.outcome['why']}"))
    return res


def _picture(rig: GraspRig, tracker: SilhouetteTracker, mon: Monitor, target: _TargetWindow, gap: float, k: int):
    """Iteration ``k``'s picture: (picture, the monitor's decision on its fingertips, the object's pose, why the
    target was not measured in the pictures taken before it, (wall clock, CPU time) when it came). One
    picture's noise can spoil a small, distant target's decoding: such a picture is missed (nothing moves) and
    the next one taken, up to the monitor's ``max_missed_frames`` in a row (then ``GraspFailed``); the
    fingertips are judged in every picture (``AlarmError`` on the monitor's alarm)."""
    missed: list[str] = []
    while True:
        img = rig.grab()
        t0, c0 = time.perf_counter(), time.process_time()
        ft = tracker.find(img, mon.C_H_G, gap)
        d = mon.step(ft.uv, ft.found, lost=ft.lost)
        if d.action == "alarm":
            raise AlarmError(f"iteration {k + 1}: {d.reason}")
        try:
            return img, d, target.pose(img), missed, (t0, c0)
        except CalibrationError as exc:
            missed.append(str(exc))
            if len(missed) >= mon.max_missed_frames:
                raise GraspFailed(f"iteration {k + 1}: the object's target, {len(missed)} picture(s) in a row "
                                  f"(monitor.max_missed_frames {mon.max_missed_frames}): {exc}") from None


def _descend(rig: GraspRig, obj: ObjectSpec, target: _TargetWindow, C_H_G, C_H_G_seen, G_H_O_seen, p_G6,
             s: ServoSettings, res: GraspResult, taught: bool) -> None:
    """The last straight descent along the tool z (the table kept as ``G_H_O_seen`` places it), then the
    pictures at the grasp pose (``_at_grasp``; not for a goal taught at the stand-off)."""
    descent = np.eye(4)
    descent[2, 3] = obj.approach_mm
    _table_check(G_H_O_seen, descent, obj, p_G6, "the descent")
    rig.tool_step(descent, max(obj.approach_mm, 0.001), 0.001)
    target.moved(C_H_G_seen, descent)
    if taught:
        res.grasp_note = "a taught goal holds at the stand-off only: the descent is not measured"
    else:
        _at_grasp(rig, obj, target, C_H_G, C_H_G_seen, p_G6, s, res)


def _at_grasp(rig: GraspRig, obj: ObjectSpec, target: _TargetWindow, C_H_G, C_H_G_seen, p_G6, s: ServoSettings,
              res: GraspResult) -> None:
    """After the descent: up to ``GRASP_PICTURES`` pictures of the target at the grasp pose, each measuring the TCP
    against G* through ``C_H_G`` (the servo's last: the block hides the fingertips) and, while beyond the stop
    thresholds, correcting by a bounded step (the servo's gain and caps, at most ``GRASP_CORRECTION_MM`` /
    ``_DEG``, the table kept as ``C_H_G_seen`` places it). A target not measured there leaves the grasp as the
    descent put it (``res.grasp_note``); a larger error raises ``GraspFailed`` before anything moves."""
    for k in range(GRASP_PICTURES):
        img = rig.grab()
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            pose = target.pose(img)
        except CalibrationError as exc:
            res.grasp_note = f"the target at the grasp pose: {exc}; the descent is not corrected"
            return
        G_H_star = inv_H(C_H_G) @ pose.C_H_O @ obj.O_H_Gstar
        e_t, e_deg = pose_error(G_H_star)
        n = float(np.linalg.norm(e_t))
        done = (n < s.stop_mm and e_deg < s.stop_deg) or k == GRASP_PICTURES - 1
        if n > GRASP_CORRECTION_MM or e_deg > GRASP_CORRECTION_DEG:
            raise GraspFailed(f"the picture at the grasp pose puts the gripper {n:.2f} mm and {e_deg:.2f} deg from the "
                              f"grasp frame, beyond the {GRASP_CORRECTION_MM:g} mm / {GRASP_CORRECTION_DEG:g} deg a "
                              "correction around the block may take: stopped")
        delta = None if done else _step_towards(G_H_star, s)
        if delta is not None:
            _table_check(inv_H(C_H_G_seen) @ pose.C_H_O, delta, obj, p_G6, f"the correction at the grasp pose {k + 1}")
        ms, cpu = (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3
        true_t, true_deg = _true_errors(rig.truth(), obj, obj.O_H_Gstar)
        res.at_grasp.append({"picture": k + 1, "error_mm": [float(v) for v in e_t], "error_deg": e_deg,
                             "true_error_mm": true_t, "true_error_deg": true_deg, "processing_ms": ms, "cpu_ms": cpu,
                             "target_rms_px": pose.rms_px, "target_sigma_mm": [float(v) for v in pose.sigma_mm]})
        res.grasp_error_mm, res.grasp_error_deg = [float(v) for v in e_t], e_deg
        if done:
            return
        rig.tool_step(delta, s.max_step_mm, s.max_step_deg)
        target.moved(C_H_G_seen, delta)


class EngineRig:
    """A ``GraspRig`` on the engine's devices (real or simulated): every motion a ``tool`` step, the jaws a
    ``gripper`` step, the pictures ``grab`` steps. ``outcome`` (simulation) returns the world's verdict."""

    def __init__(self, engine, outcome: Callable[[], dict] | None = None):
        self.e = engine
        self._outcome = outcome

    def grab(self) -> np.ndarray:
        return self.e.execute(Step("grab", {}))

    def tool_step(self, delta, max_mm, max_deg) -> None:
        self.e.execute(Step("tool", {"delta": np.asarray(delta, float), "max_mm": max_mm, "max_deg": max_deg},
                            note="servo step"))

    def jaws(self, state: str) -> None:
        self.e.execute(Step("gripper", {"state": state}))

    def truth(self) -> dict | None:
        t = self.e.devices.truth
        return t() if t is not None else None

    def outcome(self) -> dict | None:
        return self._outcome() if self._outcome is not None else None


def run_grasp(session, obj: ObjectSpec, calibration, settings: ServoSettings = ServoSettings(), *,
              start="pregrasp", result: GraspResult | None = None,
              on_iteration: Callable[[dict, np.ndarray, object], None] | None = None) -> GraspResult:
    """On an open ``CellSession``: move to the pre-grasp pose ``start`` (a taught location's name or a (4, 4)
    ``base_H_G``; checked against the limits before anything moves), servo, descend and close the jaws
    (``servo_grasp``). ``calibration`` a ``selfview.files.calfile`` calibration (its ``C_H_G``, camera and the
    fingertip points of ``settings.state``). In simulation the world's verdict on the grasp is in
    ``result.outcome``. The engine stops the robot and leaves the valve safe on any error or signal.
    ``ConfigError`` before anything moves for settings out of range, a jaw state the cell does not have, or
    a calibration that is not usable (C_H_G not a finite rigid transform, no fingertip points for
    ``settings.state``).

    Lab script::

        from selfview.procedures.grasp import run_grasp
        with CellSession.real(cell, robot=..., gripper=..., camera=...) as s:
            res = run_grasp(s, load_object("part.yaml"), load_calibration("calibration.yaml"))
    """
    settings.check()
    for st in (settings.state, settings.grip_state):
        session.cell.gripper.gap(st)  # ConfigError naming the cell's states
    if settings.state not in calibration.points_G:
        raise ConfigError(f"the calibration has no fingertip points for the jaws {settings.state!r} "
                          f"(it has {', '.join(calibration.points_G)})")
    _check_inputs(calibration.C_H_G, calibration.camera, calibration.points_G[settings.state])
    res = result if result is not None else GraspResult()
    outcome = None
    if session.sim is not None and session.sim.world.object is not None:
        from selfview.mocks.objects import grasp_outcome

        world = session.sim.world
        outcome = lambda: grasp_outcome(world, session.cell.gripper.gap(settings.state))  # noqa: E731
    plan = [Step("speed", {"pct": session.settings.speed_pct}), Step("move", {"target": start}, note="pre-grasp")]

    def body(e):
        for st in plan:
            e.execute(st)
        return servo_grasp(EngineRig(e, outcome), session.cell, obj, calibration.C_H_G, calibration.camera,
                           calibration.points_G[settings.state], settings, result=res, on_iteration=on_iteration)

    return session.engine.run(body, plan)


def draw_servo(image: np.ndarray, camera: CameraModel, pose, C_H_G, obj: ObjectSpec, axis_mm: float = 20.0) -> np.ndarray:
    """A BGR copy of ``image`` with the object's frame O (thin), the gripper frame G at the TCP and the
    stand-off goal (thick) drawn as x red, y green, z blue axes of ``axis_mm``."""
    import cv2

    out = cv2.cvtColor(np.asarray(image, np.uint8), cv2.COLOR_GRAY2BGR) if np.ndim(image) == 2 else np.array(image)
    frames = [(C_H_G, 2)]
    if pose is not None:
        frames += [(pose.C_H_O, 1), (pose.C_H_O @ obj.O_H_Gpre, 2)]
    for H, width in frames:
        p = transform_points(H, np.array([[0, 0, 0], [axis_mm, 0, 0], [0, axis_mm, 0], [0, 0, axis_mm]], float))
        if np.any(p[:, 2] <= 1.0):
            continue
        uv = camera.project(p)
        if not np.isfinite(uv).all():
            continue
        o = tuple(int(round(v)) for v in uv[0])
        for k, colour in zip(range(1, 4), ((0, 0, 255), (0, 200, 0), (255, 0, 0))):
            cv2.line(out, o, tuple(int(round(v)) for v in uv[k]), colour, width, cv2.LINE_AA)
    return out
