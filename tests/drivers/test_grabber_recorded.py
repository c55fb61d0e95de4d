"""The grabber's capture path for real: OpenCV reading PNG sequences and a video file OpenCV wrote;
averaging, fields, frames taken after a moment, and the checks (size, black, saturated)."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from selfview.drivers.frame_grabber_v4l2 import (
    EndOfStream,
    FrameGrabber,
    field_image,
    register_source,
    unregister_source,
)
from selfview.errors import ConfigError, DeviceError, DeviceTimeout, ImageError

H, W = 120, 160


def pictures(n: int, seed: int = 0) -> list[np.ndarray]:
    """Distinct mid-grey pictures: a gradient plus a moving square plus noise."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:H, 0:W]
    out = []
    for k in range(n):
        img = 60 + 0.5 * u + 0.3 * v + rng.normal(0, 5, (H, W))
        img[20:40, 10 + 10 * k : 30 + 10 * k] = 220
        out.append(np.clip(np.rint(img), 0, 255).astype(np.uint8))
    return out


@pytest.fixture
def sequence(tmp_path):
    imgs = pictures(5)
    for i, im in enumerate(imgs):
        assert cv2.imwrite(str(tmp_path / f"img_{i:03d}.png"), im)
    return f"frames://{tmp_path}/img_%03d.png", imgs


def test_png_sequence_frame_by_frame(sequence):
    url, imgs = sequence
    with FrameGrabber(url) as g:
        for k in range(5):
            f = g.grab()
            assert f.image.dtype == np.uint8 and f.image.shape == (H, W)
            assert np.array_equal(f.image, imgs[k]) and f.index == k and f.count == 1 and f.field is None
        with pytest.raises(EndOfStream, match="after 5"):
            g.grab()


def test_loop_starts_over(sequence):
    url, imgs = sequence
    with FrameGrabber(url + "?loop=1") as g:
        frames = [g.grab() for _ in range(7)]
    assert np.array_equal(frames[5].image, imgs[0]) and np.array_equal(frames[6].image, imgs[1])
    assert [f.index for f in frames] == list(range(7))


def test_average(sequence):
    url, imgs = sequence
    with FrameGrabber(url) as g:
        g.grab()
        f = g.grab(average=3)
    expected = np.rint((imgs[1].astype(float) + imgs[2] + imgs[3]) / 3)
    assert np.array_equal(f.image, expected.astype(np.uint8)) and f.index == 1 and f.count == 3


def test_field_keeps_its_rows_and_interpolates_the_others(sequence):
    url, imgs = sequence
    with FrameGrabber(url) as g:
        even = g.grab(field=True)
        odd = g.grab(field="odd")
    assert even.field == "even" and odd.field == "odd"
    assert np.array_equal(even.image[0::2], imgs[0][0::2])
    mid = np.rint((imgs[0][0:-2:2].astype(float) + imgs[0][2::2]) / 2)
    assert np.array_equal(even.image[1:-1:2], mid)
    assert np.array_equal(even.image[-1], imgs[0][-2])  # last odd row: copied from the row above
    assert np.array_equal(odd.image[1::2], imgs[1][1::2])
    assert np.array_equal(odd.image[0], imgs[1][1])
    assert np.array_equal(field_image(imgs[2], "odd")[1::2], imgs[2][1::2])


def test_colour_pictures_are_read_as_grey(tmp_path):
    img = pictures(1)[0]
    bgr = np.dstack([img, np.roll(img, 3, axis=1), 255 - img])
    cv2.imwrite(str(tmp_path / "c_0.png"), bgr)
    with FrameGrabber(f"frames://{tmp_path}/c_%d.png") as g:
        f = g.grab()
    assert f.image.ndim == 2 and np.array_equal(f.image, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))


