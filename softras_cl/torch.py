"""PyTorch bridge: the soft rasteriser and the renderer as torch.autograd Functions and nn.Modules.

    from softras_cl.torch import SoftRasterizer, Renderer     # pip install 'softras-cl[torch]'

Both run the numpy API (softras_cl.raster.rasterizer.SoftRasterizer,
softras_cl.scene.renderer.Renderer) on CPU tensors and wire its explicit adjoints into autograd:
forward calls the numpy forward, backward its backward, so images and gradients equal the numpy
API's bit for bit. Tensors cross to numpy without copies (`Tensor.numpy()` shares memory; images
come back through `torch.from_numpy`). Only the gradients autograd will ask for are computed,
and the kernel variant follows from them: a tensor counts when `requires_grad` is set and grad
mode is on, so under `torch.no_grad()` (or with no such tensor) forward runs the cheaper
forward-only kernels and builds no graph.

dtypes: float inputs are float32 or float64 CPU tensors (or numpy arrays, never differentiated);
faces are integer tensors or arrays. Images come back in settings.dtype (as from the numpy API),
each gradient in its input's dtype and shape. A CUDA (or other non-CPU) tensor, a wrong dtype, a
wrong shape or NaN raise an error naming the argument before any kernel runs. Usage and what is
differentiable: docs/interop.md. Gradients are first order only: a gradient taken with
create_graph=True is not differentiable again (differentiating it raises InputError).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from softras_cl import interop
from softras_cl.errors import InputError
from softras_cl.raster.rasterizer import SoftRasterizer as _NumpyRasterizer
from softras_cl.raster.settings import RasterSettings
from softras_cl.scene.renderer import Renderer as _NumpyRenderer

__all__ = ["SoftRasterizer", "Renderer", "Images", "RasterizeFunction", "RenderFunction",
           "rasterize", "render"]

_FLOATS = (torch.float32, torch.float64)


class Images(NamedTuple):
    """Images of one forward: rgb (B, H, W, 3), alpha (B, H, W), depth (B, H, W) tensors in
    settings.dtype; None for an output not in settings.outputs."""
    rgb: torch.Tensor | None
    alpha: torch.Tensor | None
    depth: torch.Tensor | None


def _to_numpy(name: str, value, integer: bool = False):
    """A CPU tensor as a numpy array sharing its memory (other values pass through for the numpy
    API to check). Raises for tensors on another device or of a dtype the bridge does not take."""
    if not isinstance(value, torch.Tensor):
        return value
    if value.device.type != "cpu":
        raise ValueError(f"{name} is a tensor on {value.device}; softras_cl.torch runs on CPU "
                         f"tensors: pass {name}.cpu() (and move the results back with .to(device))")
    if integer:
        if value.dtype.is_floating_point or value.dtype.is_complex or value.dtype == torch.bool:
            raise TypeError(f"{name} must be an integer tensor, got {value.dtype}")
    elif value.dtype not in _FLOATS:
        raise TypeError(f"{name} must be a float32 or float64 tensor, got {value.dtype}")
    return value.detach().resolve_conj().resolve_neg().numpy()


def _split(named: dict, integer=("faces",)):
    """(numpy arrays by name, the names whose gradient autograd will ask for, tensors by name)."""
    arrays = {n: _to_numpy(n, v, n in integer) for n, v in named.items() if v is not None}
    grad_on = torch.is_grad_enabled()
    wanted = tuple(n for n, v in named.items()
                   if grad_on and isinstance(v, torch.Tensor) and v.requires_grad and n not in integer)
    return arrays, wanted


def _images(out, settings) -> Images:
    """numpy images -> tensors sharing their memory (None where not produced)."""
    return Images(*(torch.from_numpy(getattr(out, o)) if o in settings.outputs else None
                    for o in interop.OUTPUTS))


def _cotangent(grad: torch.Tensor | None) -> np.ndarray | None:
    return None if grad is None else grad.detach().numpy()


class _FirstOrderOnly(torch.autograd.Function):
    """apply(name, n, *grads, *inputs) -> the n gradients of a bridge's backward, recorded as
    functions of the op's inputs, whose own backward (the gradient of those gradients) raises
    InputError naming the bridge's function `name`."""

    @staticmethod
    def forward(ctx, name, n, *tensors):
        ctx.name = name
        return tuple(g.clone() for g in tensors[:n])

    @staticmethod
    def backward(ctx, *unused):
        raise InputError(f"{ctx.name}: double backward is not supported: its gradients are first "
                         "order only (the OpenCL kernels have no second derivatives), so a gradient "
                         "taken with create_graph=True cannot be differentiated again")


def _first_order(name: str, grads: tuple, inputs: tuple) -> tuple:
    """A backward's gradients (tensors or None) as they are, or, when autograd records them
    (create_graph=True), passed through _FirstOrderOnly with the op's `inputs` (its saved
    tensors) so that differentiating them raises."""
    if not torch.is_grad_enabled():
        return grads
    given = [g for g in grads if g is not None]
    outs = iter(_FirstOrderOnly.apply(name, len(given), *given, *inputs))
    return tuple(None if g is None else next(outs) for g in grads)


