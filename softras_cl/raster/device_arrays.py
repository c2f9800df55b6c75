"""Element-wise device kernels of the device-resident rasteriser path (pyopencl ElementwiseKernel):
casts, face rows, corner gathers and batch sums that the numpy path does on the host
(softras_cl.raster.inputs.MeshInputs, SoftRasterizer._shape_grads), with the same results bit
for bit: casts round to nearest as numpy's astype does, and sums add in numpy's order for
their layouts (rows one after another).

Index maths uses divisions and multiply-subtracts, never a division and a remainder of the same
operands (LLVM pairs them into `freeze`, which Oclgrind cannot run).
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from softras_cl.cl.generated import shared_kernel

_CTYPES = {np.dtype(np.float32): "float", np.dtype(np.float64): "double", np.dtype(np.int32): "int",
           np.dtype(np.int64): "long", np.dtype(np.uint32): "uint", np.dtype(np.uint64): "ulong",
           np.dtype(np.int16): "short", np.dtype(np.uint16): "ushort", np.dtype(np.int8): "char",
           np.dtype(np.uint8): "uchar"}


def ctype(dtype) -> str:
    return _CTYPES[np.dtype(dtype)]


class DeviceArrays:
    """The kernels for one context, built per dtype pair on first use."""

    def __init__(self, ctx: cl.Context, queue: cl.CommandQueue):
        self.ctx, self.queue = ctx, queue

    def _kernel(self, name: str, args: str, body: str):
        from pyopencl.elementwise import ElementwiseKernel

        return shared_kernel(self.ctx, ("arrays", name, args, body),
                             lambda: ElementwiseKernel(self.ctx, args, body, name))

    def contiguous(self, value: cla.Array, dtype) -> cla.Array:
        """`value` as a C-contiguous array of `dtype` (itself when it already is one)."""
        dtype = np.dtype(dtype)
        if value.dtype == dtype and value.flags.c_contiguous:
            return value
        if not value.flags.c_contiguous:
            value = value.copy()
        return value.astype(dtype)

    def broadcast(self, value: cla.Array, batch: int, dtype) -> cla.Array:
        """(Bs, ...) -> C-contiguous (batch, ...) of `dtype`, Bs = 1 repeated over the batch."""
        value = self.contiguous(value, value.dtype)
        out = cla.empty(self.queue, (batch,) + value.shape[1:], dtype)
        per_item = int(np.prod(value.shape[1:]))
        knl = self._kernel("broadcast_cast", f"{ctype(dtype)} *out, const {ctype(value.dtype)} *src, "
                           "const long per_item, const int repeat",
                           f"out[i] = ({ctype(dtype)})src[repeat ? i - (i / per_item) * per_item : i]")
        knl(out, value, np.int64(per_item), np.int32(value.shape[0] != batch), queue=self.queue)
        return out

    def face_rows(self, faces: cla.Array, batch: int, n_vertices: int) -> cla.Array:
        """(B*F*3,) int32 rows b * V + index of (F, 3) or (B, F, 3) integer faces."""
        faces = self.contiguous(faces, faces.dtype)
        per_item = 3 * faces.shape[-2]
        out = cla.empty(self.queue, batch * per_item, np.int32)
        knl = self._kernel("face_rows", f"int *rows, const {ctype(faces.dtype)} *faces, const int per_item, "
                           "const int n_vertices, const int shared",
                           "const int b = i / per_item; "
                           "rows[i] = b * n_vertices + (int)faces[shared ? i - b * per_item : i]")
        knl(out, faces, np.int32(per_item), np.int32(n_vertices), np.int32(faces.ndim == 2 or faces.shape[0] != batch),
            queue=self.queue)
        return out

    def gather_corners(self, out: cla.Array, values: cla.Array, rows: cla.Array, n_vertices: int,
                       width: int, offset: int) -> None:
        """out[g, offset + 3 k + j] = values[corner k of face g, j] cast to out's dtype, for the
        (B*F, width) out, (Bs, V, K) values (Bs = 1 shared by the batch) and face rows."""
        values = self.contiguous(values, values.dtype)
        k = values.shape[-1]
        knl = self._kernel("gather_corners", f"{ctype(out.dtype)} *out, const {ctype(values.dtype)} *values, "
                           "const int *rows, const int n_vertices, const int k, const int width, "
                           "const int offset, const int shared",
                           f"""
                           const int corner = i / k, j = i - corner * k;
                           const int face = corner / 3;
                           int row = rows[corner];
                           if (shared)
                               row -= (row / n_vertices) * n_vertices;
                           out[face * width + offset + (corner - 3 * face) * k + j] =
                               ({ctype(out.dtype)})values[row * k + j]
                           """)
        knl(out, values, rows, np.int32(n_vertices), np.int32(k), np.int32(width), np.int32(offset),
            np.int32(values.shape[0] == 1), range=slice(rows.size * k), queue=self.queue)

    def sum_rows(self, value: cla.Array, keepdims: bool = False) -> cla.Array:
        """(N, ...) -> (...) (or (1, ...)): the rows added one after another in float64, as
        numpy's sum over the first axis of a C-contiguous array adds them."""
        value = self.contiguous(value, np.float64)
        inner = value.shape[1:]
        out = cla.empty(self.queue, ((1,) if keepdims else ()) + inner, np.float64)
        knl = self._kernel("sum_rows", "double *out, const double *src, const int n_rows, const long row",
                           "double s = src[i]; for (int r = 1; r < n_rows; ++r) s += src[r * row + i]; out[i] = s")
        knl(out, value, np.int32(value.shape[0]), np.int64(out.size), queue=self.queue)
        return out

    def fixed_to_float(self, sums: cla.Array, scale: float) -> cla.Array:
        """int64 fixed-point sums -> float64 sums / scale (numpy's astype(float64) / scale)."""
        out = cla.empty(self.queue, sums.shape, np.float64)
        knl = self._kernel("fixed_to_float", "double *out, const long *sums, const double scale",
                           "out[i] = (double)sums[i] / scale")
        knl(out, sums, np.float64(scale), queue=self.queue)
        return out

    def abs_sums(self, value: cla.Array) -> list:
        """Device scalars (float64) of sum |value[b]| per item b of the (B, ...) array."""
        from pyopencl.reduction import ReductionKernel

        kernel = shared_kernel(self.ctx, ("abs_sum", value.dtype), lambda: ReductionKernel(
            self.ctx, np.float64, neutral="0", reduce_expr="a + b", map_expr="fabs((double)x[i])",
            arguments=f"__global const {ctype(value.dtype)} *x"))
        value = self.contiguous(value, value.dtype)
        return [kernel(value[b].reshape(-1)) for b in range(value.shape[0])]


def read_together(arrays: list) -> list[np.ndarray]:
    """Device arrays of one dtype on one queue, downloaded in one transfer (one wait for the
    queue: on a GPU each wait is a round trip): numpy copies, in order, of their shapes."""
    if len(arrays) == 1:
        return [arrays[0].get()]
    queue, dtype = arrays[0].queue, arrays[0].dtype
    together = cla.empty(queue, sum(a.size for a in arrays), dtype)
    at = 0
    for a in arrays:
        if a.dtype != dtype:
            raise TypeError(f"read_together: arrays of one dtype, got {dtype} and {a.dtype}")
        a = a if a.flags.forc else a.copy()
        if a.size:
            cl.enqueue_copy(queue, together.base_data, a.base_data, byte_count=a.nbytes,
                            dst_offset=together.offset + at * dtype.itemsize, src_offset=a.offset)
        at += a.size
    flat, out, at = together.get(), [], 0
    for a in arrays:
        out.append(flat[at:at + a.size].reshape(a.shape))
        at += a.size
    return out
