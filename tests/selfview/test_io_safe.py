"""selfview.files.io_safe: pictures checked in their header before decoding, the strict YAML reader,
and the atomic writer's refusals."""

from __future__ import annotations

import os
import struct
import zlib

import cv2
import numpy as np
import pytest

from selfview.errors import ConfigError, ImageError
from selfview.files.io_safe import atomic_write, load_yaml, picture_size, read_picture

from tests.conftest import REPO


def png_header_only(width: int, height: int, idat: bytes = b"") -> bytes:
    """A PNG whose IHDR claims width x height (8-bit grey), with a valid CRC, followed by ``idat``."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


@pytest.fixture
def grey():
    rng = np.random.default_rng(5)
    return rng.integers(0, 256, size=(37, 53), dtype=np.uint8)


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp", ".pgm", ".tif"])
def test_header_sizes_of_real_files(tmp_path, grey, ext):
    p = tmp_path / f"x{ext}"
    assert cv2.imwrite(str(p), grey)
    fmt, w, h = picture_size(p.read_bytes())
    assert (w, h) == (53, 37)
    img, sha = read_picture(p)
    assert img.shape == (37, 53) and len(sha) == 64
    if ext != ".jpg":
        assert np.array_equal(img, grey)  # lossless formats round-trip exactly


def test_colour_pictures_become_grey(tmp_path, grey):
    p = tmp_path / "c.png"
    cv2.imwrite(str(p), cv2.merge([grey, grey, grey]))
    img, _ = read_picture(p)
    assert np.array_equal(img, grey)


@pytest.mark.parametrize("ext", [".png", ".pgm", ".tif"])
@pytest.mark.parametrize("bits", [10, 12, 16])
def test_a_16_bit_picture_reads_as_its_cameras_8_bits(tmp_path, grey, ext, bits):
    """A 10-, 12- or 16-bit camera's picture in a 16-bit file (its pixels unshifted: 0..2^bits - 1) reads as the
    8-bit picture of the same light, within rounding. A 12-bit one taken as 16 bits (/257) would read 0..16 and be
    'blank'."""
    full = (1 << bits) - 1
    p = tmp_path / f"x{ext}"
    assert cv2.imwrite(str(p), np.rint(grey * (full / 255)).astype(np.uint16))
    img, _ = read_picture(p)
    assert img.dtype == np.uint8 and np.abs(img.astype(int) - grey).max() <= 1


def test_a_dim_16_bit_picture_reads_by_the_bits_its_brightest_pixel_needs(tmp_path, grey):
    """A 12-bit picture with no pixel at 2^10 or above reads as 10 bits (brighter: the measures are relative)."""
    p = tmp_path / "dim.png"
    dark = (grey // 8).astype(np.uint16) * 16  # 12-bit levels under 2^10 (at most 496): the gain of 10 bits
    assert cv2.imwrite(str(p), dark)
    assert np.abs(read_picture(p)[0].astype(int) - np.rint(dark * (255 / 1023))).max() <= 1


def test_a_huge_png_is_refused_from_its_header(tmp_path):
    small = tmp_path / "over_a_small_bound.png"  # the bound is the caller's: checked first, cheaply
    small.write_bytes(png_header_only(2000, 1000, zlib.compress(b"\0" * 1000)))
    with pytest.raises(ImageError, match="2000 x 1000 pixels.*refused before decoding"):
        read_picture(small, max_side=1500)
    with pytest.raises(ImageError, match="refused before decoding"):
        read_picture(small, max_pixels=1_000_000)
    # 30000 x 30000 pixels of zeros compress to well under a megabyte; the header is all that is read
    p = tmp_path / "bomb.png"
    p.write_bytes(png_header_only(30000, 30000, zlib.compress(b"\0" * 300_000)))
    with pytest.raises(ImageError, match=r"30000 x 30000 pixels.*refused before decoding") as e:
        read_picture(p)
    assert str(p) in str(e.value)
    p.write_bytes(png_header_only(40000, 40000))
    with pytest.raises(ImageError, match="40000 x 40000"):
        read_picture(p)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "empty"),
        (b"hello, this is text\n", "not a PNG, JPEG, BMP, PGM/PPM or TIFF"),
        (b"\x89PNG\r\n\x1a\n\0\0", "IHDR"),
        (b"\xff\xd8\xff\xe0\x00\x10JFIF", "frame header"),
        (b"P5\n# only a comment\n", "width and height"),
        (b"II*\0\xff\0\0\0", "TIFF without its width and height in its first directory"),
        (b"II+\0\x08\0\0\0", "not a PNG, JPEG, BMP, PGM/PPM or TIFF"),
    ],
    ids=["empty", "text", "png-cut", "jpeg-cut", "pgm-cut", "tiff-cut", "bigtiff"],
)
def test_unreadable_pictures_name_the_file(tmp_path, content, message):
    p = tmp_path / "bad.png"
    p.write_bytes(content)
    with pytest.raises(ImageError, match=message) as e:
        read_picture(p)
    assert str(p) in str(e.value)


def tiff(pixels: np.ndarray, order: str = ">", width: int | None = None) -> bytes:
    """An uncompressed one-strip grey TIFF of uint8 or big/little-endian uint16 ``pixels``, its directory after the
    pixels (as libtiff writes it), its ImageWidth a SHORT (``width``: what it claims) and its ImageLength a LONG."""
    h, w = pixels.shape
    data = pixels.astype(pixels.dtype.newbyteorder(order)).tobytes()
    bits, at = 8 * pixels.itemsize, 8 + len(data)
    entries = [(256, 3, width or w), (257, 4, h), (258, 3, bits), (259, 3, 1), (262, 3, 1), (273, 4, 8),
               (277, 3, 1), (278, 4, h), (279, 4, len(data))]
    ifd = struct.pack(order + "H", len(entries))
    for tag, kind, value in entries:
        ifd += struct.pack(order + "HHI", tag, kind, 1)
        ifd += struct.pack(order + ("HH" if kind == 3 else "I"), *((value, 0) if kind == 3 else (value,)))
    head = (b"MM\0*" if order == ">" else b"II*\0") + struct.pack(order + "I", at)
    return head + data + ifd + b"\0\0\0\0"


@pytest.mark.parametrize("order", [">", "<"])
def test_a_tiff_is_sized_from_its_directory_after_the_pixels(tmp_path, grey, order):
    """A TIFF (a lab camera's usual file; ``write_picture`` writes one) keeps its directory after its pixels, beyond
    the first 64 KiB of a large picture: its size is read there, in either byte order, its SHORT and LONG entries;
    12-bit pixels read as the camera's 8 bits; a header claiming 40000 px is refused before decoding, a directory
    beyond the file's end by name."""
    big = np.tile(grey, (8, 4))  # 296 x 212: 125 KB of 16-bit pixels before the directory
    p = tmp_path / "x.tif"
    p.write_bytes(tiff(np.rint(big * (4095 / 255)).astype(np.uint16), order))
    assert picture_size(p.read_bytes()) == ("TIFF", 212, 296)
    img, _ = read_picture(p)
    assert img.dtype == np.uint8 and np.abs(img.astype(int) - big).max() <= 1
    p.write_bytes(tiff(big, order, width=40000))
    with pytest.raises(ImageError, match="TIFF header says 40000 x 296 pixels.*refused before decoding"):
        read_picture(p)
    p.write_bytes(tiff(big, order)[:-100])
    with pytest.raises(ImageError, match="TIFF without its width and height"):
        read_picture(p)


def test_a_jpeg_whose_frame_header_follows_large_metadata_is_read(tmp_path, grey):
    """A camera's JPEG may carry 64 KiB segments (EXIF thumbnails, colour profiles) before its frame header: it is
    sized there (the first 64 KiB alone would call it truncated); a run of fill bytes is walked to a bound, not on."""
    buf = cv2.imencode(".jpg", grey)[1]
    meta = (b"\xff\xef" + struct.pack(">H", 65535) + bytes(65533)) * 2  # two APP15 segments of the largest size
    p = tmp_path / "meta.jpg"
    p.write_bytes(buf.tobytes()[:2] + meta + buf.tobytes()[2:])
    assert picture_size(p.read_bytes()) == ("JPEG", 53, 37)
    assert np.array_equal(read_picture(p)[0], cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE))
    p.write_bytes(b"\xff\xd8" + b"\xff" * (3 << 20))
    with pytest.raises(ImageError, match="JPEG frame header not found"):
        read_picture(p)


