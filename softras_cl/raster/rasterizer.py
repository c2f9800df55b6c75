"""Soft rasteriser host side: argument checks, per-face setup, tile binning, kernel launches.

Maths: docs/conventions.md. Usage: docs/api.md. The heavy per-(pixel, face) work runs in
kernels/soft_raster.cl; the host prepares O(F) face constants and the O(bins) tile lists in numpy.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pyopencl as cl

from softras_cl.raster.corners import scatter_corners
from softras_cl.cl.device import get_context, has_fp64, has_int64_atomics, select_device
from softras_cl.raster.inputs import MeshInputs, check_cotangent, check_inputs
from softras_cl.cl.program import build_kernel
from softras_cl.raster.settings import RasterSettings

TILE_H = 8          # tile height in rows; tile width = kernel vector width (_tile_width)
FACE_STRIDE = 28    # reals per face in the geometry buffer (see Face in soft_raster.cl)
MIN_AREA = 1e-12    # faces with |doubled NDC area| below this are dropped
GRAD_NAMES = ("vertices", "colors")
# Work-group shape of both kernels. Set explicitly: left to the driver, PoCL picked groups of
# 4096 work-items whose float64 private state overflowed its thread stacks (a crash at 1024^2).
GROUP = (8, 1, 1)


@dataclass
class Bins:
    """Faces binned into tiles. Entries are (tile, face) pairs.

    tile_start: (n_tiles + 1,) int32, entries of tile t are tile_start[t]:tile_start[t+1]
    tile_faces: (n_entries,) int32 global face index (batch * F + f), increasing within a tile
    tile_slots: (n_entries,) int32 position of the entry in face-major order
    face_start: (B*F + 1,) int64, face-major entries of face g are face_start[g]:face_start[g+1]
    """
    tile_start: np.ndarray
    tile_faces: np.ndarray
    tile_slots: np.ndarray
    face_start: np.ndarray

    @property
    def n_entries(self) -> int:
        return int(self.face_start[-1])


@dataclass
class RasterOutput:
    """Images of one forward call, each cropped to (B, H, W[, 3]) in the settings' dtype;
    None for outputs not requested. `saved` holds what backward needs (device buffers)."""
    rgb: np.ndarray | None
    alpha: np.ndarray | None
    depth: np.ndarray | None
    saved: dict = field(default_factory=dict, repr=False)

    def rgba(self) -> np.ndarray:
        """(B, H, W, 4): rgb and alpha side by side (both must have been requested)."""
        if self.rgb is None or self.alpha is None:
            raise ValueError("rgba() needs both 'rgb' and 'alpha' in settings.outputs")
        return np.concatenate([self.rgb, self.alpha[..., None]], axis=-1)


class SoftRasterizer:
    """Renders batches of screen-space meshes with the soft rasteriser and back-propagates.

    settings: RasterSettings. device: a pyopencl.Device (default: softras_cl.cl.device.select_device()).
    """

    def __init__(self, settings: RasterSettings, device: cl.Device | None = None):
        if not isinstance(settings, RasterSettings):
            raise TypeError(f"settings must be a RasterSettings, got {type(settings).__name__}")
        self.settings = settings
        self.device = device if device is not None else select_device()
        if settings.dtype == "float64" and not has_fp64(self.device):
            raise ValueError(f"settings.dtype='float64' but device {self.device.name!r} has no "
                             "cl_khr_fp64; use dtype='float32' or another device")
        self.ctx, self.queue = get_context(self.device)
        self.real = np.dtype(settings.dtype)

    # ---- public API ------------------------------------------------------------------------
    def forward(self, vertices, faces, colors=None, face_textures=None, texture_image=None,
                uvs=None, normals=None, light=None, grads=()) -> RasterOutput:
        """Render. Shapes in docs/api.md; images come back as (B, H, W[, 3]) arrays.

        normals (B, V, 3) and light (27,) only with per-pixel lighting (settings.lighting).
        grads: the gradients backward() will be asked for, subset of ("vertices", "colors");
        with per-pixel lighting "colors" also gives "normals" and "light".
        """
        s = self.settings
        grads = _check_grads(grads, s)
        mesh = check_inputs(s, vertices, faces, colors, face_textures, texture_image, uvs, normals, light)
        if "colors" in grads and s.texture == "uv" and not has_int64_atomics(self.device):
            raise ValueError(f"uv-texture gradients need cl_khr_int64_base_atomics, which device "
                             f"{self.device.name!r} lacks")
        geom, drawable = face_setup(mesh, s)
        bins = bin_faces(geom, drawable, mesh.batch, mesh.n_faces, s)
        bufs = self._upload(mesh, geom, bins)
        images = self._run_forward(mesh, bufs, bool(grads))
        saved = dict(mesh=mesh, bins=bins, bufs=bufs, grads=grads, images=images)
        return RasterOutput(*(self._crop(images.get(n)) for n in ("rgb", "alpha", "depth")), saved)

    def backward(self, output: RasterOutput, grad_rgb=None, grad_alpha=None, grad_depth=None) -> dict:
        """Gradients of a scalar loss given its cotangents dL/d(rgb, alpha, depth).

        Each cotangent has the shape of the matching output (None = zero). Returns a dict with
        the names given as `grads` to forward: "vertices" (shape of the vertices given, float64)
        and "colors" (shape of the colour input given: colors, face_textures or texture_image).
        """
        saved = output.saved
        if not saved or not saved["grads"]:
            raise ValueError("output: forward() was called without grads=...; nothing to differentiate")
        s, mesh = self.settings, saved["mesh"]
        cot = {name: check_cotangent(name, g, _cot_shape(name, mesh.batch, s), name[len("grad_"):] in s.outputs)
               for name, g in (("grad_rgb", grad_rgb), ("grad_alpha", grad_alpha), ("grad_depth", grad_depth))}
        return self._gather_grads(saved, self._run_backward(saved, cot))

    # ---- kernels ---------------------------------------------------------------------------
    def _kernel(self, name: str, grads: tuple, save_state: bool) -> cl.Kernel:
        s = self.settings
        defines = dict(
            SR_DOUBLE=s.dtype == "float64",
            SR_OUT_RGB="rgb" in s.outputs, SR_OUT_ALPHA="alpha" in s.outputs,
            SR_OUT_DEPTH="depth" in s.outputs,
            SR_METRIC_BARY=s.metric == "barycentric",
            SR_COLOR_HARD=s.color_agg == "hard",
            SR_ALPHA_AGG=("occupancy", "sum", "hard").index(s.alpha_agg),
            SR_TEXTURE=("vertex", "face", "uv").index(s.texture),
            SR_PERSPECTIVE=s.perspective_correct,
            SR_LIGHTING=("none", "lambert", "sh").index(s.lighting),
            SR_SAVE_STATE=save_state,
            SR_GRAD_POS="vertices" in grads,
            SR_GRAD_COLOR="colors" in grads and "rgb" in s.outputs)
        return build_kernel(self.ctx, "soft_raster.cl", name, defines, s.fast_math)

    def _geometry_args(self, mesh: MeshInputs, bufs: dict) -> list:
        s, real = self.settings, self.real.type
        g = _grid(s)
        x_cut = -np.finfo(self.real).max if s.dist_eps == 0 else math.log(s.dist_eps / (1 - s.dist_eps))
        i32 = np.int32
        return [i32(s.width), i32(s.height), i32(g.wp), i32(g.hp), i32(g.ntx), i32(g.nty),
                real(2.0 / min(s.width, s.height)), real(1.0 / s.sigma), real(x_cut),
                real(1.0 / s.gamma), real(s.eps), real(s.near), real(s.far),
                i32(mesh.tex_res), i32(mesh.tex_shape[0]), i32(mesh.tex_shape[1]),
                bufs["geom"], bufs["attr"], bufs["tex_image"], bufs["light"], bufs["tile_start"],
                bufs["tile_faces"]]

    def _run_forward(self, mesh: MeshInputs, bufs: dict, save_state: bool) -> dict:
        s, real = self.settings, self.real
        g = _grid(s)
        npix = mesh.batch * g.hp * g.wp
        planes = dict(rgb=3 if "rgb" in s.outputs else 0, alpha=int("alpha" in s.outputs),
                      depth=int("depth" in s.outputs))
        out = {n: cl.Buffer(self.ctx, cl.mem_flags.WRITE_ONLY, npix * k * real.itemsize)
               for n, k in planes.items() if k}
        state = self._state_buffers(npix) if save_state else {}
        dummy = self._dummy()
        knl = self._kernel("soft_raster_fwd", (), save_state)
        knl(self.queue, (_round_up(g.ntx), g.hp, mesh.batch), GROUP, *self._geometry_args(mesh, bufs),
            *(real.type(c) for c in s.background),
            *(out.get(n, dummy) for n in ("rgb", "alpha", "depth")),
            *(state.get(n, dummy) for n in ("color", "alpha", "ids")))
        images = {n: self._download(b, planes[n], mesh.batch) for n, b in out.items()}
        images["state"] = state
        return images

    def _state_buffers(self, npix: int) -> dict:
        """Per-pixel state the backward reads: softmax log-normaliser or hard face ids, and the
        occupancy sums (two planes) or the sum of D."""
        s, itemsize = self.settings, self.real.itemsize
        rw = cl.mem_flags.READ_WRITE
        state = {}
        if {"rgb", "depth"} & set(s.outputs) and s.color_agg == "softmax":
            state["color"] = cl.Buffer(self.ctx, rw, npix * itemsize)
        if "alpha" in s.outputs and s.alpha_agg != "hard":
            state["alpha"] = cl.Buffer(self.ctx, rw, npix * itemsize * (2 if s.alpha_agg == "occupancy" else 1))
        state["ids"] = cl.Buffer(self.ctx, rw, npix * 4 * 2)
        return state

    def _run_backward(self, saved: dict, cot: dict):
        s, real, mesh, bins = self.settings, self.real, saved["mesh"], saved["bins"]
        g = _grid(s)
        images, grads = saved["images"], saved["grads"]
        # an output without a cotangent contributes zero; the kernel variant still reads its plane
        planes = {n: self._pad_planes(c if c is not None else np.zeros(_cot_shape(n, mesh.batch, s)), mesh.batch)
                  for n, c in cot.items() if n[len("grad_"):] in s.outputs}
        g_dot = self._g_dot_image(images, planes, mesh.batch)
        ro = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        dummy = self._dummy()
        cot_bufs = [cl.Buffer(self.ctx, ro, hostbuf=planes[n]) if n in planes else dummy
                    for n in ("grad_rgb", "grad_alpha", "grad_depth")]
        g_dot_buf = cl.Buffer(self.ctx, ro, hostbuf=g_dot) if g_dot is not None else dummy
        n = max(bins.n_entries, 1)
        slot_pos = np.zeros((n, 9), real) if "vertices" in grads else None
        slot_attr, tex_fixed, scale = self._color_grad_buffers(mesh, grads, n, cot["grad_rgb"])
        slot_light = np.zeros((n, 27), real) if slot_attr is not None and s.lighting != "none" else None
        rw = cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR
        hosts = (slot_pos, slot_attr, slot_light, tex_fixed)
        out_bufs = [cl.Buffer(self.ctx, rw, hostbuf=a) if a is not None else dummy for a in hosts]
        state = images["state"]
        kernel_grads = tuple(g for g in grads if g != "colors" or slot_attr is not None or tex_fixed is not None)
        if not kernel_grads:    # colour gradients only, and no rgb cotangent: all zero
            return dict(pos=slot_pos, attr=slot_attr, light=slot_light, tex=tex_fixed, scale=scale)
        knl = self._kernel("soft_raster_bwd", kernel_grads, True)
        knl(self.queue, (_round_up(g.ntx), g.nty, mesh.batch), GROUP, *self._geometry_args(mesh, saved["bufs"]),
            saved["bufs"]["tile_slots"], *cot_bufs, g_dot_buf,
            *(state.get(k, dummy) for k in ("color", "alpha", "ids")), real.type(scale), *out_bufs)
        for host, dev in zip(hosts, out_bufs):
            if host is not None:
                cl.enqueue_copy(self.queue, host, dev)
        return dict(pos=slot_pos, attr=slot_attr, light=slot_light, tex=tex_fixed, scale=scale)

    def _color_grad_buffers(self, mesh: MeshInputs, grads: tuple, n_entries: int, grad_rgb):
        """Host arrays the backward writes colour gradients into, and the uv fixed-point scale."""
        s = self.settings
        if "colors" not in grads or "rgb" not in s.outputs or grad_rgb is None:
            return None, None, 1.0
        if s.texture == "vertex":
            return np.zeros((n_entries, 18 if s.lighting != "none" else 9), self.real), None, 1.0
        if s.texture == "face":
            return np.zeros((n_entries, mesh.tex_res ** 2 * 3), self.real), None, 1.0
        scale = _fixed_point_scale(grad_rgb, self.real)
        return None, np.zeros((mesh.batch, *mesh.tex_shape, 3), np.int64), scale

    def _gather_grads(self, saved: dict, slots: dict) -> dict:
        """Sum the (tile, face) slots per face in a fixed order, then faces onto vertices."""
        mesh, bins, grads = saved["mesh"], saved["bins"], saved["grads"]
        out = {}
        if "vertices" in grads:
            per_face = _sum_slots(slots["pos"], bins).reshape(mesh.batch, mesh.n_faces, 3, 3)
            out["vertices"] = mesh.unbatch_vertices(scatter_corners(per_face, mesh.faces, mesh.n_vertices))
        if "colors" in grads:
            out.update(self._color_grads(mesh, bins, slots))
        return out

    def _color_grads(self, mesh: MeshInputs, bins: Bins, slots: dict) -> dict:
        """{"colors": gradient shaped like the colour input} (+ "normals", "light" when lit)."""
        s, attr = self.settings, slots["attr"]
        if s.texture == "uv":
            tex = slots["tex"]
            g = (np.zeros((mesh.batch, *mesh.tex_shape, 3)) if tex is None
                 else tex.astype(np.float64) / slots["scale"])
            return dict(colors=mesh.unbatch_colors(g))
        if s.texture == "face":
            r = mesh.tex_res
            g = (np.zeros((mesh.batch * mesh.n_faces, r * r * 3)) if attr is None else _sum_slots(attr, bins))
            return dict(colors=mesh.unbatch_colors(g.reshape(mesh.batch, mesh.n_faces, r, r, 3)))
        width = 18 if s.lighting != "none" else 9
        per_face = (np.zeros((mesh.batch * mesh.n_faces, width)) if attr is None else _sum_slots(attr, bins))
        per_face = per_face.reshape(mesh.batch, mesh.n_faces, width // 3, 3)
        out = dict(colors=mesh.unbatch_colors(
            scatter_corners(per_face[:, :, :3], mesh.faces, mesh.n_vertices)))
        if s.lighting != "none":
            out["normals"] = scatter_corners(per_face[:, :, 3:], mesh.faces, mesh.n_vertices)
            light = slots["light"]
            out["light"] = (np.zeros(27) if light is None
                            else light[:bins.n_entries].astype(np.float64).sum(0))
        return out

    # ---- buffers ---------------------------------------------------------------------------
    def _upload(self, mesh: MeshInputs, geom: np.ndarray, bins: Bins) -> dict:
        ro = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        arrays = dict(geom=geom.astype(self.real, order="C"), attr=mesh.face_attributes().astype(self.real),
                      tex_image=mesh.texture_image_array().astype(self.real),
                      light=(mesh.light if mesh.light is not None else np.zeros(0)).astype(self.real),
                      tile_start=bins.tile_start, tile_faces=bins.tile_faces,
                      tile_slots=bins.tile_slots)
        return {name: cl.Buffer(self.ctx, ro, hostbuf=np.ascontiguousarray(a)) if a.size else self._dummy()
                for name, a in arrays.items()}

    def _dummy(self) -> cl.Buffer:
        """A small buffer standing in for arguments the kernel variant never reads."""
        if not hasattr(self, "_dummy_buf"):
            self._dummy_buf = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, 64)
        return self._dummy_buf

    def _download(self, buf: cl.Buffer, n_planes: int, batch: int) -> np.ndarray:
        """(planes, B, Hp, Wp) host copy of a per-pixel device buffer."""
        g = _grid(self.settings)
        host = np.empty((n_planes, batch, g.hp, g.wp), self.real)
        cl.enqueue_copy(self.queue, host, buf)
        return host

    def _crop(self, planes: np.ndarray | None) -> np.ndarray | None:
        """(planes, B, Hp, Wp) -> (B, H, W) for one plane, (B, H, W, planes) otherwise."""
        if planes is None:
            return None
        h, w = self.settings.height, self.settings.width
        img = planes[:, :, :h, :w]
        return img[0].copy() if img.shape[0] == 1 else np.ascontiguousarray(np.moveaxis(img, 0, -1))

    def _pad_planes(self, image: np.ndarray, batch: int) -> np.ndarray:
        """(B, H, W[, C]) -> (C, B, Hp, Wp) zero-padded, in the kernel dtype."""
        g = _grid(self.settings)
        planes = image[None] if image.ndim == 3 else np.moveaxis(image, -1, 0)
        out = np.zeros((planes.shape[0], batch, g.hp, g.wp), self.real)
        out[:, :, :image.shape[1], :image.shape[2]] = planes
        return out

    def _g_dot_image(self, images: dict, planes: dict, batch: int) -> np.ndarray | None:
        """Per-pixel sum over rgb and depth channels of cotangent * output (softmax backward)."""
        s = self.settings
        if s.color_agg != "softmax" or not {"rgb", "depth"} & set(s.outputs):
            return None
        total = np.zeros(images.get("rgb", images.get("depth")).shape[1:], self.real)
        h = s.height   # the forward never writes the padding rows below the image
        for cot_name, img_name in (("grad_rgb", "rgb"), ("grad_depth", "depth")):
            if cot_name in planes:
                total[:, :h] += (planes[cot_name][:, :, :h] * images[img_name][:, :, :h]).sum(0)
        return total


# ---- face setup and binning (numpy, O(F) and O(bins)) ---------------------------------------
def _round_up(n: int) -> int:
    """n rounded up to a whole number of work-groups along x (the kernels skip the extra items)."""
    return -(-n // GROUP[0]) * GROUP[0]


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


def _grid(s: RasterSettings) -> Grid:
    """The tiling for the settings: one tile row is one kernel vector (8 floats or 4 doubles)."""
    tile_w = 4 if s.dtype == "float64" else 8
    return Grid(tile_w, -(-s.width // tile_w), -(-s.height // TILE_H))


def face_setup(mesh: MeshInputs, s: RasterSettings) -> tuple[np.ndarray, np.ndarray]:
    """Per-face constants for the kernel and which faces can be drawn at all.

    Returns geom (B*F, FACE_STRIDE) float64 (layout: Face in soft_raster.cl; a transposed view,
    made contiguous when cast to the kernel dtype) and drawable (B*F,) bool.
    """
    # one contiguous (B*F,) array per coordinate of each corner: x[k], y[k], z[k]
    x, y, z = np.moveaxis(mesh.triangles().reshape(-1, 3, 3), (2, 1), (0, 1)).copy()
    area = (x[1] - x[0]) * (y[2] - y[0]) - (x[2] - x[0]) * (y[1] - y[0])
    drawable = ((np.abs(area) >= MIN_AREA) & (z.min(0) > 0) & (z.max(0) >= s.near) & (z.min(0) <= s.far))
    if not s.double_sided:
        drawable &= area > 0
    inv_area = 1.0 / np.where(drawable, area, 1.0)
    m1 = ((y[2] - y[0]) * inv_area, -(x[2] - x[0]) * inv_area)
    m2 = (-(y[1] - y[0]) * inv_area, (x[1] - x[0]) * inv_area)
    edge_len2 = [(x[(k + 1) % 3] - x[k]) ** 2 + (y[(k + 1) % 3] - y[k]) ** 2 for k in range(3)]
    rows = np.zeros((FACE_STRIDE, len(area)))
    rows[0:6:2], rows[1:6:2] = x, y
    rows[6:12] = [-(m1[0] + m2[0]), -(m1[1] + m2[1]), *m1, *m2]
    rows[12:15] = z
    rows[15:18] = 1.0 / np.where(drawable, z, 1.0)
    rows[18:21] = [1.0 / np.where(drawable & (l2 > 0), l2, 1.0) for l2 in edge_len2]
    rows[24:28] = _footprint_boxes(x, y, s)
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


def _footprint_boxes(x: np.ndarray, y: np.ndarray, s: RasterSettings) -> np.ndarray:
    """(4, B*F) NDC boxes (xmin, xmax, ymin, ymax) where a face can reach D >= dist_eps, from
    corner coordinates x, y (3, B*F).

    Grown by a thousandth of a pixel, so that float32 kernels never meet a pair the box
    excludes; unbounded footprints (dist_eps = 0) are clipped to +-1e6.
    """
    margin = footprint_margin(s)
    if s.metric == "barycentric" and math.isfinite(margin):
        grow = 1 + 3 * margin                              # region min(b) >= -margin
        x = x.mean(0) + grow * (x - x.mean(0))
        y = y.mean(0) + grow * (y - y.mean(0))
        margin = 0.0
    margin += 2e-3 / min(s.width, s.height)
    box = [x.min(0) - margin, x.max(0) + margin, y.min(0) - margin, y.max(0) + margin]
    return np.clip(box, -1e6, 1e6)


def _pixel_ranges(boxes: np.ndarray, s: RasterSettings):
    """Inclusive pixel column and row ranges whose centres fall in the boxes (clipped)."""
    w, h = s.width, s.height
    inv_ps = min(w, h) / 2.0
    c0 = np.ceil(boxes[:, 0] * inv_ps + w / 2 - 0.5)
    c1 = np.floor(boxes[:, 1] * inv_ps + w / 2 - 0.5)
    r0 = np.ceil(h / 2 - 0.5 - boxes[:, 3] * inv_ps)
    r1 = np.floor(h / 2 - 0.5 - boxes[:, 2] * inv_ps)
    clip = lambda a, n: np.clip(a, -1, n).astype(np.int64)
    return clip(c0, w), clip(c1, w), clip(r0, h), clip(r1, h)


def bin_faces(geom: np.ndarray, drawable: np.ndarray, batch: int, n_faces: int,
              s: RasterSettings) -> Bins:
    """Bin every drawable face into the tiles its footprint touches."""
    g = _grid(s)
    c0, c1, r0, r1 = _pixel_ranges(geom[:, 24:28], s)
    c0, r0 = np.maximum(c0, 0), np.maximum(r0, 0)
    c1, r1 = np.minimum(c1, s.width - 1), np.minimum(r1, s.height - 1)
    live = drawable & (c1 >= c0) & (r1 >= r0)
    tx0, ty0 = c0 // g.tile_w, r0 // TILE_H
    nx = np.where(live, c1 // g.tile_w - tx0 + 1, 0)
    ny = np.where(live, r1 // TILE_H - ty0 + 1, 0)
    counts = nx * ny
    face_start = np.concatenate([[0], np.cumsum(counts)])
    total = int(face_start[-1])
    if total >= 2 ** 31:
        raise ValueError(f"{total} (tile, face) pairs exceed the int32 limit: lower image_size, "
                         "raise dist_eps or split the batch")
    face = np.repeat(np.arange(len(counts)), counts)
    local = np.arange(total) - face_start[face]
    tx = tx0[face] + local % nx[face]
    ty = ty0[face] + local // nx[face]
    tile = ((face // n_faces) * g.nty + ty) * g.ntx + tx if total else np.zeros(0, np.int64)
    order = np.argsort(tile, kind="stable")
    tile_start = np.concatenate([[0], np.cumsum(np.bincount(tile, minlength=batch * g.ntx * g.nty))])
    return Bins(tile_start.astype(np.int32), face[order].astype(np.int32),
                order.astype(np.int32), face_start)


# ---- gradient reduction ---------------------------------------------------------------------
def _sum_slots(slots: np.ndarray, bins: Bins) -> np.ndarray:
    """(n_entries, K) per-(tile, face) sums -> (B*F, K) per-face sums, always in the same order."""
    counts = np.diff(bins.face_start)
    out = np.zeros((len(counts), slots.shape[1]))
    has = counts > 0
    if has.any():
        out[has] = np.add.reduceat(slots[:bins.n_entries].astype(np.float64), bins.face_start[:-1][has], axis=0)
    return out


def _fixed_point_scale(grad_rgb: np.ndarray, real: np.dtype) -> float:
    """Power of two that maps uv-texel gradient sums into int64 without overflow.

    Every texel's sum is bounded by sum |dL/drgb| over the image (weights and bilinear taps sum
    to at most 1), so that bound times the scale stays below 2^62.
    """
    bound = float(np.abs(grad_rgb).sum(axis=(1, 2, 3)).max()) if grad_rgb.size else 0.0
    top = 100 if real == np.float32 else 1000
    if bound == 0.0:
        return 1.0
    return 2.0 ** min(top, math.floor(62 - math.log2(bound)))


def _cot_shape(name: str, batch: int, s: RasterSettings) -> tuple:
    """Shape of the cotangent `name` ("grad_rgb", ...): (B, H, W) plus (3,) for rgb."""
    return (batch, s.height, s.width) + ((3,) if name == "grad_rgb" else ())


def _check_grads(grads, s: RasterSettings) -> tuple:
    grads = tuple(grads)
    bad = [g for g in grads if g not in GRAD_NAMES]
    if bad:
        raise ValueError(f"grads must be a subset of {GRAD_NAMES}, got {grads!r}")
    if "colors" in grads and "rgb" not in s.outputs:
        raise ValueError(f"grads asks for 'colors' but settings.outputs={s.outputs} uses no colours")
    return grads


def soft_rasterize(vertices, faces, settings: RasterSettings | None = None, **color_inputs) -> RasterOutput:
    """One-shot forward: SoftRasterizer(settings).forward(vertices, faces, **colour_inputs)."""
    return SoftRasterizer(settings or RasterSettings()).forward(vertices, faces, **color_inputs)
