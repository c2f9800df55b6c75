"""Where a result came from: versions, OpenCL device, machine, time, command line, configuration.

`provenance(config)` is written into every params.json of the fitting commands and every
benchmark JSON, so a number can be traced to the code, driver and settings that produced it.
"""
from __future__ import annotations

import argparse
import dataclasses
import platform
import sys
from datetime import datetime, timezone
from pathlib import Path


def to_json(value):
    """``value`` as plain JSON data: dataclasses as dicts, tuples as lists, Paths as str, numpy
    arrays and scalars as lists and numbers, argparse Namespaces as dicts of their non-callable
    options; anything else that JSON cannot hold as its str()."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    if isinstance(value, argparse.Namespace):
        value = {k: v for k, v in vars(value).items() if not callable(v)}
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set, frozenset)):
        return [to_json(v) for v in value]
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if hasattr(value, "tolist"):          # numpy arrays and scalars
        return to_json(value.tolist())
    return str(value)


def opencl_device() -> dict:
    """The OpenCL device softras-cl uses: its name and version, its platform's name and version,
    and the driver version."""
    from softras_cl.cl.device import select_device

    d = select_device()
    return dict(name=d.name, version=d.version, platform=d.platform.name,
                platform_version=d.platform.version, driver_version=d.driver_version)


def cpu_model() -> str | None:
    """The CPU's model name (/proc/cpuinfo where there is one, else the platform module's
    processor string); None when neither tells."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def provenance(config=None) -> dict:
    """Versions (softras-cl, Python, numpy, pyopencl), the OpenCL platform, device and driver,
    the OS and CPU, the time (UTC, ISO 8601), the command line and ``config`` (the full effective
    configuration of the run, converted by `to_json`)."""
    import numpy
    import pyopencl

    from softras_cl import __version__

    device = opencl_device()
    return dict(softras_cl_version=__version__, python=platform.python_version(),
                numpy=numpy.__version__, pyopencl=pyopencl.VERSION_TEXT,
                platform=dict(name=device["platform"], version=device["platform_version"]),
                device=dict(name=device["name"], version=device["version"]),
                driver=device["driver_version"], os=platform.platform(), cpu=cpu_model(),
                time=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                command_line=list(sys.argv), config=to_json(config))
