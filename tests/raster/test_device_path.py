"""The device-resident rasteriser path (pyopencl arrays in, pyopencl arrays out) against the numpy
path: every image and gradient bit-identical, in float32 and float64, both kernel layouts, every
texture mode and output the numpy tests cover; the device input checks raise the numpy path's
errors."""
import numpy as np
import pyopencl.array as cla
import pytest

from softras_cl import SoftRasterizer
from softras_cl.scene.meshes import screen_space_sphere

from test_raster import VARIANTS, _ids, random_scene, settings

LIT = [dict(lighting="lambert"), dict(lighting="sh", texture="vertex")]


def scene_inputs(s, seed):
    """(vertices, faces, colour inputs by name) of random_scene for the settings s."""
    vertices, faces, colors = random_scene(seed, texture=s.texture)
    if s.lighting != "none":
        rng = np.random.default_rng(seed)
        normals = rng.normal(size=vertices.shape)
        colors = dict(colors, normals=normals / np.linalg.norm(normals, axis=-1, keepdims=True),
                      light=rng.uniform(-0.3, 0.6, 27))
    return vertices, faces, colors if "rgb" in s.outputs else {}


def to_device(raster, arrays: dict, dtype=None) -> dict:
    return {n: None if a is None else cla.to_device(raster.queue, np.ascontiguousarray(a if dtype is None or n == "faces"
                                                                                       else a.astype(dtype)))
            for n, a in arrays.items()}


def cotangents(s, out, seed=4):
    rng = np.random.default_rng(seed)
    return {f"grad_{n}": rng.normal(size=getattr(out, n).shape) for n in s.outputs}


def both_paths(s, vertices, faces, colors, grads, roi=None, input_dtype=None):
    """(numpy path's images and gradients, the device path's downloaded) of one scene."""
    results = []
    for device in (False, True):
        raster = SoftRasterizer(s)
        inputs = dict(vertices=vertices, faces=faces, **colors)
        if input_dtype is not None:
            inputs = {n: a if n == "faces" else np.asarray(a, input_dtype) for n, a in inputs.items()}
        if device:
            inputs = to_device(raster, inputs)
        out = raster.forward(**inputs, grads=grads, roi=roi)
        images = {n: getattr(out, n) for n in s.outputs}
        cot = cotangents(s, out)
        if device:
            assert all(isinstance(a, cla.Array) for a in images.values())
            images = {n: a.get() for n, a in images.items()}
            cot = to_device(raster, cot)
        g = raster.backward(out, **cot) if grads else {}
        if device:
            assert all(isinstance(a, cla.Array) for a in g.values())
            g = {n: a.get() for n, a in g.items()}
        results.append((images, g))
    return results


def assert_bit_identical(numpy_path, device_path):
    (images, grads), (d_images, d_grads) = numpy_path, device_path
    assert images.keys() == d_images.keys() and grads.keys() == d_grads.keys()
    for name in images:
        assert images[name].dtype == d_images[name].dtype and images[name].shape == d_images[name].shape, name
        assert images[name].tobytes() == d_images[name].tobytes(), name
    for name in grads:
        assert grads[name].dtype == d_grads[name].dtype and grads[name].shape == d_grads[name].shape, name
        assert np.array_equal(grads[name], d_grads[name]), (name, np.abs(grads[name] - d_grads[name]).max())


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("variant", VARIANTS + LIT, ids=_ids(VARIANTS + LIT))
def test_device_path_equals_numpy_path(variant, dtype):
    s = settings(dtype=dtype, layout="cpu", **variant)
    vertices, faces, colors = scene_inputs(s, 5)
    grads = ("vertices", "colors") if "rgb" in s.outputs else ("vertices",)
    numpy_path, device_path = both_paths(s, vertices, faces, colors, grads)
    assert numpy_path[0][s.outputs[0]].std() > 0.01
    assert_bit_identical(numpy_path, numpy_via_device_path(s, vertices, faces, colors, grads))   # a GPU's numpy call
    assert_bit_identical(numpy_path, device_path)


@pytest.mark.parametrize("variant", [dict(), dict(texture="uv"), dict(texture="face"), dict(lighting="sh")],
                         ids=["vertex", "uv", "face", "sh"])
def test_device_path_equals_numpy_path_in_the_gpu_layout(variant):
    s = settings(dtype="float32", layout="gpu", **variant)
    vertices, faces, colors = scene_inputs(s, 6)
    assert_bit_identical(*both_paths(s, vertices, faces, colors, ("vertices", "colors")))


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_device_path_on_a_sphere_with_a_region_of_interest_and_float32_inputs(dtype):
    """Over DEVICE_SETUP_FACES faces (the numpy path's set-up runs on the device too), unbatched
    inputs, float32 input arrays, a region of interest, and forward without gradients."""
    vertices, faces, colors = screen_space_sphere(4)
    s = settings(dtype=dtype, image_size=(64, 80), sigma=1e-4, gamma=1e-3, dist_eps=1e-4)
    roi = np.zeros((64, 80), bool)
    roi[10:30, 20:50] = True
    for kw in (dict(), dict(roi=roi), dict(input_dtype=np.float32)):
        assert_bit_identical(*both_paths(s, vertices, faces, dict(colors=colors), ("vertices", "colors"), **kw))
    assert_bit_identical(*both_paths(s, vertices, faces, dict(colors=colors), ()))


