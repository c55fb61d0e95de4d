"""The V4L2 side without a grabber card: ioctl request numbers, structure layouts, URL parsing, clear
failures on a missing or wrong device node, and the raw-buffer-to-grey path."""

from __future__ import annotations

import ctypes
import dataclasses
import errno
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from selfview.drivers.frame_grabber_v4l2 import FrameGrabber, V4L2Device, parse_grabber_url
from selfview.drivers.frame_grabber_v4l2 import v4l2
from selfview.drivers.frame_grabber_v4l2.capture import V4L2Source
from selfview.errors import ConfigError, DeviceError, ImageError

# The values <linux/videodev2.h> gives on x86-64 / arm64 (printed by a C program including it).
KERNEL = {
    "VIDIOC_QUERYCAP": 0x80685600,
    "VIDIOC_G_STD": 0x80085617,
    "VIDIOC_S_STD": 0x40085618,
    "VIDIOC_ENUMINPUT": 0xC050561A,
    "VIDIOC_G_INPUT": 0x80045626,
    "VIDIOC_S_INPUT": 0xC0045627,
    "VIDIOC_QUERYSTD": 0x8008563F,
    "VIDIOC_G_FMT": 0xC0D05604,
    "VIDIOC_QUERYBUF": 0xC0585609,
    "VIDIOC_G_CTRL": 0xC008561B,
    "VIDIOC_G_SELECTION": 0xC040565E,
    "VIDIOC_S_SELECTION": 0xC040565F,
}


def test_ioctl_numbers_match_the_kernel_header():
    for name, value in KERNEL.items():
        assert getattr(v4l2, name) == value, name
    assert ctypes.sizeof(v4l2.v4l2_input) == 80 and v4l2.v4l2_input.status.offset == 56
    assert v4l2.v4l2_input.std.offset == 48
    assert ctypes.sizeof(v4l2.v4l2_capability) == 104
    assert ctypes.sizeof(v4l2.v4l2_format) == 208 and v4l2.v4l2_format.fmt.offset == 8
    assert ctypes.sizeof(v4l2.v4l2_buffer) == 88
    assert (v4l2.v4l2_buffer.timestamp.offset, v4l2.v4l2_buffer.sequence.offset, v4l2.v4l2_buffer.m.offset,
            v4l2.v4l2_buffer.length.offset) == (24, 56, 64, 72)


def test_ioc_encoding_and_ranges():
    assert v4l2.IOC(0, "V", 0, 0) == ord("V") << 8
    assert v4l2.IOWR("V", 39, ctypes.c_int) == (3 << 30) | (4 << 16) | (ord("V") << 8) | 39
    with pytest.raises(ValueError):
        v4l2.IOC(4, "V", 0, 0)
    with pytest.raises(ValueError):
        v4l2.IOC(1, "V", 256, 0)
    with pytest.raises(ValueError):
        v4l2.IOC(1, "V", 0, 1 << 14)


HEADER = Path("/usr/include/linux/videodev2.h")


@pytest.mark.skipif(shutil.which("cc") is None or not HEADER.is_file(), reason="needs a C compiler and kernel headers")
def test_ioctl_numbers_against_a_compiled_header(tmp_path):
    names = list(KERNEL) + ["V4L2_STD_PAL", "V4L2_STD_NTSC", "V4L2_STD_SECAM"]
    src = tmp_path / "v.c"
    src.write_text(
        "#include <stdio.h>\n#include <linux/videodev2.h>\nint main(void){\n"
        + "".join(f'printf("%llu\\n", (unsigned long long){n});\n' for n in names)
        + "return 0;}\n"
    )
    exe = tmp_path / "v"
    subprocess.run(["cc", str(src), "-o", str(exe)], check=True, capture_output=True, timeout=60)
    out = [int(x) for x in subprocess.run([str(exe)], check=True, capture_output=True, text=True, timeout=10).stdout.split()]
    from selfview.drivers.frame_grabber_v4l2 import STANDARDS

    ours = [getattr(v4l2, n) for n in KERNEL] + [STANDARDS["pal"], STANDARDS["ntsc"], STANDARDS["secam"]]
    assert out == ours


