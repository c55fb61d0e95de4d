"""Reading and writing files that may be hostile or fail half-way (YAML, pictures): each refusal names the file and
cause as the caller's error class; nothing is read past a bound; a write leaves the old or the new file, never half."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import math
import os
import re
import secrets
import stat
import struct
import time
from pathlib import Path

import numpy as np
import yaml

from selfview.errors import CellError, ConfigError, PictureFileError
from selfview.files.lockdir import lock_slug, open_lock_file, os_cause

__all__ = ["load_yaml", "load_yaml_file", "read_bounded", "parse_number", "read_picture", "uint16_gain", "uint16_to_u8",
           "picture_size", "atomic_write", "write_picture", "MAX_YAML_BYTES", "MAX_YAML_DEPTH", "MAX_PICTURE_SIDE",
           "MAX_PICTURE_PIXELS"]

#: Largest YAML document read (cell and calibration files are a few kB).
MAX_YAML_BYTES = 1 << 20
#: Deepest nesting of mappings and sequences accepted (the files here nest 4 deep).
MAX_YAML_DEPTH = 32
#: Largest picture side and pixel count decoded (the CCIR camera gives 768 x 576).
MAX_PICTURE_SIDE = 16384
MAX_PICTURE_PIXELS = 64_000_000
#: Largest picture file read (an uncompressed picture of MAX_PICTURE_PIXELS grey pixels, and its header).
MAX_PICTURE_BYTES = MAX_PICTURE_PIXELS + (1 << 16)


_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (lambda m: not stat.S_ISREG(m), "not a file"))


def _not_regular(mode: int) -> str:
    return next((kind for test, kind in _KINDS if test(mode)), "")


def read_bounded(path, limit: int, *, error: type[CellError] = ConfigError, what: str = "file",
                 source: str | None = None, missing: str | None = None) -> bytes:
    """The regular file ``path``'s bytes, at most ``limit`` (``limit + 1`` read): a FIFO, device or folder is refused by
    kind (opened without blocking), a larger one by size. ``error`` names ``source``; ``missing``: message if absent."""
    src = str(path) if source is None else source
    refuse = lambda why: error(f"{src}: cannot read the {what}: {why}")  # noqa: E731
    try:
        fd = None
        if kind := _not_regular(os.stat(path).st_mode):
            raise refuse(f"it is {kind}, not a regular file; give the path of a {what}")
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
        st = os.fstat(fd)  # the file opened, whatever was swapped in since
        if kind := _not_regular(st.st_mode):
            raise refuse(f"it is {kind}, not a regular file; give the path of a {what}")
        if st.st_size > limit:
            raise refuse(f"{st.st_size} bytes, more than the {limit} accepted (is it the right file?)")
        data = b""
        while len(data) <= limit and (chunk := os.read(fd, limit + 1 - len(data))):
            data += chunk
    except FileNotFoundError:
        raise error(f"{src}: {missing}" if missing else f"{src}: cannot read the {what} (no such file)") from None
    except OSError as exc:
        raise refuse(os_cause(exc)) from None
    finally:
        if fd is not None:
            os.close(fd)
    if len(data) > limit:
        raise refuse(f"it grew beyond the {limit} bytes accepted while being read")
    return data


class _Refused(Exception):
    pass


def _strict(base: type) -> type:
    class Strict(base):  # type: ignore[misc, valid-type]
        _depth = 0

        def compose_node(self, parent, index):
            if self.check_event(yaml.AliasEvent):
                ev = self.peek_event()
                raise _Refused(f"line {ev.start_mark.line + 1}: YAML alias '*{ev.anchor}' refused (aliases are not "
                               "used by selfview's files, and can expand a small file into gigabytes)")
            self._depth += 1
            try:
                if self._depth > MAX_YAML_DEPTH:
                    mark = self.peek_event().start_mark
                    raise _Refused(f"line {mark.line + 1}: nested deeper than {MAX_YAML_DEPTH} levels")
                return super().compose_node(parent, index)
            finally:
                self._depth -= 1

    Strict.__name__ = f"Strict{base.__name__}"
    if issubclass(base, yaml.SafeLoader):
        for tag in ("int", "float"):
            name = f"tag:yaml.org,2002:{tag}"
            Strict.add_constructor(name, _digits_only(base.yaml_constructors[name]))
    return Strict


def _digits_only(construct):
    """A YAML 1.1 number constructor refusing ``1_0`` (read as 10) and ``1:30`` (sexagesimal, read as 90)."""
    def checked(loader, node):
        text = str(node.value)
        if "_" in text or ":" in text:
            raise _Refused(f"line {node.start_mark.line + 1}: number {_short(text, 40)!r} refused: write it in plain "
                           "digits (YAML would read '_' and ':' groups as another number)")
        return construct(loader, node)
    return checked


_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_INTEGER = re.compile(r"[+-]?[0-9]+")


def parse_number(text: str, *, integer: bool = False, lo: float | None = None, hi: float | None = None,
                 lo_open: bool = False) -> float | int:
    """A number in ASCII digits (``12``, ``-1.5``, ``2e-3``; whole with ``integer``), finite, in ``lo``..``hi`` (``lo``
    excluded with ``lo_open``); ``ValueError`` saying why. (``float`` also takes ``1_0``, full-width digits, nan.)"""
    s = str(text).strip()
    if s.lower().lstrip("+-") in ("inf", "infinity", "nan"):
        raise ValueError(f"non-finite: {s} (expected a finite number)")
    if len(s) > 40 or not (_INTEGER if integer else _NUMBER).fullmatch(s):
        raise ValueError(f"not a{' whole' if integer else ''} number in ASCII digits: {_short(repr(str(text)), 50)}")
    v = int(s) if integer else float(s)
    if not math.isfinite(v) or (lo is not None and (v <= lo if lo_open else v < lo)) or (hi is not None and v > hi):
        want = [f"{'>' if lo_open else '>='} {lo}"] * (lo is not None) + [f"<= {hi}"] * (hi is not None)
        raise ValueError(f"out of range: {s} (expected {' and '.join(want) or 'a finite number'})")
    return v


_LOADERS = {"safe": _strict(yaml.SafeLoader), "base": _strict(yaml.BaseLoader)}


def load_yaml(data: bytes | str, source: str, *, error: type[CellError] = ConfigError, text_only: bool = False,
              what: str = "file"):
    """One YAML document, no aliases (a 491-byte alias bomb expands to gigabytes), at most ``MAX_YAML_BYTES`` and
    ``MAX_YAML_DEPTH`` deep (RecursionError); ``text_only``: text scalars. ``error`` names ``source``, line, cause."""
    if len(data) > MAX_YAML_BYTES:
        raise error(f"{source}: {what} of {len(data)} bytes, more than the {MAX_YAML_BYTES} accepted")
    if isinstance(data, bytes):
        try:
            data = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise error(f"{source}: {what} is not UTF-8 text (byte {exc.start})") from None
    loader = None
    try:
        loader = _LOADERS["base" if text_only else "safe"](data)  # refuses non-printable characters: inside the try
        return loader.get_single_data()
    except _Refused as exc:
        raise error(f"{source}: {what} refused: {exc}") from None
    except yaml.YAMLError as exc:
        raise error(f"{source}: {what} is not valid YAML ({_short(str(exc), 300)})") from None
    except (ValueError, OverflowError, RecursionError, MemoryError) as exc:  # e.g. a too long integer, a bad date
        raise error(f"{source}: {what} holds a value that cannot be read ({type(exc).__name__}: "
                    f"{_short(str(exc), 200)})") from None
    finally:
        if loader is not None:
            loader.dispose()


def load_yaml_file(path, *, error: type[CellError] = ConfigError, what: str = "file", source: str | None = None,
                   missing: str | None = None, text_only: bool = False):
    """``load_yaml`` of ``read_bounded(path, MAX_YAML_BYTES)``: a YAML file checked before it is read."""
    src = str(path) if source is None else source
    blob = read_bounded(path, MAX_YAML_BYTES, error=error, what=what, source=src, missing=missing)
    return load_yaml(blob, src, error=error, text_only=text_only, what=what)


def _short(text: str, n: int = 80) -> str:
    return text if len(text) <= n else text[: n - 3] + "..."


def short_repr(value, n: int = 80) -> str:
    """``repr`` cut to ``n`` characters (for messages about values read from a file)."""
    return _short(repr(value), n)


def picture_size(head: bytes) -> tuple[str, int, int]:
    """(format, width, height) from a PNG, JPEG, BMP, PGM/PPM or TIFF file (``head``: all of it), else ValueError."""
    if not head:
        raise ValueError("the file is empty")
    if head[:8] == b"\x89PNG\r\n\x1a\n":
        if len(head) < 24 or head[12:16] != b"IHDR":
            raise ValueError("PNG without its IHDR header (truncated?)")
        w, h = struct.unpack(">II", head[16:24])
        return "PNG", w, h
    if head[:2] == b"\xff\xd8":
        i = 2
        while i + 4 <= min(len(head), 1 << 20):  # segments jump, fill bytes step: a bounded walk
            if head[i] != 0xFF:
                raise ValueError(f"JPEG marker expected at byte {i}")
            marker = head[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                i += 2
                continue
            (length,) = struct.unpack(">H", head[i + 2 : i + 4])
            if marker in (0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF):
                if i + 9 > len(head):
                    break
                h, w = struct.unpack(">HH", head[i + 5 : i + 9])
                return "JPEG", w, h
            if marker == 0xDA or length < 2:
                raise ValueError("JPEG without a frame header before its data")
            i += 2 + length
        raise ValueError("JPEG frame header not found in the file (truncated?)")
    if head[:2] == b"BM":
        if len(head) < 26:
            raise ValueError("BMP header truncated")
        (hsize,) = struct.unpack("<I", head[14:18])  # 12: the old OS/2 header of 16-bit sizes
        w, h = struct.unpack("<HH", head[18:22]) if hsize == 12 else struct.unpack("<ii", head[18:26])
        return "BMP", abs(w), abs(h)
    if head[:1] == b"P" and head[1:2] in (b"2", b"3", b"5", b"6"):
        fields: list[bytes] = []
        for line in head[2:65536].split(b"\n"):
            line = line.split(b"#", 1)[0]
            fields += line.split()
            if len(fields) >= 2:
                break
        try:
            return "PNM", int(fields[0]), int(fields[1])
        except (IndexError, ValueError):
            raise ValueError("PGM/PPM header without a width and height") from None
    if head[:4] in (b"II*\0", b"MM\0*"):  # TIFF: ImageWidth (256), ImageLength (257) in the first directory
        num = lambda at, n=2: int.from_bytes(head[at : at + n], "little" if head[:1] == b"I" else "big")  # noqa: E731
        at = num(4, 4) + 2  # the first entry (tag, type, count, value), after the entry count
        ent = [(num(i), num(i + 2), i + 8) for i in range(at, min(at + 12 * num(at - 2), len(head) - 11), 12)]
        size = {t: num(v, 2 * k - 4) for t, k, v in ent if t in (256, 257) and k in (3, 4)}  # SHORT or LONG
        if len(size) < 2:
            raise ValueError(f"TIFF without its width and height in its first directory (at byte {at - 2}; truncated?)")
        return "TIFF", size[256], size[257]
    raise ValueError(f"not a PNG, JPEG, BMP, PGM/PPM or TIFF picture (starts with {head[:8].hex(' ')})")


def uint16_gain(a: np.ndarray) -> float:
    """255 over the full scale of the fewest bits (8 to 16, even) that hold a uint16 picture's brightest pixel."""
    return 255.0 / ((1 << next(b for b in (8, 10, 12, 14, 16) if int(a.max()) < 1 << b)) - 1)


