"""The GPU work layout of the kernels (RasterSettings.layout="gpu": one pixel per work-item, tiles
staged in local memory) against the CPU layout, on PoCL: the same images up to rounding, the same
gradients up to the grouping of their sums, tiles with more faces than one local-memory chunk,
extreme settings, the layout's choice by device type, and the uv-gradient fallback for devices
without 64-bit integer atomics. Both layouts against the float64 reference and finite
differences, and their bit-identical reruns: tests/raster/test_raster.py."""
from types import SimpleNamespace

import numpy as np
import pyopencl as cl
import pytest

from softras_cl import RasterSettings, SoftRasterizer
from softras_cl.cl.device import kernel_layout
from softras_cl.cl.layout import GPU_BWD_GROUP, GPU_CHUNK, GPU_TILE_W, TILE_H
from softras_cl.raster import rasterizer, reference
from tests.raster.test_raster import VARIANTS, _cotangents, _ids, random_scene, settings

LIT = [dict(lighting="lambert"), dict(lighting="sh")]
# float32's own rounding relative to the largest value, images and gradients: each layout stays
# within it of float64 (test_float32_rounding_is_bounded_in_each_layout; on PoCL up to 2.3e-5 of
# the images and 3.5e-5 of the gradients, with the barycentric metric, whose distance divides by
# the face's area and whose sigmoid(d / sigma) magnifies that rounding by up to 1 / (4 sigma))
F32_ROUNDING = 1e-4
# layout against layout, (images, gradients) relative to the largest value: the per-pixel maths
# is the same, but compilers round scalar and vector code differently (fused multiply-adds: on
# PoCL the float32 images agreed within 2e-7, on NVIDIA's OpenCL within 2.5e-5), and the gradient
# sums group the same terms by pixel instead of by lane. In float32: two float32 roundings.
TOLERANCE = {"float64": (1e-13, 1e-11), "float32": (2 * F32_ROUNDING, 2 * F32_ROUNDING)}


def _inputs(s, seed, **scene):
    vertices, faces, colors = random_scene(seed, texture=s.texture, **scene)
    colors = colors if "rgb" in s.outputs else {}
    if s.lighting != "none":
        rng = np.random.default_rng(seed)
        colors = dict(colors, normals=rng.normal(size=vertices.shape), light=rng.uniform(0, 1, 27))
    return vertices, faces, colors


def _render(s, vertices, faces, colors, cot):
    """(images, gradients) of one forward and backward with settings s."""
    raster = SoftRasterizer(s)
    grads = ("vertices", "colors") if "rgb" in s.outputs else ("vertices",)
    out = raster.forward(vertices, faces, grads=grads, **colors)
    return {n: getattr(out, n) for n in s.outputs}, raster.backward(out, **cot)


def _assert_close(got: dict, want: dict, rtol: float):
    for k, w in want.items():
        np.testing.assert_allclose(got[k], w, rtol=0, atol=rtol * max(np.abs(w).max(), 1e-30), err_msg=k)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("variant", VARIANTS + LIT, ids=_ids(VARIANTS + LIT))
def test_gpu_layout_agrees_with_cpu_layout(variant, dtype):
    s = settings(dtype=dtype, dist_eps=1e-4, **variant)
    vertices, faces, colors = _inputs(s, 21)
    cot = _cotangents(s, 22)
    cpu_images, cpu_grads = _render(s.replace(layout="cpu"), vertices, faces, colors, cot)
    gpu_images, gpu_grads = _render(s.replace(layout="gpu"), vertices, faces, colors, cot)
    image_tol, grad_tol = TOLERANCE[dtype]
    _assert_close(gpu_images, cpu_images, image_tol)
    assert set(gpu_grads) == set(cpu_grads)
    _assert_close(gpu_grads, cpu_grads, grad_tol)
    assert np.abs(cpu_grads["vertices"]).max() > 1e-3          # the scene has gradients