def test_v4l2_url_defaults_and_settings():
    u = parse_grabber_url("v4l2:///dev/video0")
    assert (u.path, u.input, u.std, u.width, u.height, u.fourcc, u.buffers) == (
        "/dev/video0", None, 0xFF, 768, 576, "GREY", 2)
    u = parse_grabber_url("v4l2:///dev/video2?input=1&std=ntsc&width=640&height=480&format=YUYV&buffers=1")
    assert (u.input, u.std, u.width, u.height, u.fourcc, u.buffers) == (1, 0xB000, 640, 480, "YUYV", 1)
    assert parse_grabber_url("v4l2:///dev/video0?std=0x000000ff").std == 0xFF


def test_recorded_and_registered_urls():
    u = parse_grabber_url("frames:///data/run/img_%03d.png?loop=1&fps=12.5")
    assert (u.scheme, u.path, u.loop, u.fps) == ("frames", "/data/run/img_%03d.png", True, 12.5)
    assert parse_grabber_url("frames:rel/img_%d.png").path == "rel/img_%d.png"
    u = parse_grabber_url("file:///data/run.avi")
    assert (u.scheme, u.path, u.loop, u.fps) == ("file", "/data/run.avi", False, None)
    u = parse_grabber_url("sim://?fps=25&seed=3")
    assert (u.scheme, u.path, u.params) == ("sim", "", {"fps": "25", "seed": "3"})


@pytest.mark.parametrize(
    "url, match",
    [
        ("/dev/video0", "expected SCHEME"),
        ("v4l2:///dev/video0?norm=pal", "unknown parameter"),
        ("v4l2:///dev/video0?std=hd", "std='hd'"),
        ("v4l2:///dev/video0?width=10", "out of range"),
        ("v4l2:///dev/video0?input=x", "not a whole number"),
        ("v4l2:///dev/video0?format=GRAY8", "fourcc"),
        ("v4l2:///dev/video0?buffers=3", "out of range"),
        ("v4l2://video0", "device path"),
        ("v4l2://", "missing the path"),
        ("frames:///data/img.png", "printf number"),
        ("frames:///data/run_%02d/img.png", "printf number in its file name"),
        ("frames:///data/img_%03d_%03d.png", "one printf number"),
        ("frames:///data/100%_%03d.png", "no other '%'"),
        ("frames:///data/img_%03d.png?loop=yes", "loop"),
        ("file:///data/x.avi?fps=0", "out of range"),
    ],
)
def test_bad_urls_name_the_problem(url, match):
    with pytest.raises(ConfigError, match=match):
        parse_grabber_url(url)


def test_missing_device_fails_clearly():
    g = FrameGrabber("v4l2:///dev/video-selfview-missing?input=1&std=pal")
    with pytest.raises(DeviceError, match="no such video device"):
        g.connect()
    assert g.source is None
    with pytest.raises(DeviceError, match="before connect"):
        g.grab()


def test_a_node_that_is_not_v4l2_fails_clearly():
    with pytest.raises(DeviceError, match="not a V4L2 device"):
        FrameGrabber("v4l2:///dev/null").connect()
    with V4L2Device("/dev/null") as dev:  # the ioctls run for real and their errno is translated
        assert dev.query_std() is None  # ENOTTY: the driver cannot tell
        assert dev.input_status() is None
        with pytest.raises(DeviceError, match="VIDIOC_S_INPUT"):
            dev.set_input(1)
        with pytest.raises(ConfigError, match="no analogue video standards"):
            dev.set_std(0xFF)
    with pytest.raises(DeviceError, match="closed device"):
        dev.set_input(0)


def test_signal_check_translation(monkeypatch):
    dev = V4L2Device("/dev/video9")
    monkeypatch.setattr(dev, "query_std", lambda: 0)
    monkeypatch.setattr(dev, "input_status", lambda: None)  # a driver that tells no input status
    with pytest.raises(DeviceError, match="no video signal"):
        dev.check_signal(0xFF)
    monkeypatch.setattr(dev, "query_std", lambda: 0xB000)
    monkeypatch.setattr(dev, "input_status", lambda: 0)
    with pytest.raises(DeviceError, match="NTSC, but PAL"):
        dev.check_signal(0xFF)
    monkeypatch.setattr(dev, "query_std", lambda: 0x10)  # PAL-I
    dev.check_signal(0xFF)
    monkeypatch.setattr(dev, "input_status", lambda: v4l2.V4L2_IN_ST_NO_SIGNAL)
    with pytest.raises(DeviceError, match="status 0x2"):
        dev.check_signal(0xFF)


