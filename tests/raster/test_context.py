"""SoftRasterizer on a caller's own pyopencl Context / CommandQueue, and the typed backward context."""
import re

import numpy as np
import pyopencl as cl
import pytest

from softras_cl import RasterSettings, SoftRasterizer
from softras_cl.cl.device import select_device
from softras_cl.raster import rasterizer as raster_module
from softras_cl.raster.rasterizer import RasterContext

VERTS = np.array([[-0.6, -0.5, 2.0], [0.5, -0.6, 2.5], [0.0, 0.6, 3.0], [0.7, 0.5, 2.2]])
FACES = np.array([[0, 1, 2], [1, 3, 2]])
COLORS = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 0]])
SETTINGS = RasterSettings(image_size=(11, 14), sigma=1e-2, outputs=("rgb", "alpha", "depth"))


def render(raster):
    """Outputs and gradients of one forward/backward, as a flat dict of arrays."""
    out = raster.forward(VERTS, FACES, colors=COLORS, grads=("vertices", "colors"))
    rng = np.random.default_rng(1)
    grads = raster.backward(out, grad_rgb=rng.normal(size=out.rgb.shape),
                            grad_alpha=rng.normal(size=out.alpha.shape), grad_depth=rng.normal(size=out.depth.shape))
    return dict(rgb=out.rgb, alpha=out.alpha, depth=out.depth, **grads)


@pytest.fixture
def no_kernels(monkeypatch):
    monkeypatch.setattr(raster_module, "build_kernel", lambda *a, **k: pytest.fail("kernel built"))


def test_own_context_and_queue_are_bit_identical_to_the_default():
    expected = render(SoftRasterizer(SETTINGS))
    ctx = cl.Context([select_device()])
    queue = cl.CommandQueue(ctx)
    for raster in (SoftRasterizer(SETTINGS, context=ctx), SoftRasterizer(SETTINGS, context=ctx, queue=queue),
                   SoftRasterizer(SETTINGS, queue=queue)):
        assert raster.ctx == ctx
        got = render(raster)
        for name, value in expected.items():
            np.testing.assert_array_equal(got[name], value, err_msg=name)
    assert SoftRasterizer(SETTINGS, queue=queue).queue == queue


def test_queue_of_another_context_is_refused(no_kernels):
    ctx = cl.Context([select_device()])
    other = cl.CommandQueue(cl.Context([select_device()]))
    with pytest.raises(ValueError, match="queue belongs to another context"):
        SoftRasterizer(SETTINGS, context=ctx, queue=other)


def test_device_outside_the_context_is_refused(no_kernels):
    others = [d for p in cl.get_platforms() for d in p.get_devices() if d != select_device()]
    if not others:
        pytest.skip("a single OpenCL device")
    with pytest.raises(ValueError, match="device .* does not belong to the context"):
        SoftRasterizer(SETTINGS, device=others[0], context=cl.Context([select_device()]))


def test_out_of_order_queue_is_refused(no_kernels):
    ctx = cl.Context([select_device()])
    try:
        queue = cl.CommandQueue(ctx, properties=cl.command_queue_properties.OUT_OF_ORDER_EXEC_MODE_ENABLE)
    except cl.Error:
        pytest.skip("the device has no out-of-order queues")
    with pytest.raises(ValueError, match="queue must be in-order"):
        SoftRasterizer(SETTINGS, queue=queue)


@pytest.mark.parametrize("name, value", [("device", "0:0"), ("context", object()), ("queue", 3)])
def test_wrong_types_are_refused(no_kernels, name, value):
    with pytest.raises(TypeError, match=f"{name} must be a pyopencl"):
        SoftRasterizer(SETTINGS, **{name: value})


def test_saved_context_is_typed_and_only_kept_for_gradients():
    raster = SoftRasterizer(SETTINGS)
    assert raster.forward(VERTS, FACES, colors=COLORS).saved is None
    saved = raster.forward(VERTS, FACES, colors=COLORS, grads=("vertices",)).saved
    assert isinstance(saved, RasterContext)
    assert saved.grads == ("vertices",) and saved.mesh.n_faces == len(FACES)
    assert set(saved.images) == {"rgb", "alpha", "depth"}
    assert saved.state.color is not None and saved.state.alpha is not None
    assert saved.nbytes() >= saved.bins.tile_faces.nbytes + saved.state.ids.size


