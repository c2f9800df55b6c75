"""Bad input raises ValueError / TypeError naming the argument, before any kernel runs.

Every forward() test replaces the kernel builder with one that fails the test if it is reached,
so an error raised late (after a kernel was built or launched) does not count.
"""
import re

import numpy as np
import pytest

from softras_cl import RasterSettings, SoftRasterizer
from softras_cl.raster import rasterizer as raster_module
from softras_cl.raster import device_setup
from softras_cl.raster import settings as settings_module
from softras_cl.raster.settings import FLOAT32_GRAD_SIGMA

VERTS = np.array([[-0.5, -0.5, 2.0], [0.5, -0.5, 2.0], [0.0, 0.5, 2.0], [0.5, 0.5, 3.0]])
FACES = np.array([[0, 1, 2], [1, 3, 2]])
COLORS = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0]])
V, F = len(VERTS), len(FACES)
SIZE = (8, 8)


@pytest.fixture
def no_kernels(monkeypatch):
    """Any attempt to build (hence run) a kernel fails the test."""
    def refuse(*args, **kwargs):
        raise AssertionError("no error was raised before a kernel was built (the bad input was accepted)")
    monkeypatch.setattr(raster_module, "build_kernel", refuse)
    monkeypatch.setattr(device_setup, "build_kernel", refuse)


def raises(exc, *names):
    """pytest.raises(exc) whose message must mention every name in `names`."""
    class _Check:
        def __enter__(self):
            self.ctx = pytest.raises(exc)
            self.info = self.ctx.__enter__()
            return self.info

        def __exit__(self, *exc_info):
            suppressed = self.ctx.__exit__(*exc_info)   # fails the test if nothing was raised
            if suppressed:                              # the right type: now check the message
                msg = str(self.info.value)
                for name in names:
                    assert re.search(rf"\b{re.escape(name)}\b", msg), f"message does not name {name!r}: {msg!r}"
            return suppressed
    return _Check()


def rasterizer(**kw):
    kw.setdefault("image_size", SIZE)
    kw.setdefault("outputs", ("rgb", "alpha", "depth"))
    return SoftRasterizer(RasterSettings(**kw))


# ---- vertices --------------------------------------------------------------------------------
@pytest.mark.parametrize("verts", [
    np.zeros((V, 2)), np.zeros((V, 4)), np.zeros(V * 3), np.zeros((1, 1, V, 3)), np.zeros((2, V, 2)),
    np.float64(1.0),
], ids=["V2", "V4", "flat", "4d", "B-V-2", "scalar"])
def test_vertices_wrong_shape(no_kernels, verts):
    with raises(ValueError, "vertices"):
        rasterizer(outputs=("alpha",)).forward(verts, np.zeros((0, 3), np.int64))


@pytest.mark.parametrize("dtype", [np.int32, np.int64, np.bool_, np.complex128, object, "U3"])
def test_vertices_wrong_dtype(no_kernels, dtype):
    with raises(TypeError, "vertices"):
        rasterizer(outputs=("alpha",)).forward(VERTS.astype(dtype), FACES)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("coord", [0, 1, 2])
def test_vertices_not_finite(no_kernels, bad, coord):
    verts = VERTS.copy()
    verts[1, coord] = bad
    with raises(ValueError, "vertices"):
        rasterizer().forward(verts, FACES, colors=COLORS)
    with raises(ValueError, "vertices"):
        rasterizer(dtype="float32").forward(verts[None].astype(np.float32), FACES, colors=COLORS)


# ---- faces -----------------------------------------------------------------------------------
@pytest.mark.parametrize("faces", [
    np.zeros((F, 2), np.int64), np.zeros((F, 4), np.int64), np.zeros(3 * F, np.int64),
    np.zeros((1, 1, F, 3), np.int64),
], ids=["F2", "F4", "flat", "4d"])
def test_faces_wrong_shape(no_kernels, faces):
    with raises(ValueError, "faces"):
        rasterizer().forward(VERTS, faces, colors=COLORS)


