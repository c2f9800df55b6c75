"""The JAX bridge (softras_cl.jax): jax.test_util.check_grads in float64 for every differentiable
input of the rasteriser and the renderer (each input on its own), equality with the numpy API
bit for bit eagerly and under jit, the forward context cache (and its recompute fallback), the
perturbed inputs choosing the kernel variant, and clear dtype/shape/NaN errors."""
from __future__ import annotations

import numpy as np
import pytest

from bridge_scenes import cameras, raster_scene, raster_settings, render_settings
from support.sphere_scene import LIGHTS, sphere_scene

pytestmark = pytest.mark.jax

CASES = [("vertex", "none"), ("face", "none"), ("uv", "none"), ("vertex", "sh"), ("vertex", "lambert")]


@pytest.fixture(autouse=True)
def x64():
    """float64 JAX for these tests (restored afterwards)."""
    import jax
    before = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", before)


def _check_each(fn, args: dict):
    """check_grads (reverse mode, float64 central differences) for each argument on its own."""
    import jax
    from jax.test_util import check_grads

    for name in args:
        def one(x, name=name):
            return fn(**{**args, name: x})
        check_grads(one, (args[name],), order=1, modes=["rev"], eps=1e-6, atol=1e-6, rtol=1e-4)
        check_grads(jax.jit(one), (args[name],), order=1, modes=["rev"], eps=1e-6, atol=1e-6, rtol=1e-4)


def _spy(monkeypatch, obj):
    calls = []
    original = obj.forward

    def wrapped(*args, **kw):
        calls.append(tuple(kw.get("grads", ())))
        return original(*args, **kw)
    monkeypatch.setattr(obj, "forward", wrapped)
    return calls


@pytest.mark.parametrize("texture,lighting", CASES)
def test_rasterizer_check_grads_every_differentiable_input(texture, lighting):
    from softras_cl.jax import SoftRasterizer

    scene = raster_scene(texture=texture, lit=False if lighting == "none" else lighting)
    raster = SoftRasterizer(raster_settings(texture=texture, lighting=lighting))
    fixed = {k: scene[k] for k in ("faces", "uvs") if k in scene}
    args = {k: v for k, v in scene.items() if k not in fixed}
    assert len(args) == (2 if lighting == "none" else 4)
    _check_each(lambda **a: tuple(raster(**a, **fixed)), args)


RENDER_CASES = [("vertex", "sh"), ("vertex", "phong"), ("face", "lambert"), ("pixel", "sh"),
                ("pixel", "lambert"), ("none", None)]


@pytest.mark.parametrize("shading,light_name", RENDER_CASES)
def test_renderer_check_grads_every_differentiable_input(shading, light_name):
    from softras_cl.jax import Renderer

    v, f, albedo = sphere_scene()
    cams, light = cameras(), LIGHTS.get(light_name)
    renderer = Renderer(render_settings(), shading=shading)
    light_params = {f"light_{k}": np.asarray(p, float) for k, p in (light.params().items() if light else ())}
    args = dict(vertices=v, albedo=albedo, rotation=np.stack([c.rotation for c in cams]),
                translation=cams[0].translation.copy(), focal=np.stack([c.focal for c in cams]),
                **light_params)

    def fn(vertices, albedo, rotation, translation, focal, **lp):
        return tuple(renderer(vertices, f, cams, albedo=albedo, light=light,
                              camera_params=dict(rotation=rotation, translation=translation, focal=focal),
                              light_params={k[len("light_"):]: x for k, x in lp.items()}))
    _check_each(fn, args)


