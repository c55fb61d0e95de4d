"""The engine and the procedures on the simulated cell, every device on its real channel."""

import signal
import threading
import time

import numpy as np
import pytest

from selfview.mocks.world import PLATE_BASE_POSE
from selfview.procedures.engine import Cancelled, CellDevices, Engine, Step
from selfview.procedures.runs import CellSession
from selfview.files.calfile import load_calibration
from selfview.errors import CalibrationError, ConfigError, DeviceError, DeviceTimeout, ImageError, LimitError
from selfview.maths.geometry import trans

MOTIONS = ("DO MOVE", "DO MOVES", "DO APPRO", "DO DEPART", "DO DRIVE", "DO READY")


def motions(session):
    return [ln for ln in session.sim.robot_sim.received if ln.upper().startswith(MOTIONS)]


def valve_is_safe(session):
    # the default io map's safe state is all-off: both solenoids de-energised
    return not any(session.sim.valve_sim.valve_outputs.values())


@pytest.fixture
def session(cell):
    with CellSession.simulated(cell, seed=4, time_scale=0.01) as s:
        yield s


def test_calibrate_procedure_parks_calibrates_saves_and_departs(session, tmp_path):
    out = tmp_path / "cal.yaml"
    res = session.calibrate(out=out)
    kinds = [r.step.split("(")[0] for r in session.engine.records]
    assert kinds[:5] == ["speed", "appro", "gripper", "moves", "wait"]
    assert kinds[-1] == "depart" and "grab" in kinds
    assert all(r.ok for r in session.engine.records)
    cal = load_calibration(out)
    truth = session.sim.world.truth()
    assert np.allclose(cal.C_H_G[:3, 3], np.asarray(truth["C_H_G"])[:3, 3], atol=0.15)
    assert res.calibration.camera.f == pytest.approx(962.0, rel=2e-3)
    assert not session.sim.world.parked  # departed


def test_dry_run_moves_nothing(cell, capsys):
    lines = []
    with CellSession.simulated(cell, seed=1, time_scale=0.01, dry_run=True, progress=lines.append) as s:
        assert s.park() is None
        s.experiment(trials=2)
        assert motions(s) == []
    assert any("appro" in ln for ln in lines) and any("disturb" in ln for ln in lines)


@pytest.mark.parametrize("kw, match", [({"series": "cable"}, "list of one or more"), ({"series": ()}, "list of one or more"),
                                       ({"trials": 0}, "trials 0"), ({"trials": -1}, "trials -1"),
                                       ({"trials": 2.5}, "trials 2.5")])
def test_an_experiment_without_series_or_trials_is_refused_before_anything_moves(session, kw, match):
    with pytest.raises(ConfigError, match=match):
        session.experiment(**kw)
    assert motions(session) == [] and session.engine.records == []


def test_a_plan_out_of_limits_is_refused_before_anything_moves(cell):
    far = PLATE_BASE_POSE @ trans(0, 0, -60.0)
    far[0, 3] = 900.0  # outside the driver's workspace box
    taught = {"plate": far, "above": PLATE_BASE_POSE @ trans(0, 0, -60.0)}
    with CellSession.simulated(cell, seed=2, time_scale=0.01, taught=taught) as s:
        with pytest.raises(LimitError, match="plan refused before anything moved.*appro"):
            s.park()
        assert motions(s) == []
        assert s.engine.records == []


def _fault_cases():
    def robot_error(s):
        s.sim.robot_sim.inject("power_loss", at=0.5)

    def gripper_timeout(s):
        s.devices.gripper.close_jaws()
        s.sim.valve_sim.stick_jaw(True)

    def missing_frame(s):
        src = s.devices.camera.source

        def stalled(timeout_s):
            time.sleep(timeout_s)
            raise DeviceTimeout("sim camera: no frame within the timeout (stalled grabber)")

        src.read = stalled

    def calibration_failure(s):
        # somebody took the plate away: the gripper descends onto nothing and the picture has no discs
        s.sim.world.base_H_plate0 = trans(300.0, 0, 0) @ s.sim.world.base_H_plate0

    return [
        ("robot", robot_error, DeviceError),
        ("gripper", gripper_timeout, DeviceTimeout),
        ("frame", missing_frame, DeviceTimeout),
        ("calibration", calibration_failure, (CalibrationError, ImageError)),
    ]


