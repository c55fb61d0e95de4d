"""The V4L2 ioctls OpenCV does not make: video input, analogue standard, signal detection.

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


v4l2_std_id = ctypes.c_uint64

VIDIOC_QUERYCAP = IOR("V", 0, v4l2_capability)
VIDIOC_G_STD = IOR("V", 23, v4l2_std_id)
VIDIOC_S_STD = IOW("V", 24, v4l2_std_id)
VIDIOC_ENUMINPUT = IOWR("V", 26, v4l2_input)
VIDIOC_G_INPUT = IOR("V", 38, ctypes.c_int)
VIDIOC_S_INPUT = IOWR("V", 39, ctypes.c_int)
VIDIOC_QUERYSTD = IOR("V", 63, v4l2_std_id)

V4L2_CAP_VIDEO_CAPTURE = 0x00000001
V4L2_CAP_DEVICE_CAPS = 0x80000000
V4L2_IN_ST_NO_POWER = 0x00000001
V4L2_IN_ST_NO_SIGNAL = 0x00000002
V4L2_IN_ST_NO_H_LOCK = 0x00000100

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
        """Raise DeviceError if the current input carries no signal, or one of another standard."""
        detected = self.query_std()
        if detected == 0:
            raise DeviceError(f"{self.path}: no video signal on the input (VIDIOC_QUERYSTD found none)")
        if detected is not None and std is not None and not detected & std:
            raise DeviceError(
                f"{self.path}: the signal is {std_name(detected)}, but {std_name(std)} is configured"
            )
        status = self.input_status()
        if status is not None and status & (V4L2_IN_ST_NO_POWER | V4L2_IN_ST_NO_SIGNAL | V4L2_IN_ST_NO_H_LOCK):
            raise DeviceError(f"{self.path}: no video signal on the input (input status {status:#x})")