def test_faces_batch_mismatch(no_kernels):
    verts = np.stack([VERTS, VERTS])
    with raises(ValueError, "faces"):
        rasterizer().forward(verts, np.stack([FACES] * 3), colors=COLORS)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.bool_, object])
def test_faces_wrong_dtype(no_kernels, dtype):
    with raises(TypeError, "faces"):
        rasterizer().forward(VERTS, FACES.astype(dtype), colors=COLORS)


@pytest.mark.parametrize("index", [-1, -100, V, V + 7, 2 ** 40])
def test_faces_out_of_range(no_kernels, index):
    faces = FACES.copy()
    faces[1, 2] = index
    with raises(ValueError, "faces"):
        rasterizer().forward(VERTS, faces, colors=COLORS)
    with raises(ValueError, "faces"):   # batched faces too
        rasterizer().forward(np.stack([VERTS, VERTS]), np.stack([FACES, faces]), colors=COLORS)


# ---- vertex colours --------------------------------------------------------------------------
@pytest.mark.parametrize("colors", [
    np.zeros((V, 4)), np.zeros((V + 1, 3)), np.zeros((V - 1, 3)), np.zeros(V * 3), np.zeros((3, V, 3)),
    np.zeros((1, 1, V, 3)),
], ids=["V4", "V+1", "V-1", "flat", "batch3", "4d"])
def test_colors_wrong_shape(no_kernels, colors):
    # vertices have batch 2: colours with batch 3 cannot be matched to them
    with raises(ValueError, "colors"):
        rasterizer().forward(np.stack([VERTS, VERTS]), FACES, colors=colors)


@pytest.mark.parametrize("dtype", [np.int64, np.uint8, np.bool_, object])
def test_colors_wrong_dtype(no_kernels, dtype):
    with raises(TypeError, "colors"):
        rasterizer().forward(VERTS, FACES, colors=COLORS.astype(dtype))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_colors_not_finite(no_kernels, bad):
    colors = COLORS.copy()
    colors[2, 1] = bad
    with raises(ValueError, "colors"):
        rasterizer().forward(VERTS, FACES, colors=colors)


# ---- per-face textures -------------------------------------------------------------------------
def face_rasterizer():
    return rasterizer(texture="face")


@pytest.mark.parametrize("textures", [
    np.zeros((1, F + 1, 2, 2, 3)), np.zeros((1, F - 1, 2, 2, 3)),     # wrong F
    np.zeros((1, F, 2, 3, 3)), np.zeros((1, F, 1, 4, 3)),             # R x R' not square
    np.zeros((1, F, 2, 2, 4)), np.zeros((1, F, 2, 2)),                # not RGB
    np.zeros((1, F, 2, 3)), np.zeros((1, 1, F, 2, 2, 3)),             # wrong number of axes
    np.zeros((1, F, 0, 0, 3)),                                        # R = 0
], ids=["F+1", "F-1", "2x3", "1x4", "rgba", "no-channel", "3d", "6d", "R0"])
def test_face_textures_wrong_shape(no_kernels, textures):
    with raises(ValueError, "face_textures"):
        face_rasterizer().forward(VERTS, FACES, face_textures=textures)


def test_face_textures_wrong_dtype_and_values(no_kernels):
    with raises(TypeError, "face_textures"):
        face_rasterizer().forward(VERTS, FACES, face_textures=np.zeros((1, F, 2, 2, 3), np.int32))
    textures = np.zeros((1, F, 2, 2, 3))
    textures[0, 1, 1, 0, 2] = np.nan
    with raises(ValueError, "face_textures"):
        face_rasterizer().forward(VERTS, FACES, face_textures=textures)


# ---- uv textures -----------------------------------------------------------------------------
UV_IMAGE = np.zeros((1, 4, 5, 3))
UVS = np.zeros((V, 2))


def uv_rasterizer():
    return rasterizer(texture="uv")


