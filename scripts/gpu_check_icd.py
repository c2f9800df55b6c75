"""Find a GPU vendor's OpenCL driver library and register it as an ICD for the OpenCL loader.

Used by scripts/gpu_check.sh on machines where the GPU driver is installed but no OpenCL ICD
file names it (containers that mount NVIDIA's driver folders, say, without /etc/OpenCL/vendors).
Standard library only: it runs before pyopencl can see any device.

    python3 scripts/gpu_check_icd.py --vendors DIR --report FILE.json [--library NAME]

Looks for the library (default NVIDIA's libnvidia-opencl.so.1) in the usual driver folders, then
in `ldconfig -p`, then by a walk over the file system that stops after --walk-seconds. Writes DIR
with a copy of every ICD file of /etc/OpenCL/vendors (so pointing OCL_ICD_VENDORS at DIR hides
none of them) plus VENDOR.icd naming the library found, and FILE.json saying what was searched
and found. Prints the library's folder when found (for LD_LIBRARY_PATH: the driver's other
libraries sit beside it), nothing when not; either way the exit code is 0 (whether some OpenCL
GPU is there after all is for `softras-cl devices` to say).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

NVIDIA_LIBRARY = "libnvidia-opencl.so.1"
# Folders where drivers put their libraries, relative to the file system's root (checked first).
DRIVER_FOLDERS = ("usr/lib/x86_64-linux-gnu", "usr/local/nvidia/lib64", "usr/local/nvidia/lib",
                  "usr/lib64", "usr/lib", "lib/x86_64-linux-gnu", "lib64")
# Never walked (at the top of the root): kernel, device and runtime file systems (huge or endless).
WALK_EXCLUDED = ("proc", "sys", "dev", "run")
SYSTEM_VENDORS = "etc/OpenCL/vendors"
WALK_SECONDS = 20.0


def is_shared_library(path: Path) -> bool:
    """True if `path` is a file that starts like an ELF binary (not a stray copy or stub)."""
    try:
        with open(path, "rb") as f:
            return f.read(4) == b"\x7fELF"
    except OSError:
        return False


def in_driver_folders(name: str, root: Path, extra_folders=()) -> list[Path]:
    """ELF files called `name` in DRIVER_FOLDERS under `root`, then in `extra_folders`
    (absolute, e.g. LD_LIBRARY_PATH's entries), in that order, without repeats."""
    folders = [root / f for f in DRIVER_FOLDERS] + [Path(f) for f in extra_folders if f]
    found = []
    for folder in folders:
        path = folder / name
        if is_shared_library(path) and path not in found:
            found.append(path)
    return found


def in_ldconfig_cache(name: str, ldconfig_text: str) -> list[Path]:
    """Paths that `ldconfig -p` output (`ldconfig_text`) gives for library `name`, e.g. from
    '\tlibnvidia-opencl.so.1 (libc6,x86-64) => /usr/lib/x86_64-linux-gnu/libnvidia-opencl.so.1'."""
    paths = []
    for line in ldconfig_text.splitlines():
        library, arrow, path = line.strip().partition(" => ")
        if arrow and library.split(" (")[0] == name:
            paths.append(Path(path.strip()))
    return paths


def ldconfig_text() -> str:
    """`ldconfig -p` output, or '' where ldconfig is missing or fails."""
    try:
        return subprocess.run(["ldconfig", "-p"], capture_output=True, text=True, timeout=20).stdout
    except (OSError, subprocess.SubprocessError):
        return ""


def walk_for(name: str, root: Path, seconds: float) -> tuple[list[Path], bool]:
    """ELF files called `name` anywhere under `root` (symbolic links to folders not followed,
    the folders of WALK_EXCLUDED at the top skipped); stops after `seconds`. Returns (paths
    found, whether the walk finished)."""
    deadline = time.monotonic() + seconds
    found = []
    for folder, subfolders, files in os.walk(root):
        if Path(folder) == root:
            subfolders[:] = [d for d in subfolders if d not in WALK_EXCLUDED]
        if name in files and is_shared_library(Path(folder) / name):
            found.append(Path(folder) / name)
        if time.monotonic() > deadline:
            return found, False
    return found, True


def find_library(name: str, root: Path, ldconfig: str, walk_seconds: float,
                 extra_folders=()) -> dict:
    """Search for library `name` (driver folders, then the ldconfig cache, then a bounded walk,
    each only if the one before found nothing). Returns dict(library, found: str | None,
    candidates: [str], searched: [str], walk_complete: bool | None)."""
    searched = ["driver folders"]
    candidates = in_driver_folders(name, root, extra_folders)
    if not candidates:
        searched.append("ldconfig -p")
        candidates = [p for p in in_ldconfig_cache(name, ldconfig) if is_shared_library(p)]
    walk_complete = None
    if not candidates:
        searched.append(f"walk of {root} (at most {walk_seconds:g} s)")
        candidates, walk_complete = walk_for(name, root, walk_seconds)
    return dict(library=name, found=str(candidates[0]) if candidates else None,
                candidates=[str(p) for p in candidates], searched=searched,
                walk_complete=walk_complete)


def write_vendors(vendors: Path, system_vendors: Path, library: str | None, vendor: str) -> list[str]:
    """Fill folder `vendors` with the ICD files of `system_vendors` (if it exists) and, when
    `library` is given, VENDOR.icd holding its absolute path. Returns the ICD file names written."""
    vendors.mkdir(parents=True, exist_ok=True)
    written = []
    if system_vendors.is_dir():
        for icd in sorted(system_vendors.glob("*.icd")):
            shutil.copyfile(icd, vendors / icd.name)
            written.append(icd.name)
    if library:
        (vendors / f"{vendor}.icd").write_text(library + "\n")
        written.append(f"{vendor}.icd")
    return written


def icd_contents(vendors: Path) -> dict[str, str]:
    """{file name: the library it names} for the ICD files in `vendors`."""
    return {icd.name: icd.read_text().strip() for icd in sorted(vendors.glob("*.icd"))}


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--vendors", type=Path, required=True, help="folder to fill with ICD files")
    p.add_argument("--report", type=Path, required=True, help="JSON file saying what was found")
    p.add_argument("--library", default=NVIDIA_LIBRARY, help=f"file name to find (default {NVIDIA_LIBRARY})")
    p.add_argument("--vendor", default="nvidia", help="name of the ICD file written (default nvidia)")
    p.add_argument("--root", type=Path, default=Path("/"), help="file system root to search (default /)")
    p.add_argument("--walk-seconds", type=float, default=WALK_SECONDS,
                   help=f"time limit of the file system walk (default {WALK_SECONDS:g})")
    args = p.parse_args(argv)
    if args.walk_seconds < 0:
        p.error(f"--walk-seconds must be >= 0, got {args.walk_seconds}")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    library_path = os.environ.get("LD_LIBRARY_PATH", "").split(":")
    report = find_library(args.library, args.root, ldconfig_text(), args.walk_seconds, library_path)
    write_vendors(args.vendors, args.root / SYSTEM_VENDORS, report["found"], args.vendor)
    report.update(vendors=str(args.vendors), icd_files=icd_contents(args.vendors))
    args.report.write_text(json.dumps(report, indent=2) + "\n")
    if report["found"] is not None:
        print(Path(report["found"]).parent)
    return 0


if __name__ == "__main__":
    sys.exit(main())
