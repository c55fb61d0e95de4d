"""One program owns a device: a lock file per device, naming its holder (pid and command line).

The lock is an ``flock`` on a file in the user's lock folder (``selfview.files.lockdir``: ``$SELFVIEW_LOCK_DIR``,
else ``$XDG_RUNTIME_DIR/selfview``, else ``selfview-UID`` in the temporary directory; the user's own, mode
0700, lock files opened without following links). It is keyed on what the kernel says the device is, not
on how its name is spelled: a host on every address it resolves to (with the port), a device path on its
device number (a link or another name of the same device shares the lock). The kernel drops a lock when
its holder exits, however it exits, so the lock of a dead process is simply taken over; a second holder,
in another program or in the same one, meets ``DeviceBusy`` naming the first.
"""

from __future__ import annotations

import fcntl
import ipaddress
import os
import socket
import stat
import sys
import weakref
from pathlib import Path
from typing import Callable

from selfview.errors import ConfigError, DeviceError
from selfview.files.lockdir import lock_dir as _lock_dir
from selfview.files.lockdir import lock_slug, open_lock_file

__all__ = ["DeviceBusy", "StaleState", "DeviceLock", "claim_for", "lock_dir", "host_identity", "path_identity"]


class DeviceBusy(DeviceError):
    """Another program (or another driver in this one) holds the device."""


class StaleState(DeviceError):
    """The previous holder of the device ended (killed, crashed) in the middle of something that goes on
    without it: a motion, an energised valve. Nothing is sent until the operator has checked the cell and
    cleared the record (``selfview devices --reset``)."""

    what_to_do = ("check the cell (the arm may still move, the valve may still be energised), then run "
                  "'selfview devices --real ... --reset', which stops the robot, makes the valve safe and clears the record")


def lock_dir() -> Path:
    """Where the lock files are (created, private to the user; ``DeviceError`` naming a folder that is not)."""
    return _lock_dir(error=DeviceError)


def host_identity(host: str, port: int) -> list[str]:
    """The keys of a TCP device: every address ``host`` resolves to, with ``port`` ('127.0.0.1:502',
    '[::1]:502'); ``localhost``, ``127.000.000.001`` and ``2130706433`` all include '127.0.0.1:502'.
    ``DeviceError`` if the name does not resolve, ``ConfigError`` for a port that is no TCP port."""
    if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
        raise ConfigError(f"{host}:{port}: the port {port!r} is no TCP port; expected a whole number 1..65535")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        raise DeviceError(f"{host}:{port}: cannot resolve the host name ({exc})") from None
    keys = set()
    for info in infos:
        addr = ipaddress.ip_address(str(info[4][0]).split("%")[0])
        if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
            addr = addr.ipv4_mapped
        keys.add(f"{addr}:{port}" if addr.version == 4 else f"[{addr.compressed}]:{port}")
    return sorted(keys)


def path_identity(path: str) -> list[str]:
    """The key of a device named by a path: its device number for a device ('dev 188:0'), else the file
    it resolves to ('file DEV:INODE'), else (nothing there yet) the resolved path."""
    real = os.path.realpath(path)
    try:
        st = os.stat(real)
    except OSError:
        return [f"path {real}"]
    if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode):
        return [f"dev {os.major(st.st_rdev)}:{os.minor(st.st_rdev)}"]
    return [f"file {st.st_dev:x}:{st.st_ino:x}"]


