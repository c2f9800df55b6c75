"""Tile binning on the device (softras_cl.raster.device_bins) against the host's
(softras_cl.raster.binning.bin_tiles): the same lists, entry for entry."""
import numpy as np
import pyopencl as cl
import pytest

from softras_cl import RasterSettings
from softras_cl.cl.device import resolve_context
from softras_cl.raster.binning import bin_tiles, face_setup, face_tiles, roi_tiles, tile_grid
from softras_cl.raster.device_bins import DeviceBinning
from softras_cl.raster.inputs import check_inputs


@pytest.fixture(scope="module")
def queue():
    return resolve_context(None, None, None)[2]


def scene(seed, batch, n_faces, size=(40, 56), spread=0.05, huge=0, off=0, degenerate=0):
    """Random small triangles, plus `huge` faces covering the whole image, `off` faces off
    screen and `degenerate` zero-area ones, shuffled among them."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1.2, 1.2, (batch, n_faces, 1, 2))
    xy = centres + spread * rng.uniform(-1, 1, (batch, n_faces, 3, 2))
    pick = rng.permutation(n_faces)
    big, gone, flat = pick[:huge], pick[huge:huge + off], pick[huge + off:huge + off + degenerate]
    xy[:, big] = [[-5, -5], [5, -5], [0, 5]]
    xy[:, gone] += 10.0
    xy[:, flat, 2] = xy[:, flat, 0]
    z = rng.uniform(2, 3, (batch, n_faces, 3, 1))
    vertices = np.concatenate([xy, z], -1).reshape(batch, -1, 3)
    s = RasterSettings(image_size=size, sigma=1e-4, double_sided=True, outputs=("alpha",))
    mesh = check_inputs(s, vertices, np.arange(3 * n_faces).reshape(-1, 3))
    return s, mesh


def device_and_host(queue, s, mesh, tile_w, roi=None):
    g = tile_grid(s, tile_w)
    geom, drawable = face_setup(mesh, s)
    ranges = face_tiles(geom, drawable, s, g).astype(np.int32)
    tiles = roi_tiles(roi, mesh.batch, g, s)
    host = bin_tiles(ranges, mesh.batch, mesh.n_faces, g, tiles)
    buf = cl.Buffer(queue.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=ranges)
    dev = DeviceBinning(queue.context, queue, g).run(buf, mesh.batch, mesh.n_faces, tiles)
    return dev, host


def assert_same_bins(dev, host):
    tile_start, tile_faces, face_start, face_slots = dev.host()
    assert dev.n_entries == host.n_entries
    for name, got, want in [("tile_start", tile_start, host.tile_start), ("tile_faces", tile_faces, host.tile_faces),
                            ("face_start", face_start, host.face_start), ("face_slots", face_slots, host.face_slots)]:
        assert got.dtype == np.int32 and np.array_equal(got, want), name


CASES = {
    "random": dict(batch=2, n_faces=300),
    "large faces": dict(batch=1, n_faces=200, spread=0.4),
    "huge, off screen, degenerate": dict(batch=2, n_faces=120, huge=3, off=20, degenerate=15),
    "one huge face": dict(batch=1, n_faces=1, huge=1),
    "one face": dict(batch=1, n_faces=1),
    "all off screen": dict(batch=2, n_faces=10, off=10),
    "sparse (empty tiles)": dict(batch=3, n_faces=4, spread=0.01),
}


@pytest.mark.parametrize("tile_w", [8, 16])
@pytest.mark.parametrize("case", list(CASES), ids=list(CASES))
def test_device_bins_equal_host_bins(queue, case, tile_w):
    s, mesh = scene(len(case), **CASES[case])
    dev, host = device_and_host(queue, s, mesh, tile_w)
    assert_same_bins(dev, host)
    if case == "sparse (empty tiles)":
        assert (np.diff(host.tile_start) == 0).mean() > 0.5
    if case == "one huge face":
        assert host.n_entries == len(host.tile_start) - 1       # one entry per tile


@pytest.mark.parametrize("shared", [True, False], ids=["one mask", "a mask per item"])
def test_device_bins_equal_host_bins_in_a_region_of_interest(queue, shared):
    s, mesh = scene(7, batch=2, n_faces=250, huge=2)
    rng = np.random.default_rng(3)
    roi = rng.uniform(size=(2,) + s.image_size) < 0.02
    roi[:, 10:20, 5:30] = True
    dev, host = device_and_host(queue, s, mesh, 8, roi[0] if shared else roi)
    assert host.n_entries > len(host.tile_faces) > 0
    assert_same_bins(dev, host)


def test_device_bins_on_many_tiles(queue):
    """Over 2^16 tiles (2 x 128 x 258 at 1024 x 1032, 4 pixels wide): tile keys of 17 bits."""
    s, mesh = scene(11, batch=2, n_faces=2000, size=(1024, 1032), spread=0.1, huge=1)
    dev, host = device_and_host(queue, s, mesh, 4)
    assert len(host.tile_start) - 1 > 2 ** 16
    assert_same_bins(dev, host)


def test_device_bins_refuse_int32_overflow_like_the_host(queue, monkeypatch):
    from softras_cl.raster import device_bins

    monkeypatch.setattr(device_bins, "INT32_LIMIT", 10)
    s, mesh = scene(1, batch=1, n_faces=1, huge=1)
    g = tile_grid(s, 8)
    ranges = face_tiles(*face_setup(mesh, s), s, g).astype(np.int32)
    buf = cl.Buffer(queue.context, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=ranges)
    with pytest.raises(ValueError, match=r"^35 \(tile, face\) pairs exceed the int32 limit"):
        DeviceBinning(queue.context, queue, g).run(buf, 1, 1)
