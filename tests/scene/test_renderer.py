"""The whole render path (camera -> normals -> lighting -> soft raster) against central finite
differences in float64: gradients of an image loss for vertices, albedo, camera and light."""
import dataclasses
import re

import numpy as np
import pytest

from softras_cl import RasterSettings
from softras_cl.scene.camera import Camera
from softras_cl.scene.meshes import icosphere
from softras_cl.scene.renderer import Renderer
from softras_cl.scene.shading import LambertLight
from support.sphere_scene import LIGHTS, sphere_scene, two_cameras

H, W = 18, 22
H_STEP = 1e-6


def cameras():
    return two_cameras((H, W))


def settings(**kw):
    base = dict(image_size=(H, W), sigma=1e-3, gamma=1e-2, dist_eps=0.0, near=0.5, far=10.0,
                outputs=("rgb", "alpha", "depth"), dtype="float64")
    return RasterSettings(**{**base, **kw})


def _loss_fn(renderer, faces, cot):
    def loss(vertices, cams, albedo, light):
        out = renderer.forward(vertices, faces, cams, albedo=albedo, light=light)
        return sum((getattr(out, k) * g).sum() for k, g in cot.items())
    return loss


def _cot(batch, seed=1):
    rng = np.random.default_rng(seed)
    return dict(rgb=rng.normal(size=(batch, H, W, 3)), alpha=rng.normal(size=(batch, H, W)),
                depth=0.1 * rng.normal(size=(batch, H, W)))


def _fd(f, x, indices):
    out = []
    for i in indices:
        xp, xm = x.copy(), x.copy()
        xp.flat[i] += H_STEP
        xm.flat[i] -= H_STEP
        out.append((f(xp) - f(xm)) / (2 * H_STEP))
    return np.array(out)


def _assert_close(analytic, numeric, what):
    scale = max(np.abs(numeric).max(), 1e-8)
    np.testing.assert_allclose(analytic, numeric, rtol=0, atol=1e-6 * scale, err_msg=what)


CASES = [(shading, light) for shading in ("vertex", "face") for light in sorted(LIGHTS)]
CASES += [("pixel", "lambert"), ("pixel", "sh")]


@pytest.mark.parametrize("shading,light_name", CASES)
def test_render_path_gradients_match_finite_differences(shading, light_name):
    v, f, albedo = sphere_scene()
    cams, light = cameras(), LIGHTS[light_name]
    renderer = Renderer(settings(), shading=shading)
    cot = _cot(len(cams))
    out = renderer.forward(v, f, cams, albedo=albedo, light=light,
                           grads=("vertices", "albedo", "camera", "light"))
    g = renderer.backward(out, grad_rgb=cot["rgb"], grad_alpha=cot["alpha"], grad_depth=cot["depth"])
    loss = _loss_fn(renderer, f, cot)
    rng = np.random.default_rng(2)

    idx = rng.choice(v.size, 24, replace=False)
    _assert_close(g["vertices"].ravel()[idx], _fd(lambda x: loss(x, cams, albedo, light), v, idx), "vertices")
    idx = rng.choice(albedo.size, 12, replace=False)
    _assert_close(g["albedo"].ravel()[idx], _fd(lambda x: loss(v, cams, x, light), albedo, idx), "albedo")

    for view in range(len(cams)):
        def with_view(**params):
            return [c.with_params(**params) if i == view else c for i, c in enumerate(cams)]
        cam = cams[view]
        for name in ("rotation", "translation"):
            num = _fd(lambda x: loss(v, with_view(**{name: x}), albedo, light), getattr(cam, name), range(3))
            _assert_close(g["camera"][view][name], num, f"camera {view} {name}")
        num = _fd(lambda x: loss(v, with_view(fx=x[0], fy=x[1]), albedo, light), cam.focal, range(2))
        _assert_close(g["camera"][view]["focal"], num, f"camera {view} focal")

    for name, value in light.params().items():
        value = np.asarray(value, np.float64)
        num = _fd(lambda x: loss(v, cams, albedo, dataclasses.replace(light, **{name: x.reshape(value.shape)})),
                  value, range(value.size))
        _assert_close(np.ravel(g["light"][name]), num, f"light {name}")


