"""Buffers and host staging reused across calls (softras_cl.raster.pool): sizes, reuse, limits,
and that a forward's context never shares buffers with a later call while it lives."""
import gc

import numpy as np
import pytest

from softras_cl import RasterSettings, SoftRasterizer
from softras_cl.raster.pool import MIN_FREE_BYTES, BufferPool, ScratchArrays, size_class


@pytest.fixture
def context():
    return SoftRasterizer(RasterSettings()).ctx


@pytest.mark.parametrize("n", [1, 63, 64, 65, 1000, 4096, 4097, 123457, 10 ** 8 + 7])
def test_size_class_rounds_up_by_at_most_an_eighth(n):
    c = size_class(n)
    assert c >= max(n, 64)
    assert c <= max(64, n * 1.125)
    assert size_class(c) == c


def test_pool_reuses_returned_buffers_and_keeps_at_most_the_peak(context):
    pool = BufferPool(context)
    a = pool.take(1000)
    pool.give([a])
    assert pool.take(990).int_ptr == a.int_ptr          # same size class: the same buffer
    big = [pool.take(MIN_FREE_BYTES) for _ in range(3)]
    pool.give(big)
    assert pool.free_bytes <= 3 * size_class(MIN_FREE_BYTES) + size_class(1000)
    one = pool.take(2 * MIN_FREE_BYTES)                 # a new class; the peak does not grow past it
    pool.give([one])
    assert pool.free_bytes <= pool._peak


def test_give_when_dead_returns_buffers_after_the_owner_is_collected(context):
    class Owner:
        pass
    pool, owner = BufferPool(context), Owner()
    buf = pool.take(4096)
    pool.give_when_dead(owner, [buf])
    assert pool.free_bytes == 0
    del owner
    gc.collect()
    assert pool.free_bytes == buf.size


def test_scratch_arrays_grow_by_size_classes():
    scratch = ScratchArrays()
    a = scratch.get("x", (2, 3), np.float32)
    assert a.shape == (2, 3) and a.dtype == np.float32
    a[0, 0] = 5
    b = scratch.get("x", (3, 2), np.float32)      # same size class: the same memory
    assert b.shape == (3, 2) and b[0, 0] == 5
    c = scratch.get("x", (100, 3), np.float32)
    assert c.shape == (100, 3) and not np.shares_memory(a, c)


def _scene(seed):
    rng = np.random.default_rng(seed)
    v = np.concatenate([rng.uniform(-1, 1, (1, 30, 2)), rng.uniform(2, 4, (1, 30, 1))], -1)
    f = rng.integers(0, 30, (40, 3))
    f = f[np.array([len(set(x)) == 3 for x in f])]
    return v, f, rng.uniform(0, 1, (1, 30, 3))


@pytest.mark.parametrize("roi", [False, True])
def test_interleaved_calls_match_fresh_rasterisers(roi):
    """Two forwards alive at once, backwards in the other order, on one rasteriser: the same
    bits as separate rasterisers, and repeated calls do not grow the pool."""
    s = RasterSettings(image_size=(24, 40), sigma=1e-3, gamma=1e-2, dist_eps=1e-4, dtype="float32",
                       outputs=("rgb", "alpha", "depth"))
    mask = np.zeros((24, 40), bool)
    mask[3:12, 5:30] = True
    kw = dict(grads=("vertices", "colors"), roi=mask if roi else None)
    scenes = [_scene(1), _scene(2)]
    rng = np.random.default_rng(0)
    cots = [dict(grad_rgb=rng.standard_normal((1, 24, 40, 3)), grad_alpha=rng.standard_normal((1, 24, 40)),
                 grad_depth=rng.standard_normal((1, 24, 40))) for _ in scenes]
    want = []
    for (v, f, c), cot in zip(scenes, cots):
        r = SoftRasterizer(s)
        out = r.forward(v, f, colors=c, **kw)
        want.append((out, r.backward(out, **cot)))
    shared = SoftRasterizer(s)
    for _ in range(3):
        outs = [shared.forward(v, f, colors=c, **kw) for v, f, c in scenes]
        grads = [shared.backward(outs[i], **cots[i]) for i in (1, 0)][::-1]
        for (w_out, w_grads), out, g in zip(want, outs, grads):
            for name in ("rgb", "alpha", "depth"):
                np.testing.assert_array_equal(getattr(out, name), getattr(w_out, name))
            for name in w_grads:
                np.testing.assert_array_equal(g[name], w_grads[name])
        del outs, out
        gc.collect()
        if _ == 0:
            free = shared.pool.free_bytes
    assert shared.pool.free_bytes == free


def test_upload_parts_lands_every_array_in_its_buffer_with_few_transfers():
    """SoftRasterizer._upload_parts: small arrays (and any needing a cast) share one staged
    transfer, each in a sub-buffer; large contiguous ones in their dtype go on their own."""
    import pyopencl as cl

    from softras_cl import RasterSettings, SoftRasterizer
    from softras_cl.raster.rasterizer import OWN_TRANSFER

    raster = SoftRasterizer(RasterSettings(image_size=(8, 8), outputs=("alpha",), dtype="float32"))
    rng = np.random.default_rng(0)
    big = rng.normal(size=OWN_TRANSFER // 4).astype(np.float32)
    parts = dict(small=(np.arange(7, dtype=np.int32), np.int32), cast=(rng.normal(size=(5, 3)), np.float32),
                 strided=(rng.normal(size=(6, 4)).astype(np.float32).T, np.float32), empty=(np.zeros(0), np.float32),
                 big=(big, np.float32), big_cast=(big.astype(np.float64), np.float32))
    owned, bufs = raster._upload_parts("test", parts)
    raster._sync()
    assert len(owned) == 2 and bufs["empty"] is raster._dummy() and bufs["big"] in owned
    for key, (array, dtype) in parts.items():
        if array.size:
            got = np.empty(array.shape, dtype)
            cl.enqueue_copy(raster.queue, got, bufs[key])
            assert np.array_equal(got, array.astype(dtype)), key
