"""Host-side plumbing shared by the PyTorch and JAX bridges (softras_cl.torch, softras_cl.jax).

numpy and the numpy API only. The bridges turn their tensors into numpy arrays keyed by argument
name, and this module maps such a dict onto `SoftRasterizer.forward` / `Renderer.forward`
(choosing the gradient variant from the names the caller wants gradients for), and the numpy
backward's gradients back onto the same names, each in the shape of its input. Every check of
values (shapes, NaN, ranges) is the numpy API's own; this module adds only what the bridges'
extra arguments need (`camera_params`, `light_params`). BridgeRasterizer and BridgeRenderer are
the bridges' SoftRasterizer and Renderer classes but for the framework. Usage: docs/interop.md.

Arguments:
- rasteriser (the bridges' `rasterize`): vertices (B, V, 3) | (V, 3) float, screen space; faces
  (F, 3) | (B, F, 3) integer; one colour input by settings.texture: colors (B, V, 3) | (V, 3),
  face_textures (B, F, R, R, 3), or texture_image (B, Ht, Wt, 3) with uvs (B, V, 2) | (V, 2);
  per-pixel lighting (settings.lighting): normals (B, V, 3), light (27,). "vertices", "colors",
  "face_textures", "texture_image", "normals", "light" are differentiable
  (RASTER_DIFFERENTIABLE); "faces" and "uvs" are not.
- renderer: "vertices", the colour input ("albedo", "face_textures" or "texture_image"),
  "camera.rotation", "camera.translation", "camera.focal" and "light.<parameter>" (the keys of
  the light's params()) are differentiable; "faces" and "uvs" are not.
"""
from __future__ import annotations

import math

import numpy as np

from softras_cl.raster.rasterizer import SoftRasterizer
from softras_cl.raster.settings import RasterSettings
from softras_cl.scene.renderer import Renderer

OUTPUTS = ("rgb", "alpha", "depth")
RASTER_DIFFERENTIABLE = ("vertices", "colors", "face_textures", "texture_image", "normals", "light")
RASTER_ARGS = RASTER_DIFFERENTIABLE + ("faces", "uvs")
RENDER_COLOR_INPUTS = ("albedo", "face_textures", "texture_image")
CAMERA_PARAMS = {"rotation": 3, "translation": 3, "focal": 2}


def output_names(settings) -> tuple[str, ...]:
    """The images a forward returns, in the order rgb, alpha, depth (those in settings.outputs)."""
    return tuple(o for o in OUTPUTS if o in settings.outputs)


def output_shapes(settings, batch: int) -> dict[str, tuple]:
    """{output name: shape} of a forward over `batch` images: (B, H, W, 3) for rgb, else (B, H, W)."""
    h, w = settings.image_size
    return {o: (batch, h, w, 3) if o == "rgb" else (batch, h, w) for o in output_names(settings)}


def unbroadcast(name: str, grad: np.ndarray, shape: tuple) -> np.ndarray:
    """A gradient from the numpy API in the shape of the input given: reshaped when only the
    layout differs (light (27,) vs (3, 9)), summed over axes the input was broadcast along
    (no batch axis, batch 1, a scalar colour)."""
    grad = np.asarray(grad, np.float64)
    shape = tuple(shape)
    if grad.shape == shape:
        return grad
    if grad.size == math.prod(shape):
        return grad.reshape(shape)
    extra = grad.ndim - len(shape)
    if extra < 0:
        raise AssertionError(f"gradient of {name} has shape {grad.shape}, input {shape}")
    grad = grad.sum(axis=tuple(range(extra))) if extra else grad
    axes = tuple(i for i, n in enumerate(shape) if n == 1 and grad.shape[i] != 1)
    grad = grad.sum(axis=axes, keepdims=True) if axes else grad
    if grad.shape != shape:
        raise AssertionError(f"gradient of {name} has shape {grad.shape}, input {shape}")
    return grad


# ---- the rasteriser ---------------------------------------------------------------------------
def raster_grads(wanted) -> tuple[str, ...]:
    """SoftRasterizer.forward(grads=...) for gradients of the argument names `wanted`."""
    wanted = set(wanted)
    unknown = wanted - set(RASTER_DIFFERENTIABLE)
    if unknown:
        raise ValueError(f"no gradient for {sorted(unknown)}: differentiable rasteriser inputs are "
                         f"{RASTER_DIFFERENTIABLE} (uvs get none, the paper's choice)")
    color_inputs = wanted - {"vertices"}
    return (("vertices",) if "vertices" in wanted else ()) + (("colors",) if color_inputs else ())


def raster_forward(raster, arrays: dict, wanted=()):
    """SoftRasterizer.forward on the named numpy `arrays` (keys of RASTER_ARGS), keeping what
    backward needs for the names in `wanted`. Returns the RasterOutput."""
    unknown = set(arrays) - set(RASTER_ARGS)
    if unknown:
        raise TypeError(f"unknown rasteriser arguments {sorted(unknown)}; expected some of {RASTER_ARGS}")
    return raster.forward(**arrays, grads=raster_grads(wanted))


