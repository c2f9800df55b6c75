"""JAX bridge: the soft rasteriser and the renderer as `jax.custom_vjp` functions over
`jax.pure_callback`, usable under `jax.jit`, `jax.grad` / `jax.vjp` and `jax.value_and_grad`.

    from softras_cl.jax import SoftRasterizer, Renderer       # pip install 'softras-cl[jax]'

Each call runs the numpy API (softras_cl.raster.rasterizer.SoftRasterizer,
softras_cl.scene.renderer.Renderer) on the host: the primal and the forward rule call its forward,
the backward rule its backward, so images and gradients equal the numpy API's bit for bit.
The forward rule keeps the numpy forward's context (with its OpenCL buffers) in a small host
cache under an int32 token that travels as the rule's residual; the backward rule takes it from
there (and drops it). If it is gone (more than CACHE_SIZE forwards awaiting their backward, or a
vjp function called twice) the backward runs the forward again first: same result, since every
kernel is deterministic, only slower.

Only the inputs JAX differentiates are differentiated (the forward rule sees which inputs are
perturbed, `symbolic_zeros=True`), so the kernel variant follows from what `jax.grad` is taken
with respect to; without differentiation the cheaper forward-only kernels run.

dtypes: float inputs float32 or float64 (float64 needs `jax.config.update("jax_enable_x64",
True)`), faces integer. Images come back in settings.dtype, gradients in each input's dtype and
shape. Batches: a leading axis as in the numpy API ((B, V, 3) vertices, a list of B cameras or
(B, k) camera parameters); under `jax.vmap` the callback runs once per mapped element
(vmap_method="sequential"). Values (shapes, NaN) are checked by the numpy API inside the callback:
under jit the error arrives wrapped by JAX, with the numpy message naming the argument.
Usage: docs/interop.md.
"""
from __future__ import annotations

import itertools
import threading
from collections import OrderedDict
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
import numpy as np

from softras_cl import interop
from softras_cl.raster.rasterizer import SoftRasterizer as _NumpyRasterizer
from softras_cl.raster.settings import RasterSettings
from softras_cl.scene.renderer import Renderer as _NumpyRenderer

__all__ = ["SoftRasterizer", "Renderer", "Images", "rasterize", "render", "CACHE_SIZE"]

CACHE_SIZE = 16          # forward contexts kept for their backward (oldest dropped first)
_CACHE: OrderedDict = OrderedDict()
_LOCK = threading.Lock()
_TOKENS = itertools.count(1)


class Images(NamedTuple):
    """Images of one call: rgb (B, H, W, 3), alpha (B, H, W), depth (B, H, W) jax arrays in
    settings.dtype; None for an output not in settings.outputs."""
    rgb: jax.Array | None
    alpha: jax.Array | None
    depth: jax.Array | None


def _store(output) -> np.int32:
    """Keep a numpy forward's output (and context) for its backward; returns its token."""
    with _LOCK:
        token = next(_TOKENS) % (2 ** 31 - 1)
        _CACHE[token] = output
        while len(_CACHE) > CACHE_SIZE:
            _CACHE.popitem(last=False)
    return np.int32(token)


def _take(token) -> object | None:
    with _LOCK:
        return _CACHE.pop(int(token), None)


def _check(name: str, value, integer: bool = False) -> jax.Array:
    """`value` as a jax array (tracers pass through) of a dtype the bridge takes."""
    arr = value if isinstance(value, jax.Array) else jnp.asarray(value)
    if integer:
        if not jnp.issubdtype(arr.dtype, jnp.integer):
            raise TypeError(f"{name} must be an integer array, got dtype {arr.dtype}")
    elif arr.dtype not in (jnp.float32, jnp.float64):
        raise TypeError(f"{name} must be a float32 or float64 array, got dtype {arr.dtype}")
    return arr


