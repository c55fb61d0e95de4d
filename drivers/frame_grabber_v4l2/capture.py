"""Frame sources: the one module of the project that uses OpenCV's capture API (``cv2.VideoCapture``).

A source yields raw frames with the moment they were exposed; ``FrameGrabber`` turns them into checked
grey frames. Sources here: a V4L2 grabber card (``V4L2Source``), an image sequence or a video file
(``RecordedSource``). Other schemes (the simulator's ``sim://``) are plugged in with
``register_source``, so this package never imports what provides them.
"""

from __future__ import annotations

import logging
import math
import os
import re
import threading
import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

from selfview.drivers.frame_grabber_v4l2.url import GrabberUrl
from selfview.drivers.frame_grabber_v4l2 import v4l2 as _v4l2
from selfview.drivers.frame_grabber_v4l2.v4l2 import FIELD_NAMES, V4L2Device, fields_per_buffer, std_name
from selfview.errors import ConfigError, DeviceError, DeviceTimeout, ImageError
from selfview.files.io_safe import read_picture

log = logging.getLogger(__name__)

__all__ = [
    "FrameSource",
    "SourceFactory",
    "EndOfStream",
    "V4L2Source",
    "RecordedSource",
    "register_source",
    "unregister_source",
    "source_for",
    "to_grey",
]


class EndOfStream(DeviceError):
    """A recording has no more frames (and was not asked to loop)."""


@runtime_checkable
class FrameSource(Protocol):
    """What ``FrameGrabber`` reads from.

    ``read(timeout_s)`` returns ``(image, timestamp)``: a uint8 array (H, W) or (H, W, C) and the
    monotonic time (s, ``time.monotonic``'s clock) at which its exposure started; it raises
    DeviceTimeout if no frame arrives within ``timeout_s``. ``frame_period_s`` is the nominal time
    between frames (None: unknown).
    """

    description: str
    frame_period_s: float | None

    def open(self) -> None: ...

    def read(self, timeout_s: float) -> tuple[np.ndarray, float]: ...

    def close(self) -> None: ...


SourceFactory = Callable[[GrabberUrl], FrameSource]

_registry: dict[str, SourceFactory] = {}
_registry_lock = threading.Lock()


def register_source(scheme: str, factory: SourceFactory) -> SourceFactory | None:
    """Make ``scheme://`` URLs open ``factory(url)``; returns the factory it replaces (or None)."""
    if scheme in ("v4l2", "frames", "file"):
        raise ConfigError(f"register_source: {scheme!r} is built in")
    with _registry_lock:
        old = _registry.get(scheme)
        _registry[scheme] = factory
        return old


def unregister_source(scheme: str, factory: SourceFactory | None = None) -> None:
    """Forget ``scheme`` (only if it is still ``factory``, when one is given)."""
    with _registry_lock:
        if factory is None or _registry.get(scheme) is factory:
            _registry.pop(scheme, None)


def source_for(
    url: GrabberUrl, sources: dict[str, SourceFactory] | None = None, *, timeout_s: float = 1.0
) -> FrameSource:
    """The source for a parsed URL: built in, from ``sources``, or from the registry. ``timeout_s``
    bounds how long the V4L2 backend may wait for a frame."""
    if url.scheme == "v4l2":
        return V4L2Source(url, select_timeout_s=timeout_s)
    if url.scheme in ("frames", "file"):
        return RecordedSource(url)
    factory = (sources or {}).get(url.scheme)
    if factory is None:
        with _registry_lock:
            factory = _registry.get(url.scheme)
    if factory is None:
        known = sorted({"v4l2", "frames", "file"} | set(_registry) | set(sources or {}))
        hint = " (sim:// needs a simulated world attached: selfview.mocks.sim_camera.attach_world)" if url.scheme == "sim" else ""
        raise ConfigError(f"{url.url}: no frame source for scheme {url.scheme!r}{hint}; known: {', '.join(known)}")
    return factory(url)