class DeviceLock:
    """The lock of one device: ``kind`` says what it is ('valve terminal'), ``key`` which one as the user
    wrote it (an address or a device path); ``identity`` (called at ``acquire()``) the keys the lock is
    held on (default: ``key`` itself; ``for_host`` and ``for_path`` key it on the device's identity).
    ``acquire()`` raises ``DeviceBusy`` naming the holder; ``release()`` is safe twice."""

    def __init__(self, kind: str, key: str, identity: Callable[[], list[str]] | None = None):
        self.kind, self.key = kind, key
        self._identity = identity or (lambda: [key])
        self._fds: list[int] = []
        self._paths: list[Path] = []
        self._me = f"{os.getpid()} ({' '.join(sys.argv)[:300]})"
        self.previous = ""  # what the lock file held when it was taken: a holder that never let go wrote it

    @classmethod
    def for_host(cls, kind: str, host: str, port: int) -> "DeviceLock":
        return cls(kind, f"{host}:{port}", lambda: host_identity(host, port))

    @classmethod
    def for_path(cls, kind: str, path: str) -> "DeviceLock":
        return cls(kind, path, lambda: path_identity(path))

    @property
    def path(self) -> Path:
        """The (first) lock file."""
        if self._paths:
            return self._paths[0]
        return lock_dir() / lock_slug(self.kind, self._identity()[0])

    def acquire(self, *, clear_stale: bool = False) -> "DeviceLock":
        """Take the lock. A record of a holder that ended in the middle of something (``busy``) raises
        ``StaleState`` and is kept for the next one, unless ``clear_stale`` (the operator has checked)."""
        if self._fds:
            return self
        keys = sorted(self._identity())
        if not keys:
            raise DeviceError(f"{self.kind} {self.key}: nothing identifies the device, so no lock can be taken on it")
        try:
            for key in keys:
                fd, path = open_lock_file(lock_slug(self.kind, key), error=DeviceError, what=f"{self.kind} {self.key}")
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:
                    holder = (os.pread(fd, 4096, 0).decode("utf-8", errors="replace").strip().split("\n")[0]
                              or "a program that wrote no name")
                    os.close(fd)
                    raise DeviceBusy(f"{self.kind} {self.key} is in use by pid {holder}; one program drives a device at "
                                     f"a time: stop that one first (its lock: {path}, {key})") from None
                self._fds.append(fd)
                self._paths.append(path)
        except BaseException:
            self.release()
            raise
        self.previous = os.pread(self._fds[0], 4096, 0).decode("utf-8", errors="replace").strip()
        busy = [ln[len("busy: "):] for ln in self.previous.splitlines() if ln.startswith("busy: ")]
        if busy and not clear_stale:
            fds, self._fds, self._paths = self._fds, [], []
            for fd in fds:
                os.close(fd)  # the record stays for the next one
            raise StaleState(f"{self.kind} {self.key}: the program that held it before (pid "
                             f"{self.previous.splitlines()[0]}) ended without letting go while {busy[0]}")
        self.note(None)
        return self

    def note(self, busy: str | None) -> None:
        """Record what this holder is in the middle of (``busy``: 'a motion was running (DO MOVE a)'), or
        that it is in the middle of nothing (None); a holder that dies leaves it for the next one."""
        text = f"{self._me}\n" + (f"busy: {busy}\n" if busy else "")
        for fd in self._fds:
            try:
                os.ftruncate(fd, 0)
                os.pwrite(fd, text.encode("utf-8", errors="replace"), 0)
            except OSError:  # a full lock folder: the lock still holds; only the record is lost
                pass

    def release(self) -> None:
        fds, self._fds, self._paths = self._fds, [], []
        for fd in fds:
            try:
                os.ftruncate(fd, 0)
            except OSError:
                pass
            finally:
                os.close(fd)  # drops the flock

    @property
    def held(self) -> bool:
        return bool(self._fds)


def claim_for(owner, kind: str, path: str | None) -> DeviceLock | None:
    """The lock of the device at ``path`` (keyed on its identity, ``path_identity``) for as long as
    ``owner`` (the object that opens it) lives; None for a ``path`` of None (a device that needs no lock).
    Raises ``DeviceBusy`` naming the holder."""
    if path is None:
        return None
    lock = DeviceLock.for_path(kind, path).acquire()
    weakref.finalize(owner, lock.release)
    return lock