def raster_input_grads(raster, output, cotangents: dict, shapes: dict, wanted) -> dict:
    """Gradients {name: float64 array in the shape of shapes[name]} for the names in `wanted`,
    from SoftRasterizer.backward with `cotangents` {output name: array or None}."""
    g = raster.backward(output, **{f"grad_{o}": c for o, c in cotangents.items()})
    out = {}
    for name in wanted:
        key = name if name in ("vertices", "normals", "light") else "colors"
        out[name] = unbroadcast(name, g[key], shapes[name])
    return out


# ---- the renderer -----------------------------------------------------------------------------
def _param(name: str, value, width: int) -> np.ndarray:
    """A camera parameter: (width,) or (N, width) float -> float64 array."""
    from softras_cl.checks import check_finite, float_array

    arr = float_array(name, value)
    if arr.ndim not in (1, 2) or arr.shape[-1] != width or (arr.ndim == 2 and arr.shape[0] < 1):
        raise ValueError(f"{name} must have shape ({width},) or (N, {width}), got {arr.shape}")
    return check_finite(name, arr).astype(np.float64)


def camera_views(cameras, camera_params: dict | None):
    """The cameras to pass to Renderer.forward, with `camera_params` ({"rotation": (3,) | (N, 3),
    "translation": (3,) | (N, 3), "focal": (2,) | (N, 2)} [fx, fy]) replacing the cameras'
    own values. A (k,) parameter is shared by every view, an (N, k) one gives each of N views its
    own. One Camera and only shared parameters stay one Camera (its gradient summed over the
    batch, as in the numpy API); otherwise a list of N cameras."""
    from softras_cl.scene.camera import Camera

    params = dict(camera_params or {})
    unknown = set(params) - set(CAMERA_PARAMS)
    if unknown:
        raise ValueError(f"camera_params has unknown keys {sorted(unknown)}; expected some of "
                         f"{tuple(CAMERA_PARAMS)}")
    params = {k: _param(f"camera_params[{k!r}]", v, CAMERA_PARAMS[k]) for k, v in params.items()}
    if not params:
        return cameras
    single = isinstance(cameras, Camera)
    if not single and (not isinstance(cameras, (list, tuple)) or not cameras
                       or not all(isinstance(c, Camera) for c in cameras)):
        raise TypeError("cameras must be a Camera or a non-empty list of Camera objects")
    counts = {k: v.shape[0] for k, v in params.items() if v.ndim == 2}
    if not single:
        counts["cameras"] = len(cameras)
    if len(set(counts.values())) > 1:
        raise ValueError(f"camera_params and cameras disagree on the number of views: {counts}")
    if single and not counts:
        return _with_params(cameras, params, None)
    n = next(iter(counts.values()))
    templates = [cameras] * n if single else list(cameras)
    return [_with_params(cam, params, i) for i, cam in enumerate(templates)]


def _with_params(camera, params: dict, view: int | None):
    """`camera` with the parameters of `params` (row `view` of (N, k) ones)."""
    take = {k: (v if v.ndim == 1 else v[view]) for k, v in params.items()}
    changes = {k: take[k] for k in ("rotation", "translation") if k in take}
    if "focal" in take:
        changes.update(fx=float(take["focal"][0]), fy=float(take["focal"][1]))
    return camera.with_params(**changes)


def scene_light(light, light_params: dict | None):
    """`light` (LambertLight, PhongLight or SHLight; None: the paper's Lambert) with the
    parameters in `light_params` (keys of its params(), e.g. "coefficients" for SHLight)
    replaced; the light class checks their values."""
    from softras_cl.scene.shading import LambertLight

    light = LambertLight() if light is None else light
    params = dict(light_params or {})
    if not params:
        return light
    if not hasattr(light, "params"):
        raise ValueError(f"light must be a LambertLight, PhongLight or SHLight, got {type(light).__name__}")
    known = light.params()
    unknown = set(params) - set(known)
    if unknown:
        raise ValueError(f"light_params has keys {sorted(unknown)} that {type(light).__name__} does "
                         f"not have; its parameters are {tuple(known)}")
    return type(light)(**{**known, **params})


def render_batch(vertices_shape: tuple, cameras, camera_param_shapes=()) -> int:
    """B of a renderer call: the vertices' batch axis, else the number of cameras (a list's
    length, or N of (N, k) camera parameters), else 1."""
    if len(vertices_shape) == 3:
        return vertices_shape[0]
    if isinstance(cameras, (list, tuple)):
        return len(cameras)
    return next((shape[0] for shape in camera_param_shapes if len(shape) == 2), 1)