@pytest.mark.parametrize("image", [
    np.zeros((1, 4, 5, 4)), np.zeros((1, 4, 5)), np.zeros((4, 5)), np.zeros((1, 1, 4, 5, 3)),
    np.zeros((3, 4, 5, 3)), np.zeros((1, 0, 5, 3)), np.zeros((1, 4, 0, 3)),
], ids=["rgba", "no-channel", "2d", "5d", "batch3", "Ht0", "Wt0"])
def test_texture_image_wrong_shape(no_kernels, image):
    with raises(ValueError, "texture_image"):
        uv_rasterizer().forward(np.stack([VERTS, VERTS]), FACES, texture_image=image, uvs=UVS)


def test_texture_image_wrong_dtype_and_values(no_kernels):
    with raises(TypeError, "texture_image"):
        uv_rasterizer().forward(VERTS, FACES, texture_image=UV_IMAGE.astype(np.uint8), uvs=UVS)
    image = UV_IMAGE.copy()
    image[0, 3, 4, 0] = np.inf
    with raises(ValueError, "texture_image"):
        uv_rasterizer().forward(VERTS, FACES, texture_image=image, uvs=UVS)


@pytest.mark.parametrize("uvs", [
    np.zeros((V + 1, 2)), np.zeros((V - 1, 2)), np.zeros((V, 3)), np.zeros((V, 1)), np.zeros(2 * V),
    np.zeros((3, V, 2)),
], ids=["V+1", "V-1", "uvw", "u", "flat", "batch3"])
def test_uvs_wrong_shape(no_kernels, uvs):
    with raises(ValueError, "uvs"):
        uv_rasterizer().forward(np.stack([VERTS, VERTS]), FACES, texture_image=UV_IMAGE, uvs=uvs)


def test_uvs_wrong_dtype_and_values(no_kernels):
    with raises(TypeError, "uvs"):
        uv_rasterizer().forward(VERTS, FACES, texture_image=UV_IMAGE, uvs=UVS.astype(np.int64))
    uvs = UVS.copy()
    uvs[0, 0] = np.nan
    with raises(ValueError, "uvs"):
        uv_rasterizer().forward(VERTS, FACES, texture_image=UV_IMAGE, uvs=uvs)


# ---- which colour input ----------------------------------------------------------------------
@pytest.mark.parametrize("texture, missing, given", [
    ("vertex", "colors", {}),
    ("face", "face_textures", {}),
    ("uv", "texture_image", {}),
    ("uv", "uvs", {"texture_image": UV_IMAGE}),
    ("uv", "texture_image", {"uvs": UVS}),
])
def test_color_input_missing_for_rgb(no_kernels, texture, missing, given):
    with raises(ValueError, missing):
        rasterizer(texture=texture).forward(VERTS, FACES, **given)


@pytest.mark.parametrize("texture, given, expected", [
    ("vertex", {"face_textures": np.zeros((1, F, 1, 1, 3))}, "colors"),
    ("vertex", {"texture_image": UV_IMAGE, "uvs": UVS}, "colors"),
    ("face", {"colors": COLORS}, "face_textures"),
    ("face", {"texture_image": UV_IMAGE, "uvs": UVS}, "face_textures"),
    ("uv", {"colors": COLORS}, "texture_image"),
    ("uv", {"face_textures": np.zeros((1, F, 1, 1, 3))}, "texture_image"),
])
def test_color_input_of_the_wrong_kind(no_kernels, texture, given, expected):
    # the message names the argument given and the one the texture mode expects
    with raises(ValueError, sorted(given)[0], expected):
        rasterizer(texture=texture).forward(VERTS, FACES, **given)


def test_color_input_without_rgb_output(no_kernels):
    with raises(ValueError, "colors"):
        rasterizer(outputs=("alpha", "depth")).forward(VERTS, FACES, colors=COLORS)


# ---- settings --------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["sigma", "gamma"])
@pytest.mark.parametrize("value", [0, 0.0, -0.0, -1e-5, -1, float("nan"), float("inf"), -float("inf")])
def test_sigma_gamma_not_positive(name, value):
    with raises(ValueError, name):
        RasterSettings(**{name: value})
    with raises(ValueError, name):
        RasterSettings().replace(**{name: value})