@pytest.mark.parametrize("texture", ["face", "uv"])
def test_renderer_check_grads_unlit_textures(texture):
    from softras_cl.jax import Renderer

    v, f, _ = sphere_scene()
    rng = np.random.default_rng(2)
    renderer = Renderer(render_settings(), shading="none")
    cam = cameras()[0]
    if texture == "face":
        args = dict(vertices=v, face_textures=rng.uniform(0, 1, (1, len(f), 2, 2, 3)))
        fn = lambda vertices, face_textures: tuple(renderer(vertices, f, cam, face_textures=face_textures))
    else:
        uvs = rng.uniform(0, 1, (len(v), 2))
        args = dict(vertices=v, texture_image=rng.uniform(0, 1, (1, 4, 5, 3)))
        fn = lambda vertices, texture_image: tuple(renderer(vertices, f, cam, texture_image=texture_image, uvs=uvs))
    _check_each(fn, args)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_equals_numpy_api_bit_for_bit_eager_and_jit(dtype):
    import jax
    import jax.numpy as jnp

    from softras_cl import SoftRasterizer as NumpyRasterizer
    from softras_cl.jax import SoftRasterizer

    s = raster_settings(dtype=dtype)
    scene = raster_scene(seed=3)
    v, c = scene["vertices"].astype(dtype), scene["colors"].astype(dtype)
    rng = np.random.default_rng(4)
    raster = SoftRasterizer(s)
    out = raster(v, scene["faces"], colors=c)
    cot = {o: rng.normal(size=getattr(out, o).shape).astype(dtype) for o in s.outputs}

    def loss(v, c):
        img = raster(v, scene["faces"], colors=c)
        return sum(jnp.sum(getattr(img, o) * cot[o]) for o in s.outputs)

    ref_raster = NumpyRasterizer(s)
    ref = ref_raster.forward(v, scene["faces"], colors=c, grads=("vertices", "colors"))
    g = ref_raster.backward(ref, **{f"grad_{o}": cot[o] for o in s.outputs})
    for o in s.outputs:
        assert getattr(out, o).dtype == dtype and np.array_equal(np.asarray(getattr(out, o)), getattr(ref, o))
    for grad_fn in (jax.grad(loss, (0, 1)), jax.jit(jax.grad(loss, (0, 1)))):
        gv, gc = grad_fn(v, c)
        assert gv.dtype == dtype and gc.dtype == dtype
        assert np.array_equal(np.asarray(gv), g["vertices"].astype(dtype))
        assert np.array_equal(np.asarray(gc), g["colors"].astype(dtype))


def test_renderer_equals_numpy_api_bit_for_bit():
    import jax
    import jax.numpy as jnp

    from softras_cl.jax import Renderer
    from softras_cl.scene.renderer import Renderer as NumpyRenderer

    v, f, albedo = sphere_scene(1)
    cams, light = cameras(), LIGHTS["sh"]
    renderer = Renderer(render_settings(), shading="vertex")

    def loss(v, a, coefficients):
        out = renderer(v, f, cams, albedo=a, light=light, light_params=dict(coefficients=coefficients))
        return jnp.sum(out.rgb) + 2 * jnp.sum(out.alpha) + 0.1 * jnp.sum(out.depth)

    gv, ga, gl = jax.jit(jax.grad(loss, (0, 1, 2)))(v, albedo, light.coefficients)
    ref_renderer = NumpyRenderer(render_settings(), shading="vertex")
    ref = ref_renderer.forward(v, f, cams, albedo=albedo, light=light, grads=("vertices", "albedo", "light"))
    g = ref_renderer.backward(ref, grad_rgb=np.ones_like(ref.rgb), grad_alpha=np.full_like(ref.alpha, 2.0),
                              grad_depth=np.full_like(ref.depth, 0.1))
    assert np.array_equal(np.asarray(renderer(v, f, cams, albedo=albedo, light=light).rgb), ref.rgb)
    assert np.array_equal(np.asarray(gv), g["vertices"])
    assert np.array_equal(np.asarray(ga), g["albedo"])
    assert np.array_equal(np.asarray(gl), g["light"]["coefficients"])


