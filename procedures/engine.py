"""The engine: executes a procedure's steps against the cell's devices, safely.

A procedure describes steps (``Step``); the engine executes them. Before the first step it checks every
planned motion against the robot's limits (``LimitError`` names the step; nothing has moved). With
``dry_run`` it prints the steps and moves nothing. On a signal or any error it stops the robot, makes
the gripper safe and closes the devices, and nothing cuts that cleanup short (``Engine``).
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from selfview.errors import CellError, ConfigError, LimitError
from selfview.maths.geometry import check_rigid, rotation_angle, trans
from selfview.drivers.signals import TERMINATION_SIGNALS, Interrupted, signal_name

__all__ = ["Step", "Engine", "Cancelled", "Interrupted", "CellDevices", "StepRecord", "TERMINATION_SIGNALS",
           "signal_name"]

log = logging.getLogger("selfview.engine")

MOTION_KINDS = ("move", "moves", "appro", "depart", "drive", "ready", "tool")
KINDS = MOTION_KINDS + ("speed", "define", "gripper", "grab", "wait", "ask", "disturb", "restore", "compute")


_WATCH_S = 0.02  # how often the main thread looks at the signal flag while the procedure runs

#: A tool-relative straight motion ("tool" step) is refused beyond these unless the step sets its own caps.
TOOL_STEP_MAX_MM = 50.0
TOOL_STEP_MAX_DEG = 10.0


class Cancelled(CellError):
    """The run was interrupted: by the operator (Ctrl-C) or by a termination signal (``signum``)."""

    def __init__(self, message: str, signum: int = signal.SIGINT):
        super().__init__(message)
        self.signum = int(signum)


class SignalFlag:
    """While active (main thread only), each signal of ``TERMINATION_SIGNALS`` that is not ignored only records itself:
    the first in ``signum``, every one in ``count``. Restores the previous handlers on exit. ``seen``
    (shared): the first signal any run of this process has noted, or None."""

    seen: int | None = None

    def __init__(self):
        self.signum: int | None = None
        self.count = 0
        self._old: dict[int, Any] = {}

    def _note(self, signum, frame) -> None:
        self.count += 1
        if self.signum is None:
            self.signum = signum
        if SignalFlag.seen is None:
            SignalFlag.seen = signum

    def __enter__(self) -> "SignalFlag":
        if threading.current_thread() is threading.main_thread():
            for sig in TERMINATION_SIGNALS:
                if signal.getsignal(sig) is signal.SIG_IGN:
                    continue  # ignored on purpose (nohup, a background job): it stays ignored
                try:
                    self._old[sig] = signal.signal(sig, self._note)
                except (OSError, ValueError):  # not settable here
                    pass
        return self

    def __exit__(self, *exc) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old if old is not None else signal.SIG_DFL)
        self._old.clear()


class RaiseOnSignal:
    """While active (main thread only), the first termination signal raises where the program is
    (``KeyboardInterrupt`` for SIGINT, ``Interrupted`` for the others); every later one is only noted, so
    the cleanup the first one started (ABORT, safe valve, closes, the report) is never cut short. Inside an
    engine run the run's own flag takes them (``SignalFlag``). Signals ignored on purpose (nohup, a
    background job) stay ignored. Nested uses share one first signal.

    On exit the previous handlers come back, unless ``keep`` (a program about to end): then the signals are
    ignored, so that one arriving as it exits cannot kill it halfway through and take its exit status."""

    _depth = 0

    def __init__(self, keep: bool = False):
        self.keep = keep
        self._old: dict[int, Any] = {}

    @staticmethod
    def _raise(signum, frame):
        if SignalFlag.seen is not None:
            return
        SignalFlag.seen = signum
        raise KeyboardInterrupt() if signum == signal.SIGINT else Interrupted(signum)

    def __enter__(self) -> "RaiseOnSignal":
        if threading.current_thread() is threading.main_thread():
            if RaiseOnSignal._depth == 0:
                SignalFlag.seen = None
            RaiseOnSignal._depth += 1
            for sig in TERMINATION_SIGNALS:
                if signal.getsignal(sig) is not signal.SIG_IGN:
                    self._old[sig] = signal.signal(sig, self._raise)
        return self

    def __exit__(self, *exc) -> None:
        if threading.current_thread() is not threading.main_thread():
            return
        RaiseOnSignal._depth = max(0, RaiseOnSignal._depth - 1)
        if self.keep:
            # ignored, not handled: the interpreter's shutdown puts back the default action of every signal
            # a Python handler took (not of an ignored one), and a late signal, delivered to whichever thread
            # is still running, would then kill the program with its work or cleanup done and its exit
            # status lost
            for sig in self._old:
                signal.signal(sig, signal.SIG_IGN)
            return
        for sig, old in self._old.items():
            signal.signal(sig, old if old is not None else signal.SIG_DFL)
        self._old.clear()


@dataclass
class Step:
    """One step of a procedure.

    ``kind`` one of ``KINDS``; ``params`` its arguments (``target`` a location name or a (4, 4) pose for
    motions, ``distance_mm`` for appro/depart, ``joint``, ``deg``, ``speed`` for drive, ``delta`` (4, 4) for tool (a straight motion to ``where() @ delta``,
    the tool frame's own motion; ``max_mm``, ``max_deg`` its caps), ``state`` for the gripper, ``seconds`` for wait, ``text`` for
    ask, ``series`` for disturb, ``fn`` a callable taking the engine for compute); ``name`` stores the
    step's result in ``engine.results``; ``note`` says what the step is for.
    """

    kind: str
    params: dict = field(default_factory=dict)
    name: str | None = None
    note: str = ""

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ConfigError(f"step kind {self.kind!r}: expected one of {', '.join(KINDS)}")

    def describe(self) -> str:
        p = {k: v for k, v in self.params.items() if k != "fn"}
        if isinstance(p.get("target"), np.ndarray):
            p["target"] = ("pose " + " ".join(f"{v:.1f}" for v in p["target"][:3, 3]) if p["target"].shape == (4, 4)
                           else "numbers " + " ".join(f"{v:.1f}" for v in p["target"].ravel()[:6]))
        if isinstance(p.get("delta"), np.ndarray):
            p["delta"] = ("by " + " ".join(f"{v:.2f}" for v in p["delta"][:3, 3]) + " mm" if p["delta"].shape == (4, 4)
                          else f"a {p['delta'].shape} array")  # malformed: the check says so, the description must not fail
        args = ", ".join(f"{k}={v}" for k, v in p.items())
        out = f"{self.kind}({args})" if args else self.kind
        if self.note:
            out += f"  # {self.note}"
        return out


@dataclass
class StepRecord:
    index: int
    step: str
    started: float
    seconds: float
    ok: bool
    result: str = ""


@dataclass
class CellDevices:
    """The connected devices a run uses. ``disturber``: callable(series) -> dict that disturbs the
    camera (the simulated world's; ``None`` on a real cell, where the engine asks the operator);
    ``restorer`` likewise; ``truth``: callable() -> dict of the simulator's truth, or None."""

    robot: Any = None
    gripper: Any = None
    camera: Any = None
    disturber: Callable[[str], dict] | None = None
    restorer: Callable[[], None] | None = None
    truth: Callable[[], dict] | None = None


class Engine:
    """Executes steps on ``devices`` (``CellDevices``).

    ``dry_run`` prints instead of executing; ``ask`` is how the operator is asked (default: ``input``;
    in CI there is no operator and asking raises); ``progress`` a callable(str) for progress lines;
    ``settle_s`` default wait for the cell to settle; ``abort_timeout_s`` how long the cleanup waits for
    the procedure to end, and for each of its own steps (ABORT, safe valve, each close);
    ``on_step(n, step)``, when set, hears of each step as it starts (a live view, a time estimate).

    Each executed step is logged with its time and result. The procedure runs in a worker thread and
    the main thread watches it, with every catchable termination signal (SIGINT, SIGTERM, SIGHUP,
    SIGQUIT) turned into a flag, so a signal never lands in the middle of a write to a device. On a
    signal or on any error the engine stops the robot (VAL's ABORT, which the driver writes at once,
    even while a motion is in flight, then confirms), waits for the worker to end, puts the gripper
    valve in its safe state, closes the devices, and reports the state it left the cell in: whether the
    controller confirmed the ABORT, whether the procedure had stopped, and what failed. Once the cleanup
    has begun further signals are only noted; each of its steps has its own time limit, and none can
    stop the next: a failed (or raising) ABORT still leaves the valve made safe and every device closed.
    """

    def __init__(self, devices: CellDevices, *, dry_run: bool = False, ask: Callable[[str], str] | None = None,
                 progress: Callable[[str], None] | None = None, abort_timeout_s: float = 10.0):
        if not (isinstance(abort_timeout_s, (int, float)) and 0 < abort_timeout_s < float("inf")):
            raise ConfigError(f"abort_timeout_s: expected a finite positive number of seconds, got {abort_timeout_s!r}")
        self.devices = devices
        self.dry_run = dry_run
        self._ask = ask
        self._progress = progress or (lambda s: None)
        self.abort_timeout_s = float(abort_timeout_s)
        self.results: dict[str, Any] = {}
        self.records: list[StepRecord] = []
        self.cancel = threading.Event()
        self.cleanup_report: dict | None = None
        self.on_step: Callable[[int, Step], None] | None = None
        self._n = 0

    # --- planning -------------------------------------------------------------------------------
    def check_plan(self, steps: list[Step]) -> None:
        """Check every planned motion against the robot's limits before anything moves.

        Named locations are read from the controller (POINT); appro targets are backed off along their
        tool z (a negative distance, beyond the location, is refused); depart from the previous target; READY's tool point comes from the driver's kinematics;
        a drive is checked by the driver against the joints it reads just before sending. Raises
        ``LimitError`` naming the step."""
        robot = self.devices.robot
        if robot is None or not any(s.kind in MOTION_KINDS + ("speed",) for s in steps):
            return
        if not getattr(robot, "knows_poses", True):
            self._check_plan_without_poses(steps)
            return
        limits = robot.limits
        last = None
        for i, s in enumerate(steps):
            try:
                if s.kind == "speed":
                    limits.check_speed(s.params["pct"], f"step {i + 1} SPEED")
                    continue
                if s.kind == "ready":
                    ready_pose = getattr(robot, "ready_pose", None)
                    last = ready_pose() if ready_pose is not None else None
                    if last is not None:
                        limits.check_position(last[:3, 3], f"step {i + 1} {s.describe()}")
                    continue
                if s.kind == "drive":
                    limits.check_speed(s.params["speed"], f"step {i + 1} DRIVE")
                    last = None
                    continue
                if s.kind == "tool":
                    tool_step_size(s.params, f"step {i + 1} TOOL")
                    last = None  # relative to wherever the robot is: checked against the limits when sent
                    continue
                if s.kind not in MOTION_KINDS:
                    continue
                if s.kind in ("appro", "depart"):
                    limits.check_distance(s.params["distance_mm"], f"step {i + 1} {s.describe()}")
                if s.kind == "depart":
                    if last is None:
                        continue  # relative to wherever the robot is: checked by the driver when sent
                    goal = last @ trans(0, 0, -float(s.params["distance_mm"]))
                else:
                    goal = self._pose_of(s.params["target"])
                    if s.kind == "appro":
                        goal = goal @ trans(0, 0, -float(s.params["distance_mm"]))
                limits.check_position(goal[:3, 3], f"step {i + 1} {s.describe()}")
                last = goal
            except LimitError as exc:
                raise LimitError(f"plan refused before anything moved: {exc}") from None

    def _check_plan_without_poses(self, steps: list[Step]) -> None:
        """A robot that knows no pose (``manual://``) reaches named locations only: a numeric target, a
        joint drive or a tool-relative step (it starts from where the arm is) is refused (``ConfigError``)
        before anything moves."""
        for i, s in enumerate(steps):
            if s.kind in ("drive", "tool") or (s.kind in MOTION_KINDS and "target" in s.params
                                               and not isinstance(s.params["target"], str)):
                raise ConfigError(f"plan refused before anything moved: step {i + 1} {s.describe()}: "
                                  f"{self.devices.robot!r} knows no pose; only named locations can be reached")

    def _pose_of(self, target) -> np.ndarray:
        robot = self.devices.robot
        if isinstance(target, str):
            return robot.pose_to_H(robot.location(target))
        try:
            H = np.asarray(target, float)
        except (TypeError, ValueError):
            H = np.full(1, np.nan)
        if H.shape not in ((6,), (4, 4)) or not np.isfinite(H).all():
            raise ConfigError(f"motion target {target!r}: expected a location name, a finite (4, 4) pose or "
                              "6 numbers (x, y, z, O, A, T); nothing was sent")
        if H.shape == (6,):
            return robot.pose_to_H(H)
        return H

    # --- running --------------------------------------------------------------------------------
    def progress(self, msg: str) -> None:
        """One progress line; never raises (a closed terminal must not cut the cleanup short)."""
        try:
            self._progress(msg)
        except Exception as exc:  # e.g. EIO on the terminal a SIGHUP came from
            log.warning("progress line lost (%s): %s", exc, msg)

    def run(self, body: Callable[["Engine"], Any], plan: list[Step] | None = None) -> Any:
        """Run ``body(engine)`` (which calls ``engine.execute``) in a worker thread, safely.

        ``plan`` lists the motions ``body`` will make, checked before it starts; with ``dry_run`` the
        plan is printed and ``body`` not run. On error or on a termination signal (Ctrl-C, SIGTERM,
        SIGHUP, SIGQUIT): cleanup (``cleanup``), then the error re-raised, or ``Cancelled`` carrying the
        signal's number.
        """
        plan = plan or []
        if self.dry_run:
            for i, s in enumerate(plan):
                self.progress(f"[dry-run] {i + 1:3d}. {s.describe()}")
            return None
        self.check_plan(plan)
        box: dict[str, Any] = {}
        done = threading.Event()  # set by the worker itself as its very last act

        def worker():
            try:
                box["result"] = body(self)
            except BaseException as exc:  # handed to the main thread
                box["error"] = exc
            finally:
                done.set()

        with SignalFlag() as flag:
            try:
                threading.Thread(target=worker, name="procedure", daemon=True).start()
                while not done.wait(_WATCH_S) and flag.signum is None:
                    pass
            except KeyboardInterrupt as exc:  # the handlers could not be installed (not the main thread)
                flag.signum = getattr(exc, "signum", signal.SIGINT)
            if flag.signum is not None:
                signum = flag.signum
                self.cancel.set()
                what = "interrupted by the operator (Ctrl-C)" if signum == signal.SIGINT else f"terminated by {signal_name(signum)}"
                self.progress(f"{what}: " + ("stopping the robot" if self.devices.robot is not None else "making the cell safe"))
                first = self._bounded("ABORT", self._abort_robot, ("ABORT did not return", False))
                interrupt = getattr(self.devices.gripper, "interrupt", None)
                if interrupt is not None:  # a jaw wait in progress ends now, not at its own timeout
                    interrupt()
                stopped = done.wait(self.abort_timeout_s)
                self.cleanup(what, first_abort=first, worker_stopped=stopped)
                raise Cancelled(f"{what}; " + self.state_sentence(), signum) from None
            if "error" in box:
                exc = box["error"]
                self.cleanup(f"{type(exc).__name__}: {exc}", worker_stopped=True)
                if flag.signum is not None:  # a signal came during the cleanup: it ends the command
                    raise Cancelled(f"{signal_name(flag.signum)} during the cleanup after {type(exc).__name__}: {exc}; "
                                    + self.state_sentence(), flag.signum) from exc
                raise exc
        return box.get("result")

    def execute(self, step: Step) -> Any:
        """Execute one step now (from inside ``run``'s body); logs it; stores a named result."""
        if self.cancel.is_set():
            raise Cancelled("run cancelled")
        self._n += 1
        if self.on_step is not None:
            self.on_step(self._n, step)
        t0 = time.monotonic()
        wall = time.time()
        try:
            out = self._do(step)
        except BaseException as exc:
            self.records.append(StepRecord(self._n, step.describe(), wall, time.monotonic() - t0, False,
                                           f"{type(exc).__name__}: {exc}"))
            log.error("step %d %s failed: %s", self._n, step.describe(), exc)
            raise
        dt = time.monotonic() - t0
        self.records.append(StepRecord(self._n, step.describe(), wall, dt, True, _brief(out)))
        log.info("step %d %s ok in %.3f s", self._n, step.describe(), dt)
        if step.name:
            self.results[step.name] = out
        return out

    def _do(self, step: Step) -> Any:
        d, p, k = self.devices, step.params, step.kind
        if k in MOTION_KINDS or k in ("speed", "define"):
            if d.robot is None:
                raise ConfigError(f"step {step.describe()}: no robot configured")
            if k == "move":
                return d.robot.move(p["target"])
            if k == "moves":
                return d.robot.moves(p["target"])
            if k == "appro":
                return d.robot.appro(p["target"], p["distance_mm"])
            if k == "depart":
                return d.robot.depart(p["distance_mm"])
            if k == "drive":
                return d.robot.drive(p["joint"], p["deg"], p["speed"])
            if k == "ready":
                return d.robot.ready()
            if k == "tool":
                return self._tool_motion(p)
            if k == "speed":
                return d.robot.speed(p["pct"])
            return d.robot.define(p["name"], p["pose"])
        if k == "gripper":
            if d.gripper is None:
                raise ConfigError(f"step {step.describe()}: no gripper configured")
            return d.gripper.move(p["state"])
        if k == "grab":
            if d.camera is None:
                raise ConfigError(f"step {step.describe()}: no camera configured")
            frame = d.camera.grab(after=time.monotonic(), average=int(p.get("average", 1)))
            return frame.image
        if k == "wait":
            if self.cancel.wait(float(p["seconds"])):
                raise Cancelled("run cancelled")
            return None
        if k == "ask":
            return self.ask(p["text"])
        if k == "disturb":
            if d.disturber is not None:
                return d.disturber(p["series"])
            self.ask(f"Disturb the camera ({p['series']}): {p.get('instruction', 'pull the cable')}, then press Enter")
            return {"series": p["series"], "by": "operator"}
        if k == "restore":
            if d.restorer is not None:
                d.restorer()
                return None
            self.ask("Put the camera back on its mount as it was, then press Enter")
            return None
        if k == "compute":
            return p["fn"](self)
        raise ConfigError(f"step kind {k!r} has no executor")  # pragma: no cover

    def _tool_motion(self, p: dict) -> np.ndarray:
        """A straight motion of the tool frame by ``p['delta']`` (in the tool frame): the goal
        ``where().base_H_T @ delta`` checked against the caps and the limits before anything is sent.
        Returns the goal (4, 4)."""
        robot = self.devices.robot
        tool_step_size(p, "TOOL")
        goal = robot.where().base_H_T @ np.asarray(p["delta"], float)
        robot.limits.check_position(goal[:3, 3], "TOOL step goal")
        if self.cancel.is_set():
            raise Cancelled("run cancelled")
        robot.moves(goal)
        return goal

    def ask(self, text: str) -> str:
        if self._ask is None:
            raise ConfigError(f"the procedure needs the operator ('{text}') but no operator is attached")
        return self._ask(text)

    # --- safety ---------------------------------------------------------------------------------
    def _abort_robot(self) -> tuple[str, bool]:
        """Stop the robot: (what the report says, whether the stop was confirmed). Never raises."""
        robot = self.devices.robot
        if robot is None:
            return "no robot", True
        if not getattr(robot, "connected", False):
            return "not connected (no ABORT possible)", False
        try:
            res = robot.abort()
        except Exception as exc:  # never let cleanup itself die: the valve and the closes still follow
            return f"ABORT failed: {type(exc).__name__}: {exc}", False
        if res is None:  # a robot whose abort() reports nothing
            return "ABORT sent (no confirmation available)", False
        return str(res), bool(getattr(res, "confirmed", False))

    def _bounded(self, what: str, fn: Callable[[], Any], late: Any) -> Any:
        """``fn()`` in its own thread, waited for at most ``abort_timeout_s``; ``late`` if it has not
        returned by then (it goes on alone). Exceptions come back to the caller."""
        out: dict[str, Any] = {}
        ev = threading.Event()

        def go():
            try:
                out["value"] = fn()
            except BaseException as exc:
                out["error"] = exc
            finally:
                ev.set()

        threading.Thread(target=go, name=f"cleanup {what}", daemon=True).start()
        if not ev.wait(self.abort_timeout_s):
            log.error("cleanup: %s did not return within %g s", what, self.abort_timeout_s)
            return late
        if "error" in out:
            raise out["error"]
        return out.get("value")

    def cleanup(self, reason: str, first_abort: tuple[str, bool] | None = None, worker_stopped: bool | None = None) -> dict:
        """Stop the robot, leave the gripper safe, close the devices; record and return what was done.

        ``first_abort``: the (report, confirmed) of an ABORT already sent at the interrupt; the cleanup
        sends its own as well (an ABORT more is harmless) and reports both. ``worker_stopped``: whether
        the procedure's thread is known to have ended (False: it is reported as still running). Each
        step is bounded by ``abort_timeout_s``."""
        t = self.abort_timeout_s
        rep: dict[str, Any] = {"reason": reason}
        if worker_stopped is False:
            rep["procedure"] = f"its thread had NOT ended {t:g} s after the stop (no further step is sent)"
        if first_abort is not None:
            rep["robot_at_interrupt"] = first_abort[0]
        rep["robot"], rep["robot_stopped"] = self._bounded(
            "ABORT", self._abort_robot, (f"ABORT did not return within {t:g} s", False))
        g = self.devices.gripper
        if g is not None:
            try:
                ok = self._bounded("the safe valve", lambda: g.safe() or True, None)
                rep["gripper"] = "valve set to its safe state" if ok else f"the safe state did not return within {t:g} s"
            except Exception as exc:  # reported; the closes below still run
                rep["gripper"] = f"could not set the safe state: {type(exc).__name__}: {exc}"
        for nm in ("camera", "gripper", "robot"):
            dev = getattr(self.devices, nm)
            if dev is not None:
                try:
                    if not self._bounded(f"closing the {nm}", lambda dev=dev: dev.close() or True, None):
                        rep[f"{nm}_close"] = f"close did not return within {t:g} s"
                except Exception as exc:
                    rep[f"{nm}_close"] = f"close failed: {exc}"
        self.cleanup_report = rep
        log.warning("cleanup after %s: %s", reason, rep)
        self.progress("cell left: " + self.state_sentence())
        return rep

    def state_sentence(self) -> str:
        r = dict(self.cleanup_report or {})
        first = r.pop("robot_at_interrupt", None)
        if first is not None and "robot" in r:  # two ABORTs were sent: one outcome said
            r["robot"] = _one_abort(first, r["robot"], bool(r.get("robot_stopped")))
        return "; ".join(f"{k}: {v}" for k, v in r.items() if k not in ("reason", "robot_stopped")) or "no cleanup was needed"


def _one_abort(first: str, second: str, stopped: bool) -> str:
    """One sentence for the ABORT sent at an interrupt (``first``'s report) and the cleanup's (``second``):
    the one that settled it first, the other only as a note."""
    if first.startswith("ABORT sent and confirmed"):
        return first
    if stopped:
        return f"{second} (the ABORT at the interrupt was not confirmed)"
    return f"{first}; the cleanup's ABORT was not confirmed either ({second})"


def tool_step_size(p: dict, what: str) -> tuple[float, float]:
    """(mm, deg) of a tool step's ``delta``; ``ConfigError`` for a malformed one (not a finite rigid (4, 4)
    transform, ``selfview.maths.geometry.check_rigid``) or a cap that is not a finite number > 0,
    ``LimitError`` when it exceeds its caps (``max_mm``, ``max_deg``; defaults ``TOOL_STEP_MAX_MM``,
    ``TOOL_STEP_MAX_DEG``)."""
    D = check_rigid(p.get("delta"), f"{what}: 'delta'")
    caps = []
    for key, default in (("max_mm", TOOL_STEP_MAX_MM), ("max_deg", TOOL_STEP_MAX_DEG)):
        cap = p.get(key, default)
        try:
            cap = float(cap)
        except (TypeError, ValueError):
            cap = float("nan")
        if not (np.isfinite(cap) and cap > 0):  # a NaN cap would let any step through, 0 or less none
            raise ConfigError(f"{what}: cap {key} {p.get(key)!r}: expected a finite number > 0; nothing was sent")
        caps.append(cap)
    cap_mm, cap_deg = caps
    mm = float(np.linalg.norm(D[:3, 3]))
    deg = float(np.degrees(rotation_angle(D[:3, :3])))
    if mm > cap_mm or deg > cap_deg:
        raise LimitError(f"{what}: a step of {mm:.2f} mm and {deg:.2f} deg exceeds its cap of {cap_mm:g} mm and "
                         f"{cap_deg:g} deg; nothing was sent")
    return mm, deg


def _brief(out) -> str:
    if out is None:
        return ""
    if isinstance(out, np.ndarray):
        return f"array {out.shape} {out.dtype}"
    s = str(out)
    return s if len(s) < 120 else s[:117] + "..."
