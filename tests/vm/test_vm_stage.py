"""The vm stage: the drivers against real kernel drivers in a qemu guest (marker ``vm``).

One guest boots (virtme-ng, software emulation, one vCPU, the host's file system shared read-only, a
pinned Debian kernel unpacked by ``tests/vm/setup.sh``) and runs ``tests/vm/guest.sh``: the grabber's
contract suite against the kernel's vivid, the robot driver over the guest's 8250 UART to the VAL-II
simulator here on the host (qemu's serial device on a 127.0.0.1 telnet socket, replies paced at 9600
baud) through ``UartRelay``: every reply chunk wrapped in XOFF ... XON (only the URL's ``xonxoff=1``
reaching the guest's tty lets the replies through) and BREAKs injected where tests/vm/guest_serial_break.py
asks; and the gripper driver over Modbus RTU on a second UART to the valve simulator. The cases here
read the guest's results. Run with ``SELFVIEW_VM_TESTS=1 pytest -m vm`` after ``tests/vm/setup.sh``.
"""

from __future__ import annotations

import glob
import os
import select
import socket
import subprocess
import sys
import tempfile
import threading
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
CACHE = Path(os.environ.get("SELFVIEW_VM_CACHE", Path.home() / ".cache" / "selfview-vm"))
GUEST_TIMEOUT_S = 1500  # the whole guest run; about 5 min on an idle 2-core machine
ROBOT_URL = "serial:///dev/ttyS1?baud=9600&xonxoff=1&rtscts=1"
GRIPPER_URL = "modbus-rtu:///dev/ttyS2?baud=19200&parity=E&unit=1"
GRABBER_URL = "v4l2:///dev/video0?input=1&std=pal&width=768&height=576&format=GREY"

pytestmark = [
    pytest.mark.vm,
    pytest.mark.timeout(GUEST_TIMEOUT_S + 120),  # the first case boots the guest
    pytest.mark.skipif(os.environ.get("SELFVIEW_VM_TESTS") != "1",
                       reason="the vm stage boots a qemu guest: run tests/vm/setup.sh, then SELFVIEW_VM_TESTS=1 pytest -m vm"),
]


def _kernel() -> Path:
    found = sorted(glob.glob(str(CACHE / "linux-image-*" / "boot" / "vmlinuz-*")))
    if not found or not (CACHE / "venv" / "bin" / "vng").exists():
        pytest.fail(f"no guest kernel or virtme-ng in {CACHE}: run tests/vm/setup.sh first")
    return Path(found[-1])


IAC, BRK, WILL, DONT = 0xFF, 0xF3, 0xFB, 0xFE
XOFF, XON = b"\x13", b"\x11"


def _free_port() -> int:
    with socket.create_server(("127.0.0.1", 0)) as s:
        return s.getsockname()[1]