def test_no_lock_no_signal_and_no_power_are_told_apart(monkeypatch):
    dev = V4L2Device("/dev/video9")
    monkeypatch.setattr(dev, "query_std", lambda: 0)  # a card that finds no standard in all three cases
    for status, message in ((v4l2.V4L2_IN_ST_NO_H_LOCK, "a signal but no lock"), (v4l2.V4L2_IN_ST_NO_SIGNAL,
                            "no video signal"), (v4l2.V4L2_IN_ST_NO_POWER, "no power")):
        monkeypatch.setattr(dev, "input_status", lambda status=status: status)
        with pytest.raises(DeviceError, match=message):
            dev.check_signal(0xFF)


def test_a_frame_from_a_lost_signal_is_a_device_error(monkeypatch):
    src = V4L2Source(parse_grabber_url("v4l2:///dev/video0?width=16&height=16"))
    monkeypatch.setattr(src.device, "buffers", lambda: (2, v4l2.V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC))
    monkeypatch.setattr(src.device, "input_status", lambda: v4l2.V4L2_IN_ST_NO_SIGNAL)
    monkeypatch.setattr(src.device, "check_orientation", lambda: None)
    import time

    src._cap = FakeCapture([(time.monotonic(), 61)], 16, 16)  # a noise frame, delivered as if good
    with pytest.raises(DeviceError, match="no video signal"):
        src.read(1.0)


def test_an_unplugged_grabber_is_no_such_device(monkeypatch):
    def gone(*a, **k):
        raise OSError(errno.ENODEV, "No such device")

    with V4L2Device("/dev/null") as dev:
        monkeypatch.setattr(v4l2.fcntl, "ioctl", gone)
        with pytest.raises(DeviceError, match="no such device .*unplugged.*VIDIOC_QUERYSTD"):
            dev.query_std()


def test_a_525_line_standard_at_576_lines_is_refused():
    with pytest.raises(ConfigError, match="NTSC has 480 active lines, but height=576"):
        V4L2Source(parse_grabber_url("v4l2:///dev/video0?std=ntsc"))
    assert V4L2Source(parse_grabber_url("v4l2:///dev/video0?std=ntsc&width=640&height=480")).frame_period_s == 1 / 30


@pytest.mark.parametrize(
    "status, hflip, vflip, error",
    [(0, 0, 0, None), (0, 1, 0, "mirrored left to right.*horizontal_flip"), (0, 0, 1, "upside down"),
     (v4l2.V4L2_IN_ST_HFLIP, 0, 0, "mirrored.*source sends it flipped"), (v4l2.V4L2_IN_ST_HFLIP, 1, 0, None),
     (0, None, None, None)],
)
def test_a_mirrored_or_upside_down_stream_is_refused(monkeypatch, status, hflip, vflip, error):
    dev = V4L2Device("/dev/video9")
    monkeypatch.setattr(dev, "input_status", lambda: status)
    monkeypatch.setattr(dev, "control", lambda cid: {v4l2.V4L2_CID_HFLIP: hflip, v4l2.V4L2_CID_VFLIP: vflip}[cid])
    if error is None:
        dev.check_orientation()
    else:
        with pytest.raises(DeviceError, match=error):
            dev.check_orientation()


class FakeSelection:
    """A card's crop and compose rectangles; ``keep`` rectangles it will not change."""

    def __init__(self, fmt, crop_default, compose, keep=()):
        self.fmt = fmt
        self.rects = {v4l2.V4L2_SEL_TGT_CROP_DEFAULT: crop_default, v4l2.V4L2_SEL_TGT_CROP: (0, 0, 640, 480),
                      v4l2.V4L2_SEL_TGT_COMPOSE: compose}
        self.keep = keep

    def install(self, monkeypatch, dev):
        monkeypatch.setattr(dev, "format", lambda: self.fmt)
        monkeypatch.setattr(dev, "selection", lambda target: self.rects[target])

        def set_selection(target, rect):
            if target not in self.keep:
                self.rects[target] = rect
            return self.rects[target]

        monkeypatch.setattr(dev, "set_selection", set_selection)