@pytest.mark.parametrize("name, value", [
    ("outputs", ("rgba",)), ("outputs", ("rgb", "normals")), ("outputs", ()), ("outputs", ("alpha", "alpha")),
    ("metric", "manhattan"), ("metric", "Euclidean"),
    ("texture", "vertices"), ("texture", "bogus"),
    ("color_agg", "max"), ("alpha_agg", "product"), ("dtype", "float16"),
])
def test_bad_names(name, value):
    with raises(ValueError, name):
        RasterSettings(**{name: value})


@pytest.mark.parametrize("name, value", [
    ("image_size", (0, 8)), ("image_size", (8,)), ("image_size", (8.0, 8.0)), ("image_size", 8),
    ("near", 0.0), ("near", -1.0), ("far", 0.5), ("far", float("inf")),
    ("dist_eps", -1e-3), ("dist_eps", 0.5), ("background", (0, 0)), ("background", (0, 0, float("nan"))),
])
def test_other_bad_settings(name, value):
    with raises(ValueError, name):
        RasterSettings(**{name: value})


def test_settings_not_raster_settings():
    with raises(TypeError, "settings"):
        SoftRasterizer({"sigma": 1e-5})


def test_bad_grads_names(no_kernels):
    with raises(ValueError, "grads"):
        rasterizer().forward(VERTS, FACES, colors=COLORS, grads=("vertices", "uvs"))


# ---- backward --------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rendered():
    r = rasterizer()
    out = r.forward(np.stack([VERTS, VERTS]), FACES, colors=COLORS, grads=("vertices", "colors"))
    return r, out


@pytest.mark.parametrize("name, shape", [
    ("grad_rgb", (2, 8, 8)), ("grad_rgb", (2, 8, 8, 4)), ("grad_rgb", (1, 8, 8, 3)), ("grad_rgb", (8, 8, 3)),
    ("grad_alpha", (2, 8, 8, 1)), ("grad_alpha", (2, 8, 7)), ("grad_alpha", (8, 8)),
    ("grad_depth", (2, 8, 8, 3)), ("grad_depth", (3, 8, 8)),
])
def test_cotangent_wrong_shape(rendered, monkeypatch, name, shape):
    r, out = rendered
    monkeypatch.setattr(raster_module, "build_kernel", lambda *a, **k: pytest.fail("kernel built"))
    with raises(ValueError, name):
        r.backward(out, **{name: np.ones(shape)})


def test_cotangent_wrong_dtype_or_values(rendered, monkeypatch):
    r, out = rendered
    monkeypatch.setattr(raster_module, "build_kernel", lambda *a, **k: pytest.fail("kernel built"))
    with raises(TypeError, "grad_alpha"):
        r.backward(out, grad_alpha=np.ones((2, 8, 8), np.int64))
    bad = np.ones((2, 8, 8, 3))
    bad[1, 2, 3, 0] = np.nan
    with raises(ValueError, "grad_rgb"):
        r.backward(out, grad_rgb=bad)


def test_cotangent_for_missing_output(monkeypatch):
    r = rasterizer(outputs=("alpha",))
    out = r.forward(VERTS, FACES, grads=("vertices",))
    monkeypatch.setattr(raster_module, "build_kernel", lambda *a, **k: pytest.fail("kernel built"))
    with raises(ValueError, "grad_depth"):
        r.backward(out, grad_depth=np.ones((1, 8, 8)))


def test_backward_without_grads_in_forward(monkeypatch):
    r = rasterizer()
    out = r.forward(VERTS, FACES, colors=COLORS)
    monkeypatch.setattr(raster_module, "build_kernel", lambda *a, **k: pytest.fail("kernel built"))
    with raises(ValueError, "grads"):
        r.backward(out, grad_alpha=np.ones((1, 8, 8)))