# ---- run-time settings per call ----------------------------------------------------------------
BASE = SETTINGS.replace(sigma=1e-4)
RUN = dict(sigma=3e-3, gamma=2e-3, near=1.5, far=9.0)     # sigma above BASE's: wider footprints


def test_per_call_settings_equal_a_rasteriser_made_with_them_to_the_bit():
    """forward(sigma=, gamma=, near=, far=) draws and differentiates exactly as a rasteriser whose
    settings hold those values, on the host and on the device face set-up alike."""
    expected_raster = SoftRasterizer(BASE.replace(**RUN))
    expected_raster.device_setup_faces = 10 ** 9        # the host's face set-up
    expected = render(expected_raster)
    for setup_faces in (10 ** 9, 1):
        raster = SoftRasterizer(BASE)
        raster.device_setup_faces = setup_faces
        out = raster.forward(VERTS, FACES, colors=COLORS, grads=("vertices", "colors"), **RUN)
        rng = np.random.default_rng(1)
        grads = raster.backward(out, grad_rgb=rng.normal(size=out.rgb.shape),
                                grad_alpha=rng.normal(size=out.alpha.shape), grad_depth=rng.normal(size=out.depth.shape))
        got = dict(rgb=out.rgb, alpha=out.alpha, depth=out.depth, **grads)
        assert out.saved.settings == BASE.replace(**RUN)
        for name, value in expected.items():
            np.testing.assert_array_equal(got[name], value, err_msg=name)


def test_backward_uses_the_settings_of_its_own_forward():
    """An output keeps its call's sigma and gamma: a forward at other values in between does not
    change its gradients (one rasteriser serves a whole sigma/gamma schedule)."""
    expected = render(SoftRasterizer(SETTINGS))
    raster = SoftRasterizer(SETTINGS)
    first = raster.forward(VERTS, FACES, colors=COLORS, grads=("vertices", "colors"))
    raster.forward(VERTS, FACES, colors=COLORS, grads=("vertices", "colors"), sigma=1e-5, gamma=1e-5)
    rng = np.random.default_rng(1)
    grads = raster.backward(first, grad_rgb=rng.normal(size=first.rgb.shape),
                            grad_alpha=rng.normal(size=first.alpha.shape), grad_depth=rng.normal(size=first.depth.shape))
    for name in ("vertices", "colors"):
        np.testing.assert_array_equal(grads[name], expected[name], err_msg=name)


@pytest.mark.parametrize("run, says", [
    (dict(sigma=0.0), "sigma must be a finite number > 0"), (dict(gamma=float("nan")), "gamma"),
    (dict(near=-1.0), "near"), (dict(far=0.5), "far must be finite and > near"),
    (dict(sigma=1e-30), "sigma=1e-30 is too small for dtype='float32'"),
])
def test_bad_per_call_settings_are_named_before_any_kernel(no_kernels, run, says):
    with pytest.raises(ValueError, match=re.escape(says)):
        SoftRasterizer(SETTINGS).forward(VERTS, FACES, colors=COLORS, **run)


# ---- an output goes back through the rasteriser that made it ---------------------------------
@pytest.mark.parametrize("other", [
    dict(sigma=1e-4, gamma=1e-5), dict(dtype="float64"), dict(image_size=(9, 7)),
], ids=["other sigma and gamma", "other dtype", "other size"])
def test_backward_refuses_the_output_of_another_rasteriser(other):
    """Before, these gave NaN gradients, zeros or an error blaming grad_rgb."""
    foreign = SoftRasterizer(SETTINGS.replace(**other))
    out = foreign.forward(VERTS, FACES, colors=COLORS, grads=("vertices", "colors"))
    raster = SoftRasterizer(SETTINGS)
    with pytest.raises(ValueError, match=r"^output was made by another SoftRasterizer"):
        raster.backward(out, grad_rgb=np.ones(out.rgb.shape), grad_alpha=np.ones(out.alpha.shape))
    assert np.isfinite(foreign.backward(out, grad_rgb=np.ones(out.rgb.shape))["vertices"]).all()


def test_backward_refuses_what_is_not_an_output():
    with pytest.raises(TypeError, match="output must be the RasterOutput"):
        SoftRasterizer(SETTINGS).backward(dict(rgb=None), grad_rgb=None)
