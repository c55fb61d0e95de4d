"""The V4L2 ioctls OpenCV does not make: video input, analogue standard, signal detection, crop and
compose rectangles, the flip controls.

Standard library only (``os``, ``fcntl``, ``ctypes``). Request numbers are encoded as the kernel's
``<asm-generic/ioctl.h>`` does (``_IOC(dir, type, nr, size)``: nr in bits 0-7, type 8-15, size 16-29,
direction 30-31), with the argument sizes of ``<linux/videodev2.h>`` taken from ctypes mirrors of its
structures. The generic layout holds for x86, ARM and RISC-V; PowerPC, MIPS, SPARC and Alpha place the
direction bits differently and are refused by ``_IOC``.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import os
import platform

from selfview.errors import ConfigError, DeviceError

__all__ = [
    "IOC",
    "IOR",
    "IOW",
    "IOWR",
    "VIDIOC_QUERYCAP",
    "VIDIOC_G_STD",
    "VIDIOC_S_STD",
    "VIDIOC_ENUMINPUT",
    "VIDIOC_G_INPUT",
    "VIDIOC_S_INPUT",
    "VIDIOC_QUERYSTD",
    "VIDIOC_G_FMT",
    "VIDIOC_QUERYBUF",
    "VIDIOC_G_CTRL",
    "VIDIOC_G_SELECTION",
    "VIDIOC_S_SELECTION",
    "FIELD_NAMES",
    "fields_per_buffer",
    "V4L2Device",
    "std_name",
]

_IOC_NONE, _IOC_WRITE, _IOC_READ = 0, 1, 2
_NRBITS, _TYPEBITS, _SIZEBITS, _DIRBITS = 8, 8, 14, 2
_NRSHIFT = 0
_TYPESHIFT = _NRSHIFT + _NRBITS
_SIZESHIFT = _TYPESHIFT + _TYPEBITS
_DIRSHIFT = _SIZESHIFT + _SIZEBITS
_GENERIC_MACHINES = ("x86_64", "amd64", "i386", "i686", "aarch64", "arm64", "armv7l", "armv6l", "riscv64", "s390x")


def IOC(direction: int, type_: str, nr: int, size: int) -> int:
    """The kernel's ``_IOC``: an ioctl request number from direction, type letter, number and size."""
    if not 0 <= direction < 1 << _DIRBITS or not 0 <= nr < 1 << _NRBITS or not 0 <= size < 1 << _SIZEBITS:
        raise ValueError(f"_IOC({direction}, {type_!r}, {nr}, {size}): a field is out of range")
    return (direction << _DIRSHIFT) | (ord(type_) << _TYPESHIFT) | (nr << _NRSHIFT) | (size << _SIZESHIFT)


def IOR(type_: str, nr: int, ctype) -> int:
    return IOC(_IOC_READ, type_, nr, ctypes.sizeof(ctype))


def IOW(type_: str, nr: int, ctype) -> int:
    return IOC(_IOC_WRITE, type_, nr, ctypes.sizeof(ctype))


def IOWR(type_: str, nr: int, ctype) -> int:
    return IOC(_IOC_READ | _IOC_WRITE, type_, nr, ctypes.sizeof(ctype))


class v4l2_capability(ctypes.Structure):
    _fields_ = [
        ("driver", ctypes.c_char * 16),
        ("card", ctypes.c_char * 32),
        ("bus_info", ctypes.c_char * 32),
        ("version", ctypes.c_uint32),
        ("capabilities", ctypes.c_uint32),
        ("device_caps", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32 * 3),
    ]


class v4l2_input(ctypes.Structure):
    _fields_ = [
        ("index", ctypes.c_uint32),
        ("name", ctypes.c_char * 32),
        ("type", ctypes.c_uint32),
        ("audioset", ctypes.c_uint32),
        ("tuner", ctypes.c_uint32),
        ("std", ctypes.c_uint64),
        ("status", ctypes.c_uint32),
        ("capabilities", ctypes.c_uint32),
        ("reserved", ctypes.c_uint32 * 3),
    ]


class v4l2_pix_format(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_uint32)
        for name in ("width", "height", "pixelformat", "field", "bytesperline", "sizeimage", "colorspace", "priv",
                     "flags", "ycbcr_enc", "quantization", "xfer_func")
    ]


class _v4l2_format_union(ctypes.Union):
    # the kernel's union holds structures with pointers (v4l2_window): pointer alignment
    _fields_ = [("pix", v4l2_pix_format), ("raw_data", ctypes.c_uint8 * 200), ("_align", ctypes.c_void_p)]