# ---- float32 range -----------------------------------------------------------------------------
@pytest.mark.parametrize("arg, index", [("vertices", (3, 2)), ("colors", (1, 0))])
def test_float32_kernels_refuse_values_beyond_2_to_the_64(no_kernels, arg, index):
    """Finite in float64 is not enough: depth 1e30 gave NaN vertex gradients, colour 1e39 Inf."""
    verts, colors = VERTS.copy(), COLORS.copy()
    (verts if arg == "vertices" else colors)[index] = 1e30 if arg == "vertices" else 1e39
    with raises(ValueError, arg, "float32", "2^64"):
        rasterizer(far=1e19).forward(verts, FACES, colors=colors, grads=("vertices",))


def test_float64_kernels_take_large_values():
    verts = VERTS.copy()
    verts[:, 2] *= 1e30
    out = rasterizer(dtype="float64", near=1e29, far=1e32).forward(verts, FACES, colors=COLORS * 1e39)
    assert np.isfinite(out.rgb).all() and out.alpha.max() > 0.5


def test_limit_keeps_float32_gradients_finite():
    """At the limit (depths of 1.8e19) images and gradients stay finite in float32."""
    verts = VERTS.copy()
    verts[:, 2] = 1.8e19
    r = rasterizer(near=1.0, far=1.84e19)
    out = r.forward(verts, FACES, colors=COLORS, grads=("vertices", "colors"))
    g = r.backward(out, grad_rgb=np.ones_like(out.rgb), grad_depth=np.ones_like(out.depth),
                   grad_alpha=np.ones_like(out.alpha))
    assert all(np.isfinite(a).all() for a in (out.rgb, out.depth, out.alpha, *g.values()))


@pytest.mark.parametrize("field, value, says", [
    ("far", 1e38, "far=1e+38 is beyond what dtype='float32' kernels handle"),
    ("sigma", 1e-39, "sigma=1e-39 is too small for dtype='float32' kernels"),
    ("gamma", 1e-25, "gamma=1e-25 is too small for dtype='float32' kernels"),
])
def test_float32_settings_range(field, value, says):
    with pytest.raises(ValueError, match=re.escape(says)):
        RasterSettings(**{field: value})
    RasterSettings(**{field: value}, dtype="float64")      # float64 takes them


def test_float32_gradients_need_sigma_of_at_least_the_bound(no_kernels):
    """float32 gradients below FLOAT32_GRAD_SIGMA are refused, per call too; renders without
    gradients and float64 take the small sigma."""
    r = rasterizer()
    for call in (dict(), dict(sigma=FLOAT32_GRAD_SIGMA / 10)):
        raster = rasterizer(sigma=FLOAT32_GRAD_SIGMA / 10) if not call else r
        with raises(ValueError, "sigma", "float32", "float64"):
            raster.forward(VERTS, FACES, colors=COLORS, grads=("vertices",), **call)


def test_float32_gradients_hold_at_the_bound_on_pixels_on_an_edge():
    """At FLOAT32_GRAD_SIGMA the float32 vertex gradients stay within 5% (of the largest) of
    float64's for an edge through a column of pixel centres; at a tenth of it (forced past the
    check) they do not: the bound is where the kernels' float32 rounding starts to show."""
    x = (8 - 7.5) / 8                              # NDC x of pixel column 8's centres, 16 x 16
    verts = np.array([[x, 0.6875, 2.0], [-0.7, 0.0, 2.0], [x, -0.6875, 2.0]])   # CCW
    colors = COLORS[:3]
    rng = np.random.default_rng(0)
    cot = dict(grad_rgb=rng.normal(size=(1, 16, 16, 3)), grad_alpha=rng.normal(size=(1, 16, 16)))

    def error(sigma):
        grads = {}
        for dtype in ("float32", "float64"):
            r = SoftRasterizer(RasterSettings(image_size=(16, 16), sigma=sigma, outputs=("rgb", "alpha"), dtype=dtype))
            out = r.forward(verts, [[0, 1, 2]], colors=colors, grads=("vertices",))
            grads[dtype] = r.backward(out, **cot)["vertices"]
        return np.abs(grads["float32"] - grads["float64"]).max() / np.abs(grads["float64"]).max()

    assert error(FLOAT32_GRAD_SIGMA) < 0.05
    settings_module.FLOAT32_GRAD_SIGMA, bound = 0.0, FLOAT32_GRAD_SIGMA
    try:
        assert error(bound / 10) > 0.2
    finally:
        settings_module.FLOAT32_GRAD_SIGMA = bound


