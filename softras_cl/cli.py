"""`softras-cl` command line.

Each subcommand is one registration function `register_<name>(subparsers)` that adds its parser
(every option with a help text) and sets `func`, a callable (args) -> exit code. Add a subcommand
by writing such a function (here or in its own module) and listing it in `SUBCOMMANDS`.
Heavy imports go inside the `func`, so `softras-cl --help` stays fast.
"""
from __future__ import annotations

import argparse
import json
import sys


def _run_devices(args: argparse.Namespace) -> int:
    from . import device

    try:
        rows = device.list_devices()
    except RuntimeError as e:
        print(f"softras-cl: {e}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        yn = {True: "yes", False: "no"}
        table = [("used", "P:D", "type", "platform", "version", "device", "CUs", "fp64", "int64 atomics")]
        table += [("*" if r["chosen"] else "", f"{r['platform_index']}:{r['device_index']}", r["type"],
                   r["platform_name"], r["platform_version"].split("  ")[0][:40], r["device_name"],
                   str(r["compute_units"]), yn[r["fp64"]], yn[r["int64_atomics"]]) for r in rows]
        widths = [max(len(row[i]) for row in table) for i in range(len(table[0]))]
        for row in table:
            print("  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip())
    try:
        device.select_device()
    except ValueError as e:  # a bad SOFTRAS_CL_DEVICE / PYOPENCL_CTX: listed above, none used
        print(f"softras-cl: {e}", file=sys.stderr)
        return 2
    return 0


def register_devices(sub) -> None:
    p = sub.add_parser("devices", help="list OpenCL platforms/devices and mark the one used",
                       description="List every OpenCL platform and device with fp64 and 64-bit "
                                   "atomics support; '*' marks the device softras-cl uses "
                                   "(choose with SOFTRAS_CL_DEVICE='P:D' or a name substring).")
    p.add_argument("--json", action="store_true", help="print the list as JSON instead of a table")
    p.set_defaults(func=_run_devices)


def register_bench(sub) -> None:
    """`softras-cl bench raster`: options and runner live in softras_cl/bench.py."""
    from .bench import register

    register(sub)


def register_demo(sub) -> None:
    """`softras-cl demo`: options and runner live in softras_cl/demo.py."""
    from .demo import register

    register(sub)


def register_fit_face(sub) -> None:
    """`softras-cl fit-face`: options and runner live in fitting/face_cli.py."""
    from .fitting.face_cli import register

    register(sub)


def register_fit_body(sub) -> None:
    """`softras-cl fit-body`: options and runner live in fitting/body_cli.py."""
    from .fitting.body_cli import register

    register(sub)


def register_scene_commands(sub) -> None:
    from .scene_cli import register_compare, register_render

    register_render(sub)
    register_compare(sub)


def register_detect_landmarks(sub) -> None:
    """`softras-cl detect-landmarks`: options and runner live in softras_cl/landmark_detect.py."""
    from .landmark_detect import register

    register(sub)


# name -> registration function. `demo` (render a built-in mesh to a PNG) and `bench`
# (`softras-cl bench raster`) are added here by their modules' register functions.
SUBCOMMANDS = {
    "devices": register_devices,
    "demo": register_demo,
    "bench": register_bench,
    "render, compare": register_scene_commands,
    "detect-landmarks": register_detect_landmarks,
    "fit-face": register_fit_face,
    "fit-body": register_fit_body,
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="softras-cl",
                                     description="Differentiable soft rasterizer in OpenCL.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True,
                                help="one of: " + ", ".join(SUBCOMMANDS))
    for register in SUBCOMMANDS.values():
        register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `softras-cl` console script; returns the exit code."""
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
