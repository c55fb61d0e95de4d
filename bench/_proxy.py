"""A corrupting TCP proxy on 127.0.0.1 for the fault campaign (``bench/faults/``).

It sits between a driver (the client) and a simulated device (upstream) and, on demand, corrupts the
byte stream in one direction: host to device (``h2d``) or device to host (``d2h``). Every wait is
bounded: one thread, a select loop with a short timeout that checks the stop event.
"""

from __future__ import annotations

import select
import socket
import threading
import time
from dataclasses import dataclass, field

import numpy as np

__all__ = ["FaultProxy", "Fault", "STREAM_FAULTS"]

#: what the proxy can do to a byte stream
STREAM_FAULTS = (
    "bitflip",  # one bit of one byte
    "digit_swap",  # two neighbouring different digits swapped (or one digit changed)
    "drop",  # one byte removed
    "dup",  # one byte sent twice
    "stray_prompt",  # the prompt character (or a random byte on a binary link) inserted
    "error_line",  # a whole error line inserted (text protocols)
    "stall",  # the direction held for ``seconds``, then released (nothing lost)
    "cutoff",  # the client's connection closed at that byte
    "nonascii",  # one byte replaced by a byte >= 0x80
)
_POLL_S = 0.005


@dataclass
class Fault:
    """One armed fault: ``kind`` (one of ``STREAM_FAULTS``) on ``direction`` ('h2d' or 'd2h') at byte
    ``at`` after arming; ``insert`` the bytes an insertion fault puts in; ``seconds`` a stall's length."""

    kind: str
    direction: str
    at: int
    insert: bytes = b""
    seconds: float = 0.0
    fired: str | None = None  # what was done, once it fired
    seen: int = 0  # bytes counted since arming
    extra: dict = field(default_factory=dict)


class _Pipe:
    """One direction: bytes waiting to go out, and a hold time for stalls."""

    def __init__(self):
        self.out = bytearray()
        self.hold_until = 0.0
        self.bytes = 0  # bytes that came in from the source (since the last reset)


