"""Soft rasteriser host side: the `SoftRasterizer` API, kernel launches and gradient reductions.

Maths: docs/conventions.md. Usage: docs/api.md. The heavy per-(pixel, face) work runs in
kernels/soft_raster.cl; face set-up and tile binning (numpy) live in softras_cl.raster.binning.
What a forward keeps for its backward is a `RasterContext`.

One rasteriser serves every sigma, gamma and depth range: those run-time settings can be given to
each forward (RUN_FIELDS), which keeps them in its output for the backward.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, fields

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from softras_cl.cl.device import has_fp64, has_int64_atomics, kernel_layout, resolve_context, vector_lanes
from softras_cl.cl.layout import (CORNER_COLORS, FACE_STRIDE, GPU_BWD_GROUP, GPU_CHUNK, GPU_TILE_W, LANES,
                                  LIGHT_PARAMS, TILE_H, vertex_attr_width)
from softras_cl.cl.program import build_kernel, launch
from softras_cl.raster.binning import Bins, RoiTiles, bin_tiles, face_setup, face_tiles, tile_grid
from softras_cl.raster.device_arrays import DeviceArrays, read_together
from softras_cl.raster.device_bins import DeviceBinning, DeviceBins
from softras_cl.raster.device_inputs import (ValueChecks, any_bad, check_context, is_device_array, on_host,
                                             standin)
from softras_cl.raster.device_setup import DeviceSetup
from softras_cl.raster.inputs import MeshInputs, check_cotangent, check_inputs
from softras_cl.raster.memory import check_forward_memory
from softras_cl.raster.pool import BufferPool, ScratchArrays
from softras_cl.raster.reduce import GradSums
from softras_cl.raster.settings import RasterSettings, check_float32_gradients, depth_bound

GRAD_NAMES = ("vertices", "colors")
# run-time settings that forward() takes per call (None: the rasteriser's settings' value)
RUN_FIELDS = ("sigma", "gamma", "near", "far")
# distinct per-call settings kept made (validated) per rasteriser: a fit's schedule has a handful
RUN_SETTINGS_KEPT = 64
# B*F faces from which the face set-up runs on the device (where it can): below, the host's numpy
# costs less than the device's upload, launch and wait (PoCL, 2 cores: about equal at 1000 faces)
DEVICE_SETUP_FACES = 1024
# bytes from which an upload that needs no conversion gets its own transfer rather than a copy
# into the staging of the others (SoftRasterizer._upload_parts): ~0.1 ms per MB copied against
# ~30 us per transfer enqueued (PoCL, 2 cores)
OWN_TRANSFER = 256 * 1024
# Work-group shape of both kernels. Set explicitly: left to the driver, PoCL picked groups of
# 4096 work-items whose float64 private state overflowed its thread stacks (a crash at 1024^2).
GROUP = (8, 1, 1)
# Image rows per forward work-item (kernels/soft_raster.cl, SR_ROWS; divides TILE_H): each face
# record is loaded once for that many rows. A whole tile, as in the backward: 1, 2, 4, 8 rows cost
# 57, 59, 55, 52 ms CPU at 1024^2 on PoCL (docs/notes/raster_passes.md, "Sixth pass: kernels").
FWD_ROWS = 8


@dataclass
class FaceBuffers:
    """Read-only device copies of one forward's per-face inputs and bins. `real` is the settings'
    dtype; an empty input is the rasteriser's small dummy buffer instead.

    geom: (B*F, FACE_STRIDE) real, records of softras_cl.raster.binning.face_setup
    attr: (B*F, K) real, MeshInputs.face_attributes() (corner colours [+ normals], texels or uvs)
    tex_image: (B, Ht, Wt, 3) real uv texture map
    light: (LIGHT_PARAMS,) real lighting parameters
    tile_start, tile_faces, face_start, face_slots: int32, the arrays of the same names in Bins
        (the last two only with gradients, for the backward's sums; else the dummy buffer)
    owned: the pooled buffers behind them (the others are sub-buffers of these, or the dummy)
    arrays: pyopencl arrays behind the others (the device-resident path), kept alive with them
    """
    geom: cl.Buffer
    attr: cl.Buffer
    tex_image: cl.Buffer
    light: cl.Buffer
    tile_start: cl.Buffer
    tile_faces: cl.Buffer
    face_start: cl.Buffer
    face_slots: cl.Buffer
    owned: list
    arrays: list = field(default_factory=list)


@dataclass
class PixelState:
    """Per-pixel device state the forward writes for the backward, over the padded image
    (planes of B x Hp x Wp pixels, see binning.Grid); None where the settings need none.

    color: (B, Hp, Wp) real, softmax log-normaliser of rgb/depth (softmax colour aggregation)
    alpha: (2, B, Hp, Wp) real for occupancy (sum of log(1 - D) without its smallest term, and
        that term), (B, Hp, Wp) real sum of D for alpha_agg "sum"
    ids: (2, B, Hp, Wp) int32, face of the hard colour and face of the smallest occupancy term
    """
    color: cl.Buffer | None
    alpha: cl.Buffer | None
    ids: cl.Buffer


@dataclass
class RasterContext:
    """What one forward keeps for its backward.

    rasterizer: the SoftRasterizer whose forward made it (only its backward takes it: the device
    buffers belong to its pool). settings: the settings the forward drew with (the rasteriser's,
    with the call's sigma, gamma, near and far). mesh: the checked inputs. grads: the gradient
    names forward was asked for (non-empty). bins: the (tile, face) lists (host). buffers: the
    device inputs. images: the forward's outputs as device buffers of (planes, B, Hp, Wp) reals,
    keyed "rgb" (3 planes), "alpha", "depth" (1 plane each), requested outputs only. state: the
    per-pixel device state. The device buffers go back to the rasteriser's pool when the context
    is garbage collected. device_faces: the faces as given, a pyopencl array, when the forward
    took device arrays (then `mesh` holds stand-ins for the shapes, `bins` are DeviceBins and
    backward returns pyopencl arrays, or numpy arrays for numpy_io: a forward of numpy inputs
    through the device path, see SoftRasterizer.numpy_via_device); else None.
    """
    rasterizer: "SoftRasterizer"
    settings: RasterSettings
    mesh: MeshInputs
    grads: tuple[str, ...]
    bins: Bins
    buffers: FaceBuffers
    images: dict[str, cl.Buffer]
    state: PixelState
    device_faces: cla.Array | None = None
    numpy_io: bool = False      # a device forward of numpy inputs: backward downloads the gradients
    check_values: bool = True   # backward checks its device cotangents' values (forward's check_values)

    def nbytes(self) -> int:
        """Bytes kept: bin arrays (host or device) and device buffers, each buffer counted once."""
        host = sum(a.nbytes for a in (self.bins.tile_start, self.bins.tile_faces,
                                      self.bins.face_start, self.bins.face_slots))
        return host + sum(b.size for b in self.device_buffers())

    def device_buffers(self) -> list:
        """Every pooled device buffer the context holds (sub-buffers are counted in theirs), each once."""
        found = self.buffers.owned + [getattr(self.state, f.name) for f in fields(self.state)]
        return list({b.int_ptr: b for b in found + list(self.images.values()) if b is not None}.values())


@dataclass
class ForwardImages:
    """The images of a forward call: rgb (B, H, W, 3), alpha and depth (B, H, W) in the
    settings' dtype; None for outputs not requested."""
    rgb: np.ndarray | None
    alpha: np.ndarray | None
    depth: np.ndarray | None

    def rgba(self) -> np.ndarray:
        """(B, H, W, 4): rgb and alpha side by side (both must have been requested)."""
        if self.rgb is None or self.alpha is None:
            raise ValueError("rgba() needs both 'rgb' and 'alpha' in settings.outputs")
        return np.concatenate([self.rgb, self.alpha[..., None]], axis=-1)


@dataclass
class RasterOutput(ForwardImages):
    """Images of one SoftRasterizer.forward call, each cropped to (B, H, W[, 3]) (ForwardImages).
    `saved` holds what backward needs; None when forward was called without grads."""
    saved: RasterContext | None = None


class SoftRasterizer:
    """Renders batches of screen-space meshes with the soft rasteriser and back-propagates.

    settings: RasterSettings. device, context, queue: optional pyopencl Device, Context and
    in-order CommandQueue to run on (see softras_cl.cl.device.resolve_context); by default the
    cached context of softras_cl.cl.device.select_device(). lanes: pixels per kernel vector
    (and tile width) of the CPU layout, one of softras_cl.cl.layout.LANES[settings.dtype]; None
    picks the device's (softras_cl.cl.device.vector_lanes). Images are the same at any width;
    gradient sums are grouped by tile, so their last bits depend on it. settings.layout picks the
    kernels' work layout (`layout`: "cpu" or "gpu", softras_cl.cl.device.kernel_layout); the GPU
    layout has one pixel per work-item (lanes is then 1) on tiles GPU_TILE_W wide.

    One rasteriser renders at any sigma, gamma, near and far (forward's RUN_FIELDS arguments);
    the other settings are fixed: they select the kernel variant, the tiling and the buffers.

    numpy_via_device: numpy inputs go through the device path (uploaded, checked, set up and
    binned on the device, the results downloaded; the same bits as the host path, docs/api.md)
    instead of the host path (host checks, set-up and binning). True on a GPU or an accelerator
    that does not also say it is a CPU (kernel_layout's "auto"; Oclgrind's simulator claims
    every type and runs the host path), where the host
    passes and their transfers cost 30 times the kernels (docs/gpu_check.md); False on a CPU
    device, where each device launch costs more than the host pass it replaces (docs/speed.md).
    """

    def __init__(self, settings: RasterSettings, device: cl.Device | None = None,
                 context: cl.Context | None = None, queue: cl.CommandQueue | None = None,
                 lanes: int | None = None):
        if not isinstance(settings, RasterSettings):
            raise TypeError(f"settings must be a RasterSettings, got {type(settings).__name__}")
        self.settings = settings
        self.device, self.ctx, self.queue = resolve_context(device, context, queue)
        if settings.dtype == "float64" and not has_fp64(self.device):
            raise ValueError(f"settings.dtype='float64' but device {self.device.name!r} has no "
                             "cl_khr_fp64; use dtype='float32' or another device")
        self.real = np.dtype(settings.dtype)
        self.layout = kernel_layout(self.device, settings.layout)
        if lanes is not None and self.layout == "gpu":
            raise ValueError(f"lanes applies to layout 'cpu' only; settings.layout={settings.layout!r} "
                             f"runs the 'gpu' layout on {self.device.name!r} (one pixel per work-item)")
        if lanes is not None and lanes not in LANES[settings.dtype]:
            raise ValueError(f"lanes must be one of {LANES[settings.dtype]} for dtype={settings.dtype!r}, got {lanes!r}")
        if self.layout == "gpu":
            _check_local_memory(self.device, self.real.itemsize)
            self.lanes = 1
            self.grid = tile_grid(settings, GPU_TILE_W)
        else:
            self.lanes = lanes or vector_lanes(self.device, settings.dtype)
            self.grid = tile_grid(settings, self.lanes)
        self.roi_tiles = RoiTiles(self.grid, settings)
        # device buffers and host staging reused from call to call (softras_cl.raster.pool)
        self.pool = BufferPool(self.ctx)
        self.scratch = ScratchArrays()
        self.sums = GradSums(self.ctx, self.queue, self.pool, self.real, self.lanes, has_fp64(self.device))
        self.setup = (DeviceSetup(self.ctx, self.queue, self.pool, self.grid, self.real)
                      if has_fp64(self.device) else None)
        self.device_setup_faces = DEVICE_SETUP_FACES
        self.numpy_via_device = kernel_layout(self.device, "auto") == "gpu"
        # events of transfers in flight: pyopencl's transfer events wait for their transfer when
        # freed, so they are kept until _sync waits for all of them at once
        self._transfers: list = []
        # stage_ms: None (default), or a dict that forward/backward add their stages' wall times
        # to, in ms: "setup" (input checks, face set-up), "binning", "upload", "forward" (kernel
        # and image download), "cotangent_checks" (backward's input checks), "cotangent_upload"
        # (their cast and transfer), "backward_prep" (cotangent planes and buffers), "backward"
        # (kernel), "reductions" (per-face sums and sums onto vertices, their download).
        # Kernel stages then end with a queue.finish(); for profiling (softras-cl bench raster).
        self.stage_ms: dict | None = None
        self._kernels: dict = {}
        self._run_settings: dict = {}      # RUN_FIELDS values -> the settings made with them
        self._depth_ranges: dict = {}      # (near, far, batch) -> their device copy

    def _stage(self, name: str, start: float, finish: bool = False) -> float:
        """Add the time since `start` to stage_ms[name] (when profiling); returns the new start."""
        if self.stage_ms is None:
            return start
        if finish:
            self.queue.finish()
        now = time.perf_counter()
        self.stage_ms[name] = self.stage_ms.get(name, 0.0) + 1e3 * (now - start)
        return now

    # ---- public API ------------------------------------------------------------------------
    def forward(self, vertices, faces, colors=None, face_textures=None, texture_image=None,
                uvs=None, normals=None, light=None, grads=(), roi=None, sigma=None, gamma=None,
                near=None, far=None, check_values: bool = True) -> RasterOutput:
        """Render. Shapes in docs/api.md; images come back as (B, H, W[, 3]) arrays.

        sigma, gamma, near, far: this call's values of those settings (None: the rasteriser's
        settings' own), checked as RasterSettings checks them; the output keeps them for backward.

        roi: None, or an (H, W) / (B, H, W) bool mask of the pixels wanted: only the tiles
        (binning.Grid) holding one of them are rasterised; every other pixel comes back as
        background (rgb background, alpha 0, depth far) and passes no gradient. Pixels in those
        tiles are bit-identical to a render without roi, and so are the gradients of a loss whose
        cotangents are zero outside the tiles.

        normals (B, V, 3) and light (27,) only with per-pixel lighting (settings.lighting).
        grads: the gradients backward() will be asked for, subset of ("vertices", "colors");
        with per-pixel lighting "colors" also gives "normals" and "light".

        Device-resident inputs: when any array argument is a pyopencl.array.Array (in this
        rasteriser's context: `queue`), every input is checked, set up and binned on the device
        and the images come back as pyopencl arrays (docs/api.md, "Device-resident calls").
        check_values=False skips the device checks of their values (NaN/Inf, face indices) here
        and of the cotangents' in backward, for a caller whose arrays come from its own kernels
        on values it checked (a fit's objective: one reduction and one wait less per argument);
        their shapes and dtypes are checked all the same. Numpy inputs are always checked.
        """
        t = time.perf_counter()
        s = self.call_settings(sigma=sigma, gamma=gamma, near=near, far=far)
        grads = _check_grads(grads, s)
        if grads:
            check_float32_gradients(s)
        inputs = dict(vertices=vertices, faces=faces, colors=colors, face_textures=face_textures,
                      texture_image=texture_image, uvs=uvs, normals=normals, light=light)
        if any(is_device_array(v) for v in inputs.values()):
            return self._forward_device(s, inputs, grads, roi, t, check_values)
        if self.numpy_via_device:
            return self._forward_numpy_via_device(s, inputs, grads, roi, t)
        return self._forward_host(s, inputs, grads, roi, t)

    def _forward_host(self, s: RasterSettings, inputs: dict, grads: tuple, roi, t: float) -> RasterOutput:
        """forward() of numpy inputs on the host path: host checks, face set-up and binning."""
        mesh = check_inputs(s, **inputs)
        self._check_resources(s, mesh, grads)
        tiles = self.roi_tiles(roi, mesh.batch)
        geom, ranges = self._face_setup(mesh, s)
        t = self._stage("setup", t)
        bins = bin_tiles(ranges, mesh.batch, mesh.n_faces, self.grid, tiles)
        t = self._stage("binning", t)
        buffers = self._upload(mesh, geom, bins, bool(grads))
        state = self._state_buffers(mesh.batch) if grads else None
        t = self._stage("upload", t, finish=True)
        images = self._run_forward(s, mesh, buffers, state)
        hosts, packed = self._download(images, mesh.batch, state is not None)
        self._sync()
        self.pool.give(packed.values())
        crops = [hosts.get(n) for n in ("rgb", "alpha", "depth")]
        saved = RasterContext(self, s, mesh, grads, bins, buffers, images, state) if grads else None
        if saved is not None:
            self.pool.give_when_dead(saved, saved.device_buffers())
        else:
            self.pool.give(list(images.values()) + buffers.owned)
        self._stage("forward", t, finish=True)
        return RasterOutput(*crops, saved)

    def _check_resources(self, s: RasterSettings, mesh: MeshInputs, grads: tuple) -> None:
        """The device's support for the call (uv gradients) and its memory (ResourceError)."""
        if ("colors" in grads and s.texture == "uv" and not has_int64_atomics(self.device)
                and not self.device.endian_little):
            raise ValueError(f"texture='uv' gradients need cl_khr_int64_base_atomics or a little-endian "
                             f"device (32-bit word pairs); device {self.device.name!r} has neither")
        check_forward_memory(s, self.device, mesh.batch, mesh.n_faces, grads, mesh.tex_res, mesh.tex_shape)

    # ---- device-resident path --------------------------------------------------------------
    @property
    def device_arrays(self) -> DeviceArrays:
        if not hasattr(self, "_device_arrays"):
            self._device_arrays = DeviceArrays(self.ctx, self.queue)
        return self._device_arrays

    @property
    def value_checks(self) -> ValueChecks:
        if not hasattr(self, "_value_checks"):
            self._value_checks = ValueChecks(self.ctx)
        return self._value_checks

    @property
    def device_binning(self) -> DeviceBinning:
        if not hasattr(self, "_device_binning"):
            self._device_binning = DeviceBinning(self.ctx, self.queue, self.grid)
        return self._device_binning

    def _check_device_inputs(self, s: RasterSettings, inputs: dict, check_values: bool = True
                             ) -> tuple[MeshInputs, dict]:
        """(MeshInputs of stand-ins for the shapes, {name: pyopencl array or None}) of forward's
        arguments, some of them pyopencl arrays: their context, then what they are (on the host,
        from their shapes and dtypes), then (check_values) their values (one device reduction
        each). Numpy arguments among them are uploaded. Anything wrong raises the numpy path's
        error."""
        for name, value in inputs.items():
            check_context(name, value, self.ctx)
        try:
            mesh = check_inputs(s, **{n: standin(v) for n, v in inputs.items()}, values=False)
        except (ValueError, TypeError):
            check_inputs(s, **{n: on_host(v) for n, v in inputs.items()})      # the numpy path's first error
            raise
        dev = {n: v if v is None or is_device_array(v) else cla.to_device(self.queue, np.ascontiguousarray(v))
               for n, v in inputs.items()}
        if dev["light"] is not None:
            dev["light"] = dev["light"].reshape(-1)
        if not check_values:
            return mesh, dev
        counts = [self.value_checks.count_bad_floats(v, s.dtype == "float32")
                  for n, v in dev.items() if v is not None and n != "faces"]
        if dev["faces"].size:
            counts.append(self.value_checks.count_bad_indices(dev["faces"], mesh.n_vertices))
        if any_bad(counts):
            check_inputs(s, **{n: on_host(v) for n, v in inputs.items()})
            raise RuntimeError("the device input checks found bad values that the host checks did not")
        return mesh, dev

    def _forward_numpy_via_device(self, s: RasterSettings, inputs: dict, grads: tuple, roi,
                                  t: float) -> RasterOutput:
        """forward() of numpy inputs through the device path: the images downloaded, and the
        context marked so that backward downloads the gradients."""
        out = self._forward_device(s, inputs, grads, roi, t)
        if out.saved is not None:
            out.saved.numpy_io = True
        return RasterOutput(*(None if a is None else a.get() for a in (out.rgb, out.alpha, out.depth)), out.saved)

    def _forward_device(self, s: RasterSettings, inputs: dict, grads: tuple, roi, t: float,
                        check_values: bool = True) -> RasterOutput:
        """forward() of device-resident inputs: images as pyopencl arrays (the numpy path's bits)."""
        mesh, dev = self._check_device_inputs(s, inputs, check_values)
        self._check_resources(s, mesh, grads)
        if mesh.n_faces == 0:       # nothing to set up or bin: the host path's background images
            out = self._forward_host(s, {n: on_host(v) for n, v in inputs.items()}, grads, on_host(roi), t)
            out = RasterOutput(*(None if a is None else cla.to_device(self.queue, a)
                                 for a in (out.rgb, out.alpha, out.depth)), out.saved)
            return out
        tiles = self.roi_tiles(on_host(roi), mesh.batch)
        batch, n = mesh.batch, mesh.batch * mesh.n_faces
        rows = self.device_arrays.face_rows(dev["faces"], batch, mesh.n_vertices)
        geom, ranges = self._device_face_setup(s, mesh, dev, rows)
        t = self._stage("setup", t, finish=True)
        bins = self.device_binning.run(ranges, batch, mesh.n_faces, tiles)
        self.pool.give([ranges])
        t = self._stage("binning", t, finish=True)
        buffers = self._device_face_buffers(mesh, dev, rows, geom, bins, n)
        state = self._state_buffers(batch) if grads else None
        t = self._stage("upload", t, finish=True)
        images = self._run_forward(s, mesh, buffers, state)
        outs = self._images_to_arrays(images, batch, state is not None)
        saved = (RasterContext(self, s, mesh, grads, bins, buffers, images, state, dev["faces"],
                               check_values=check_values) if grads else None)
        if saved is not None:
            self.pool.give_when_dead(saved, saved.device_buffers())
        else:
            self.pool.give(list(images.values()) + buffers.owned)   # an in-order queue: later users come after
        self._stage("forward", t, finish=True)
        return RasterOutput(*(outs.get(n) for n in ("rgb", "alpha", "depth")), saved)

    def _device_face_setup(self, s: RasterSettings, mesh: MeshInputs, dev: dict, rows: cla.Array) -> tuple:
        """(pooled records buffer, pooled (B*F, 4) int32 tile-range buffer) of the device inputs:
        kernel face_setup on the device's float64 vertices; without cl_khr_fp64 the host's
        set-up of the downloaded vertices (binning.face_setup, face_tiles), uploaded."""
        if self.setup is not None:
            vertices = self.device_arrays.contiguous(dev["vertices"], np.float64)
            return self.setup.run_device(vertices.data, rows.data, mesh.batch, mesh.n_faces, s)
        host = check_inputs(s, on_host(dev["vertices"]), on_host(dev["faces"]))
        geom, drawable = face_setup(host, s)
        ranges = face_tiles(geom, drawable, s, self.grid).astype(np.int32)
        bufs = [self.pool.take(a.nbytes) for a in (np.ascontiguousarray(geom, self.real), ranges)]
        for buf, a in zip(bufs, (np.ascontiguousarray(geom, self.real), ranges)):
            cl.enqueue_copy(self.queue, buf, a, is_blocking=True)
        return bufs[0], bufs[1]

    def _device_face_buffers(self, mesh: MeshInputs, dev: dict, rows: cla.Array, geom: cl.Buffer,
                             bins: DeviceBins, n: int) -> FaceBuffers:
        """FaceBuffers of the device inputs: per-face colour data gathered and cast on the device
        as MeshInputs.face_attributes() and the rasteriser's upload do on the host."""
        s, real, arrays = self.settings, self.real, self.device_arrays
        ndims = dict(colors=3, normals=3, uvs=3, face_textures=5, texture_image=4)
        dev = {n: _with_batch_axis(v, ndims[n]) if n in ndims else v for n, v in dev.items()}
        attr = tex_image = light = None
        if dev["colors"] is not None:
            lit = dev["normals"] is not None
            attr = cla.empty(self.queue, (n, vertex_attr_width(lit)), real)
            arrays.gather_corners(attr, dev["colors"], rows, mesh.n_vertices, attr.shape[1], 0)
            if lit:
                arrays.gather_corners(attr, dev["normals"], rows, mesh.n_vertices, attr.shape[1], CORNER_COLORS)
                light = arrays.contiguous(dev["light"], real)
        elif dev["face_textures"] is not None:
            attr = arrays.broadcast(dev["face_textures"], mesh.batch, real)
        elif dev["uvs"] is not None:
            attr = cla.empty(self.queue, (n, 6), real)
            arrays.gather_corners(attr, dev["uvs"], rows, mesh.n_vertices, 6, 0)
            tex_image = arrays.broadcast(dev["texture_image"], mesh.batch, real)
        dummy = self._dummy()
        data = lambda a: dummy if a is None else a.data
        return FaceBuffers(geom, data(attr), data(tex_image), data(light), bins.tile_start.data,
                           bins.tile_faces.data, bins.face_start.data, bins.face_slots.data, [geom],
                           [a for a in (attr, tex_image, light, rows) if a is not None])

    def _images_to_arrays(self, images: dict, batch: int, save_state: bool) -> dict:
        """{name: pyopencl array} (B, H, W[, 3]) of the forward's planes, by kernel planes_to_pixels."""
        s, g = self.settings, self.grid
        outs = {n: cla.empty(self.queue, (batch, s.height, s.width) + ((3,) if n == "rgb" else ()), self.real)
                for n in images}
        dummy, names = self._dummy(), ("rgb", "alpha", "depth")
        launch(self._kernel("planes_to_pixels", (), save_state), self.queue, (_round_up(g.wp // self.lanes), s.height, batch),
               GROUP, *self._layout_args(), *(images.get(n, dummy) for n in names),
               *(outs[n].data if n in outs else dummy for n in names))
        return outs

    def _check_device_cotangents(self, saved: RasterContext, given: dict) -> dict:
        """{name: C-contiguous pyopencl array of the kernel dtype, or None} of backward's
        cotangents when its forward took device arrays: checked as _check_device_inputs checks
        forward's arguments (the numpy path's errors)."""
        s, batch = saved.settings, saved.mesh.batch
        checked = {}
        for name, value in given.items():
            check_context(name, value, self.ctx)
            args = (_cot_shape(name, batch, s), name[len("grad_"):] in s.outputs)
            try:
                check_cotangent(name, standin(value), *args, values=False)
            except (ValueError, TypeError):
                check_cotangent(name, on_host(value), *args)
                raise
            if value is not None and not is_device_array(value):
                value = cla.to_device(self.queue, np.ascontiguousarray(value))
            checked[name] = value
        counts = ({n: self.value_checks.count_bad_floats(v, False) for n, v in checked.items() if v is not None}
                  if saved.check_values else {})
        bad = read_together(list(counts.values())) if counts else []
        for name, count in zip(counts, bad):
            if count.any():
                check_cotangent(name, on_host(checked[name]), _cot_shape(name, batch, s), True)
        return {n: None if v is None else self.device_arrays.contiguous(v, self.real) for n, v in checked.items()}

    def call_settings(self, **run) -> RasterSettings:
        """The settings of one forward: these settings with the RUN_FIELDS values given in `run`
        (None: unchanged), validated as RasterSettings validates them (ValueError naming the
        field). Each distinct set is made once (up to RUN_SETTINGS_KEPT of them)."""
        unknown = set(run) - set(RUN_FIELDS)
        if unknown:
            raise TypeError(f"call_settings takes only {RUN_FIELDS}, got {sorted(unknown)}")
        key = tuple(depth_bound(name, run[name]) if name in ("near", "far") and run.get(name) is not None
                    else run.get(name) for name in RUN_FIELDS)
        made = self._run_settings.get(key)
        if made is None:
            changes = {name: value for name, value in zip(RUN_FIELDS, key) if value is not None}
            made = self.settings.replace(**changes) if changes else self.settings
            if len(self._run_settings) >= RUN_SETTINGS_KEPT:
                self._run_settings.clear()
            self._run_settings[key] = made
        return made

    def backward(self, output: RasterOutput, grad_rgb=None, grad_alpha=None, grad_depth=None) -> dict:
        """Gradients of a scalar loss given its cotangents dL/d(rgb, alpha, depth).

        Each cotangent has the shape of the matching output (None = zero). Returns a dict with
        the names given as `grads` to forward: "vertices" (shape of the vertices given, float64)
        and "colors" (shape of the colour input given: colors, face_textures or texture_image).
        output: what this rasteriser's forward returned, with grads (ValueError for another's:
        its buffers, sizes, dtype and settings are that rasteriser's).
        """
        saved = _own_context(self, output)
        s, mesh = saved.settings, saved.mesh
        t = time.perf_counter()
        given = dict(grad_rgb=grad_rgb, grad_alpha=grad_alpha, grad_depth=grad_depth)
        if saved.device_faces is not None:
            cot = self._check_device_cotangents(saved, given)
        else:
            cot = {name: check_cotangent(name, on_host(g), _cot_shape(name, mesh.batch, s),
                                         name[len("grad_"):] in s.outputs) for name, g in given.items()}
        t = self._stage("cotangent_checks", t, finish=saved.device_faces is not None)
        slots = self._run_backward(saved, cot, t)
        t = time.perf_counter()
        if saved.device_faces is None:
            grads = self._gather_grads(saved, slots)
        elif saved.numpy_io:
            grads = {k: v.get() for k, v in self._gather_grads_device(saved, slots).items()}
        else:
            grads = self._gather_grads_device(saved, slots)
        self.pool.give(b for b in slots.values() if isinstance(b, cl.Buffer))
        self._stage("reductions", t, finish=saved.device_faces is not None)
        return grads

    # ---- kernels ---------------------------------------------------------------------------
    def _kernel(self, name: str, grads: tuple, save_state: bool) -> cl.Kernel:
        """Kernel `name` of the variant for the settings, grads and save_state (kept per rasteriser:
        building the flags for the program cache's lookup cost more than a launch on small images)."""
        key = (name, grads, save_state)
        if key not in self._kernels:
            self._kernels[key] = self._build_kernel(name, grads, save_state)
        return self._kernels[key]

    def _build_kernel(self, name: str, grads: tuple, save_state: bool) -> cl.Kernel:
        s = self.settings
        defines = dict(
            SR_DOUBLE=s.dtype == "float64", SR_LANES=self.lanes,
            SR_OUT_RGB="rgb" in s.outputs, SR_OUT_ALPHA="alpha" in s.outputs,
            SR_OUT_DEPTH="depth" in s.outputs,
            SR_METRIC_BARY=s.metric == "barycentric",
            SR_COLOR_HARD=s.color_agg == "hard",
            SR_ALPHA_AGG=("occupancy", "sum", "hard").index(s.alpha_agg),
            SR_TEXTURE=("vertex", "face", "uv").index(s.texture),
            SR_PERSPECTIVE=s.perspective_correct,
            SR_LIGHTING=("none", "lambert", "sh").index(s.lighting),
            SR_SAVE_STATE=save_state, SR_ROWS=FWD_ROWS,
            SR_INT64_ATOMICS=has_int64_atomics(self.device),
            SR_GRAD_POS="vertices" in grads,
            SR_GRAD_COLOR="colors" in grads and "rgb" in s.outputs)
        return build_kernel(self.ctx, "soft_raster.cl", name, defines, s.fast_math)

    def _geometry_args(self, s: RasterSettings, mesh: MeshInputs, bufs: FaceBuffers) -> list:
        """The GEOMETRY_ARGS shared by both kernels (kernels/soft_raster.cl) for the call's settings s."""
        real = self.real.type
        g = self.grid
        x_cut = -np.finfo(self.real).max if s.dist_eps == 0 else math.log(s.dist_eps / (1 - s.dist_eps))
        i32 = np.int32
        return [i32(s.width), i32(s.height), i32(g.wp), i32(g.hp), i32(g.ntx), i32(g.nty),
                real(2.0 / min(s.width, s.height)), real(1.0 / s.sigma), real(x_cut),
                real(1.0 / s.gamma), real(s.eps),
                i32(mesh.tex_res), i32(mesh.tex_shape[0]), i32(mesh.tex_shape[1]),
                bufs.geom, bufs.attr, bufs.tex_image, bufs.light, bufs.tile_start, bufs.tile_faces,
                self._depth_range_buffer(s, mesh.batch)]

    def _depth_range_buffer(self, s: RasterSettings, batch: int) -> cl.Buffer:
        """A device copy of each view's (near, far), (batch, 2) in the kernels' dtype, kept for
        the last RUN_SETTINGS_KEPT settings and batch sizes (a fit draws with a few)."""
        key = (s.near, s.far, batch)
        buf = self._depth_ranges.get(key)
        if buf is None:
            ranges = np.ascontiguousarray(s.depth_ranges(batch), self.real)
            buf = cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=ranges)
            if len(self._depth_ranges) >= RUN_SETTINGS_KEPT:
                self._depth_ranges.clear()
            self._depth_ranges[key] = buf
        return buf

    def _run_forward(self, s: RasterSettings, mesh: MeshInputs, bufs: FaceBuffers,
                     state: PixelState | None) -> dict:
        """Run the forward kernel at the call's settings s (writing `state` too, if given):
        {output name: (planes, B, Hp, Wp)}."""
        real = self.real
        g = self.grid
        npix = mesh.batch * g.hp * g.wp
        planes = dict(rgb=3 if "rgb" in s.outputs else 0, alpha=int("alpha" in s.outputs),
                      depth=int("depth" in s.outputs))
        out = {n: self.pool.take(npix * k * real.itemsize) for n, k in planes.items() if k}
        dummy = self._dummy()
        if self.layout == "gpu":
            knl = self._kernel("soft_raster_fwd_tile", (), state is not None)
            shape = (g.wp, g.hp, mesh.batch), (GPU_TILE_W, TILE_H, 1)
        else:
            knl = self._kernel("soft_raster_fwd", (), state is not None)
            shape = (_round_up(g.ntx), g.hp // FWD_ROWS, mesh.batch), GROUP
        launch(knl, self.queue, *shape, *self._geometry_args(s, mesh, bufs),
               *(real.type(c) for c in s.background),
               *(out.get(n, dummy) for n in ("rgb", "alpha", "depth")), *self._state_args(state))
        return out

    def _state_buffers(self, batch: int) -> PixelState:
        """Per-pixel state the backward reads: softmax log-normaliser or hard face ids, and the
        occupancy sums (two planes) or the sum of D."""
        s, g, itemsize = self.settings, self.grid, self.real.itemsize
        npix = batch * g.hp * g.wp
        new = self.pool.take
        soft_color = {"rgb", "depth"} & set(s.outputs) and s.color_agg == "softmax"
        alpha_planes = ("alpha" in s.outputs) * {"occupancy": 2, "sum": 1, "hard": 0}[s.alpha_agg]
        return PixelState(color=new(npix * itemsize) if soft_color else None,
                          alpha=new(npix * itemsize * alpha_planes) if alpha_planes else None,
                          ids=new(npix * 4 * 2))

    def _state_args(self, state: PixelState | None) -> list:
        """The color, alpha and id state kernel arguments (the dummy buffer where absent)."""
        bufs = (state.color, state.alpha, state.ids) if state is not None else (None,) * 3
        return [b if b is not None else self._dummy() for b in bufs]

    def _run_backward(self, saved: RasterContext, cot: dict, t: float) -> dict:
        """Run the backward kernel: {"pos", "attr", "light": pooled device buffers of the
        per-(tile, face) slot sums (the caller gives them back), "tex": uv texel sums (host
        staging that the next backward overwrites), None where not computed; "scale": the uv
        fixed-point scale}. t: perf_counter at the start of backward (stage timing)."""
        s, real, mesh, bins = saved.settings, self.real, saved.mesh, saved.bins
        g = self.grid
        # the device bins' tile lists are not cut at the region of interest: n_entries bounds them
        n_list = bins.n_entries if isinstance(bins, DeviceBins) else len(bins.tile_faces)
        shapes, scale = self._slot_shapes(mesh, saved.grads, max(n_list, 1), cot["grad_rgb"])
        kernel_grads = tuple(x for x in saved.grads if x != "colors" or {"attr", "tex"} & set(shapes))
        if not kernel_grads:    # colour gradients only, and no rgb cotangent: all zero
            return dict(pos=None, attr=None, light=None, tex=None, scale=scale)
        # an output without a cotangent contributes zero; the kernel variant still reads its (zero) plane
        self._stage("backward_prep", t)
        cot_bufs, sources = self._cotangent_planes(saved, cot, kernel_grads)     # times cotangent_upload
        t = time.perf_counter()
        g_dot = cot_bufs.pop("g_dot")
        nbytes = {k: math.prod(shape) * np.dtype(dtype).itemsize for k, (shape, dtype) in shapes.items()}
        out_bufs = {k: self.pool.take(n) for k, n in nbytes.items()}
        for k, buf in out_bufs.items():
            if k == "tex" or s.texture == "face":             # texels are added into
                # zeros copied from the host: Oclgrind does not count clEnqueueFillBuffer as
                # initialising memory (and the copy is cheap: calloc's pages are not touched)
                self._transfers.append(cl.enqueue_copy(self.queue, buf, np.zeros(nbytes[k], np.uint8),
                                                       is_blocking=False))
        if self.layout == "gpu":
            knl = self._kernel("soft_raster_bwd_tile", kernel_grads, True)
            shape = (g.ntx * GPU_BWD_GROUP, g.nty, mesh.batch), (GPU_BWD_GROUP, 1, 1)
        else:
            knl = self._kernel("soft_raster_bwd", kernel_grads, True)
            shape = (_round_up(g.ntx), g.nty, mesh.batch), GROUP
        t = self._stage("backward_prep", t, finish=True)
        dummy = self._dummy()
        launch(knl, self.queue, *shape, *self._geometry_args(s, mesh, saved.buffers),
               *(cot_bufs.get(n, dummy) for n in ("grad_rgb", "grad_alpha", "grad_depth")),
               dummy if g_dot is None else g_dot, *self._state_args(saved.state), real.type(scale),
               *(out_bufs.get(k, dummy) for k in ("pos", "attr", "light", "tex")))
        tex = None
        if "tex" in shapes and saved.device_faces is not None:
            tex = self.device_arrays.fixed_to_float(cla.Array(self.queue, shapes["tex"][0], np.int64,
                                                              data=out_bufs["tex"]), scale)
        elif "tex" in shapes:
            tex = self.scratch.get("slot_tex", *shapes["tex"])
            self._transfers.append(cl.enqueue_copy(self.queue, tex, out_bufs["tex"], is_blocking=False))
            self._sync()        # the texel sums are read on the host next; else _gather_grads waits
        # given back before the kernel ends: an in-order queue runs any later use after it
        self.pool.give([*cot_bufs.values(), *sources, *([g_dot] if g_dot is not None else []),
                        *([out_bufs.pop("tex")] if tex is not None else [])])
        self._stage("backward", t, finish=True)
        return {**dict(pos=None, attr=None, light=None), **out_bufs, "tex": tex, "scale": scale}

    def _slot_shapes(self, mesh: MeshInputs, grads: tuple, n_entries: int, grad_rgb) -> tuple[dict, float]:
        """{name: (shape, dtype)} of what the backward kernel writes, and the uv fixed-point scale:
        "pos" (n_entries, 9) and "attr" (n_entries, K) colour and normal slots, "light"
        (n_entries, LIGHT_PARAMS) slots, in tile-list order; "tex" (B, Ht, Wt, 3) int64 uv
        texel sums."""
        s, real = self.settings, self.real
        widths = self._slot_widths(mesh)
        shapes = {"pos": ((n_entries, widths["pos"]), real)} if "vertices" in grads else {}
        if "colors" not in grads or "rgb" not in s.outputs or grad_rgb is None:
            return shapes, 1.0
        if s.texture == "uv":
            shapes["tex"] = ((mesh.batch, *mesh.tex_shape, 3), np.int64)
            return shapes, _fixed_point_scale(self._abs_bound(grad_rgb), real)
        shapes["attr"] = ((n_entries, widths["attr"]), real)
        if s.lighting != "none":
            shapes["light"] = ((n_entries, widths["light"]), real)
        return shapes, 1.0

    def _abs_bound(self, grad_rgb) -> float:
        """max over the batch of sum |grad_rgb[b]| (numpy, or device reductions for a pyopencl
        array: their sums may round differently in the last bits)."""
        if is_device_array(grad_rgb):
            return max(float(x.get()) for x in self.device_arrays.abs_sums(grad_rgb)) if grad_rgb.size else 0.0
        return float(np.abs(grad_rgb).sum(axis=(1, 2, 3)).max()) if grad_rgb.size else 0.0

    def _gather_grads_device(self, saved: RasterContext, slots: dict) -> dict:
        """_gather_grads for a device-resident forward: the same sums, left on the device as
        float64 pyopencl arrays shaped like the inputs (_shape_grads' shapes and batch sums)."""
        mesh, grads, arrays, q = saved.mesh, saved.grads, self.device_arrays, self.queue
        bins = saved.buffers.face_start, saved.buffers.face_slots
        n_faces = mesh.batch * mesh.n_faces
        sums = {k: self.sums.face_sums(slots[k], width, *bins, n_faces)
                for k, width in self._slot_widths(mesh).items() if slots.get(k) is not None}
        faces = []

        def on_vertices(face_sums, width: int, offset: int) -> cla.Array:
            shape = (mesh.batch, mesh.n_vertices, 3)
            if face_sums is None:
                return cla.zeros(q, shape, np.float64)
            if not faces:       # the corner index is built on the host (reduce.corner_index)
                faces.append(np.broadcast_to(saved.device_faces.get(), (mesh.batch, mesh.n_faces, 3)))
            buf = self.sums.vertex_sums(face_sums, width, offset, faces[0], mesh.n_vertices)
            out = cla.empty(q, shape, self.sums.dtype)
            cl.enqueue_copy(q, out.data, buf, byte_count=out.nbytes)
            self.pool.give([buf])
            return arrays.contiguous(out, np.float64)

        def per_face(name: str, width: int) -> cla.Array:
            if name not in sums:
                return cla.zeros(q, (n_faces, width), np.float64)
            out = cla.empty(q, (n_faces, width), self.sums.dtype)
            cl.enqueue_copy(q, out.data, sums[name], byte_count=out.nbytes)
            return arrays.contiguous(out, np.float64)

        out = {}
        if "vertices" in grads:
            v = on_vertices(sums.get("pos"), 9, 0)
            out["vertices"] = v if mesh.vertices_batched else v.reshape(mesh.n_vertices, 3)
        if "colors" in grads:
            s = self.settings
            if s.texture == "uv":
                tex = slots["tex"]
                colors = cla.zeros(q, (mesh.batch, *mesh.tex_shape, 3), np.float64) if tex is None else tex
            elif s.texture == "face":
                r = mesh.tex_res
                colors = per_face("attr", r * r * 3).reshape(mesh.batch, mesh.n_faces, r, r, 3)
            else:
                width = vertex_attr_width(s.lighting != "none")
                colors = on_vertices(sums.get("attr"), width, 0)
                if s.lighting != "none":
                    out["normals"] = on_vertices(sums.get("attr"), width, CORNER_COLORS)
                    out["light"] = arrays.sum_rows(per_face("light", LIGHT_PARAMS) if "light" in sums
                                                   else cla.zeros(q, (1, LIGHT_PARAMS), np.float64))
            if not mesh.colors_batched:
                colors = arrays.sum_rows(colors)
            elif mesh.colors_batch == 1:
                colors = arrays.sum_rows(colors, keepdims=True)
            out["colors"] = colors
        self.pool.give(sums.values())       # an in-order queue: later users come after
        return out

    def _gather_grads(self, saved: RasterContext, slots: dict) -> dict:
        """Sum the (tile, face) slots per face in a fixed order, then faces onto vertices (on the
        device: softras_cl.raster.reduce); every transfer is enqueued, then waited for once."""
        mesh, grads = saved.mesh, saved.grads
        bins = saved.buffers.face_start, saved.buffers.face_slots
        sums = {k: self.sums.face_sums(slots[k], width, *bins, mesh.batch * mesh.n_faces)
                for k, width in self._slot_widths(mesh).items() if slots.get(k) is not None}
        hosts = {}
        if "vertices" in grads:
            hosts["vertices"] = self._vertex_sums(mesh, sums.get("pos"), 9, 0)
        if "colors" in grads:
            hosts.update(self._color_sums(mesh, sums, slots))
        self.sums.wait()
        self.pool.give(sums.values())
        return self._shape_grads(mesh, hosts)

    def _slot_widths(self, mesh: MeshInputs) -> dict:
        """Reals per slot row of "pos", "attr" and "light" (_slot_shapes)."""
        s = self.settings
        attr = vertex_attr_width(s.lighting != "none") if s.texture == "vertex" else mesh.tex_res ** 2 * 3
        return dict(pos=9, attr=attr, light=LIGHT_PARAMS)

    def _vertex_sums(self, mesh: MeshInputs, face_sums: cl.Buffer | None, width: int, offset: int) -> np.ndarray:
        """(B, V, 3) host array (valid after self.sums.wait()): corner k of face g holds
        face_sums[g, offset + 3k : offset + 3k + 3] of the (B*F, width) device per-face sums,
        summed onto the vertices; zeros when face_sums is None."""
        shape = (mesh.batch, mesh.n_vertices, 3)
        if face_sums is None:
            return np.zeros(shape)
        buf = self.sums.vertex_sums(face_sums, width, offset, mesh.faces, mesh.n_vertices)
        self.pool.give([buf])       # an in-order queue reads it before any later reuse
        return self.sums.download(buf, shape)

    def _color_sums(self, mesh: MeshInputs, sums: dict, slots: dict) -> dict:
        """Host arrays (valid after self.sums.wait()) of "colors": uv texel sums (B, Ht, Wt, 3),
        face texel sums (B*F, R*R*3) or vertex sums (B, V, 3); when lit also "normals" (B, V, 3)
        and "light" (B*F or 1, LIGHT_PARAMS) per-face sums."""
        s = self.settings
        if s.texture == "uv":
            tex = slots["tex"]
            return dict(colors=np.zeros((mesh.batch, *mesh.tex_shape, 3)) if tex is None
                        else tex.astype(np.float64) / slots["scale"])
        n_faces = mesh.batch * mesh.n_faces
        if s.texture == "face":
            width = mesh.tex_res ** 2 * 3
            return dict(colors=np.zeros((n_faces, width)) if "attr" not in sums
                        else self.sums.download(sums["attr"], (n_faces, width)))
        width = vertex_attr_width(s.lighting != "none")
        out = dict(colors=self._vertex_sums(mesh, sums.get("attr"), width, 0))
        if s.lighting != "none":
            out["normals"] = self._vertex_sums(mesh, sums.get("attr"), width, CORNER_COLORS)
            light = sums.get("light")
            out["light"] = (np.zeros((1, LIGHT_PARAMS)) if light is None
                            else self.sums.download(light, (n_faces, LIGHT_PARAMS)))
        return out

    def _shape_grads(self, mesh: MeshInputs, hosts: dict) -> dict:
        """The downloaded sums (_gather_grads) as float64 gradients shaped like the inputs."""
        out = {k: np.asarray(v, np.float64) for k, v in hosts.items()}
        if "vertices" in out:
            out["vertices"] = mesh.unbatch_vertices(out["vertices"])
        if "colors" in out:
            colors = out["colors"]
            if self.settings.texture == "face":
                colors = colors.reshape(mesh.batch, mesh.n_faces, mesh.tex_res, mesh.tex_res, 3)
            out["colors"] = mesh.unbatch_colors(colors)
        if "light" in out:
            out["light"] = out["light"].sum(0)     # the per-face sums added in face order
        return out

    # ---- buffers ---------------------------------------------------------------------------
    def _face_setup(self, mesh: MeshInputs, s: RasterSettings) -> tuple:
        """(records, tile ranges) of every face at the call's settings s: on the device where it has cl_khr_fp64 and there
        are at least device_setup_faces (softras_cl.raster.device_setup: a pooled buffer), else on
        the host (binning.face_setup: a (B*F, FACE_STRIDE) float64 array); the ranges are
        (B*F, 4) ints (binning.face_tiles). Both give the same bits."""
        if self.setup is not None and mesh.n_faces and mesh.batch * mesh.n_faces >= self.device_setup_faces:
            return self.setup.run(mesh, s)
        geom, drawable = face_setup(mesh, s)
        return geom, face_tiles(geom, drawable, s, self.grid)

    def _upload(self, mesh: MeshInputs, geom, bins: Bins, grads: bool) -> FaceBuffers:
        """Device copies of the face records (unless `geom` is already a device buffer), colour
        inputs and bins (face_start and face_slots only with `grads`), in the kernel dtype, by
        one transfer (_upload_parts)."""
        real, i32 = self.real, np.int32
        parts = dict(attr=(mesh.face_attributes(), real), tex_image=(mesh.texture_image_array(), real),
                     light=(mesh.light if mesh.light is not None else np.zeros(0), real),
                     tile_start=(bins.tile_start, i32), tile_faces=(bins.tile_faces, i32),
                     face_start=(bins.face_start if grads else np.zeros(0), i32),
                     face_slots=(bins.face_slots if grads else np.zeros(0), i32))
        owned = [geom] if isinstance(geom, cl.Buffer) else []     # the device set-up's pooled records
        if not owned:
            parts["geom"] = (geom, real)
        uploaded, bufs = self._upload_parts("upload", parts)
        return FaceBuffers(**{"geom": geom, **bufs, "owned": owned + uploaded})

    def _upload_parts(self, name: str, parts: dict) -> tuple[list, dict]:
        """Copy arrays to the device in few transfers (on PoCL each transfer enqueued costs tens
        of microseconds, under load much more): parts {key: (array, dtype)}. Arrays of at least
        OWN_TRANSFER bytes already in their dtype and contiguous get a buffer and a transfer each;
        the others are converted into host staging `name` (overwritten by the next call: the
        transfer must be waited for first, as _sync does), each at an offset a sub-buffer can
        start at, and go by one transfer. Returns (the pooled buffers, {key: its buffer or
        sub-buffer, or the dummy buffer for an empty array})."""
        bufs, owned, layout, end = {}, [], {}, 0
        align = self.device.mem_base_addr_align // 8
        for key, (array, dtype) in parts.items():
            nbytes = array.size * np.dtype(dtype).itemsize
            if not nbytes:
                bufs[key] = self._dummy()
            elif nbytes >= OWN_TRANSFER and array.dtype == dtype and array.flags.c_contiguous:
                bufs[key] = self.pool.take(nbytes)
                owned.append(bufs[key])
                self._transfers.append(cl.enqueue_copy(self.queue, bufs[key], array, is_blocking=False))
            else:
                layout[key] = (end, nbytes)
                end += -(-nbytes // align) * align
        if layout:
            staging = self.scratch.get(name, (end,), np.uint8)
            for key, (start, nbytes) in layout.items():
                array, dtype = parts[key]
                np.copyto(staging[start:start + nbytes].view(dtype).reshape(array.shape), array, casting="unsafe")
            packed = self.pool.take(end)
            owned.append(packed)
            self._transfers.append(cl.enqueue_copy(self.queue, packed, staging, is_blocking=False))
            bufs.update({key: packed.get_sub_region(*where) for key, where in layout.items()})
        return owned, bufs

    def _dummy(self) -> cl.Buffer:
        """A small buffer standing in for arguments the kernel variant never reads."""
        if not hasattr(self, "_dummy_buf"):
            self._dummy_buf = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, 64)
        return self._dummy_buf

    def _download(self, images: dict, batch: int, save_state: bool) -> tuple[dict, dict]:
        """Start reading the forward's images ({name: (planes, B, Hp, Wp) device buffer}) into
        fresh (B, H, W) arrays, (B, H, W, 3) for rgb, through pooled buffers that kernel
        planes_to_pixels fills. Returns ({name: array}, {name: pooled buffer}); the arrays are
        valid and the buffers free after _sync() (one wait for all the downloads)."""
        s, g = self.settings, self.grid
        hosts = {n: np.empty((batch, s.height, s.width) + ((3,) if n == "rgb" else ()), self.real) for n in images}
        packed = {n: self.pool.take(a.nbytes) for n, a in hosts.items()}
        dummy, names = self._dummy(), ("rgb", "alpha", "depth")
        launch(self._kernel("planes_to_pixels", (), save_state), self.queue, (_round_up(g.wp // self.lanes), s.height, batch),
               GROUP, *self._layout_args(), *(images.get(n, dummy) for n in names), *(packed.get(n, dummy) for n in names))
        for n, host in hosts.items():
            self._transfers.append(cl.enqueue_copy(self.queue, host, packed[n], is_blocking=False))
        return hosts, packed

    def _layout_args(self) -> list:
        """W, H, Wp, Hp and kernel vectors per padded row: the first arguments of kernels
        planes_to_pixels and soft_raster_cotangents."""
        s, g, i32 = self.settings, self.grid, np.int32
        return [i32(s.width), i32(s.height), i32(g.wp), i32(g.hp), i32(g.wp // self.lanes)]

    def _sync(self) -> None:
        """Wait for everything queued, then let go of the finished transfers."""
        self.queue.finish()
        self._transfers.clear()

    def _cotangent_planes(self, saved: RasterContext, cot: dict, kernel_grads: tuple) -> tuple[dict, list]:
        """Kernel soft_raster_cotangents: the cotangents (B, H, W[, 3]; None = zeros) of every
        output as pooled device buffers of zero-padded (planes, B, Hp, Wp) planes in the kernel
        dtype, and for softmax colours the g.out image (B, Hp, Wp). Returns ({"grad_rgb", ...:
        planes, "g_dot": image (None without softmax colours)}, pooled buffers to give back after
        _sync(): the planes' sources, device copies of the cotangents cast to the kernel dtype)."""
        s, g, batch = self.settings, self.grid, saved.mesh.batch
        npix, itemsize = batch * g.hp * g.wp, self.real.itemsize
        names = [n for n in ("grad_rgb", "grad_alpha", "grad_depth") if n[len("grad_"):] in s.outputs]
        planes = {n: self.pool.take(npix * itemsize * (3 if n == "grad_rgb" else 1)) for n in names}
        soft = s.color_agg == "softmax" and {"rgb", "depth"} & set(s.outputs)
        planes["g_dot"] = self.pool.take(npix * itemsize) if soft else None
        t = time.perf_counter()
        if saved.device_faces is not None:      # checked device arrays of the kernel dtype
            uploaded, sources = [], {n: cot[n].data for n in names if cot[n] is not None}
        else:
            uploaded, sources = self._upload_parts("cotangents", {n: (cot[n], self.real) for n in names
                                                                  if cot[n] is not None})
        self._stage("cotangent_upload", t, finish=True)
        dummy, all_names = self._dummy(), ("grad_rgb", "grad_alpha", "grad_depth")
        launch(self._kernel("soft_raster_cotangents", kernel_grads, True), self.queue,
               (_round_up(g.wp // self.lanes), g.hp, batch), GROUP, *self._layout_args(),
               *(np.int32(n in sources) for n in all_names), *(sources.get(n, dummy) for n in all_names),
               saved.images.get("rgb", dummy), saved.images.get("depth", dummy),
               *(planes.get(n) or dummy for n in (*all_names, "g_dot")))
        return planes, uploaded


def _own_context(raster: SoftRasterizer, output) -> RasterContext:
    """output.saved, checked to be what `raster`'s own forward kept (ValueError otherwise: the
    context's buffers, sizes, dtype and settings belong to the rasteriser that made it)."""
    if not isinstance(output, RasterOutput):
        raise TypeError(f"output must be the RasterOutput of this rasteriser's forward, got {type(output).__name__}")
    saved = output.saved
    if saved is None:
        raise ValueError("output: forward() was called without grads=...; nothing to differentiate")
    if saved.rasterizer is not raster:
        made, mine = saved.settings, raster.settings
        raise ValueError(f"output was made by another SoftRasterizer (image_size={made.image_size}, "
                         f"dtype={made.dtype!r}, sigma={made.sigma:g}, gamma={made.gamma:g}) than this one "
                         f"(image_size={mine.image_size}, dtype={mine.dtype!r}): call backward on the "
                         "rasteriser whose forward made it")
    return saved


def _check_local_memory(device: cl.Device, real_size: int) -> None:
    """ValueError when `device` has less local memory than the GPU layout's kernels declare."""
    # what kernels/soft_raster.cl declares: the forward GPU_CHUNK face records and their indices,
    # the backward a PixelIn (10 reals and 2 masks as wide) and a flag per tile pixel
    need = max(GPU_CHUNK * (FACE_STRIDE * real_size + 4), GPU_TILE_W * TILE_H * (12 * real_size + 4))
    if device.local_mem_size < need:
        raise ValueError(f"layout='gpu' needs {need} bytes of local memory per work-group; device "
                         f"{device.name!r} has {device.local_mem_size}: use layout='cpu'")


def _with_batch_axis(value, ndim: int):
    """A pyopencl array of `ndim` - 1 dimensions (unbatched) with a leading axis of 1; others as
    they are."""
    return value.reshape((1,) + value.shape) if value is not None and value.ndim == ndim - 1 else value


def _round_up(n: int) -> int:
    """n rounded up to a whole number of work-groups along x (the kernels skip the extra items)."""
    return -(-n // GROUP[0]) * GROUP[0]


def _fixed_point_scale(bound: float, real: np.dtype) -> float:
    """Power of two that maps uv-texel gradient sums into int64 without overflow.

    Every texel's sum is bounded by `bound`, the largest sum |dL/drgb| over an image
    (SoftRasterizer._abs_bound; weights and bilinear taps sum to at most 1), so that bound times
    the scale stays below 2^62.
    """
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
