"""The `papl-map` command line. The only place that turns PaplError into one line and an exit code.

Each command lives in its own module `papl_mapper.cli.<name>` exposing `add_parser(subparsers)`,
which registers the sub-command and sets `func(args) -> int` on it.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import math
import signal
import sys
import threading
from typing import NoReturn

from papl_mapper import __version__
from papl_mapper.errors import InputError, PaplError

#: Sub-command modules, in the order `--help` lists them.
COMMANDS = ("run", "batch", "scale", "info", "synth", "eval", "export", "render", "report", "view")

log = logging.getLogger("papl_mapper")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="papl-map",
        description="Principal-axis-anchored point-line mapping of recorded walkthroughs.",
    )
    parser.add_argument("--version", action="version", version=f"papl-mapper {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"papl_mapper.cli.{name}").add_parser(sub)
    return parser


def _configure_logging(debug: bool, quiet: bool) -> None:
    level = logging.DEBUG if debug else logging.WARNING if quiet else logging.INFO
    handler = logging.StreamHandler(sys.stderr)
    handler.setLevel(level)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s" if debug else "%(message)s"))
    root = logging.getLogger("papl_mapper")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False
    # OpenCV's own warnings (a truncated PNG) would repeat our one-line messages in another format
    import cv2

    cv2.utils.logging.setLogLevel(
        cv2.utils.logging.LOG_LEVEL_INFO if debug else cv2.utils.logging.LOG_LEVEL_ERROR
    )


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so that a run stops the same clean way (outputs kept, checkpoints)."""


def _terminate(signum: int, frame: object) -> None:
    raise Terminated()


def entry() -> NoReturn:
    """The `papl-map` command: `main`, then the exit, without the interpreter's last garbage collection
    over every object the job made (frozen: the process ends anyway; about 0.1 s of a mapping run)."""
    code = main()
    gc.freeze()
    sys.exit(code)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    _configure_logging(args.debug, args.quiet)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    if threading.current_thread() is not threading.main_thread():  # signals belong to the main thread
        return _call(args)
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        return _call(args)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _call(args: argparse.Namespace) -> int:
    """Run the command; every expected failure becomes one line on stderr and an exit code."""
    try:
        _check_numbers(args)
        return int(args.func(args) or 0)
    except PaplError as exc:
        if args.debug:
            raise
        return _fail(args, str(exc), exc.exit_code)
    except Terminated:
        print(f"papl-map {args.command}: terminated (SIGTERM)", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print(f"papl-map {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 0
    except OSError as exc:  # a file the library did not anticipate (a disappearing disk)
        if args.debug:
            raise
        where = f"{exc.filename}: " if exc.filename else ""
        return _fail(args, f"{where}{exc.strerror or exc}", 2)
    except MemoryError:
        if args.debug:
            raise
        return _fail(args, "out of memory (an input is too large for this machine)", 2)


def _check_numbers(args: argparse.Namespace) -> None:
    """Every number on the command line is finite: argparse's float() takes 'nan' and 'inf'."""
    for name, value in vars(args).items():
        if isinstance(value, float) and not math.isfinite(value):
            raise InputError(f"--{name.replace('_', '-')} {value}: give a finite number")


def _fail(args: argparse.Namespace, message: str, code: int) -> int:
    """Print the one error line (newlines in a message folded, so it stays one line)."""
    line = " ".join(message.split())
    print(f"papl-map {args.command}: error: {line}", file=sys.stderr)
    return code