@pytest.mark.parametrize("kind, inject, exc", _fault_cases(), ids=[c[0] for c in _fault_cases()])
def test_cleanup_after_a_fault_at_each_kind_of_step(cell, tmp_path, kind, inject, exc):
    out = tmp_path / "cal.yaml"
    with CellSession.simulated(cell, seed=5, time_scale=0.01) as s:
        s.calibrate(out=out)  # a previous, good calibration
        before = out.read_bytes()
        inject(s)
        n_before = len(s.sim.robot_sim.received)
        with pytest.raises(exc):
            s.calibrate(out=out)
        rep = s.engine.cleanup_report
        assert rep is not None and rep["robot"].startswith("ABORT sent and confirmed") and rep["robot_stopped"], rep
        assert "ABORT" in [ln.upper() for ln in s.sim.robot_sim.received[n_before:]]
        assert not s.sim.robot_sim.moving.is_set()
        assert valve_is_safe(s)
        assert out.read_bytes() == before  # the previous calibration is intact
        assert load_calibration(out).C_H_G.shape == (4, 4)


def test_ctrl_c_stops_the_robot_and_leaves_the_gripper_safe(cell):
    with CellSession.simulated(cell, seed=6, time_scale=1.0) as s:  # real-time motions: slow enough to interrupt
        main = threading.get_ident()
        sim = s.sim.robot_sim
        # Ctrl-C as soon as the arm moves: an event, not a clock
        ctrl_c = threading.Thread(target=lambda: sim.moving.wait(30.0) and signal.pthread_kill(main, signal.SIGINT))
        ctrl_c.start()
        try:
            with pytest.raises(Cancelled, match="interrupted"):
                s.park()
        finally:
            ctrl_c.join(30.0)
        assert "ABORT" in [ln.upper() for ln in sim.received]
        assert not sim.moving.is_set()
        assert not s.sim.world.parked  # stopped before it reached the plate
        assert valve_is_safe(s)
        rep = s.engine.cleanup_report
        assert "interrupted" in rep["reason"] and rep["robot"].startswith("ABORT sent and confirmed")
        # the ABORT written at the interrupt stopped the motion itself
        assert rep["robot_at_interrupt"] == "ABORT sent and confirmed (the controller answered *Motion aborted*)"


def test_ctrl_c_during_selfview_park_exits_130(cell, capsys, monkeypatch):
    from selfview.procedures.cli import main as cli

    started = threading.Event()
    real = Engine.execute

    def execute(self, step):
        if step.kind in ("appro", "moves"):
            started.set()
        return real(self, step)

    monkeypatch.setattr(Engine, "execute", execute)
    main = threading.get_ident()
    ctrl_c = threading.Thread(target=lambda: started.wait(60.0) and signal.pthread_kill(main, signal.SIGINT))
    ctrl_c.start()
    try:
        code = cli(["park", "--time-scale", "1.0", "--seed", "3"])
    finally:
        ctrl_c.join(60.0)
    err = capsys.readouterr().err
    assert code == 130, err
    assert "this is a bug" not in err and "ABORT sent" in err


def _stall_robot_replies(s):
    s.sim.robot_sim.inject("stall")  # the reply line dies as the next motion starts


def _abort_raises(s):
    def broken():
        raise RuntimeError("the link driver crashed")

    s.devices.robot.abort = broken
    s.sim.robot_sim.inject("power_loss", at=0.5)


@pytest.mark.parametrize("fault, says", [(_stall_robot_replies, "ABORT sent, NOT confirmed"),
                                         (_abort_raises, "ABORT failed: RuntimeError: the link driver crashed")],
                         ids=["abort-unconfirmed", "abort-raises"])