# ---- memory ------------------------------------------------------------------------------------
class FakeDevice:
    """A device with the given limits (bytes); type 0 = neither CPU nor GPU, own memory."""
    name, type, host_unified_memory = "fake", 0, False

    def __init__(self, max_alloc, global_mem):
        self.max_mem_alloc_size, self.global_mem_size = max_alloc, global_mem


def test_memory_estimate_bounds_what_a_forward_allocates():
    """The estimate's device bytes are at least what the forward's context holds on the device."""
    from softras_cl.raster.memory import memory_estimate

    s = RasterSettings(image_size=(96, 130), outputs=("rgb", "alpha", "depth"))
    r = SoftRasterizer(s)
    out = r.forward(VERTS, FACES, colors=COLORS, grads=("vertices", "colors"))
    est = memory_estimate(s, 1, F, ("vertices", "colors"))
    held = out.saved.nbytes()
    assert held <= est.device < 4 * held + 10_000
    # rgb planes, width padded to the widest float vector (16 lanes)
    assert est.pixels == 96 * 130 and est.largest_buffer == 3 * 4 * 96 * 144


def test_memory_estimate_grows_with_pixels_batch_and_precision():
    from softras_cl.raster.memory import memory_estimate

    s = RasterSettings(image_size=(1024, 1024))
    one = memory_estimate(s, 1, 320)
    assert 30 < one.shared / 1024 ** 2 < 40          # rgb + alpha float32: ~36 bytes a pixel
    assert memory_estimate(s, 4, 320).shared > 3.9 * one.shared
    assert memory_estimate(s.replace(dtype="float64"), 1, 320).shared > 1.8 * one.shared
    assert memory_estimate(s, 1, 320, ("vertices",)).shared > 3 * one.shared


def test_request_over_the_device_buffer_limit_is_refused_before_allocation(no_kernels, monkeypatch):
    from softras_cl.errors import ResourceError
    from softras_cl.raster import memory

    r = rasterizer(image_size=(4096, 4096))
    r.device = FakeDevice(max_alloc=128 * 1024 ** 2, global_mem=1024 ** 3)
    monkeypatch.setattr(raster_module, "face_setup", lambda *a: pytest.fail("set-up ran"))
    monkeypatch.setattr(device_setup.DeviceSetup, "run", lambda *a: pytest.fail("set-up ran"))
    with pytest.raises(ResourceError, match=r"rasterising 1 x 4096 x 4096 pixels needs a 192 MB buffer, "
                                            r"but device 'fake' allows at most 128 MB in one buffer"):
        r.forward(VERTS, FACES, colors=COLORS)
    r.device = FakeDevice(max_alloc=1024 ** 3, global_mem=256 * 1024 ** 2)
    with pytest.raises(ResourceError, match=r"needs ~3\d\d MB of device memory, but device 'fake' has 256 MB"):
        r.forward(VERTS, FACES, colors=COLORS)
    assert issubclass(ResourceError, MemoryError)
    monkeypatch.setattr(memory, "available_host_memory", lambda: 100 * 1024 ** 2)
    with pytest.raises(ResourceError, match=r"pixels needs ~70\d MB of memory, but the machine has 100 MB available; lower image_size"):
        memory.check_memory(memory.memory_estimate(r.settings, 1, F), None)


def test_available_host_memory_is_a_positive_number():
    from softras_cl.raster.memory import available_host_memory

    assert available_host_memory() > 0
