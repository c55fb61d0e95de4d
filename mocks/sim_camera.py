"""The simulated wrist camera behind ``sim://``: the renderer's picture of a SimWorld, frame by frame.

``attach_world(world)`` registers the ``sim`` scheme with the frame grabber's source registry, so
``FrameGrabber('sim://?fps=25&seed=3')`` reads this world; procedures do the wiring, drivers never
import this module.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import numpy as np

from selfview.drivers.frame_grabber_v4l2.capture import register_source, unregister_source
from selfview.drivers.frame_grabber_v4l2.url import GrabberUrl
from selfview.mocks.render import RenderResult, render
from selfview.mocks.world import SimWorld
from selfview.errors import ConfigError, DeviceError, DeviceTimeout

__all__ = ["SimCamera", "attach_world", "Attachment"]

_PARAMS = {"fps", "seed", "noise", "exact", "blur", "gain", "supersample"}


class SimCamera:
    """A frame source (``selfview.drivers.frame_grabber_v4l2.FrameSource``) that renders ``world``.

    ``fps``: frame rate (CCIR: 25). ``seed``: seeds the per-frame noise seeds. ``noise``: add sensor
    noise. ``exact``: render each frame in full. ``blur_px``, ``gain``, ``supersample``: as
    ``selfview.mocks.render.render``. ``clock`` / ``sleep``: the monotonic clock and how to wait on it.

    A frame clock ticks at ``fps`` from ``open()``; a read waits for the next tick (frames nobody read
    are lost, as on a real grabber) and returns the world's view at that moment, stamped with the tick's
    monotonic time. Each frame has its own noise seed, so frames differ in noise like a real camera's
    and a run is repeatable. Rendering takes a good part of a second, so the noise-free picture is
    cached per ``world.version`` and each frame adds the renderer's sensor noise to it: equal to
    ``render(world, seed=s)`` within one grey level (the cached picture is already rounded); with
    ``exact`` every frame is rendered in full, bit for bit ``render(world, seed=s)``.
    """

    def __init__(
        self,
        world: SimWorld,
        *,
        fps: float = 25.0,
        seed: int = 0,
        noise: bool = True,
        exact: bool = False,
        blur_px: float | None = None,
        gain: float = 1.0,
        supersample: int = 4,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ):
        if not isinstance(world, SimWorld):
            raise ConfigError(f"sim camera: expected a SimWorld, got {type(world).__name__}")
        if not (isinstance(fps, (int, float)) and 0 < fps <= 1000):
            raise ConfigError(f"sim camera fps={fps!r}: expected a frame rate in (0, 1000]")
        self.world = world
        self.fps = float(fps)
        self.frame_period_s = 1.0 / self.fps
        self.seed = int(seed)
        self.noise = bool(noise)
        self.exact = bool(exact)
        self.render_kw = {"blur_px": blur_px, "gain": float(gain), "supersample": int(supersample)}
        self.clock = clock
        self.sleep = sleep
        self.description = f"sim:// (world seed {world.seed}, {self.fps:g} fps)"
        self._rng = np.random.default_rng(self.seed)
        self._t0: float | None = None
        self._k = -1  # tick of the last frame
        self._cache: tuple[int, RenderResult] | None = None  # (world.version, noise-free render)
        self._lock = threading.Lock()
        self.renders = 0  # full renders made (the cache's misses and exact frames)
        self.last_seed: int | None = None
        self.last_render: RenderResult | None = None
        self.last_tick: int | None = None

    @classmethod
    def from_url(cls, world: SimWorld, url: GrabberUrl, **defaults) -> "SimCamera":
        """A camera configured by a ``sim://?fps=..&seed=..&noise=0|1&exact=0|1&blur=..&gain=..&supersample=..``
        URL; ``defaults`` are used for what the URL leaves out."""
        if url.path not in ("", "/"):
            raise ConfigError(f"{url.url}: a sim URL has no path; expected sim://?fps=25&seed=0")
        unknown = sorted(set(url.params) - _PARAMS)
        if unknown:
            raise ConfigError(f"{url.url}: unknown parameter(s) {', '.join(unknown)}; sim:// takes {', '.join(sorted(_PARAMS))}")
        kw = dict(defaults)

        def num(key, conv):
            try:
                return conv(url.params[key])
            except ValueError:
                raise ConfigError(f"{url.url}: {key}={url.params[key]!r} is not a {conv.__name__}") from None

        for key, name, conv in (("fps", "fps", float), ("seed", "seed", int), ("blur", "blur_px", float),
                                ("gain", "gain", float), ("supersample", "supersample", int)):
            if key in url.params:
                kw[name] = num(key, conv)
        for key in ("noise", "exact"):
            if key in url.params:
                if url.params[key] not in ("0", "1"):
                    raise ConfigError(f"{url.url}: {key}={url.params[key]!r}; expected 0 or 1")
                kw[key] = url.params[key] == "1"
        return cls(world, **kw)

    # --- FrameSource --------------------------------------------------------------------------
    def open(self) -> None:
        with self._lock:
            if self._t0 is None:
                self._t0 = self.clock()
                self._k = -1

    def close(self) -> None:
        with self._lock:
            self._t0 = None
            self._cache = None

    def _noise_free(self) -> RenderResult:
        version = self.world.version
        if self._cache is None or self._cache[0] != version:
            res = render(self.world, seed=None, noise=False, **self.render_kw)
            self.renders += 1
            self._cache = (version, res)  # a change during the render shows as a new version next time
        return self._cache[1]

    def read(self, timeout_s: float) -> tuple[np.ndarray, float]:
        """The next frame: wait for the next tick, render the world then. Returns (image (H, W) uint8,
        tick time). Raises DeviceTimeout if the next tick lies beyond ``timeout_s``."""
        with self._lock:
            if self._t0 is None:
                raise DeviceError("sim://: read before open")
            now = self.clock()
            k = max(self._k + 1, math.ceil((now - self._t0) * self.fps - 1e-9))
            t_k = self._t0 + k / self.fps
            if t_k - now > timeout_s:
                self.sleep(timeout_s)
                raise DeviceTimeout(f"sim://: next frame due in {t_k - now:.3f} s, beyond timeout_s={timeout_s}")
            if t_k > now:
                self.sleep(t_k - now)
            self._k = k
            seed = int(self._rng.integers(0, 2**63 - 1))
            if self.exact or self.world.imperfections.per_frame:  # a real grabber: each frame its own draws
                res = render(self.world, seed=seed, noise=self.noise, **self.render_kw)
                self.renders += 1
                image = res.image
            else:
                res = self._noise_free()
                sigma = self.world.cell.simulation.image.noise_gray
                if self.noise and sigma > 0:
                    noisy = res.image + np.random.default_rng(seed).normal(0.0, sigma, res.image.shape)
                    image = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
                else:
                    image = res.image.copy()
            self.last_seed, self.last_render, self.last_tick = seed, res, k
            return image, t_k


class Attachment:
    """The ``sim`` scheme bound to one world; ``detach()`` (or leaving the ``with``) restores the
    previous binding."""

    def __init__(self, world: SimWorld, **defaults):
        self.world = world
        self.defaults = defaults
        self.cameras: list[SimCamera] = []
        self._registered = self._factory  # one bound method object, so unregistering finds it
        self._previous = register_source("sim", self._registered)
        self._attached = True

    def _factory(self, url: GrabberUrl) -> SimCamera:
        cam = SimCamera.from_url(self.world, url, **self.defaults)
        self.cameras.append(cam)
        return cam

    def detach(self) -> None:
        if not self._attached:
            return
        self._attached = False
        if self._previous is not None:
            register_source("sim", self._previous)
        else:
            unregister_source("sim", self._registered)

    def __enter__(self) -> "Attachment":
        return self

    def __exit__(self, *exc) -> None:
        self.detach()


def attach_world(world: SimWorld, **defaults) -> Attachment:
    """Make ``sim://`` URLs render ``world`` (``defaults``: SimCamera settings the URL may override).
    Returns the attachment; its ``cameras`` lists the cameras opened through it."""
    return Attachment(world, **defaults)