def test_unlit_uv_texture_gradients_and_single_camera_sum():
    """shading='none' with a uv texture; one Camera for a batch of two meshes sums its gradient."""
    v, f, _ = sphere_scene(4)
    rng = np.random.default_rng(5)
    uvs = rng.uniform(0, 1, (len(v), 2))
    image = rng.uniform(0, 1, (1, 6, 5, 3))
    verts = np.stack([v, v + [0.05, -0.02, 0.1]])
    cam = cameras()[0]
    renderer = Renderer(settings(), shading="none")
    cot = _cot(2, seed=6)
    out = renderer.forward(verts, f, cam, texture_image=image, uvs=uvs, grads=("vertices", "albedo", "camera"))
    g = renderer.backward(out, grad_rgb=cot["rgb"], grad_alpha=cot["alpha"], grad_depth=cot["depth"])

    def loss(vx, c, img):
        o = renderer.forward(vx, f, c, texture_image=img, uvs=uvs)
        return sum((getattr(o, k) * gk).sum() for k, gk in cot.items())

    idx = rng.choice(verts.size, 12, replace=False)
    _assert_close(g["vertices"].ravel()[idx], _fd(lambda x: loss(x, cam, image), verts, idx), "vertices")
    idx = rng.choice(image.size, 12, replace=False)
    _assert_close(g["albedo"].ravel()[idx], _fd(lambda x: loss(verts, cam, x), image, idx), "texture")
    num = _fd(lambda x: loss(verts, cam.with_params(translation=x), image), cam.translation, range(3))
    _assert_close(g["camera"]["translation"], num, "translation")


def test_only_requested_gradients_are_returned():
    v, f, albedo = sphere_scene()
    renderer = Renderer(settings(outputs=("rgb",)))
    out = renderer.forward(v, f, cameras()[0], albedo=albedo, grads=("light",))
    g = renderer.backward(out, grad_rgb=np.ones_like(out.rgb))
    assert set(g) == {"light"}
    assert set(g["light"]) == {"ambient", "directional", "direction"}
    assert out.saved.raster_out.saved.grads == ("colors",)   # no position adjoint compiled


@pytest.mark.parametrize("single", [True, False], ids=["one camera", "camera list"])
def test_focal_group_is_the_camera_groups_focal_to_the_bit(single):
    """grads=("focal",) returns camera's focal gradients (checked against finite differences
    above) and nothing else, for one Camera (summed over the batch) or a list."""
    v, f, albedo = sphere_scene()
    verts = np.stack([v, v + [0.05, -0.02, 0.1]])
    cams = cameras()[0] if single else cameras()[:2]
    cot = _cot(2, seed=8)
    renderer = Renderer(settings())
    full, focal = (renderer.forward(verts, f, cams, albedo=albedo, grads=grads) for grads in
                   (("vertices", "camera"), ("focal",)))
    want = renderer.backward(full, grad_rgb=cot["rgb"], grad_alpha=cot["alpha"])["camera"]
    got = renderer.backward(focal, grad_rgb=cot["rgb"], grad_alpha=cot["alpha"])
    assert set(got) == {"focal"} and focal.saved.raster_out.saved.grads == ("vertices", "colors")
    want = [want["focal"]] if single else [w["focal"] for w in want]
    for g, w in zip([got["focal"]] if single else got["focal"], want, strict=True):
        assert g.shape == (2,) and np.array_equal(g, w)


def test_per_call_sigma_gamma_and_depth_equal_a_renderer_of_those_settings():
    """forward(sigma=, gamma=, near=, far=) gives the images and gradients, to the bit, of a
    renderer made with those settings, and draws with the renderer's one rasteriser."""
    v, f, albedo = sphere_scene()
    run = dict(sigma=2e-4, gamma=3e-3, near=0.8, far=7.0)
    cot = _cot(1, seed=4)
    renders = []
    renderer = Renderer(settings())
    for r, kw in ((Renderer(settings(**run)), {}), (renderer, run)):
        out = r.forward(v, f, cameras()[0], albedo=albedo, grads=("vertices", "albedo"), **kw)
        g = r.backward(out, grad_rgb=cot["rgb"], grad_alpha=cot["alpha"], grad_depth=cot["depth"])
        renders.append(dict(rgb=out.rgb, alpha=out.alpha, depth=out.depth, **g))
    for name, value in renders[0].items():
        np.testing.assert_array_equal(renders[1][name], value, err_msg=name)
    renderer.forward(v, f, cameras()[0], albedo=albedo, sigma=1e-5)
    assert len(renderer._rasterizers) == 1 and renderer.settings == settings()