def _real(settings: RasterSettings):
    if settings.dtype == "float64" and not jax.config.jax_enable_x64:
        raise ValueError("settings.dtype='float64' needs 64-bit JAX: call "
                         "jax.config.update('jax_enable_x64', True) first, or use dtype='float32'")
    return np.dtype(settings.dtype)


def _host(values: dict) -> dict:
    return {n: np.asarray(v) for n, v in values.items()}


def _call(forward, backward, settings: RasterSettings, batch: int, diff: dict, fixed: dict) -> Images:
    """One differentiable host call. forward(arrays, wanted) -> numpy output with .rgb/.alpha/
    .depth; backward(output, cotangents, shapes, wanted) -> {name: gradient}. `diff` holds the
    float inputs (differentiated when JAX perturbs them), `fixed` the others."""
    names = interop.output_names(settings)
    shapes = interop.output_shapes(settings, batch)
    real = _real(settings)
    out_specs = tuple(jax.ShapeDtypeStruct(shapes[o], real) for o in names)
    token_spec = jax.ShapeDtypeStruct((), np.int32)

    def images(out) -> tuple:
        return tuple(np.asarray(getattr(out, o), real) for o in names)

    def host_primal(d, f):
        return images(forward({**_host(d), **_host(f)}, ()))

    @jax.custom_vjp
    def op(d, f):
        return jax.pure_callback(host_primal, out_specs, d, f, vmap_method="sequential")

    def op_fwd(d, f):
        wanted = tuple(n for n, p in d.items() if p.perturbed)
        d = {n: p.value for n, p in d.items()}
        f = {n: p.value for n, p in f.items()}
        if not wanted:
            return op(d, f), (jnp.int32(0), d, f, {})

        def host_forward(d, f):
            out = forward({**_host(d), **_host(f)}, wanted)
            return images(out) + (_store(out),)

        *outs, token = jax.pure_callback(host_forward, out_specs + (token_spec,), d, f,
                                         vmap_method="sequential")
        # the residual's dict of the differentiated inputs carries their names to op_bwd
        return tuple(outs), (token, d, f, {n: d[n] for n in wanted})

    def op_bwd(res, cots):
        token, d, f, marked = res
        wanted = tuple(marked)
        given = {o: c for o, c in zip(names, cots) if not isinstance(c, SymbolicZero)}
        if not wanted or not given:
            return {n: None for n in d}, None

        def host_backward(token, cot, d, f):
            d, f = _host(d), _host(f)
            out = _take(token)
            if out is None:                # evicted, or a second backward: recompute
                out = forward({**d, **f}, wanted)
            cot = {o: (np.asarray(cot[o]) if o in cot else None) for o in names}
            grads = backward(out, cot, {n: d[n].shape for n in wanted}, wanted)
            return {n: grads[n].astype(d[n].dtype) for n in wanted}

        specs = {n: jax.ShapeDtypeStruct(d[n].shape, d[n].dtype) for n in wanted}
        grads = jax.pure_callback(host_backward, specs, token, given, d, f, vmap_method="sequential")
        return {n: grads.get(n) for n in d}, None

    op.defvjp(op_fwd, op_bwd, symbolic_zeros=True)
    outs = iter(op(diff, fixed))
    return Images(*(next(outs) if o in settings.outputs else None for o in interop.OUTPUTS))


def rasterize(rasterizer: _NumpyRasterizer, vertices, faces, colors=None, face_textures=None,
              texture_image=None, uvs=None, normals=None, light=None) -> Images:
    """The soft rasteriser on jax arrays: `rasterizer` a numpy SoftRasterizer, the other
    arguments as SoftRasterizer.forward takes them (docs/api.md); their shapes and which are
    differentiable (all but faces and uvs): softras_cl.interop.
    Returns Images (rgb, alpha, depth; None where not in settings.outputs)."""
    given = dict(vertices=vertices, colors=colors, face_textures=face_textures,
                 texture_image=texture_image, normals=normals, light=light)
    diff = {n: _check(n, v) for n, v in given.items() if v is not None}
    fixed = {"faces": _check("faces", faces, integer=True)}
    if uvs is not None:
        fixed["uvs"] = _check("uvs", uvs)

    def forward(arrays, wanted):
        return interop.raster_forward(rasterizer, arrays, wanted)

    def backward(out, cot, shapes, wanted):
        return interop.raster_input_grads(rasterizer, out, cot, shapes, wanted)

    batch = diff["vertices"].shape[0] if diff["vertices"].ndim == 3 else 1
    return _call(forward, backward, rasterizer.settings, batch, diff, fixed)


