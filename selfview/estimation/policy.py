"""The on-line policy (paper, section 4): update, recalibrate or raise the alarm.

Each picture of the fingertips gives a differential estimate of the camera's motion on its mount; ``Policy`` judges it
against the cell's ``monitor`` limits and ``Monitor`` applies that frame by frame, telling a missed frame from an alarm.
"""

from __future__ import annotations

import hashlib
import logging
import math
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from selfview.maths.camera import CameraModel
from selfview.maths.lm import wald_chi2
from selfview.files.cell import POINT_NAMES, MonitorLimits
from selfview.errors import AlarmError, CalibrationError, ConfigError
from selfview.maths.geometry import H_from_rotvec, check_rigid, inv_H, orthonormalize, rotation_angle, rotvec_from_R
from selfview.estimation.online import MODEL_METHOD, MotionEstimate, estimate, parse_method, select_points

__all__ = ["ACTIONS", "CHI2_SIGNIFICANT", "TRACKER_NOISE_PX", "MODEL_TOLERANCE_PX", "Decision", "Policy", "Monitor",
           "significance"]

ACTIONS: tuple[str, ...] = ("update", "recalibrate", "alarm", "missed")

#: A picture whose grey levels span less than this (1st to 99th percentile) shows nothing: a blank frame.
BLANK_CONTRAST_GREY = 8.0
#: Frames over which poses alternating between two values (a loose mount, two cameras) raise the alarm.
ALTERNATION_WINDOW = 6
#: Upper 0.1 % point of chi-square with 6 dof: an update whose motion scores under it against its covariance is
#: noise and is not applied (a still camera exceeds it once in a thousand frames).
CHI2_SIGNIFICANT = 22.458
#: Frame-to-frame pixel noise of the tracker's fingertip corners, camera still: 0.29 px on the worst coordinate.
TRACKER_NOISE_PX = 0.3
#: Noise of the first picture after a calibration against the nominal ``p_G6``: fingers made to ISO 2768-1 m
#: (0.1 mm sd, 0.9 px at 110 mm), seen by another measurement than the calibration's, differ by up to a pixel.
MODEL_TOLERANCE_PX = 1.0

_LOG = logging.getLogger("selfview.estimation.policy")
_LEVEL = {"update": logging.INFO, "recalibrate": logging.WARNING, "alarm": logging.ERROR, "calibrated": logging.INFO,
          "missed": logging.WARNING}


@dataclass(frozen=True)
class Decision:
    """What the policy decided for one picture, and the measures that led to it.

    ``action`` in ``ACTIONS``; ``reason`` naming measure and limit; ``delta_deg``, ``d_mm`` the change since the last
    calibration, ``rms_px`` the judged estimate's residual (NaN without); ``C_H_G`` (4, 4) the transform from now on,
    re-orthonormalised so no error accumulates (eq. 13's own: ``estimate.C_H_G``), unchanged on an alarm (None if
    unknown); ``method``, ``points_used``, ``estimate``: the estimate judged; ``n_found`` fingertips found."""

    action: str
    reason: str
    delta_deg: float
    d_mm: float
    rms_px: float
    C_H_G: np.ndarray | None
    method: str | None = None
    n_found: int = 0
    points_used: tuple[str, ...] = ()
    estimate: MotionEstimate | None = field(default=None, repr=False, compare=False)

    @classmethod
    def of(cls, action: str, reason: str, C_H_G, est: MotionEstimate | None = None, n_found: int = 0,
           delta: float = math.nan, d: float = math.nan) -> "Decision":
        """The decision with the residual, method and points of the judged estimate ``est`` (if any)."""
        if est is None:
            return cls(action, reason, delta, d, math.nan, C_H_G, None, int(n_found))
        return cls(action, reason, delta, d, est.rms_px, C_H_G, est.method, int(n_found), est.points_used, est)

    def to_dict(self) -> dict:
        """Plain JSON-ready record (NaN as None)."""

        def num(v):
            return None if v is None or not math.isfinite(v) else float(v)

        est = self.estimate
        return {"action": self.action, "reason": self.reason, "delta_deg": num(self.delta_deg), "d_mm": num(self.d_mm),
                "rms_px": num(self.rms_px), "method": self.method, "n_found": int(self.n_found),
                "points_used": list(self.points_used), "condition": num(est.condition) if est is not None else None,
                "chi2": num(significance(est)) if est is not None else None,
                "C_H_G": None if self.C_H_G is None else np.asarray(self.C_H_G).tolist()}


