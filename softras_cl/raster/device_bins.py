"""Tile binning on the device: the (tile, face) lists of softras_cl.raster.binning.bin_tiles
(the host reference) built from the device's tile ranges, without a round trip to the host.

Four steps, every one deterministic (no atomics):
1. an inclusive scan (pyopencl.scan.GenericScanKernel) of each face's tile count nx * ny, in
   int64: the face-major entry starts (Bins.face_start); its last value, the entry count, is the
   one number read back (it sizes the lists, and must fit int32 as on the host);
2. an expansion (pyopencl.elementwise.ElementwiseKernel), one work-item per face, writing each of
   its entries' tile (row-major over its tile box, as the host numbers them; tiles outside the
   region of interest get the key n_tiles, after every tile), face and face-major index;
3. a stable radix sort of the entries by tile (pyopencl.algorithm.RadixSort): within a tile the
   entries keep their face-major order, so each tile lists its faces in increasing order;
4. a finish (ElementwiseKernel), one work-item per sorted entry: the tile lists, the inverse
   permutation (Bins.face_slots, -1 outside the region) and the tile starts (each written by the
   one entry where the sorted keys pass it).

The lists are the host's, entry for entry (tests/raster/test_device_bins.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from softras_cl.cl.generated import shared_kernel
from softras_cl.raster.binning import Grid

INT32_LIMIT = 2 ** 31


@dataclass
class DeviceBins:
    """Bins (softras_cl.raster.binning.Bins) as int32 device arrays.

    tile_start: (n_tiles + 1,); tile_faces: (n_entries,), of which the first tile_start[-1] are
    the tile lists (the rest, entries outside a region of interest, is not read); face_start:
    (B*F + 1,); face_slots: (n_entries,). n_entries: the number of (tile, face) pairs (host int).
    Arrays of zero entries hold one unused element (OpenCL buffers cannot be empty).
    """
    tile_start: cla.Array
    tile_faces: cla.Array
    face_start: cla.Array
    face_slots: cla.Array
    n_entries: int

    def host(self) -> tuple:
        """(tile_start, tile_faces, face_start, face_slots) as numpy arrays of the host Bins'
        lengths (the tile lists cut at tile_start[-1])."""
        tile_start = self.tile_start.get()
        n = self.n_entries
        return (tile_start, self.tile_faces.get()[:tile_start[-1]], self.face_start.get(),
                self.face_slots.get()[:n])


class DeviceBinning:
    """Bins faces into the tiles of `grid` on `queue` (kernels built on first use, once per
    context: softras_cl.cl.generated)."""

    def __init__(self, ctx: cl.Context, queue: cl.CommandQueue, grid: Grid):
        self.ctx, self.queue, self.grid = ctx, queue, grid

    def _build(self) -> tuple:
        """(scan, expand, sort, finish): pyopencl's templated kernels (they need Mako)."""
        from pyopencl.algorithm import RadixSort
        from pyopencl.elementwise import ElementwiseKernel
        from pyopencl.scan import GenericScanKernel

        scan = GenericScanKernel(
            self.ctx, np.int64, arguments="const int *ranges, long *starts",
            input_expr="(long)ranges[4 * i + 2] * ranges[4 * i + 3]", scan_expr="a + b", neutral="0",
            output_statement="starts[i + 1] = item; if (i == 0) starts[0] = 0;")
        # entry e = starts[g] + r * nx + c of face g is tile (ty0 + r, tx0 + c) of its batch item
        expand = ElementwiseKernel(
            self.ctx, "const int n_faces, const int faces_per_item, const int ntx, const int nty, "
                      "const int n_tiles, const int use_roi, const int *ranges, const long *starts, "
                      "const char *roi, int *face_start, int *keys, int *faces, int *entries",
            """
            const int tx0 = ranges[4 * i], ty0 = ranges[4 * i + 1];
            const int nx = ranges[4 * i + 2], ny = ranges[4 * i + 3];
            const int first = (i / faces_per_item * nty + ty0) * ntx + tx0;
            int e = (int)starts[i];
            face_start[i] = e;
            if (i == n_faces - 1)
                face_start[n_faces] = (int)starts[n_faces];
            for (int r = 0; r < ny; ++r)
                for (int c = 0; c < nx; ++c, ++e) {
                    const int tile = first + r * ntx + c;
                    keys[e] = (use_roi && !roi[tile]) ? n_tiles : tile;
                    faces[e] = i;
                    entries[e] = e;
                }
            """, "bin_expand")
        sort = RadixSort(self.ctx, "int *keys, int *faces, int *entries",
                         key_expr="keys[i]", sort_arg_names=["keys", "faces", "entries"], key_dtype=np.uint32)
        # work-item i of n_entries + 1: tile_start[t] = i for the tiles t in (keys[i-1], keys[i]]
        finish = ElementwiseKernel(
            self.ctx, "const int n_entries, const int n_tiles, const int *keys, const int *faces, "
                      "const int *entries, int *tile_start, int *tile_faces, int *face_slots",
            """
            const int key = i < n_entries ? keys[i] : n_tiles;
            const int prev = i > 0 ? keys[i - 1] : -1;
            for (int t = prev + 1; t <= key; ++t)
                tile_start[t] = i;
            if (i < n_entries) {
                tile_faces[i] = key < n_tiles ? faces[i] : -1;
                face_slots[entries[i]] = key < n_tiles ? i : -1;
            }
            """, "bin_finish")
        return scan, expand, sort, finish

    def run(self, ranges: cl.Buffer, batch: int, n_faces: int, tiles: np.ndarray | None = None) -> DeviceBins:
        """Bins of the B*F faces (B*F >= 1) whose (B*F, 4) int32 tile ranges (tx0, ty0, nx, ny;
        binning.face_tiles) are in device buffer `ranges`. tiles: None or the (B * nty * ntx,)
        bool region of interest (binning.roi_tiles). ValueError when the (tile, face) pairs
        would overflow int32 (the host's message)."""
        scan, expand, sort, finish = shared_kernel(self.ctx, "binning", self._build)
        q, g = self.queue, self.grid
        count, n_tiles = batch * n_faces, batch * g.ntx * g.nty
        ranges = cla.Array(q, (4 * count,), np.int32, data=ranges)
        starts = cla.empty(q, count + 1, np.int64)
        scan(ranges, starts, size=count, queue=q)
        total = int(starts[count:].get()[0])
        if total >= INT32_LIMIT:
            raise ValueError(f"{total} (tile, face) pairs exceed the int32 limit: lower image_size, "
                             "raise dist_eps or split the batch")
        keys, faces, entries = (cla.empty(q, max(total, 1), np.int32) for _ in range(3))
        face_start = cla.empty(q, count + 1, np.int32)
        roi = cla.to_device(q, tiles.astype(np.int8)) if tiles is not None else cla.zeros(q, 1, np.int8)
        expand(np.int32(count), np.int32(n_faces), np.int32(g.ntx), np.int32(g.nty), np.int32(n_tiles),
               np.int32(tiles is not None), ranges, starts, roi, face_start, keys, faces, entries,
               range=slice(count), queue=q)
        if total > 1:
            (keys, faces, entries), _ = sort(keys, faces, entries, key_bits=max(n_tiles.bit_length(), 1), queue=q)
        tile_start = cla.empty(q, n_tiles + 1, np.int32)
        tile_faces, face_slots = (cla.empty(q, max(total, 1), np.int32) for _ in range(2))
        finish(np.int32(total), np.int32(n_tiles), keys, faces, entries, tile_start, tile_faces, face_slots,
               range=slice(total + 1), queue=q)
        return DeviceBins(tile_start, tile_faces, face_start, face_slots, total)