def render_groups(wanted) -> tuple[str, ...]:
    """Renderer.forward(grads=...) for gradients of the argument names `wanted`."""
    groups = []
    for name in wanted:
        group = ("albedo" if name in RENDER_COLOR_INPUTS else "camera" if name.startswith("camera.")
                 else "light" if name.startswith("light.") else name)
        if group not in ("vertices", "albedo", "camera", "light"):
            raise ValueError(f"no gradient for {name!r}: differentiable renderer inputs are vertices, "
                             f"{', '.join(RENDER_COLOR_INPUTS)}, camera_params and light_params")
        groups.append(group)
    return tuple(g for g in ("vertices", "albedo", "camera", "light") if g in groups)


def render_forward(renderer, arrays: dict, cameras, light, wanted=()):
    """Renderer.forward on the named numpy `arrays`: "vertices", "faces", the colour input,
    "uvs", and "camera.<k>" / "light.<k>" entries that replace the parameters of `cameras` and
    `light`; keeps what backward needs for the names in `wanted`. Returns the RenderOutput."""
    cam_params = {k[len("camera."):]: v for k, v in arrays.items() if k.startswith("camera.")}
    light_params = {k[len("light."):]: v for k, v in arrays.items() if k.startswith("light.")}
    rest = {k: v for k, v in arrays.items() if "." not in k}
    unknown = set(rest) - {"vertices", "faces", "uvs", *RENDER_COLOR_INPUTS}
    if unknown:
        raise TypeError(f"unknown renderer arguments {sorted(unknown)}")
    views = camera_views(cameras, cam_params)
    lit = scene_light(light, light_params) if (light is not None or light_params) else None
    return renderer.forward(rest["vertices"], rest["faces"], views, light=lit,
                            grads=render_groups(wanted),
                            **{k: v for k, v in rest.items() if k not in ("vertices", "faces")})


def render_input_grads(renderer, output, cotangents: dict, shapes: dict, wanted) -> dict:
    """Gradients {name: float64 array in the shape of shapes[name]} for the names in `wanted`,
    from Renderer.backward with `cotangents` {output name: array or None}."""
    g = renderer.backward(output, **{f"grad_{o}": c for o, c in cotangents.items()})
    out = {}
    for name in wanted:
        if name == "vertices":
            grad = g["vertices"]
        elif name in RENDER_COLOR_INPUTS:
            grad = g["albedo"]
        elif name.startswith("camera."):
            key = name[len("camera."):]
            cams = g["camera"]
            grad = (cams[key] if isinstance(cams, dict) else
                    np.stack([c[key] for c in cams]) if len(shapes[name]) == 2 else
                    sum(c[key] for c in cams))
        else:
            grad = g["light"][name[len("light."):]]
        out[name] = unbroadcast(name, grad, shapes[name])
    return out


# ---- the bridges' classes ---------------------------------------------------------------------
class BridgeRasterizer:
    """The bridges' SoftRasterizer: `SoftRasterizer(settings, device=None, context=None,
    queue=None)` (the OpenCL device) holds the numpy SoftRasterizer `.raster`; `forward` runs it
    through the bridge's function `rasterize_with`, a staticmethod the subclass sets to its
    rasterize(raster, vertices, faces, ...) -> Images."""

    rasterize_with = None

    def __init__(self, settings: RasterSettings, device=None, context=None, queue=None):
        super().__init__()      # torch.nn.Module's in the PyTorch bridge
        self.raster = SoftRasterizer(settings, device=device, context=context, queue=queue)

    @property
    def settings(self) -> RasterSettings:
        return self.raster.settings

    def forward(self, vertices, faces, colors=None, face_textures=None, texture_image=None,
                uvs=None, normals=None, light=None):
        """The bridge's Images (rgb (B, H, W, 3), alpha and depth (B, H, W) in settings.dtype) of
        the arguments of its `rasterize`."""
        return self.rasterize_with(self.raster, vertices, faces, colors=colors, face_textures=face_textures,
                                   texture_image=texture_image, uvs=uvs, normals=normals, light=light)


class BridgeRenderer:
    """The bridges' Renderer: `Renderer(settings, shading="vertex", device=None, context=None,
    queue=None)` holds the numpy Renderer `.renderer`; `forward` runs it through the bridge's
    function `render_with`, a staticmethod the subclass sets to its
    render(renderer, vertices, faces, cameras, ...) -> Images."""

    render_with = None

    def __init__(self, settings: RasterSettings, shading: str = "vertex", device=None, context=None,
                 queue=None):
        super().__init__()      # torch.nn.Module's in the PyTorch bridge
        self.renderer = Renderer(settings, shading=shading, device=device, context=context, queue=queue)

    @property
    def settings(self) -> RasterSettings:
        return self.renderer.settings

    def forward(self, vertices, faces, cameras, albedo=None, light=None, face_textures=None,
                texture_image=None, uvs=None, camera_params=None, light_params=None):
        """The bridge's Images (rgb (B, H, W, 3), alpha and depth (B, H, W) in settings.dtype) of
        the arguments of its `render`."""
        return self.render_with(self.renderer, vertices, faces, cameras, albedo=albedo, light=light,
                                face_textures=face_textures, texture_image=texture_image, uvs=uvs,
                                camera_params=camera_params, light_params=light_params)
