"""The grabber's contract on a real V4L2 device named by ``SELFVIEW_GRABBER_URL`` (``-m hardware``), e.g.
``v4l2:///dev/video0?input=1&std=pal``: a lab's CCIR card, or the kernel's vivid in the vm stage. The cases
that inject faults (signal lost, no lock, dropped buffers, flips, a disconnect) use vivid's controls through
``v4l2-ctl`` and run only on vivid; the disconnect comes last, since vivid stays unplugged afterwards.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from urllib.parse import parse_qsl, urlencode

import numpy as np
import pytest

from selfview.drivers.frame_grabber_v4l2 import FrameGrabber, V4L2Device, parse_grabber_url
from selfview.drivers.frame_grabber_v4l2 import v4l2
from selfview.errors import ConfigError, DeviceError, DeviceTimeout

URL = os.environ.get("SELFVIEW_GRABBER_URL", "")
pytestmark = [pytest.mark.hardware,
              pytest.mark.skipif(not URL, reason="set SELFVIEW_GRABBER_URL to a V4L2 grabber (v4l2:///dev/videoN?...)")]
DEVICE = parse_grabber_url(URL).path if URL else ""
PERIOD = 0.04  # a CCIR frame
VIVID_DEFAULTS = {"standard_signal_mode": 0, "timestamp_source": 0, "percentage_of_dropped_buffers": 0,
                  "horizontal_flip": 0, "vertical_flip": 0, "sensor_flipped_horizontally": 0,
                  "sensor_flipped_vertically": 0, "test_pattern": 0, "osd_text_mode": 0}


def url_with(**params) -> str:
    base, _, query = URL.partition("?")
    q = dict(parse_qsl(query))
    q.update({k: str(v) for k, v in params.items() if v is not None})
    for k in [k for k, v in params.items() if v is None]:
        q.pop(k, None)
    return base + "?" + urlencode(q)


def is_vivid() -> bool:
    with V4L2Device(DEVICE) as dev:
        return dev.querycap()["driver"] == "vivid"


@pytest.fixture
def vivid():
    """vivid's fault controls, back at their defaults after the case."""
    if not is_vivid() or not shutil.which("v4l2-ctl"):
        pytest.skip("needs the kernel's vivid driver and v4l2-ctl: its controls inject the faults")
    set_controls(**VIVID_DEFAULTS)
    yield set_controls
    set_controls(**VIVID_DEFAULTS)


def set_controls(**values) -> None:
    arg = ",".join(f"{k}={int(v)}" for k, v in values.items())
    subprocess.run(["v4l2-ctl", "-d", DEVICE, "-c", arg], check=True, capture_output=True, timeout=10)


def grabber(url=None, **kw) -> FrameGrabber:
    kw.setdefault("timeout_s", 2.0)
    kw.setdefault("saturation_level", None)
    return FrameGrabber(url or URL, **kw)


def test_inputs_and_the_configured_input_and_standard():
    with V4L2Device(DEVICE) as dev:
        assert dev.querycap()["capabilities"] & 1
        assert len(dev.inputs()) >= 1
    with grabber() as g:
        f = g.grab()
        assert f.image.shape == (g.height, g.width) and f.image.dtype == np.uint8


@pytest.mark.parametrize("fmt", ["GREY", "YUYV", "UYVY"])
@pytest.mark.parametrize("width", [720, 768])
def test_formats_and_sizes_through_the_scaler(fmt, width):
    with grabber(url_with(format=fmt, width=width, height=576)) as g:
        f = g.grab()
        assert f.image.shape == (576, width)
        dev = g.source.device  # the grabber's own control node (a second opener may be refused)
        assert dev.format() == (width, 576, fmt)
        assert dev.selection(v4l2.V4L2_SEL_TGT_COMPOSE) in (None, (0, 0, width, 576))


def test_a_frame_after_an_opencv_style_open_is_the_whole_picture(vivid):
    # OpenCV's open() sets 640x480 first; the card kept that compose rectangle inside a 768x576 frame
    subprocess.run(["v4l2-ctl", "-d", DEVICE, "--set-fmt-video=width=640,height=480"], check=True,
                   capture_output=True, timeout=10)
    vivid(test_pattern=VIVID_PATTERN_WHITE, osd_text_mode=2)
    with grabber(url_with(width=768, height=576)) as g:
        img = g.grab().image
    with V4L2Device(DEVICE) as dev:
        assert dev.selection(v4l2.V4L2_SEL_TGT_COMPOSE) == (0, 0, 768, 576)
        assert dev.selection(v4l2.V4L2_SEL_TGT_CROP) == dev.selection(v4l2.V4L2_SEL_TGT_CROP_DEFAULT)
    # a white picture fills every corner of the frame (a squeezed one leaves x >= 640, y >= 480 black)
    for corner in (img[:40, :40], img[:40, -40:], img[-40:, :40], img[-40:, -40:]):
        assert float(np.median(corner)) > 150, [float(np.median(c)) for c in (img[:40, -40:], img[-40:, -40:])]