def test_an_abort_that_fails_in_the_cleanup_still_leaves_the_valve_safe_and_closes(cell, fault, says):
    with CellSession.simulated(cell, seed=5, time_scale=0.0) as s:
        s.devices.robot.timeout_s = 0.3  # short waits: the stalled line never answers
        fault(s)
        with pytest.raises((DeviceError, DeviceTimeout)):
            s.park()
        rep = s.engine.cleanup_report
        assert rep["robot"].startswith(says) and rep["robot_stopped"] is False, rep
        assert says in s.engine.state_sentence()
        assert valve_is_safe(s) and rep["gripper"] == "valve set to its safe state"
        assert not s.devices.robot.connected and not s.devices.gripper.connected
        assert not s.sim.robot_sim.moving.is_set()


def test_engine_rejects_unknown_steps_and_asks_only_with_an_operator():
    with pytest.raises(ConfigError, match="step kind"):
        Step("teleport")
    e = Engine(CellDevices())
    with pytest.raises(ConfigError, match="no operator"):
        e.run(lambda eng: eng.execute(Step("ask", {"text": "pull the cable"})))
    answers = []
    e2 = Engine(CellDevices(), ask=lambda t: answers.append(t) or "")
    e2.run(lambda eng: eng.execute(Step("disturb", {"series": "cable"})))
    assert answers and "cable" in answers[0]


def test_monitor_updates_then_recalibrates_then_raises_the_alarm(cell, tmp_path):
    from selfview.errors import AlarmError

    out = tmp_path / "cal.yaml"
    with CellSession.simulated(cell, seed=7, time_scale=0.01) as s:
        s.calibrate(out=out)
        w = s.sim.world
        spec = cell.simulation.disturbances["cable"]
        # the camera creeps on its mount, faster and faster; once the fingertips leave the picture (or their
        # fit is not believed) the frames are missed ones, and the cell's max_missed_frames (3) of them in a
        # row raise the alarm, if the alarm limit has not already
        steps = [0.15, 0.15, 0.15, 0.15, 0.6, 0.2, 0.2, 2.5, 3.0, 3.0, 3.0]
        n_rx = len(s.sim.robot_sim.received)
        with pytest.raises(AlarmError):
            s.monitor(out, frames=len(steps),
                      disturb=lambda k: w.disturb_by_angle(spec.axis_C, steps[k], spec.pivot_C, series="creep"))
        actions = [r["action"] for r in s.monitor_records if r["action"] != "calibrated"]
        assert actions[0] == "update"
        assert "recalibrate" in actions
        assert actions[-1] == "alarm"
        assert actions.index("recalibrate") < len(actions) - 1
        # the fingertips were searched for in the first frame and after the big turns, tracked between
        how = [r["fingertips"] for r in s.monitor_records if r["action"] != "calibrated"]
        assert how[0] == "searched (no earlier frame)" and "tracked" in how[1:4], how
        assert "ABORT" in [ln.upper() for ln in s.sim.robot_sim.received[n_rx:]]
        assert valve_is_safe(s)


def test_monitor_refuses_no_frames_an_unknown_state_or_no_work_locations_before_anything_moves(session, tmp_path):
    import dataclasses

    out = tmp_path / "cal.yaml"
    session.calibrate(out=out)
    n_rx, n_rec = len(motions(session)), len(session.engine.records)
    for kw, match in (({"frames": 0}, "frames 0"), ({"frames": 2.5}, "frames 2.5"), ({"state": "clamped"}, "'clamped'")):
        with pytest.raises(ConfigError, match=match):
            session.monitor(out, **kw)
    session.settings = dataclasses.replace(session.settings, work_locations=())
    with pytest.raises(ConfigError, match="no work_locations"):
        session.monitor(out, frames=2)
    assert len(motions(session)) == n_rx and len(session.engine.records) == n_rec


@pytest.mark.parametrize("signals, gap_s", [((signal.SIGTERM,), 0.0), ((signal.SIGHUP,), 0.0), ((signal.SIGQUIT,), 0.0),
                                            ((signal.SIGINT, signal.SIGINT), 0.0), ((signal.SIGINT, signal.SIGINT), 0.01),
                                            ((signal.SIGINT, signal.SIGINT), 0.03), ((signal.SIGTERM, signal.SIGINT), 0.02)],
                         ids=["TERM", "HUP", "QUIT", "INT-INT-0ms", "INT-INT-10ms", "INT-INT-30ms", "TERM-INT-20ms"])
