"""The Modbus valve terminal behind a corrupting proxy (``modbus.<h2d|d2h>.<fault>``): the gripper driver,
its poller, jaw motions through the engine (whose cleanup makes the valve safe)."""

from __future__ import annotations

import time

import numpy as np

from selfview.bench._proxy import Fault, FaultProxy
from selfview.errors import CellError
from selfview.bench.faults.common import MODBUS_FAULTS, Tally, _RigDead, _build, _call, _err_text, _in_threads, _is_clear, _quiet_logs


# --- the Modbus valve terminal --------------------------------------------------------------------------
MODBUS_OPS = ("state", "outputs", "open", "close")


class ModbusRig:
    """The valve terminal behind the proxy; the gripper driver (poller on, as a session runs it)."""

    def __init__(self, seed: int):
        from selfview.drivers.pneumatic_gripper import IoMap, PneumaticGripper
        from selfview.mocks.valve_terminal import ValveTerminal

        self.sim = ValveTerminal(None, seed=seed, travel_s=0.02, watchdog_s=1.0).start()
        self.proxy = FaultProxy(self.sim.port, serial=False, seed=seed).start()
        self.url = f"modbus-tcp://127.0.0.1:{self.proxy.port}?unit=1"
        # the simulated terminal serves this gripper alone: a coil a corrupted write switched on is
        # switched off again (io map stray_coils; a shared terminal's default is to report it)
        self.gripper = PneumaticGripper(self.url, io_map=IoMap(stray_coils="switch-off"), timeout_s=0.3,
                                        request_timeout_s=0.1, poll_s=0.1)
        self.io_map = self.gripper.io_map
        self.gripper.connect()

    def stop(self):
        try:
            self.gripper.close()
        except Exception:
            pass
        self.proxy.stop()
        self.sim.stop()

    def truth_state(self) -> str:
        o, c = self.sim.sensors
        return "open" if o and not c else "closed" if c and not o else "between" if not (o or c) else "both"

    def prepare(self, start: str) -> None:
        """Connected, jaws at ``start`` driven there, no other coil on (clean, no fault armed)."""
        valve_coils = {p.address for p in self.io_map.valves.values() if p.kind == "coil"}
        for _ in range(3):
            try:
                self.gripper.connect()
                for i, v in enumerate(self.sim.table("coil")):
                    if v and i not in valve_coils:  # left on by an earlier corrupted write
                        self.gripper.link.write_coil(i, False)
                if self.gripper.state() != start:
                    self.gripper.move(start)
                return
            except CellError:
                self.gripper.close()
        raise _RigDead("the gripper driver cannot talk to the valve terminal any more")


def modbus_case(rig: ModbusRig, op: str, fault: str, direction: str, at: int, rng, tally: Tally) -> bool:
    from selfview.procedures.engine import CellDevices, Engine, Step

    sim, g = rig.sim, rig.gripper
    target = {"open": "open", "close": "closed"}.get(op)
    start = ("closed" if target == "open" else "open") if target else str(rng.choice(["open", "closed"]))
    rig.prepare(start)
    if target:
        step = Step("gripper", {"state": target})
    elif op == "state":
        step = Step("compute", {"fn": lambda e: g.state()})
    else:
        step = Step("compute", {"fn": lambda e: g.outputs()})
    f = Fault("stray_prompt" if fault == "stray_prompt" else fault, direction, at)
    if fault == "stray_prompt":
        f.insert = bytes([int(rng.integers(256))])
    elif fault == "stall":
        f.seconds = float(rng.uniform(0.02, 0.08) if rng.random() < 0.5 else rng.uniform(0.15, 0.6))
    engine = Engine(CellDevices(gripper=g), abort_timeout_s=3.0)
    rig.proxy.arm(f)

    valve_coils = {p.address for p in rig.io_map.valves.values() if p.kind == "coil"}

    def snap():
        coils = sim.table("coil")
        return {"state": rig.truth_state(), "outputs": sim.valve_outputs, "halted": g.halted,
                "stray": [i for i, v in enumerate(coils) if v and i not in valve_coils]}

    status, value, at_end = _call(lambda: engine.run(lambda e: e.execute(step), [step]), 15.0, snap)
    rig.proxy.disarm()
    kind = f"modbus.{direction}.{'stray_byte' if fault == 'stray_prompt' else fault}"
    what = f"{op} from {start}: {f.fired or 'the fault never fired'}"
    if status == "hang":  # counted whether the fault fired or not: a hang is never hidden
        tally.add(kind, "hang", f"{what}: no return within 15 s; {value}")
        g.close()
        return True
    if f.fired is None:
        tally.not_fired[kind] += 1
        return False
    err = value if status == "error" else None
    energised = {k: v for k, v in at_end["outputs"].items() if v}
    if err is not None and not _is_clear(err):
        outcome, seen = "traceback", f"{what}: {_err_text(err)}"
    elif at_end["stray"]:
        outcome, seen = "unsafe", f"{what}: coil(s) {at_end['stray']} energised, which the driver never commands"
    elif err is not None:
        if energised and rig.io_map.safe_state == "all-off" and not _safe_confirmed(engine):
            # the driver could not reach the terminal to make it safe (a stalled or cut link) and said so:
            # what then keeps the cell safe is the terminal's watchdog, which the driver no longer feeds
            energised = _energised_after_watchdog(sim, rig)
        if energised and rig.io_map.safe_state == "all-off":
            report = (engine.cleanup_report or {}).get("gripper", "")
            outcome, seen = "unsafe", f"{what}: valve {energised} energised after the driver gave up ({_err_text(err)[:100]}; cleanup: {report})"
        else:
            outcome, seen = "clear_error", ""
    elif target:
        want = rig.io_map.drive(target)
        if at_end["state"] != target:
            outcome, seen = "wrong_value", f"{what}: reported {target!r}, the reed switches say {at_end['state']!r}"
        elif at_end["outputs"] != want:
            outcome, seen = "unsafe", (f"{what}: reported {target!r} with the valve outputs {at_end['outputs']} (commanded "
                                       f"{want}; driver halted: {at_end['halted']})")
        else:
            outcome, seen = "no_effect", ""
    elif op == "state":
        outcome, seen = ("no_effect", "") if value == at_end["state"] else (
            "wrong_value", f"{what}: state() returned {value!r}, the reed switches say {at_end['state']!r}")
    else:
        outcome, seen = ("no_effect", "") if value == at_end["outputs"] else (
            "wrong_value", f"{what}: outputs() returned {value}, the terminal has {at_end['outputs']}")
    tally.add(kind, outcome, seen)
    return True


