"""Rasteriser settings.

Every field is either *build-time* (it selects a kernel variant through a -D flag, so a scene
pays nothing for effects it does not use) or *run-time* (a kernel argument or host-side choice).
The maths behind each field is written down in docs/conventions.md.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

import numpy as np

METRICS = ("euclidean", "barycentric")
COLOR_AGGS = ("softmax", "hard")
ALPHA_AGGS = ("occupancy", "sum", "hard")
TEXTURES = ("vertex", "face", "uv")
LIGHTINGS = ("none", "lambert", "sh")
OUTPUTS = ("rgb", "alpha", "depth")
DTYPES = ("float32", "float64")
LAYOUTS = ("auto", "cpu", "gpu")
# Largest magnitude a float32 kernel takes: 2^64, the square root of float32's largest value
# (~3.4e38). The kernels square depths and distances, so depths up to this bound keep images
# and gradients finite (measured: z = 1.8e19 finite, 1e20 gives NaN vertex gradients).
FLOAT32_LIMIT = 2.0 ** 64
# Smallest sigma at which float32 kernels give gradients (forward with grads). Where a pixel centre
# lies exactly on an edge, D = 1/2 and its derivative is 1 / (4 sigma) times the float32 rounding
# of the pixel-edge distance: against float64, the vertex gradients' worst error was about
# 5e-9 / sigma of their largest value (0.5% at 1e-6, 5% at 1e-7, 50% at 1e-8, 5x at 1e-9, 1e7x
# at 1e-16; 16 x 16 images, edges through pixel centres; off the centres 0.2% down to 1e-9).
# Images stay within 1e-6 of float64's down to sigma 1e-9 (1e-5 at 1e-10), so renders without
# gradients may go down to 1 / FLOAT32_LIMIT.
FLOAT32_GRAD_SIGMA = 1e-7


def _build(doc: str, **kw):
    return field(metadata={"build": True, "doc": doc}, **kw)


def _run(doc: str, **kw):
    return field(metadata={"build": False, "doc": doc}, **kw)


@dataclass(frozen=True)
class RasterSettings:
    """All knobs of the soft rasteriser; immutable, hashable, validated on creation.

    Image size is (height, width) in pixels. sigma is in squared NDC units.
    """

    image_size: tuple = _run("(height, width) of the output image in pixels", default=(256, 256))
    sigma: float = _run("sharpness of the probability map D (eq. 2), squared NDC units", default=1e-5)
    gamma: float = _run("sharpness of the softmax aggregation (eq. 9)", default=1e-4)
    dist_eps: float = _run("cut-off: skip (pixel, face) pairs with D < dist_eps; 0 = exact", default=1e-4)
    eps: float = _run("background weight exp(eps / gamma) (eq. 9)", default=1e-3)
    near: float | tuple = _run("near clipping depth (view z), > 0; or one per view (a tuple of B)", default=1.0)
    far: float | tuple = _run("far clipping depth (view z), > near; or one per view (a tuple of B)", default=100.0)
    background: tuple = _run("background RGB colour", default=(0.0, 0.0, 0.0))
    double_sided: bool = _run("draw faces of both orientations (else CCW only)", default=False)
    outputs: tuple = _build("which images to produce: subset of rgb, alpha, depth", default=("rgb", "alpha"))
    metric: str = _build("pixel-to-face distance: euclidean (eq. 4) or barycentric (eq. 6)", default="euclidean")
    color_agg: str = _build("aggregation of rgb and depth: softmax (eq. 8) or hard (z-buffer)", default="softmax")
    alpha_agg: str = _build("aggregation of alpha: occupancy (eq. 13), sum or hard", default="occupancy")
    texture: str = _build("colour source: vertex colours, per-face RxR textures or a uv map", default="vertex")
    perspective_correct: bool = _build("perspective-correct depth and colour interpolation", default=True)
    lighting: str = _build("per-pixel lighting of vertex albedo with interpolated vertex normals: "
                           "none, lambert or sh (texture='vertex' only)", default="none")
    dtype: str = _build("kernel precision: float32 or float64 (needs cl_khr_fp64)", default="float32")
    fast_math: bool = _build("build with -cl-fast-relaxed-math (an accuracy knob: measure it)", default=False)
    layout: str = _build("work layout of the kernels: cpu (vectors of pixels per work-item), gpu (one "
                         "pixel per work-item, tiles staged in local memory) or auto (gpu on GPU and "
                         "accelerator devices, else cpu); same maths, gradients' last bits differ", default="auto")

    def __post_init__(self):
        _check_settings(self)

    def replace(self, **changes) -> "RasterSettings":
        """A copy with some fields changed (validated again)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(changes)
        return RasterSettings(**values)

    @property
    def height(self) -> int:
        return int(self.image_size[0])

    @property
    def width(self) -> int:
        return int(self.image_size[1])

    def depth_ranges(self, batch: int) -> np.ndarray:
        """(batch, 2) float64: each view's (near, far); a single near or far is every view's.
        ValueError when a per-view tuple does not hold one value per view of the batch."""
        for name in ("near", "far"):
            value = getattr(self, name)
            if isinstance(value, tuple) and len(value) != batch:
                raise ValueError(f"{name} holds {len(value)} values (one per view), but the batch has "
                                 f"{batch} view{'s' * (batch != 1)}")
        ranges = np.empty((batch, 2))
        ranges[:, 0], ranges[:, 1] = self.near, self.far
        return ranges


def _positive_finite(name, value):
    if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


def _choice(name, value, allowed):
    if value not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {value!r}")