def uint16_to_u8(a: np.ndarray) -> np.ndarray:
    """A (non-empty) uint16 picture as uint8 by ``uint16_gain``, rounded; a picture of any other type as it is."""
    return np.rint(a * uint16_gain(a)).astype(np.uint8) if a.dtype == np.uint16 else a


def read_picture(path, *, max_side: int = MAX_PICTURE_SIDE, max_pixels: int = MAX_PICTURE_PIXELS,
                 what: str = "picture") -> tuple[np.ndarray, str]:
    """(2-D uint8 grey picture, a 16-bit one by ``uint16_gain``; SHA-256 of the file); ``PictureFileError`` naming an
    unreadable, empty, unknown, oversized or undecodable file. The header's size is checked first: a small file may
    decode to 30000 x 30000 px."""
    import cv2

    p = Path(path)
    blob = read_bounded(p, MAX_PICTURE_BYTES, error=PictureFileError, what=what)
    try:
        fmt, w, h = picture_size(blob)
    except ValueError as exc:
        raise PictureFileError(f"{p}: not a usable {what}: {exc}") from None
    if w <= 0 or h <= 0:
        raise PictureFileError(f"{p}: {fmt} header says {w} x {h} pixels")
    if w > max_side or h > max_side or w * h > max_pixels:
        raise PictureFileError(f"{p}: {fmt} header says {w} x {h} pixels, beyond the {max_side} px side / "
                               f"{max_pixels} pixel bound; refused before decoding")
    try:
        img = cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise PictureFileError(f"{p}: OpenCV cannot decode the {fmt} {what} "
                               f"({_short(str(exc).strip(), 200)})") from None
    if img is None:
        raise PictureFileError(f"{p}: OpenCV cannot decode the {fmt} {what} (truncated or corrupt?)")
    if img.ndim == 3:
        if img.shape[2] not in (3, 4):
            raise PictureFileError(f"{p}: {img.shape[2]} channels; expected a grey or colour picture")
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    img = uint16_to_u8(img)  # a 10- to 16-bit camera's picture (PNG, PGM, TIFF)
    if img.dtype != np.uint8:
        raise PictureFileError(f"{p}: {img.dtype} pixels; expected an 8- or 16-bit grey picture")
    if img.shape != (h, w):
        raise PictureFileError(f"{p}: decoded to {img.shape[1]} x {img.shape[0]}, but its header says {w} x {h}")
    return img, hashlib.sha256(blob).hexdigest()


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def remove_leftovers(folder, name: str | None = None) -> None:
    """Remove the temporary files (``.NAME.PID.TOKEN.tmp``) of ``name`` (or any) in ``folder`` whose pid is gone."""
    pattern = re.compile(rf"\.{re.escape(name) if name else '.+'}\.([0-9]+)\.[0-9a-f]{{12}}\.tmp")
    with contextlib.suppress(OSError):
        for entry in os.scandir(folder):
            if (m := pattern.fullmatch(entry.name)) and entry.is_file(follow_symlinks=False):
                try:
                    os.kill(int(m.group(1)), 0)
                except ProcessLookupError:
                    os.unlink(entry.path)
                except (PermissionError, OverflowError):
                    pass


