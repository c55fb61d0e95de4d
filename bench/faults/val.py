"""The VAL-II link (``val.<h2d|d2h>.<fault>``): the controller simulator on TCP behind a corrupting proxy
(``bench/_proxy.py``, the serial-cable model: the controller never sees the host leave), the driver on
``socket://``, every operation through the engine (whose cleanup sends ABORT). ``h2d`` corrupts what the
host sends, ``d2h`` what it receives."""

from __future__ import annotations

import socket
import time

import numpy as np

from selfview.bench._proxy import Fault, FaultProxy
from selfview.errors import CellError
from selfview.bench.faults.common import ANG_TOL_DEG, POS_TOL_MM, TIME_SCALE, WHERE_TOL_DEG, WHERE_TOL_MM, Tally, VAL_FAULTS, _RigDead, _build, _call, _err_text, _in_threads, _is_clear, _quiet_logs


# --- the VAL-II link -----------------------------------------------------------------------------------
class ValRig:
    """The VAL-II simulator on TCP, the corrupting proxy, the driver on socket://, an engine per step."""

    def __init__(self, seed: int):
        from selfview.drivers.puma_val_serial import ValLimits
        from selfview.drivers.puma_val_serial.limits import PUMA260_JOINT_SPEED_DEG_S
        from selfview.mocks.val_controller import ValController

        self.seed = seed
        self.sim = ValController(None, seed=seed, time_scale=TIME_SCALE, calibrated=True, speed_pct=20.0)
        port = self.sim.start_tcp(0)
        self.proxy = FaultProxy(port, serial=True, seed=seed).start()
        # the driver's motion-time model describes the arm it drives: here one 1/TIME_SCALE times faster
        k = 1.0 / TIME_SCALE
        limits = ValLimits(
            cart_speed_mm_s=250.0 * k,
            rot_speed_deg_s=90.0 * k,
            joint_speed_deg_s=tuple(v * k for v in PUMA260_JOINT_SPEED_DEG_S),
            calibrate_s=20.0 * TIME_SCALE,
            accel_s=0.5 * TIME_SCALE,
            timeout_margin_s=0.3,
        )
        self._limits = limits
        self.fresh = False
        self.robot = self._driver()
        self.dialect = self.robot.dialect
        self.taught = self.sim.locations()
        self.ready_q = np.array(self.robot.limits.ready_joints_deg, float)
        self.above_q = self.sim.kin.ik(self.taught["ABOVE"] @ _inv(self.sim.tool), self.ready_q)
        from selfview.maths.geometry import trans

        # 40 mm back from 'above' along its tool z: a straight line from there to 'above' is reachable
        self.back_q = self.sim.kin.ik(self.taught["ABOVE"] @ trans(0.0, 0.0, -40.0) @ _inv(self.sim.tool), self.above_q)
        self.robot.connect()
        self.robot.speed(20)

    def _driver(self):
        """A driver on a new socket:// port, opened here and handed over open (so the engine's close()
        leaves it open: pyserial's socket close() sleeps 0.3 s) with TCP_NODELAY, as a serial line sends
        each byte at once."""
        import serial

        from selfview.drivers.puma_val_serial import PumaVAL

        self._ser = serial.serial_for_url(f"socket://127.0.0.1:{self.proxy.port}", timeout=0.01, write_timeout=0.2)
        self._ser._socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        return PumaVAL(self._ser, timeout_s=0.2, limits=self._limits)

    def _unplug(self) -> None:
        """Close the driver's socket and mark its port closed: pyserial's close() of a socket port, which
        its finaliser calls when the port is collected, would otherwise sleep 0.3 s in whatever thread the
        collector runs in (a later case's, inside its bound)."""
        try:
            self._ser._socket.close()
        except Exception:
            pass
        self._ser.is_open = False

    def stop(self):
        try:
            self.robot.close()
        except Exception:
            pass
        self._unplug()
        self.proxy.stop()
        try:  # a loaded machine may keep the simulator's thread in a motion past stop()'s own limit
            self.sim.stop(timeout_s=20.0)
        except RuntimeError as exc:
            self.stop_error = str(exc)  # its links left open; the campaign goes on with a new rig

    def healthy(self) -> bool:
        """A clean WHERE works (reconnecting, then on a new socket, if needed)."""
        for attempt in range(3):
            try:
                if not self.robot.connected:
                    self.robot.connect()
                self.robot.where()
                return True
            except CellError:
                self.robot.close()
                if attempt >= 1:  # the link itself is gone (cut off): plug a new one in
                    self._unplug()
                    self.robot = self._driver()
                    self.fresh = True
        return False

    def reset(self, q) -> None:
        """The simulator's state before a case (the simulator owns it; set directly, no motion)."""
        s = self.sim
        with s._state:
            s._joints = np.asarray(q, float).copy()
            s._locations = {k: v.copy() for k, v in self.taught.items()}
            s.arm_power = True
            s.calibrated = True
            s.speed_pct = 20.0
            s._faults.clear()
        try:  # the driver reads the speed back before each motion: it learns this one, as set by its owner
            self.robot.speed_now()
        except CellError:
            pass  # the case's first command resynchronises