def test_settings_are_read_only():
    renderer = Renderer(settings())
    with pytest.raises(AttributeError):
        renderer.settings = settings(sigma=1e-4)


def test_backward_refuses_the_output_of_another_renderer():
    v, f, albedo = sphere_scene()
    other = Renderer(settings(), shading="face")
    out = other.forward(v, f, cameras()[0], albedo=albedo, grads=("vertices",))
    with pytest.raises(ValueError, match=r"^output was made by another Renderer \(shading='face'"):
        Renderer(settings()).backward(out, grad_alpha=np.ones(out.alpha.shape))


@pytest.mark.parametrize("shading", ["vertex", "face", "pixel", "none"])
@pytest.mark.parametrize("shape", [(5, 3), (3, 12, 3), (3, 42, 3), (42, 4), (42,)])
def test_albedo_of_the_wrong_shape_is_named_before_any_kernel(monkeypatch, shading, shape):
    """Before, numpy's broadcast error (or the rasteriser's, naming colors) came out."""
    from softras_cl.raster import rasterizer as raster_module

    monkeypatch.setattr(raster_module, "build_kernel", lambda *a, **k: pytest.fail("kernel built"))
    v, f = icosphere(1, radius=0.6)      # 42 vertices
    verts = np.stack([v, v + 0.01])
    with pytest.raises(ValueError, match=re.escape(f"albedo must have shape ({len(v)}, 3) or (B, {len(v)}, 3) "
                                                   f"with B = 1 or 2 (one RGB colour per vertex), got {shape}")):
        Renderer(settings(), shading=shading).forward(verts, f, cameras()[0], albedo=np.ones(shape))


def test_own_context_and_queue_reach_the_rasterizer_and_change_nothing():
    import pyopencl as cl

    from softras_cl.cl.device import select_device

    v, f, albedo = sphere_scene()
    ctx = cl.Context([select_device()])
    queue = cl.CommandQueue(ctx)
    default = Renderer(settings()).forward(v, f, cameras()[0], albedo=albedo, light=LambertLight())
    own = Renderer(settings(), context=ctx, queue=queue)
    out = own.forward(v, f, cameras()[0], albedo=albedo, light=LambertLight())
    np.testing.assert_array_equal(out.rgb, default.rgb)
    assert [(r.ctx, r.queue) for r in own._rasterizers.values()] == [(ctx, queue)]
    other = cl.CommandQueue(cl.Context([select_device()]))
    with pytest.raises(ValueError, match="queue belongs to another context"):
        Renderer(settings(), context=ctx, queue=other).forward(v, f, cameras()[0], albedo=albedo,
                                                               light=LambertLight())


def test_bad_scene_input_is_named():
    v, f, albedo = sphere_scene()
    renderer = Renderer(settings())
    with pytest.raises(ValueError, match="image_size"):
        renderer.forward(v, f, Camera.look_at((0, 0, 3), (0, 0, 0), image_size=(10, 10)), albedo=albedo)
    with pytest.raises(ValueError, match="behind the camera"):
        renderer.forward(v, f, Camera.look_at((0, 0, 0.3), (0, 0, 0), image_size=(H, W)), albedo=albedo)
    with pytest.raises(ValueError, match="albedo"):
        renderer.forward(v, f, cameras()[0])
    with pytest.raises(ValueError, match="faces"):
        renderer.forward(v, np.zeros((0, 3), int), cameras()[0], albedo=albedo)
    with pytest.raises(ValueError, match="shading"):
        Renderer(settings(), shading="per-pixel-magic")


def test_per_pixel_shading_agrees_with_per_vertex_on_a_fine_mesh():
    """On a finely tessellated sphere, lighting per pixel and per vertex give nearly the same
    image (they differ by the interpolation of a smooth function)."""
    v, f = icosphere(4, radius=0.6)
    albedo = np.full(v.shape, 0.8)
    light = LIGHTS["sh"]
    cam = cameras()[0]
    images = [Renderer(settings(outputs=("rgb",)), shading=mode).forward(v, f, cam, albedo=albedo, light=light).rgb
              for mode in ("vertex", "pixel")]
    assert np.abs(images[0] - images[1]).max() < 0.02


