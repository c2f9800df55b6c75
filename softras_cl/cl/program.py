"""Build OpenCL programs from kernels/ with -D flags, cached per (context, device, flags).

Every build also receives the host/kernel data layout (softras_cl.cl.layout.LAYOUT) as -D flags.
Programs are kept per process (a lookup by source name and flags, without re-reading the source)
and, as device binaries, on disk across processes (softras_cl.cl.binary_cache).
"""
from __future__ import annotations

import hashlib
import logging
from contextlib import contextmanager

import numpy as np
import pyopencl as cl

from softras_cl.cl import binary_cache
from softras_cl.cl.layout import LAYOUT
from softras_cl.cl.source import kernel_source

logger = logging.getLogger(__name__)

_cache: dict = {}
_kernels: dict = {}
_by_name: dict = {}     # (context, source name, options) -> program: the per-call fast path
_typed: set = set()     # int_ptr of the kernels whose scalar dtypes launch() has declared
_recorders: list = []   # the logs of the open recorded_launches blocks, innermost last

# Every program is the shared header followed by one op file; concatenating on the host avoids
# relying on each driver's #include search path.
_HEADER = "common.h"


def build_kernel(ctx: cl.Context, source_name: str, kernel_name: str, defines: dict,
                 fast_math: bool = False) -> cl.Kernel:
    """Kernel `kernel_name` of build_program(...), itself cached (kernel objects are costly)."""
    program = build_program(ctx, source_name, defines, fast_math)
    key = (id(program), kernel_name)
    if key not in _kernels:
        _kernels[key] = cl.Kernel(program, kernel_name)
    return _kernels[key]


def launch(kernel: cl.Kernel, queue: cl.CommandQueue, global_size: tuple, local_size: tuple, *args) -> cl.Event:
    """Enqueue `kernel` over global_size in groups of local_size with `args`: numpy scalars (of
    one dtype per position, call after call) and buffers.

    The first launch of each kernel object declares its scalar dtypes to pyopencl, which then
    packs the scalars itself: on PoCL a launch with 20 scalars took ~220 us, ~18 us after (the
    generic path converts every numpy scalar through the buffer protocol).
    """
    if kernel.int_ptr not in _typed:
        kernel.set_scalar_arg_dtypes([a.dtype if isinstance(a, np.generic) else None for a in args])
        _typed.add(kernel.int_ptr)
    event = kernel(queue, global_size, local_size, *args)
    if _recorders:
        _recorders[-1].append((kernel.function_name, event))
    return event


@contextmanager
def recorded_launches():
    """Within the block, every launch's (kernel name, event) is appended to the list it yields:
    on a queue made with PROFILING_ENABLE, the events give each kernel's device time
    (launch_device_ms; softras-cl bench raster)."""
    log: list = []
    _recorders.append(log)
    try:
        yield log
    finally:
        _recorders.remove(log)


def launch_device_ms(log: list) -> dict:
    """{kernel name: device ms summed over its launches} of a recorded_launches log whose
    queue had profiling enabled (each event is waited for)."""
    totals: dict = {}
    for name, event in log:
        event.wait()
        totals[name] = totals.get(name, 0.0) + 1e-6 * (event.profile.end - event.profile.start)
    return totals


def build_program(ctx: cl.Context, source_name: str, defines: dict, fast_math: bool = False) -> cl.Program:
    """The program for `source_name` (e.g. "soft_raster.cl") specialised by `defines`.

    defines: {flag name: int} turned into -D NAME=value, together with every layout constant
    (ValueError if `defines` names one). fast_math adds -cl-fast-relaxed-math.
    Builds once per (context, source text, flags); later calls return the cached program.
    """
    clash = sorted(set(defines) & set(LAYOUT))
    if clash:
        raise ValueError(f"defines must not set the layout constants {clash}: they come from "
                         "softras_cl.cl.layout")
    options = [f"-D{name}={int(value)}" for name, value in sorted({**defines, **LAYOUT}.items())]
    if fast_math:
        options.append("-cl-fast-relaxed-math")
    fast_key = (ctx.int_ptr, source_name, tuple(options))
    program = _by_name.get(fast_key)
    if program is not None:
        return program
    source = kernel_source(_HEADER) + "\n" + kernel_source(source_name)
    key = (ctx.int_ptr, hashlib.sha1(source.encode()).hexdigest(), tuple(options))
    if key not in _cache:
        _cache[key] = _build(ctx, source_name, source, options)
    _by_name[fast_key] = _cache[key]
    return _cache[key]


def _build(ctx: cl.Context, source_name: str, source: str, options: list[str]) -> cl.Program:
    """Load the program from the on-disk binary cache (one-device contexts), else build it from
    source and store its binary."""
    devices = ctx.devices
    disk_key = binary_cache.program_key(source, options, devices[0]) if len(devices) == 1 else None
    if disk_key is not None:
        program = binary_cache.load(ctx, devices[0], disk_key, options)
        if program is not None:
            return program
    logger.debug("building %s with %s", source_name, " ".join(options) or "no options")
    try:
        program = cl.Program(ctx, source).build(options=options)
    except cl.RuntimeError as e:  # compile errors: show the flags that produced them
        raise RuntimeError(f"building {source_name} with {' '.join(options)} failed:\n{e}") from e
    if disk_key is not None:
        binary_cache.store(program, devices[0], disk_key)
    return program
