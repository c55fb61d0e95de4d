"""One program owns a device: a lock file per device, naming its holder (pid and command line).

The lock is an ``flock`` on a file in the runtime directory (``$SELFVIEW_LOCK_DIR``, else
``$XDG_RUNTIME_DIR/selfview``, else ``selfview-UID`` in the temporary directory). The kernel drops it
when its holder exits, however it exits, so the lock of a dead process is simply taken over; a second
holder, in another program or in the same one, meets ``DeviceBusy`` naming the first.
"""

from __future__ import annotations

import fcntl
import os
import re
import sys
import tempfile
import weakref
from pathlib import Path

from selfview.errors import DeviceError

__all__ = ["DeviceBusy", "DeviceLock", "claim_for", "lock_dir"]


class DeviceBusy(DeviceError):
    """Another program (or another driver in this one) holds the device."""


def lock_dir() -> Path:
    """Where the lock files are (created, private to the user)."""
    if os.environ.get("SELFVIEW_LOCK_DIR"):
        d = Path(os.environ["SELFVIEW_LOCK_DIR"])
    elif os.environ.get("XDG_RUNTIME_DIR") and Path(os.environ["XDG_RUNTIME_DIR"]).is_dir():
        d = Path(os.environ["XDG_RUNTIME_DIR"]) / "selfview"
    else:
        d = Path(tempfile.gettempdir()) / f"selfview-{os.getuid()}"
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    return d


class DeviceLock:
    """The lock of one device: ``kind`` says what it is ('valve terminal'), ``key`` which one (an address
    or a device path). ``acquire()`` raises ``DeviceBusy`` naming the holder; ``release()`` is safe twice."""

    def __init__(self, kind: str, key: str):
        self.kind, self.key = kind, key
        self._slug = re.sub(r"[^A-Za-z0-9._-]+", "_", f"{kind}-{key}").strip("_")[:150]
        self._fd: int | None = None

    @property
    def path(self) -> Path:
        return lock_dir() / f"{self._slug}.lock"

    def acquire(self) -> "DeviceLock":
        if self._fd is not None:
            return self
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o600)
        except OSError as exc:
            raise DeviceError(f"{self.kind} {self.key}: cannot create its lock file ({exc}); set SELFVIEW_LOCK_DIR "
                              "to a writable folder") from exc
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 4096, 0).decode("utf-8", errors="replace").strip() or "a program that wrote no name"
            os.close(fd)
            raise DeviceBusy(f"{self.kind} {self.key} is in use by pid {holder}; one program drives a device at a "
                             f"time: stop that one first (its lock: {self.path})") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()} ({' '.join(sys.argv)[:300]})\n".encode("utf-8", errors="replace"), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is not None:
            try:
                os.ftruncate(fd, 0)
            finally:
                os.close(fd)  # drops the flock

    @property
    def held(self) -> bool:
        return self._fd is not None


def claim_for(owner, kind: str, key: str | None) -> DeviceLock | None:
    """The lock of a device for as long as ``owner`` (the object that opens it) lives; None for a
    ``key`` of None (a device that needs no lock). Raises ``DeviceBusy`` naming the holder."""
    if key is None:
        return None
    lock = DeviceLock(kind, key).acquire()
    weakref.finalize(owner, lock.release)
    return lock
