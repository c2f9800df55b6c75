"""What a rasterisation needs in memory, checked before anything is allocated.

`memory_estimate(settings, batch, n_faces, ...)` adds up the buffers one forward (and, when
gradients are asked for, the backward after it) allocates, from the image size, batch, face
count, outputs, gradients and dtype; `check_memory(estimate, device)` compares it with the
OpenCL device's limits (CL_DEVICE_MAX_MEM_ALLOC_SIZE for the largest buffer,
CL_DEVICE_GLOBAL_MEM_SIZE for all of them) and the machine's available memory, and raises
softras_cl.errors.ResourceError saying what the request needs and what there is. A CPU device
(PoCL) allocates its buffers in the same RAM as the host arrays, so there both count against
the machine's available memory.

Accuracy: an upper bound within +3 % to +12 % of the measured peak (getrusage max RSS above
the imported baseline; PoCL 3.1 CPU device, 320 faces, 1024^2 to 4096^2 pixels): forward of
rgb + alpha in float32 36.2 B/px estimated, 34.4 to 35.1 measured; with depth 44.2 against 42.4
to 43.1; forward + backward with vertex and colour gradients 126.5 against 112.8 to 115.0
(float32) and 245.5 against 236.3 to 239.4 (float64). The per-pixel terms dominate from about
512^2. The number of (tile, face) bin entries is not known before binning; it is estimated as
one per tile plus four per face, which is what meshes spread over the image give (a few faces
covering the whole image at once give more, but then the per-pixel terms dominate anyway).
Requests under SMALL bytes skip the machine-memory look-up, so fitting loops pay nothing for the check.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

from softras_cl.cl.layout import FACE_STRIDE, LANES, LIGHT_PARAMS, UV_ATTRS, vertex_attr_width
from softras_cl.errors import ResourceError
from softras_cl.raster.settings import RasterSettings

GB = 1024 ** 3
SMALL = 256 * 1024 ** 2      # below this total, only the device limits are checked
BIN_BYTES = 40               # host bytes per bin entry while binning (face, local, tile, order, ...)
SLACK = 4                    # bytes per padded pixel measured beyond the buffers above (PoCL's
                             # bookkeeping of the kernel's work-items, allocator rounding)


@dataclass(frozen=True)
class MemoryEstimate:
    """Bytes one request needs (ints).

    device: every OpenCL buffer the request allocates (forward and backward); largest_buffer:
    the largest single buffer; host: the most numpy memory alive at once (downloads, crops,
    bins, backward planes); shared: the most memory alive at once when device buffers live in
    the host's RAM (CPU devices); pixels: B x H x W; what: the request in words (for messages).
    """
    device: int
    largest_buffer: int
    host: int
    shared: int
    pixels: int
    what: str

    def plus_host(self, nbytes: int, what: str | None = None) -> "MemoryEstimate":
        """A copy with `nbytes` more host memory alive at the peak (e.g. what a command does with
        the images it gets back), and `what` renamed if given."""
        n = int(nbytes)
        return MemoryEstimate(self.device, self.largest_buffer, self.host + n, self.shared + n,
                              self.pixels, what or self.what)


def memory_estimate(settings: RasterSettings, batch: int = 1, n_faces: int = 0, grads=(),
                    tex_res: int = 0, tex_shape: tuple = (0, 0), n_entries: int | None = None
                    ) -> MemoryEstimate:
    """Memory of SoftRasterizer.forward (and of its backward when `grads` is non-empty).

    settings: the RasterSettings (image size, outputs, aggregations, dtype); batch B >= 1;
    n_faces F per mesh; grads: the gradient names given to forward; tex_res: R of face
    textures (B, F, R, R, 3); tex_shape: (Ht, Wt) of a uv texture image; n_entries: (tile, face)
    bin entries if known (default: one per tile plus four per face).
    """
    from softras_cl.raster.binning import tile_grid

    s, grads = settings, tuple(grads)
    real = 8 if s.dtype == "float64" else 4
    g = tile_grid(s, max(LANES[s.dtype]))        # the widest padding any device uses
    npix = batch * g.hp * g.wp                       # padded planes
    image = batch * s.height * s.width
    n_tiles = batch * g.ntx * g.nty
    faces = batch * n_faces
    entries = n_tiles + 4 * faces if n_entries is None else int(n_entries)
    planes = 3 * ("rgb" in s.outputs) + ("alpha" in s.outputs) + ("depth" in s.outputs)
    if s.texture == "vertex":
        attr = vertex_attr_width(s.lighting != "none")
    else:
        attr = 3 * tex_res ** 2 if s.texture == "face" else UV_ATTRS
    tex_image = batch * tex_shape[0] * tex_shape[1] * 3

    # forward: the output planes on the device, then their download (the device buffers are
    # released before the crop), then the cropped copies returned to the caller
    out_dev = [npix * real * (3 if name == "rgb" else 1) for name in s.outputs]
    planes_bytes, crops = sum(out_dev), planes * real * image
    face_dev = [faces * FACE_STRIDE * real, faces * attr * real, tex_image * real,
                4 * (n_tiles + 1), 4 * entries, 4 * entries]
    setup = entries * BIN_BYTES + faces * (2 * FACE_STRIDE * 8 + attr * 8)   # host, while binning
    state, cot_dev, slots, sums = [0], [0], 0, 0
    if grads:
        # per-pixel state kept for the backward (softras_cl.raster.rasterizer.PixelState)
        soft_color = bool({"rgb", "depth"} & set(s.outputs)) and s.color_agg == "softmax"
        alpha_planes = ("alpha" in s.outputs) * {"occupancy": 2, "sum": 1, "hard": 0}[s.alpha_agg]
        state = [npix * real * soft_color, npix * real * alpha_planes, npix * 8]
        # backward: padded cotangent planes and the softmax g.out image (host and device), and
        # the per-(tile, face) gradient slots (host and device)
        cot_dev = out_dev + [npix * real * soft_color]
        slots = entries * real * (9 * ("vertices" in grads)
                                  + ("colors" in grads) * (attr + LIGHT_PARAMS * (s.lighting != "none")))
        slots += ("colors" in grads) * tex_image * 8 * (s.texture == "uv")
        # the slots' per-face sums on the device, in double (softras_cl.raster.reduce); the host
        # still counts the slots, which it no longer downloads: an upper bound
        sums = 8 * faces * (9 * ("vertices" in grads) + ("colors" in grads) * (s.texture != "uv")
                            * (attr + LIGHT_PARAMS * (s.lighting != "none")))
    kept_dev = sum(face_dev) + sum(state) + SLACK * npix
    device = kept_dev + planes_bytes + sum(cot_dev) + slots + sums
    # host arrays at each step (the forward's download stays in the context when grads are kept)
    host_steps = [setup, planes_bytes, planes_bytes + crops]
    ram_steps = [kept_dev + setup, kept_dev + 2 * planes_bytes, kept_dev + planes_bytes + crops]
    if grads:
        # the caller's cotangents (shaped like the crops), their padded copies, and the rgb
        # product image summed into g.out
        bwd_host = planes_bytes + 2 * crops + sum(cot_dev) + 3 * real * npix * ("rgb" in s.outputs) + slots
        host_steps.append(bwd_host)
        ram_steps.append(kept_dev + bwd_host + sum(cot_dev) + slots)
    return MemoryEstimate(int(device), int(max(out_dev + face_dev + state + cot_dev + [slots])),
                          int(max(host_steps)), int(max(ram_steps)), int(image),
                          f"rasterising {batch} x {s.height} x {s.width} pixels")


def available_host_memory() -> int | None:
    """Bytes the machine can still give this process: MemAvailable of /proc/meminfo (Linux),
    else psutil's available memory, else the physical memory (os.sysconf); None if unknown."""
    try:
        with open("/proc/meminfo", "rb") as f:
            for line in f:
                if line.startswith(b"MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        import psutil
        return int(psutil.virtual_memory().available)
    except Exception:       # not installed, or no answer on this system
        pass
    try:
        return int(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def _gb(n: int) -> str:
    return f"{n / GB:.1f} GB" if n >= GB else f"{n / 1024 ** 2:.0f} MB"


def check_memory(estimate: MemoryEstimate, device=None, advice: str = "lower image_size or the batch",
                 unified: bool | None = None) -> None:
    """Raise ResourceError if `estimate` cannot fit: its largest buffer over the device's
    CL_DEVICE_MAX_MEM_ALLOC_SIZE, its device buffers over CL_DEVICE_GLOBAL_MEM_SIZE, or what it
    needs in RAM over the machine's available memory (device and host together on a CPU device,
    or when `unified` says the device shares the host's RAM). `device`: a pyopencl Device or None
    (machine memory only). `advice` ends the message (what the caller can change)."""
    e = estimate
    name = ""
    if device is not None:
        import pyopencl as cl
        name = f"device {device.name!r}"
        if unified is None:
            unified = bool(device.type & cl.device_type.CPU) or bool(device.host_unified_memory)
        if e.largest_buffer > device.max_mem_alloc_size:
            raise ResourceError(f"{e.what} needs a {_gb(e.largest_buffer)} buffer, but {name} "
                                f"allows at most {_gb(device.max_mem_alloc_size)} in one buffer; {advice}")
        if e.device > device.global_mem_size:
            raise ResourceError(f"{e.what} needs ~{_gb(e.device)} of device memory, but {name} "
                                f"has {_gb(device.global_mem_size)}; {advice}")
    in_ram = e.shared if (unified or device is None) else e.host
    if in_ram < SMALL:
        return
    free = available_host_memory()
    if free is not None and in_ram > free:
        raise ResourceError(f"{e.what} needs ~{_gb(in_ram)} of memory, but the machine has "
                            f"{_gb(free)} available; {advice}")


def check_forward_memory(settings: RasterSettings, device, batch: int, n_faces: int, grads=(),
                         tex_res: int = 0, tex_shape: tuple = (0, 0)) -> MemoryEstimate:
    """memory_estimate + check_memory for one SoftRasterizer.forward call; returns the estimate."""
    estimate = memory_estimate(settings, batch, n_faces, grads, tex_res, tex_shape)
    check_memory(estimate, device)
    return estimate
