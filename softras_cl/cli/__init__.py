"""The `softras-cl` command line: one module per command, listed in COMMANDS.

Each command module has `register(subparsers)`, which adds its parser (every option with a help
text) and sets `func`, a callable (args) -> exit code. Modules import their heavy dependencies
inside `func`, so building the parser (and `softras-cl --help`) stays fast.
"""
from __future__ import annotations

import argparse
import logging
import sys
from importlib import import_module

from softras_cl import __version__

# command name -> module of softras_cl.cli (or softras_cl.bench) that registers it
COMMANDS = {
    "devices": "softras_cl.cli.devices",
    "demo": "softras_cl.cli.demo",
    "render": "softras_cl.cli.render",
    "compare": "softras_cl.cli.compare",
    "detect-landmarks": "softras_cl.cli.detect_landmarks",
    "fit-face": "softras_cl.cli.fit_face",
    "fit-body": "softras_cl.cli.fit_body",
    "bench": "softras_cl.bench",
}


LOG_HANDLER = "softras-cl command line"   # name of the stderr handler main() installs


def build_parser() -> argparse.ArgumentParser:
    """The `softras-cl` parser: global options, then one subcommand of COMMANDS."""
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
    for module in COMMANDS.values():
        import_module(module).register(sub)
    return parser


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


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `softras-cl` console script; returns the exit code."""
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