def _inv(H):
    from selfview.maths.geometry import inv_H

    return inv_H(H)


def _pose_err(A, B) -> tuple[float, float]:
    from selfview.maths.geometry import rotation_angle

    return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), float(np.degrees(rotation_angle(A[:3, :3].T @ B[:3, :3])))


VAL_OPS = ("where", "location", "speed", "define", "cal", "move", "moves", "appro", "depart", "ready")
MOTION_OPS = ("move", "moves", "appro", "depart", "ready")


def _val_plan(rig: ValRig, op: str, rng):
    """(start joints, engine step, expected motion (kind, fields) or None, truth dict)."""
    from selfview.procedures.engine import Step

    d = rig.dialect
    tool = rig.sim.tool
    fk = rig.sim.kin.fk
    if op in ("move", "moves"):
        return (rig.ready_q if op == "move" else rig.back_q), Step(op, {"target": "above"}), (op, {"name": "ABOVE"}), {"goal": rig.taught["ABOVE"]}
    if op == "appro":
        dist = float(rng.choice([30.0, 50.0, 80.0]))
        from selfview.maths.geometry import trans

        return rig.ready_q, Step("appro", {"target": "plate", "distance_mm": dist}), ("appro", {"name": "PLATE", "d": dist}), {
            "goal": rig.taught["PLATE"] @ trans(0.0, 0.0, -dist)}
    if op == "depart":
        dist = float(rng.choice([20.0, 40.0, 60.0]))
        from selfview.maths.geometry import trans

        return rig.above_q, Step("depart", {"distance_mm": dist}), ("depart", {"d": dist}), {
            "goal": fk(rig.above_q) @ tool @ trans(0.0, 0.0, -dist)}
    if op == "ready":
        return rig.above_q, Step("ready", {}), ("ready", {}), {"goal": fk(rig.ready_q) @ tool}
    if op == "speed":
        pct = float(rng.integers(5, 51))
        return rig.above_q, Step("speed", {"pct": pct}), None, {"pct": pct}
    if op == "define":
        pose = (float(rng.uniform(250, 400)), float(rng.uniform(-100, 100)), float(rng.uniform(80, 250)),
                float(rng.uniform(-90, 90)), float(rng.uniform(120, 179)), float(rng.uniform(-90, 90)))
        pose = tuple(round(v, 2) for v in pose)
        return rig.above_q, Step("define", {"name": "p1", "pose": pose}), None, {"H": d.pose_to_H(pose)}
    robot = rig.robot
    if op == "where":
        return rig.above_q, Step("compute", {"fn": lambda e: robot.where()}), None, {}
    if op == "location":
        name = str(rng.choice(["above", "plate"]))
        return rig.above_q, Step("compute", {"fn": lambda e: robot.location(name)}), None, {"name": name.upper()}
    if op == "cal":
        return rig.above_q, Step("compute", {"fn": lambda e: robot.calibrate()}), None, {}
    raise ValueError(op)


def _same_motion(d, line: str, expected) -> bool:
    parsed = d.parse_command(line)
    if parsed is None:
        return False
    kind, f = parsed
    f = {k: (v.upper() if isinstance(v, str) else v) for k, v in f.items()}
    return kind == expected[0] and f == expected[1]


def _motion_line(d, line: str) -> bool:
    parsed = d.parse_command(line)
    return parsed is not None and parsed[0] in MOTION_OPS + ("drive",)


