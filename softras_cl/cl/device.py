"""OpenCL platform/device choice and capability queries.

Order of choice (`select_device`):
1. `SOFTRAS_CL_DEVICE`: "P:D" (platform and device index, "P" alone means device 0) or a
   case-insensitive substring of "platform name + platform version + device name", e.g. "pocl 3.1".
2. `PYOPENCL_CTX`: pyopencl's format, "P:D" where each part is an index or a name substring.
3. The best device found whose compiler works (`compiler_fault`: a PoCL whose LLVM does not know
   the CPU fails every build with "unknown target CPU 'generic'"): GPUs, then CPUs (CPU platforms
   ranked by `PREFERRED_CPU_PLATFORMS`), then anything else; ties keep pyopencl's order.

`resolve_context` turns a user's optional device, context and queue into a consistent triple.
"""
from __future__ import annotations

import functools
import logging
import os
import re
import warnings

import pyopencl as cl

from softras_cl.cl.layout import LANES
from softras_cl.errors import DeviceError, InputError

logger = logging.getLogger(__name__)

ENV_VAR = "SOFTRAS_CL_DEVICE"

# Substrings of platform.version, best first; CPU platforms matching none come after these.
PREFERRED_CPU_PLATFORMS = ("PoCL 3.1",)

NO_PLATFORM_HELP = (
    "No OpenCL platform found. Install one: `pip install pocl-binary-distribution` (CPU, any OS), "
    "or `apt-get install pocl-opencl-icd` (Debian/Ubuntu CPU driver), or your GPU vendor's "
    "OpenCL driver (NVIDIA, AMD ROCm, Intel compute-runtime).")

_contexts: dict = {}


@functools.cache
def _entries() -> list[tuple[int, int, cl.Platform, cl.Device]]:
    """All (platform index, device index, platform, device); RuntimeError if there are none.
    Enumerated once per process (a few ms on PoCL, and every renderer asks for its device)."""
    try:
        platforms = cl.get_platforms()
    except cl.Error as e:
        raise DeviceError(f"{NO_PLATFORM_HELP} (pyopencl: {e})") from e
    out = []
    for pi, p in enumerate(platforms):
        try:
            devices = p.get_devices()
        except cl.Error:  # a platform with no usable device
            continue
        out.extend((pi, di, p, d) for di, d in enumerate(devices))
    if not out:
        raise DeviceError(NO_PLATFORM_HELP)
    return out


def _type_name(device: cl.Device) -> str:
    if device.type & cl.device_type.GPU:
        return "GPU"
    if device.type & cl.device_type.CPU:
        return "CPU"
    if device.type & cl.device_type.ACCELERATOR:
        return "ACCELERATOR"
    return "OTHER"


def _label(p: cl.Platform, d: cl.Device) -> str:
    return f"{p.name} {p.version} {d.name}"


def _rank(entry) -> tuple[int, int]:
    """Sort key, smaller is better: (device type, CPU platform preference)."""
    _, _, p, d = entry
    kind = {"GPU": 0, "CPU": 1}.get(_type_name(d), 2)
    pref = next((i for i, s in enumerate(PREFERRED_CPU_PLATFORMS) if s.lower() in p.version.lower()),
                len(PREFERRED_CPU_PLATFORMS))
    return kind, pref if kind == 1 else 0


def _available(entries) -> str:
    return "; ".join(f"{pi}:{di} = {_label(p, d)}" for pi, di, p, d in entries)


def _by_index(entries, pi: int, di: int):
    return next((e for e in entries if e[0] == pi and e[1] == di), None)


def _from_softras_env(entries, value: str):
    m = re.fullmatch(r"\s*(\d+)\s*(?::\s*(\d+)\s*)?", value)
    if m:
        found = _by_index(entries, int(m[1]), int(m[2] or 0))
    else:
        matches = [e for e in entries if value.strip().lower() in _label(e[2], e[3]).lower()]
        found = min(matches, key=_rank) if matches else None
    if found is None:
        raise InputError(f"{ENV_VAR}={value!r} matches no OpenCL device. Use 'P:D' indices or a "
                         f"substring of platform name+version+device name. Available: "
                         f"{_available(entries)}")
    return found