VIVID_PATTERN_WHITE = 6  # vivid's test_pattern menu item "100% White" (v4l2-ctl -L)


def test_single_fields_and_averaging():
    with grabber() as g:
        assert g.grab(field="odd").field == "odd"
        f = g.grab(average=3)
        assert f.count == 3


def test_grab_after_now_with_end_of_frame_stamps(vivid):
    vivid(timestamp_source=0)
    with grabber() as g:
        g.grab()
        src = g.source
        assert src.tstamp == "end"
        waits = []
        for _ in range(5):
            after = time.monotonic()
            f = g.grab(after=after)
            waits.append(time.monotonic() - after)
            # exposed after the moment asked for, and the first such frame (no fresh frame dropped)
            assert f.timestamp > after and f.timestamp - after < 3 * PERIOD, (f.timestamp - after, g.dropped_last)
            assert g.dropped_last <= 2
        print(f"grab(after=now), end-of-frame stamps: {[round(w * 1000) for w in waits]} ms")


def test_start_of_exposure_stamps(vivid):
    vivid(timestamp_source=1)
    with grabber() as g:
        g.grab()
        assert g.source.tstamp == "start"
        after = time.monotonic()
        f = g.grab(after=after)
        assert after < f.timestamp < after + 3 * PERIOD


def test_dropped_buffers_are_counted(vivid):
    with grabber() as g:
        g.grab()
        src = g.source
        vivid(percentage_of_dropped_buffers=50)
        before = src.lost_frames
        for _ in range(10):
            g.grab()
        assert src.lost_frames - before >= 2, (before, src.lost_frames)
        print(f"50 % dropped: {src.lost_frames - before} of about 20 frames counted lost over 10 grabs")


def test_a_fatal_streaming_error_is_a_device_error(vivid):
    with grabber(timeout_s=1.0) as g:
        g.grab()
        set_controls(inject_fatal_streaming_error=1)
        with pytest.raises(DeviceError, match="ended the stream"):  # never a good frame
            for _ in range(4):
                g.grab()


def test_every_buffer_dropped_is_a_timeout_and_the_stream_recovers(vivid):
    with grabber(timeout_s=1.0) as g:
        g.grab()
        vivid(percentage_of_dropped_buffers=100)
        with pytest.raises(DeviceTimeout):
            for _ in range(3):  # a frame already in a buffer may still come
                g.grab()
        vivid(percentage_of_dropped_buffers=0)
    with grabber() as g:
        g.grab()


@pytest.mark.parametrize("mode, message", [(1, "no video signal"), (2, "a signal but no lock")])
def test_a_signal_lost_mid_stream_is_a_device_error_at_the_next_frame(vivid, mode, message):
    with grabber() as g:
        g.grab()
        vivid(standard_signal_mode=mode)
        t0 = time.monotonic()
        with pytest.raises(DeviceError, match=message):
            g.grab()  # no good frame after the signal went
        print(f"signal mode {mode}: device error after {1000 * (time.monotonic() - t0):.0f} ms")
    with pytest.raises(DeviceError, match=message):
        grabber().connect()  # nor at open


@pytest.mark.parametrize(
    "controls, message",
    [({"horizontal_flip": 1}, "mirrored left to right"), ({"vertical_flip": 1}, "upside down"),
     ({"sensor_flipped_horizontally": 1}, "source sends it flipped")],
)
def test_a_mirrored_or_upside_down_stream_is_refused(vivid, controls, message):
    vivid(**controls)
    with pytest.raises(DeviceError, match=message):
        grabber().connect()  # at open
    vivid(**VIVID_DEFAULTS)
    with grabber() as g:  # and mid-stream
        g.grab()
        vivid(**controls)
        with pytest.raises(DeviceError, match=message):
            g.grab()


def test_a_flipped_sensor_undone_by_the_flip_control_is_upright(vivid):
    vivid(sensor_flipped_horizontally=1, horizontal_flip=1)
    with grabber() as g:
        g.grab()


def test_ntsc_at_576_lines_is_refused():
    with pytest.raises(ConfigError, match="480 active lines"):
        grabber(url_with(std="ntsc")).connect()


def test_a_standard_on_a_webcam_input_is_refused(vivid):
    with pytest.raises(ConfigError, match="no analogue video standards"):
        grabber(url_with(input=0, width=640, height=480)).connect()


def test_zz_a_disconnect_mid_stream_is_no_such_device():
    if not is_vivid() or not shutil.which("v4l2-ctl"):
        pytest.skip("needs the kernel's vivid driver and v4l2-ctl: its disconnect control unplugs it")
    set_controls(**VIVID_DEFAULTS)
    with grabber() as g:
        g.grab()
        subprocess.run(["v4l2-ctl", "-d", DEVICE, "-c", "disconnect=1"], capture_output=True, timeout=10)
        with pytest.raises(DeviceError, match="no such device"):
            for _ in range(3):
                g.grab()
