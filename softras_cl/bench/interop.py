"""`softras-cl bench interop`: what the PyTorch and JAX bridges add to the numpy call."""
from __future__ import annotations

import argparse
import random
import statistics
import time

import numpy as np

from softras_cl.bench.render import RENDER_MAIN, make_render_scene, render_settings
from softras_cl.bench.tools import add_output_options, format_table, run_with_progress

INTEROP_DOC = """Overhead of the PyTorch and JAX bridges (softras_cl.torch, softras_cl.jax) over the
numpy call they wrap, on the render bench's scene: an icosphere(5) (20480 faces) with bumps, smooth
vertex albedo, SH light, per-vertex shading, one look-at camera at 512^2, float32, rgb + alpha.

Six operations, each timed through the numpy API, the torch bridge and the JAX bridge:
renderer forward+backward with gradients for vertices, albedo, camera (rotation, translation,
focal) and the SH coefficients; renderer forward only (no gradients: torch.no_grad, a jitted JAX
forward); and the same two for the rasteriser alone (the scene projected once to screen space,
vertex colours, gradients for vertices and colours). torch: float32 tensors, loss-free
`torch.autograd.backward` with the bench's cotangents; JAX: `jax.jit` of the forward and of
`jax.vjp` + its backward. Each round runs every (operation, API) once in a seeded random order,
after one warm-up round (kernel builds, JAX compilation); medians of --repeats rounds. The
overhead is median(bridge) / median(numpy) - 1, measured in the same run."""
OPERATIONS = (("render_fb", "renderer forward+backward"), ("render_f", "renderer forward only"),
              ("raster_fb", "rasteriser forward+backward"), ("raster_f", "rasteriser forward only"))
APIS = ("numpy", "torch", "jax")
QUICK = dict(subdivisions=3, size=64, texture=8, repeats=1)
TARGET = 0.05


def interop_plan(args: argparse.Namespace) -> dict:
    p = dict(QUICK if args.quick else dict(RENDER_MAIN, texture=8))
    if args.repeats is not None:
        if args.repeats < 1:
            raise ValueError(f"--repeats must be >= 1, got {args.repeats}")
        p["repeats"] = args.repeats
    p["apis"] = [a for a in APIS if a == "numpy" or _available(a)]
    return p


def _available(api: str) -> bool:
    import importlib.util
    return importlib.util.find_spec(api) is not None


def make_calls(p: dict) -> dict:
    """{(operation, api): a function that runs it once and returns something to block on}."""
    from softras_cl.raster.rasterizer import SoftRasterizer
    from softras_cl.scene.renderer import Renderer

    scene = make_render_scene(p["subdivisions"], p["size"], p["texture"])
    settings = render_settings(scene.size)
    cam, light = scene.camera, scene.sh_light
    f32 = lambda a: np.asarray(a, np.float32)
    verts, albedo = f32(scene.vertices), f32(scene.albedo)
    cam_arrays = dict(rotation=f32(cam.rotation), translation=f32(cam.translation), focal=f32(cam.focal))
    coefficients = f32(light.coefficients)
    grad_rgb, grad_alpha = f32(scene.grad_rgb), f32(scene.grad_alpha)
    screen, _ = cam.project(scene.vertices)
    screen = f32(screen)
    raster = SoftRasterizer(settings)
    renderer = Renderer(settings, shading="vertex")
    groups = ("vertices", "albedo", "camera", "light")

    def np_render_fb():
        out = renderer.forward(verts, scene.faces, cam.with_params(**_camera_changes(cam_arrays)),
                               albedo=albedo, light=type(light)(coefficients), grads=groups)
        return renderer.backward(out, grad_rgb=grad_rgb, grad_alpha=grad_alpha)

    def np_raster_fb():
        out = raster.forward(screen, scene.faces, colors=albedo, grads=("vertices", "colors"))
        return raster.backward(out, grad_rgb=grad_rgb, grad_alpha=grad_alpha)

    calls = {("render_fb", "numpy"): np_render_fb,
             ("render_f", "numpy"): lambda: renderer.forward(verts, scene.faces, cam, albedo=albedo, light=light),
             ("raster_fb", "numpy"): np_raster_fb,
             ("raster_f", "numpy"): lambda: raster.forward(screen, scene.faces, colors=albedo)}
    if "torch" in p["apis"]:
        calls.update(_torch_calls(raster, renderer, scene, verts, albedo, cam_arrays, coefficients,
                                  screen, grad_rgb, grad_alpha))
    if "jax" in p["apis"]:
        calls.update(_jax_calls(raster, renderer, scene, verts, albedo, cam_arrays, coefficients,
                                screen, grad_rgb, grad_alpha))
    return calls


def _camera_changes(arrays: dict) -> dict:
    return dict(rotation=arrays["rotation"], translation=arrays["translation"],
                fx=float(arrays["focal"][0]), fy=float(arrays["focal"][1]))


def _torch_calls(raster, renderer, scene, verts, albedo, cam_arrays, coefficients, screen,
                 grad_rgb, grad_alpha) -> dict:
    import torch

    from softras_cl.torch import rasterize, render

    t = torch.from_numpy
    cot = (t(grad_rgb), t(grad_alpha))
    cam, light = scene.camera, scene.sh_light

    def leaf(a):
        return t(a.copy()).requires_grad_()

    v, a, s, c = leaf(verts), leaf(albedo), leaf(screen), leaf(albedo)
    cp = {k: leaf(x) for k, x in cam_arrays.items()}
    sh = leaf(coefficients)
    leaves = [v, a, s, c, sh, *cp.values()]

    def fresh():
        for x in leaves:
            x.grad = None

    def render_fb():
        fresh()
        out = render(renderer, v, scene.faces, cam, albedo=a, light=light, camera_params=cp,
                     light_params=dict(coefficients=sh))
        torch.autograd.backward([out.rgb, out.alpha], list(cot))
        return v.grad

    def render_f():
        with torch.no_grad():
            return render(renderer, t(verts), scene.faces, cam, albedo=t(albedo), light=light)

    def raster_fb():
        fresh()
        out = rasterize(raster, s, scene.faces, colors=c)
        torch.autograd.backward([out.rgb, out.alpha], list(cot))
        return s.grad

    def raster_f():
        with torch.no_grad():
            return rasterize(raster, t(screen), scene.faces, colors=t(albedo))

    return {("render_fb", "torch"): render_fb, ("render_f", "torch"): render_f,
            ("raster_fb", "torch"): raster_fb, ("raster_f", "torch"): raster_f}