@pytest.mark.parametrize("layout", ["cpu", "gpu"])
@pytest.mark.parametrize("variant", VARIANTS + LIT, ids=_ids(VARIANTS + LIT))
def test_float32_rounding_is_bounded_in_each_layout(variant, layout):
    s = settings(dtype="float64", dist_eps=1e-4, layout=layout, **variant)
    vertices, faces, colors = _inputs(s, 21)
    cot = _cotangents(s, 22)
    images64, grads64 = _render(s, vertices, faces, colors, cot)
    images32, grads32 = _render(s.replace(dtype="float32"), vertices, faces, colors, cot)
    _assert_close(images32, images64, F32_ROUNDING)
    _assert_close(grads32, grads64, F32_ROUNDING)


def test_tiles_with_more_faces_than_a_chunk():
    """Over GPU_CHUNK faces cover one tile: the forward stages them in several chunks, and the
    backward's GPU_BWD_GROUP work-items each take several of the tile's entries; both layouts and
    the float64 reference agree."""
    n = 3 * GPU_CHUNK + 5
    rng = np.random.default_rng(5)
    centre = rng.uniform(-0.2, 0.2, (n, 1, 2))
    xy = centre + rng.uniform(-0.3, 0.3, (n, 3, 2))
    z = rng.uniform(2.0, 4.0, (n, 3, 1))
    vertices = np.concatenate([xy, z], -1).reshape(1, 3 * n, 3)
    faces = np.arange(3 * n).reshape(n, 3)
    colors = dict(colors=rng.uniform(0, 1, (1, 3 * n, 3)))
    s = settings(image_size=(2 * TILE_H, 2 * GPU_TILE_W), dist_eps=1e-4, sigma=1e-3)
    raster = SoftRasterizer(s.replace(layout="gpu"))
    out = raster.forward(vertices, faces, grads=("vertices", "colors"), **colors)
    counts = np.diff(out.saved.bins.tile_start)
    assert counts.max() > 2 * GPU_CHUNK and counts.max() > 4 * GPU_BWD_GROUP
    ref = reference.soft_rasterize(vertices, faces, s, **colors)
    for name in s.outputs:
        np.testing.assert_allclose(getattr(out, name), ref[name], rtol=1e-9, atol=1e-9, err_msg=name)
    rng = np.random.default_rng(6)
    cot = {f"grad_{n}": rng.normal(size=getattr(out, n).shape) for n in s.outputs}
    _, cpu_grads = _render(s.replace(layout="cpu"), vertices, faces, colors, cot)
    _assert_close(raster.backward(out, **cot), cpu_grads, TOLERANCE["float64"][1])


@pytest.mark.parametrize("layout", ["cpu", "gpu"])
def test_uv_gradients_without_int64_atomics_are_the_same(layout, monkeypatch):
    """Devices without cl_khr_int64_base_atomics add the uv texel gradients as pairs of 32-bit
    words: the 64-bit fixed-point sums, and so the gradients, keep every bit."""
    s = settings(texture="uv", dtype="float32", dist_eps=1e-4, layout=layout)
    vertices, faces, colors = _inputs(s, 9)
    cot = _cotangents(s, 10)
    with_atomics = _render(s, vertices, faces, colors, cot)[1]["colors"]
    monkeypatch.setattr(rasterizer, "has_int64_atomics", lambda device: False)
    without = _render(s, vertices, faces, colors, cot)[1]["colors"]
    assert np.abs(with_atomics).max() > 0
    assert np.array_equal(without, with_atomics)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("extreme", [dict(sigma=1e-7, gamma=1e-8), dict(sigma=10.0, gamma=10.0),
                                     dict(near=1e-6, far=1e6), dict(dist_eps=0.0, sigma=1e-7)],
                         ids=["sharp", "blurred", "depth_range", "no_cutoff"])
def test_extreme_settings_stay_finite(extreme, dtype):
    s = settings(dtype=dtype, layout="gpu", **extreme)
    vertices, faces, colors = _inputs(s, 11)
    vertices = vertices * [1.0, 1.0, 1e5 if "near" in extreme else 1.0]       # depths up to 4e5
    images, grads = _render(s, vertices, faces, colors, _cotangents(s, 12))
    for name, a in {**images, **grads}.items():
        assert np.isfinite(a).all(), name


