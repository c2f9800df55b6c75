"""`softras-cl devices`: list OpenCL platforms and devices and mark the one softras-cl uses."""
from __future__ import annotations

import argparse
import json

DESCRIPTION = ("List every OpenCL platform and device with fp64 and 64-bit atomics support; '*' marks "
               "the device softras-cl uses (choose with SOFTRAS_CL_DEVICE='P:D' or a name substring).")


def _run(args: argparse.Namespace) -> int:
    from softras_cl.cl import device

    rows = device.list_devices()       # DeviceError (exit 4) when there is no platform
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
        for r in (r for r in rows if r["compiler_fault"]):
            print(f"{r['platform_index']}:{r['device_index']} cannot compile kernels (never chosen by default): "
                  f"{r['compiler_fault']}")
    device.select_device()   # a bad SOFTRAS_CL_DEVICE / PYOPENCL_CTX: InputError (exit 2), after the list
    return 0


def register(sub) -> None:
    p = sub.add_parser("devices", help="list OpenCL platforms/devices and mark the one used",
                       description=DESCRIPTION)
    p.add_argument("--json", action="store_true", help="print the list as JSON instead of a table")
    p.set_defaults(func=_run)
