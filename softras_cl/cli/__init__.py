"""The `softras-cl` command line: one module per command, listed in COMMANDS.

Each command module has `register(subparsers)`, which adds its parser (every option with a help
text) and sets `func`, a callable (args) -> exit code. Modules import their heavy dependencies
inside `func`, so building the parser (and `softras-cl --help`) stays fast.

`main` is the one place errors become exit codes: a command raises (softras_cl.errors, or a
ValueError/OSError about its input) and `main` prints one line to stderr and returns the code
of softras_cl.errors; an unexpected exception is reported as an internal error (the traceback
with -vv). SIGTERM stops a command the way Ctrl-C does.
"""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import traceback
from contextlib import contextmanager
from importlib import import_module

from softras_cl import __version__
from softras_cl.errors import (EXIT_INPUT, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_RESOURCE,
                               SoftrasError)

# command name -> module of softras_cl.cli (or softras_cl.bench) that registers it
COMMANDS = {
    "devices": "softras_cl.cli.devices",
    "demo": "softras_cl.cli.demo",
    "render": "softras_cl.cli.render",
    "compare": "softras_cl.cli.compare",
    "detect-landmarks": "softras_cl.cli.detect_landmarks",
    "fit-face": "softras_cl.cli.fit_face",
    "fit-body": "softras_cl.cli.fit_body",
    "track-face": "softras_cl.cli.track_face",
    "bench": "softras_cl.bench",
}


LOG_HANDLER = "softras-cl command line"   # name of the stderr handler main() installs


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The `softras-cl` parser: global options, then one subcommand of COMMANDS; with `command`
    (one of COMMANDS) only that one is registered, so a run imports only its own module."""
    parser = argparse.ArgumentParser(prog="softras-cl",
                                     description="Differentiable soft rasterizer in OpenCL.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    loudness = parser.add_mutually_exclusive_group()
    loudness.add_argument("-v", "--verbose", action="count", default=0,
                          help="log more to stderr: -v the OpenCL device and steps, -vv debug details "
                               "such as kernel builds (give before the command)")
    loudness.add_argument("-q", "--quiet", action="store_true",
                          help="log errors only, no warnings (give before the command)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                help="one of: " + ", ".join(COMMANDS))
    for name, module in COMMANDS.items():
        if command in (None, name):
            import_module(module).register(sub)
    return parser


def command_of(argv: list[str]) -> str | None:
    """The command an argument list runs (its first word that is not an option: the global
    options take no values), or None when that is not one of COMMANDS."""
    words = [a for a in argv if not a.startswith("-")]
    return words[0] if words and words[0] in COMMANDS else None


def configure_logging(verbose: int = 0, quiet: bool = False) -> None:
    """Log the package's records to stderr at WARNING, INFO (verbose 1), DEBUG (verbose >= 2) or
    ERROR (quiet), replacing the handler of an earlier call."""
    level = logging.ERROR if quiet else {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)
    logger = logging.getLogger("softras_cl")
    for old in [h for h in logger.handlers if h.get_name() == LOG_HANDLER]:
        logger.removeHandler(old)
    handler = logging.StreamHandler(sys.stderr)
    handler.set_name(LOG_HANDLER)
    handler.setFormatter(logging.Formatter("softras-cl: %(levelname)s: %(name)s: %(message)s"))
    logger.addHandler(handler)
    logger.setLevel(level)


def exit_code(error: BaseException) -> int:
    """The documented exit code (softras_cl.errors) for an exception that ended a command."""
    if isinstance(error, KeyboardInterrupt):
        return EXIT_INTERRUPTED
    if isinstance(error, SoftrasError):
        return error.exit_code
    if isinstance(error, MemoryError) or type(error).__module__.startswith("pyopencl"):
        return EXIT_RESOURCE
    if isinstance(error, (ValueError, OSError)):
        return EXIT_INPUT
    return EXIT_INTERNAL


def _report(command: str, error: BaseException, verbose: int) -> int:
    """Print one line about ``error`` to stderr (the traceback too when it is a bug and -vv was
    given); return its exit code."""
    code = exit_code(error)
    prefix = f"softras-cl {command}".rstrip()
    if code == EXIT_INTERRUPTED:
        print(f"{prefix}: interrupted", file=sys.stderr)
    elif code == EXIT_INTERNAL:
        if verbose >= 2:
            traceback.print_exception(error, file=sys.stderr)
        print(f"{prefix}: internal error: {type(error).__name__}: {error} "
              f"({'see the traceback above' if verbose >= 2 else 'run with -vv for the traceback'}; "
              f"please report it)", file=sys.stderr)
    else:
        print(f"{prefix}: {error}", file=sys.stderr)
    return code


class _SigtermAsInterrupt:
    """While active (main thread only), SIGTERM raises KeyboardInterrupt like Ctrl-C, so a
    terminated run stops cleanly and keeps its results."""

    def __enter__(self):
        self.previous = None
        if threading.current_thread() is threading.main_thread():
            self.previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
        return self

    def __exit__(self, *exc):
        if self.previous is not None:
            signal.signal(signal.SIGTERM, self.previous)
        return False


# numpy's BLAS runs on one thread under the command line (unless the user sets these): the fits'
# small matrix products gain nothing from more, a second thread waiting for a busy core stalls
# them, and the last bits of a fit would otherwise depend on the machine's core count.
SINGLE_THREAD_BLAS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# whether the user set them, read before main sets them (a later main in the same process sees ours)
_USER_SET_BLAS = any(variable in os.environ for variable in SINGLE_THREAD_BLAS)


@contextmanager
def single_thread_blas():
    """Within the block numpy's BLAS runs on one thread, unless the user set SINGLE_THREAD_BLAS.
    The variables are read when numpy loads: they do it when main runs first (the console
    script). When numpy was loaded before (a program that imports softras_cl and then calls
    main), its BLAS is limited at run time instead (threadpoolctl), so a fit gives the same bits
    whatever was imported first (it did not: the astronaut's landmark error moved by 0.02 px)."""
    for variable in SINGLE_THREAD_BLAS:
        os.environ.setdefault(variable, "1")
    if _USER_SET_BLAS or "numpy" not in sys.modules:
        yield
        return
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `softras-cl` console script; returns the exit code."""
    command, verbose = "", 0
    with single_thread_blas(), _SigtermAsInterrupt():
        try:
            argv = sys.argv[1:] if argv is None else list(argv)
            args = build_parser(command_of(argv)).parse_args(argv)
            command = " ".join(n for n in (args.command, getattr(args, "benchmark", None)) if n)
            verbose = args.verbose
            configure_logging(args.verbose, args.quiet)
            return args.func(args)
        except (Exception, KeyboardInterrupt) as error:    # the top of the program: one line
            return _report(command, error, verbose)


if __name__ == "__main__":
    sys.exit(main())