def render(renderer: _NumpyRenderer, vertices, faces, cameras, albedo=None, light=None,
           face_textures=None, texture_image=None, uvs=None, camera_params=None,
           light_params=None) -> Images:
    """The whole render path on jax arrays: `renderer` a numpy Renderer, the other arguments as
    Renderer.forward takes them (docs/api.md):

    vertices (V, 3) | (B, V, 3) float, world; faces (F, 3) integer; cameras a Camera or a list
    of B (Python objects, fixed at trace time); albedo (V, 3) | (B, V, 3) (or, unlit,
    face_textures / texture_image + uvs); light a LambertLight / PhongLight / SHLight (None:
    the paper's Lambert).
    camera_params: optional dict of arrays replacing the cameras' parameters, "rotation" (3,) |
    (B, 3) axis-angle, "translation" (3,) | (B, 3), "focal" (2,) | (B, 2) [fx, fy] in pixels; a
    (k,) array is shared by all views, a (B, k) one is per view.
    light_params: optional dict of arrays replacing the light's parameters, keyed as
    light.params(): "ambient", "directional", "direction" (3,) (Lambert), "specular" (3,) and
    "shininess" () (Phong), "coefficients" (3, 9) (SH).
    Differentiable: vertices, the colour input, every camera_params and light_params array.
    Returns Images (rgb, alpha, depth; None where not in settings.outputs)."""
    given = dict(vertices=vertices, albedo=albedo, face_textures=face_textures, texture_image=texture_image)
    given.update({f"camera.{k}": v for k, v in (camera_params or {}).items()})
    given.update({f"light.{k}": v for k, v in (light_params or {}).items()})
    diff = {n: _check(n, v) for n, v in given.items() if v is not None}
    fixed = {"faces": _check("faces", faces, integer=True)}
    if uvs is not None:
        fixed["uvs"] = _check("uvs", uvs)

    def forward(arrays, wanted):
        return interop.render_forward(renderer, arrays, cameras, light, wanted)

    def backward(out, cot, shapes, wanted):
        return interop.render_input_grads(renderer, out, cot, shapes, wanted)

    batch = interop.render_batch(diff["vertices"].shape, cameras,
                                 [v.shape for n, v in diff.items() if n.startswith("camera.")])
    return _call(forward, backward, renderer.settings, batch, diff, fixed)


class SoftRasterizer(interop.BridgeRasterizer):
    """Mirrors softras_cl.SoftRasterizer: `SoftRasterizer(settings, device=None, context=None,
    queue=None)` (OpenCL device), called as `raster(vertices, faces, colors=..., ...)` with the
    arguments of `rasterize` -> Images. `.raster` is the numpy SoftRasterizer it runs."""

    rasterize_with = staticmethod(rasterize)
    __call__ = interop.BridgeRasterizer.forward


class Renderer(interop.BridgeRenderer):
    """Mirrors softras_cl.scene.renderer.Renderer: `Renderer(settings, shading="vertex",
    device=None, context=None, queue=None)`, called as `renderer(vertices, faces, cameras,
    albedo=..., light=..., camera_params=..., light_params=...)` with the arguments of `render`
    -> Images. `.renderer` is the numpy Renderer it runs."""

    render_with = staticmethod(render)
    __call__ = interop.BridgeRenderer.forward