def _modbus_lengths(rig: ModbusRig) -> dict:
    from selfview.procedures.engine import CellDevices, Engine, Step

    out = {}
    g = rig.gripper
    for op in MODBUS_OPS:
        target = {"open": "open", "close": "closed"}.get(op)
        rig.prepare(("closed" if target == "open" else "open") if target else "open")
        step = Step("gripper", {"state": target}) if target else Step("compute", {"fn": lambda e: g.state()})
        rig.proxy.reset_counts()
        Engine(CellDevices(gripper=g)).run(lambda e: e.execute(step), [step])
        out[op] = rig.proxy.counts()
    return out


def run_modbus(n: int, seed: int, deadline: float, tally: Tally, workers: int = 4) -> None:
    _quiet_logs()
    _in_threads(_modbus_worker, n, seed, deadline, tally, workers)


def _modbus_worker(n: int, seed: int, index: int, deadline: float, tally: Tally) -> None:
    rng = np.random.default_rng([seed, 2, index])
    rig = _build(ModbusRig, seed * 1000 + index, tally)
    rebuilt = 0
    try:
        lengths = _modbus_lengths(rig)
        done = 0
        while done < n and time.monotonic() < deadline:
            op = str(rng.choice(MODBUS_OPS))
            fault = str(rng.choice(MODBUS_FAULTS))
            direction = str(rng.choice(["h2d", "d2h"]))
            at = int(rng.integers(0, max(1, lengths[op][direction])))
            try:
                if modbus_case(rig, op, fault, direction, at, rng, tally):
                    done += 1
            except _RigDead as exc:
                tally.notes["modbus: rig rebuilt (" + str(exc) + ")"] += 1
                rig.stop()
                rebuilt += 1
                rig = _build(ModbusRig, seed * 1000 + index + 17 * rebuilt, tally)
    finally:
        rig.stop()


def _safe_confirmed(engine) -> bool:
    """Whether the engine's cleanup confirmed the valve's safe state (the driver's own report)."""
    report = str((engine.cleanup_report or {}).get("gripper", ""))
    return "NOT confirmed" not in report and "could not" not in report


def _energised_after_watchdog(sim, rig) -> dict:
    """The valve outputs once the terminal's watchdog period has passed with the proxy out of the way
    (disarmed): the driver must have stopped feeding it, so the outputs drop; still energised is unsafe."""
    wd = getattr(sim, "watchdog_s", None) or 0.0
    deadline = time.monotonic() + 3.0 * wd + 0.5
    while time.monotonic() < deadline:
        out = {k: v for k, v in sim.valve_outputs.items() if v}
        if not out:
            return {}
        time.sleep(0.05)
    return {k: v for k, v in sim.valve_outputs.items() if v}


