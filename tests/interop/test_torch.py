"""The PyTorch bridge (softras_cl.torch): gradcheck in float64 for every differentiable input of
the rasteriser and the renderer, equality with the numpy API bit for bit, requires_grad and
no_grad choosing the kernel variant, and clear errors for CUDA tensors, dtypes, shapes and NaN."""
from __future__ import annotations

import numpy as np
import pytest

from bridge_scenes import cameras, raster_scene, raster_settings, render_settings
from support.sphere_scene import LIGHTS, sphere_scene

pytestmark = pytest.mark.torch

CASES = [("vertex", "none"), ("face", "none"), ("uv", "none"), ("vertex", "sh"), ("vertex", "lambert")]


def _torch():
    import torch
    return torch


def _spy(monkeypatch, obj, attr="forward"):
    """Record the grads= of every call of obj.<attr> (a SoftRasterizer or Renderer)."""
    calls = []
    original = getattr(obj, attr)

    def wrapped(*args, **kw):
        calls.append(tuple(kw.get("grads", ())))
        return original(*args, **kw)
    monkeypatch.setattr(obj, attr, wrapped)
    return calls


@pytest.mark.slow
@pytest.mark.parametrize("texture,lighting", CASES)
def test_rasterizer_gradcheck_every_differentiable_input(texture, lighting):
    torch = _torch()
    from softras_cl.torch import SoftRasterizer

    lit = False if lighting == "none" else lighting
    scene = raster_scene(texture=texture, lit=lit)
    module = SoftRasterizer(raster_settings(texture=texture, lighting=lighting))
    names = [k for k in scene if k not in ("faces", "uvs")]
    fixed = {k: scene[k] for k in ("faces", "uvs") if k in scene}
    inputs = [torch.tensor(scene[k], requires_grad=True) for k in names]
    assert set(names) >= {"vertices"} and len(names) == (2 if lighting == "none" else 4)
    assert torch.autograd.gradcheck(lambda *a: tuple(module(**dict(zip(names, a)), **fixed)),
                                    inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


RENDER_CASES = [("vertex", "sh"), ("vertex", "phong"), ("face", "lambert"), ("pixel", "sh"),
                ("pixel", "lambert"), ("none", None)]


@pytest.mark.slow
@pytest.mark.parametrize("shading,light_name", RENDER_CASES)
def test_renderer_gradcheck_every_differentiable_input(shading, light_name):
    """vertices, albedo, per-view rotation and focal (B, k), a shared translation (3,), and every
    parameter of the light."""
    torch = _torch()
    from softras_cl.torch import Renderer

    v, f, albedo = sphere_scene()
    cams, light = cameras(), LIGHTS.get(light_name)
    module = Renderer(render_settings(), shading=shading)
    light_params = {k: np.asarray(p, float) for k, p in (light.params().items() if light else ())}
    keys = list(light_params)
    inputs = [torch.tensor(a, requires_grad=True) for a in
              (v, albedo, np.stack([c.rotation for c in cams]), cams[0].translation.copy(),
               np.stack([c.focal for c in cams]), *light_params.values())]

    def fn(vertices, alb, rotation, translation, focal, *lp):
        return tuple(module(vertices, f, cams, albedo=alb, light=light,
                            camera_params=dict(rotation=rotation, translation=translation, focal=focal),
                            light_params=dict(zip(keys, lp))))
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("texture", ["face", "uv"])
def test_renderer_gradcheck_unlit_textures(texture):
    torch = _torch()
    from softras_cl.torch import Renderer

    v, f, _ = sphere_scene()
    rng = np.random.default_rng(2)
    module = Renderer(render_settings(), shading="none")
    cam = cameras()[0]
    if texture == "face":
        tex = rng.uniform(0, 1, (1, len(f), 2, 2, 3))
        fn = lambda vv, t: tuple(module(vv, f, cam, face_textures=t))
    else:
        tex, uvs = rng.uniform(0, 1, (1, 4, 5, 3)), rng.uniform(0, 1, (len(v), 2))
        fn = lambda vv, t: tuple(module(vv, f, cam, texture_image=t, uvs=uvs))
    inputs = [torch.tensor(v, requires_grad=True), torch.tensor(tex, requires_grad=True)]
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_rasterizer_equals_numpy_api_bit_for_bit(dtype):
    torch = _torch()
    from softras_cl import SoftRasterizer as NumpyRasterizer
    from softras_cl.torch import SoftRasterizer

    s = raster_settings(dtype=dtype)
    scene = raster_scene(seed=3)
    real = getattr(torch, dtype)
    module = SoftRasterizer(s)
    v = torch.tensor(scene["vertices"], dtype=real, requires_grad=True)
    c = torch.tensor(scene["colors"], dtype=real, requires_grad=True)
    out = module(v, torch.from_numpy(scene["faces"]), colors=c)
    rng = np.random.default_rng(4)
    cot = {o: rng.normal(size=getattr(out, o).shape) for o in s.outputs}
    torch.autograd.backward([getattr(out, o) for o in s.outputs],
                            [torch.from_numpy(cot[o]).to(real) for o in s.outputs])

    raster = NumpyRasterizer(s)
    np_in = dict(vertices=scene["vertices"].astype(dtype), faces=scene["faces"], colors=scene["colors"].astype(dtype))
    ref = raster.forward(**np_in, grads=("vertices", "colors"))
    g = raster.backward(ref, **{f"grad_{o}": cot[o].astype(dtype) for o in s.outputs})
    for o in s.outputs:
        assert getattr(out, o).dtype == real and np.array_equal(getattr(out, o).detach().numpy(), getattr(ref, o))
    assert v.grad.dtype == real and c.grad.dtype == real
    assert np.array_equal(v.grad.numpy(), g["vertices"].astype(dtype))
    assert np.array_equal(c.grad.numpy(), g["colors"].astype(dtype))


def test_renderer_equals_numpy_api_bit_for_bit():
    torch = _torch()
    from softras_cl.scene.renderer import Renderer as NumpyRenderer
    from softras_cl.torch import Renderer

    v, f, albedo = sphere_scene(1)
    cams, light = cameras(), LIGHTS["sh"]
    module = Renderer(render_settings(), shading="vertex")
    tv, ta = torch.tensor(v, requires_grad=True), torch.tensor(albedo, requires_grad=True)
    coeffs = torch.tensor(light.coefficients, requires_grad=True)
    out = module(tv, f, cams, albedo=ta, light=light, light_params=dict(coefficients=coeffs))
    (out.rgb.sum() + 2 * out.alpha.sum() + 0.1 * out.depth.sum()).backward()

    renderer = NumpyRenderer(render_settings(), shading="vertex")
    ref = renderer.forward(v, f, cams, albedo=albedo, light=light, grads=("vertices", "albedo", "light"))
    g = renderer.backward(ref, grad_rgb=np.ones_like(ref.rgb), grad_alpha=np.full_like(ref.alpha, 2.0),
                          grad_depth=np.full_like(ref.depth, 0.1))
    for o in ("rgb", "alpha", "depth"):
        assert np.array_equal(getattr(out, o).detach().numpy(), getattr(ref, o))
    assert np.array_equal(tv.grad.numpy(), g["vertices"])
    assert np.array_equal(ta.grad.numpy(), g["albedo"])
    assert np.array_equal(coeffs.grad.numpy(), g["light"]["coefficients"])


def test_requires_grad_selects_the_kernel_variant(monkeypatch):
    torch = _torch()
    from softras_cl.torch import SoftRasterizer

    scene = raster_scene()
    module = SoftRasterizer(raster_settings())
    calls = _spy(monkeypatch, module.raster)
    v = torch.tensor(scene["vertices"], requires_grad=True)
    c = torch.tensor(scene["colors"])
    out = module(v, scene["faces"], colors=c)
    out.alpha.sum().backward()
    assert calls[-1] == ("vertices",) and v.grad is not None and c.grad is None
    module(v.detach(), scene["faces"], colors=c.requires_grad_()).rgb.sum().backward()
    assert calls[-1] == ("colors",) and c.grad is not None
    with torch.no_grad():
        out = module(v, scene["faces"], colors=c)
    assert calls[-1] == () and not out.rgb.requires_grad
    out = module(v.detach(), scene["faces"], colors=c.detach())
    assert calls[-1] == () and out.rgb.grad_fn is None


def test_renderer_requires_grad_selects_groups(monkeypatch):
    torch = _torch()
    from softras_cl.torch import Renderer

    v, f, albedo = sphere_scene()
    cam = cameras()[0]
    module = Renderer(render_settings(), shading="vertex")
    calls = _spy(monkeypatch, module.renderer)
    t = torch.tensor(cam.translation.copy(), requires_grad=True)
    out = module(torch.tensor(v), f, cam, albedo=albedo, camera_params=dict(translation=t))
    out.alpha.sum().backward()
    assert calls[-1] == ("camera",) and t.grad.shape == (3,)
    with torch.no_grad():
        module(torch.tensor(v), f, cam, albedo=albedo, camera_params=dict(translation=t))
    assert calls[-1] == ()


def test_batched_meshes_and_views():
    """B meshes (B, V, 3) with a list of B cameras and per-view (B, 3) rotations: gradients come
    back per mesh and per view, equal to rendering each alone."""
    torch = _torch()
    from softras_cl.torch import Renderer

    v, f, albedo = sphere_scene()
    cams = cameras()
    module = Renderer(render_settings(), shading="vertex")
    batch_v = torch.tensor(np.stack([v, v * 1.1]), requires_grad=True)
    rot = torch.tensor(np.stack([c.rotation for c in cams]), requires_grad=True)
    out = module(batch_v, f, cams, albedo=albedo, camera_params=dict(rotation=rot))
    out.rgb.sum().backward()
    assert out.rgb.shape == (2, 9, 11, 3) and batch_v.grad.shape == (2, len(v), 3) and rot.grad.shape == (2, 3)
    for b in range(2):
        vb = torch.tensor(batch_v.detach().numpy()[b], requires_grad=True)
        rb = torch.tensor(cams[b].rotation.copy(), requires_grad=True)
        one = module(vb, f, cams[b], albedo=albedo, camera_params=dict(rotation=rb))
        one.rgb.sum().backward()
        assert torch.equal(one.rgb[0], out.rgb[b])
        np.testing.assert_allclose(vb.grad.numpy(), batch_v.grad.numpy()[b], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(rb.grad.numpy(), rot.grad.numpy()[b], rtol=1e-10, atol=1e-12)


def test_inputs_share_memory_with_numpy(monkeypatch):
    """The numpy API sees the tensor's own memory (no copy on the way in)."""
    torch = _torch()
    from softras_cl.torch import SoftRasterizer

    scene = raster_scene()
    module = SoftRasterizer(raster_settings())
    seen = {}
    original = module.raster.forward

    def spy(vertices, faces, **kw):
        seen["vertices"] = vertices
        return original(vertices, faces, **kw)
    monkeypatch.setattr(module.raster, "forward", spy)
    v = torch.tensor(scene["vertices"], requires_grad=True)
    module(v, scene["faces"], colors=scene["colors"])
    assert np.shares_memory(seen["vertices"], v.detach().numpy())


def test_bad_inputs_name_the_argument(monkeypatch):
    torch = _torch()
    from softras_cl.torch import Renderer, SoftRasterizer

    scene = raster_scene()
    module = SoftRasterizer(raster_settings())
    kernels = _spy(monkeypatch, module.raster, "_run_forward")
    v, c, f = (torch.tensor(scene[k]) for k in ("vertices", "colors", "faces"))
    with pytest.raises(ValueError, match=r"vertices is a tensor on meta.*vertices\.cpu\(\)"):
        module(torch.empty(v.shape, dtype=torch.float64, device="meta"), f, colors=c)
    with pytest.raises(TypeError, match="colors must be a float32 or float64 tensor, got torch.float16"):
        module(v, f, colors=c.half())
    with pytest.raises(TypeError, match="faces must be an integer tensor"):
        module(v, f.double(), colors=c)
    with pytest.raises(ValueError, match=r"vertices must have shape"):
        module(v[..., :2], f, colors=c)
    bad = c.clone()
    bad[0, 1, 2] = float("nan")
    with pytest.raises(ValueError, match="colors contains NaN"):
        module(v.requires_grad_(), f, colors=bad)
    assert kernels == []                  # no kernel ran for any of them
    renderer = Renderer(render_settings())
    rv, rf, ra = sphere_scene()
    with pytest.raises(ValueError, match=r"camera_params\['focal'\] must have shape \(2,\) or \(N, 2\)"):
        renderer(torch.tensor(rv), rf, cameras()[0], albedo=ra,
                 camera_params=dict(focal=torch.ones(3, dtype=torch.float64, requires_grad=True)))
    with pytest.raises(ValueError, match="light_params has keys \\['shininess'\\]"):
        renderer(torch.tensor(rv), rf, cameras()[0], albedo=ra, light=LIGHTS["lambert"],
                 light_params=dict(shininess=torch.tensor(2.0, requires_grad=True)))


@pytest.mark.jax
def test_bench_interop_quick_runs_every_bridge(tmp_path):
    """`softras-cl bench interop --quick` times all four operations through numpy, torch and
    JAX and writes its JSON with provenance."""
    import json

    from softras_cl.cli import main

    assert main(["bench", "interop", "--quick", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "interop.json").read_text())
    assert [r["operation"] for r in result["rows"]] == ["render_fb", "render_f", "raster_fb", "raster_f"]
    for row in result["rows"]:
        assert row["numpy_ms"] > 0 and row["torch_ms"] > 0 and row["jax_ms"] > 0
        assert row["torch_overhead"] == pytest.approx(row["torch_ms"] / row["numpy_ms"] - 1)
    assert "provenance" in result and set(result["versions"]) == {"torch", "jax"}


@pytest.mark.parametrize("which", ["rasterize", "render"])
def test_double_backward_is_refused_naming_the_function(which):
    """create_graph=True gives the first-order gradients unchanged; differentiating them again
    raises InputError naming the bridge's function (before: torch's generic error)."""
    torch = _torch()
    from softras_cl.errors import InputError
    from softras_cl.torch import Renderer, SoftRasterizer

    if which == "rasterize":
        scene = raster_scene(2)
        module, vertices = SoftRasterizer(raster_settings()), scene["vertices"]
        arguments = dict(faces=scene["faces"], colors=scene["colors"])
    else:
        vertices, f, albedo = sphere_scene(2)
        module = Renderer(render_settings(), shading="vertex")
        arguments = dict(faces=f, cameras=cameras(), albedo=albedo, light=LIGHTS["sh"])
    v = torch.tensor(vertices, requires_grad=True)

    def loss():
        images = module(v, **arguments)
        return (images.rgb ** 2).sum() + images.alpha.sum()

    plain, = torch.autograd.grad(loss(), v)
    first, = torch.autograd.grad(loss(), v, create_graph=True)
    assert torch.equal(first.detach(), plain) and first.requires_grad
    with pytest.raises(InputError, match=rf"^softras_cl\.torch\.{which}: double backward is not supported"):
        torch.autograd.grad((first ** 2).sum(), v)
    with pytest.raises(InputError, match=rf"^softras_cl\.torch\.{which}: double backward"):
        (first ** 2).sum().backward()
