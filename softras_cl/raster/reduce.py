"""Gradient reductions on the device (kernels/grad_sums.cl): the backward kernel's (tile, face)
slots summed per face, and per-face corner sums summed onto vertices.

Every sum adds its terms one after another in a fixed order (one work-item per output value, no
atomics): reruns are bit-identical, and with double accumulation (`sum_double`, the default where
the device has cl_khr_fp64) the results carry the same bits as a sequential float64 loop over the
same terms: the slots in face-major order (Bins.face_start) for the per-face sums (np.add.reduceat
is not such a loop: it adds the first row to a pairwise sum of the others), the (B, F, 3) corners
in order for the vertex sums (np.bincount's order: softras_cl.raster.corners.scatter_corners).
Without fp64 a float32 build sums in float32: within n * 2^-24 * sum |terms| of the float64 sum.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl as cl

from softras_cl.cl.program import build_kernel, launch
from softras_cl.raster.pool import BufferPool

GROUP = (64,)       # work-group of both kernels; the items beyond the end are skipped


@dataclass
class CornerIndex:
    """Which face corners touch each vertex, for faces (B, F, 3) over B*V vertices.

    vertex_start: (B*V + 1,) int32, vertex u's corners are corners[vertex_start[u]:vertex_start[u+1]]
    corners: (B*F*3,) int32 corner ids 4 * (b * F + f) + k, increasing within each vertex
    """
    vertex_start: np.ndarray
    corners: np.ndarray


def corner_index(faces: np.ndarray, n_vertices: int) -> CornerIndex:
    """CornerIndex of int faces (B, F, 3) with indices below n_vertices."""
    batch = faces.shape[0]
    if 4 * batch * faces.shape[1] >= 2 ** 31:
        raise ValueError(f"{batch} x {faces.shape[1]} faces: corner ids 4 * face + corner exceed int32; split the batch")
    flat = (np.arange(batch)[:, None, None] * n_vertices + faces).ravel()
    counts = np.bincount(flat, minlength=batch * n_vertices)
    order = np.argsort(flat, kind="stable")       # positions 3 g + k in (b, f, k) order
    return CornerIndex(np.concatenate([[0], np.cumsum(counts)]).astype(np.int32),
                       (order // 3 * 4 + order % 3).astype(np.int32))


class GradSums:
    """Launches the reductions on `queue`, with buffers from `pool`.

    real: dtype of the slots (the backward kernel's); sum_double: accumulate in float64 (needs
    cl_khr_fp64), else in `real`. `dtype` is the dtype of every result.
    """

    def __init__(self, ctx: cl.Context, queue: cl.CommandQueue, pool: BufferPool, real: np.dtype,
                 lanes: int, sum_double: bool):
        self.ctx, self.queue, self.pool = ctx, queue, pool
        self.dtype = np.dtype(np.float64 if sum_double else real)
        self._defines = dict(SR_DOUBLE=np.dtype(real) == np.float64, SR_LANES=lanes, SR_SUM_DOUBLE=sum_double)
        self._kernels: dict = {}
        self._index_key = None
        self._index_bufs = None
        # transfers in flight: pyopencl's transfer events wait for their transfer when freed,
        # so they are kept until wait()
        self._transfers: list = []

    def _kernel(self, name: str) -> cl.Kernel:
        """Kernel `name`, kept (the program cache's lookup formats every flag, per call)."""
        if name not in self._kernels:
            self._kernels[name] = build_kernel(self.ctx, "grad_sums.cl", name, self._defines)
        return self._kernels[name]

    def face_sums(self, slots: cl.Buffer, width: int, face_start: cl.Buffer, face_slots: cl.Buffer,
                  n_faces: int) -> cl.Buffer:
        """Pooled buffer of (n_faces, width) per-face sums (`dtype`) of the (n_list, width) slot
        rows `slots` (real), grouped by the device copies of Bins.face_start and Bins.face_slots."""
        out = self.pool.take(n_faces * width * self.dtype.itemsize)
        launch(self._kernel("face_sums"), self.queue, (_round_up(n_faces),), GROUP, np.int32(n_faces),
               np.int32(width), face_start, face_slots, slots, out)
        return out

    def vertex_sums(self, face_vals: cl.Buffer, face_width: int, offset: int, faces: np.ndarray,
                    n_vertices: int) -> cl.Buffer:
        """Pooled buffer of (B*V, 3) vertex sums (`dtype`) of corner values: corner k of face g
        holds face_vals[g, offset + 3k : offset + 3k + 3] of the (B*F, face_width) `face_vals`.
        faces: (B, F, 3) int, n_vertices: V."""
        start, corners = self._corner_buffers(faces, n_vertices)
        total = faces.shape[0] * n_vertices
        out = self.pool.take(total * 3 * self.dtype.itemsize)
        launch(self._kernel("vertex_sums"), self.queue, (_round_up(total),), GROUP, np.int32(total),
               np.int32(face_width), np.int32(offset), start, corners, face_vals, out)
        return out

    def _corner_buffers(self, faces: np.ndarray, n_vertices: int) -> tuple[cl.Buffer, cl.Buffer]:
        """Device copies of corner_index(faces, n_vertices), kept while the faces stay the same
        (a fit renders one mesh hundreds of times; comparing is far cheaper than sorting)."""
        key = self._index_key
        if key is None or key[1] != n_vertices or not np.array_equal(key[0], faces):
            index = corner_index(faces, n_vertices)
            self._index_bufs = [cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                                          hostbuf=np.ascontiguousarray(a) if a.size else np.zeros(1, np.int32))
                                for a in (index.vertex_start, index.corners)]
            self._index_key = (np.array(faces, copy=True), n_vertices)
        return self._index_bufs[0], self._index_bufs[1]

    def download(self, buf: cl.Buffer, shape: tuple) -> np.ndarray:
        """A new `dtype` array of `shape` that `buf` is read into, valid after wait()."""
        host = np.empty(shape, self.dtype)
        if host.size:
            self._transfers.append(cl.enqueue_copy(self.queue, host, buf, is_blocking=False))
        return host

    def wait(self) -> None:
        """Wait for everything queued (the transfers above included)."""
        self.queue.finish()
        self._transfers.clear()


def _round_up(n: int) -> int:
    return -(-max(n, 1) // GROUP[0]) * GROUP[0]

