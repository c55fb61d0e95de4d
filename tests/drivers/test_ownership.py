"""One program owns a device: the lock files of the valve terminal and the grabber, and a second program."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from selfview.drivers._ownership import DeviceBusy, DeviceLock, claim_for, path_identity
from selfview.drivers.pneumatic_gripper import PneumaticGripper
from selfview.errors import ConfigError, DeviceError
from selfview.mocks.valve_terminal import ValveTerminal
from selfview.procedures.cli import EXIT_DEVICE, EXIT_USAGE, main
from tests.conftest import REPO

HOLD = "import sys, time; from selfview.drivers._ownership import DeviceLock; DeviceLock(sys.argv[1], sys.argv[2]).acquire(); print('held', flush=True); time.sleep(30)"


@pytest.fixture(autouse=True)
def lock_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("SELFVIEW_LOCK_DIR", str(tmp_path))
    return tmp_path


def _holder(kind, key, env):
    proc = subprocess.Popen([sys.executable, "-c", HOLD, kind, key], cwd=REPO, env=env, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_second_holder_is_refused_with_the_first_ones_pid_and_a_dead_ones_lock_is_taken_over():
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = _holder("valve terminal", "10.0.0.5:502", env)
    try:
        with pytest.raises(DeviceBusy, match=rf"valve terminal 10.0.0.5:502 is in use by pid {proc.pid} \(-c valve"):
            DeviceLock("valve terminal", "10.0.0.5:502").acquire()
        other = DeviceLock("valve terminal", "10.0.0.6:502").acquire()  # another terminal: free
        other.release()
    finally:
        proc.send_signal(signal.SIGKILL)  # dies holding it: no cleanup of its own
        proc.wait(10)
        proc.stdout.close()
    lock = DeviceLock("valve terminal", "10.0.0.5:502").acquire()
    assert lock.path.read_text().startswith(f"{os.getpid()} ")
    with pytest.raises(DeviceBusy, match=f"pid {os.getpid()}"):  # a second driver in this program too
        DeviceLock("valve terminal", "10.0.0.5:502").acquire()
    lock.release()
    lock.release()
    assert DeviceLock("valve terminal", "10.0.0.5:502").acquire().held


def test_a_lock_claimed_for_an_object_lasts_as_long_as_it():
    class Source:
        pass

    src = Source()
    assert claim_for(src, "frame grabber", None) is None  # a source that needs no lock
    claim_for(src, "frame grabber", "/dev/video7")
    with pytest.raises(DeviceBusy, match="frame grabber /dev/video7"):
        DeviceLock.for_path("frame grabber", "/dev/video7").acquire()
    del src
    assert DeviceLock.for_path("frame grabber", "/dev/video7").acquire().held


def test_a_second_program_on_the_valve_terminal_is_refused_with_exit_4():
    with ValveTerminal(travel_s=0.02) as t:
        with PneumaticGripper(t.url) as g:  # its poller feeds the terminal's watchdog
            g.close_jaws()
            env = dict(os.environ, PYTHONPATH=str(REPO))
            run = subprocess.run([sys.executable, "-m", "selfview.procedures.cli", "gripper", "--url", t.url, "open"],
                                 cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
            assert run.returncode == EXIT_DEVICE, run.stderr
            assert f"in use by pid {os.getpid()}" in run.stderr
            assert t.valve_outputs == {"open": False, "close": True}  # untouched
        # released at close: the next one connects
        assert main(["gripper", "--url", t.url, "open"]) == 0


def test_every_jaw_wait_is_finite(capsys):
    for v in ("inf", "nan", "-1"):
        with pytest.raises(SystemExit) as info:
            main(["gripper", "--url", "modbus-tcp://127.0.0.1:1", "--timeout", v, "state"])
        assert info.value.code == EXIT_USAGE
    assert "--timeout" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="finite"):
        PneumaticGripper("modbus-tcp://127.0.0.1:1", timeout_s=float("inf"))
    with pytest.raises(ConfigError, match="finite"):
        PneumaticGripper("modbus-tcp://127.0.0.1:1", poll_s=float("inf"))


def test_an_unusable_lock_folder_is_named(tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("SELFVIEW_LOCK_DIR", str(blocker))
    with pytest.raises(DeviceError, match=f"lock folder {blocker} is not a folder.*SELFVIEW_LOCK_DIR"):
        DeviceLock("valve terminal", "10.0.0.5:502").acquire()


@pytest.mark.parametrize("spelling", ["localhost", "127.000.000.001", "2130706433", "127.0.0.1"])
def test_the_valve_terminals_lock_is_keyed_on_the_address_not_its_spelling(spelling):
    with ValveTerminal(travel_s=0.02) as t:
        with PneumaticGripper(t.url, poll_s=None):
            g = PneumaticGripper(f"modbus-tcp://{spelling}:{t.port}?unit=1", poll_s=None)
            with pytest.raises(DeviceBusy, match=f"valve terminal {spelling}:{t.port} is in use by pid {os.getpid()}"):
                g.connect()
        with PneumaticGripper(f"modbus-tcp://{spelling}:{t.port}?unit=1", poll_s=None) as g:  # free again
            assert g.connected
    with pytest.raises(DeviceError, match="no-such-host.invalid:502: cannot resolve"):
        DeviceLock.for_host("valve terminal", "no-such-host.invalid", 502).acquire()


def test_a_device_paths_lock_is_keyed_on_the_device_not_the_link(tmp_path):
    link = tmp_path / "serial-link"
    link.symlink_to("/dev/null")
    held = DeviceLock.for_path("valve terminal", "/dev/null").acquire()
    with pytest.raises(DeviceBusy, match=f"valve terminal {link} is in use"):
        DeviceLock.for_path("valve terminal", str(link)).acquire()
    held.release()
    assert DeviceLock.for_path("valve terminal", str(link)).acquire().held
    assert path_identity(str(link)) == path_identity("/dev/null") == [f"dev {os.major(os.stat('/dev/null').st_rdev)}:"
                                                                      f"{os.minor(os.stat('/dev/null').st_rdev)}"]


def test_a_planted_link_in_the_lock_folder_is_not_followed(lock_dir, tmp_path_factory):
    victim = tmp_path_factory.mktemp("user") / "notes.txt"
    victim.write_text("the user's own words\n")
    lock = DeviceLock("valve terminal", "10.0.0.5:502")
    lock.path.symlink_to(victim)
    with pytest.raises(DeviceError, match="its lock file .* symbolic link"):
        lock.acquire()
    assert victim.read_text() == "the user's own words\n" and not lock.held


def test_a_lock_folder_others_may_use_is_refused_by_name(tmp_path, monkeypatch):
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o777)
    shared.chmod(0o777)
    monkeypatch.setenv("SELFVIEW_LOCK_DIR", str(shared))
    with pytest.raises(DeviceError, match=f"lock folder {shared} has mode 0777"):
        DeviceLock("valve terminal", "10.0.0.5:502").acquire()
    link = tmp_path / "link"
    link.symlink_to(tmp_path)
    monkeypatch.setenv("SELFVIEW_LOCK_DIR", str(link))
    with pytest.raises(DeviceError, match=f"lock folder {link} is a symbolic link"):
        DeviceLock("valve terminal", "10.0.0.5:502").acquire()


def test_a_full_lock_folder_is_named_with_the_lock_file_and_its_cause(lock_dir, monkeypatch):
    """A lock folder on a full disk: the error names the lock file and says why, not a bare "No space left on
    device"; nothing is held after it."""
    import errno

    from selfview.files import lockdir

    real_open = lockdir.os.open

    def full(path, flags, mode=0o777, **kw):
        if str(path).startswith(str(lock_dir)) and flags & os.O_CREAT:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_open(path, flags, mode, **kw)

    monkeypatch.setattr(lockdir.os, "open", full)
    lock = DeviceLock("valve terminal", "10.0.0.5:502")
    with pytest.raises(DeviceError, match=rf"valve terminal 10\.0\.0\.5:502: cannot open its lock file {lock_dir}/\S+\.lock: "
                       "no space left on the device; set SELFVIEW_LOCK_DIR"):
        lock.acquire()
    assert not lock.held