def _pose_about(est: MotionEstimate, C_H_G) -> np.ndarray:
    """The estimate's pose about ``C_H_G`` as (rotation vector, translation) (6,), for fusion and outlier tests."""
    M = orthonormalize(np.asarray(est.C_H_G_orth, float)) @ inv_H(np.asarray(C_H_G, float))
    return np.concatenate([rotvec_from_R(M[:3, :3]), M[:3, 3]])


def significance(est: MotionEstimate) -> float:
    """The chi-square ``m^T C^-1 m`` of an estimate's motion (6,) against its covariance (6, 6); NaN if unknown."""
    C = np.asarray(est.covariance, float)
    m = np.asarray(est.motion, float)
    if C.shape != (6, 6) or m.shape != (6,) or not (np.isfinite(C).all() and np.isfinite(m).all()):
        return math.nan
    chi2 = wald_chi2(m, C)
    return chi2 if math.isfinite(chi2) else math.nan


def _selectable(points: str, found: np.ndarray) -> bool:
    """Can the ``found`` (6,) fingertips serve an estimate from ``points`` ('3P' to '6P')?"""
    try:
        select_points(points, found)
        return True
    except CalibrationError:
        return False


class Policy:
    """The update / recalibrate / alarm rule of section 4 for one cell's limits.

    ``limits``: ``Cell.monitor`` (update_limit, alarm_limit: angle [deg] and shift [mm], either exceeding; max_rms_px).
    Within ``update_limit``: update; within ``alarm_limit``: recalibrate (NP-R); beyond it, fewer than 3 fingertips or
    a residual over ``max_rms_px``: the alarm, ``C_H_G`` unchanged. The change is delta and d of eq. 14 (the camera's
    motion ``C'_H_G C_H_G^-1``) since the last calibration, not the previous frame, so a creeping camera is caught.
    ``chi2_limit`` (e.g. ``CHI2_SIGNIFICANT``; None: off): an estimate whose motion since the current ``C_H_G`` scores
    under it (``significance``) is noise, however large its poorly determined part: 'update', ``C_H_G`` kept."""

    def __init__(self, limits: MonitorLimits, *, chi2_limit: float | None = None):
        if not isinstance(limits, MonitorLimits):
            raise ConfigError(f"policy limits: expected selfview.files.cell.MonitorLimits, got {type(limits).__name__}")
        if chi2_limit is not None and not (isinstance(chi2_limit, (int, float)) and math.isfinite(chi2_limit)
                                           and chi2_limit > 0.0):
            raise ConfigError(f"policy chi2_limit: expected a positive chi-square or None, got {chi2_limit!r}")
        self.limits = limits
        self.chi2_limit = None if chi2_limit is None else float(chi2_limit)

    @staticmethod
    def change(C_H_G_new, C_H_G_ref) -> tuple[float, float]:
        """(delta [deg], d [mm]) of eq. 14: rotation angle and shift of ``C_H_G_new C_H_G_ref^-1``, both (4, 4)."""
        new = orthonormalize(np.asarray(C_H_G_new, dtype=float))
        M = new @ inv_H(orthonormalize(np.asarray(C_H_G_ref, dtype=float)))
        return math.degrees(rotation_angle(M)), float(np.linalg.norm(M[:3, 3]))

    def _exceeds(self, limit, delta_deg: float, d_mm: float) -> bool:
        return delta_deg > limit.angle_deg or d_mm > limit.shift_mm

    def classify(self, delta_deg: float, d_mm: float) -> str:
        """'update', 'recalibrate' or 'alarm' for a change (deg, mm) since the last calibration."""
        if self._exceeds(self.limits.alarm_limit, delta_deg, d_mm):
            return "alarm"
        if self._exceeds(self.limits.update_limit, delta_deg, d_mm):
            return "recalibrate"
        return "update"

    def decide(self, estimate_U: MotionEstimate | None, n_found: int, *, C_H_G=None, C_H_G_calibrated=None,
               recalibration: MotionEstimate | Callable[[], MotionEstimate] | None = None,
               error: str | None = None) -> Decision:
        """Decide for one picture.

        ``estimate_U`` the NP-U or NP-I estimate (None: ``error`` says why); ``C_H_G`` (4, 4) the current transform
        (default the estimate's prior); ``C_H_G_calibrated`` (4, 4) the one the limits refer to (default the current);
        ``recalibration`` an NP-R estimate or a callable computing it when needed (its ``CalibrationError``: an alarm;
        none: 'recalibrate' leaves ``C_H_G`` unchanged)."""
        lim = self.limits
        if C_H_G is None and estimate_U is not None:
            C_H_G = estimate_U.C_H_G_prior
        unchanged = None if C_H_G is None else np.asarray(C_H_G, dtype=float).copy()

        def alarm(reason, delta=math.nan, d=math.nan, est=None):
            return Decision.of("alarm", reason, unchanged, est, n_found, delta, d)

        if n_found < 3:
            return alarm(f"only {n_found} fingertip point(s) found; at least 3 are needed to follow the camera")
        if estimate_U is None:
            return alarm(f"no update estimate: {error or 'none was computed'}")
        est = estimate_U
        if not est.rms_px <= lim.max_rms_px:
            return alarm(f"{est.method} residual {est.rms_px:.3f} px exceeds max_rms_px {lim.max_rms_px} px: "
                         "the model no longer fits the fingertips", est=est)
        chi2 = significance(est) if self.chi2_limit is not None else math.nan
        if math.isfinite(chi2) and chi2 < self.chi2_limit:  # first: a large but weak motion is no move
            known = C_H_G_calibrated is not None and unchanged is not None
            kept = self.change(unchanged, C_H_G_calibrated) if known else (0.0, 0.0)
            return Decision.of("update", f"the motion since the current C_H_G ({est.delta_deg:.3f} deg / "
                               f"{est.d_mm:.3f} mm, {est.method}) is within the measurement's noise (chi-square "
                               f"{chi2:.1f} under {self.chi2_limit:g}): C_H_G kept", unchanged, est, n_found, *kept)
        delta, d = (self.change(est.C_H_G_orth, C_H_G_calibrated) if C_H_G_calibrated is not None
                    else (est.delta_deg, est.d_mm))
        where = f"change since the last calibration {delta:.3f} deg / {d:.3f} mm ({est.method})"
        action = self.classify(delta, d)
        if action == "alarm":
            a = lim.alarm_limit
            return alarm(f"{where} exceeds the alarm limit {a.angle_deg} deg / {a.shift_mm} mm", delta, d, est)
        u = lim.update_limit
        if action == "update":
            return Decision.of("update", f"{where} within the update limit {u.angle_deg} deg / {u.shift_mm} mm",
                               est.C_H_G_orth.copy(), est, n_found, delta, d)
        why = f"{where} exceeds the update limit {u.angle_deg} deg / {u.shift_mm} mm"
        if recalibration is None:
            return Decision.of("recalibrate", f"{why}; no recalibration supplied, C_H_G unchanged", unchanged, est,
                               n_found, delta, d)
        try:
            est_R = recalibration() if callable(recalibration) else recalibration
        except CalibrationError as exc:
            return alarm(f"{why}, and the recalibration failed: {exc}", delta, d, est)
        if not est_R.rms_px <= lim.max_rms_px:
            return alarm(f"{why}; the recalibration's residual {est_R.rms_px:.3f} px exceeds max_rms_px "
                         f"{lim.max_rms_px} px: the model no longer fits the fingertips", delta, d, est_R)
        ref = est_R.C_H_G_prior if C_H_G_calibrated is None else C_H_G_calibrated
        delta_R, d_R = self.change(est_R.C_H_G, ref) if ref is not None else (est_R.delta_deg, est_R.d_mm)
        if self.classify(delta_R, d_R) == "alarm":
            a = lim.alarm_limit
            return alarm(f"{why}; the recalibration ({est_R.method}) measures {delta_R:.3f} deg / {d_R:.3f} mm, beyond "
                         f"the alarm limit {a.angle_deg} deg / {a.shift_mm} mm", delta_R, d_R, est_R)
        return Decision.of("recalibrate", f"{why}; recalibrated by {est_R.method} ({delta_R:.3f} deg / {d_R:.3f} mm, "
                           f"residual {est_R.rms_px:.3f} px)", est_R.C_H_G.copy(), est_R, n_found, delta, d)


