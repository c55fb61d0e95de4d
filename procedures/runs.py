"""What a lab does with the cell: park, calibrate, monitor, and the paper's experiment.

Each procedure is a plan (the motions it will make, checked before anything moves, printed by
``--dry-run``) and a body that executes steps through the ``Engine``. Devices are opened from URLs: the
simulated cell's by default, the lab's with ``real=True``.

Python API for lab scripts::

    from selfview.procedures.runs import CellSession
    with CellSession.simulated(cell, seed=1) as s:      # or CellSession.real(cell, robot=..., ...)
        result = s.calibrate(out="calibration.yaml")     # park, grab, calibrate, save, depart
        records = s.monitor(frames=50)                   # grab, track, update/recalibrate/alarm
"""

from __future__ import annotations

import logging
import signal
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from selfview.procedures.engine import Cancelled, CellDevices, Engine, RaiseOnSignal, Step, SignalFlag, signal_name
from selfview.procedures.experiment import TrialRecord, run_trial, summarise, tables_markdown
from selfview.procedures.simcell import CellURLs, SimulatedCell
from selfview.files.calfile import load_calibration, save_calibration
from selfview.files.cell import Cell
from selfview.errors import AlarmError, CalibrationError, ConfigError, DeviceTimeout, ImageError
from selfview.measurement.fingers import SilhouetteTracker
from selfview.files.io_safe import atomic_write, write_picture
from selfview.estimation.offline import OfflineResult, calibrate_offline
from selfview.estimation.pcc import jaw_gap_of
from selfview.estimation.online import METHODS
from selfview.estimation.policy import Monitor

__all__ = ["RunSettings", "CellSession", "park_plan", "depart_plan", "refuse_unfitting_camera"]

log = logging.getLogger("selfview.procedures")


@dataclass
class RunSettings:
    """How procedures move the cell. ``plate`` the taught location where the gripper presses the plate
    (a few mm into the foam); ``approach_mm`` how far above it the approach ends; ``speed_pct`` the
    monitor speed; ``settle_s`` the wait before a picture; ``work_locations`` where the monitor run
    moves the robot between pictures."""

    plate: str = "plate"
    approach_mm: float = 60.0
    speed_pct: float = 20.0
    settle_s: float = 0.05
    work_locations: tuple[str, ...] = ("above",)
    average: int = 1


def park_plan(s: RunSettings, state: str) -> list[Step]:
    """Approach above the plate, open the gripper (confirmed), descend straight until the fingertips
    press the plate (the foam lets it tilt into coincidence), settle."""
    return [
        Step("appro", {"target": s.plate, "distance_mm": s.approach_mm}, note="above the plate"),
        Step("gripper", {"state": state}, note="jaws in the calibration state, confirmed by the switches"),
        Step("moves", {"target": s.plate}, note="straight down: press the fingertips onto the plate"),
        Step("wait", {"seconds": s.settle_s}, note="settle"),
    ]


def depart_plan(s: RunSettings) -> list[Step]:
    return [Step("depart", {"distance_mm": s.approach_mm}, note="lift off the plate")]


def refuse_unfitting_camera(res: OfflineResult, camera, cam_path, force: bool) -> dict | None:
    """The camera file's fit to the picture (``selfview.estimation.intrinsics.camera_file_fit``; None without a camera
    file); ``CalibrationError`` when it does not fit, unless ``force``."""
    from selfview.estimation.intrinsics import camera_file_fit

    if camera is None:
        return None
    fit = camera_file_fit(res, camera, f"the camera file {cam_path}")
    if not fit["fits"] and not force:
        exc = CalibrationError(f"calibrate: {fit['refusal']}; nothing written")
        exc.what_to_do = ("measure this camera with 'selfview intrinsics --out CAMERA.yaml' and calibrate with "
                          "--camera CAMERA.yaml (or add --force to write this calibration anyway)")
        raise exc
    return fit


