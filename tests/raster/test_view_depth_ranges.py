"""One depth range per view: near and far given as one value per view of a batch. Each view of
the batch renders as it does alone with its own range (images and gradients to the bit, on the
numpy and the device-resident path, both kernel layouts, host and device face set-up), the
kernels match the float64 reference, and bad ranges are refused before any kernel runs."""
import numpy as np
import pyopencl.array as cla
import pytest

from softras_cl import RasterSettings, SoftRasterizer
from softras_cl.cl.device import has_fp64
from softras_cl.raster import reference

from test_raster import LAYOUTS, random_scene, settings

# the scene's depths lie in 2..4: each range below clips some of its faces, and no two views
# of a batch share one (so that a kernel reading another view's range changes the images)
NEAR = (1.0, 2.6, 2.2)
FAR = (10.0, 3.6, 3.1)
GRADS = ("vertices", "colors")
VARIANTS = [dict(), dict(color_agg="hard", alpha_agg="hard"), dict(texture="uv", perspective_correct=False)]


def _ids(variants):
    return [",".join(f"{k}={v}" for k, v in d.items()) or "default" for d in variants]


def _scene(variant: dict, layout: str, seed: int = 3):
    """(settings (float64), vertices (3, V, 3), faces, colour inputs by name) of a 3-view scene."""
    s = settings(layout=layout, **variant)
    vertices, faces, colors = random_scene(seed, batch=len(NEAR), texture=s.texture)
    return s, vertices, faces, colors


def _view(arrays: dict, k: int) -> dict:
    """View k of batched inputs as a batch of one (faces (F, 3) are shared)."""
    return {n: a if n == "faces" else a[k:k + 1] for n, a in arrays.items()}


def _render(raster, inputs: dict, near, far, views=None, cotangent_seed: int = 5):
    """(images by name, gradients by name) of a forward with GRADS and a backward of random
    cotangents: one fixed draw per view, view k of the scene (``views``: the scene's views
    given, default all) getting the same draw alone as in the batch."""
    out = raster.forward(**inputs, grads=GRADS, near=near, far=far)
    images = {n: getattr(out, n) for n in raster.settings.outputs}
    if any(isinstance(a, cla.Array) for a in images.values()):
        images = {n: a.get() for n, a in images.items()}
    cot = {}
    for n, image in images.items():
        draws = [np.random.default_rng((cotangent_seed, k)).normal(size=image.shape[1:])
                 for k in (range(len(image)) if views is None else views)]
        cot[f"grad_{n}"] = np.stack(draws)
    grads = raster.backward(out, **cot)
    return images, {n: g.get() if isinstance(g, cla.Array) else g for n, g in grads.items()}


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("variant", VARIANTS, ids=_ids(VARIANTS))
def test_each_view_renders_as_alone_with_its_own_range(variant, layout):
    s, vertices, faces, colors = _scene(variant, layout)
    inputs = dict(vertices=vertices, faces=faces, **colors)
    raster = SoftRasterizer(s)
    images, grads = _render(raster, inputs, NEAR, FAR)
    for k in range(len(NEAR)):
        alone_images, alone_grads = _render(SoftRasterizer(s), _view(inputs, k), NEAR[k], FAR[k], views=[k])
        for n, image in alone_images.items():
            assert images[n][k:k + 1].tobytes() == image.tobytes(), (n, k)
        for n, g in alone_grads.items():
            assert grads[n][k:k + 1].tobytes() == g.tobytes(), (n, k)
    # the ranges matter: the views drawn with the first view's range differ
    shared, _ = _render(SoftRasterizer(s), inputs, NEAR[0], FAR[0])
    name = "depth" if "depth" in s.outputs else s.outputs[0]
    assert all(not np.array_equal(shared[name][k], images[name][k]) for k in (1, 2))


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("variant", VARIANTS, ids=_ids(VARIANTS))
def test_per_view_ranges_match_the_reference_float64(variant, layout):
    s, vertices, faces, colors = _scene(variant, layout)
    out = SoftRasterizer(s).forward(vertices, faces, **colors, near=NEAR, far=FAR)
    ref = reference.soft_rasterize(vertices, faces, s.replace(near=NEAR, far=FAR), **colors)
    for name in s.outputs:
        want = ref[name]
        np.testing.assert_allclose(getattr(out, name), want, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(want).max()),
                                   err_msg=name)