class Monitor:
    """Keeps ``C_H_G`` true while the robot works: one policy decision per picture.

    ``C_H_G`` (4, 4) the calibrated start; ``camera`` its interior orientation; ``p_G6`` (6, 3) fingertip points [mm];
    ``limits`` ``MonitorLimits`` or a ``Policy``. ``update_method`` NP-U or NP-I (default '4P-U', down to 3P when not
    all are found) or 'E' (``step``'s ``model_C_H_G``); ``recalibration_method`` '4P-R', '5P-R' or 'auto'.
    ``raise_on_alarm``: raise ``AlarmError`` after logging. Decisions are logged and kept in ``records``. A missed
    frame (``lost``, under 3 points, ``missed``, ``frame_problem``) never updates; ``max_missed_frames`` in a row raise
    the alarm, as do poses alternating over ``ALTERNATION_WINDOW`` frames. ``noise_px`` (e.g. ``TRACKER_NOISE_PX``):
    the pixel noise between frames; given, an insignificant update keeps ``C_H_G`` (``CHI2_SIGNIFICANT`` unless
    ``limits`` is a ``Policy``) and pictures within the noise after a followed move are fused with it (``_fuse``).
    ``learn_view``: the first picture after each calibration replaces the found points' nominal rows by their
    back-projection onto the fingertips' plane, so a measurement's own view of the real fingers cancels in the
    differential; an estimate using a point not yet learned is judged at ``MODEL_TOLERANCE_PX``."""

    def __init__(self, C_H_G, camera: CameraModel, p_G6, limits: MonitorLimits | Policy, *,
                 update_method: str = "4P-U", recalibration_method: str = "auto", raise_on_alarm: bool = False,
                 logger: logging.Logger | None = None, max_missed_frames: int | None = None,
                 noise_px: float | None = None, learn_view: bool = False):
        if noise_px is not None and not (isinstance(noise_px, (int, float)) and math.isfinite(noise_px)
                                         and noise_px > 0):
            raise ConfigError(f"noise_px: expected a positive pixel noise or None, got {noise_px!r}")
        self.noise_px = None if noise_px is None else float(noise_px)
        self.learn_view = bool(learn_view)
        chi2_limit = CHI2_SIGNIFICANT if self.noise_px is not None else None
        self.policy = limits if isinstance(limits, Policy) else Policy(limits, chi2_limit=chi2_limit)
        n_miss = getattr(self.policy.limits, "max_missed_frames", 3) if max_missed_frames is None else max_missed_frames
        if isinstance(n_miss, bool) or not isinstance(n_miss, (int, np.integer)) or n_miss < 1:
            raise ConfigError(f"max_missed_frames: expected a positive whole number of frames, got {n_miss!r}")
        self.max_missed_frames = int(n_miss)
        self.missed_in_a_row = 0
        if update_method != MODEL_METHOD and parse_method(update_method)[1] not in ("U", "I"):
            raise ConfigError(f"update_method {update_method!r}: expected an NP-U or NP-I method, e.g. 4P-U or 4P-I, "
                              "or E (the model's own estimate)")
        if recalibration_method != "auto" and parse_method(recalibration_method)[1] != "R":
            raise ConfigError(f"recalibration_method {recalibration_method!r}: expected 'auto', '4P-R' or '5P-R'")
        if not isinstance(camera, CameraModel):
            raise ConfigError(f"camera: expected a selfview.maths.camera.CameraModel, got {type(camera).__name__}")
        self.camera = camera
        self.p_G6 = self._points(p_G6)
        self.update_method = update_method
        self.recalibration_method = recalibration_method
        self.raise_on_alarm = bool(raise_on_alarm)
        self.log = logger or _LOG
        self.records: list[dict] = []
        self.frame = 0
        self.alarmed = False
        self.C_H_G = check_rigid(C_H_G, "C_H_G")
        self.C_H_G_calibrated = self.C_H_G.copy()
        self._last_picture: bytes | None = None
        self._poses: deque = deque(maxlen=ALTERNATION_WINDOW)
        self._seen_for: np.ndarray | None = None  # the nominal points the learned view belongs to
        self._seen = self.p_G6.copy()  # the fingertip points as this measurement sees them (learn_view)
        self._learned = np.zeros(len(POINT_NAMES), bool)
        self._anchor: np.ndarray | None = None  # C_H_G applied at the last followed move (fusion), None: calibrated
        self._fused: list[np.ndarray] = []
        self._before_jump: tuple | None = None  # (C_H_G, anchor, fused) before the last picture's significant jump
        self._record(None, "initial calibration")

    @staticmethod
    def _points(p_G6) -> np.ndarray:
        p = np.asarray(p_G6, dtype=float)
        if p.shape != (len(POINT_NAMES), 3) or not np.isfinite(p).all():
            raise ConfigError(f"p_G6: expected ({len(POINT_NAMES)}, 3) finite fingertip points in G [mm], "
                              f"got {p.shape}")
        return p

    def _record(self, d: Decision | None, reason: str = "") -> None:
        """Keep and log the decision ``d``, or (None) a calibration to the current ``C_H_G`` for ``reason``."""
        if d is None:
            self.records.append({"frame": self.frame, "action": "calibrated", "reason": reason,
                                 "C_H_G": self.C_H_G.tolist()})
            self.log.log(_LEVEL["calibrated"], "frame %d: %s (%s)", self.frame, "calibrated", reason)
            return
        self.records.append({"frame": self.frame, **d.to_dict()})
        if d.method is None:
            self.log.log(_LEVEL[d.action], "frame %d: %s (%s)", self.frame, d.action, d.reason)
        else:
            values = (f"{v:.4f}" if math.isfinite(v) else "-" for v in (d.delta_deg, d.d_mm, d.rms_px))
            self.log.log(_LEVEL[d.action], "frame %d: %s by %s: %s [delta %s deg, d %s mm, rms %s px, %d points found]",
                         self.frame, d.action, d.method, d.reason, *values, d.n_found)

    def _conclude(self, d: Decision) -> Decision:
        """The frame's decision ``d`` kept, logged and returned; ``AlarmError`` on an alarm if ``raise_on_alarm``."""
        self.alarmed = d.action == "alarm"
        self._record(d)
        if self.alarmed and self.raise_on_alarm:
            raise AlarmError(f"frame {self.frame}: {d.reason}")
        return d

    def calibrated(self, C_H_G, reason: str = "off-line calibration") -> None:
        """Start again from a new calibration (off-line): the limits refer to it from now on."""
        self.C_H_G = check_rigid(C_H_G, "C_H_G")
        self.C_H_G_calibrated = self.C_H_G.copy()
        self.alarmed = False
        self._learned[:] = False  # a new reference: the next picture
        self._anchor, self._before_jump = None, None
        self._record(None, reason)

    def _view_points(self, p_nominal: np.ndarray) -> np.ndarray:
        """The points the estimates use: ``p_nominal`` (6, 3), or with ``learn_view`` its learned rows."""
        if not self.learn_view:
            return p_nominal
        if self._seen_for is None or not np.array_equal(self._seen_for, p_nominal):  # new points (jaw state)
            self._seen_for, self._seen = p_nominal.copy(), p_nominal.copy()
            self._learned = np.zeros(len(p_nominal), bool)
        return self._seen

    def _learn(self, uv: np.ndarray, found: np.ndarray) -> None:
        """``learn_view``: learn the found points not yet learned, back-projected onto their plane in G."""
        new = found & ~self._learned
        if not self.learn_view or not new.any():
            return
        try:
            p, _ = self.camera.backproject_to_plane(uv[new], self.C_H_G, self._seen_for[new, 2])
        except CalibrationError:  # seen edge-on: keep the nominal points
            return
        self._seen[new], self._learned[new] = p, True

    def _prior(self, method: str, found: np.ndarray) -> dict:
        """The estimator's prior pixel noise: ``noise_px``, at least ``MODEL_TOLERANCE_PX`` with an unlearned point."""
        if method == MODEL_METHOD:
            return {}
        sigma = self.noise_px
        if self.learn_view:
            try:
                if not self._learned[select_points(method, found)].all():
                    sigma = max(MODEL_TOLERANCE_PX, self.noise_px or 0.0)
            except CalibrationError:
                pass
        return {} if sigma is None else {"prior_sigma_px": sigma}

    def _update_method(self, found: np.ndarray) -> str:
        if self.update_method == MODEL_METHOD:
            return MODEL_METHOD
        n, kind = parse_method(self.update_method)
        k = next((k for k in range(n, 2, -1) if _selectable(f"{k}P", found)), None)
        return self.update_method if k is None else f"{k}P-{kind}"  # its own error names the missing points

    def _recalibration_method(self, found: np.ndarray) -> str:
        if self.recalibration_method != "auto":
            return self.recalibration_method
        return "5P-R" if _selectable("5P", found) else "4P-R"

    def frame_problem(self, image) -> str | None:
        """Why ``image`` (H, W) cannot be measured (blank, or the previous one again: a stuck source), or None."""
        img = np.asarray(image)
        digest = hashlib.blake2b(np.ascontiguousarray(img).tobytes(), digest_size=16).digest()
        same, self._last_picture = digest == self._last_picture, digest
        if same:
            return ("the picture is bit-identical to the previous one: the frame grabber or its source is stuck "
                    "(a camera's noise never repeats)")
        lo, hi = np.percentile(img, (1, 99)) if img.size else (0.0, 0.0)
        if hi - lo < BLANK_CONTRAST_GREY:
            return (f"blank picture (grey levels {lo:.0f}-{hi:.0f}, under {BLANK_CONTRAST_GREY:g} apart): no camera "
                    "signal, lens cap on, or no light")
        return None

    def _alternating(self) -> bool:
        """Do the last ``ALTERNATION_WINDOW`` measured poses alternate between two values?"""
        P = list(self._poses)
        if len(P) < ALTERNATION_WINDOW:
            return False
        lim, ex = self.policy.limits.update_limit, self.policy._exceeds
        return (all(ex(lim, *self.policy.change(a, b)) for a, b in zip(P, P[1:]))
                and not any(ex(lim, *self.policy.change(a, b)) for a, b in zip(P, P[2:])))

    def missed(self, reason: str) -> Decision:
        """A frame without the fingertips: never an update; after ``max_missed_frames`` in a row the alarm
        (``AlarmError`` if ``raise_on_alarm``)."""
        self.frame += 1
        return self._missed(str(reason), 0)

    def _missed(self, why: str, n_found: int) -> Decision:
        self.missed_in_a_row += 1
        k, n = self.missed_in_a_row, self.max_missed_frames
        if k >= n:
            reason = f"{k} frames in a row without the fingertips (monitor.max_missed_frames {n}); the last: {why}"
        else:
            reason = f"fingertips not found ({k} of {n} missed frames before the alarm): {why}"
        return self._conclude(Decision.of("alarm" if k >= n else "missed", reason, self.C_H_G.copy(), None, n_found))

    def step(self, uv6, found6, p_G6=None, *, lost: str | None = None, model_C_H_G=None,
             model_rms_px: float = float("nan")) -> Decision:
        """Judge and apply one picture: ``uv6`` (6, 2) distorted pixels (NaN where not found), ``found6`` (6,) bool,
        ``p_G6`` new points if the gripper state changed, ``lost`` why the measurement lost the fingertips (a missed
        frame, as is one with under 3 points). ``model_C_H_G`` (4, 4), ``model_rms_px``: the model-based pose and
        residual, for 'E'. Raises ``ValueError`` for bad shapes, ``AlarmError`` on an alarm if ``raise_on_alarm``."""
        self.frame += 1
        p = self._view_points(self.p_G6 if p_G6 is None else self._points(p_G6))
        uv = np.asarray(uv6, dtype=float)
        if uv.shape != (len(POINT_NAMES), 2):
            raise ValueError(f"uv6: expected shape ({len(POINT_NAMES)}, 2), got {uv.shape}")
        found = np.asarray(found6, dtype=bool).reshape(-1)
        if found.shape != (len(POINT_NAMES),):
            raise ValueError(f"found6: expected shape ({len(POINT_NAMES)},), got {np.shape(found6)}")
        found = found & np.isfinite(uv).all(axis=1)
        n_found = int(found.sum())
        if lost is not None:
            return self._missed(str(lost), n_found)
        if n_found < 3:
            return self._missed(f"only {n_found} fingertip point(s) found; at least 3 are needed to follow the camera",
                                n_found)
        self.missed_in_a_row = 0
        est_U, err = None, None
        method = self._update_method(found)
        try:
            est_U = estimate(method, self.C_H_G, p, uv, found, self.camera, model_C_H_G=model_C_H_G,
                             model_rms_px=model_rms_px, **self._prior(method, found))
        except (CalibrationError, ConfigError) as exc:  # E without the model's pose: no estimate
            err = str(exc)

        def recalibration():
            m = self._recalibration_method(found)
            return estimate(m, self.C_H_G, p, uv, found, self.camera, **self._prior(m, found))

        decision = self.policy.decide(est_U, n_found, C_H_G=self.C_H_G, C_H_G_calibrated=self.C_H_G_calibrated,
                                      recalibration=recalibration, error=err)
        if decision.action != "alarm" and decision.estimate is not None:
            self._poses.append(np.asarray(decision.estimate.C_H_G, float))
            if self._alternating():
                decision = Decision.of(
                    "alarm", f"camera mount loose or source switching: the measured pose alternated between two "
                    f"values over the last {ALTERNATION_WINDOW} frames (each beyond the update limit from the one "
                    "before, within it of the one before that)", self.C_H_G.copy(), decision.estimate, n_found,
                    decision.delta_deg, decision.d_mm)
        current = decision.action == "update"  # C_H_G is where the camera is (as far as this frame tells)
        if current:
            decision = self._fuse(decision)
            self.C_H_G = decision.C_H_G.copy()
        elif decision.action == "recalibrate" and decision.estimate is not None and decision.method.endswith("R"):
            self.C_H_G = decision.C_H_G.copy()
            self.C_H_G_calibrated = self.C_H_G.copy()
            self._moved_to(self.C_H_G)
            current = True
        if current:
            self._learn(uv, found)
        return self._conclude(decision)

    def _moved_to(self, C_H_G) -> None:
        """A move was followed to ``C_H_G``: the pictures within the noise after it are fused with it."""
        if self.policy.chi2_limit is not None:
            self._anchor, self._fused = np.array(C_H_G, float), [np.zeros(6)]
        self._before_jump = None

    def _fuse(self, decision: Decision) -> Decision:
        """An 'update' decision as applied: a significant move starts a fusion, later pictures within the noise give the
        mean pose since; a picture back within the noise of the pose before a jump makes that jump an outlier."""
        est = decision.estimate
        lim = self.policy.chi2_limit
        if est is None or lim is None or not np.isfinite(est.covariance).all():
            return decision
        before, self._before_jump = self._before_jump, None
        back = ""
        if before is not None and self._within_noise(est, before[0]):  # a move stays; one picture's outlier goes
            C_before, self._anchor, self._fused = before
            back = ("; the picture before was an outlier (this one is back within the noise of the pose before it): "
                    "taken out")
            if self._anchor is None:
                return replace(decision, C_H_G=C_before.copy(), reason=f"{decision.reason}{back}; C_H_G kept")
        elif not significance(est) < lim:
            jumped = (self.C_H_G.copy(), self._anchor, list(self._fused))
            self._moved_to(decision.C_H_G)
            self._before_jump = jumped
            return decision
        if self._anchor is None:
            return decision  # still since the calibration: kept
        self._fused.append(_pose_about(est, self._anchor))
        v = np.mean(self._fused, axis=0)
        C = H_from_rotvec(v[:3], v[3:]) @ self._anchor
        return replace(decision, C_H_G=C, reason=f"{decision.reason}{back}; fused: the mean of the {len(self._fused)} "
                       "pictures since the last move")

    def _within_noise(self, est: MotionEstimate, C_H_G) -> bool:
        """Is the estimate's pose within its noise (the policy's chi-square) of ``C_H_G``?"""
        return bool(wald_chi2(_pose_about(est, C_H_G), np.asarray(est.covariance, float)) < self.policy.chi2_limit)