@contextlib.contextmanager
def file_lock(path, *, error: type[CellError] = ConfigError, what: str = "file", timeout_s: float = 10.0):
    """Hold an exclusive flock for writing ``path`` (writers take turns), waiting at most ``timeout_s``, else ``error``;
    the lock file in ``lockdir``'s folder is keyed on the folder's device and inode (two spellings, one lock)."""
    path = Path(path)
    try:
        st = os.stat(path.parent)
    except OSError as exc:
        raise error(f"{path}: cannot write the {what}: its folder {path.parent}: {os_cause(exc)}") from None
    fd, lock = open_lock_file(lock_slug("file", f"{st.st_dev:x}", f"{st.st_ino:x}", path.name), error=error,
                              what=f"{path}: cannot write the {what}")
    try:
        end = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > end:
                    raise error(f"{path}: another process has been writing the {what} for {timeout_s:g} s "
                                f"(it holds {lock}); nothing written") from None
            time.sleep(0.02)
        yield
    finally:
        os.close(fd)  # releases the lock


def check_folder(path, *, error: type[CellError] = ConfigError, what: str = "file") -> None:
    """``error`` naming ``path`` unless its folder exists (a writer here never creates one)."""
    folder = Path(path).parent
    if not folder.is_dir():
        why = "does not exist (it is not created)" if not folder.exists() else "is a file, not a folder"
        raise error(f"{path}: cannot write the {what}: the folder {folder} {why}")


