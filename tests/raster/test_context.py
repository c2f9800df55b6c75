"""SoftRasterizer on a caller's own pyopencl Context / CommandQueue, and the typed backward context."""
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
