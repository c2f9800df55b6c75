"""Face set-up on the device (kernels/face_setup.cl): the per-face geometry records and tile ranges
computed by a kernel from the vertices, instead of on the host (softras_cl.raster.binning.face_setup
and face_tiles, which stay the reference and the path for devices without cl_khr_fp64).

A call uploads the (B, V, 3) float64 vertices (the faces once, while they stay the same), runs
the kernel into a pooled records buffer that the forward kernel reads as is, and downloads the
(B*F, 4) int32 tile ranges the host bins (binning.bin_tiles). The kernel repeats the host's
float64 operations in their order: the records and the bins carry the same bits as the host's
(tests/raster/test_device_setup.py), so images and gradients do too. This saves the host's
per-face arithmetic, the transposing cast of the records and their upload, about 3 ms a call
on the 15k-face face mesh.
"""
from __future__ import annotations

import numpy as np
import pyopencl as cl

from softras_cl.cl.layout import FACE_STRIDE
from softras_cl.cl.program import build_kernel, launch
from softras_cl.raster.binning import Grid, box_growth, pixel_scale
from softras_cl.raster.inputs import MeshInputs
from softras_cl.raster.pool import BufferPool, ScratchArrays
from softras_cl.raster.settings import RasterSettings

GROUP = (64,)       # work-items per group; the items beyond the faces are skipped


class DeviceSetup:
    """Runs kernel face_setup for one rasteriser's grid on `queue` (needs cl_khr_fp64), with
    buffers from `pool`; `real` is the records' dtype. Each call passes the settings it draws
    with (sigma and the depth range change the footprints and which faces are drawable)."""

    def __init__(self, ctx: cl.Context, queue: cl.CommandQueue, pool: BufferPool, grid: Grid, real: np.dtype):
        self.ctx, self.queue, self.pool = ctx, queue, pool
        self.real = np.dtype(real)
        self._defines = dict(SR_DOUBLE=self.real == np.float64, SR_TILE_W=grid.tile_w)
        self._kernel: cl.Kernel | None = None
        self._args_of: tuple | None = None      # ((settings, batch), their kernel arguments): the last ones
        self._scratch = ScratchArrays()
        self._faces_key: tuple | None = None
        self._faces_buf: cl.Buffer | None = None

    def _settings_args(self, s: RasterSettings, batch: int) -> list:
        """The kernel's arguments after the face counts for settings s and a batch of views (kept
        for the last ones): each view's depth range goes in a (batch, 2) float64 buffer."""
        if self._args_of is None or self._args_of[0] != (s, batch):
            grow, factor, margin = box_growth(s)
            inv_ps, half_w, top = pixel_scale(s)
            i32, f64 = np.int32, np.float64
            ranges = cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                               hostbuf=s.depth_ranges(batch))
            self._args_of = ((s, batch), [i32(s.width), i32(s.height), i32(s.double_sided), ranges,
                                          i32(grow), f64(factor), f64(margin), f64(half_w), f64(top), f64(inv_ps)])
        return self._args_of[1]

    def run(self, mesh: MeshInputs, settings: RasterSettings) -> tuple[cl.Buffer, np.ndarray]:
        """(records, ranges) of mesh's B*F faces (B*F >= 1) drawn with `settings`: a pooled
        (B*F, FACE_STRIDE) `real` buffer of the records, and the (B*F, 4) int32 (tx0, ty0, nx,
        ny) tile ranges (binning.face_tiles; a scratch array that the next call overwrites)."""
        n = mesh.batch * mesh.n_faces
        vertices = self.pool.take(mesh.vertices.nbytes)
        upload = cl.enqueue_copy(self.queue, vertices, np.ascontiguousarray(mesh.vertices), is_blocking=False)
        geom, ranges_buf = self.run_device(vertices, self._faces(mesh.faces, mesh.n_vertices), mesh.batch,
                                           mesh.n_faces, settings)
        ranges = self._scratch.get("ranges", (n, 4), np.int32)
        cl.enqueue_copy(self.queue, ranges, ranges_buf, is_blocking=True)
        upload.wait()
        self.pool.give([vertices, ranges_buf])     # an in-order queue: later users come after
        return geom, ranges

    def run_device(self, vertices: cl.Buffer, rows: cl.Buffer, batch: int, n_faces: int,
                   settings: RasterSettings) -> tuple:
        """(records, ranges) of the n = batch * n_faces >= 1 faces from device data: `vertices`
        (B*V, 3) float64 and `rows` (n, 3) int32 (b * V + index): pooled buffers of the (n,
        FACE_STRIDE) `real` records and of the (n, 4) int32 tile ranges, both left on the device."""
        n = batch * n_faces
        geom = self.pool.take(n * FACE_STRIDE * self.real.itemsize)
        ranges = self.pool.take(n * 16)
        if self._kernel is None:
            self._kernel = build_kernel(self.ctx, "face_setup.cl", "face_setup", self._defines)
        launch(self._kernel, self.queue, (-(-n // GROUP[0]) * GROUP[0],), GROUP, np.int32(n), np.int32(n_faces),
               *self._settings_args(settings, batch), vertices, rows, geom, ranges)
        return geom, ranges

    def _faces(self, faces: np.ndarray, n_vertices: int) -> cl.Buffer:
        """A device int32 copy of the (B, F, 3) faces as rows of the (B*V, 3) vertices (b * V +
        index), kept while they stay the same (a fit renders one mesh hundreds of times;
        comparing is far cheaper than converting and copying)."""
        key = self._faces_key
        if key is None or key[1] != n_vertices or not np.array_equal(key[0], faces):
            rows = np.arange(faces.shape[0])[:, None, None] * n_vertices + faces
            self._faces_buf = cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                                        hostbuf=np.ascontiguousarray(rows, np.int32))
            self._faces_key = (np.array(faces, copy=True), n_vertices)
        return self._faces_buf