def test_a_truncated_picture_is_an_image_error(tmp_path, grey):
    p = tmp_path / "cut.png"
    cv2.imwrite(str(p), grey)
    p.write_bytes(p.read_bytes()[:60])
    with pytest.raises(ImageError, match="cannot decode"):
        read_picture(p)
    with pytest.raises(ImageError, match="cannot read"):
        read_picture(tmp_path / "none.png")
    with pytest.raises(ImageError, match="header says 0 x"):
        p.write_bytes(png_header_only(0, 10))
        read_picture(p)


def test_the_command_line_calibrates_from_a_12_bit_cameras_16_bit_file(cell, tmp_path, capsys):
    """A 12-bit camera's parked picture in a 16-bit PNG or TIFF (pixels 0..4095, unshifted): ``selfview calibrate``
    gives the 8-bit file's calibration (its pixels read back exactly), as ``calibrate_offline`` does given the array;
    a 16-bit file was refused, a 12-bit array taken as 16 bits would read 0..16 and be blank."""
    import json

    from selfview.estimation.offline import calibrate_offline
    from selfview.mocks.render import render
    from selfview.mocks.world import SimWorld
    from selfview.procedures.cli import main

    w = SimWorld(cell, seed=3)
    w.park()
    img = render(w, seed=1).image
    img12 = np.rint(img * (4095 / 255)).astype(np.uint16)
    C_H_G = calibrate_offline(img, cell).calibration.C_H_G
    assert np.array_equal(calibrate_offline(img12, cell).calibration.C_H_G, C_H_G)
    with pytest.raises(ImageError, match=r"shape \(576, 768, 3\); expected a 2-D grey picture \(no colour channels\)"):
        calibrate_offline(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), cell)
    docs = []
    for name, pic in (("p8.png", img), ("p16.png", img12), ("p16.tif", img12)):  # a lab camera's TIFF too
        assert cv2.imwrite(str(tmp_path / name), pic)
        assert main(["calibrate", "--image", str(tmp_path / name), "--out", str(tmp_path / f"{name}.yaml"),
                     "--json"]) == 0
        docs.append(json.loads(capsys.readouterr().out))
    assert all(d["C_H_G"] == docs[0]["C_H_G"] and d["f"] == docs[0]["f"] for d in docs[1:])