def to_grey(image: np.ndarray, what: str = "frame") -> np.ndarray:
    """A frame as a 2-D uint8 grey image: (H, W) kept, (H, W, 1) squeezed, BGR / BGRA converted."""
    a = np.asarray(image)
    if a.dtype != np.uint8:
        raise ImageError(f"{what}: expected 8-bit pixels, got {a.dtype}")
    if a.ndim == 2:
        return a
    if a.ndim == 3 and a.shape[2] == 1:
        return a[:, :, 0]
    if a.ndim == 3 and a.shape[2] == 3:
        return cv2.cvtColor(a, cv2.COLOR_BGR2GRAY)
    if a.ndim == 3 and a.shape[2] == 4:
        return cv2.cvtColor(a, cv2.COLOR_BGRA2GRAY)
    raise ImageError(f"{what}: expected a grey or BGR picture, got shape {a.shape}")


class _Paced:
    """Releases frames no faster than ``fps`` (None: as they come); times on the monotonic clock."""

    def __init__(self, fps: float | None):
        self.frame_period_s = None if fps is None else 1.0 / fps
        self._next = 0.0

    def wait(self, timeout_s: float, what: str) -> float:
        now = time.monotonic()
        if self.frame_period_s is None:
            return now
        due = max(now, self._next)
        if due - now > timeout_s:
            time.sleep(timeout_s)
            raise DeviceTimeout(f"{what}: next frame due in {due - now:.3f} s, beyond timeout_s={timeout_s}")
        if due > now:
            time.sleep(due - now)
        self._next = due + self.frame_period_s
        return due


class _ImageSequence:
    """A numbered image sequence (``img_%03d.png``) read in index order from the smallest index present up to
    the first gap, as OpenCV's CAP_IMAGES reader does; written here because that reader's behaviour changes
    between OpenCV releases (4.10 cannot open a sequence of one picture). Each file is read by
    ``selfview.files.io_safe.read_picture`` (decoded in memory, no native call sees the path, a picture too
    large refused from its header), as a grey picture. The VideoCapture calls ``RecordedSource`` makes of it."""

    def __init__(self, pattern: str):
        folder, name = os.path.split(pattern)
        m = re.search(r"%(0?)(\d*)d", name)
        self._folder, self._head, self._tail = folder or ".", name[: m.start()], name[m.end() :]
        self._format = pattern
        width = int(m.group(2) or 0) if m.group(1) else 0
        digits = rf"\d{{{width},}}" if width else r"\d+"
        rx = re.compile(re.escape(self._head) + f"({digits})" + re.escape(self._tail) + "$")
        try:
            names = os.listdir(self._folder)
        except OSError as exc:
            raise DeviceError(f"{pattern}: cannot list the folder {self._folder}: {exc.strerror or exc}") from None
        found = [int(mm.group(1)) for f in names if (mm := rx.match(f))]
        self._next = min(found) if found else None

    def isOpened(self) -> bool:
        return self._next is not None

    def read(self):
        if self._next is None:
            return False, None
        path = self._format % self._next
        if not os.path.exists(path):  # the first gap ends the sequence
            return False, None
        try:
            img, _ = read_picture(path, what="frame")  # bounded in its header before it is decoded
        except ImageError as exc:
            raise DeviceError(str(exc)) from None
        self._next += 1
        return True, img

    def release(self) -> None:
        self._next = None