def atomic_write(path, data: bytes, *, error: type[CellError] = ConfigError, what: str = "file",
                 mode: int | None = None) -> None:
    """Replace ``path`` with ``data``: a temporary file in its folder (named by pid; dead writers' leftovers removed),
    flushed to disk, renamed over it; mode: the old file's, else ``mode``, else 0o666 less umask. A symlink's target is
    replaced; a device, FIFO, socket or missing folder refused. ``error`` naming path and cause; old file untouched."""
    path = Path(os.path.realpath(path)) if Path(path).is_symlink() else Path(path)
    folder = path.parent
    fail = lambda why: error(f"{path}: cannot write the {what}: {why}")  # noqa: E731
    check_folder(path, error=error, what=what)
    try:
        st_mode = os.stat(path).st_mode
    except FileNotFoundError:
        st_mode = None
    except OSError as exc:
        raise fail(os_cause(exc)) from None
    if st_mode is not None and (kind := _not_regular(st_mode)):
        raise fail("a folder of that name exists" if stat.S_ISDIR(st_mode) else f"it is {kind}, not a regular file")
    old_mode = mode if st_mode is None else stat.S_IMODE(st_mode)
    remove_leftovers(folder, path.name)
    tmp = folder / f".{path.name}.{os.getpid()}.{secrets.token_hex(6)}.tmp"  # see remove_leftovers
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666 if old_mode is None else old_mode)
    except OSError as exc:
        raise fail(os_cause(exc)) from None
    try:
        try:
            _write_all(fd, data)
            if old_mode is not None:
                os.fchmod(fd, old_mode)  # the replaced file's permissions, whatever the umask
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise fail(f"{os_cause(exc)}; the previous file is unchanged") from None
        raise
    with contextlib.suppress(OSError):  # make the rename itself durable
        dfd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