def test_reference_views_are_the_views_alone():
    """The reference itself: view k of a per-view render is view k rendered with its range."""
    s, vertices, faces, colors = _scene({}, "cpu")
    batched = reference.soft_rasterize(vertices, faces, s.replace(near=NEAR, far=FAR), **colors)
    for k in range(len(NEAR)):
        alone = reference.soft_rasterize(vertices[k:k + 1], faces, s.replace(near=NEAR[k], far=FAR[k]),
                                         **_view(colors, k))
        for name in s.outputs:
            np.testing.assert_array_equal(batched[name][k:k + 1], alone[name], err_msg=name)


def test_device_setup_and_device_inputs_give_the_host_bits():
    """The device face set-up (forced on a small mesh) and device-resident inputs read each
    view's range as the host set-up does."""
    s, vertices, faces, colors = _scene({}, "cpu")
    inputs = dict(vertices=vertices, faces=faces, **colors)
    host = SoftRasterizer(s)
    host.device_setup_faces = 10 ** 9
    want_images, want_grads = _render(host, inputs, NEAR, FAR)
    on_device = SoftRasterizer(s)
    if not has_fp64(on_device.device):
        pytest.skip("device without cl_khr_fp64: the host set-up runs")
    on_device.device_setup_faces = 0
    device_inputs = {n: cla.to_device(on_device.queue, np.ascontiguousarray(a)) for n, a in inputs.items()}
    for raster, args in ((on_device, inputs), (SoftRasterizer(s), device_inputs)):
        images, grads = _render(raster, args, np.array(NEAR), list(FAR))
        for n, image in want_images.items():
            assert images[n].tobytes() == image.tobytes(), n
        for n, g in want_grads.items():
            assert grads[n].tobytes() == g.tobytes(), n


def test_float32_per_view_ranges_within_the_float32_tolerance():
    """float32 kernels with per-view ranges against the float64 reference, within the 1e-4
    that test_raster states for gamma 3e-2."""
    s, vertices, faces, colors = _scene({"dtype": "float32"}, "cpu")
    out = SoftRasterizer(s).forward(vertices, faces, **colors, near=NEAR, far=FAR)
    ref = reference.soft_rasterize(vertices, faces, s.replace(near=NEAR, far=FAR), **colors)
    np.testing.assert_allclose(out.rgb, ref["rgb"], atol=1e-4)
    np.testing.assert_allclose(out.depth, ref["depth"], rtol=1e-4)


@pytest.mark.parametrize("near, far, message", [
    ((1.0, 2.0), 10.0, r"near holds 2 values \(one per view\), but the batch has 3 views"),
    (1.0, (5.0, 6.0, 7.0, 8.0), r"far holds 4 values \(one per view\), but the batch has 3 views"),
    ((1.0, 2.0, 3.0), (5.0, 6.0), "near and far must give one value per view each: 3 near, 2 far"),
    ((1.0, 4.0, 1.0), (5.0, 3.0, 5.0), r"far\[1\] must be finite and > near\[1\] \(4.0\), got 3.0"),
    ((1.0, -1.0, 1.0), 5.0, r"near\[1\] must be a finite number > 0, got -1.0"),
    ((1.0, 1.0, 1.0), (5.0, np.inf, 5.0), r"far\[1\] must be finite"),
    ([], 5.0, "near must be a number, or one number per view"),
    (np.ones((3, 1)), 5.0, "near must be a number, or one number per view"),
])
def test_bad_per_view_ranges_are_refused_before_any_kernel(near, far, message):
    s, vertices, faces, colors = _scene({}, "cpu")
    raster = SoftRasterizer(s)
    with pytest.raises(ValueError, match=message):
        raster.forward(vertices, faces, **colors, near=near, far=far)
    assert raster._kernels == {}


def test_settings_hold_per_view_ranges_as_tuples():
    s = RasterSettings(near=np.array([0.5, 1.0]), far=[4, 5])
    assert s.near == (0.5, 1.0) and s.far == (4.0, 5.0)
    assert hash(s) == hash(RasterSettings(near=(0.5, 1.0), far=(4.0, 5.0)))
    np.testing.assert_array_equal(s.depth_ranges(2), [[0.5, 4.0], [1.0, 5.0]])
    np.testing.assert_array_equal(RasterSettings(near=0.5, far=(2.0, 3.0)).depth_ranges(2), [[0.5, 2.0], [0.5, 3.0]])
    np.testing.assert_array_equal(RasterSettings(near=0.5, far=2.0).depth_ranges(3), [[0.5, 2.0]] * 3)