class RecordedSource:
    """An image sequence (``frames://``, read by ``_ImageSequence``) or a video file (``file://``, OpenCV's
    reader).

    Each frame is stamped with the moment it is read (paced at ``fps`` when the URL gives one).
    At the end of the recording: EndOfStream, or the first frame again with ``loop=1``.
    """

    def __init__(self, url: GrabberUrl):
        self.url = url
        self.description = url.url
        self._pace = _Paced(url.fps)
        self.frame_period_s = self._pace.frame_period_s
        self._cap: cv2.VideoCapture | _ImageSequence | None = None
        self.frames_read = 0

    def _open_capture(self):
        path = self.url.path
        if self.url.scheme == "frames":
            folder = os.path.dirname(path) or "."
            if not os.path.isdir(folder):
                raise DeviceError(f"{self.url.url}: folder {folder} does not exist")
            cap = _ImageSequence(path)
        else:
            if not os.path.isfile(path):
                raise DeviceError(f"{self.url.url}: video file {path} does not exist")
            cap = cv2.VideoCapture(path, cv2.CAP_ANY)
        if not cap.isOpened():
            cap.release()
            what = "no image matches the pattern" if self.url.scheme == "frames" else "OpenCV cannot decode the file"
            raise DeviceError(f"{self.url.url}: cannot open ({what})")
        return cap

    def open(self) -> None:
        if self._cap is None:
            self._cap = self._open_capture()

    def read(self, timeout_s: float) -> tuple[np.ndarray, float]:
        if self._cap is None:
            raise DeviceError(f"{self.url.url}: read before open")
        ok, img = self._cap.read()
        if not ok and self.url.loop and self.frames_read > 0:
            self._cap.release()
            self._cap = self._open_capture()
            ok, img = self._cap.read()
        if not ok or img is None:
            raise EndOfStream(f"{self.url.url}: no more frames after {self.frames_read} (end of the recording)")
        t = self._pace.wait(timeout_s, self.url.url)
        self.frames_read += 1
        return img, t

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()


# V4L2 fourccs whose raw buffer holds the grey (luma) values without colour conversion: (bytes per
# pixel, offset of the luma byte in a pixel).
_RAW_GREY = {"GREY": (1, 0), "YUYV": (2, 0), "UYVY": (2, 1)}


def exposure_start(
    ts: float,
    now: float,
    *,
    tstamp: str | None,
    buffer_s: float,
    frame_period_s: float,
    buffers: int,
) -> float:
    """When the exposure of a dequeued buffer started, on the monotonic clock.

    ``ts`` the buffer's timestamp (s), ``now`` the time it was read; ``tstamp`` the buffer's timestamp
    source: 'end' (V4L2_BUF_FLAG_TSTAMP_SRC_EOF, V4L2's default and bttv's: the last byte of the frame),
    'start' (TSTAMP_SRC_SOE) or None (unknown: taken as 'end'); ``buffer_s`` how long the buffer's fields
    take (one frame period for a frame of two fields, half of it for a single field).

    A driver's clock has slop: a stamp may lie up to one frame period after the read (a driver that
    stamps the end of a frame from its schedule, as vivid does, or from an interrupt on another CPU); it
    counts as the read time. Any stamp in the past is taken as it is (a frame that waited long in its
    buffer is old). A timestamp that is not a plausible monotonic time (not finite, not positive, or
    further ahead than that slop) is replaced by the most pessimistic one: ``buffers`` + 1 frame periods
    before the read (a frame may have waited in every buffer)."""
    if not (math.isfinite(ts) and 0.0 < ts <= now + frame_period_s):
        return now - (buffers + 1) * frame_period_s - buffer_s
    ts = min(ts, now)
    return ts if tstamp == "start" else ts - buffer_s