class FaultProxy:
    """Proxy 127.0.0.1:``port`` -> 127.0.0.1:``upstream_port``. ``seed`` drives the random choices made
    while a fault fires (which bit, which replacement byte). Start with ``start()``, end with ``stop()``.

    A fault is armed with the byte offset (counted from the arming, in that direction) where it strikes;
    it fires once when that byte passes, and ``fired`` says what it did (so a fault that never met its
    byte is not counted as injected). ``serial=True`` (the VAL-II terminal): one upstream connection for
    the proxy's whole life, like a serial cable whose far end never notices the host: a client that
    disconnects leaves the controller running, what it says meanwhile is lost, and the next client is
    joined to the same upstream connection. ``serial=False`` (Modbus TCP): one upstream connection per
    client, closed with it. The listening port comes from the OS (kept bound until ``stop()``)."""

    def __init__(self, upstream_port: int, *, serial: bool, seed: int = 0):
        self.upstream_port = int(upstream_port)
        self.serial = bool(serial)
        self.rng = np.random.default_rng(seed)
        self._lsock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._lsock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._lsock.bind(("127.0.0.1", 0))
        self._lsock.listen(4)
        self._lsock.setblocking(False)
        self.port = self._lsock.getsockname()[1]
        self._client: socket.socket | None = None
        self._up: socket.socket | None = None
        self._pipes = {"h2d": _Pipe(), "d2h": _Pipe()}
        self._fault: Fault | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.clients = 0
        self.error: BaseException | None = None  # an unexpected error of the proxy thread itself

    # --- control ----------------------------------------------------------------------------------
    def start(self) -> "FaultProxy":
        if self.serial:
            self._up = socket.create_connection(("127.0.0.1", self.upstream_port), timeout=2.0)
            self._up.setblocking(False)
            self._up.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._thread = threading.Thread(target=self._loop, name=f"fault-proxy:{self.port}", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        for s in (self._client, self._up, self._lsock):
            if s is not None:
                try:
                    s.close()
                except OSError:
                    pass

    def arm(self, fault: Fault) -> None:
        with self._lock:
            self._fault = fault
            fault.seen = 0

    def disarm(self) -> Fault | None:
        """Remove the armed fault (fired or not) and release any stall; returns it."""
        with self._lock:
            f, self._fault = self._fault, None
            for p in self._pipes.values():
                p.hold_until = 0.0
            return f

    def counts(self) -> dict[str, int]:
        """Bytes that came in per direction since the last ``reset_counts()``."""
        with self._lock:
            return {k: p.bytes for k, p in self._pipes.items()}

    def reset_counts(self) -> None:
        with self._lock:
            for p in self._pipes.values():
                p.bytes = 0

    def cut_client(self) -> None:
        """Close the client's connection now (the upstream stays in the serial model)."""
        with self._lock:
            self._close_client()

    # --- the loop -----------------------------------------------------------------------------------
    def _close_client(self) -> None:
        if self._client is not None:
            try:
                self._client.close()
            except OSError:
                pass
            self._client = None
            self._pipes["d2h"].out.clear()
            self._pipes["h2d"].out.clear()
        if not self.serial and self._up is not None:
            try:
                self._up.close()
            except OSError:
                pass
            self._up = None

    def _loop(self) -> None:
        try:
            while not self._stop.is_set():
                self._step()
        except BaseException as exc:  # reported to the campaign, which counts it as a proxy failure
            self.error = exc

    def _step(self) -> None:
        socks = [self._lsock] + [s for s in (self._client, self._up) if s is not None]
        now = time.monotonic()
        wants_out = []
        with self._lock:
            for d, dst in (("h2d", self._up), ("d2h", self._client)):
                p = self._pipes[d]
                if dst is not None and p.out and p.hold_until <= now:
                    wants_out.append(dst)
        try:
            r, w, _ = select.select(socks, wants_out, [], _POLL_S)
        except (OSError, ValueError):  # a socket closed under us: next round
            return
        if self._lsock in r:
            self._accept()
        with self._lock:
            if self._client is not None and self._client in r:
                self._pull("h2d", self._client)
            if self._up is not None and self._up in r:
                self._pull("d2h", self._up)
            now = time.monotonic()
            for d, dst in (("h2d", self._up), ("d2h", self._client)):
                p = self._pipes[d]
                if dst is not None and dst in w and p.out and p.hold_until <= now:
                    try:
                        n = dst.send(bytes(p.out))
                        del p.out[:n]
                    except BlockingIOError:
                        pass
                    except OSError:
                        self._close_client()

    def _accept(self) -> None:
        try:
            conn, _ = self._lsock.accept()
        except (BlockingIOError, OSError):
            return
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self._lock:
            self._close_client()  # one client at a time: a new one replaces the old (a re-plugged cable)
            if not self.serial:
                try:
                    up = socket.create_connection(("127.0.0.1", self.upstream_port), timeout=1.0)
                except OSError:
                    conn.close()
                    return
                up.setblocking(False)
                up.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._up = up
            self._client = conn
            self.clients += 1

    def _pull(self, direction: str, src: socket.socket) -> None:
        try:
            data = src.recv(4096)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            if src is self._client:
                self._close_client()
            else:  # the device closed: so does the client's side
                self._up = None
                self._close_client()
            return
        p = self._pipes[direction]
        p.bytes += len(data)
        f = self._fault
        if f is not None and f.fired is None and f.direction == direction:
            data = self._apply(f, bytearray(data), p)
            if data is None:
                return
        p.out += data
        if self._client is None:  # nobody on the cable: what the device says is lost
            self._pipes["d2h"].out.clear()

    # --- faults ---------------------------------------------------------------------------------------
    def _apply(self, f: Fault, data: bytearray, p: _Pipe) -> bytearray | None:
        i = f.at - f.seen
        f.seen += len(data)
        if i >= len(data):
            return data
        i = max(i, 0)
        k = f.kind
        if k == "bitflip":
            bit = int(self.rng.integers(8))
            old = data[i]
            data[i] ^= 1 << bit
            f.fired = f"bit {bit} of byte {i} flipped: {bytes([old])!r} -> {bytes([data[i]])!r}"
        elif k == "digit_swap":
            digits = [j for j in range(i, len(data)) if 0x30 <= data[j] <= 0x39]
            pairs = [j for j in digits if j + 1 < len(data) and 0x30 <= data[j + 1] <= 0x39 and data[j] != data[j + 1]]
            if pairs:
                j = pairs[0]
                data[j], data[j + 1] = data[j + 1], data[j]
                f.fired = f"digits at {j} swapped: {bytes(data[max(0, j - 8):j + 10])!r}"
            elif digits:
                j = digits[0]
                old = data[j]
                data[j] = 0x30 + (old - 0x30 + 1 + int(self.rng.integers(9))) % 10
                f.fired = f"digit at {j} changed {chr(old)} -> {chr(data[j])}: {bytes(data[max(0, j - 8):j + 10])!r}"
            else:
                f.at = f.seen  # no digit in this chunk: strike at the next one
        elif k == "drop":
            f.fired = f"byte {bytes([data[i]])!r} dropped"
            del data[i]
        elif k == "dup":
            data.insert(i, data[i])
            f.fired = f"byte {bytes([data[i]])!r} duplicated"
        elif k in ("stray_prompt", "error_line"):
            data[i:i] = f.insert
            f.fired = f"{f.insert!r} inserted at {i}"
        elif k == "nonascii":
            old = data[i]
            data[i] = 0x80 | int(self.rng.integers(0x80))
            f.fired = f"byte {bytes([old])!r} replaced by {bytes([data[i]])!r}"
        elif k == "stall":
            p.out += data[:i]
            p.hold_until = time.monotonic() + f.seconds
            f.fired = f"stalled {f.seconds:.3f} s before byte {i}"
            return data[i:]
        elif k == "cutoff":
            p.out += data[:i]
            f.fired = f"connection cut at byte {i}"
            rest = bytes(p.out)
            if f.direction == "h2d" and self._up is not None and rest:  # what was on the wire goes through
                try:
                    self._up.send(rest)
                except OSError:
                    pass
            elif f.direction == "d2h" and self._client is not None and rest:
                try:
                    self._client.send(rest)
                except OSError:
                    pass
            p.out.clear()
            self._close_client()
            return None
        else:
            raise ValueError(f"unknown stream fault {k!r}")
        return data