def test_the_robots_record_is_keyed_on_its_port_or_socket_address():
    """The PUMA driver's record lock: a device path by its identity, socket://HOST:PORT by the address it
    resolves to, nothing for a URL that names no device of its own (loop://) or no usable port."""
    from selfview.drivers.puma_val_serial.driver import _record_lock

    assert _record_lock("/dev/null").path == DeviceLock.for_path("robot", "/dev/null").path
    for url in ("socket://localhost:5000", "socket://127.0.0.1:5000/?logging=debug", "socket://[::ffff:127.0.0.1]:5000"):
        assert _record_lock(url).path == DeviceLock.for_host("robot", "127.0.0.1", 5000).path, url
    for url in ("loop://", "spy:///dev/ttyS0", "socket://localhost", "socket://localhost:99999"):
        assert _record_lock(url) is None, url


def test_a_lock_on_no_port_or_on_nothing_is_refused_by_name():
    """A host lock with a port that is no TCP port (it would be keyed on '127.0.0.1:None'), or a lock whose
    identity names nothing, is refused naming it, not an IndexError."""
    from selfview.drivers._ownership import host_identity

    for port in (None, 70000, 0, "502", True):
        with pytest.raises(ConfigError, match="is no TCP port"):
            host_identity("localhost", port)
    with pytest.raises(DeviceError, match="valve terminal k: nothing identifies the device"):
        DeviceLock("valve terminal", "k", lambda: []).acquire()
