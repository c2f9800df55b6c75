"""Gradient reductions on the device (softras_cl.raster.reduce, kernels/grad_sums.cl) against
plain float64 numpy loops: per-face sums of (tile, face) slots and corner sums onto vertices."""
import numpy as np
import pyopencl as cl
import pytest

from softras_cl.cl.device import resolve_context
from softras_cl.cl.layout import LAYOUT
from softras_cl.cl.source import kernel_source
from softras_cl.raster.binning import Bins
from softras_cl.raster.corners import scatter_corners
from softras_cl.raster.pool import BufferPool
from softras_cl.raster.reduce import GradSums, corner_index


def gradsums(real, sum_double):
    _, ctx, queue = resolve_context(None, None, None)
    return GradSums(ctx, queue, BufferPool(ctx), np.dtype(real), 8, sum_double)


def random_bins(rng, n_faces=40, with_roi=True):
    """Bins with 0..6 entries per face (some faces none); with_roi: a fifth of the entries are
    outside the region (-1), the rest in a random tile-list order."""
    counts = rng.integers(0, 7, n_faces)
    counts[:3] = [0, 1, 6]
    face_start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    total = int(face_start[-1])
    listed = rng.uniform(size=total) > (0.2 if with_roi else -1)
    face_slots = np.full(total, -1, np.int32)
    face_slots[listed] = rng.permutation(int(listed.sum()))
    return Bins(np.zeros(1, np.int32), np.zeros(int(listed.sum()), np.int32), face_start, face_slots)


def sequential_face_sums(slots, bins):
    """(B*F, K) float64: each face's rows (0 outside the region) added one after another."""
    out = np.zeros((len(bins.face_start) - 1, slots.shape[1]))
    for g in range(len(out)):
        rows = [slots[k].astype(np.float64) if k >= 0 else np.zeros(slots.shape[1])
                for k in bins.face_slots[bins.face_start[g]:bins.face_start[g + 1]]]
        if rows:
            total = rows[0]
            for row in rows[1:]:
                total = total + row
            out[g] = total
    return out


def device_face_sums(sums, slots, bins):
    buf = cl.Buffer(sums.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=slots)
    index = [cl.Buffer(sums.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)
             for a in (bins.face_start, bins.face_slots)]
    out = sums.face_sums(buf, slots.shape[1], *index, len(bins.face_start) - 1)
    host = sums.download(out, (len(bins.face_start) - 1, slots.shape[1]))
    sums.wait()
    return host


@pytest.mark.parametrize("real", ["float64", "float32"])
def test_face_sums_equal_sequential_float64_sums_bitwise(real, fp64_device):
    """With double accumulation the kernel adds the same terms in the same order as the loop:
    the same bits (float32 slots are exact in float64)."""
    rng = np.random.default_rng(0)
    bins = random_bins(rng)
    slots = (rng.normal(size=(len(bins.tile_faces), 9)) * 10.0 ** rng.integers(-8, 8, (len(bins.tile_faces), 1))).astype(real)
    single = [bins.face_slots[bins.face_start[g]] for g in np.flatnonzero(np.diff(bins.face_start) == 1)]
    slots[max(single), 0] = -0.0          # a face whose one term is -0.0 sums to -0.0, as numpy's
    got = device_face_sums(gradsums(real, True), slots, bins)
    want = sequential_face_sums(slots, bins)
    assert got.dtype == np.float64
    assert np.array_equal(got.view(np.int64), want.view(np.int64))
    assert not got[np.diff(bins.face_start) == 0].any()


def test_face_sums_in_float32_without_fp64_stay_within_their_bound():
    """sum_double=False (devices without cl_khr_fp64): float32 sums of n terms are within
    n * 2^-24 * sum |terms| of the float64 sums."""
    rng = np.random.default_rng(1)
    bins = random_bins(rng, n_faces=200)
    slots = rng.normal(size=(len(bins.tile_faces), 27)).astype(np.float32)
    got = device_face_sums(gradsums("float32", False), slots, bins)
    assert got.dtype == np.float32
    want = sequential_face_sums(slots, bins)
    magnitude = sequential_face_sums(np.abs(slots), bins)
    n = np.diff(bins.face_start)[:, None]
    assert np.all(np.abs(got - want) <= n * 2.0 ** -24 * magnitude)
    assert np.abs(got - want).max() > 0       # really float32 sums


def test_vertex_sums_equal_numpy_bincount_bitwise():
    """Batch of 2 with a face list per item, a vertex no face uses, and values spanning 16 decades:
    the same bits as scatter_corners (np.bincount); a new face list replaces the cached index."""
    rng = np.random.default_rng(2)
    sums = gradsums("float64", True)
    n_vertices, width, offset = 30, 18, 9
    for trial in range(2):
        faces = rng.integers(0, n_vertices - 1, (2, 50, 3))
        values = rng.normal(size=(2 * 50, width)) * 10.0 ** rng.integers(-8, 8, (100, width))
        buf = cl.Buffer(sums.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=values)
        got = sums.download(sums.vertex_sums(buf, width, offset, faces, n_vertices), (2, n_vertices, 3))
        sums.wait()
        want = scatter_corners(values[:, offset:offset + 9].reshape(2, 50, 3, 3), faces, n_vertices)
        assert np.array_equal(got.view(np.int64), want.view(np.int64)), trial
        assert not got[:, -1].any()


def test_corner_index_lists_each_vertex_corners_in_order():
    faces = np.array([[[0, 1, 2], [2, 1, 3]]])
    index = corner_index(faces, 5)
    assert index.vertex_start.tolist() == [0, 1, 3, 5, 6, 6]
    assert index.corners.tolist() == [0, 1, 5, 2, 4, 6]


def test_float32_reductions_build_without_the_double_type():
    """What a device without cl_khr_fp64 compiles (float32 slots, float32 sums) names no double:
    with `double` defined away at the top of the source, any use would fail to build."""
    _, ctx, _ = resolve_context(None, None, None)
    source = ("#define double no_fp64_type\n" + kernel_source("common.h") + "\n"
              + kernel_source("grad_sums.cl"))
    flags = {**LAYOUT, "SR_DOUBLE": 0, "SR_LANES": 8}
    options = [f"-D{k}={v}" for k, v in flags.items()]
    program = cl.Program(ctx, source).build(options=options + ["-DSR_SUM_DOUBLE=0"])
    assert {k.function_name for k in program.all_kernels()} == {"face_sums", "vertex_sums"}
    with pytest.raises(cl.RuntimeError):
        cl.Program(ctx, source).build(options=options + ["-DSR_SUM_DOUBLE=1"])