def test_cli_exit_3_for_bad_picture_files(tmp_path, capsys):
    """A file that is not a usable picture is a file fault (exit 3, the README's), with its own advice; a
    picture that shows nothing usable is a calibration fault (exit 5)."""
    from selfview.procedures.cli import EXIT_CALIBRATION, EXIT_CONFIG, main

    (tmp_path / "text.png").write_text("hello\n")
    for name, content in [("zero.png", b""), ("huge.png", png_header_only(40000, 40000)), ("missing.png", None),
                          ("text.png", None)]:
        p = tmp_path / name
        if content is not None:
            p.write_bytes(content)
        assert main(["calibrate", "--image", str(p), "--out", str(tmp_path / "cal.yaml")]) == EXIT_CONFIG
        err = capsys.readouterr().err
        assert name in err and "Traceback" not in err
        assert "give the path of a picture file" in err and "light, focus" not in err
    cv2.imwrite(str(tmp_path / "blank.png"), np.full((576, 768), 128, np.uint8))
    assert main(["calibrate", "--image", str(tmp_path / "blank.png"), "--out", str(tmp_path / "cal.yaml")]) \
        == EXIT_CALIBRATION
    assert "blank" in capsys.readouterr().err
    assert not (tmp_path / "cal.yaml").exists()


