"""Termination signals, and the connected devices a signal must stop whatever the entry point.

The command line and the engine take the signals themselves while they run (``selfview.procedures.engine``). Every
other entry point (a lab script driving ``PumaVAL`` or ``PneumaticGripper`` directly, a ``CellSession`` in a worker
thread) gets the same first response from here: while a driver is connected (``watch``), a termination signal whose
action is still the default one (SIGINT's ``KeyboardInterrupt``, SIGTERM's, SIGHUP's, SIGQUIT's death) is taken by
the main thread's handler, which

1. writes ABORT to every connected robot and ends every jaw wait at once, then, in a helper thread, waits for the
   robots' motions to end and puts every valve in its safe state;
2. raises ``Interrupted`` (a ``KeyboardInterrupt`` carrying the signal's number) where the main thread is, so the
   script's ``finally`` and ``with`` blocks run; a program left by that exception says so in one line and ends,
   once the helper is done, by the signal itself (the status a shell reports as 128 + N).

Ctrl-Z (SIGTSTP) holds the arm: ABORT first, then the program stops; resumed, it says so on stderr, and the stopped
motion is not taken up again (its driver reports the ABORT). A signal ignored when the program started (``nohup``, a
background job) stays ignored, and a handler the script installed itself is left alone. Python runs handlers in the
main thread only: they are installed when a driver connects there or when this module is first imported there (a
driver connecting in a worker thread was imported by the main thread first).
"""

from __future__ import annotations

import atexit
import logging
import os
import signal
import sys
import threading
import weakref

__all__ = ["TERMINATION_SIGNALS", "Interrupted", "signal_name", "watch", "unwatch", "install"]

log = logging.getLogger("selfview.drivers.signals")

#: The catchable signals that end a run as Ctrl-C does (the platform's subset).
TERMINATION_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT") if hasattr(signal, n))

_STOP_WAIT_S = 10.0  # how long the helper may take to stop the devices before the program ends anyway


def signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


class Interrupted(KeyboardInterrupt):
    """A termination signal (``signum``), raised where Ctrl-C would raise ``KeyboardInterrupt``: for SIGTERM,
    SIGHUP and SIGQUIT by the engine and the command line, for any of them by this module's handler."""

    def __init__(self, signum: int):
        super().__init__(signal_name(signum))
        self.signum = int(signum)


_live: "weakref.WeakSet" = weakref.WeakSet()
_live_lock = threading.Lock()
_helpers: list[threading.Thread] = []
_ended_by: list[int] = []  # the signal an uncaught Interrupted came from: the program ends by it


def watch(device) -> None:
    """A device was connected: a termination signal stops it from now on (``unwatch`` at close). A
    robot has ``abort_now()`` and ``wait_motion_end(timeout_s)``; a gripper ``interrupt()`` and ``safe()``
    (``TypeError`` naming what is missing: the stop on a signal would otherwise fail in its helper thread)."""
    for pair in (("abort_now", "wait_motion_end"), ("interrupt", "safe")):
        have = [hasattr(device, m) for m in pair]
        if any(have) and not all(have):
            raise TypeError(f"signals.watch({device!r}): it has {pair[have.index(True)]}() but no "
                            f"{pair[have.index(False)]}(); a signal could not stop it")
    if not (hasattr(device, "abort_now") or hasattr(device, "interrupt")):
        raise TypeError(f"signals.watch({device!r}): neither a robot (abort_now, wait_motion_end) nor a gripper "
                        "(interrupt, safe); a signal could not stop it")
    with _live_lock:
        _live.add(device)
    install()


def unwatch(device) -> None:
    with _live_lock:
        _live.discard(device)


def _default(sig: int):
    return signal.default_int_handler if sig == signal.SIGINT else signal.SIG_DFL