class UartRelay:
    """Between qemu's UART and the VAL simulator, as a telnet client of qemu's chardev (``telnet=on``):
    passes the guest's bytes on (qemu's telnet negotiation stripped), wraps every chunk of the simulator's
    reply in XOFF ... XON as a controller pausing its terminal does (only a port opened with XON/XOFF flow
    control, the kernel's IXON, reads the replies unharmed; a 0xFF would go doubled), and injects a BREAK
    (IAC BRK: qemu's 16550A then receives a break) where the guest asks for one by recording a location:
    ``HERE BRKMID`` in the middle of the next WHERE's reply, ``HERE BRKIDLE`` once the line has been quiet
    for ``IDLE_S``, ``HERE BRKMOVE`` ``MOVE_S`` after the next motion (``DO ...``) was executed. Each break
    is recorded in ``breaks`` (its kind, whether the simulated arm was moving, how many lines the
    simulator had received)."""

    MID_BYTES = 60  # into WHERE's reply: inside its second line
    IDLE_S = 0.5
    MOVE_S = 0.3

    def __init__(self, val):
        self.val = val
        self.port = _free_port()  # qemu listens here
        self.pauses = 0
        self.negotiations = 0  # telnet option commands qemu sent (and the relay stripped)
        self.breaks: list[dict] = []
        self._tn = 0  # telnet decoder state: 0 data, 1 after IAC, 2 before an option byte
        self._line = bytearray()
        self._armed = None  # "mid", "idle", "move" (waiting for its command), or "mid-reply"
        self._reply_bytes = 0
        self._at = None  # when the armed break goes out (idle and move)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="uart-relay", daemon=True)
        self._thread.start()

    def _untelnet(self, data: bytes) -> bytes:
        out = bytearray()
        for b in data:  # qemu does not double a 0xFF it sends: the guest sends none (VAL is ASCII)
            if self._tn == 0:
                if b == IAC:
                    self._tn = 1
                else:
                    out.append(b)
            elif self._tn == 1:
                if b == IAC:
                    out.append(b)
                    self._tn = 0
                else:
                    self.negotiations += 1
                    self._tn = 2 if WILL <= b <= DONT else 0
            else:
                self._tn = 0
        return bytes(out)

    def _watch_guest(self, data: bytes) -> None:
        for b in data:
            if b == 0x15:  # CTRL-U erases the line
                self._line.clear()
            elif b == 0x0D:
                line = " ".join(self._line.decode("ascii", "replace").split()).upper()
                self._line.clear()
                if line in ("HERE BRKMID", "HERE BRKIDLE", "HERE BRKMOVE"):
                    self._armed = line[len("HERE BRK"):].lower()
                    self._at = None
                elif self._armed == "mid" and line == "WHERE":
                    self._armed, self._reply_bytes = "mid-reply", 0
                elif self._armed == "move" and line.startswith("DO "):
                    self._at = time.monotonic() + self.MOVE_S
            elif b != 0x0A:
                self._line.append(b)
        if self._armed == "idle":
            self._at = time.monotonic() + self.IDLE_S

    def _break(self, guest, kind: str) -> None:
        time.sleep(0.1)  # qemu delivers an IAC BRK before the data of the same read: let that go first
        guest.sendall(bytes((IAC, BRK)))
        self.breaks.append({"kind": kind, "moving": self.val.moving.is_set(), "received": len(self.val.received)})
        self._armed, self._at = None, None
        time.sleep(0.1)

    def _to_guest(self, guest, data: bytes) -> None:
        self.pauses += 1
        guest.sendall(XOFF + data.replace(bytes((IAC,)), bytes((IAC, IAC))) + XON)

    def _connect(self) -> socket.socket | None:
        while not self._stop.is_set():
            try:
                return socket.create_connection(("127.0.0.1", self.port), timeout=1)
            except OSError:
                time.sleep(0.2)  # qemu is not listening yet
        return None

    def _run(self) -> None:
        guest = self._connect()
        if guest is None:
            return
        with guest, socket.create_connection(("127.0.0.1", self.val.start_tcp(0)), timeout=5) as sim:
            while not self._stop.is_set():
                ready, _, _ = select.select([guest, sim], [], [], 0.05)
                for s in ready:
                    data = s.recv(4096)
                    if not data:
                        return
                    if s is guest:
                        data = self._untelnet(data)
                        self._watch_guest(data)
                        if data:
                            sim.sendall(data)
                        continue
                    if self._armed == "idle":
                        self._at = time.monotonic() + self.IDLE_S
                    if self._armed == "mid-reply":
                        k = max(0, min(len(data), self.MID_BYTES - self._reply_bytes))
                        self._reply_bytes += len(data)
                        if self._reply_bytes >= self.MID_BYTES:
                            if k:
                                self._to_guest(guest, data[:k])
                            self._break(guest, "mid")
                            data = data[k:]
                    if data:
                        self._to_guest(guest, data)
                if self._at is not None and time.monotonic() >= self._at:
                    self._break(guest, self._armed)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)


