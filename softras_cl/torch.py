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

from functools import partial
from typing import NamedTuple

import numpy as np
import torch

from softras_cl import interop
from softras_cl.errors import InputError
from softras_cl.raster.rasterizer import SoftRasterizer as _NumpyRasterizer
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


def _forward(ctx, run, settings, arrays: dict, names: tuple, tensors: tuple, head: int) -> tuple:
    """Forward of an autograd op: run(arrays, wanted) -> the numpy output, on `arrays` (the fixed
    inputs) plus the `tensors` (named by `names`, after the op's `head` other arguments) as numpy
    arrays, keeping in ctx what _backward needs. Returns the images in settings.outputs order,
    (B, H, W, 3) or (B, H, W) tensors sharing the numpy output's memory."""
    named = dict(zip(names, tensors))
    wanted = tuple(n for n, need in zip(names, ctx.needs_input_grad[head:]) if need)
    out = run({**arrays, **{n: _to_numpy(n, t) for n, t in named.items()}}, wanted)
    ctx.set_materialize_grads(False)
    ctx.out, ctx.wanted = out, wanted
    ctx.save_for_backward(*tensors)     # only for _first_order's record of a double backward
    ctx.inputs = {n: (t.dtype, t.shape) for n, t in named.items()}
    return tuple(torch.from_numpy(getattr(out, o)) for o in interop.output_names(settings))


def _backward(ctx, name: str, input_grads, settings, grad_outputs: tuple) -> tuple:
    """Backward of an autograd op whose forward was _forward: input_grads(output, cotangents,
    shapes, wanted) -> {name: float64 gradient} from the numpy backward. Returns one gradient a
    tensor input (None where not wanted), each in its input's dtype and shape; `name` is the
    bridge's function, named by the error of a double backward."""
    names = interop.output_names(settings)
    cot = {o: _cotangent(g) for o, g in zip(names, grad_outputs)}
    grads = input_grads(ctx.out, cot, {n: tuple(s) for n, (_, s) in ctx.inputs.items()}, ctx.wanted)
    return _first_order(name, tuple(torch.from_numpy(grads[n]).to(dtype) if n in grads else None
                                     for n, (dtype, _) in ctx.inputs.items()), ctx.saved_tensors)


class RasterizeFunction(torch.autograd.Function):
    """Autograd op of SoftRasterizer: apply(rasterizer, arrays, names, *tensors) -> the images in
    settings.outputs order. `arrays` holds the non-differentiated inputs as numpy arrays; the
    tensors are the differentiated ones, named by `names`. Use `rasterize` or the
    SoftRasterizer module rather than this directly."""

    @staticmethod
    def forward(ctx, rasterizer, arrays, names, *tensors):
        ctx.rasterizer = rasterizer
        return _forward(ctx, partial(interop.raster_forward, rasterizer), rasterizer.settings,
                        arrays, names, tensors, head=3)

    @staticmethod
    def backward(ctx, *grad_outputs):
        return (None, None, None) + _backward(ctx, "softras_cl.torch.rasterize",
                                              partial(interop.raster_input_grads, ctx.rasterizer),
                                              ctx.rasterizer.settings, grad_outputs)


class RenderFunction(torch.autograd.Function):
    """Autograd op of Renderer: apply(renderer, cameras, light, arrays, names, *tensors) -> the
    images in settings.outputs order. Tensor names: "vertices", the colour input, "camera.<k>",
    "light.<k>" (softras_cl.interop). Use `render` or the Renderer module rather than this."""

    @staticmethod
    def forward(ctx, renderer, cameras, light, arrays, names, *tensors):
        ctx.renderer = renderer

        def run(arrays, wanted):
            return interop.render_forward(renderer, arrays, cameras, light, wanted)

        return _forward(ctx, run, renderer.settings, arrays, names, tensors, head=5)

    @staticmethod
    def backward(ctx, *grad_outputs):
        return (None,) * 5 + _backward(ctx, "softras_cl.torch.render",
                                       partial(interop.render_input_grads, ctx.renderer),
                                       ctx.renderer.settings, grad_outputs)


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
    as SoftRasterizer.forward takes them (docs/api.md), as CPU tensors or numpy arrays; their
    shapes and which are differentiable (all but faces and uvs): softras_cl.interop.
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


class SoftRasterizer(interop.BridgeRasterizer, torch.nn.Module):
    """nn.Module mirroring softras_cl.SoftRasterizer: `SoftRasterizer(settings, device=None,
    context=None, queue=None)` (the OpenCL device, not a torch device), called as
    `module(vertices, faces, colors=..., ...)` with the arguments of `rasterize` -> Images.
    No parameters; `.raster` is the numpy SoftRasterizer it runs."""

    rasterize_with = staticmethod(rasterize)

    def extra_repr(self) -> str:
        return repr(self.settings)


class Renderer(interop.BridgeRenderer, torch.nn.Module):
    """nn.Module mirroring softras_cl.scene.renderer.Renderer: `Renderer(settings,
    shading="vertex", device=None, context=None, queue=None)`, called as `module(vertices,
    faces, cameras, albedo=..., light=..., camera_params=..., light_params=...)` with the
    arguments of `render` -> Images. No parameters of its own: keep the tensors you optimise
    (vertices, albedo, camera or light parameters) in your own module or optimiser.
    `.renderer` is the numpy Renderer it runs."""

    render_with = staticmethod(render)

    def extra_repr(self) -> str:
        return f"shading={self.renderer.shading!r}, {self.settings!r}"