def _from_pyopencl_env(entries, value: str):
    """pyopencl's PYOPENCL_CTX: "P[:D]", each part an index or a case-insensitive name substring."""
    p_part, _, d_part = (part.strip() for part in value.partition(":"))

    def ok(part: str, index: int, name: str) -> bool:
        return not part or (int(part) == index if part.isdigit() else part.lower() in name.lower())

    matches = [e for e in entries if ok(p_part, e[0], e[2].name) and ok(d_part, e[1], e[3].name)]
    if not matches:
        raise InputError(f"PYOPENCL_CTX={value!r} matches no OpenCL device. "
                         f"Available: {_available(entries)}")
    return matches[0]


PROBE_KERNEL = "__kernel void probe(__global float *x) { x[get_global_id(0)] *= 2.0f; }"


@functools.cache
def _compiler_fault(platform: cl.Platform, device: cl.Device) -> str | None:
    with warnings.catch_warnings():         # pyopencl warns about the failed build's log as well
        warnings.simplefilter("ignore")
        try:
            cl.Program(cl.Context([device]), PROBE_KERNEL).build()
        except cl.Error as e:
            lines = [line.strip() for line in str(e).splitlines() if "error" in line.lower()]
            return (lines[-1] if lines else str(e).strip().splitlines()[0])[:200]
    return None


def compiler_fault(device: cl.Device) -> str | None:
    """Why ``device``'s OpenCL compiler cannot build a trivial kernel (its first error line), or
    None when it can. Probed once per device and process (tens of ms on PoCL)."""
    return _compiler_fault(device.platform, device)


def _usable_best(entries):
    """The best-ranked device whose compiler works; DeviceError naming each fault when none does."""
    faults = []
    for entry in sorted(entries, key=_rank):
        fault = compiler_fault(entry[3])
        if fault is None:
            return entry
        faults.append(f"{entry[0]}:{entry[1]} {_label(entry[2], entry[3])}: {fault}")
        logger.info("OpenCL device %d:%d cannot compile kernels, skipped: %s", entry[0], entry[1], fault)
    raise DeviceError("no OpenCL device can compile kernels: " + "; ".join(faults))


def _select(entries):
    value = os.environ.get(ENV_VAR, "").strip()
    if value:
        return _from_softras_env(entries, value)
    value = os.environ.get("PYOPENCL_CTX", "").strip()
    if value:
        return _from_pyopencl_env(entries, value)
    return _usable_best(entries)


def select_device() -> cl.Device:
    """The OpenCL device to use (see the module docstring for the order of choice).

    Raises ValueError (naming the variable and listing devices) for a bad SOFTRAS_CL_DEVICE or
    PYOPENCL_CTX, RuntimeError (saying how to install one) when there is no OpenCL platform.
    """
    pi, di, platform, device = _select(_entries())
    logger.info("OpenCL device %d:%d: %s", pi, di, _label(platform, device))
    return device


def has_fp64(device: cl.Device) -> bool:
    """True if the device supports double precision (cl_khr_fp64)."""
    return "cl_khr_fp64" in device.extensions.split()


def vector_lanes(device: cl.Device, dtype: str) -> int:
    """Pixels per kernel vector (and tile width) for `dtype` on `device`: 16 floats where the
    device prefers 16-wide float vectors (AVX-512 CPUs: PoCL then uses the full 512-bit
    registers), else 8; always 4 doubles (wider double vectors break pip's PoCL 3.0 on CPUs
    without AVX-512, see kernels/common.h)."""
    choices = LANES[dtype]
    preferred = device.preferred_vector_width_float if dtype == "float32" else 0
    return max([n for n in choices if n <= preferred] or [choices[0]])


def kernel_layout(device: cl.Device, layout: str) -> str:
    """The kernels' work layout for RasterSettings.layout `layout` on `device`: "cpu" or "gpu" as
    asked; "auto" gives "gpu" on GPU and accelerator devices (one pixel per work-item fills them),
    "cpu" on the others (vectors of pixels per work-item use a CPU's SIMD lanes) and on devices
    that say they are a CPU as well (Oclgrind's simulator claims every type)."""
    if layout != "auto":
        return layout
    if device.type & cl.device_type.CPU:
        return "cpu"
    return "gpu" if device.type & (cl.device_type.GPU | cl.device_type.ACCELERATOR) else "cpu"