def test_video_file_written_by_opencv(tmp_path):
    imgs = pictures(4, seed=1)
    path = tmp_path / "run.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 25.0, (W, H), isColor=False)
    assert writer.isOpened(), "OpenCV's FFmpeg writer is missing"
    for im in imgs:
        writer.write(im)
    writer.release()
    with FrameGrabber(f"file://{path}", width=W, height=H) as g:
        got = [g.grab().image for _ in range(4)]
        with pytest.raises(EndOfStream):
            g.grab()
    assert all(np.array_equal(a, b) for a, b in zip(got, imgs))  # FFV1 is lossless


def test_paced_recording_and_frames_after_a_moment(sequence):
    url, imgs = sequence
    with FrameGrabber(url + "?fps=50&loop=1") as g:
        f0 = g.grab()
        f1 = g.grab()
        assert f1.timestamp - f0.timestamp >= 0.02 - 1e-9  # released at 50 frames/s
        moment = time.monotonic() + 0.05  # e.g. when the robot will have settled
        f = g.grab(after=moment)
        assert f.timestamp > moment and time.monotonic() >= moment


class StaleSource:
    """A grabber whose buffers hold frames exposed 10 s ago (a card repeating old buffers), the first
    ``stale`` of them, or all of them if None; then fresh ones."""

    description = "stale"
    frame_period_s = 0.01

    def __init__(self, url, stale: int | None = None):
        self.stale = stale
        self.reads = 0

    def open(self):
        pass

    def read(self, timeout_s):
        time.sleep(0.01)
        self.reads += 1
        old = self.stale is None or self.reads <= self.stale
        return np.full((H, W), 128, np.uint8), time.monotonic() - (10.0 if old else 0.0)

    def close(self):
        pass


def test_buffered_frames_are_dropped():
    with FrameGrabber("stale://", sources={"stale": lambda url: StaleSource(url, stale=3)}) as g:
        moment = time.monotonic()
        f = g.grab(after=moment)
        assert f.timestamp > moment and f.index == 3 and g.dropped_last == 3


def test_stale_frames_are_dropped_until_the_timeout():
    with FrameGrabber("stale://", timeout_s=0.2, sources={"stale": StaleSource}) as g:
        assert g.grab().index == 0  # without 'after' any frame will do
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout):
            g.grab(after=time.monotonic())
        assert time.monotonic() - t0 < 2.0  # its timeout (0.2 s), not forever
        assert g.source.reads > 2  # it did keep reading meanwhile


def test_registry_and_unknown_schemes():
    with pytest.raises(ConfigError, match="no frame source for scheme 'stale'"):
        FrameGrabber("stale://").connect()
    register_source("stale", StaleSource)
    try:
        with FrameGrabber("stale://") as g:
            assert g.grab().image.shape == (H, W)
    finally:
        unregister_source("stale")
    with pytest.raises(ConfigError, match="attach_world"):
        FrameGrabber("sim://").connect()
    with pytest.raises(ConfigError, match="built in"):
        register_source("v4l2", StaleSource)