def test_layout_is_chosen_by_device_type():
    gpu = SimpleNamespace(type=cl.device_type.GPU)
    accelerator = SimpleNamespace(type=cl.device_type.ACCELERATOR)
    cpu = SimpleNamespace(type=cl.device_type.CPU)
    every = SimpleNamespace(type=cl.device_type.ALL)     # Oclgrind's simulator says it is all of them
    assert [kernel_layout(d, "auto") for d in (gpu, accelerator, cpu, every)] == ["gpu", "gpu", "cpu", "cpu"]
    assert kernel_layout(gpu, "cpu") == "cpu" and kernel_layout(cpu, "gpu") == "gpu"


def test_auto_layout_is_the_device_types_layout():
    """The default runs the CPU layout on a device that is a CPU (PoCL: the CPU kernels and their
    bits), the GPU layout on a GPU, bit for bit as if that layout were asked for."""
    s = settings(dtype="float32")
    auto = SoftRasterizer(s)
    expected = "cpu" if auto.device.type & cl.device_type.CPU else "gpu"
    chosen = SoftRasterizer(s.replace(layout=expected))
    assert auto.layout == expected and auto.lanes == chosen.lanes
    vertices, faces, colors = random_scene(13)
    a, b = auto.forward(vertices, faces, **colors), chosen.forward(vertices, faces, **colors)
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.alpha, b.alpha)


def test_gpu_layout_tiles():
    raster = SoftRasterizer(settings(layout="gpu", image_size=(13, 18)))
    assert (raster.layout, raster.lanes, raster.grid.tile_w) == ("gpu", 1, GPU_TILE_W)
    assert (raster.grid.wp, raster.grid.hp) == (2 * GPU_TILE_W, 2 * TILE_H)


def test_bad_layout_is_refused():
    with pytest.raises(ValueError, match=r"layout must be one of \('auto', 'cpu', 'gpu'\), got 'cuda'"):
        RasterSettings(layout="cuda")
    with pytest.raises(ValueError, match="lanes applies to layout 'cpu' only"):
        SoftRasterizer(settings(dtype="float32", layout="gpu"), lanes=8)


def test_too_little_local_memory_is_refused():
    small = SimpleNamespace(name="tiny", local_mem_size=4096)
    with pytest.raises(ValueError, match=r"layout='gpu' needs \d+ bytes of local memory.*'tiny' has 4096"):
        rasterizer._check_local_memory(small, 8)
    rasterizer._check_local_memory(SimpleNamespace(name="gpu", local_mem_size=48 * 1024), 8)


def test_renderer_honours_the_layout():
    """The Renderer's rasterisers take the layout from its settings: both layouts give the same
    render and gradients, up to rounding."""
    from softras_cl.scene.camera import Camera
    from softras_cl.scene.meshes import icosphere
    from softras_cl.scene.renderer import Renderer
    from softras_cl.scene.shading import LambertLight

    v, f = icosphere(1, radius=0.6)
    size = (20, 24)
    camera = Camera.look_at((0.4, 0.5, 3.0), (0.0, 0.0, 0.0), fov_deg=35, image_size=size)
    light = LambertLight(ambient=(0.3, 0.4, 0.5), directional=(0.6, 0.5, 0.4), direction=(0.3, 1.0, 0.6))
    albedo = np.random.default_rng(3).uniform(0.2, 0.9, v.shape)
    results = {}
    for layout in ("cpu", "gpu"):
        s = RasterSettings(image_size=size, sigma=1e-3, gamma=1e-2, near=0.5, far=10.0,
                           outputs=("rgb", "alpha"), dtype="float64", layout=layout)
        renderer = Renderer(s, shading="pixel")
        out = renderer.forward(v, f, camera, grads=("vertices", "albedo"), albedo=albedo, light=light)
        grads = renderer.backward(out, grad_rgb=np.cos(out.rgb), grad_alpha=np.sin(out.alpha))
        assert {r.layout for r in renderer._rasterizers.values()} == {layout}
        results[layout] = ({"rgb": out.rgb, "alpha": out.alpha}, grads)
    _assert_close(results["gpu"][0], results["cpu"][0], TOLERANCE["float64"][0])
    _assert_close(results["gpu"][1], results["cpu"][1], TOLERANCE["float64"][1])