def val_case(rig: ValRig, op: str, fault: str, direction: str, at: int, rng, tally: Tally) -> tuple[bool, bool]:
    """One fault on one operation, classified into ``tally``: (the fault fired, the rig needs settling)."""
    from selfview.procedures.engine import CellDevices, Engine

    sim, d = rig.sim, rig.dialect
    q0, step, expected, truth = _val_plan(rig, op, rng)
    rig.reset(q0)
    if op == "cal":
        with sim._state:
            sim.calibrated = False
    H0 = sim.base_H_T
    f = Fault(fault, direction, at)
    if fault == "stray_prompt":
        f.insert = d.prompt.encode()
    elif fault == "error_line":
        cls = str(rng.choice([c for _, c in d.errors if c != "JointLimit"]))
        f.insert = (d.controller_eol + f"*{d.error_text(cls)}*" + d.controller_eol).encode()
    elif fault == "stall":
        # shorter than the driver's 0.2 s timeout (it must ride it out) or longer (it must give up cleanly)
        f.seconds = float(rng.uniform(0.02, 0.15) if rng.random() < 0.5 else rng.uniform(0.3, 0.8))
    n_rx = len(sim.received)
    speed_before = sim.speed_pct
    engine = Engine(CellDevices(robot=rig.robot), abort_timeout_s=3.0)
    rig.proxy.arm(f)

    def snap():
        return {"H": sim.base_H_T, "moving": sim.moving.is_set(), "q": sim.joints}

    status, value, at_end = _call(lambda: engine.run(lambda e: e.execute(step), [step]), 15.0, snap)
    rig.proxy.disarm()
    kind = f"val.{direction}.{fault}"
    what = f"{op}: {f.fired or 'the fault never fired'}"
    if status == "hang":  # counted whether the fault fired or not: a hang is never hidden
        tally.add(kind, "hang", f"{what}: no return within 15 s; {value}")
        rig.robot.close()
        return True, True
    if f.fired is None:
        tally.not_fired[kind] += 1
        return False, True
    # after the software returned (or gave up and cleaned up): does the arm keep moving?
    t_end = time.monotonic()
    while sim.moving.is_set() and time.monotonic() - t_end < 3.0:
        time.sleep(0.005)
    H_final = sim.base_H_T
    moved_after, ang_after = _pose_err(at_end["H"], H_final)
    received = sim.received[n_rx:]
    motion_lines = [ln for ln in received if _motion_line(d, ln)]
    foreign = [ln for ln in motion_lines if expected is None or not _same_motion(d, ln, expected)]
    own = [ln for ln in motion_lines if expected is not None and _same_motion(d, ln, expected)]
    moved = float(np.max(np.abs(sim.joints - q0))) > 0.01
    err = value if status == "error" else None
    report = engine.cleanup_report or {}
    outcome, seen = None, ""
    if err is not None and not _is_clear(err):
        outcome, seen = "traceback", f"{what}: {_err_text(err)}"
    elif foreign and moved:
        outcome, seen = "unsafe", f"{what}: the controller ran {foreign[0]!r}, not the checked motion"
    elif len(own) > 1 and _pose_err(H_final, truth["goal"])[0] > POS_TOL_MM:
        outcome, seen = "unsafe", f"{what}: the motion was received {len(own)} times and ran again"
    elif moved_after > POS_TOL_MM or ang_after > ANG_TOL_DEG:
        state = "returned" if err is None else f"gave up ({_err_text(err)[:120]}; cleanup: {report.get('robot', '')})"
        outcome, seen = "unsafe", f"{what}: the arm went on {moved_after:.1f} mm after the software {state}"
    elif expected is None and moved:
        outcome, seen = "unsafe", f"{what}: the arm moved during a command that moves nothing"
    elif sim.speed_pct > rig.robot.limits.max_speed_pct:
        outcome, seen = "unsafe", f"{what}: SPEED {sim.speed_pct:g} applied, above the {rig.robot.limits.max_speed_pct:g} % maximum"
    elif err is not None:
        if expected is None and not own and moved:
            outcome, seen = "unsafe", f"{what}: a motion after the error {_err_text(err)}"
        else:
            outcome = "clear_error"
    else:  # success: is what was returned or done the truth?
        outcome, seen = _val_success(rig, op, value, truth, at_end, H0, speed_before)
        seen = f"{what}: {seen}" if seen else ""
    tally.add(kind, outcome, seen)
    return True, err is not None or outcome != "no_effect"