def install() -> None:
    """Take, in the main thread, each termination signal (and SIGTSTP) whose action is still the default
    one; an ignored one and a handler of the program's own are left as they are. Idempotent."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in TERMINATION_SIGNALS + ((signal.SIGTSTP,) if hasattr(signal, "SIGTSTP") else ()):
        try:
            if signal.getsignal(sig) is _default(sig):
                signal.signal(sig, _handle)
        except (OSError, ValueError):  # not settable here
            pass


def _devices() -> list:
    with _live_lock:
        return list(_live)


def _stop(devices: list) -> None:
    """ABORT every robot, end every jaw wait, wait for the motions to end, make every valve safe; never raises."""
    robots = [d for d in devices if hasattr(d, "abort_now")]
    grippers = [d for d in devices if hasattr(d, "interrupt")]
    for r in robots:
        why = r.abort_now()
        if why:
            log.error("%r: ABORT on a signal: %s", r, why)
    for g in grippers:
        g.interrupt()
    for r in robots:
        if not r.wait_motion_end(_STOP_WAIT_S / 2):
            log.error("%r: the motion's wait did not end after the ABORT", r)
    for g in grippers:
        try:
            g.safe()
        except Exception as exc:  # the report says what could be confirmed; go on with the others
            log.error("%r: safe state on a signal: %s", g, exc)


def _handle(signum, frame) -> None:
    devices = _devices()
    if signum == getattr(signal, "SIGTSTP", None):
        _suspend(devices)
        return
    if not devices:  # nothing to stop: exactly what the default action does
        signal.signal(signum, _default(signum))
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        signal.raise_signal(signum)
        return
    if _helpers and _helpers[-1].is_alive():
        return  # the stop the first one started is under way: a second signal is only noted, never cuts it short
    _say(f"{signal_name(signum)}: stopping the robot (ABORT) and making the valve safe")
    # in a helper: the main thread may hold a driver's write lock right now; a short wait lets the ABORT
    # go out before this thread raises (the rest goes on meanwhile, and the program's end waits for it)
    helper = threading.Thread(target=_stop, args=(devices,), name="stop on signal", daemon=True)
    _helpers.append(helper)
    helper.start()
    helper.join(0.5)
    raise Interrupted(signum)  # a KeyboardInterrupt: what Ctrl-C raises, carrying the signal's number


def _suspend(devices: list) -> None:
    """SIGTSTP: the arm held (ABORT, valve left as it is) before the program stops; on resume, say so."""
    robots = [d for d in devices if hasattr(d, "abort_now")]
    if robots:
        helper = threading.Thread(target=lambda: [r.abort_now() for r in robots], name="ABORT on Ctrl-Z", daemon=True)
        helper.start()
        helper.join(1.0)
        _say("Ctrl-Z: the robot was stopped (ABORT) before the program is suspended")
    signal.signal(signal.SIGTSTP, signal.SIG_DFL)
    try:
        os.kill(os.getpid(), signal.SIGTSTP)  # stops here until SIGCONT
    finally:
        signal.signal(signal.SIGTSTP, _handle)
    if robots:
        _say("resumed: the motion stopped at Ctrl-Z is not taken up again; its command reports the ABORT")


def _say(text: str) -> None:
    try:
        print(f"selfview: {text}", file=sys.stderr, flush=True)
    except (OSError, ValueError):  # the terminal is gone (SIGHUP)
        pass


def _excepthook(exc_type, exc, tb, _previous=sys.excepthook) -> None:
    if isinstance(exc, Interrupted) and threading.current_thread() is threading.main_thread():
        _ended_by.append(exc.signum)
        _say("interrupted (Ctrl-C)" if exc.signum == signal.SIGINT else f"terminated by {signal_name(exc.signum)}")
        return
    _previous(exc_type, exc, tb)


@atexit.register
def _at_exit() -> None:
    """The program ends: the devices' stop finishes first; a program ended by a signal then ends by it."""
    for t in list(_helpers):
        t.join(_STOP_WAIT_S)
    if _ended_by:
        sig = _ended_by[0]
        signal.signal(sig, signal.SIG_DFL)
        os.kill(os.getpid(), sig)


sys.excepthook = _excepthook
install()