def test_perturbed_inputs_select_the_kernel_variant(monkeypatch):
    import jax
    import jax.numpy as jnp

    from softras_cl.jax import SoftRasterizer

    scene = raster_scene()
    raster = SoftRasterizer(raster_settings())
    calls = _spy(monkeypatch, raster.raster)
    loss = lambda v, c: jnp.sum(raster(v, scene["faces"], colors=c).alpha)
    jax.grad(loss, 0)(scene["vertices"], scene["colors"])
    assert calls == [("vertices",)]
    jax.jit(loss)(scene["vertices"], scene["colors"])
    assert calls[-1] == ()


def test_backward_without_its_cached_forward_recomputes_the_same_gradients(monkeypatch):
    import jax
    import jax.numpy as jnp

    import softras_cl.jax as sjax

    scene = raster_scene()
    raster = sjax.SoftRasterizer(raster_settings())
    calls = _spy(monkeypatch, raster.raster)
    loss = lambda v: jnp.sum(raster(v, scene["faces"], colors=scene["colors"]).rgb ** 2)
    cached = jax.grad(loss)(scene["vertices"])
    assert len(calls) == 1 and not sjax._CACHE
    monkeypatch.setattr(sjax, "CACHE_SIZE", 0)
    recomputed = jax.grad(loss)(scene["vertices"])
    assert len(calls) == 3                       # forward, then the backward's forward again
    assert np.array_equal(np.asarray(cached), np.asarray(recomputed))
    _, vjp = jax.vjp(lambda v: raster(v, scene["faces"], colors=scene["colors"]).rgb, scene["vertices"])
    ct = np.ones((2, 9, 11, 3))
    assert np.array_equal(np.asarray(vjp(ct)[0]), np.asarray(vjp(ct)[0]))   # a vjp called twice


def test_batched_views_under_jit():
    import jax
    import jax.numpy as jnp

    from softras_cl.jax import Renderer

    v, f, albedo = sphere_scene()
    cams = cameras()
    renderer = Renderer(render_settings(), shading="vertex")
    rot = np.stack([c.rotation for c in cams])
    loss = lambda r: jnp.sum(renderer(v, f, cams[0], albedo=albedo, camera_params=dict(rotation=r)).alpha)
    g = jax.jit(jax.grad(loss))(rot)
    assert g.shape == (2, 3)
    for b in range(2):
        one = lambda r: jnp.sum(renderer(v, f, cams[0], albedo=albedo, camera_params=dict(rotation=r)).alpha)
        np.testing.assert_allclose(np.asarray(jax.grad(one)(rot[b])), np.asarray(g[b]), rtol=1e-10, atol=1e-12)


def test_bad_inputs_name_the_argument():
    import jax

    from softras_cl.jax import SoftRasterizer

    scene = raster_scene()
    raster = SoftRasterizer(raster_settings())
    v, f, c = scene["vertices"], scene["faces"], scene["colors"]
    with pytest.raises(TypeError, match="colors must be a float32 or float64 array, got dtype float16"):
        raster(v, f, colors=c.astype(np.float16))
    with pytest.raises(TypeError, match="faces must be an integer array"):
        raster(v, f.astype(float), colors=c)
    # value checks run in the numpy API inside the callback: JAX may wrap the ValueError in its
    # own runtime error, whose message ends with the numpy one
    with pytest.raises(Exception, match=r"vertices must have shape \(B, n, 3\) or \(n, 3\)"):
        raster(v[..., :2], f, colors=c)
    bad = c.copy()
    bad[1, 2, 0] = np.nan
    with pytest.raises(Exception, match="colors contains NaN"):
        raster(v, f, colors=bad)
    with pytest.raises(Exception, match="colors contains NaN"):
        jax.jit(lambda c: raster(v, f, colors=c).rgb)(bad)
    jax.config.update("jax_enable_x64", False)
    with pytest.raises(ValueError, match="jax_enable_x64"):
        raster(v.astype(np.float32), f.astype(np.int32), colors=c.astype(np.float32))