class RasterizeFunction(torch.autograd.Function):
    """Autograd op of SoftRasterizer: apply(rasterizer, arrays, names, *tensors) -> the images in
    settings.outputs order. `arrays` holds the non-differentiated inputs as numpy arrays; the
    tensors are the differentiated ones, named by `names`. Use `rasterize` or the
    SoftRasterizer module rather than this directly."""

    @staticmethod
    def forward(ctx, rasterizer, arrays, names, *tensors):
        named = dict(zip(names, tensors))
        wanted = tuple(n for n, need in zip(names, ctx.needs_input_grad[3:]) if need)
        out = interop.raster_forward(rasterizer, {**arrays, **{n: _to_numpy(n, t) for n, t in named.items()}},
                                     wanted)
        ctx.set_materialize_grads(False)
        ctx.rasterizer, ctx.out, ctx.wanted = rasterizer, out, wanted
        ctx.save_for_backward(*tensors)     # only for _first_order's record of a double backward
        ctx.inputs = {n: (t.dtype, t.shape) for n, t in named.items()}
        return tuple(torch.from_numpy(getattr(out, o)) for o in interop.output_names(rasterizer.settings))

    @staticmethod
    def backward(ctx, *grad_outputs):
        names = interop.output_names(ctx.rasterizer.settings)
        cot = {o: _cotangent(g) for o, g in zip(names, grad_outputs)}
        grads = interop.raster_input_grads(ctx.rasterizer, ctx.out, cot,
                                           {n: tuple(s) for n, (_, s) in ctx.inputs.items()}, ctx.wanted)
        return (None, None, None) + _first_order("softras_cl.torch.rasterize", tuple(
            torch.from_numpy(grads[n]).to(dtype) if n in grads else None
            for n, (dtype, _) in ctx.inputs.items()), ctx.saved_tensors)


class RenderFunction(torch.autograd.Function):
    """Autograd op of Renderer: apply(renderer, cameras, light, arrays, names, *tensors) -> the
    images in settings.outputs order. Tensor names: "vertices", the colour input, "camera.<k>",
    "light.<k>" (softras_cl.interop). Use `render` or the Renderer module rather than this."""

    @staticmethod
    def forward(ctx, renderer, cameras, light, arrays, names, *tensors):
        named = dict(zip(names, tensors))
        wanted = tuple(n for n, need in zip(names, ctx.needs_input_grad[5:]) if need)
        out = interop.render_forward(renderer, {**arrays, **{n: _to_numpy(n, t) for n, t in named.items()}},
                                     cameras, light, wanted)
        ctx.set_materialize_grads(False)
        ctx.renderer, ctx.out, ctx.wanted = renderer, out, wanted
        ctx.save_for_backward(*tensors)     # only for _first_order's record of a double backward
        ctx.inputs = {n: (t.dtype, t.shape) for n, t in named.items()}
        return tuple(torch.from_numpy(getattr(out, o)) for o in interop.output_names(renderer.settings))

    @staticmethod
    def backward(ctx, *grad_outputs):
        names = interop.output_names(ctx.renderer.settings)
        cot = {o: _cotangent(g) for o, g in zip(names, grad_outputs)}
        grads = interop.render_input_grads(ctx.renderer, ctx.out, cot,
                                           {n: tuple(s) for n, (_, s) in ctx.inputs.items()}, ctx.wanted)
        return (None,) * 5 + _first_order("softras_cl.torch.render", tuple(
            torch.from_numpy(grads[n]).to(dtype) if n in grads else None
            for n, (dtype, _) in ctx.inputs.items()), ctx.saved_tensors)


def _apply(function, head: tuple, named: dict, arrays: dict, wanted: tuple, settings) -> Images:
    """Run `function` with the differentiated tensors as its inputs; put None where an output
    is not in settings.outputs."""
    tensors = {n: named[n] for n in wanted}
    fixed = {n: a for n, a in arrays.items() if n not in tensors}
    outs = iter(function.apply(*head, fixed, tuple(tensors), *tensors.values()))
    return Images(*(next(outs) if o in settings.outputs else None for o in interop.OUTPUTS))


def rasterize(rasterizer: _NumpyRasterizer, vertices, faces, colors=None, face_textures=None,
              texture_image=None, uvs=None, normals=None, light=None) -> Images:
    """The soft rasteriser on tensors: `rasterizer` a numpy SoftRasterizer, the other arguments
    as SoftRasterizer.forward takes them (docs/api.md), as CPU tensors or numpy arrays:

    vertices (B, V, 3) | (V, 3) float, screen space; faces (F, 3) | (B, F, 3) integer;
    one colour input by settings.texture: colors (B, V, 3) | (V, 3), face_textures
    (B, F, R, R, 3), or texture_image (B, Ht, Wt, 3) with uvs (B, V, 2) | (V, 2);
    per-pixel lighting (settings.lighting): normals (B, V, 3), light (27,).
    Differentiable: vertices, colors / face_textures / texture_image, normals, light (not uvs).
    Returns Images (rgb, alpha, depth; None where not in settings.outputs)."""
    named = dict(vertices=vertices, faces=faces, colors=colors, face_textures=face_textures,
                 texture_image=texture_image, uvs=uvs, normals=normals, light=light)
    named = {n: v for n, v in named.items() if v is not None}
    arrays, wanted = _split(named, integer=("faces",))
    wanted = tuple(n for n in wanted if n != "uvs")
    if not wanted:
        return _images(interop.raster_forward(rasterizer, arrays), rasterizer.settings)
    return _apply(RasterizeFunction, (rasterizer,), named, arrays, wanted, rasterizer.settings)