def test_yaml_reader_keeps_text_when_asked():
    assert load_yaml("a: 00001\nb: 40001.10\n", "m.yaml", text_only=True) == {"a": "00001", "b": "40001.10"}
    assert load_yaml("a: 1\n", "m.yaml") == {"a": 1}
    with pytest.raises(ConfigError, match="m.yaml.*alias"):
        load_yaml("a: &x 1\nb: *x\n", "m.yaml")


def test_atomic_write_refuses_a_folder_target(tmp_path):
    (tmp_path / "d").mkdir()
    with pytest.raises(ConfigError, match="a folder of that name"):
        atomic_write(tmp_path / "d", b"x")
    atomic_write(tmp_path / "f.txt", b"abc")
    assert (tmp_path / "f.txt").read_bytes() == b"abc"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["d", "f.txt"]


# --- files checked before they are read -----------------------------------------------------------
def test_bounded_reads_refuse_what_is_not_a_regular_file(tmp_path):
    from selfview.files.io_safe import read_bounded

    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)  # opening it to read would block until a writer came
    for path, kind in ((fifo, "a FIFO"), ("/dev/zero", "a character device"), (tmp_path, "a folder")):
        with pytest.raises(ConfigError, match=f"{path}: cannot read the cell file: it is {kind}"):
            read_bounded(path, 1000, what="cell file")
    big = tmp_path / "big.yaml"
    big.write_bytes(b"a" * 1001)
    with pytest.raises(ConfigError, match="1001 bytes, more than the 1000 accepted"):
        read_bounded(big, 1000)
    assert read_bounded(big, 1001) == b"a" * 1001
    with pytest.raises(ConfigError, match="none.yaml: no such thing"):
        read_bounded(tmp_path / "none.yaml", 10, missing="no such thing")


def test_a_bounded_read_stops_at_its_bound_on_a_file_whose_size_lies(tmp_path, monkeypatch):
    """A regular file whose size says 0 but whose reads never end (a /proc or /sys file, a FUSE mount): the
    read stops after ``limit + 1`` bytes and refuses the file, instead of reading until memory runs out."""
    from selfview.files import io_safe

    liar = tmp_path / "liar.yaml"
    liar.write_bytes(b"")
    ino, real_read, served = liar.stat().st_ino, os.read, []

    def endless(fd, n):
        if os.fstat(fd).st_ino != ino:
            return real_read(fd, n)
        served.append(n)
        if len(served) > 1000:
            raise AssertionError("the read went on past its bound")
        return b"a" * min(n, 4096)

    monkeypatch.setattr(io_safe.os, "read", endless)
    with pytest.raises(ConfigError, match="liar.yaml: cannot read the cell file: it grew beyond the 10000 bytes"):
        io_safe.read_bounded(liar, 10_000, what="cell file")
    assert sum(min(n, 4096) for n in served) == 10_001


#: Run in the child: the command line, then the peak resident memory of this program alone (VmHWM of its
#: own address space; the rusage of a forked child also counts the parent's pages from before its exec).
_CHILD = ("import atexit, runpy, sys\n"
          "def peak():\n"
          "    for line in open('/proc/self/status'):\n"
          "        if line.startswith('VmHWM:'):\n"
          "            sys.stderr.write('\\npeak-kb ' + line.split()[1] + '\\n')\n"
          "atexit.register(peak)\n"
          "sys.argv = ['selfview'] + sys.argv[1:]\n"
          "runpy.run_module('selfview.procedures.cli', run_name='__main__')\n")