def _val_success(rig, op, value, truth, at_end, H0, speed_before):
    sim, d = rig.sim, rig.dialect
    if op in MOTION_OPS:
        dist, ang = _pose_err(at_end["H"], truth["goal"])
        if dist > POS_TOL_MM or ang > ANG_TOL_DEG:
            moving = " and still moving" if at_end["moving"] else ""
            return "unsafe", f"reported complete with the arm {dist:.1f} mm / {ang:.1f} deg from its target{moving}"
        return "no_effect", ""
    if op == "where":
        dist, ang = _pose_err(value.base_H_T, sim.base_H_T)
        dq = float(np.max(np.abs(np.asarray(value.joints) - sim.joints)))
        if dist > WHERE_TOL_MM or ang > WHERE_TOL_DEG or dq > WHERE_TOL_DEG:
            return "wrong_value", f"WHERE accepted {dist:.2f} mm / {ang:.2f} deg / joints {dq:.2f} deg off the truth: {value.pose}"
        return "no_effect", ""
    if op == "location":
        dist, ang = _pose_err(d.pose_to_H(value), sim.locations()[truth["name"]])
        if dist > WHERE_TOL_MM or ang > WHERE_TOL_DEG:
            return "wrong_value", f"POINT {truth['name']} accepted {dist:.2f} mm / {ang:.2f} deg off: {value}"
        return "no_effect", ""
    if op == "speed":
        if sim.speed_pct != truth["pct"]:
            return "wrong_value", f"SPEED {truth['pct']:g} accepted, the controller runs at {sim.speed_pct:g}"
        return "no_effect", ""
    if op == "define":
        H = sim.locations().get("P1")
        if H is None:
            return "wrong_value", "the location was reported defined, the controller has none"
        dist, ang = _pose_err(H, truth["H"])
        if dist > WHERE_TOL_MM or ang > WHERE_TOL_DEG:
            return "wrong_value", f"the location was defined {dist:.2f} mm / {ang:.2f} deg off"
        return "no_effect", ""
    if op == "cal":
        if not sim.calibrated:
            return "wrong_value", "CAL reported done, the controller is not calibrated"
        return "no_effect", ""
    raise ValueError(op)


def _val_settle(rig: ValRig) -> None:
    """After a faulted case: wait for the arm, get the dialogue back (reconnecting), or rebuild the rig."""
    t0 = time.monotonic()
    while rig.sim.moving.is_set() and time.monotonic() - t0 < 5.0:
        time.sleep(0.005)
    if not rig.healthy():
        raise _RigDead("the driver cannot talk to the simulator any more")
    if rig.fresh:  # a new driver: tell it the speed (a fresh driver assumes 10 %)
        try:
            rig.robot.speed(20)
        except CellError as exc:
            raise _RigDead(f"a clean SPEED failed after a reconnection ({_err_text(exc)})") from None
        rig.fresh = False


def _clean_lengths(rig: ValRig, rng, tally: Tally) -> dict:
    """Bytes per direction of each operation done cleanly (where a fault can strike); an operation that
    fails (a loaded machine can miss an exchange) is done again, three times at most, and noted."""
    from selfview.procedures.engine import CellDevices, Engine

    out = {}
    for op in VAL_OPS:
        for attempt in range(3):
            q0, step, _, _ = _val_plan(rig, op, rng)
            rig.reset(q0)
            rig.proxy.reset_counts()
            try:
                Engine(CellDevices(robot=rig.robot)).run(lambda e: e.execute(step), [step])
                break
            except CellError as exc:
                if attempt == 2:
                    raise
                tally.notes[f"val: a clean {op} failed ({type(exc).__name__}); done again"] += 1
                _val_settle(rig)  # the engine's cleanup closed the driver: reconnect (or plug a new link in)
        time.sleep(0.02)
        out[op] = rig.proxy.counts()
    rig.robot.speed(20)
    return out

def run_val(n: int, seed: int, deadline: float, tally: Tally, workers: int = 8) -> None:
    """``n`` faults on the VAL-II link, shared by ``workers`` rigs running side by side (each case
    mostly waits on a timeout or a simulated motion)."""
    _quiet_logs()
    _in_threads(_val_worker, n, seed, deadline, tally, workers)

def _val_worker(n: int, seed: int, index: int, deadline: float, tally: Tally) -> None:
    rng = np.random.default_rng([seed, 1, index])
    rig = _build(ValRig, seed * 1000 + index, tally)
    rebuilt = 0
    try:
        lengths = _clean_lengths(rig, rng, tally)
        done = 0
        while done < n and time.monotonic() < deadline:
            op = str(rng.choice(VAL_OPS))
            fault = str(rng.choice(VAL_FAULTS))
            direction = str(rng.choice(["h2d", "d2h"]))
            at = int(rng.integers(0, max(1, lengths[op][direction])))
            fired, settle = val_case(rig, op, fault, direction, at, rng, tally)
            done += fired
            try:
                if settle:
                    _val_settle(rig)
            except (_RigDead, CellError) as exc:
                tally.notes["val: rig rebuilt (" + (str(exc) if isinstance(exc, _RigDead) else type(exc).__name__) + ")"] += 1
                if rig.proxy.error is not None:
                    tally.notes[f"val: proxy error {_err_text(rig.proxy.error)}"] += 1
                if not any(t.is_alive() for t in rig.sim._threads):
                    tally.notes["val: the simulator's server thread died"] += 1
                rig.stop()
                if getattr(rig, "stop_error", None):
                    tally.notes[f"val: {rig.stop_error}"] += 1
                rebuilt += 1
                rig = _build(ValRig, seed * 1000 + index + 17 * rebuilt, tally)
    finally:
        rig.stop()