class v4l2_format(ctypes.Structure):
    _fields_ = [("type", ctypes.c_uint32), ("fmt", _v4l2_format_union)]


class timeval(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_usec", ctypes.c_long)]


class v4l2_timecode(ctypes.Structure):
    _fields_ = [
        ("type", ctypes.c_uint32),
        ("flags", ctypes.c_uint32),
        ("frames", ctypes.c_uint8),
        ("seconds", ctypes.c_uint8),
        ("minutes", ctypes.c_uint8),
        ("hours", ctypes.c_uint8),
        ("userbits", ctypes.c_uint8 * 4),
    ]


class _v4l2_buffer_m(ctypes.Union):
    _fields_ = [("offset", ctypes.c_uint32), ("userptr", ctypes.c_ulong), ("planes", ctypes.c_void_p),
                ("fd", ctypes.c_int32)]


class v4l2_buffer(ctypes.Structure):
    _fields_ = [
        ("index", ctypes.c_uint32),
        ("type", ctypes.c_uint32),
        ("bytesused", ctypes.c_uint32),
        ("flags", ctypes.c_uint32),
        ("field", ctypes.c_uint32),
        ("timestamp", timeval),
        ("timecode", v4l2_timecode),
        ("sequence", ctypes.c_uint32),
        ("memory", ctypes.c_uint32),
        ("m", _v4l2_buffer_m),
        ("length", ctypes.c_uint32),
        ("reserved2", ctypes.c_uint32),
        ("request_fd", ctypes.c_int32),
    ]


class v4l2_rect(ctypes.Structure):
    _fields_ = [("left", ctypes.c_int32), ("top", ctypes.c_int32), ("width", ctypes.c_uint32), ("height", ctypes.c_uint32)]


class v4l2_selection(ctypes.Structure):
    _fields_ = [("type", ctypes.c_uint32), ("target", ctypes.c_uint32), ("flags", ctypes.c_uint32), ("r", v4l2_rect),
                ("reserved", ctypes.c_uint32 * 9)]


class v4l2_control(ctypes.Structure):
    _fields_ = [("id", ctypes.c_uint32), ("value", ctypes.c_int32)]


v4l2_std_id = ctypes.c_uint64

VIDIOC_QUERYCAP = IOR("V", 0, v4l2_capability)
VIDIOC_G_STD = IOR("V", 23, v4l2_std_id)
VIDIOC_S_STD = IOW("V", 24, v4l2_std_id)
VIDIOC_ENUMINPUT = IOWR("V", 26, v4l2_input)
VIDIOC_G_INPUT = IOR("V", 38, ctypes.c_int)
VIDIOC_S_INPUT = IOWR("V", 39, ctypes.c_int)
VIDIOC_QUERYSTD = IOR("V", 63, v4l2_std_id)
VIDIOC_G_FMT = IOWR("V", 4, v4l2_format)
VIDIOC_QUERYBUF = IOWR("V", 9, v4l2_buffer)
VIDIOC_G_CTRL = IOWR("V", 27, v4l2_control)
VIDIOC_G_SELECTION = IOWR("V", 94, v4l2_selection)
VIDIOC_S_SELECTION = IOWR("V", 95, v4l2_selection)
V4L2_SEL_TGT_CROP, V4L2_SEL_TGT_CROP_DEFAULT, V4L2_SEL_TGT_COMPOSE = 0x0000, 0x0001, 0x0100
V4L2_CID_HFLIP, V4L2_CID_VFLIP = 0x00980914, 0x00980915

V4L2_BUF_TYPE_VIDEO_CAPTURE = 1
V4L2_BUF_FLAG_TIMESTAMP_MASK = 0x0000E000
V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC = 0x00002000
V4L2_BUF_FLAG_TSTAMP_SRC_MASK = 0x00070000
V4L2_BUF_FLAG_TSTAMP_SRC_EOF = 0x00000000  # V4L2's default: the time the last byte of the frame arrived
V4L2_BUF_FLAG_TSTAMP_SRC_SOE = 0x00010000  # the time the exposure started

#: enum v4l2_field
FIELD_NAMES = {
    0: "ANY",
    1: "NONE",
    2: "TOP",
    3: "BOTTOM",
    4: "INTERLACED",
    5: "SEQ_TB",
    6: "SEQ_BT",
    7: "ALTERNATE",
    8: "INTERLACED_TB",
    9: "INTERLACED_BT",
}


def fields_per_buffer(field: int) -> int:
    """How many video fields one buffer of this field order holds: 1 (NONE, a progressive frame, counted
    as one frame period by the caller), 2 (both fields: INTERLACED*, SEQ_*), or 1 field (TOP, BOTTOM,
    ALTERNATE). Raises ValueError for ANY (not a format a driver may return) or an unknown value."""
    if field in (4, 5, 6, 8, 9):
        return 2
    if field in (1, 2, 3, 7):
        return 1
    raise ValueError(f"field order {FIELD_NAMES.get(field, field)} is not one a capture format may have")

V4L2_CAP_VIDEO_CAPTURE = 0x00000001
V4L2_CAP_DEVICE_CAPS = 0x80000000
V4L2_IN_ST_NO_POWER = 0x00000001
V4L2_IN_ST_NO_SIGNAL = 0x00000002
V4L2_IN_ST_HFLIP = 0x00000010  # the source sends its picture mirrored and the driver does not undo it
V4L2_IN_ST_VFLIP = 0x00000020
V4L2_IN_ST_NO_H_LOCK = 0x00000100
V4L2_IN_ST_NO_V_LOCK = 0x00000400
V4L2_IN_ST_NO_STD_LOCK = 0x00000800
V4L2_IN_ST_NO_SYNC = 0x00010000
_NO_LOCK = V4L2_IN_ST_NO_H_LOCK | V4L2_IN_ST_NO_V_LOCK | V4L2_IN_ST_NO_STD_LOCK | V4L2_IN_ST_NO_SYNC

_STD_NAMES = {
    0x000000FF: "PAL",
    0x00000100: "PAL-M",
    0x00000200: "PAL-N",
    0x00000400: "PAL-Nc",
    0x00000800: "PAL-60",
    0x0000B000: "NTSC",
    0x00FF0000: "SECAM",
}


def std_name(std: int) -> str:
    """A readable name for v4l2_std_id bits (the families they touch, or the number)."""
    names = [n for bits, n in _STD_NAMES.items() if std & bits]
    return "/".join(names) if names else f"{std:#x}"


class V4L2Device:
    """A V4L2 device node opened for its control ioctls (not for streaming; OpenCV streams).

    Construction does no I/O; ``open()`` / ``close()`` are safe to call twice. Every failure raises
    DeviceError (or ConfigError for a setting the device refuses) naming the device and the errno.
    """

    def __init__(self, path: str):
        self.path = path
        self.fd: int | None = None

    def open(self) -> "V4L2Device":
        if self.fd is not None:
            return self
        if platform.machine().lower() not in _GENERIC_MACHINES:
            raise DeviceError(f"{self.path}: V4L2 ioctl numbers are only encoded for {', '.join(_GENERIC_MACHINES)}")
        try:
            self.fd = os.open(self.path, os.O_RDWR | os.O_NONBLOCK)
        except FileNotFoundError:
            raise DeviceError(f"{self.path}: no such video device (is the grabber card's driver loaded?)") from None
        except PermissionError:
            raise DeviceError(f"{self.path}: permission denied (is the user in group 'video'?)") from None
        except OSError as exc:
            if exc.errno == errno.EBUSY:
                raise DeviceError(f"{self.path}: device busy (another program is capturing)") from None
            raise DeviceError(f"{self.path}: cannot open: {exc.strerror}") from None
        return self

    def close(self) -> None:
        fd, self.fd = self.fd, None
        if fd is not None:
            os.close(fd)

    def __enter__(self) -> "V4L2Device":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    def _ioctl(self, request: int, arg, name: str):
        if self.fd is None:
            raise DeviceError(f"{self.path}: {name} on a closed device")
        for _ in range(3):  # an ioctl interrupted by a signal is simply repeated
            try:
                fcntl.ioctl(self.fd, request, arg, True)
                return arg
            except InterruptedError:
                continue
            except OSError as exc:
                if exc.errno == errno.ENODEV:  # whatever the ioctl, the card is gone
                    raise DeviceError(f"{self.path}: no such device (the grabber was unplugged or its driver "
                                      f"unloaded; {name})") from None
                raise
        raise DeviceError(f"{self.path}: {name} interrupted three times")

    def querycap(self) -> dict:
        """Driver, card, bus and capability bits; raises DeviceError if this is not a capture device."""
        cap = v4l2_capability()
        try:
            self._ioctl(VIDIOC_QUERYCAP, cap, "VIDIOC_QUERYCAP")
        except OSError as exc:
            if exc.errno in (errno.ENOTTY, errno.EINVAL):
                raise DeviceError(f"{self.path}: not a V4L2 device (VIDIOC_QUERYCAP: {exc.strerror})") from None
            raise DeviceError(f"{self.path}: VIDIOC_QUERYCAP failed: {exc.strerror}") from None
        caps = cap.device_caps if cap.capabilities & V4L2_CAP_DEVICE_CAPS else cap.capabilities
        info = {
            "driver": cap.driver.decode(errors="replace"),
            "card": cap.card.decode(errors="replace"),
            "bus_info": cap.bus_info.decode(errors="replace"),
            "capabilities": int(caps),
        }
        if not caps & V4L2_CAP_VIDEO_CAPTURE:
            raise DeviceError(f"{self.path}: {info['card']!r} ({info['driver']}) cannot capture video")
        return info

    def inputs(self) -> list[tuple[int, str, int]]:
        """[(index, name, status bits)] of the device's video inputs."""
        out = []
        for i in range(64):
            inp = v4l2_input(index=i)
            try:
                self._ioctl(VIDIOC_ENUMINPUT, inp, "VIDIOC_ENUMINPUT")
            except OSError as exc:
                if exc.errno == errno.EINVAL:
                    break
                raise DeviceError(f"{self.path}: VIDIOC_ENUMINPUT failed: {exc.strerror}") from None
            out.append((i, inp.name.decode(errors="replace"), int(inp.status)))
        return out

    def set_input(self, index: int) -> None:
        """VIDIOC_S_INPUT. ConfigError for an input the device lacks, DeviceError if busy."""
        arg = ctypes.c_int(index)
        try:
            self._ioctl(VIDIOC_S_INPUT, arg, "VIDIOC_S_INPUT")
        except OSError as exc:
            if exc.errno == errno.EINVAL:
                names = ", ".join(f"{i}: {n}" for i, n, _ in self.inputs()) or "none listed"
                raise ConfigError(f"{self.path}: input={index} does not exist (inputs: {names})") from None
            if exc.errno == errno.EBUSY:
                raise DeviceError(f"{self.path}: cannot switch to input {index}: device busy") from None
            raise DeviceError(f"{self.path}: VIDIOC_S_INPUT({index}) failed: {exc.strerror}") from None

    def set_std(self, std: int) -> None:
        """VIDIOC_S_STD. ConfigError if the device refuses the standard or has none (a digital camera)."""
        arg = v4l2_std_id(std)
        try:
            self._ioctl(VIDIOC_S_STD, arg, "VIDIOC_S_STD")
        except OSError as exc:
            if exc.errno in (errno.ENODATA, errno.ENOTTY):
                raise ConfigError(f"{self.path}: the device has no analogue video standards (std= does not apply)") from None
            if exc.errno == errno.EINVAL:
                raise ConfigError(f"{self.path}: standard {std_name(std)} not supported by the device") from None
            if exc.errno == errno.EBUSY:
                raise DeviceError(f"{self.path}: cannot set standard {std_name(std)}: device busy") from None
            raise DeviceError(f"{self.path}: VIDIOC_S_STD({std_name(std)}) failed: {exc.strerror}") from None

    def _pix_format(self) -> v4l2_pix_format | None:
        """VIDIOC_G_FMT of the capture queue, or None if the driver does not say."""
        fmt = v4l2_format(type=V4L2_BUF_TYPE_VIDEO_CAPTURE)
        try:
            self._ioctl(VIDIOC_G_FMT, fmt, "VIDIOC_G_FMT")
        except OSError as exc:
            if exc.errno in (errno.ENOTTY, errno.EINVAL):
                return None
            raise DeviceError(f"{self.path}: VIDIOC_G_FMT failed: {exc.strerror}") from None
        return fmt.fmt.pix

    def field_order(self) -> int | None:
        """The capture format's field order (enum v4l2_field), or None if the driver does not say."""
        pix = self._pix_format()
        return None if pix is None else int(pix.field)

    def buffers(self, most: int = 32) -> tuple[int, int | None]:
        """VIDIOC_QUERYBUF over indices 0, 1, ...: (how many capture buffers the driver allocated, the
        first buffer's flags), after streaming started. (0, None) when the driver tells nothing."""
        count, flags = 0, None
        for i in range(most):
            buf = v4l2_buffer(index=i, type=V4L2_BUF_TYPE_VIDEO_CAPTURE)
            try:
                self._ioctl(VIDIOC_QUERYBUF, buf, "VIDIOC_QUERYBUF")
            except OSError as exc:
                if exc.errno in (errno.EINVAL, errno.ENOTTY, errno.EBUSY):
                    break
                raise DeviceError(f"{self.path}: VIDIOC_QUERYBUF failed: {exc.strerror}") from None
            count += 1
            if flags is None:
                flags = int(buf.flags)
        return count, flags

    def query_std(self) -> int | None:
        """VIDIOC_QUERYSTD: the standards the input's signal fits (0: no signal), or None if the driver
        cannot tell."""
        arg = v4l2_std_id(0)
        try:
            self._ioctl(VIDIOC_QUERYSTD, arg, "VIDIOC_QUERYSTD")
        except OSError as exc:
            if exc.errno == errno.ENOLINK:
                return 0
            if exc.errno in (errno.ENODATA, errno.ENOTTY, errno.EINVAL):
                return None
            raise DeviceError(f"{self.path}: VIDIOC_QUERYSTD failed: {exc.strerror}") from None
        return int(arg.value)

    def input_status(self) -> int | None:
        """Status bits (V4L2_IN_ST_*) of the current input, or None if the driver does not say."""
        cur = ctypes.c_int(0)
        try:
            self._ioctl(VIDIOC_G_INPUT, cur, "VIDIOC_G_INPUT")
            inp = v4l2_input(index=cur.value)
            self._ioctl(VIDIOC_ENUMINPUT, inp, "VIDIOC_ENUMINPUT")
        except OSError:
            return None
        return int(inp.status)

    def check_signal(self, std: int | None) -> None:
        """Raise DeviceError if the current input carries no signal, one the grabber cannot lock to, or
        one of another standard. The input status is asked first: it tells "no signal" from "no lock"."""
        status = self.input_status()
        if status is not None and status & (V4L2_IN_ST_NO_POWER | V4L2_IN_ST_NO_SIGNAL):
            what = "the camera has no power" if status & V4L2_IN_ST_NO_POWER else "no video signal on the input"
            raise DeviceError(f"{self.path}: {what} (input status {status:#x}): is the camera connected and on?")
        if status is not None and status & _NO_LOCK:
            raise DeviceError(
                f"{self.path}: a signal but no lock (input status {status:#x}): the grabber cannot synchronise to "
                "it; a bad cable, a source of another line standard or a camera that is not CCIR?"
            )
        detected = self.query_std()
        if detected == 0:
            raise DeviceError(f"{self.path}: no video signal on the input (VIDIOC_QUERYSTD found none)")
        if detected is not None and std is not None and not detected & std:
            raise DeviceError(
                f"{self.path}: the signal is {std_name(detected)}, but {std_name(std)} is configured"
            )

    def _optional_ioctl(self, request: int, arg, name: str, what: str, unsupported: tuple[int, ...]) -> bool:
        """``_ioctl`` for a query the device may not support: False when it says so (an errno in
        ``unsupported``), DeviceError naming ``name(what)`` on any other failure."""
        try:
            self._ioctl(request, arg, name)
        except OSError as exc:
            if exc.errno in unsupported:
                return False
            raise DeviceError(f"{self.path}: {name}({what}) failed: {exc.strerror}") from None
        return True

    def control(self, cid: int) -> int | None:
        """VIDIOC_G_CTRL: a control's value, or None if the device has no such control."""
        ctrl = v4l2_control(id=cid)
        if not self._optional_ioctl(VIDIOC_G_CTRL, ctrl, "VIDIOC_G_CTRL", f"{cid:#x}",
                                    (errno.EINVAL, errno.ENOTTY, errno.EACCES)):
            return None
        return int(ctrl.value)

    def check_orientation(self) -> None:
        """Raise DeviceError if the frames come mirrored or upside down: the input's flip status bits
        (a source sending its picture flipped) combined with the driver's HFLIP / VFLIP controls."""
        status = self.input_status() or 0
        for axis, bit, cid, ctl, what in (
            ("horizontal", V4L2_IN_ST_HFLIP, V4L2_CID_HFLIP, "horizontal_flip", "mirrored left to right"),
            ("vertical", V4L2_IN_ST_VFLIP, V4L2_CID_VFLIP, "vertical_flip", "upside down"),
        ):
            src, flip = bool(status & bit), bool(self.control(cid))
            if src != flip:
                why = (f"the source sends it flipped (input status {status:#x}) and the {axis} flip control is off"
                       if src else f"the {axis} flip control ({ctl}) is on")
                raise DeviceError(
                    f"{self.path}: frames come {what}: {why}; a flipped picture calibrates to a wrong pose, "
                    f"set {ctl}={int(src)} (v4l2-ctl -c {ctl}={int(src)})"
                )

    def selection(self, target: int) -> tuple[int, int, int, int] | None:
        """VIDIOC_G_SELECTION of the capture queue: (left, top, width, height), or None if not supported."""
        sel = v4l2_selection(type=V4L2_BUF_TYPE_VIDEO_CAPTURE, target=target)
        if not self._optional_ioctl(VIDIOC_G_SELECTION, sel, "VIDIOC_G_SELECTION", f"{target:#x}",
                                    (errno.EINVAL, errno.ENOTTY, errno.ENODATA)):
            return None
        return (int(sel.r.left), int(sel.r.top), int(sel.r.width), int(sel.r.height))

    def set_selection(self, target: int, rect: tuple[int, int, int, int]) -> tuple[int, int, int, int] | None:
        """VIDIOC_S_SELECTION: ask for ``rect``; returns the rectangle the driver chose (None: not supported)."""
        left, top, width, height = rect
        sel = v4l2_selection(type=V4L2_BUF_TYPE_VIDEO_CAPTURE, target=target,
                             r=v4l2_rect(left=left, top=top, width=width, height=height))
        try:
            self._ioctl(VIDIOC_S_SELECTION, sel, "VIDIOC_S_SELECTION")
        except OSError as exc:
            if exc.errno in (errno.EINVAL, errno.ENOTTY, errno.ENODATA):
                return None
            if exc.errno == errno.EBUSY:
                raise DeviceError(f"{self.path}: cannot set the {'compose' if target & 0x100 else 'crop'} "
                                  "rectangle: device busy") from None
            raise DeviceError(f"{self.path}: VIDIOC_S_SELECTION({target:#x}) failed: {exc.strerror}") from None
        return (int(sel.r.left), int(sel.r.top), int(sel.r.width), int(sel.r.height))

    def format(self) -> tuple[int, int, str] | None:
        """The capture format's (width, height, fourcc), or None if the driver does not say."""
        pix = self._pix_format()
        if pix is None:
            return None
        return int(pix.width), int(pix.height), int(pix.pixelformat).to_bytes(4, "little").decode("ascii", "replace")

    def whole_picture(self, width: int, height: int) -> None:
        """Make a frame the whole picture at ``width`` x ``height``: the crop rectangle the card's default
        (its whole active picture), the compose rectangle the whole buffer; read both and the format back.
        Raises ConfigError naming what the card gave when it keeps anything else (a cropped or squeezed
        frame would calibrate to a wrong aspect and principal point)."""
        fmt = self.format()
        if fmt is not None and fmt[:2] != (width, height):
            raise ConfigError(f"{self.path}: the capture format is {fmt[0]}x{fmt[1]}, not {width}x{height}")
        default = self.selection(V4L2_SEL_TGT_CROP_DEFAULT)
        if default is not None:
            self.set_selection(V4L2_SEL_TGT_CROP, default)
            crop = self.selection(V4L2_SEL_TGT_CROP)
            if crop is not None and crop != default:
                raise ConfigError(
                    f"{self.path}: the card crops the picture to {crop[2]}x{crop[3]} at ({crop[0]}, {crop[1]}) and "
                    f"will not take its whole picture {default[2]}x{default[3]} at ({default[0]}, {default[1]})"
                )
        want = (0, 0, width, height)
        if self.selection(V4L2_SEL_TGT_COMPOSE) is not None:
            self.set_selection(V4L2_SEL_TGT_COMPOSE, want)
            compose = self.selection(V4L2_SEL_TGT_COMPOSE)
            if compose != want:
                raise ConfigError(
                    f"{self.path}: the card composes the picture into {compose[2]}x{compose[3]} at ({compose[0]}, "
                    f"{compose[1]}) of the {width}x{height} frame, not the whole frame: the picture would be squeezed"
                )
        fmt = self.format()
        if fmt is not None and fmt[:2] != (width, height):
            raise ConfigError(f"{self.path}: after setting crop and compose the format is {fmt[0]}x{fmt[1]}, "
                              f"not {width}x{height}")