@pytest.fixture(scope="module")
def guest(cell):
    """Boot the guest once with both simulators serving; the guest's results, log and timings."""
    from selfview.mocks.val_controller import ValController
    from selfview.mocks.valve_terminal import ValveTerminal
    from selfview.mocks.world import SimWorld

    kernel = _kernel()
    # kept after the run (the guest's log has the timings); not under pytest's basetemp, which another
    # pytest run of the same user may prune while the guest still writes
    out = Path(os.environ.get("SELFVIEW_VM_OUT") or tempfile.mkdtemp(prefix="selfview-vm-"))
    out.mkdir(parents=True, exist_ok=True)
    world = SimWorld(cell, seed=5)
    with ValController(world, seed=5, time_scale=0.02, pace_baud=9600) as val, \
            ValveTerminal(travel_s=0.04, watchdog_s=None, framing="rtu") as valve:
        relay = UartRelay(val)
        qemu = (f"-chardev socket,id=val,host=127.0.0.1,port={relay.port},server=on,wait=off,telnet=on "
                "-device isa-serial,chardev=val "
                f"-chardev socket,id=valve,host=127.0.0.1,port={valve.port} -device isa-serial,chardev=valve")
        cmd = [str(CACHE / "venv" / "bin" / "vng"), "--disable-kvm", "--force-9p", "--cpus", "1", "--memory", "2G",
               "--rwdir", str(out), "--cwd", str(REPO), "--run", str(kernel), f"--qemu-opts={qemu}", "--exec",
               f"sh tests/vm/guest.sh {out} {sys.executable} '{ROBOT_URL}' '{GRIPPER_URL}' '{GRABBER_URL}'"]
        env = dict(os.environ, PATH=f"{CACHE / 'venv' / 'bin'}:{os.environ.get('PATH', '')}")
        t0 = time.monotonic()
        try:
            with open(out / "console.log", "wb") as console:
                # vng exits 255 whatever the command did (no virtio-serial without udev): the status is in OUT
                subprocess.run(cmd, stdin=subprocess.DEVNULL, stdout=console, stderr=subprocess.STDOUT, env=env,
                               timeout=GUEST_TIMEOUT_S, cwd=REPO)
        finally:
            relay.close()
        wall = time.monotonic() - t0
        received = list(val.received)
    status = (out / "status").read_text().strip() if (out / "status").exists() else None
    log = (out / "guest.log").read_text(errors="replace") if (out / "guest.log").exists() else ""
    if not (out / "guest.xml").exists():
        tail = (out / "console.log").read_text(errors="replace")[-3000:]
        pytest.fail(f"the guest wrote no results (status {status}); guest log:\n{log[-3000:]}\nconsole:\n{tail}")
    cases, why = {}, {}
    for tc in ET.parse(out / "guest.xml").getroot().iter("testcase"):
        outcome, name = "passed", f"{tc.get('classname')}::{tc.get('name')}"
        for child in tc:
            if child.tag in ("failure", "error", "skipped"):
                outcome = child.tag
                if child.tag != "skipped":  # each failure whole, whatever the log's length
                    why[name] = f"{child.get('message', '')}\n{child.text or ''}"
        cases[name] = (outcome, float(tc.get("time") or 0))
    timing = (out / "timing").read_text() if (out / "timing").exists() else ""
    print(f"\nvm stage ({out}): {wall:.0f} s wall; guest uptime {' '.join(timing.split())}; {len(cases)} cases, status {status}")
    for name, (outcome, t) in cases.items():
        print(f"  {outcome:8s} {t:6.1f} s  {name}")
    print(f"  robot line: {relay.pauses} XOFF-wrapped reply chunks, {relay.negotiations} telnet options stripped, "
          f"BREAKs {relay.breaks}")
    return {"cases": cases, "why": why, "status": status, "log": log, "received": received, "out": out,
            "pauses": relay.pauses, "breaks": relay.breaks, "negotiations": relay.negotiations}


def _suite(guest, module: str, least: int):
    cases = {k: v for k, v in guest["cases"].items() if f".{module}::" in k or k.startswith(f"{module}::")}
    bad = {k: v[0] for k, v in cases.items() if v[0] != "passed"}
    failures = "\n".join(f"--- {k}\n{guest['why'].get(k, '')}" for k in bad)
    assert len(cases) >= least and not bad, f"{len(cases)} cases of {module}, not passed: {bad}\n{failures}"


def test_the_grabber_contract_against_vivid(guest):
    _suite(guest, "test_grabber_device", 20)


def test_the_robot_driver_over_the_8250_uart_at_9600_baud(guest):
    _suite(guest, "test_puma_contract", 2)
    # the commands crossed qemu's UART to the simulator here
    assert any(line.strip().upper().startswith("WHERE") for line in guest["received"]), guest["received"][-10:]
    assert guest["pauses"] > 20  # every reply chunk came wrapped in XOFF ... XON


def test_a_break_on_the_robot_line_is_refused_and_never_ends_a_motion(guest):
    _suite(guest, "guest_serial_break", 4)
    assert guest["negotiations"] >= 4  # qemu's telnet options, stripped before the simulator
    breaks = {b["kind"]: b for b in guest["breaks"]}
    assert sorted(breaks) == ["idle", "mid", "move"] and len(guest["breaks"]) == 3, guest["breaks"]
    received = guest["received"]
    # between commands: the driver resynchronised (an empty line) before its next command
    assert received[breaks["idle"]["received"]:][:2] == ["", "WHERE"], received[breaks["idle"]["received"]:][:5]
    # during the motion: the arm was moving when the break came, and the driver's next line stopped it
    assert breaks["move"]["moving"], guest["breaks"]
    assert received[breaks["move"]["received"]] == "ABORT", received[breaks["move"]["received"] - 2:][:5]
    assert received[breaks["move"]["received"] - 1].startswith("DO DRIVE 1")


def test_the_gripper_over_modbus_rtu_on_a_second_uart(guest):
    _suite(guest, "test_gripper_terminal", 2)


def test_the_guest_run_passed_as_a_whole(guest):
    assert guest["status"] == "0", guest["log"][-4000:]