def test_per_pixel_shading_rejects_phong():
    v, f, albedo = sphere_scene()
    with pytest.raises(ValueError, match="light"):
        Renderer(settings(), shading="pixel").forward(v, f, cameras()[0], albedo=albedo, light=LIGHTS["phong"])


@pytest.mark.parametrize("shading", ["vertex", "face"])
def test_one_light_per_view_renders_each_view_as_its_light_alone(shading):
    """A list of B lights: each view's image and gradients are those of rendering it alone under
    its light, bit for bit; the light gradients stack the views' (B, ...); a Phong list too."""
    from softras_cl.scene.shading import PhongLight, SHLight

    v, f, albedo = sphere_scene()
    rng = np.random.default_rng(4)
    cams = cameras()
    renderer = Renderer(settings(), shading=shading)
    for lights in ([SHLight(LIGHTS["sh"].coefficients + rng.normal(scale=0.1, size=(3, 9))) for _ in cams],
                   [PhongLight(ambient=0.2 + 0.1 * b, directional=0.6, direction=(0.5, 0.8 - b, 0.7), specular=0.3,
                               shininess=5.0) for b in range(len(cams))]):
        out = renderer.forward(v, f, cams, albedo=albedo, light=lights, grads=("vertices", "light", "albedo", "camera"))
        cot = _cot(len(cams))
        g = renderer.backward(out, grad_rgb=cot["rgb"], grad_alpha=cot["alpha"])
        for b, (cam, light) in enumerate(zip(cams, lights)):
            alone = renderer.forward(v, f, [cam], albedo=albedo, light=light, grads=("vertices", "light", "albedo",
                                                                                     "camera"))
            g_alone = renderer.backward(alone, grad_rgb=cot["rgb"][b:b + 1], grad_alpha=cot["alpha"][b:b + 1])
            assert np.array_equal(out.rgb[b], alone.rgb[0])
            for name, value in g_alone["light"].items():
                assert np.array_equal(g["light"][name][b], value), name
            assert g["camera"][b].keys() == g_alone["camera"][0].keys()
            for name, value in g_alone["camera"][0].items():
                assert np.array_equal(g["camera"][b][name], value), name


def test_one_depth_range_per_view_renders_each_view_as_alone():
    """near and far lists: each view's images and camera gradients are those of rendering it
    alone with its own range, to the bit (the ranges clip the sphere differently)."""
    v, f, albedo = sphere_scene()
    cams, near, far = cameras(), [2.4, 1.8], [3.3, 2.7]
    renderer, grads, cot = Renderer(settings()), ("vertices", "albedo", "camera"), _cot(2)
    out = renderer.forward(v, f, cams, albedo=albedo, grads=grads, near=near, far=far)
    g = renderer.backward(out, grad_rgb=cot["rgb"], grad_alpha=cot["alpha"], grad_depth=cot["depth"])
    for b, cam in enumerate(cams):
        alone = renderer.forward(v, f, [cam], albedo=albedo, grads=grads, near=near[b], far=far[b])
        g_alone = renderer.backward(alone, **{f"grad_{n}": c[b:b + 1] for n, c in cot.items()})
        for name in ("rgb", "alpha", "depth"):
            assert np.array_equal(getattr(out, name)[b], getattr(alone, name)[0]), name
        for name, value in g_alone["camera"][0].items():
            assert np.array_equal(g["camera"][b][name], value), name
    shared = renderer.forward(v, f, cams, albedo=albedo, near=near[0], far=far[0])
    assert not np.array_equal(shared.depth[1], out.depth[1])


@pytest.mark.parametrize("lights, says", [
    ([], "a list of lights needs one light per view, got an empty list"),
    ([LambertLight()], "1 lights for 2 views; give one light per view"),
    ([LambertLight(), LIGHTS["sh"]], "must hold LambertLight, PhongLight or SHLight, all of one type"),
    ([LIGHTS["sh"], LIGHTS["sh"]], "shading='pixel' lights every view with one light"),
])
def test_a_list_of_lights_is_checked(lights, says):
    v, f, albedo = sphere_scene()
    shading = "pixel" if "pixel" in says else "vertex"
    with pytest.raises(ValueError, match=re.escape(says)):
        Renderer(settings(), shading=shading).forward(v, f, cameras(), albedo=albedo, light=lights)
