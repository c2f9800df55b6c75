"""Face set-up and tile binning (numpy, O(F) and O(bin entries)), run on the host before the
kernels: the per-face geometry records (layout: softras_cl.cl.layout), the tiling of the padded
image (`Grid`), each face's footprint box and the (tile, face) lists the kernels loop over (`Bins`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softras_cl.cl.layout import (FACE_BOX, FACE_INV_LEN2, FACE_INV_Z, FACE_M, FACE_STRIDE, FACE_XY,
                                  FACE_Z, TILE_H)
from softras_cl.raster.inputs import MeshInputs
from softras_cl.raster.settings import RasterSettings

MIN_AREA = 1e-12    # faces with |doubled NDC area| below this are dropped


@dataclass
class Bins:
    """Faces binned into tiles. Entries are (tile, face) pairs.

    tile_start: (n_tiles + 1,) int32, entries of tile t are tile_start[t]:tile_start[t+1]
    tile_faces: (n_list,) int32 global face index (batch * F + f), increasing within a tile
    face_start: (B*F + 1,) int32, face-major entries of face g are face_start[g]:face_start[g+1]
    face_slots: (n_entries,) int32, for each face-major entry its index in the tile lists (the
        backward kernel's slot), -1 for an entry outside the region of interest

    With a region of interest (bin_faces' tiles) the tile lists hold only the entries in its
    tiles (n_list <= n_entries), while face_start still counts every entry.
    """
    tile_start: np.ndarray
    tile_faces: np.ndarray
    face_start: np.ndarray
    face_slots: np.ndarray

    @property
    def n_entries(self) -> int:
        return int(self.face_start[-1])


@dataclass(frozen=True)
class Grid:
    """Tiling of the image: tiles of tile_w x TILE_H pixels, ntx x nty of them, covering the
    padded image of wp x hp pixels that every per-pixel device buffer holds."""
    tile_w: int
    ntx: int
    nty: int

    @property
    def wp(self) -> int:
        return self.ntx * self.tile_w

    @property
    def hp(self) -> int:
        return self.nty * TILE_H


def tile_grid(s: RasterSettings, tile_w: int) -> Grid:
    """The tiling for the settings with tiles `tile_w` pixels wide: one kernel vector
    (SoftRasterizer.lanes) in the CPU layout, GPU_TILE_W in the GPU layout."""
    return Grid(tile_w, -(-s.width // tile_w), -(-s.height // TILE_H))


def face_setup(mesh: MeshInputs, s: RasterSettings) -> tuple[np.ndarray, np.ndarray]:
    """Per-face constants for the kernel and which faces can be drawn at all.

    Returns geom (B*F, FACE_STRIDE) float64 (layout: softras_cl.cl.layout; a transposed view,
    made contiguous when cast to the kernel dtype) and drawable (B*F,) bool.
    """
    # one contiguous (B*F,) array per coordinate of each corner: x[k], y[k], z[k]
    x, y, z = np.moveaxis(mesh.triangles().reshape(-1, 3, 3), (2, 1), (0, 1)).copy()
    area = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0])
    near, far = np.repeat(s.depth_ranges(mesh.batch), mesh.n_faces, axis=0).T     # each face's view's
    drawable = ((np.abs(area) >= MIN_AREA) & (z.min(0) > 0) & (z.max(0) >= near) & (z.min(0) <= far))
    if not s.double_sided:
        drawable &= area > 0
    inv_area = 1.0 / np.where(drawable, area, 1.0)
    m1 = ((y[2] - y[0]) * inv_area, -(x[2] - x[0]) * inv_area)
    m2 = (-(y[1] - y[0]) * inv_area, (x[1] - x[0]) * inv_area)
    edge_len2 = [(x[(k + 1) % 3] - x[k]) ** 2 + (y[(k + 1) % 3] - y[k]) ** 2 for k in range(3)]
    rows = np.empty((FACE_STRIDE, len(area)))      # not zeros: calloc'd pages fault on every call
    rows[FACE_INV_LEN2 + 3:FACE_BOX] = 0.0         # unused in the layout
    rows[FACE_XY:FACE_XY + 6:2], rows[FACE_XY + 1:FACE_XY + 6:2] = x, y
    rows[FACE_M:FACE_M + 6] = [-(m1[0] + m2[0]), -(m1[1] + m2[1]), *m1, *m2]
    rows[FACE_Z:FACE_Z + 3] = z
    rows[FACE_INV_Z:FACE_INV_Z + 3] = 1.0 / np.where(drawable, z, 1.0)
    rows[FACE_INV_LEN2:FACE_INV_LEN2 + 3] = [1.0 / np.where(drawable & (l2 > 0), l2, 1.0)
                                             for l2 in edge_len2]
    rows[FACE_BOX:FACE_BOX + 4] = _footprint_boxes(x, y, s)
    rows[:, ~drawable] = 0.0
    return rows.T, drawable


def footprint_margin(s: RasterSettings) -> float:
    """How far beyond a face (NDC, or barycentric units for that metric) D stays >= dist_eps.

    inf when nothing is cut off (dist_eps = 0); 0 when only hard aggregations are used.
    """
    soft = ((s.color_agg == "softmax" and {"rgb", "depth"} & set(s.outputs))
            or ("alpha" in s.outputs and s.alpha_agg != "hard"))
    if not soft:
        return 0.0
    if s.dist_eps == 0:
        return math.inf
    return math.sqrt(s.sigma * math.log(1.0 / s.dist_eps - 1.0))


def box_growth(s: RasterSettings) -> tuple[bool, float, float]:
    """(grow, factor, margin) of the footprint boxes: with grow, each triangle is first scaled by
    `factor` about its centroid (the barycentric metric's region min(b) >= -margin); then its box
    is widened by `margin` NDC (inf: unbounded). Shared by _footprint_boxes and the device set-up."""
    margin = footprint_margin(s)
    grow = s.metric == "barycentric" and math.isfinite(margin)
    factor = 1 + 3 * margin if grow else 1.0
    if grow:
        margin = 0.0
    return grow, factor, margin + 2e-3 / min(s.width, s.height)


def _footprint_boxes(x: np.ndarray, y: np.ndarray, s: RasterSettings) -> np.ndarray:
    """(4, B*F) NDC boxes (xmin, xmax, ymin, ymax) where a face can reach D >= dist_eps, from
    corner coordinates x, y (3, B*F) (box_growth).

    Grown by a thousandth of a pixel, so that float32 kernels never meet a pair the box
    excludes; unbounded footprints (dist_eps = 0) are clipped to +-1e6.
    """
    grow, factor, margin = box_growth(s)
    if grow:
        x = x.mean(0) + factor * (x - x.mean(0))
        y = y.mean(0) + factor * (y - y.mean(0))
    box = [x.min(0) - margin, x.max(0) + margin, y.min(0) - margin, y.max(0) + margin]
    return np.clip(box, -1e6, 1e6)


def pixel_scale(s: RasterSettings) -> tuple[float, float, float]:
    """(inv_ps, half_w, top): NDC x maps to pixel column x * inv_ps + half_w - 0.5 and NDC y to
    row top - y * inv_ps (pixel centres at integers)."""
    return min(s.width, s.height) / 2.0, s.width / 2, s.height / 2 - 0.5


def _pixel_ranges(boxes: np.ndarray, s: RasterSettings):
    """Inclusive pixel column and row ranges (c0, c1, r0, r1), each (B*F,) int64, whose centres
    fall in the (B*F, 4) NDC boxes; clipped to [-1, width] and [-1, height]."""
    w, h = s.width, s.height
    inv_ps, half_w, top = pixel_scale(s)
    c0 = np.ceil(boxes[:, 0] * inv_ps + half_w - 0.5)
    c1 = np.floor(boxes[:, 1] * inv_ps + half_w - 0.5)
    r0 = np.ceil(top - boxes[:, 3] * inv_ps)
    r1 = np.floor(top - boxes[:, 2] * inv_ps)
    clip = lambda a, n: np.clip(a, -1, n).astype(np.int64)
    return clip(c0, w), clip(c1, w), clip(r0, h), clip(r1, h)


def roi_tiles(roi, batch: int, g: Grid, s: RasterSettings) -> np.ndarray | None:
    """(B * nty * ntx,) bool: the tiles of grid g holding at least one pixel of the region of interest.

    roi: None (every tile: returns None), an (H, W) bool mask shared by the batch or (B, H, W).
    """
    if roi is None:
        return None
    mask = np.asarray(roi)
    if mask.dtype != bool or mask.shape not in ((s.height, s.width), (batch, s.height, s.width)):
        raise ValueError(f"roi must be a bool mask of shape ({s.height}, {s.width}) or "
                         f"({batch}, {s.height}, {s.width}), got {mask.dtype} {mask.shape}")
    padded = np.zeros((batch, g.hp, g.wp), bool)
    padded[:, :s.height, :s.width] = mask
    return padded.reshape(batch, g.nty, TILE_H, g.ntx, g.tile_w).any(axis=(2, 4)).reshape(-1)


class RoiTiles:
    """roi_tiles for one grid and settings, remembering the last mask's answer (a fit passes the
    same region for a whole stage; comparing the mask costs a tenth of recomputing it)."""

    def __init__(self, g: Grid, s: RasterSettings):
        self.grid, self.settings = g, s
        self._last: tuple | None = None        # (mask copy, batch, tiles)

    def __call__(self, roi, batch: int) -> np.ndarray | None:
        last = self._last
        if (last is not None and isinstance(roi, np.ndarray) and roi.dtype == last[0].dtype
                and last[1] == batch and np.array_equal(last[0], roi)):
            return last[2]
        tiles = roi_tiles(roi, batch, self.grid, self.settings)
        if tiles is not None:
            tiles.flags.writeable = False
            self._last = (np.array(roi, copy=True), batch, tiles)
        return tiles


def face_tiles(geom: np.ndarray, drawable: np.ndarray, s: RasterSettings, g: Grid) -> np.ndarray:
    """(B*F, 4) int64 (tx0, ty0, nx, ny): the first tile column and row of grid g each face's
    footprint box touches and how many columns and rows; all four 0 for faces that touch no
    pixel or cannot be drawn. geom, drawable: from face_setup."""
    c0, c1, r0, r1 = _pixel_ranges(geom[:, FACE_BOX:FACE_BOX + 4], s)
    c0, r0 = np.maximum(c0, 0), np.maximum(r0, 0)
    c1, r1 = np.minimum(c1, s.width - 1), np.minimum(r1, s.height - 1)
    live = drawable & (c1 >= c0) & (r1 >= r0)
    tx0, ty0 = c0 // g.tile_w, r0 // TILE_H
    ranges = np.stack([tx0, ty0, c1 // g.tile_w - tx0 + 1, r1 // TILE_H - ty0 + 1], 1)
    ranges[~live] = 0
    return ranges


def bin_faces(geom: np.ndarray, drawable: np.ndarray, batch: int, n_faces: int,
              s: RasterSettings, g: Grid, tiles: np.ndarray | None = None) -> Bins:
    """bin_tiles of face_tiles(geom, drawable, s, g): every drawable face binned into the tiles
    its footprint touches."""
    return bin_tiles(face_tiles(geom, drawable, s, g), batch, n_faces, g, tiles)


def bin_tiles(ranges: np.ndarray, batch: int, n_faces: int, g: Grid, tiles: np.ndarray | None = None) -> Bins:
    """Bin every face into the tiles of grid g of its tile range.

    ranges: (B*F, 4) int (tx0, ty0, nx, ny) from face_tiles (or the device set-up); tiles: None
    (all tiles) or (B * nty * ntx,) bool from roi_tiles: only these tiles get faces, the others
    render as background and pass no gradient. ValueError when the (tile, face) pairs would
    overflow int32.
    """
    n_tiles = batch * g.ntx * g.nty
    index = np.int32 if n_tiles < 2 ** 31 else np.int64      # tile ids; int32 arithmetic is faster
    tx0, ty0, nx, ny = (ranges[:, i].astype(index) for i in range(4))
    counts = nx * ny
    face_start = np.concatenate([[0], np.cumsum(counts, dtype=np.int64)])
    total = int(face_start[-1])
    if total >= 2 ** 31:
        raise ValueError(f"{total} (tile, face) pairs exceed the int32 limit: lower image_size, "
                         "raise dist_eps or split the batch")
    face_start = face_start.astype(np.int32)
    face = np.repeat(np.arange(len(counts), dtype=np.int32), counts)
    # entry k of a face is its tile row k // nx, column k % nx, from the face's first tile
    row, col = np.divmod(np.arange(total, dtype=np.int32) - face_start[face], nx[face])
    item = np.arange(len(counts), dtype=index) // n_faces
    tile = ((item * g.nty + ty0) * g.ntx + tx0)[face] + row * g.ntx + col
    slots = None
    if tiles is not None:
        # only the entries in the region of interest go to the kernels; they keep their slots
        # in the full face-major list, whose other slots stay zero, so the per-face sums add
        # the same numbers in the same order as without a region (bit-identical gradients)
        slots = np.flatnonzero(tiles[tile])
        face, tile = face[slots], tile[slots]
    # numpy's stable sort of 16-bit keys is a radix sort: ~10x faster than on wider integers
    order = np.argsort(tile.astype(np.uint16) if n_tiles <= 2 ** 16 else tile, kind="stable")
    tile_start = np.concatenate([[0], np.cumsum(np.bincount(tile, minlength=n_tiles))])
    face_slots = np.full(total, -1, np.int32)
    face_slots[order if slots is None else slots[order]] = np.arange(len(order), dtype=np.int32)
    return Bins(tile_start.astype(np.int32), face[order], face_start, face_slots)
