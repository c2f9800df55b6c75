"""The device face set-up (kernels/face_setup.cl) against the host's float64 numpy set-up
(binning.face_setup, face_tiles): the same records and tile ranges to the bit."""
import numpy as np
import pyopencl as cl
import pytest

from softras_cl import RasterSettings, SoftRasterizer
from softras_cl.cl.device import has_fp64
from softras_cl.raster.binning import face_setup, face_tiles
from softras_cl.raster.inputs import check_inputs

SETTINGS = {
    "float64 single-sided": dict(dtype="float64"),
    "float32 double-sided, 8 lanes": dict(dtype="float32", double_sided=True),
    "barycentric": dict(dtype="float64", metric="barycentric", double_sided=True),
    "barycentric float32 hard": dict(dtype="float32", metric="barycentric", color_agg="hard",
                                     alpha_agg="hard", double_sided=True),
    "unbounded (dist_eps 0)": dict(dtype="float64", dist_eps=0.0, double_sided=True),
    "wide sigma, 16 lanes": dict(dtype="float32", sigma=3e-2, double_sided=True),
}


def mesh_vertices(rng, batch, n_faces):
    """(B, 3F, 3) screen-space vertices of faces spread over and beyond the image, at depths on
    both sides of near (0.5) and far (8), with zero-area, sub-pixel and huge faces among them."""
    centres = rng.uniform(-1.5, 1.5, (batch, n_faces, 1, 2))
    sizes = rng.choice([1e-4, 1e-2, 0.2, 5.0], (batch, n_faces, 1, 1))
    xy = centres + sizes * rng.uniform(-1, 1, (batch, n_faces, 3, 2))
    xy[:, ::17, 2] = xy[:, ::17, 0]                                     # zero area
    z = rng.uniform(-0.5, 10.0, (batch, n_faces, 3, 1))
    return np.concatenate([xy, z], -1).reshape(batch, 3 * n_faces, 3)


@pytest.mark.parametrize("name", list(SETTINGS))
def test_device_records_and_ranges_equal_the_host_setup_to_the_bit(name):
    rng = np.random.default_rng(len(name))
    batch, n_faces = 2, 700
    kw = SETTINGS[name]
    lanes = 16 if name.endswith("16 lanes") else 8 if name.endswith("8 lanes") else None
    s = RasterSettings(image_size=(37, 52), sigma=kw.pop("sigma", 1e-4), near=0.5, far=8.0,
                       outputs=("alpha",), layout="auto" if lanes is None else "cpu", **kw)
    raster = SoftRasterizer(s, lanes=lanes)
    if raster.setup is None:
        pytest.skip("device without cl_khr_fp64: the host set-up runs")
    faces = rng.permutation(3 * n_faces).reshape(-1, 3)       # shared by the batch, vertices in any order
    mesh = check_inputs(s, mesh_vertices(rng, batch, n_faces), faces)
    geom, drawable = face_setup(mesh, s)
    want_ranges = face_tiles(geom, drawable, s, raster.grid)
    assert 0 < drawable.sum() < len(drawable) and (want_ranges[:, 2] > 1).any()
    buf, ranges = raster.setup.run(mesh, s)
    records = np.empty((batch * n_faces, geom.shape[1]), raster.real)
    cl.enqueue_copy(raster.queue, records, buf)
    want = np.ascontiguousarray(geom, raster.real)
    assert records.tobytes() == want.tobytes(), np.argwhere(records != want)[:5]
    assert np.array_equal(ranges, want_ranges)


def test_faces_copy_follows_a_change_in_place():
    """The kept device copy of the faces is refreshed when the caller changes the face array in place."""
    s = RasterSettings(image_size=(16, 16), sigma=1e-4, outputs=("alpha",), double_sided=True)
    raster = SoftRasterizer(s)
    raster.device_setup_faces = 1
    if not has_fp64(raster.device):
        pytest.skip("device without cl_khr_fp64")
    rng = np.random.default_rng(1)
    vertices = mesh_vertices(rng, 1, 40)[0]
    vertices[:, 2] = 2.0
    faces = np.arange(120).reshape(-1, 3)
    first = raster.forward(vertices, faces).alpha
    faces[:, 2] = faces[::-1, 2]        # other triangles
    again = raster.forward(vertices, faces).alpha
    fresh = SoftRasterizer(s).forward(vertices, faces).alpha
    assert not np.array_equal(first, fresh) and np.array_equal(again, fresh)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_host_setup_path_renders_the_same_bits(dtype):
    """A rasteriser without the device set-up (as on devices without cl_khr_fp64) gives the same
    images and gradients, with a region of interest and a batch."""
    from softras_cl.scene.meshes import screen_space_sphere

    v, f, c = screen_space_sphere(2)
    vertices = np.stack([v, v * [0.8, 1.1, 1.0]])
    s = RasterSettings(image_size=(29, 23), sigma=3e-4, dtype=dtype)
    roi = np.zeros((29, 23), bool)
    roi[5:20, 3:15] = True
    results = []
    for device_setup in (True, False):
        raster = SoftRasterizer(s)
        raster.device_setup_faces = 1
        if not device_setup:
            raster.setup = None
        elif raster.setup is None:
            pytest.skip("device without cl_khr_fp64")
        out = raster.forward(vertices, f, colors=c, roi=roi, grads=("vertices", "colors"))
        g = raster.backward(out, grad_rgb=out.rgb - 0.5, grad_alpha=out.alpha)
        results.append([out.rgb, out.alpha, g["vertices"], g["colors"]])
    assert all(a.tobytes() == b.tobytes() for a, b in zip(*results))
    assert np.abs(results[0][2]).max() > 0
