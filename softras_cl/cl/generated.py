"""pyopencl's generated kernels (ElementwiseKernel, ReductionKernel, GenericScanKernel, RadixSort)
built once per OpenCL context and process, shared by every renderer, rasteriser and objective of
that context.

Each of them compiles a program when made (tens of milliseconds, even with pyopencl's binary
cache on disk); a fit makes several renderers (one per image size) and rasterisers (one per
shading), and a kernel each of them had built for itself was built again for the next.
"""
from __future__ import annotations

from typing import Callable, Hashable

_BUILT: dict = {}


def shared_kernel(ctx, key: Hashable, make: Callable):
    """make() for context ctx, made on the first call with this key and returned as it is after
    that. key: everything the kernel's source depends on (its name, arguments, body, dtypes).
    The context is kept alive with its kernels, so its handle is never reused by another."""
    entry = (ctx.int_ptr, key)
    if entry not in _BUILT:
        _BUILT[entry] = (ctx, make())
    return _BUILT[entry][1]