class V4L2Source:
    """A V4L2 capture device (an analogue CCIR grabber card) through OpenCV's V4L2 backend.

    ``open()``: open the node for control ioctls, check it captures video, select the input and the
    analogue standard (VIDIOC_S_INPUT, VIDIOC_S_STD), check a signal is present (input status, VIDIOC_QUERYSTD),
    set ``OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT`` (whole seconds, before the first capture), then open the
    capture with size, pixel format, 1-2 buffers and no RGB conversion, and check OpenCV got them; set
    crop and compose to the whole picture and read them back (OpenCV first sets 640x480, and a card may
    keep that compose rectangle inside a larger frame); refuse a mirrored or upside-down stream;
    read the field order back (VIDIOC_G_FMT) and check it fits the height. Frames come as the raw
    buffer; the luma bytes are picked out (GREY, YUYV, UYVY). After the first frame the buffers the
    driver really allocated are counted (VIDIOC_QUERYBUF: bttv allocates at least 2 whatever is asked)
    and their timestamp source read from the flags. A frame's time is the start of its exposure:
    ``exposure_start`` from the buffer's timestamp (V4L2's default stamps the END of the frame). The
    signal and the orientation are checked again with every frame.
    """

    def __init__(self, url: GrabberUrl, *, select_timeout_s: float = 1.0):
        if url.fourcc not in _RAW_GREY:
            raise ConfigError(
                f"{url.url}: format={url.fourcc} cannot be read as grey without colour conversion; "
                f"use one of {', '.join(_RAW_GREY)}"
            )
        self.url = url
        self.description = url.url
        self.select_timeout_s = select_timeout_s
        lines625 = url.std is not None and bool(url.std & 0x00FF06FF)  # PAL, PAL-N/Nc, SECAM: 576 active lines
        if url.std is not None and not lines625 and url.height > 480:
            raise ConfigError(
                f"{url.url}: std={std_name(url.std)} has 480 active lines, but height={url.height}: the card would "
                "scale the lines up (or refuse); use std=pal for a CCIR camera, or height<=480"
            )
        self.frame_period_s = 1.0 / 25.0 if lines625 else 1.0 / 30.0
        self.device = V4L2Device(url.path)
        self.info: dict | None = None
        self._cap: cv2.VideoCapture | None = None
        self.field: int | None = None  # the capture format's field order (enum v4l2_field), None: not told
        self.buffer_s = self.frame_period_s  # how long one buffer's fields take
        self.buffers: int | None = None  # buffers the driver allocated (read back after the first frame)
        self.tstamp: str | None = None  # 'end' or 'start' of the frame (from the buffer flags), None: unknown
        self.lost_frames = 0  # frames the driver never delivered (gaps between buffer timestamps)
        self._last_ts: float | None = None

    def open(self) -> None:
        if self._cap is not None:
            return
        u = self.url
        self.device.open()
        try:
            self.info = self.device.querycap()
            if u.input is not None:
                self.device.set_input(u.input)
            if u.std is not None:
                self.device.set_std(u.std)
            self.device.check_signal(u.std)
            # OpenCV reads this once, at the first V4L2 frame of the process; whole seconds, >= 1.
            os.environ.setdefault("OPENCV_VIDEOIO_V4L_SELECT_TIMEOUT", str(max(1, math.ceil(self.select_timeout_s))))
            cap = cv2.VideoCapture(u.path, cv2.CAP_V4L2)
            if not cap.isOpened():
                cap.release()
                raise DeviceError(f"{u.url}: OpenCV's V4L2 backend cannot open {u.path} (busy?)")
            try:
                self._configure(cap)
                self.device.whole_picture(u.width, u.height)
                self.device.check_orientation()
                self._check_field()
            except BaseException:
                cap.release()
                raise
            self._cap = cap
        except BaseException:
            self.device.close()
            raise

    def _configure(self, cap: cv2.VideoCapture) -> None:
        u = self.url
        cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*u.fourcc))
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, u.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, u.height)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, u.buffers)
        cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        if (w, h) != (u.width, u.height):
            raise ConfigError(f"{u.url}: the grabber gives {w}x{h}, not the configured {u.width}x{u.height}")
        got = int(cap.get(cv2.CAP_PROP_FOURCC)) & 0xFFFFFFFF
        name = got.to_bytes(4, "little").decode("ascii", errors="replace")
        if name != u.fourcc:
            raise ConfigError(f"{u.url}: the grabber gives pixel format {name!r}, not {u.fourcc}")
        if int(cap.get(cv2.CAP_PROP_CONVERT_RGB)) != 0:
            raise DeviceError(f"{u.url}: OpenCV would not switch RGB conversion off")

    def _check_field(self) -> None:
        u = self.url
        self.field = self.device.field_order()
        if self.field is None:  # not told: a frame of two fields, the longer (safer) duration
            self.buffer_s = self.frame_period_s
            return
        name = FIELD_NAMES.get(self.field, str(self.field))
        try:
            n = fields_per_buffer(self.field)
        except ValueError as exc:
            raise DeviceError(f"{u.url}: the driver reports {exc}") from None
        if self.field == 1:  # NONE: progressive frames
            self.buffer_s = self.frame_period_s
            return
        lines = 288 if self.frame_period_s == 1.0 / 25.0 else 240  # active lines of one field
        if n == 1 and u.height > lines:
            raise ConfigError(
                f"{u.url}: field order {name} gives single fields of at most {lines} lines, but height={u.height}; "
                f"ask for height<={lines} or a driver set to INTERLACED"
            )
        self.buffer_s = self.frame_period_s * n / 2.0

    def _read_buffers(self) -> None:
        """After streaming started: how many buffers the driver allocated, and their timestamp source."""
        n, flags = self.device.buffers()
        self.buffers = n or None
        if n and n != self.url.buffers:
            log.warning("%s: asked for %d buffer(s), the driver allocated %d: frames may be up to %d periods old",
                        self.url.url, self.url.buffers, n, n)
        if flags is not None:
            src = flags & _v4l2.V4L2_BUF_FLAG_TSTAMP_SRC_MASK
            self.tstamp = "start" if src == _v4l2.V4L2_BUF_FLAG_TSTAMP_SRC_SOE else "end"
            if flags & _v4l2.V4L2_BUF_FLAG_TIMESTAMP_MASK != _v4l2.V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC:
                self.tstamp = "not monotonic"

    def _count_lost(self, ts: float) -> None:
        """Frames the driver never delivered (no free buffer, or dropped), from the gaps between
        consecutive buffer timestamps: OpenCV queues each buffer again before its sequence number can be
        read, and a gap of k frame periods is k - 1 frames lost."""
        if self._last_ts is not None and math.isfinite(ts) and ts > self._last_ts:
            self.lost_frames += max(0, round((ts - self._last_ts) / self.buffer_s) - 1)
        self._last_ts = ts if math.isfinite(ts) else None

    def _grey_from_raw(self, raw: np.ndarray) -> np.ndarray:
        u = self.url
        bpp, offset = _RAW_GREY[u.fourcc]
        data = np.asarray(raw, dtype=np.uint8).reshape(-1)
        if data.size < u.height * u.width * bpp or data.size % u.height:
            raise ImageError(f"{u.url}: frame of {data.size} bytes, expected {u.height} rows of {u.width * bpp}")
        rows = data.reshape(u.height, -1)  # rows may be padded (bytesperline > width * bpp)
        return np.ascontiguousarray(rows[:, offset : u.width * bpp : bpp])

    def read(self, timeout_s: float) -> tuple[np.ndarray, float]:
        if self._cap is None:
            raise DeviceError(f"{self.url.url}: read before open")
        t0 = time.monotonic()
        ok, raw = self._cap.read()
        now = time.monotonic()
        if not ok or raw is None:
            self.device.check_signal(self.url.std)  # says "no signal" when that is why
            if now - t0 < 0.5 * min(timeout_s, self.select_timeout_s):
                raise DeviceError(f"{self.url.url}: the capture failed at once although the signal is "
                                  f"{std_name(self.url.std or 0)}: the driver ended the stream (a capture error)")
            raise DeviceTimeout(
                f"{self.url.url}: no frame within {now - t0:.2f} s although the signal is "
                f"{std_name(self.url.std or 0)} (grabber stalled?)"
            )
        if now - t0 > timeout_s:
            raise DeviceTimeout(f"{self.url.url}: the frame took {now - t0:.2f} s, beyond timeout_s={timeout_s}")
        # every frame: a card keeps delivering (noise) frames after the signal is gone, and a flip control
        # may be switched while streaming
        self.device.check_signal(self.url.std)
        self.device.check_orientation()
        if self.buffers is None:
            self._read_buffers()
        ts = self._cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        if self.tstamp == "not monotonic":
            ts = math.nan  # not comparable with time.monotonic(): the pessimistic estimate below
        self._count_lost(ts)
        buffers = self.buffers if self.buffers is not None else max(self.url.buffers, 2)
        start = exposure_start(ts, now, tstamp=self.tstamp, buffer_s=self.buffer_s,
                               frame_period_s=self.frame_period_s, buffers=buffers)
        return self._grey_from_raw(raw), start

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()
        self.device.close()
