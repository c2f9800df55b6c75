"""Input checks of device-resident (pyopencl.array.Array) arguments, without a host pass over
their data.

What an argument is (dtype, shape, which are given) is checked on the host by the numpy path's
own functions (softras_cl.raster.inputs.check_inputs / check_cotangent with values=False) on
zero-stride stand-ins of the right shape and dtype; its values by one device reduction per
argument (pyopencl.reduction.ReductionKernel) counting the bad ones: NaN/Inf or beyond
FLOAT32_LIMIT for float32 kernels, face indices outside [0, V). Only when something is wrong are
the arguments downloaded and checked by the numpy path, so that the error is the numpy path's,
word for word (the same argument named, the same counts and indices).
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from softras_cl.cl.generated import shared_kernel
from softras_cl.raster.device_arrays import read_together
from softras_cl.raster.settings import FLOAT32_LIMIT


def is_device_array(value) -> bool:
    return isinstance(value, cla.Array)


def standin(value):
    """A read-only numpy array of `value`'s shape and dtype holding zeros, without its memory
    (zero strides); other values as they are."""
    if not is_device_array(value):
        return value
    return np.lib.stride_tricks.as_strided(np.zeros(1, value.dtype), shape=value.shape,
                                           strides=(0,) * value.ndim, writeable=False)


def on_host(value):
    """`value` downloaded if it is a device array (for the numpy path's error messages)."""
    return value.get() if is_device_array(value) else value


def check_context(name: str, value, ctx: cl.Context):
    """`value` itself if it is not a device array or lives in `ctx`; else ValueError naming it."""
    if is_device_array(value) and value.context.int_ptr != ctx.int_ptr:
        raise ValueError(f"{name} is a pyopencl array of another OpenCL context than this rasteriser's: "
                         "make it on raster.queue (or copy it there through the host)")
    return value


class ValueChecks:
    """Device reductions counting an array's bad values, built per (kind, dtype) on first use."""

    def __init__(self, ctx: cl.Context):
        self.ctx = ctx

    def _kernel(self, kind: str, dtype: np.dtype):
        from pyopencl.reduction import ReductionKernel

        ctype = {np.float32: "float", np.float64: "double", np.int32: "int", np.int64: "long",
                 np.uint32: "uint", np.uint64: "ulong", np.int16: "short", np.uint16: "ushort",
                 np.int8: "char", np.uint8: "uchar"}[np.dtype(dtype).type]
        if kind == "float":    # limit 0: finite only
            args = f"__global const {ctype} *x, const {ctype} limit"
            bad = "(isfinite(x[i]) && (limit == 0 || fabs(x[i]) <= limit)) ? 0 : 1"
        else:
            args = f"__global const {ctype} *x, const long upper"
            bad = "((long)x[i] < 0 || (long)x[i] >= upper) ? 1 : 0"
        return shared_kernel(self.ctx, ("value check", kind, ctype), lambda: ReductionKernel(
            self.ctx, np.int64, neutral="0", reduce_expr="a + b", map_expr=bad, arguments=args))

    def count_bad_floats(self, value: cla.Array, float32_kernels: bool) -> cla.Array:
        """Device scalar: how many values are NaN/Inf (or, with float32_kernels, beyond FLOAT32_LIMIT)."""
        limit = value.dtype.type(FLOAT32_LIMIT if float32_kernels else 0)
        return self._kernel("float", value.dtype)(_flat(value), limit)

    def count_bad_indices(self, value: cla.Array, upper: int) -> cla.Array:
        """Device scalar: how many values lie outside [0, upper)."""
        return self._kernel("index", value.dtype)(_flat(value), np.int64(upper))


def _flat(value: cla.Array) -> cla.Array:
    """A 1-D contiguous view (or copy) of `value`."""
    if not value.flags.forc:
        value = value.copy()
    return value.reshape(value.size)


def any_bad(counts: list) -> bool:
    """Whether any of the device scalars (int64) counted something: one read for all of them
    (each read waits for the queue; on a GPU every wait costs a round trip)."""
    return any(bool(c.any()) for c in read_together(counts))
