"""The ``icefab`` command.

Each subcommand lives in its own module ``icefab.cli.<name>`` and exposes
``add_parser(subparsers)`` that registers it and sets ``func(args) -> int``. This module
is the only place that prints errors and chooses exit codes: an ``IcefabError`` becomes one
line on stderr and exit status 2, and so does an operating-system error (disk full, no
permission); Ctrl-C exits with 130.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import re
import signal
import sys
import threading

from icefab.cli.common import (Terminated, check_output_dir, check_terminated,
                               forget_terminated, forked_end, terminate)
from icefab.cli.compiling import compile_notice
from icefab.errors import IcefabError, interruption

# Subcommand modules ``icefab.cli.<name>_cmd``, in the order shown by --help. Add a command
# here when its module lands: a listed module that cannot be imported is an error (it was
# skipped silently, so a misspelled name dropped a command unnoticed).
SUBCOMMANDS = ("demo", "slice", "paths", "plan", "valves", "simulate", "tune", "calibrate",
               "build", "export", "cell")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="icefab",
        description="Turn a CAD mesh into a robotic rapid-freeze-prototyping build.")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug details")
    parser.add_argument("--version", action="version", version=f"icefab {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in SUBCOMMANDS:
        importlib.import_module(f"icefab.cli.{name}_cmd").add_parser(sub)
    _negative_numbers_are_values(parser)
    _verbose_after_the_command(parser)
    return parser


def _verbose_after_the_command(parser: argparse.ArgumentParser) -> None:
    """Let ``-v`` follow the command too (``icefab slice m.stl -o out -v``: "unrecognized
    arguments: -v", a docs hunt's): every subparser takes it, with no default of its own,
    so ``icefab -v slice ...`` still sets it."""
    stack = [action.choices.values() for action in parser._actions
             if isinstance(action, argparse._SubParsersAction)]
    while stack:
        for p in stack.pop():
            p.add_argument("-v", "--verbose", action="store_true", default=argparse.SUPPRESS,
                           help="log debug details (also taken before the command)")
            stack.extend(action.choices.values() for action in p._actions
                         if isinstance(action, argparse._SubParsersAction))


#: A word that starts like a negative number, "-1e9" or "-50,-50,50,50" included.
_NEGATIVE_VALUE = re.compile(r"^-\.?\d")


def _negative_numbers_are_values(parser: argparse.ArgumentParser) -> None:
    """Let ``--zbase -1e9`` and ``--bounds -50,-50,50,50`` be values: argparse takes a word
    for an option unless it looks like a plain negative number ("-5", "-0.5"), and said
    "expected one argument" to a tester's two (no icefab option starts with a digit).
    Uses argparse's matcher for that, on every parser and subparser."""
    stack = [parser]
    while stack:
        p = stack.pop()
        p._negative_number_matcher = _NEGATIVE_VALUE
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                stack.extend(action.choices.values())


def _version() -> str:
    from icefab import __version__
    return __version__


def _stdout_gone() -> bool:
    """Whether standard output's reader went away (a pipe with no reader polls as an
    error); if so, standard output is pointed at /dev/null, so that the interpreter's own
    flush at exit stays quiet. (A broken pipe may also be a cell's link.)"""
    import select

    try:
        fd = sys.stdout.fileno()
        poll = select.poll()
        poll.register(fd, select.POLLOUT)
        gone = any(ev & select.POLLERR for _fd, ev in poll.poll(0))
        if gone:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, fd)
            os.close(null)
        return gone
    except (OSError, ValueError, AttributeError):   # not a real file (a test's stand-in)
        return False


def _on_sigterm(signum, frame) -> None:
    if not forked_end(_on_sigterm.pid):
        terminate()