def _run_limited(argv: list[str], tmp_path, timeout_s: float = 20.0):
    """(exit code, stderr, peak resident kB) of ``selfview ARGV`` in a child whose address space is capped
    (1.5 GB: a program that reads an endless file dies of MemoryError instead of taking the machine)."""
    import resource
    import subprocess
    import sys

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (1_500_000_000, 1_500_000_000))

    env = dict(os.environ, PYTHONPATH=str(REPO))
    try:
        proc = subprocess.run([sys.executable, "-c", _CHILD, *argv], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, env=env, preexec_fn=cap, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        pytest.fail(f"selfview {' '.join(argv)} still reading after {timeout_s} s")
    err = proc.stderr.decode(errors="replace")
    body, _, peak = err.rpartition("\npeak-kb ")
    assert peak, f"no peak memory reported: {err}"
    return proc.returncode, body, int(peak)


@pytest.mark.parametrize("kind", ["/dev/zero", "fifo"])
def test_endless_files_are_refused_at_the_command_line(tmp_path, kind):
    path = kind
    if kind == "fifo":
        path = str(tmp_path / "cal.yaml")
        os.mkfifo(path)
    for argv in (["track", "--calibration", path, "--image", str(tmp_path / "x.png")],
                 ["calibrate", "--cell", path, "--image", str(tmp_path / "x.png"), "--out", str(tmp_path / "o.yaml")]):
        code, err, peak_kb = _run_limited(argv, tmp_path)
        assert code == 3 and path in err and "not a regular file" in err and "Traceback" not in err, err
        assert peak_kb < 200_000


def test_numbers_in_files_and_typed_are_plain_ascii_digits():
    from selfview.files.io_safe import parse_number

    for text in ("a: 1_0\n", "a: 1:30\n", "a: 1_000.5\n"):  # YAML 1.1 reads 10, 90 and 1000.5
        with pytest.raises(ConfigError, match="plain digits"):
            load_yaml(text, "m.yaml")
    assert load_yaml("a: -10\nb: 2.5e-3\n", "m.yaml") == {"a": -10, "b": 0.0025}
    assert parse_number(" -1.5e2 ") == -150.0 and parse_number("7", integer=True, lo=1, hi=7) == 7
    for text, kw, why in (("1_0", {}, "ASCII digits"), ("\uff11\uff10", {}, "ASCII digits"), ("1.5", {"integer": True}, "whole"),
                          ("inf", {}, "non-finite"), ("-nan", {}, "non-finite"), ("1e400", {}, "out of range"),
                          ("1e308", {"lo": -360, "hi": 360}, "out of range"), ("0", {"lo": 0, "lo_open": True}, "> 0")):
        with pytest.raises(ValueError, match=why):
            parse_number(text, **kw)


def test_write_picture_refuses_what_is_no_8_bit_picture(tmp_path):
    """A float, wider, empty or oddly shaped array is refused by name (OpenCV would convert a float one to 8
    bits itself, NaN included, and write it); nothing is written."""
    from selfview.files.io_safe import write_picture

    for bad in (np.zeros((4, 4)), np.full((4, 4), np.nan, np.float32), np.zeros((4, 4), np.uint16),
                np.zeros((0, 0), np.uint8), np.zeros((4, 4, 2), np.uint8), [[1, 2], [3, 4]]):
        with pytest.raises(ConfigError, match=r"p\.png: cannot write the picture: expected an 8-bit grey or BGR"):
            write_picture(tmp_path / "p.png", bad)
    assert list(tmp_path.iterdir()) == []
    write_picture(tmp_path / "p.png", np.full((4, 4, 3), 7, np.uint8))
    assert read_picture(tmp_path / "p.png")[0].tolist() == [[7] * 4] * 4