def render(renderer: _NumpyRenderer, vertices, faces, cameras, albedo=None, light=None,
           face_textures=None, texture_image=None, uvs=None, camera_params=None,
           light_params=None) -> Images:
    """The whole render path on tensors: `renderer` a numpy Renderer, the other arguments as
    Renderer.forward takes them (docs/api.md), as CPU tensors or numpy arrays:

    vertices (V, 3) | (B, V, 3) float, world; faces (F, 3) integer; cameras a Camera or a list
    of B; albedo (V, 3) | (B, V, 3) (or, unlit, face_textures / texture_image + uvs); light a
    LambertLight / PhongLight / SHLight (None: the paper's Lambert).
    camera_params: optional dict replacing the cameras' parameters with tensors, "rotation"
    (3,) | (B, 3) axis-angle, "translation" (3,) | (B, 3), "focal" (2,) | (B, 2) [fx, fy] in
    pixels; a (k,) tensor is shared by all views, a (B, k) one is per view.
    light_params: optional dict replacing the light's parameters with tensors, keyed as
    light.params(): "ambient", "directional", "direction" (3,) (Lambert), "specular" (3,) and
    "shininess" () (Phong), "coefficients" (3, 9) (SH).
    Differentiable: vertices, the colour input, every camera_params and light_params tensor.
    Returns Images (rgb, alpha, depth; None where not in settings.outputs)."""
    named = dict(vertices=vertices, faces=faces, albedo=albedo, face_textures=face_textures,
                 texture_image=texture_image, uvs=uvs)
    named.update({f"camera.{k}": v for k, v in (camera_params or {}).items()})
    named.update({f"light.{k}": v for k, v in (light_params or {}).items()})
    named = {n: v for n, v in named.items() if v is not None}
    arrays, wanted = _split(named, integer=("faces",))
    wanted = tuple(n for n in wanted if n != "uvs")
    if not wanted:
        return _images(interop.render_forward(renderer, arrays, cameras, light), renderer.settings)
    return _apply(RenderFunction, (renderer, cameras, light), named, arrays, wanted, renderer.settings)


class SoftRasterizer(torch.nn.Module):
    """nn.Module mirroring softras_cl.SoftRasterizer: `SoftRasterizer(settings, device=None,
    context=None, queue=None)` (the OpenCL device, not a torch device), called as
    `module(vertices, faces, colors=..., ...)` with the arguments of `rasterize` -> Images.
    No parameters; `.raster` is the numpy SoftRasterizer it runs."""

    def __init__(self, settings: RasterSettings, device=None, context=None, queue=None):
        super().__init__()
        self.raster = _NumpyRasterizer(settings, device=device, context=context, queue=queue)

    @property
    def settings(self) -> RasterSettings:
        return self.raster.settings

    def forward(self, vertices, faces, colors=None, face_textures=None, texture_image=None,
                uvs=None, normals=None, light=None) -> Images:
        return rasterize(self.raster, vertices, faces, colors=colors, face_textures=face_textures,
                         texture_image=texture_image, uvs=uvs, normals=normals, light=light)

    def extra_repr(self) -> str:
        return repr(self.settings)


class Renderer(torch.nn.Module):
    """nn.Module mirroring softras_cl.scene.renderer.Renderer: `Renderer(settings,
    shading="vertex", device=None, context=None, queue=None)`, called as `module(vertices,
    faces, cameras, albedo=..., light=..., camera_params=..., light_params=...)` with the
    arguments of `render` -> Images. No parameters of its own: keep the tensors you optimise
    (vertices, albedo, camera or light parameters) in your own module or optimiser.
    `.renderer` is the numpy Renderer it runs."""

    def __init__(self, settings: RasterSettings, shading: str = "vertex", device=None, context=None,
                 queue=None):
        super().__init__()
        self.renderer = _NumpyRenderer(settings, shading=shading, device=device, context=context,
                                       queue=queue)

    @property
    def settings(self) -> RasterSettings:
        return self.renderer.settings

    def forward(self, vertices, faces, cameras, albedo=None, light=None, face_textures=None,
                texture_image=None, uvs=None, camera_params=None, light_params=None) -> Images:
        return render(self.renderer, vertices, faces, cameras, albedo=albedo, light=light,
                      face_textures=face_textures, texture_image=texture_image, uvs=uvs,
                      camera_params=camera_params, light_params=light_params)

    def extra_repr(self) -> str:
        return f"shading={self.renderer.shading!r}, {self.settings!r}"