def test_every_termination_signal_and_a_second_one_get_the_whole_cleanup(cell, signals, gap_s):
    with CellSession.simulated(cell, seed=6, time_scale=1.0) as s:
        main = threading.get_ident()
        sim = s.sim.robot_sim

        def send():
            if sim.moving.wait(30.0):
                for k, sig in enumerate(signals):
                    if k:
                        time.sleep(gap_s)
                    signal.pthread_kill(main, sig)

        sender = threading.Thread(target=send)
        sender.start()
        try:
            with pytest.raises(Cancelled) as info:
                s.park()
        finally:
            sender.join(30.0)
        assert info.value.signum == signals[0]
        assert "ABORT" in [ln.upper() for ln in sim.received] and not sim.moving.is_set()
        assert valve_is_safe(s)
        rep = s.engine.cleanup_report
        assert rep["robot"].startswith("ABORT sent and confirmed") and rep["gripper"] == "valve set to its safe state"
        assert "procedure" not in rep  # the worker is known to have ended
        assert not [t for t in threading.enumerate() if t.name == "procedure"]  # and nothing of it runs at exit
        assert not s.devices.robot.connected and not s.devices.gripper.connected


class _Valve:
    def __init__(self):
        self.calls = []

    def safe(self):
        self.calls.append("safe")

    def close(self):
        self.calls.append("close")


def test_a_signal_while_the_worker_starts_still_gets_the_cleanup(monkeypatch):
    main = threading.get_ident()
    real = threading.Thread

    class Starting(real):
        def start(self):
            if self.name == "procedure":
                signal.pthread_kill(main, signal.SIGTERM)
            super().start()

    monkeypatch.setattr(threading, "Thread", Starting)
    valve = _Valve()
    e = Engine(CellDevices(gripper=valve))
    with pytest.raises(Cancelled, match="SIGTERM") as info:
        e.run(lambda eng: eng.execute(Step("wait", {"seconds": 5.0})))
    assert info.value.signum == signal.SIGTERM
    assert valve.calls == ["safe", "close"]


def test_the_cell_is_reported_safe_only_once_the_worker_has_ended():
    main = threading.get_ident()
    ended = threading.Event()

    def body(eng):
        eng.execute(Step("compute", {"fn": lambda _e: time.sleep(0.8)}))  # a step that does not look at the flag
        eng.execute(Step("wait", {"seconds": 0.0}))
        ended.set()

    def interrupt():
        time.sleep(0.2)
        signal.pthread_kill(main, signal.SIGINT)

    # long enough: the engine waits for the step, so the cleanup follows the worker's end
    e = Engine(CellDevices(gripper=_Valve()), abort_timeout_s=5.0)
    threading.Thread(target=interrupt).start()
    with pytest.raises(Cancelled):
        e.run(body)
    assert "procedure" not in e.cleanup_report and e.records[-1].ok
    assert not ended.is_set()  # the step after it was refused (cancelled)
    # too short: the report says the worker had not ended
    e = Engine(CellDevices(gripper=_Valve()), abort_timeout_s=0.2)
    threading.Thread(target=interrupt).start()
    with pytest.raises(Cancelled, match="NOT ended"):
        e.run(body)
    assert "NOT ended" in e.cleanup_report["procedure"]


def test_the_command_line_raises_for_the_first_signal_only():
    from selfview.procedures.engine import Interrupted, RaiseOnSignal, SignalFlag

    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    try:
        with RaiseOnSignal():
            with pytest.raises(Interrupted) as info:
                signal.raise_signal(signal.SIGTERM)
            assert info.value.signum == signal.SIGTERM
            signal.raise_signal(signal.SIGINT)  # the cleanup the first one started goes on
            signal.raise_signal(signal.SIGHUP)
            assert SignalFlag.seen == signal.SIGTERM
        assert {s: signal.getsignal(s) for s in before} == before  # the handlers come back
    finally:
        SignalFlag.seen = None