def test_crop_and_compose_are_set_to_the_whole_picture(monkeypatch):
    dev = V4L2Device("/dev/video9")
    card = FakeSelection((768, 576, "GREY"), (0, 0, 720, 576), (0, 0, 640, 480))  # OpenCV's 640x480 left over
    card.install(monkeypatch, dev)
    dev.whole_picture(768, 576)
    assert card.rects[v4l2.V4L2_SEL_TGT_COMPOSE] == (0, 0, 768, 576)
    assert card.rects[v4l2.V4L2_SEL_TGT_CROP] == (0, 0, 720, 576)
    card = FakeSelection((768, 576, "GREY"), (0, 0, 720, 576), (0, 0, 640, 480), keep={v4l2.V4L2_SEL_TGT_COMPOSE})
    card.install(monkeypatch, dev)
    with pytest.raises(ConfigError, match="composes the picture into 640x480 at \\(0, 0\\) of the 768x576 frame"):
        dev.whole_picture(768, 576)
    card = FakeSelection((768, 576, "GREY"), (0, 0, 720, 576), (0, 0, 768, 576), keep={v4l2.V4L2_SEL_TGT_CROP})
    card.install(monkeypatch, dev)
    with pytest.raises(ConfigError, match="crops the picture to 640x480"):
        dev.whole_picture(768, 576)
    card = FakeSelection((640, 480, "GREY"), (0, 0, 720, 576), (0, 0, 640, 480))
    card.install(monkeypatch, dev)
    with pytest.raises(ConfigError, match="format is 640x480, not 768x576"):
        dev.whole_picture(768, 576)


def test_errno_of_a_busy_device(monkeypatch):
    def busy(*a, **k):
        raise OSError(errno.EBUSY, "Device or resource busy")

    monkeypatch.setattr(v4l2.os, "open", busy)
    with pytest.raises(DeviceError, match="busy"):
        V4L2Device("/dev/video0").open()


def test_raw_buffers_become_grey():
    # OpenCV hands the raw buffer over (CONVERT_RGB=0) as one row of bytes; tiny frames for the test
    src = V4L2Source(parse_grabber_url("v4l2:///dev/video0"))
    base = src.url
    src.url = dataclasses.replace(base, width=4, height=2)
    raw = np.array([[1, 2, 3, 4, 0, 0, 5, 6, 7, 8, 0, 0]], np.uint8)  # rows padded to 6 bytes
    assert np.array_equal(src._grey_from_raw(raw), [[1, 2, 3, 4], [5, 6, 7, 8]])
    with pytest.raises(ImageError, match="bytes"):
        src._grey_from_raw(np.zeros((1, 5), np.uint8))
    src.url = dataclasses.replace(base, width=4, height=1, fourcc="YUYV")  # Y0 U Y1 V: luma at even bytes
    assert np.array_equal(src._grey_from_raw(np.array([[10, 99, 11, 98, 12, 97, 13, 96]], np.uint8)), [[10, 11, 12, 13]])
    src.url = dataclasses.replace(base, width=2, height=1, fourcc="UYVY")  # U Y0 V Y1: luma at odd bytes
    assert np.array_equal(src._grey_from_raw(np.array([[99, 20, 98, 21]], np.uint8)), [[20, 21]])


def test_formats_that_need_colour_conversion_are_refused():
    with pytest.raises(ConfigError, match="MJPG"):
        FrameGrabber("v4l2:///dev/video0?format=MJPG").connect()


# --- frame stamps and the std range --------------------------------------------------------------------
@pytest.mark.parametrize("std", ["0", "0x10000000000000000", "-1", "-0xff"])
def test_std_numbers_outside_a_v4l2_std_id_are_refused(std):
    with pytest.raises(ConfigError, match="not a v4l2_std_id"):
        parse_grabber_url(f"v4l2:///dev/video0?std={std}")
    assert parse_grabber_url("v4l2:///dev/video0?std=0xffffffffffffffff").std == (1 << 64) - 1  # the largest


