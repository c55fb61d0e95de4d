"""The ``selfview`` operator command.

Each subcommand lives in its own module under ``procedures/commands/`` and defines
``register(subparsers) -> argparse.ArgumentParser`` that sets ``func(args) -> int`` on its parser.
Modules are found at start-up, so adding a command never touches this file.

Exit codes (stable; scripts may rely on them):
  0 success, 1 unexpected internal error, 2 usage error, 3 bad configuration or input file,
  4 device error or timeout, 5 calibration failed, 6 alarm raised by the monitor, 130 interrupted
  (Ctrl-C), 128+N ended by signal N (SIGTERM 143, SIGHUP 129, SIGQUIT 131) after the same cleanup; 141
  (128+SIGPIPE) when standard output was closed before the command finished (``| head -1``).
"""

from __future__ import annotations

import os

# One BLAS thread unless the user says otherwise (before numpy loads): the fits' matrices are small, and
# OpenBLAS's threads on a loaded machine only contend (the camera's fit of 5 pictures: 6.9 s with them,
# 1.6 s without, at load 6 on 2 cores).
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import difflib  # noqa: E402
import importlib  # noqa: E402
import logging  # noqa: E402
import pkgutil  # noqa: E402
import re  # noqa: E402
import signal  # noqa: E402
import sys  # noqa: E402

from selfview import __version__  # noqa: E402
from selfview.procedures.engine import Cancelled, RaiseOnSignal  # noqa: E402
from selfview.errors import (  # noqa: E402
    AlarmError,
    CalibrationError,
    CalibrationFileError,
    CellError,
    ConfigError,
    DeviceError,
    DeviceTimeout,
    ImageError,
    LimitError,
    PictureFileError,
    ProtocolError,
)

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_USAGE = 2
EXIT_CONFIG = 3
EXIT_DEVICE = 4
EXIT_CALIBRATION = 5
EXIT_ALARM = 6
EXIT_INTERRUPTED = 130

_EXIT_FOR = [
    (Cancelled, EXIT_INTERRUPTED, "the run was interrupted; the cell was left as stated above"),
    (AlarmError, EXIT_ALARM, "stop the cell and check the camera mount"),
    (PictureFileError, EXIT_CONFIG, "give the path of a picture file (PNG, JPEG, BMP, PGM or TIFF; 8- or 16-bit)"),
    ((CalibrationError, ImageError), EXIT_CALIBRATION, "check the picture (light, focus, plate and fingers in view)"),
    ((ConfigError, CalibrationFileError), EXIT_CONFIG, "correct the file or argument named above"),
    ((DeviceTimeout, ProtocolError, DeviceError, LimitError), EXIT_DEVICE, "check the device's cable, power and URL"),
]


_THIRD_PARTY_LOGGERS = ("pymodbus", "asyncio", "matplotlib", "PIL")


def exit_code_for(exc: BaseException) -> tuple[int, str]:
    """(exit code, what to do) for an exception reaching the command line (its own ``what_to_do``, if it
    has one, before its kind's)."""
    for types, code, hint in _EXIT_FOR:
        if isinstance(exc, types):
            if isinstance(exc, Cancelled):  # ended by a signal: 128 + its number (130 for Ctrl-C)
                code = 128 + exc.signum
            return code, getattr(exc, "what_to_do", None) or hint
    return EXIT_INTERNAL, "this is a bug; please report it with the command line"


class _Parser(argparse.ArgumentParser):
    """argparse with "did you mean" for a mistyped choice (a command, a method, a format)."""

    def error(self, message):
        m = re.search(r"invalid choice: '([^']*)' \(choose from (.*)\)", message)
        if m:
            choices = re.findall(r"'([^']*)'", m.group(2)) or [c.strip() for c in m.group(2).split(",")]
            near = difflib.get_close_matches(m.group(1), choices, n=3, cutoff=0.5)
            if near:
                message += f"; did you mean {' or '.join(near)}?"
        super().error(message)