def main(argv: list[str] | None = None) -> int:
    for name in ("stdout", "stderr"):
        if getattr(sys, name) is None:
            # started with the stream closed ('>&-'): Python gives None, and the command
            # ended in an AttributeError after its work (hunt P); /dev/null takes the free
            # descriptor, so no result file opened later gets it
            setattr(sys, name, os.fdopen(os.open(os.devnull, os.O_WRONLY), "w"))
    forget_terminated()
    if threading.current_thread() is not threading.main_thread():
        return _main(argv)
    _on_sigterm.pid = os.getpid()
    old = signal.signal(signal.SIGTERM, _on_sigterm)
    hook = threading.excepthook
    threading.excepthook = _quiet_broken_pool(hook)
    try:
        code = _main(argv)
    finally:
        signal.signal(signal.SIGTERM, old)
    if argv is None and code in (130, 143):
        # the program (not a caller of main) ends here, its clean-up done: SIGTERM to the
        # process group ('timeout', a service stop) ends the pool's workers first, the
        # pool's own thread then fails on the items the command cancelled (CPython 3.11)
        # before it closes its queue, and the interpreter waited for that queue at exit
        # for ever (a hunt's, 4 runs in 10)
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    threading.excepthook = hook
    return code


def _quiet_broken_pool(hook):
    """A ``threading.excepthook`` that leaves out the traceback of a process pool's manager
    thread failing on cancelled items after its workers were ended (see :func:`main`;
    the command says in one line that it was interrupted or terminated) and hands every
    other exception to ``hook``."""
    import traceback
    from concurrent.futures import InvalidStateError

    def quiet(args: threading.ExceptHookArgs) -> None:
        if args.exc_type is not None and issubclass(args.exc_type, InvalidStateError) and any(
                "concurrent/futures/process.py" in f.filename
                for f in traceback.extract_tb(args.exc_traceback)):
            return
        hook(args)
    return quiet


def _stopped(who: str, exc: KeyboardInterrupt) -> int:
    """Say that Ctrl-C or SIGTERM ended the command; its exit status (130, 143)."""
    term = isinstance(exc, Terminated)
    print(f"{who}: {'terminated' if term else 'interrupted'}", file=sys.stderr)
    return 143 if term else 130


def _main(argv: list[str] | None) -> int:
    try:
        # SIGTERM while the options were read and the command's modules imported (the
        # first second) ended in a Terminated traceback and exit 1 (a hunt's)
        parser = build_parser()
        args = parser.parse_args(argv)
        logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                            format="%(levelname)s: %(message)s")
        # -v is icefab's: matplotlib's font search alone printed 292 debug lines (hunt P)
        logging.getLogger("matplotlib").setLevel(logging.WARNING)
    except KeyboardInterrupt as exc:
        return _stopped("icefab", exc)
    try:
        if getattr(args, "out", None) is not None:  # before any work, not after a long job
            check_output_dir(args.out)
        with compile_notice():  # the first run's silent numba compiling, said plainly
            rc = int(args.func(args) or 0)
        sys.stdout.flush()    # a reader that left shows here, not in the exit's own flush
        # a SIGTERM lost after the last progress report (plan's pictures) or in a command
        # that reports none (tune, calibrate, export) let the command end with 0, as if no
        # stop had been asked for (session 42's hunt): it ends as terminated, its files
        # written whole (a build's runner, which took such a stop over, said so itself)
        if rc not in (130, 143):
            check_terminated()
        return rc
    except IcefabError as exc:
        print(f"icefab {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError as exc:
        if _stdout_gone():
            # the reader of the output left ('icefab build --status B | head -1'): nothing
            # to say, and nobody to say it to ("error: Broken pipe", exit 2, before)
            return 141
        print(f"icefab {args.command}: error: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # disk full, permissions, a folder where a file should be
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"icefab {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        return _stopped(f"icefab {args.command}", exc)
    except Exception as exc:
        # Ctrl-C or SIGTERM that C code or the interpreter wrapped in another error: while
        # numba loaded a cached kernel "SystemError: CPUDispatcher(...) returned a result
        # with an exception set", in a class's __set_name__ a RuntimeError, in
        # matplotlib's first import an ImportError; each a traceback and exit 1 (hunts')
        stop = interruption(exc)
        if stop is None:
            raise
        return _stopped(f"icefab {args.command}", stop)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