def _jax_calls(raster, renderer, scene, verts, albedo, cam_arrays, coefficients, screen,
               grad_rgb, grad_alpha) -> dict:
    import jax

    from softras_cl.jax import rasterize, render

    cam, light = scene.camera, scene.sh_light
    faces = scene.faces.astype(np.int32)
    cot = (jax.device_put(grad_rgb), jax.device_put(grad_alpha))

    def render_images(v, a, cp, sh):
        out = render(renderer, v, faces, cam, albedo=a, light=light, camera_params=cp,
                     light_params=dict(coefficients=sh))
        return out.rgb, out.alpha

    def raster_images(v, c):
        out = rasterize(raster, v, faces, colors=c)
        return out.rgb, out.alpha

    @jax.jit
    def render_fb(v, a, cp, sh, cot):
        out, vjp = jax.vjp(render_images, v, a, cp, sh)
        return out, vjp(cot)

    @jax.jit
    def raster_fb(v, c, cot):
        out, vjp = jax.vjp(raster_images, v, c)
        return out, vjp(cot)

    render_f = jax.jit(lambda v, a: render(renderer, v, faces, cam, albedo=a, light=light)[:2])
    raster_f = jax.jit(lambda v, c: rasterize(raster, v, faces, colors=c)[:2])
    v, a, s = (jax.device_put(x) for x in (verts, albedo, screen))
    cp = {k: jax.device_put(x) for k, x in cam_arrays.items()}
    sh = jax.device_put(coefficients)
    block = jax.block_until_ready
    return {("render_fb", "jax"): lambda: block(render_fb(v, a, cp, sh, cot)),
            ("render_f", "jax"): lambda: block(render_f(v, a)),
            ("raster_fb", "jax"): lambda: block(raster_fb(s, a, cot)),
            ("raster_f", "jax"): lambda: block(raster_f(s, a))}


def run_interop_benchmark(p: dict, progress=None) -> dict:
    """Time every (operation, API) of make_calls(p): one warm-up round, then p["repeats"] rounds
    in a seeded random order; medians and overheads against numpy."""
    calls = make_calls(p)
    keys = sorted(calls)
    times = {k: [] for k in keys}
    rng = random.Random(0)
    for round_ in range(p["repeats"] + 1):
        order = keys[:]
        rng.shuffle(order)
        for k in order:
            t0 = time.perf_counter()
            calls[k]()
            if round_:
                times[k].append(time.perf_counter() - t0)
        if progress is not None:
            progress.update(1)
    rows = []
    for op, label in OPERATIONS:
        base = statistics.median(times[(op, "numpy")])
        row = dict(operation=op, label=label, numpy_ms=1e3 * base)
        for api in p["apis"]:
            if api == "numpy":
                continue
            med = statistics.median(times[(op, api)])
            row[f"{api}_ms"] = 1e3 * med
            row[f"{api}_overhead"] = med / base - 1.0
        rows.append(row)
    faces = 20 * 4 ** p["subdivisions"]
    return dict(description=INTEROP_DOC, scene=dict(faces=faces, size=p["size"]),
                target_overhead=TARGET, rows=rows,
                samples_ms={f"{op}/{api}": [1e3 * x for x in ts] for (op, api), ts in times.items()})


def interop_report_text(result: dict) -> str:
    cols = [("operation", "label", "s"), ("numpy ms", "numpy_ms", ".1f")]
    for api in ("torch", "jax"):
        if any(f"{api}_ms" in r for r in result["rows"]):
            cols += [(f"{api} ms", f"{api}_ms", ".1f"), (f"{api} overhead", f"{api}_overhead", "+.1%")]
    sc = result["scene"]
    head = (f"bridge overhead against the numpy call, {sc['faces']} faces at {sc['size']}^2 "
            f"(target < {result['target_overhead']:.0%})")
    return head + "\n" + format_table(result["rows"], cols)


def run_interop(args: argparse.Namespace) -> int:
    """`softras-cl bench interop`: run, print the table (or JSON), write OUT/interop.json."""
    p = interop_plan(args)
    return run_with_progress(args, "interop", p, p["repeats"] + 1, run_interop_benchmark, interop_report_text,
                             unit="round", extras=dict(versions=_framework_versions(p["apis"])))


def _framework_versions(apis) -> dict:
    from importlib import import_module
    return {api: import_module(api).__version__ for api in apis if api != "numpy"}


def register(which) -> None:
    """Add `interop` to the `bench` subparsers `which`."""
    p = which.add_parser("interop", help="overhead of the PyTorch and JAX bridges over the numpy call",
                         description=INTEROP_DOC, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=None,
                   help=f"timed rounds after one warm-up; the median is reported (default {RENDER_MAIN['repeats']})")
    p.add_argument("--quick", action="store_true", help="tiny run for tests/CI: 1280 faces at 64^2, 1 repeat")
    add_output_options(p, "directory for interop.json (default out/bench)", run_interop, shown="the table")