#: The picture formats ``write_picture`` writes (by the name's extension).
PICTURE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".pnm")


def write_picture(path, image, *, error: type[CellError] = ConfigError, what: str = "picture") -> None:
    """Write 8-bit grey or BGR(A) ``image`` (OpenCV would silently convert others) in the format of ``path``'s
    extension, encoded in memory (OpenCV never sees the path), then ``atomic_write``; ``error`` naming the cause."""
    import cv2

    path = Path(path)
    ext = path.suffix.lower()
    if ext not in PICTURE_EXTENSIONS:
        raise error(f"{path}: cannot write the {what}: the name must end in one of {', '.join(PICTURE_EXTENSIONS)}")
    img = np.asarray(image)
    if img.dtype != np.uint8 or img.size == 0 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (1, 3, 4))):
        raise error(f"{path}: cannot write the {what}: expected an 8-bit grey or BGR picture, got {img.dtype} "
                    f"pixels of shape {img.shape}")
    try:
        ok, buf = cv2.imencode(ext, img)
    except cv2.error as exc:
        raise error(f"{path}: cannot write the {what}: OpenCV cannot encode it ({str(exc).strip()})") from None
    if not ok:
        raise error(f"{path}: cannot write the {what}: OpenCV cannot encode it as {ext}")
    atomic_write(path, buf.tobytes(), error=error, what=what)