def depth_bound(name: str, value):
    """A depth bound (near or far) as given when a number, else as a tuple of floats (one per view)
    from a 1-d sequence or array of numbers; ValueError naming it otherwise."""
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return value
    try:
        values = tuple(float(v) for v in np.asarray(value, np.float64).reshape(-1))
    except (TypeError, ValueError):
        values = ()
    if np.ndim(value) != 1 or not values:
        raise ValueError(f"{name} must be a number, or one number per view (a non-empty sequence), got {value!r}")
    return values


def _check_depth_range(s: RasterSettings) -> None:
    """near > 0 and far > near, both finite, view by view (a tuple is one value per view)."""
    near, far = depth_bound("near", s.near), depth_bound("far", s.far)
    object.__setattr__(s, "near", near)
    object.__setattr__(s, "far", far)
    sizes = {len(v) for v in (near, far) if isinstance(v, tuple)}
    if len(sizes) > 1:
        raise ValueError(f"near and far must give one value per view each: {len(near)} near, {len(far)} far")
    for k, (n, f) in enumerate(s.depth_ranges(sizes.pop() if sizes else 1).tolist()):
        where = f"[{k}]" if isinstance(near, tuple) or isinstance(far, tuple) else ""
        _positive_finite(f"near{where}", n)
        if not (math.isfinite(f) and f > n):
            raise ValueError(f"far{where} must be finite and > near{where} ({n}), got {f!r}")


def _check_settings(s: RasterSettings) -> None:
    size = s.image_size
    if (not isinstance(size, (tuple, list)) or len(size) != 2
            or not all(isinstance(n, int) and n >= 1 for n in size)):
        raise ValueError(f"image_size must be (height, width), two ints >= 1, got {size!r}")
    object.__setattr__(s, "image_size", (int(size[0]), int(size[1])))
    for name in ("sigma", "gamma"):
        _positive_finite(name, getattr(s, name))
    _check_depth_range(s)
    if not (isinstance(s.dist_eps, (int, float)) and 0 <= s.dist_eps < 0.5):
        raise ValueError(f"dist_eps must be in [0, 0.5), got {s.dist_eps!r}")
    if not (isinstance(s.eps, (int, float)) and math.isfinite(s.eps)):
        raise ValueError(f"eps must be a finite number, got {s.eps!r}")
    bg = tuple(float(c) for c in s.background)
    if len(bg) != 3 or not all(math.isfinite(c) for c in bg):
        raise ValueError(f"background must be 3 finite numbers (RGB), got {s.background!r}")
    object.__setattr__(s, "background", bg)
    outputs = tuple(s.outputs)
    if not outputs or any(o not in OUTPUTS for o in outputs) or len(set(outputs)) != len(outputs):
        raise ValueError(f"outputs must be a non-empty subset of {OUTPUTS}, got {s.outputs!r}")
    object.__setattr__(s, "outputs", tuple(o for o in OUTPUTS if o in outputs))
    _choice("metric", s.metric, METRICS)
    _choice("color_agg", s.color_agg, COLOR_AGGS)
    _choice("alpha_agg", s.alpha_agg, ALPHA_AGGS)
    _choice("texture", s.texture, TEXTURES)
    _choice("dtype", s.dtype, DTYPES)
    _choice("lighting", s.lighting, LIGHTINGS)
    _choice("layout", s.layout, LAYOUTS)
    if s.lighting != "none" and s.texture != "vertex":
        raise ValueError(f"lighting={s.lighting!r} (per-pixel) needs texture='vertex', got {s.texture!r}")
    if s.dtype == "float32":
        _check_float32(s)


def check_float32_gradients(s: RasterSettings) -> None:
    """ValueError when gradients are asked of float32 kernels at a sigma below
    FLOAT32_GRAD_SIGMA, where they can be wrong by more than 5% (up to 1e7 times off)."""
    if s.dtype == "float32" and s.sigma < FLOAT32_GRAD_SIGMA:
        raise ValueError(f"sigma={s.sigma!r} is too small for gradients of dtype='float32' kernels "
                         f"(sigma >= {FLOAT32_GRAD_SIGMA:g}: below it, pixels on an edge get vertex "
                         "gradients wrong by more than 5%); use dtype='float64', or forward without grads")


def _check_float32(s: RasterSettings) -> None:
    """Run-time values a float32 kernel can take: magnitudes and the inverses of sigma and gamma
    within FLOAT32_LIMIT."""
    for name in ("near", "far", "eps"):
        if np.max(np.abs(getattr(s, name))) > FLOAT32_LIMIT:
            raise ValueError(f"{name}={getattr(s, name)!r} is beyond what dtype='float32' kernels handle "
                             f"(|{name}| <= {FLOAT32_LIMIT:.3g} = 2^64); use dtype='float64'")
    if max(abs(c) for c in s.background) > FLOAT32_LIMIT:
        raise ValueError(f"background={s.background!r} is beyond what dtype='float32' kernels handle "
                         f"(|value| <= {FLOAT32_LIMIT:.3g} = 2^64); use dtype='float64'")
    for name in ("sigma", "gamma"):
        if 1.0 / getattr(s, name) > FLOAT32_LIMIT:
            raise ValueError(f"{name}={getattr(s, name)!r} is too small for dtype='float32' kernels "
                             f"(1/{name} <= {FLOAT32_LIMIT:.3g} = 2^64, i.e. {name} >= "
                             f"{1 / FLOAT32_LIMIT:.3g}); use dtype='float64'")