class CellSession:
    """An open cell: devices connected, an engine, the cell description. Use as a context manager.

    Build it with ``CellSession.simulated(cell, seed)`` (simulated devices on real channels) or
    ``CellSession.real(cell, robot=URL, gripper=URL, camera=URL)``.
    """

    def __init__(self, cell: Cell, urls: CellURLs, *, sim: SimulatedCell | None = None,
                 settings: RunSettings | None = None, dry_run: bool = False,
                 ask: Callable[[str], str] | None = None, progress: Callable[[str], None] | None = None,
                 timeout_s: float = 2.0):
        self.cell = cell
        self.urls = urls
        self.sim = sim
        self.settings = settings or RunSettings()
        self.dry_run = dry_run
        self.ask = ask
        self.progress = progress or (lambda s: None)
        self.timeout_s = timeout_s
        self.devices: CellDevices | None = None
        self.engine: Engine | None = None

    @classmethod
    def simulated(cls, cell: Cell, seed: int = 0, *, time_scale: float = 0.02, link: str = "pty",
                  taught: dict | None = None, profile=None, camera="ideal", camera_url: str | None = None,
                  **kw) -> "CellSession":
        """The simulated cell; ``camera_url`` (e.g. ``frames:///dir/img_%03d.png``) reads the pictures from
        that grabber URL instead of the simulated camera."""
        sim = SimulatedCell(cell, seed=seed, time_scale=time_scale, link=link, taught=taught, profile=profile,
                            camera=camera)
        session = cls(cell, CellURLs("", "", ""), sim=sim, **kw)
        session.camera_url = camera_url
        return session

    @classmethod
    def real(cls, cell: Cell, *, robot: str, gripper: str, camera: str, **kw) -> "CellSession":
        for nm, u in (("robot", robot), ("gripper", gripper), ("camera", camera)):
            if not u:
                raise ConfigError(f"--real needs a {nm} URL (--{nm} URL)")
        return cls(cell, CellURLs(robot, gripper, camera), **kw)

    # --- devices ----------------------------------------------------------------------------------
    def open(self) -> "CellSession":
        from selfview.drivers.frame_grabber_v4l2 import FrameGrabber
        from selfview.drivers.pneumatic_gripper import PneumaticGripper
        from selfview.drivers.robot import open_robot

        if self.sim is not None:
            self.sim.start()
            self.urls = self.sim.urls
            if getattr(self, "camera_url", None):
                self.urls = CellURLs(self.urls.robot, self.urls.gripper, self.camera_url)
        cs = self.cell.camera
        robot = open_robot(self.urls.robot, self.cell, timeout_s=self.timeout_s, ask=self.ask)
        gripper = PneumaticGripper(self.urls.gripper)
        camera = FrameGrabber(self.urls.camera, width=cs.width, height=cs.height, timeout_s=self.timeout_s)
        devs = CellDevices(robot=robot, gripper=gripper, camera=camera)
        if self.sim is not None:
            w = self.sim.world
            devs.disturber = lambda series: _disturbance_dict(w.disturb(series))
            devs.restorer = w.reset_disturbance
            devs.truth = w.truth
        self.devices = devs
        self.engine = Engine(devs, dry_run=self.dry_run, ask=self.ask, progress=self.progress)
        if not self.dry_run:
            try:
                robot.connect()
                gripper.connect()
                camera.connect()
            except KeyboardInterrupt as exc:  # a signal while connecting: what an interrupted run gets
                self._interrupted(exc)
            except BaseException:
                self.close()
                raise
        return self

    def close(self) -> None:
        if self.devices is not None:
            for dev in (self.devices.camera, self.devices.gripper, self.devices.robot):
                try:
                    dev.close()
                except Exception:  # closing is best effort; the cleanup report says what failed
                    log.exception("closing %r", dev)
        if self.sim is not None:
            self.sim.stop()

    def __enter__(self) -> "CellSession":
        # a termination signal between the engine's runs (a lab script's own code, a calibration being
        # computed) raises here too, so that the cleanup below runs instead of the process dying
        self._signals = RaiseOnSignal().__enter__()
        try:
            return self.open()
        except BaseException:
            self._signals.__exit__(None, None, None)
            raise

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if isinstance(exc, KeyboardInterrupt) and self.engine is not None and not self.dry_run:
                self._interrupted(exc)
            with SignalFlag() as flag:  # closing is short and bounded: a signal now is noted, not raised
                self.close()
            if flag.signum is not None and exc is None:
                raise Cancelled(f"{signal_name(flag.signum)} while the devices were closing, after the procedures "
                                "had ended: the cell is as they left it", flag.signum)
        finally:
            self._signals.__exit__(None, None, None)

    def _interrupted(self, exc: KeyboardInterrupt):
        """A signal outside an engine run (while connecting, between procedures): what an interrupted run
        gets (ABORT, the valve safe, the devices closed, the state reported), then ``Cancelled``."""
        signum = getattr(exc, "signum", signal.SIGINT)
        what = "interrupted by the operator (Ctrl-C)" if signum == signal.SIGINT else f"terminated by {signal_name(signum)}"
        self.engine.cancel.set()
        self.engine.cleanup(what)
        self.close()
        raise Cancelled(f"{what}; " + self.engine.state_sentence(), signum) from None

    # --- procedures -------------------------------------------------------------------------------
    def _run(self, body, plan):
        return self.engine.run(body, plan)

    def park(self, state: str | None = None) -> np.ndarray | None:
        """Park the gripper on the plate and grab a picture of it (returned)."""
        state = state or self.cell.gripper.calibrate_in
        s = self.settings
        plan = [Step("speed", {"pct": s.speed_pct})] + park_plan(s, state) + [Step("grab", {"average": s.average}, name="parked")]

        def body(e: Engine):
            for st in plan:
                e.execute(st)
            return e.results["parked"]

        return self._run(body, plan)

    def calibrate(self, out: str | Path = "calibration.yaml", state: str | None = None,
                  mode: str = "full") -> OfflineResult | None:
        """Park, grab, calibrate off-line, save the calibration file, depart.

        The file is only written when the calibration succeeded; the previous one is kept."""
        return self.calibrate_camera(out, state=state, mode=mode)

    def calibrate_camera(self, out: str | Path = "calibration.yaml", *, camera=None, camera_file: dict | None = None,
                         state: str | None = None, mode: str = "full", force: bool = False,
                         before_save: Callable | None = None) -> OfflineResult | None:
        """``calibrate`` with a measured camera (``selfview intrinsics``): park, grab, calibrate off-line
        with ``camera``'s principal point and aspect (None: the cell's nominal ones), save the calibration
        file (recording ``camera_file`` {path, sha256}), depart. Nothing is written on a failure; the
        previous file's history copy is left in ``calibration_kept``. A camera file that does not fit the
        picture (``selfview.estimation.intrinsics.camera_file_fit``, in ``camera_file_fit``) stops the run with a
        ``CalibrationError`` before anything is written, unless ``force``. ``before_save(picture, result)``
        runs between the calibration and the save (to keep the picture beside the file, to show it)."""
        self.calibration_kept = self.camera_file_fit = None
        state = state or self.cell.gripper.calibrate_in
        s = self.settings
        grab = Step("grab", {"average": s.average}, name="picture", note="the calibration picture")
        plan = [Step("speed", {"pct": s.speed_pct})] + park_plan(s, state) + [grab] + depart_plan(s)

        def body(e: Engine):
            for st in plan[:-1]:
                e.execute(st)
            res = e.execute(Step("compute", {"fn": lambda e: calibrate_offline(
                e.results["picture"], self.cell, state=state, mode=mode, camera=camera, camera_file=camera_file)},
                name="offline", note="off-line calibration"))
            self.camera_file_fit = refuse_unfitting_camera(res, camera, (camera_file or {}).get("path"), force)
            if before_save is not None:
                before_save(e.results["picture"], res)
            self.calibration_kept = e.execute(Step("compute", {"fn": lambda e: save_calibration(res.calibration, out)},
                                                   note=f"save {out}"))
            e.execute(plan[-1])
            return res

        return self._run(body, plan)

    def intrinsics_views(self, views: int = 12, state: str | None = None) -> tuple[list, list[dict]] | None:
        """Take the pictures for ``selfview.estimation.intrinsics``: from above the plate, the robot moves in straight
        lines through ``views`` planned poses (``selfview.procedures.viewplan.plan_view_poses``: lifted 15-120 mm,
        tilted up to 40 deg about axes in the plate, turned about the approach axis, the fingers clear of
        the plate), grabs a picture at each, and goes back above the plate. Every pose is checked against
        the robot's limits before the first motion. Returns (pictures, the poses' descriptions), or None
        in a dry run."""
        from selfview.maths.geometry import trans
        from selfview.procedures.viewplan import plan_view_poses

        state = state or self.cell.gripper.calibrate_in
        s = self.settings
        if self.dry_run:
            plate_H, lean = None, None
        else:
            robot = self.devices.robot
            if not getattr(robot, "knows_poses", True):
                raise ConfigError(f"intrinsics: {getattr(robot, 'url', robot)} knows no pose, so the planned views "
                                  "cannot be reached; the operator takes them instead ('selfview intrinsics --view "
                                  "--operator-views', CellSession.operator_views), or give pictures (--images)")
            plate_H = robot.pose_to_H(robot.location(s.plate))
            lean = (np.linalg.inv(plate_H) @ np.array([0.0, 0.0, 0.0, 1.0]))[:2]  # towards the robot's base
        poses = plan_view_poses(self.cell, views, state=state, lean_W=lean)
        plan = self._views_start(state)
        for i, v in enumerate(poses):
            target = f"{s.plate} view {i + 1}" if plate_H is None else plate_H @ v["W_H_G"]
            plan += [Step("moves", {"target": target},
                          note=f"view {i + 1}: lift {v['lift_mm']:.0f} mm, tilt {v['tilt_deg']:.0f} deg about "
                               f"{v['axis_deg']:.0f} deg, turn {v['turn_deg']:+.0f} deg"),
                     Step("wait", {"seconds": s.settle_s}, note="settle"),
                     Step("grab", {"average": s.average}, name=f"view{i + 1}")]
        above = f"{s.plate} approach" if plate_H is None else plate_H @ trans(0, 0, -s.approach_mm)
        plan.append(Step("moves", {"target": above}, note="back above the plate"))

        def body(e: Engine):
            for st in plan:
                e.execute(st)
            return [e.results[f"view{i + 1}"] for i in range(len(poses))], poses

        return self._run(body, plan)

    def _views_start(self, state: str) -> list[Step]:
        """The steps before views of the plate: the monitor speed, above the plate, the jaws as in the calibration."""
        s = self.settings
        return [Step("speed", {"pct": s.speed_pct}),
                Step("appro", {"target": s.plate, "distance_mm": s.approach_mm}, note="above the plate"),
                Step("gripper", {"state": state}, note="jaws as in the calibration")]

    def operator_views(self, take: Callable[[int], str], state: str | None = None) -> tuple[list, list[dict]] | None:
        """The pictures for ``selfview.estimation.intrinsics``, taken by the operator: the robot goes above the plate
        (the jaws as in the calibration) and moves no more; then ``take(n)`` (n: views taken so far) waits for
        the operator, who moves the arm (pendant, hand guiding, ``manual://``) and answers 'take' (a picture
        is grabbed now, exposed after the answer) or 'done'; ``take`` raises to end the run. Returns (the
        pictures, a description of each), or None in a dry run."""
        state = state or self.cell.gripper.calibrate_in
        plan = self._views_start(state)

        def body(e: Engine):
            for st in plan:
                e.execute(st)
            images = []
            while (answer := take(len(images))) == "take":
                images.append(e.execute(Step("grab", {"average": self.settings.average}, name=f"view{len(images) + 1}",
                                             note="taken by the operator")))
            if answer != "done":
                raise ConfigError(f"operator views: the answer {answer!r}; expected 'take' or 'done'")
            return images, [{"taken_by": "operator"} for _ in images]

        return self._run(body, plan)

    def monitor(self, calibration: str | Path, frames: int = 20, *, method: str = "4P-U",
                disturb: Callable[[int], None] | None = None, state: str | None = None,
                on_decision: Callable[[dict], None] | None = None,
                on_frame: Callable | None = None) -> list[dict]:
        """Grab pictures as the robot works, track the fingertips, apply the policy to each.

        The robot moves between ``settings.work_locations``; ``disturb(k)`` (simulation) may move the
        camera before frame k. On an alarm the engine stops the robot and ``AlarmError`` is raised.
        ``on_frame(picture, fingertips, C_H_G)`` sees each tracked frame. Returns the monitor's decision records."""
        from selfview.api import tcp_sigma_after

        if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
            raise ConfigError(f"frames {frames!r}: expected a whole number >= 1")
        if not self.settings.work_locations:
            raise ConfigError("the run settings name no work_locations for the robot to move between while monitored")
        cal = load_calibration(calibration)
        state = state or cal.state
        if state not in cal.points_G:
            raise ConfigError(f"gripper state {state!r}: the calibration {calibration} has fingertip points for "
                              f"{', '.join(cal.points_G)} only")
        pG = cal.points_G[state]
        gap = jaw_gap_of(pG)
        mon = Monitor(cal.C_H_G, cal.camera, pG, self.cell.monitor, update_method=method,
                      raise_on_alarm=True)
        s = self.settings
        plan = [Step("speed", {"pct": s.speed_pct})] + [Step("move", {"target": loc}) for loc in s.work_locations]

        # the fingertips followed from frame to frame by the model-based measurement (searched for when the
        # tracking does not hold; a frame whose fit is not believed is a missed frame, never an update)
        tracker = SilhouetteTracker(cal.camera, self.cell.gripper, points=range(6))

        def body(e: Engine):
            e.execute(plan[0])
            e.execute(Step("gripper", {"state": state}))
            for k in range(frames):
                e.execute(Step("move", {"target": s.work_locations[k % len(s.work_locations)]}))
                if disturb is not None:
                    disturb(k)
                try:
                    img = e.execute(Step("grab", {}))
                    why = mon.frame_problem(img)
                except (DeviceTimeout, ImageError) as exc:  # no usable picture (none, black, saturated)
                    img, why = None, str(exc)
                if why is not None:  # a missed frame (the alarm after max_missed_frames), never the end of the run
                    try:
                        mon.missed(why if img is not None else f"no picture: {why}")
                    finally:
                        mon.records[-1]["fingertips"] = "no picture" if img is None else "picture refused"
                        if on_decision:
                            on_decision(mon.records[-1])
                    tracker.reset()
                    continue

                def track(e, img=img):
                    ft = tracker.find(img, mon.C_H_G, gap)
                    if on_frame is not None:
                        on_frame(img, ft, mon.C_H_G)
                    logged = len(mon.records)
                    d = None
                    try:
                        d = mon.step(ft.uv, ft.found, lost=ft.lost)
                        return d
                    finally:  # how the fingertips were found, beside the decision (an alarm too)
                        if len(mon.records) > logged:
                            if d is not None and d.action in ("update", "recalibrate"):
                                # the new TCP's sigma: the estimate's and the calibration's own
                                mon.records[-1]["tcp_sigma_mm"] = tcp_sigma_after(d.estimate, d.C_H_G, cal)
                            mon.records[-1]["fingertips"] = (
                                "tracked" if ft.tracked else f"searched ({tracker.last_failure or 'no earlier frame'})"
                            )
                            if ft.quality is not None:
                                mon.records[-1]["quality"] = ft.quality

                try:
                    e.execute(Step("compute", {"fn": track}, note=f"track frame {k + 1}"))
                finally:
                    if on_decision:
                        on_decision(mon.records[-1])
            return mon.records

        try:
            return self._run(body, plan)
        except AlarmError:
            self.monitor_records = mon.records
            raise

    def experiment(self, series=("cable", "tilt"), trials: int = 20, state: str | None = None,
                   on_trial: Callable[[str, int, int, TrialRecord], None] | None = None, camera=None):
        """The paper's section 5 on this cell: per series, ``trials`` times park, calibrate, disturb,
        re-measure with every on-line method and the off-line reference. Returns (records, summary,
        artefacts of the first trial). ``camera``: a measured camera for the off-line calibrations
        (``selfview.estimation.intrinsics``; None: the cell's nominal one)."""
        if isinstance(series, str) or not series:
            raise ConfigError(f"series {series!r}: expected a list of one or more series names, e.g. ['cable', 'tilt']")
        if isinstance(trials, bool) or not isinstance(trials, (int, np.integer)) or trials < 1:
            raise ConfigError(f"trials {trials!r}: expected a whole number >= 1")
        state = state or self.cell.gripper.calibrate_in
        s = self.settings
        for name in series:
            if self.sim is not None and name not in self.cell.simulation.disturbances:
                raise ConfigError(f"series {name!r}: expected one of {', '.join(self.cell.simulation.disturbances)}")
        one = park_plan(s, state) + depart_plan(s)
        plan = [Step("speed", {"pct": s.speed_pct})] + one * (len(series) * trials)
        if self.dry_run:
            plan = [Step("speed", {"pct": s.speed_pct})]
            for name in series:
                plan += park_plan(s, state) + [Step("grab", {}), Step("compute", {}, note="off-line calibration"),
                                               Step("disturb", {"series": name}), Step("grab", {}),
                                               Step("compute", {}, note="on-line methods and off-line reference"),
                                               Step("restore", {})] + depart_plan(s)
            plan.append(Step("wait", {"seconds": 0}, note=f"... {trials} trials per series"))
        session = self

        class Rig:
            def __init__(self, e: Engine):
                self.e = e

            def park(self):
                for st in park_plan(s, state):
                    self.e.execute(st)

            def grab(self):
                return self.e.execute(Step("grab", {"average": s.average}))

            def disturb(self, name):
                return self.e.execute(Step("disturb", {"series": name}))

            def truth(self):
                t = session.devices.truth
                return t() if t else None

            def restore(self):
                self.e.execute(Step("restore", {}))
                for st in depart_plan(s):
                    self.e.execute(st)

        # what is finished so far, kept where a caller finds it if the run is interrupted
        self.experiment_partial = partial = {"records": [], "failures": [], "first": None}

        def body(e: Engine):
            e.execute(plan[0])
            records, failures, first = partial["records"], partial["failures"], None
            rig = Rig(e)
            for name in series:
                for k in range(trials):
                    seed = None if self.sim is None else self.sim.seed
                    try:
                        rec, art = run_trial(rig, self.cell, name, k, seed=seed, state=state, camera=camera)
                    except (CalibrationError, ImageError) as exc:
                        # a picture that cannot be measured spoils one trial, not the run
                        failures.append({"series": name, "index": k, "seed": seed, "error": f"{type(exc).__name__}: {exc}"})
                        self.progress(f"{name} trial {k + 1}: failed ({exc}); the cell carries on")
                        rig.restore()
                        continue
                    records.append(rec)
                    if first is None:
                        first = partial["first"] = art
                    if on_trial:
                        on_trial(name, k, trials, rec)
            summary = summarise(records)
            summary["failures"] = failures
            return records, summary, first

        return self._run(body, plan)