def _unrecognized(parser: argparse.ArgumentParser, extra: list[str]) -> int:
    """The usage of the command that was given and, per unknown option, the options it has that are
    nearest to it; exit status 2."""
    options = [s for a in parser._actions for s in a.option_strings]  # noqa: SLF001 (argparse has no public list)
    hints = []
    for arg in extra:
        if arg.startswith("-"):
            near = difflib.get_close_matches(arg.split("=", 1)[0], options, n=1, cutoff=0.6)
            if near:
                hints.append(f"{arg}: did you mean {' or '.join(near)}?")
    parser.print_usage(sys.stderr)
    _say(f"{parser.prog}: error: unrecognized arguments: {' '.join(extra)}"
         + "".join(f"\n  {h}" for h in hints) + f"\n  see '{parser.prog} --help'")
    return EXIT_USAGE


def _innermost(parser: argparse.ArgumentParser, args) -> argparse.ArgumentParser:
    """The parser of the deepest sub-command given (``selfview mock robot``), for its usage."""
    for _ in range(4):
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]  # noqa: SLF001
        chosen = subs and subs[0].choices.get(getattr(args, subs[0].dest, None) or "")
        if not chosen:
            break
        parser = chosen
    return parser


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="selfview",
        description=(
            "Calibration and monitoring of a self-viewing eye-on-hand robot cell: a wrist camera that "
            "keeps the gripper's fingertips in view. Without --real, commands run on the simulated cell."
        ),
        epilog=(
            "Exit codes: 0 ok, 1 internal error, 2 usage, 3 configuration or file, 4 device, "
            "5 calibration, 6 alarm, 130 interrupted, 128+N ended by signal N (143 SIGTERM, 129 SIGHUP)."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"selfview {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="log more on stderr (-v: each step and decision, -vv: debugging)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    parser.commands = sub.choices  # name -> its parser
    import selfview.procedures.commands as pkg

    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"selfview.procedures.commands.{info.name}")
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """The command line (``argv`` None: the program's own arguments, and the program ends after it)."""
    with RaiseOnSignal(keep=argv is None):
        try:
            return _main(argv)
        except KeyboardInterrupt as exc:  # before the command started (parsing, start-up)
            return 128 + getattr(exc, "signum", signal.SIGINT)


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:
        return _unrecognized(_innermost(parser.commands.get(getattr(args, "command", None)) or parser, args), extra)
    level = {0: logging.ERROR, 1: logging.INFO}.get(args.verbose, logging.DEBUG)
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s: %(message)s", stream=sys.stderr)
    logging.getLogger().setLevel(level)
    # a library's own log lines (pymodbus dumps every frame it could not parse) only with -v: the errors
    # it raises reach the operator as this command's message
    for name in _THIRD_PARTY_LOGGERS:
        logging.getLogger(name).setLevel(level if args.verbose else logging.CRITICAL + 1)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt as exc:
        signum = getattr(exc, "signum", signal.SIGINT)
        _say("selfview: interrupted" if signum == signal.SIGINT else f"selfview: terminated by {exc}")
        return 128 + signum
    except CellError as exc:
        code, hint = exit_code_for(exc)
        _say(f"selfview {args.command}: error: {exc}\n  what to do: {hint}")
        return code
    except argparse.ArgumentTypeError as exc:  # a number or name checked after parsing
        print(f"selfview {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as exc:  # a file or folder the command was given (a name too long, a read-only disk, ...)
        if isinstance(exc, BrokenPipeError):  # stdout's reader went away (``| head -1``): the run did not finish
            _stdout_gone()
            _say(f"selfview {args.command}: its standard output was closed (the reader of a pipe ended) before it "
                 "finished; what it had done stays done (its cleanup, where it has one, is said above)")
            return 128 + signal.SIGPIPE
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"selfview {args.command}: error: {where}{exc.strerror or exc}\n  what to do: correct the file or "
              "argument named above", file=sys.stderr)
        return EXIT_CONFIG
    except MemoryError:
        print(f"selfview {args.command}: error: out of memory (a file or argument far larger than the cell's)\n"
              "  what to do: correct the file or argument", file=sys.stderr)
        return EXIT_CONFIG


def _stdout_gone() -> None:
    """Point standard output at /dev/null, so that flushing it at exit raises no second EPIPE."""
    try:
        fd = os.open(os.devnull, os.O_WRONLY)
        os.dup2(fd, sys.stdout.fileno())
        os.close(fd)
    except (OSError, ValueError):
        pass


def _say(text: str) -> None:
    try:
        print(text, file=sys.stderr)
    except OSError:  # the terminal is gone (SIGHUP): the exit code still tells
        pass


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
