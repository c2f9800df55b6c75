"""Build OpenCL programs from kernels/ with -D flags, cached per (context, device, flags).

Every build also receives the host/kernel data layout (softras_cl.cl.layout.LAYOUT) as -D flags.
"""
from __future__ import annotations

import hashlib
import logging

import pyopencl as cl

from softras_cl.cl.layout import LAYOUT
from softras_cl.cl.source import kernel_source

logger = logging.getLogger(__name__)

_cache: dict = {}
_kernels: dict = {}

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
    source = kernel_source(_HEADER) + "\n" + kernel_source(source_name)
    options = [f"-D{name}={int(value)}" for name, value in sorted({**defines, **LAYOUT}.items())]
    if fast_math:
        options.append("-cl-fast-relaxed-math")
    key = (ctx.int_ptr, hashlib.sha1(source.encode()).hexdigest(), tuple(options))
    if key not in _cache:
        logger.debug("building %s with %s", source_name, " ".join(options) or "no options")
        try:
            _cache[key] = cl.Program(ctx, source).build(options=options)
        except cl.RuntimeError as e:  # compile errors: show the flags that produced them
            raise RuntimeError(f"building {source_name} with {' '.join(options)} failed:\n{e}") from e
    return _cache[key]