def _disturbance_dict(d) -> dict:
    return {"series": d.series, "angle_deg": float(d.angle_deg), "axis_C": d.axis_C.tolist(),
            "tcp_shift_C": d.tcp_shift_C.tolist()}


def write_experiment_folder(folder: Path, records, summary, first, *, cell: Cell, config: dict) -> dict:
    """results.json, tables.md, annotated pictures of the first trial and the error plot in ``folder``."""
    from selfview.procedures.results import annotate_offline, annotate_online, environment, plot_errors, write_json

    folder = Path(folder)
    files = {}
    if first is not None:
        files["offline_annotated"] = annotate_offline(first["img1"], first["first"], folder / "trial1_offline.png").name
        fr = first["first"].calibration
        files["online_annotated"] = annotate_online(first["img2"], fr.camera, fr.C_H_G, first["estimates"],
                                                    first["fingertips2"], fr.points_G[fr.state],
                                                    folder / "trial1_online.png").name
        write_picture(folder / "trial1_picture1.png", first["img1"])
        write_picture(folder / "trial1_picture2.png", first["img2"])
    plot = plot_errors(summary, folder / "errors.png", METHODS)
    if plot is not None:
        files["plot"] = plot.name
    atomic_write(folder / "tables.md", (tables_markdown(summary) + "\n").encode("utf-8"), what="tables")
    files["tables"] = "tables.md"
    results = {
        "config": config,
        "cell": {"source": Path(cell.source).name, "sha256": cell.sha256},
        "environment": environment(),
        "summary": summary,
        "trials": [r.__dict__ for r in records],
        "files": files,
    }
    write_json(folder / "results.json", results)
    return results
