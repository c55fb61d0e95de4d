"""Frame source URLs: which grabber, recording or simulator the pictures come from.

- ``v4l2:///dev/videoN?input=1&std=pal&width=768&height=576&format=GREY&buffers=2`` - a V4L2 capture
  device (an analogue CCIR frame grabber card). ``input`` (0-based video input, default: leave as set),
  ``std`` (pal, ntsc, secam, pal-m, pal-n, pal-nc, pal-60, or a number such as 0xff; default pal),
  ``width`` x ``height`` (default 768 x 576: square pixels need a square-pixel grabber), ``format``
  (a V4L2 fourcc, default GREY; Windows names such as Y800 or YUY2 are refused with the V4L2 name), ``buffers`` (driver buffers, 1 or 2, default 2: few, so frames are fresh).
- ``frames:///dir/img_%03d.png`` - a numbered image sequence (from its smallest index to the first gap);
  ``frames:rel/dir/img_%03d.png`` is relative to the working directory. ``loop=1`` starts over at the end.
- ``file:///path/x.avi`` (or ``file:rel/x.avi``) - a video file; ``loop=1`` likewise.
- ``sim://`` - the simulated camera, supplied by whoever registered the ``sim`` scheme (see
  ``register_source``); its parameters (e.g. ``fps``, ``seed``) are the factory's to read.

Recorded sources also take ``fps`` (the nominal frame rate used to pace and time-stamp them; default:
as fast as they decode). The path is taken literally (``%`` is printf's, not a URL escape).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from urllib.parse import parse_qsl

from selfview.errors import ConfigError

__all__ = ["GrabberUrl", "parse_grabber_url", "STANDARDS", "FOURCC_ALIASES"]

#: V4L2 analogue video standards (linux/videodev2.h, v4l2_std_id bits).
STANDARDS: dict[str, int] = {
    "pal": 0x000000FF,  # PAL B/B1/G/H/I/D/D1/K: CCIR 625 lines, 25 frames/s
    "pal-m": 0x00000100,
    "pal-n": 0x00000200,
    "pal-nc": 0x00000400,
    "pal-60": 0x00000800,
    "ntsc": 0x0000B000,  # NTSC M, M-JP, M-KR
    "secam": 0x00FF0000,
}

#: Names other systems give V4L2's formats (DirectShow, FourCC.org, GStreamer): name -> the V4L2 fourcc.
FOURCC_ALIASES: dict[str, str] = {
    "Y800": "GREY",
    "Y8": "GREY",
    "GRAY": "GREY",
    "GRAY8": "GREY",
    "YUY2": "YUYV",
    "YUNV": "YUYV",
    "V422": "YUYV",
    "UYNV": "UYVY",
    "Y422": "UYVY",
    "HDYC": "UYVY",
}

_KNOWN = {
    "v4l2": {"input", "std", "width", "height", "format", "buffers"},
    "frames": {"loop", "fps"},
    "file": {"loop", "fps"},
}


@dataclass(frozen=True)
class GrabberUrl:
    """A parsed frame source URL.

    ``scheme`` ('v4l2', 'frames', 'file', or a registered one such as 'sim'), ``path`` (device, pattern
    or file), ``params`` (the raw query). For v4l2 the typed settings are filled in.
    """

    url: str
    scheme: str
    path: str = ""
    params: dict[str, str] = field(default_factory=dict)
    input: int | None = None
    std: int | None = None
    width: int | None = None
    height: int | None = None
    fourcc: str | None = None
    buffers: int | None = None
    loop: bool = False
    fps: float | None = None

    def param(self, key: str, default=None):
        return self.params.get(key, default)


def _int(url: str, key: str, text: str, lo: int, hi: int) -> int:
    try:
        v = int(text, 0)
    except ValueError:
        raise ConfigError(f"{url}: {key}={text!r} is not a whole number") from None
    if not lo <= v <= hi:
        raise ConfigError(f"{url}: {key}={v} out of range {lo}..{hi}")
    return v


def parse_std(url: str, text: str) -> int:
    """A video standard name or number -> its v4l2_std_id bits."""
    key = text.strip().lower()
    if key in STANDARDS:
        return STANDARDS[key]
    try:
        v = int(key, 0)
    except ValueError:
        raise ConfigError(f"{url}: std={text!r}; expected one of {', '.join(STANDARDS)} or a number") from None
    if not 0 < v < 1 << 64:
        raise ConfigError(f"{url}: std={text!r} is not a v4l2_std_id")
    return v


def parse_grabber_url(url: str) -> GrabberUrl:
    """Parse a frame source URL (see the module doc). Raises ConfigError naming the URL and the part."""
    if not isinstance(url, str):
        raise ConfigError(f"frame source URL {url!r}: expected text such as v4l2:///dev/video0 or sim://")
    m = re.fullmatch(r"([A-Za-z][A-Za-z0-9+.\-]*):(.*)", url, flags=re.DOTALL)
    if not m:
        raise ConfigError(
            f"frame source URL {url!r}: expected SCHEME:..., e.g. v4l2:///dev/video0?input=1&std=pal, "
            "frames:///dir/img_%03d.png, file:///dir/run.avi or sim://"
        )
    scheme, rest = m.group(1).lower(), m.group(2)
    rest, _, query = rest.partition("?")
    params = dict(parse_qsl(query, keep_blank_values=True))
    path = rest[2:] if rest.startswith("//") else rest
    if scheme not in _KNOWN:
        # a registered source (e.g. sim://) reads its own parameters
        return GrabberUrl(url=url, scheme=scheme, path=path, params=params)
    unknown = sorted(set(params) - _KNOWN[scheme])
    if unknown:
        raise ConfigError(
            f"{url}: unknown parameter(s) {', '.join(unknown)}; a {scheme} URL takes {', '.join(sorted(_KNOWN[scheme]))}"
        )
    if not path:
        raise ConfigError(f"{url}: missing the path (e.g. {scheme}:///dev/video0 or {scheme}:///dir/name)")
    kw: dict = {"url": url, "scheme": scheme, "path": path, "params": params}
    if scheme == "v4l2":
        if not path.startswith("/dev/"):
            raise ConfigError(f"{url}: expected a device path such as v4l2:///dev/video0, got {path!r}")
        kw["input"] = None if "input" not in params else _int(url, "input", params["input"], 0, 255)
        kw["std"] = parse_std(url, params.get("std", "pal"))
        kw["width"] = _int(url, "width", params.get("width", "768"), 16, 8192)
        kw["height"] = _int(url, "height", params.get("height", "576"), 16, 8192)
        fourcc = params.get("format", "GREY")
        if fourcc.upper() in FOURCC_ALIASES:
            right = FOURCC_ALIASES[fourcc.upper()]
            raise ConfigError(
                f"{url}: format={fourcc} is not a V4L2 fourcc (it is the Windows/FourCC.org name); V4L2 calls this "
                f"format {right}: use format={right}"
            )
        if len(fourcc) != 4 or not fourcc.isascii():
            raise ConfigError(f"{url}: format={fourcc!r}; expected a 4-character V4L2 fourcc such as GREY or YUYV")
        kw["fourcc"] = fourcc
        kw["buffers"] = _int(url, "buffers", params.get("buffers", "2"), 1, 2)
    else:
        if scheme == "frames":
            name = path.rsplit("/", 1)[-1]  # the sequence reader numbers the file name, never a folder
            if len(re.findall(r"%0?\d*d", name)) != 1 or "%" in re.sub(r"%0?\d*d", "", name):
                raise ConfigError(f"{url}: an image sequence needs one printf number in its file name and no other "
                                  f"'%', e.g. img_%03d.png; got {name!r}")
        loop = params.get("loop", "0")
        if loop not in ("0", "1"):
            raise ConfigError(f"{url}: loop={loop!r}; expected 0 or 1")
        kw["loop"] = loop == "1"
        if "fps" in params:
            try:
                fps = float(params["fps"])
            except ValueError:
                raise ConfigError(f"{url}: fps={params['fps']!r} is not a number") from None
            if not 0 < fps <= 10000:
                raise ConfigError(f"{url}: fps={fps} out of range (0, 10000]")
            kw["fps"] = fps
    return GrabberUrl(**kw)
