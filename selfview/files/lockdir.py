"""The user's lock folder: every selfview lock is an ``flock`` on a file there, never beside the user's files. It is
``$SELFVIEW_LOCK_DIR``, else ``$XDG_RUNTIME_DIR/selfview``, else ``selfview-UID`` in the temp directory, mode 0700 and
the user's (others could plant a link or hold a lock); no link is followed (it could make a lock truncate a file)."""

from __future__ import annotations

import errno
import os
import re
import stat
import tempfile
from pathlib import Path

from selfview.errors import CellError

__all__ = ["lock_dir", "open_lock_file", "lock_slug", "os_cause"]

_FIX = "set SELFVIEW_LOCK_DIR to a folder of yours with mode 0700"
_CAUSES = {errno.ENOSPC: "no space left on the device", errno.EFBIG: "file too large (a file-size limit)",
           errno.EDQUOT: "disk quota exceeded", errno.EROFS: "a read-only file system",
           errno.ELOOP: "it is a symbolic link (not followed)"}


def os_cause(exc: OSError) -> str:
    """What an operating-system error means for the file being written or read, in words."""
    return _CAUSES.get(exc.errno) or exc.strerror or str(exc)


def lock_dir(*, error: type[CellError]) -> Path:
    """The lock folder, made 0700 if missing; ``error`` unless a real folder (no link) of this user, shut to others."""
    if os.environ.get("SELFVIEW_LOCK_DIR"):
        d = Path(os.environ["SELFVIEW_LOCK_DIR"])
    elif os.environ.get("XDG_RUNTIME_DIR") and Path(os.environ["XDG_RUNTIME_DIR"]).is_dir():
        d = Path(os.environ["XDG_RUNTIME_DIR"]) / "selfview"
    else:
        d = Path(tempfile.gettempdir()) / f"selfview-{os.getuid()}"
    try:
        os.mkdir(d, 0o700)
    except FileExistsError:
        pass
    except OSError as exc:
        raise error(f"the lock folder {d}: cannot create it: {os_cause(exc)}; {_FIX}") from None
    try:
        st = os.lstat(d)
    except OSError as exc:
        raise error(f"the lock folder {d}: {os_cause(exc)}; {_FIX}") from None
    if stat.S_ISLNK(st.st_mode):
        raise error(f"the lock folder {d} is a symbolic link (not followed); {_FIX}")
    if not stat.S_ISDIR(st.st_mode):
        raise error(f"the lock folder {d} is not a folder; {_FIX}")
    if st.st_uid != os.getuid():
        raise error(f"the lock folder {d} belongs to uid {st.st_uid}, not to this user (uid {os.getuid()}); {_FIX}")
    if stat.S_IMODE(st.st_mode) & 0o077:
        raise error(f"the lock folder {d} has mode {stat.S_IMODE(st.st_mode):04o}: others may use it; {_FIX}")
    return d


def lock_slug(*parts: str) -> str:
    """A lock file's name (without the folder) for the parts of a key: safe characters only, bounded."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", "-".join(parts)).strip("_")[:150] + ".lock"


def open_lock_file(name: str, *, error: type[CellError], what: str) -> tuple[int, Path]:
    """(fd, path) of lock file ``name`` in ``lock_dir()``: made 0600, never through a link, regular; else ``error``."""
    path = lock_dir(error=error) / name
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK, 0o600)
    except OSError as exc:
        raise error(f"{what}: cannot open its lock file {path}: {os_cause(exc)}; {_FIX}") from None
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise error(f"{what}: its lock file {path} is not a regular file; {_FIX}")
    return fd, path