def test_black_saturated_and_wrong_size(tmp_path):
    black = np.full((H, W), 3, np.uint8)
    black[0, :5] = 200  # a few bright pixels do not make a picture
    bright = np.full((H, W), 255, np.uint8)
    bright[: H // 2] = 100
    for name, im in (("black", black), ("bright", bright)):
        cv2.imwrite(str(tmp_path / f"{name}_0.png"), im)
    with FrameGrabber(f"frames://{tmp_path}/black_%d.png") as g:
        with pytest.raises(ImageError, match="black frame"):
            g.grab()
    with FrameGrabber(f"frames://{tmp_path}/bright_%d.png") as g:
        with pytest.raises(ImageError, match="saturated frame"):
            g.grab()
    with FrameGrabber(f"frames://{tmp_path}/bright_%d.png", saturation_level=None, black_level=None) as g:
        assert g.grab().image.max() == 255  # checks off
    with FrameGrabber(f"frames://{tmp_path}/black_%d.png", black_level=None, width=768, height=576) as g:
        with pytest.raises(ImageError, match="160x120, expected 768x576"):
            g.grab()


def test_missing_recordings_fail_clearly(tmp_path):
    with pytest.raises(DeviceError, match="does not exist"):
        FrameGrabber(f"frames://{tmp_path}/nothere/img_%03d.png").connect()
    with pytest.raises(DeviceError, match="no image matches"):
        FrameGrabber(f"frames://{tmp_path}/img_%03d.png").connect()
    with pytest.raises(DeviceError, match="does not exist"):
        FrameGrabber(f"file://{tmp_path}/run.avi").connect()
    (tmp_path / "junk.avi").write_bytes(b"not a video" * 100)
    with pytest.raises(DeviceError, match="cannot"):
        FrameGrabber(f"file://{tmp_path}/junk.avi").connect()


def test_bad_grab_arguments(sequence):
    url, _ = sequence
    with pytest.raises(ConfigError):
        FrameGrabber(url, timeout_s=0)
    for kw in ({"timeout_s": float("inf")}, {"timeout_s": float("nan")}, {"width": -768}, {"height": "576"},
               {"width": 768.0}):
        with pytest.raises(ConfigError, match=f"frame grabber {next(iter(kw))}="):
            FrameGrabber(url, **kw)
    with pytest.raises(ConfigError):
        FrameGrabber(url, black_level=300)
    with FrameGrabber(url) as g:
        for kw in ({"average": 0}, {"average": 2.0}, {"field": "top"}, {"field": True, "average": 2}):
            with pytest.raises(ConfigError):
                g.grab(**kw)
        g.close()
        g.close()
        with pytest.raises(DeviceError, match="before connect"):
            g.grab()


def test_a_sequence_runs_from_its_smallest_index_to_the_first_gap(tmp_path):
    """The numbered sequence is read as OpenCV's CAP_IMAGES reads it on every release: from the smallest
    index present (here 7, zero-padded), in order, ending at the first missing index."""
    imgs = pictures(4, seed=3)
    for i, idx in enumerate((7, 8, 9, 11)):
        cv2.imwrite(str(tmp_path / f"s_{idx:03d}.png"), imgs[i])
    with FrameGrabber(f"frames://{tmp_path}/s_%03d.png") as g:
        got = [g.grab().image for _ in range(3)]
        with pytest.raises(EndOfStream):
            g.grab()
    assert all(np.array_equal(a, b) for a, b in zip(got, imgs[:3]))


def test_a_frame_that_is_no_usable_picture_is_a_device_error_naming_it(tmp_path):
    """A sequence's files are read as the picture files of the rest of the project (``read_picture``): one that
    is no picture, or whose header claims a picture far beyond any camera's, stops the grab with the file's
    name, before the huge one is decoded; the frames before it were read."""
    from tests.selfview.test_io_safe import png_header_only

    imgs = pictures(1)
    for bad, why in ((b"not a picture\n", "not a usable frame"), (png_header_only(40000, 40000), "refused before decoding")):
        cv2.imwrite(str(tmp_path / "b_000.png"), imgs[0])
        (tmp_path / "b_001.png").write_bytes(bad)
        with FrameGrabber(f"frames://{tmp_path}/b_%03d.png") as g:
            assert np.array_equal(g.grab().image, imgs[0])
            with pytest.raises(DeviceError, match=rf"b_001\.png: .*{why}") as info:
                g.grab()
        assert not isinstance(info.value, EndOfStream)


def test_a_sequence_folder_that_cannot_be_listed_is_named(tmp_path, monkeypatch):
    import os

    def refuse(folder):
        raise PermissionError(13, "Permission denied", folder)

    monkeypatch.setattr(os, "listdir", refuse)
    with pytest.raises(DeviceError, match=f"cannot list the folder {tmp_path}: Permission denied"):
        FrameGrabber(f"frames://{tmp_path}/c_%03d.png").connect()