@pytest.mark.parametrize("alias, right", [("Y800", "GREY"), ("YUY2", "YUYV"), ("y800", "GREY"), ("HDYC", "UYVY")])
def test_windows_fourcc_names_are_refused_with_the_v4l2_name(alias, right):
    with pytest.raises(ConfigError, match=f"not a V4L2 fourcc.*use format={right}"):
        parse_grabber_url(f"v4l2:///dev/video0?format={alias}")
    assert parse_grabber_url(f"v4l2:///dev/video0?format={right}").fourcc == right


def test_exposure_start_from_the_buffer_timestamp():
    from selfview.drivers.frame_grabber_v4l2.capture import exposure_start

    kw = dict(buffer_s=0.04, frame_period_s=0.04, buffers=2)
    # V4L2's default (and bttv's): the timestamp is the END of the frame, one frame period after its start
    assert exposure_start(100.0, 100.01, tstamp="end", **kw) == pytest.approx(99.96, abs=1e-12)
    assert exposure_start(100.0, 100.01, tstamp=None, **kw) == pytest.approx(99.96, abs=1e-12)
    assert exposure_start(100.0, 100.01, tstamp="start", **kw) == 100.0
    # not a monotonic time: as old as a frame can be (waited in both buffers, plus its own duration)
    assert exposure_start(5e9, 100.0, tstamp="end", **kw) == pytest.approx(100.0 - 0.12 - 0.04, abs=1e-12)
    assert exposure_start(float("nan"), 100.0, tstamp="end", **kw) == pytest.approx(99.84, abs=1e-12)
    # a real clock's slop: an end-of-frame stamp up to one frame period after the read is the read time
    assert exposure_start(100.033, 100.0, tstamp="end", **kw) == pytest.approx(99.96, abs=1e-12)
    assert exposure_start(100.05, 100.0, tstamp="end", **kw) == pytest.approx(99.84, abs=1e-12)  # beyond it
    assert exposure_start(0.0, 100.0, tstamp="end", **kw) == pytest.approx(99.84, abs=1e-12)  # not stamped
    # a frame that waited long in its buffer keeps its own (old) time, never a younger guess
    assert exposure_start(90.0, 100.0, tstamp="start", **kw) == 90.0


class FakeCapture:
    """OpenCV's capture as V4L2Source uses it: raw buffers, and the buffer timestamp in ms."""

    def __init__(self, frames, width, height):
        self.frames = list(frames)  # [(timestamp s, grey level)]
        self.size = (height, width)
        self.ts = 0.0

    def read(self):
        ts, level = self.frames.pop(0)
        self.ts = ts
        return True, np.full((1, self.size[0] * self.size[1]), level, np.uint8)

    def get(self, prop):
        import cv2

        assert prop == cv2.CAP_PROP_POS_MSEC
        return self.ts * 1000.0

    def release(self):
        pass


def good_stream(monkeypatch, src):
    """The per-frame checks of a node that is not open: a locked signal, an upright picture."""
    monkeypatch.setattr(src.device, "check_signal", lambda std: None)
    monkeypatch.setattr(src.device, "check_orientation", lambda: None)


def test_gaps_between_buffer_timestamps_count_the_lost_frames(monkeypatch):
    import time

    src = V4L2Source(parse_grabber_url("v4l2:///dev/video0?width=16&height=16"))
    monkeypatch.setattr(src.device, "buffers", lambda: (2, v4l2.V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC))
    good_stream(monkeypatch, src)
    t = time.monotonic() - 1.0
    src._cap = FakeCapture([(t, 50), (t + 0.04, 50), (t + 0.161, 50), (t + 0.2, 50)], 16, 16)
    for _ in range(4):
        src.read(1.0)
    assert src.lost_frames == 2  # 0.121 s between the second and the third: two frames never came


