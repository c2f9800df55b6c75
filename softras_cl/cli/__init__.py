"""The `softras-cl` command line: one module per command, listed in COMMANDS.

Each command module has `register(subparsers)`, which adds its parser (every option with a help
text) and sets `func`, a callable (args) -> exit code. Modules import their heavy dependencies
inside `func`, so building the parser (and `softras-cl --help`) stays fast.
"""
from __future__ import annotations

import argparse
import sys
from importlib import import_module

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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="softras-cl",
                                     description="Differentiable soft rasterizer in OpenCL.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                help="one of: " + ", ".join(COMMANDS))
    for module in COMMANDS.values():
        import_module(module).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `softras-cl` console script; returns the exit code."""
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