def test_shared_colours_and_faces_of_a_batch():
    """Colours of batch 1 shared by a batch of 2, (B, F, 3) faces: gradients summed as numpy does."""
    s = settings()
    vertices, faces, colors = random_scene(8)
    colors = dict(colors=colors["colors"][:1])
    assert_bit_identical(*both_paths(s, vertices, np.stack([faces, faces[::-1]]), colors, ("vertices", "colors")))
    assert_bit_identical(*both_paths(s, vertices, faces, dict(colors=colors["colors"][0]), ("vertices", "colors")))


def test_device_arrays_of_another_context_are_refused():
    import pyopencl as cl

    s = settings(outputs=("alpha",))
    raster = SoftRasterizer(s)
    other = cl.CommandQueue(cl.Context([raster.device]))
    vertices, faces, _ = random_scene(1)
    with pytest.raises(ValueError, match="^faces is a pyopencl array of another OpenCL context"):
        raster.forward(cla.to_device(raster.queue, vertices), cla.to_device(other, faces))


CHECKS = [
    ("vertices", lambda a: a.__setitem__((1, 3, 2), np.nan), "vertices contains NaN or Inf"),
    ("vertices", lambda a: a.__setitem__((0, 2, 0), 1e30), "vertices has values up to"),
    ("faces", lambda a: a.__setitem__((4, 1), 12), "faces must index vertices in"),
    ("faces", lambda a: a.__setitem__((4, 1), -1), "faces must index vertices in"),
    ("colors", lambda a: a.__setitem__((1, 0, 0), -np.inf), "colors contains NaN or Inf"),
]


@pytest.mark.parametrize("name, spoil, message", CHECKS, ids=[c[2].split(" ", 2)[-1] for c in CHECKS])
def test_device_input_checks_raise_the_numpy_paths_errors(name, spoil, message):
    s = settings(dtype="float32")
    vertices, faces, colors = random_scene(2)
    inputs = dict(vertices=vertices, faces=faces, **colors)
    spoil(inputs[name])
    raster = SoftRasterizer(s)
    with pytest.raises(ValueError) as numpy_error:
        raster.forward(**inputs)
    assert str(numpy_error.value).startswith(message)
    with pytest.raises(ValueError) as device_error:
        raster.forward(**to_device(raster, inputs))
    assert str(device_error.value) == str(numpy_error.value)


def test_device_shape_and_dtype_errors_and_cotangent_checks_are_the_numpy_paths():
    s = settings()
    vertices, faces, colors = random_scene(2)
    raster = SoftRasterizer(s)
    for bad in (dict(vertices=vertices[..., :2]), dict(faces=faces.astype(np.float64)),
                dict(colors=colors["colors"][:, :5])):
        inputs = {**dict(vertices=vertices, faces=faces, **colors), **bad}
        with pytest.raises((ValueError, TypeError)) as numpy_error:
            raster.forward(**inputs)
        with pytest.raises(type(numpy_error.value)) as device_error:
            raster.forward(**to_device(raster, inputs))
        assert str(device_error.value) == str(numpy_error.value)
    out = raster.forward(**to_device(raster, dict(vertices=vertices, faces=faces, **colors)), grads=("vertices",))
    cot = cotangents(s, out)
    cot["grad_alpha"][1, 2, 3] = np.nan
    with pytest.raises(ValueError, match=r"^grad_alpha contains NaN or Inf \(1 non-finite value\(s\), first at index \(1, 2, 3\)\)"):
        raster.backward(out, **to_device(raster, cot))
    with pytest.raises(ValueError, match=r"^grad_rgb must have shape \(2, 13, 18, 3\), got \(2, 13, 18\)"):
        raster.backward(out, grad_rgb=to_device(raster, cot)["grad_alpha"])



def numpy_via_device_path(s, vertices, faces, colors, grads):
    """The images and gradients of a numpy call through the device path (numpy_via_device, as a
    GPU's rasteriser takes numpy inputs): numpy arrays in and out."""
    raster = SoftRasterizer(s)
    raster.numpy_via_device = True
    out = raster.forward(vertices=vertices, faces=faces, **colors, grads=grads)
    images = {n: getattr(out, n) for n in s.outputs}
    g = raster.backward(out, **cotangents(s, out)) if grads else {}
    assert all(isinstance(a, np.ndarray) for a in [*images.values(), *g.values()])
    return images, g


def test_numpy_via_device_is_the_default_on_gpus_only():
    import pyopencl as cl

    from softras_cl.cl.device import kernel_layout

    raster = SoftRasterizer(settings())
    assert raster.numpy_via_device == (kernel_layout(raster.device, "auto") == "gpu")
    assert not raster.numpy_via_device or raster.device.type & cl.device_type.GPU


def test_numpy_via_device_with_no_faces_gives_the_background():
    s = settings(dtype="float64", layout="cpu")
    raster = SoftRasterizer(s)
    raster.numpy_via_device = True
    out = raster.forward(np.zeros((3, 3)), np.zeros((0, 3), np.int64), colors=np.zeros((3, 3)), grads=("vertices",))
    assert isinstance(out.alpha, np.ndarray) and not out.alpha.any()
    g = raster.backward(out, grad_alpha=np.ones_like(out.alpha))
    assert isinstance(g["vertices"], np.ndarray) and not g["vertices"].any()