def test_a_frame_ending_after_settling_but_exposed_before_is_dropped(monkeypatch):
    """A frame whose END-of-frame stamp lies after the moment the robot settled was still
    exposed (mostly) before it: dropped; the next one, exposed entirely after, is taken."""
    import time

    g = FrameGrabber("v4l2:///dev/video0?width=16&height=16", black_level=None, saturation_level=None)
    src = V4L2Source(g.url)
    monkeypatch.setattr(src.device, "buffers", lambda: (2, v4l2.V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC))  # EOF stamps
    good_stream(monkeypatch, src)
    settled = time.monotonic() - 0.5
    src._cap = FakeCapture([(settled + 0.005, 10), (settled + 0.045, 20), (settled + 0.085, 30)], 16, 16)
    g.source = src
    f = g.grab(after=settled)
    # the first frame ended 5 ms after settling: exposed from 35 ms before; the second ended 45 ms after,
    # so it started 5 ms after settling
    assert g.dropped_last == 1 and int(f.image[0, 0]) == 20
    assert f.timestamp == pytest.approx(settled + 0.005, abs=1e-6)
    assert src.tstamp == "end" and src.buffers == 2


def test_start_of_exposure_stamps_are_taken_as_they_are(monkeypatch):
    import time

    g = FrameGrabber("v4l2:///dev/video0?width=16&height=16&buffers=1", black_level=None, saturation_level=None)
    src = V4L2Source(g.url)
    flags = v4l2.V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC | v4l2.V4L2_BUF_FLAG_TSTAMP_SRC_SOE
    monkeypatch.setattr(src.device, "buffers", lambda: (2, flags))  # bttv: at least 2, whatever was asked
    good_stream(monkeypatch, src)
    settled = time.monotonic() - 0.5
    src._cap = FakeCapture([(settled + 0.005, 10)], 16, 16)
    g.source = src
    f = g.grab(after=settled)
    assert g.dropped_last == 0 and f.timestamp == pytest.approx(settled + 0.005, abs=1e-6)
    assert src.tstamp == "start" and src.buffers == 2  # the count read back, not the one asked for


@pytest.mark.parametrize(
    "field, height, buffer_s, error",
    [
        (4, 576, 0.04, None),  # INTERLACED: both fields, one frame period
        (8, 576, 0.04, None),  # INTERLACED_TB
        (1, 576, 0.04, None),  # NONE: progressive frames
        (7, 288, 0.02, None),  # ALTERNATE: one field per buffer
        (7, 576, None, "at most 288 lines"),
        (2, 576, None, "at most 288 lines"),
        (0, 576, None, "ANY"),
        (42, 576, None, "42"),
    ],
)
def test_field_order_is_read_and_checked(monkeypatch, field, height, buffer_s, error):
    src = V4L2Source(parse_grabber_url(f"v4l2:///dev/video0?height={height}"))
    monkeypatch.setattr(src.device, "field_order", lambda: field)
    if error is None:
        src._check_field()
        assert src.buffer_s == pytest.approx(buffer_s, abs=1e-12)
    else:
        with pytest.raises((ConfigError, DeviceError), match=error):
            src._check_field()


def test_field_order_and_buffers_on_a_node_that_is_not_v4l2():
    with V4L2Device("/dev/null") as dev:
        assert dev.field_order() is None and dev.buffers() == (0, None)


def test_the_devices_lock_is_released_on_close_and_on_a_failed_open_whoever_holds_the_source(monkeypatch):
    """The lock went with the source object's collection, so a failing test (or a lab script's saved error),
    whose traceback still held the source, left the device 'in use' by its own process: the next
    ``FrameGrabber`` was refused with DeviceBusy (seen in the VM stage under load). It is released by
    ``close`` and by a failed ``connect``, whoever still holds the source."""
    from selfview.drivers._ownership import DeviceLock

    monkeypatch.setattr(V4L2Source, "open", lambda self: None)
    monkeypatch.setattr(V4L2Source, "close", lambda self: None)
    url, lock = "v4l2:///dev/video9", lambda: DeviceLock.for_path("frame grabber", "/dev/video9")
    g = FrameGrabber(url)
    kept = g.connect().source  # as a traceback's frame keeps it
    with pytest.raises(DeviceError, match="in use"):
        lock().acquire()
    g.close()
    lock().acquire().release()

    def fails(self):
        raise DeviceError("/dev/video9: no such device")

    monkeypatch.setattr(V4L2Source, "open", fails)
    with pytest.raises(DeviceError, match="no such device") as err:
        FrameGrabber(url).connect()
    assert err.value.__traceback__ is not None and kept is not None
    lock().acquire().release()