class _Device:
    """A stand-in device that records what the engine asks of it; its close may fail."""

    def __init__(self, name: str, calls: list, fail_close: bool = False):
        self.name, self.calls, self.fail_close = name, calls, fail_close

    def safe(self):
        self.calls.append(f"{self.name} safe")

    def close(self):
        self.calls.append(f"{self.name} close")
        if self.fail_close:
            raise OSError(5, "Input/output error")


def test_every_device_is_closed_when_one_close_fails():
    calls: list[str] = []
    e = Engine(CellDevices(camera=_Device("camera", calls, fail_close=True), gripper=_Device("gripper", calls)))
    e.devices.robot = None
    with pytest.raises(ImageError):
        e.run(lambda eng: eng.execute(Step("compute", {"fn": lambda _e: (_ for _ in ()).throw(ImageError("blank"))})))
    # the camera's close failed first; the gripper was still made safe and closed after it
    assert calls == ["gripper safe", "camera close", "gripper close"]
    assert "close failed" in e.cleanup_report["camera_close"] and "gripper_close" not in e.cleanup_report


def test_no_step_starts_after_a_cancellation():
    ran: list[str] = []
    e = Engine(CellDevices(gripper=_Device("gripper", [])))

    def body(eng):
        eng.execute(Step("compute", {"fn": lambda _e: ran.append("first")}))
        eng.cancel.set()  # what a signal does while a step runs
        eng.execute(Step("compute", {"fn": lambda _e: ran.append("second")}))

    with pytest.raises(Cancelled, match="cancelled"):
        e.run(body)
    assert ran == ["first"] and len(e.records) == 1


def test_cleanup_runs_for_an_exception_outside_the_projects_errors():
    calls: list[str] = []
    e = Engine(CellDevices(gripper=_Device("gripper", calls)))

    def broken(_e):
        raise RuntimeError("a bug in a step")

    with pytest.raises(RuntimeError, match="a bug in a step"):
        e.run(lambda eng: eng.execute(Step("compute", {"fn": broken})))
    assert calls == ["gripper safe", "gripper close"]
    assert e.cleanup_report is not None and "RuntimeError" in e.cleanup_report["reason"]


def test_a_signal_between_the_engines_runs_still_gets_the_cleanup(cell):
    """A lab script's own code between two procedures (the arm parked, the valve energised): a SIGTERM
    there raises, and the session does what a run's interruption does before it ends."""
    with pytest.raises(Cancelled, match="terminated by SIGTERM") as info:
        with CellSession.simulated(cell, seed=3, time_scale=0.01) as s:
            s.park()
            assert not valve_is_safe(s)  # the jaws are held in the calibration state
            robot, valve = s.sim.robot_sim, s.sim.valve_sim
            n = len(robot.received)
            signal.raise_signal(signal.SIGTERM)
    assert info.value.signum == signal.SIGTERM
    assert "ABORT" in [ln.upper() for ln in robot.received[n:]]
    assert not any(valve.valve_outputs.values())  # all-off: the default io map's safe state
    assert s.engine.cleanup_report["robot"].startswith("ABORT sent and confirmed")


class _Camera(_Device):
    """A stand-in camera that records the ``after`` each grab asks for."""

    def grab(self, after=None, average=1):
        self.calls.append(after)

        class Frame:
            image = np.zeros((4, 4), np.uint8)

        return Frame()


def test_the_grab_step_asks_for_a_frame_exposed_after_the_step_began():
    """A frame exposed before the robot settled is not used: the engine's grab step asks the camera for a frame
    whose exposure began once the step started (``after=``); without it a grabber's queue hands out a frame
    taken while the arm still moved."""
    calls: list = []
    e = Engine(CellDevices(camera=_Camera("camera", calls)))
    e.devices.robot = None
    t0 = time.monotonic()
    e.run(lambda eng: eng.execute(Step("grab", {})))
    after = [c for c in calls if not isinstance(c, str)]
    assert len(after) == 1 and after[0] is not None and t0 <= after[0] <= time.monotonic()