def has_int64_atomics(device: cl.Device) -> bool:
    """True if the device supports 64-bit integer atomics (cl_khr_int64_base_atomics)."""
    return "cl_khr_int64_base_atomics" in device.extensions.split()


def list_devices() -> list[dict]:
    """Every OpenCL device, one dict each with keys: platform_index, device_index (int),
    platform_name, platform_version, device_name, type ("CPU"/"GPU"/"ACCELERATOR"/"OTHER"),
    compute_units (int), fp64, int64_atomics, local_mem_bytes (int), layout (the kernels' work
    layout RasterSettings.layout="auto" picks there: "cpu" or "gpu"), compiler_fault (None, or why
    its compiler cannot build kernels: such a device is never chosen by default), chosen (bool;
    True for the one `select_device` returns, none if the environment variable names no device)."""
    entries = _entries()
    try:
        chosen = _select(entries)
    except (ValueError, DeviceError):
        chosen = None
    return [dict(platform_index=pi, device_index=di, platform_name=p.name,
                 platform_version=p.version, device_name=d.name, type=_type_name(d),
                 compute_units=d.max_compute_units, fp64=has_fp64(d),
                 int64_atomics=has_int64_atomics(d), local_mem_bytes=d.local_mem_size,
                 layout=kernel_layout(d, "auto"), compiler_fault=compiler_fault(d),
                 chosen=chosen is not None and chosen[:2] == (pi, di))
            for pi, di, p, d in entries]


def get_context(device: cl.Device | None = None) -> tuple[cl.Context, cl.CommandQueue]:
    """(context, in-order queue) for `device` (default: `select_device()`), cached per device."""
    device = select_device() if device is None else device
    if device not in _contexts:
        ctx = cl.Context([device])
        _contexts[device] = (ctx, cl.CommandQueue(ctx, device))
    return _contexts[device]


def resolve_context(device: cl.Device | None = None, context: cl.Context | None = None,
                    queue: cl.CommandQueue | None = None) -> tuple[cl.Device, cl.Context, cl.CommandQueue]:
    """(device, context, in-order queue) from whichever of the three the caller gives.

    Nothing given: `get_context(device)` (cached). A queue alone brings its context and device; a
    context brings its device (given, or the queue's, or its only one) and a new queue unless one
    is given. TypeError for arguments of the wrong type, ValueError (naming the argument) for a
    device outside the context, a queue of another context or device, or an out-of-order queue.
    """
    for name, value, kind in (("device", device, cl.Device), ("context", context, cl.Context),
                              ("queue", queue, cl.CommandQueue)):
        if value is not None and not isinstance(value, kind):
            raise TypeError(f"{name} must be a pyopencl.{kind.__name__} or None, got {type(value).__name__}")
    if context is None and queue is None:
        device = select_device() if device is None else device
        return (device, *get_context(device))
    if device is None and queue is not None:
        device = queue.device
    context = queue.context if context is None else context
    device = _context_device(context, device)
    if queue is None:
        return device, context, cl.CommandQueue(context, device)
    _check_queue(queue, context, device)
    return device, context, queue


def _context_device(context: cl.Context, device: cl.Device | None) -> cl.Device:
    """`device` if it belongs to `context`, or the context's only device when None."""
    devices = context.devices
    if device is None:
        if len(devices) != 1:
            raise ValueError(f"context holds {len(devices)} devices: pass device= to choose one")
        return devices[0]
    if device not in devices:
        raise ValueError(f"device {device.name!r} does not belong to the context "
                         f"(its devices: {[d.name for d in devices]})")
    return device


def _check_queue(queue: cl.CommandQueue, context: cl.Context, device: cl.Device) -> None:
    if queue.context != context:
        raise ValueError("queue belongs to another context than the one given as context")
    if queue.device != device:
        raise ValueError(f"queue runs on device {queue.device.name!r}, not on device {device.name!r}")
    if queue.properties & cl.command_queue_properties.OUT_OF_ORDER_EXEC_MODE_ENABLE:
        raise ValueError("queue must be in-order (the rasteriser relies on the order of its commands)")
