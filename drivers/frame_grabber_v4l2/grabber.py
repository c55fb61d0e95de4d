"""The frame grabber: checked grey frames, taken after a given moment, averaged or as one field.

``FrameGrabber(url)`` reads from the source the URL names (``selfview.drivers.frame_grabber_v4l2.url``):
the CCIR grabber card over V4L2, a recorded image sequence or video file, or a registered source such as
the simulator's ``sim://``. Failures raise (DeviceError, DeviceTimeout, ImageError, ConfigError);
nothing returns None or False.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from selfview.drivers._ownership import claim_for
from selfview.drivers.frame_grabber_v4l2.capture import FrameSource, SourceFactory, source_for, to_grey
from selfview.drivers.frame_grabber_v4l2.url import GrabberUrl, parse_grabber_url
from selfview.errors import ConfigError, DeviceError, DeviceTimeout, ImageError

__all__ = ["Frame", "FrameGrabber"]


@dataclass(frozen=True)
class Frame:
    """A grabbed picture.

    ``image`` (H, W) uint8; ``timestamp`` the monotonic time (s) its (first) exposure started;
    ``index`` the source's running number of that frame (0 first); ``count`` frames averaged;
    ``field`` None, 'even' or 'odd'.
    """

    image: np.ndarray
    timestamp: float
    index: int
    count: int = 1
    field: str | None = None


def field_image(image: np.ndarray, which: str) -> np.ndarray:
    """One field of an interlaced frame at full size: the rows of field ``which`` ('even': rows 0, 2,
    ...) kept where they are, the other rows interpolated between them, so pixel (u, v) keeps its
    meaning. (H, W) uint8 -> (H, W) uint8."""
    a = np.asarray(image, dtype=np.float32)
    out = a.copy()
    start = 0 if which == "even" else 1
    h = a.shape[0]
    for r in range(1 - start, h, 2):  # rows of the other field
        up, down = r - 1, r + 1
        if up < 0:
            out[r] = a[down]
        elif down >= h:
            out[r] = a[up]
        else:
            out[r] = 0.5 * (a[up] + a[down])
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


class FrameGrabber:
    """Grabs checked grey frames from the source a URL names.

    ``timeout_s``: how long a frame may take (past ``after``). ``black_level``: a frame whose 99th
    percentile grey level lies below it is black (no light, lens cap, no camera). ``saturation_level`` /
    ``max_saturated``: a frame with more than that fraction of pixels at or above the level is
    saturated. Either check is off when its level is None. ``width`` / ``height``: the expected size
    (default: the URL's for v4l2, else not checked). ``sources``: extra scheme factories for this
    grabber (beside the module registry). Construction does no I/O.
    """

    def __init__(
        self,
        url: str,
        *,
        timeout_s: float = 1.0,
        black_level: float | None = 8.0,
        saturation_level: float | None = 250.0,
        max_saturated: float = 0.25,
        width: int | None = None,
        height: int | None = None,
        sources: dict[str, SourceFactory] | None = None,
    ):
        self.url: GrabberUrl = parse_grabber_url(url)
        if isinstance(timeout_s, bool) or not isinstance(timeout_s, (int, float)) or not 0 < timeout_s < float("inf"):
            raise ConfigError(f"frame grabber timeout_s={timeout_s!r}: expected a finite positive number of seconds "
                              "(every wait ends)")
        for name, v in (("width", width), ("height", height)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1):
                raise ConfigError(f"frame grabber {name}={v!r}: expected a positive whole number of pixels or None")
        for name, v in (("black_level", black_level), ("saturation_level", saturation_level)):
            if v is not None and not 0 <= v <= 255:
                raise ConfigError(f"frame grabber {name}={v!r}: expected a grey level 0..255 or None")
        if not 0 < max_saturated <= 1:
            raise ConfigError(f"frame grabber max_saturated={max_saturated!r}: expected a fraction in (0, 1]")
        self.timeout_s = float(timeout_s)
        self.black_level = black_level
        self.saturation_level = saturation_level
        self.max_saturated = float(max_saturated)
        self.width = width if width is not None else self.url.width
        self.height = height if height is not None else self.url.height
        self._sources = sources
        self.source: FrameSource | None = None
        self._claim = None  # the device's lock while connected
        self._index = 0
        self.dropped_last = 0  # frames dropped by the last grab as exposed too early
        self._lock = threading.Lock()

    # --- connection ---------------------------------------------------------------------------
    def connect(self) -> "FrameGrabber":
        """Open the source (safe to call twice). Raises DeviceError / ConfigError naming the cause."""
        with self._lock:
            if self.source is None:
                src = source_for(self.url, self._sources, timeout_s=self.timeout_s)
                claim = claim_for(src, "frame grabber", self.url.path if self.url.scheme == "v4l2" else None)
                try:
                    src.open()
                except BaseException:  # released now, not when the traceback holding ``src`` is freed
                    if claim is not None:
                        claim.release()
                    raise
                self.source, self._claim = src, claim
                self._index = 0
        return self

    def close(self) -> None:
        """Release the source and its lock (safe to call twice), whoever still holds the source object."""
        with self._lock:
            src, self.source = self.source, None
            claim, self._claim = self._claim, None
            try:
                if src is not None:
                    src.close()
            finally:
                if claim is not None:
                    claim.release()

    def __enter__(self) -> "FrameGrabber":
        return self.connect()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- grabbing -----------------------------------------------------------------------------
    def _next(self, deadline: float) -> tuple[np.ndarray, float, int]:
        left = deadline - time.monotonic()
        if left <= 0:
            raise DeviceTimeout(f"{self.url.url}: no frame within timeout_s={self.timeout_s}")
        img, ts = self.source.read(left)
        img = to_grey(img, self.url.url)
        if self.width is not None and self.height is not None and img.shape != (self.height, self.width):
            raise ImageError(
                f"{self.url.url}: frame is {img.shape[1]}x{img.shape[0]}, expected {self.width}x{self.height}"
            )
        i = self._index
        self._index += 1
        return img, float(ts), i

    def check(self, image: np.ndarray) -> None:
        """Raise ImageError if ``image`` is black or saturated (the configured thresholds)."""
        if self.black_level is not None:
            p99 = float(np.percentile(image, 99))
            if p99 < self.black_level:
                raise ImageError(
                    f"{self.url.url}: black frame (99% of pixels below grey {p99:.0f} < black_level "
                    f"{self.black_level:g}): light off, lens cap on, or no camera signal?"
                )
        if self.saturation_level is not None:
            frac = float(np.mean(image >= self.saturation_level))
            if frac > self.max_saturated:
                raise ImageError(
                    f"{self.url.url}: saturated frame ({100 * frac:.0f}% of pixels at grey >= "
                    f"{self.saturation_level:g}, more than {100 * self.max_saturated:.0f}%): too much light or gain"
                )

    def grab(self, after: float | None = None, average: int = 1, field: bool | str = False) -> Frame:
        """One checked frame exposed after ``after`` (a ``time.monotonic()`` value; None: the next).

        Frames exposed before ``after`` are dropped: a picture taken after the robot settled must have
        been exposed after it settled, and buffered frames are older.

        ``average`` consecutive frames are averaged (rounded to uint8). ``field`` True or 'even' /
        'odd' returns that field with the other rows interpolated (not with ``average`` > 1).
        Raises DeviceTimeout if no frame exposed after ``after`` arrives within ``timeout_s`` of
        ``max(now, after)``, ImageError for a wrong size, black or saturated frame.
        """
        if isinstance(average, bool) or not isinstance(average, int) or not 1 <= average <= 256:
            raise ConfigError(f"grab average={average!r}: expected a whole number 1..256")
        which = {False: None, True: "even", "even": "even", "odd": "odd"}.get(field, "bad")
        if which == "bad":
            raise ConfigError(f"grab field={field!r}: expected False, True, 'even' or 'odd'")
        if which is not None and average > 1:
            raise ConfigError("grab: a field is for a moving scene; it cannot be averaged (average must be 1)")
        with self._lock:
            if self.source is None:
                raise DeviceError(f"{self.url.url}: grab before connect()")
            start = time.monotonic() if after is None else max(time.monotonic(), float(after))
            deadline = start + self.timeout_s
            img, ts, idx = self._next(deadline)
            dropped = 0
            while after is not None and ts <= after:
                dropped += 1
                img, ts, idx = self._next(deadline)
            first_ts, first_idx = ts, idx
            if average > 1:
                acc = img.astype(np.float64)
                for k in range(1, average):
                    more, _, _ = self._next(time.monotonic() + self.timeout_s)
                    acc += more
                img = np.clip(np.rint(acc / average), 0, 255).astype(np.uint8)
            if which is not None:
                img = field_image(img, which)
            self.dropped_last = dropped
        self.check(img)
        return Frame(image=img, timestamp=first_ts, index=first_idx, count=average, field=which)
