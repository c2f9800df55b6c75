"""Hard cases: nothing NaN or Inf in outputs or gradients, forward or backward, in
float32 and float64, plus a value check wherever one exists, and agreement with the dense
float64 reference (softras_cl/raster/reference.py) where that is cheap.

Every case runs forward(grads=("vertices", "colors")) (alpha-only cases: grads=("vertices",), as
no colour input goes with them) and backward() with random cotangents for every output. Pixel centres follow docs/conventions.md: x = (2 (i + 0.5) - W) / s,
y = (H - 2 (r + 0.5)) / s, s = min(W, H).
"""
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from softras_cl import RasterSettings, SoftRasterizer
from softras_cl.raster import reference
from softras_cl.raster.settings import FLOAT32_GRAD_SIGMA
from softras_cl.cl.device import has_fp64, select_device
from softras_cl.scene.meshes import screen_space_sphere

ALL = ("rgb", "alpha", "depth")
BG = (0.25, 0.5, 0.75)
DTYPES = ["float32", pytest.param("float64", marks=pytest.mark.skipif(
    not has_fp64(select_device()), reason="device has no cl_khr_fp64"))]
# float32 kernels: values are exact up to a few ulps of the quantities involved
TOL = {"float32": 1e-5, "float64": 1e-12}


def pixel_xy(col, row, width, height):
    """NDC centre of pixel (column, row) (docs/conventions.md)."""
    s = min(width, height)
    return (2.0 * (col + 0.5) - width) / s, (height - 2.0 * (row + 0.5)) / s


def overlap_scene(seed=0, n_faces=6, z_range=(2.0, 8.0)):
    """A few big random CCW triangles that overlap and occlude each other, with vertex colours."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-0.5, 0.5, (n_faces, 1, 2))
    offsets = rng.uniform(0.3, 0.9, (n_faces, 1, 1)) * np.array(
        [[np.cos(a), np.sin(a)] for a in np.deg2rad([90.0, 210.0, 330.0])])
    rot = rng.uniform(0, 2 * np.pi, n_faces)
    c, s = np.cos(rot)[:, None], np.sin(rot)[:, None]
    xy = centres + np.stack([c * offsets[..., 0] - s * offsets[..., 1],
                             s * offsets[..., 0] + c * offsets[..., 1]], -1)   # CCW kept
    z = rng.uniform(*z_range, (n_faces, 3, 1))
    verts = np.concatenate([xy, z], -1).reshape(-1, 3)
    faces = np.arange(3 * n_faces).reshape(-1, 3)
    colors = rng.uniform(0.0, 1.0, (3 * n_faces, 3))
    return verts, faces, colors


def run(verts, faces, colors=None, seed=1, **settings):
    """Forward and backward with random cotangents; every array checked for NaN/Inf. float32
    below FLOAT32_GRAD_SIGMA gives no gradients (forward with grads must refuse): forward only.

    Returns (settings, output, gradients or None)."""
    settings.setdefault("outputs", ALL)
    s = RasterSettings(**settings)
    raster = SoftRasterizer(s)
    grads = ("vertices", "colors") if "rgb" in s.outputs else ("vertices",)
    colors = colors if "rgb" in s.outputs else None
    if s.dtype == "float32" and s.sigma < FLOAT32_GRAD_SIGMA:
        with pytest.raises(ValueError, match="too small for gradients"):
            raster.forward(verts, faces, colors=colors, grads=grads)
        grads = ()
    out = raster.forward(verts, faces, colors=colors, grads=grads)
    for n in s.outputs:
        img = getattr(out, n)
        assert img.dtype == np.dtype(s.dtype), n
        assert np.isfinite(img).all(), f"{n}: {np.argwhere(~np.isfinite(img))[:5]}"
    if not grads:
        return s, out, None
    rng = np.random.default_rng(seed)
    cot = {f"grad_{n}": rng.standard_normal(getattr(out, n).shape) for n in s.outputs}
    g = raster.backward(out, **cot)
    assert set(g) == set(grads)
    assert g["vertices"].shape == np.shape(verts)
    assert np.isfinite(g["vertices"]).all(), f"vertex grads: {np.argwhere(~np.isfinite(g['vertices']))[:5]}"
    if "colors" in g:
        assert g["colors"].shape == np.shape(colors)
        assert np.isfinite(g["colors"]).all(), f"colour grads: {np.argwhere(~np.isfinite(g['colors']))[:5]}"
    return s, out, g


def check_ranges(s, out, colors=None):
    """alpha in [0, 1]; rgb inside the range of the colours and the background; depth in [near, far]."""
    tol = TOL[s.dtype]
    if out.alpha is not None:
        assert out.alpha.min() >= 0.0 and out.alpha.max() <= 1.0, (out.alpha.min(), out.alpha.max())
    if out.rgb is not None:
        lo = np.minimum(np.min(colors, axis=tuple(range(np.ndim(colors) - 1))), s.background)
        hi = np.maximum(np.max(colors, axis=tuple(range(np.ndim(colors) - 1))), s.background)
        assert (out.rgb >= lo - tol).all() and (out.rgb <= hi + tol).all(), (out.rgb.min((0, 1, 2)),
                                                                              out.rgb.max((0, 1, 2)))
    if out.depth is not None:
        assert out.depth.min() >= s.near * (1 - tol) and out.depth.max() <= s.far * (1 + tol), \
            (out.depth.min(), out.depth.max())


def check_reference(s, out, verts, faces, colors=None, rtol=1e-9):
    """float64 kernels against the dense reference (the caller uses dist_eps = 0)."""
    ref = reference.soft_rasterize(verts, faces, s, colors=colors)
    for n in s.outputs:
        got, want = getattr(out, n), ref[n]
        scale = np.abs(want).max() if want.size else 1.0
        err = np.abs(got - want)
        assert (err <= rtol * np.abs(want) + 1e-13 * scale).all(), \
            f"{n}: max abs err {err.max():.3g} at {np.unravel_index(err.argmax(), err.shape)}, " \
            f"max rel err {(err / np.maximum(np.abs(want), 1e-300)).max():.3g}"


# ---- sigma and gamma extremes --------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("gamma", [1e-8, 1e-4, 1.0, 10.0])
def test_gamma_extremes(dtype, gamma):
    verts, faces, colors = overlap_scene(0)
    s, out, _ = run(verts, faces, colors, image_size=(12, 16), sigma=1e-3, gamma=gamma, dist_eps=0.0,
                    background=BG, dtype=dtype)
    check_ranges(s, out, colors)
    if dtype == "float64":
        check_reference(s, out, verts, faces, colors)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("sigma", [1e-10, 1e-5, 1e-2, 1.0])
def test_sigma_extremes(dtype, sigma):
    verts, faces, colors = overlap_scene(1)
    s, out, _ = run(verts, faces, colors, image_size=(12, 16), sigma=sigma, gamma=1e-3, dist_eps=0.0,
                    background=BG, dtype=dtype)
    check_ranges(s, out, colors)
    if dtype == "float64":
        check_reference(s, out, verts, faces, colors)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("sigma, gamma", [(1e-10, 1e-8), (1e-10, 10.0), (1.0, 1e-8), (1.0, 10.0)])
@pytest.mark.parametrize("metric", ["euclidean", "barycentric"])
def test_sigma_gamma_corners(dtype, sigma, gamma, metric):
    verts, faces, colors = overlap_scene(2)
    s, out, _ = run(verts, faces, colors, image_size=(10, 10), sigma=sigma, gamma=gamma, dist_eps=0.0,
                    metric=metric, background=BG, dtype=dtype)
    check_ranges(s, out, colors)
    if dtype == "float64":
        check_reference(s, out, verts, faces, colors)


# ---- degenerate faces ------------------------------------------------------------------------
def degenerate_scene(height):
    """A normal face, then degenerate ones: collinear (zero area), two and three coincident
    vertices, and needles of the given height crossing the image."""
    good = [[-0.8, -0.8, 3.0], [0.8, -0.7, 4.0], [0.0, 0.8, 5.0]]
    collinear = [[-0.9, -0.9, 2.0], [0.0, 0.0, 2.5], [0.9, 0.9, 3.0]]
    two_same = [[0.1, 0.2, 2.0], [0.1, 0.2, 2.0], [0.5, -0.3, 2.0]]
    three_same = [[0.3, 0.3, 2.5]] * 3
    needle = [[-0.9, 0.1, 2.0], [0.9, 0.1, 2.0], [0.0, 0.1 + height, 2.0]]        # horizontal
    needle_v = [[0.2, -0.9, 2.2], [0.2 + height, 0.0, 2.2], [0.2, 0.9, 2.2]]      # vertical
    needle_d = [[-0.7, -0.7, 2.4], [0.7, 0.7 - height, 2.4], [0.7, 0.7, 2.4]]     # diagonal, CCW
    verts = np.array(good + collinear + two_same + three_same + needle + needle_v + needle_d, float)
    faces = np.arange(len(verts)).reshape(-1, 3)
    colors = np.random.default_rng(3).uniform(0, 1, (len(verts), 3))
    return verts, faces, colors


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("height", [1e-3, 1e-7, 1e-9, 1e-13])
@pytest.mark.parametrize("sigma", [1e-5, 1e-2])
def test_degenerate_and_needle_faces(dtype, height, sigma):
    verts, faces, colors = degenerate_scene(height)
    s, out, g = run(verts, faces, colors, image_size=(16, 16), sigma=sigma, gamma=1e-3, dist_eps=0.0,
                    background=BG, double_sided=True, dtype=dtype)
    check_ranges(s, out, colors)
    # faces 1-3 have zero doubled area: dropped entirely, so no gradient reaches their vertices
    np.testing.assert_array_equal(g["vertices"][3:12], 0.0)
    np.testing.assert_array_equal(g["colors"][3:12], 0.0)
    if height < 1e-12:  # below the 1e-12 area threshold: the needles are dropped too
        np.testing.assert_array_equal(g["vertices"][12:], 0.0)
    if dtype == "float64":
        # A needle of height h makes U ill-conditioned (cond ~ 1/h): the kernel (precomputed U^-1
        # rows) and the reference (sub-triangle areas) round b differently, by ~1e-16 / h. The
        # colour interpolated with those weights shows it (measured: 1.4e-9 at h = 1e-7,
        # 1.2e-7 at h = 1e-9; alpha and depth agree to 1e-13), hence rtol = 1e-15 / h there.
        rtol = 1e-15 / height if 1e-12 <= height < 1e-6 else 1e-9
        check_reference(s, out, verts, faces, colors, rtol=rtol)


# ---- faces behind the camera, on the camera plane, straddling near / far -----------------------
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("sigma", [1e-5, 1e-2])
def test_faces_behind_camera_and_straddling_near_far(dtype, sigma):
    tri = np.array([[-0.8, -0.8, 0.0], [0.8, -0.8, 0.0], [0.0, 0.8, 0.0]])
    zs = [
        [3.0, 3.0, 3.0],          # 0 ordinary, in range
        [-1.0, -2.0, -3.0],       # 1 entirely behind the camera
        [0.0, 2.0, 3.0],          # 2 one vertex on the camera plane (z = 0)
        [-1.0, 2.0, 3.0],         # 3 crossing the camera plane
        [0.5, 2.0, 4.0],          # 4 straddling near = 1
        [50.0, 150.0, 90.0],      # 5 straddling far = 100
        [0.2, 0.3, 0.4],          # 6 entirely nearer than near
        [120.0, 200.0, 300.0],    # 7 entirely beyond far
        [0.5, 60.0, 151.0],       # 8 straddling both (150 would put Z exactly on far)
        [0.0, 0.0, 0.0],          # 9 all on the camera plane
    ]
    shrink = np.linspace(1.0, 0.5, len(zs))[:, None, None]
    verts = np.concatenate([np.concatenate([tri[:, :2] * k, np.array(z)[:, None]], 1)
                            for k, z in zip(shrink, zs)])
    faces = np.arange(len(verts)).reshape(-1, 3)
    colors = np.random.default_rng(4).uniform(0, 1, (len(verts), 3))
    s, out, g = run(verts, faces, colors, image_size=(16, 16), sigma=sigma, gamma=1e-3, dist_eps=0.0,
                    background=BG, dtype=dtype)
    check_ranges(s, out, colors)
    dropped = [1, 2, 3, 6, 7, 9]   # some z <= 0, or all out of [near, far]
    for f in dropped:
        np.testing.assert_array_equal(g["vertices"][3 * f:3 * f + 3], 0.0, err_msg=f"face {f}")
        np.testing.assert_array_equal(g["colors"][3 * f:3 * f + 3], 0.0, err_msg=f"face {f}")
    assert out.alpha.max() > 0.4  # the ordinary face is drawn
    if dtype == "float64":
        check_reference(s, out, verts, faces, colors)


# ---- depth spread 1e-6 .. 1e6 ----------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("perspective_correct", [True, False])
def test_depth_spread(dtype, perspective_correct):
    rng = np.random.default_rng(5)
    verts, faces, colors = overlap_scene(5, n_faces=8)
    verts[:, 2] = 10.0 ** rng.uniform(-6, 6, len(verts))
    verts[:3, 2] = [1e-6, 1e6, 1e-6]
    verts[3:6, 2] = [1e6, 1e6, 1e-6]
    s, out, _ = run(verts, faces, colors, image_size=(12, 12), sigma=1e-3, gamma=1e-3, near=1e-7, far=1e7,
                    dist_eps=0.0, background=BG, dtype=dtype, perspective_correct=perspective_correct)
    check_ranges(s, out, colors)
    if dtype == "float64":
        check_reference(s, out, verts, faces, colors)


# ---- pixels exactly on an edge or a vertex ---------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("metric", ["euclidean", "barycentric"])
def test_pixel_on_edge_and_vertex(dtype, metric):
    w = h = 8   # pixel centres are multiples of 1/8: exact in binary
    corners = [pixel_xy(c, r, w, h) for c, r in [(1, 6), (6, 6), (6, 1), (1, 1)]]   # CCW square
    verts = np.array([[x, y, z] for (x, y), z in zip(corners, [2.0, 3.0, 4.0, 3.0])])
    faces = np.array([[0, 1, 2], [0, 2, 3]])   # share the diagonal (1, 6)-(6, 1)
    colors = np.random.default_rng(6).uniform(0, 1, (4, 3))
    sigma = 1e-8 if dtype == "float64" else FLOAT32_GRAD_SIGMA     # float32 gradients need sigma >= 1e-7
    s, out, g = run(verts, faces, colors, image_size=(h, w), sigma=sigma, gamma=1e-3, dist_eps=0.0,
                    metric=metric, background=BG, dtype=dtype)
    check_ranges(s, out, colors)
    a = out.alpha[0]
    # a vertex owned by one face only: D = sigmoid(0) = 1/2
    assert a[6, 6] == pytest.approx(0.5, abs=TOL[dtype]) and a[1, 1] == pytest.approx(0.5, abs=TOL[dtype])
    # vertices and pixels on the shared diagonal: both faces at D = 1/2
    for r in range(1, 7):
        assert a[r, 7 - r] == pytest.approx(0.75, abs=TOL[dtype]), (r, a[r, 7 - r])
    # pixels on an outer edge, away from the diagonal: one face at D = 1/2 (the other far away)
    for r, c in [(6, 3), (3, 6), (1, 3), (3, 1)]:
        assert a[r, c] == pytest.approx(0.5, abs=TOL[dtype]), (r, c, a[r, c])
    assert a[0].max() == 0 and a[:, 0].max() == 0   # one pixel outside, sigma tiny
    assert a[3, 3] == 1.0 and a[4, 4] == 1.0   # well inside one face, sigma tiny: D = 1
    if dtype == "float64":
        check_reference(s, out, verts, faces, colors)


# ---- occupancy with many faces at D close to 1 -----------------------------------------------
def stacked_scene(n=200, shift=0.01):
    base = np.array([[-0.6, -0.6, 3.0], [0.6, -0.6, 3.0], [0.0, 0.6, 3.0]])
    verts = np.tile(base, (n, 1))
    verts[3 * 7:3 * 8, :2] += shift   # face 7 slightly displaced
    return verts, np.arange(3 * n).reshape(-1, 3)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("sigma", [1e-6, 1e-3])
def test_occupancy_many_faces_near_one(dtype, sigma):
    verts, faces = stacked_scene()
    s, out, g = run(verts, faces, image_size=(24, 24), sigma=sigma, dist_eps=0.0, outputs=("alpha",),
                    dtype=dtype)
    check_ranges(s, out)
    assert out.alpha[0, 12, 12] == 1.0   # deep inside every copy
    assert out.alpha[0, 0, 0] < 1e-3
    if dtype == "float64":
        check_reference(s, out, verts, faces)


def test_occupancy_many_faces_gradient_matches_finite_differences(fp64_device):
    verts, faces = stacked_scene()
    s = RasterSettings(image_size=(24, 24), sigma=3e-3, dist_eps=0.0, outputs=("alpha",), dtype="float64")
    raster = SoftRasterizer(s)
    cot = np.random.default_rng(7).standard_normal((1, 24, 24))
    out = raster.forward(verts, faces, grads=("vertices",))
    g = raster.backward(out, grad_alpha=cot)["vertices"]
    assert np.isfinite(g).all()
    assert (out.alpha[0] > 1 - 1e-12).sum() > 50    # many pixels where 200 faces have D ~ 1

    def loss(v):
        return float((raster.forward(v, faces).alpha * cot).sum())

    h = 1e-6
    for vertex, coord in [(3 * 7 + 1, 0), (3 * 7 + 2, 1), (3 * 7, 1), (3 * 8 + 2, 0)]:
        vp, vm = verts.copy(), verts.copy()
        vp[vertex, coord] += h
        vm[vertex, coord] -= h
        fd = (loss(vp) - loss(vm)) / (2 * h)
        assert g[vertex, coord] == pytest.approx(fd, rel=1e-6, abs=1e-9), (vertex, coord, g[vertex, coord], fd)
    assert abs(g[3 * 7 + 1, 0]) > 1e-3   # the displaced face does move alpha


# ---- image sizes -----------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("sigma", [1e-5, 1e-1])
def test_one_by_one_image(dtype, sigma):
    verts, faces, colors = overlap_scene(8)
    verts[:3, :2] = [[-0.5, -0.5], [0.5, -0.5], [0.0, 0.5]]   # covers the single pixel centre (0, 0)
    s, out, _ = run(verts, faces, colors, image_size=(1, 1), sigma=sigma, gamma=1e-3, dist_eps=0.0,
                    background=BG, dtype=dtype)
    assert out.rgb.shape == (1, 1, 1, 3) and out.alpha.shape == (1, 1, 1) and out.depth.shape == (1, 1, 1)
    check_ranges(s, out, colors)
    assert out.alpha[0, 0, 0] > (0.99 if sigma < 1e-3 else 0.5)
    if dtype == "float64":
        check_reference(s, out, verts, faces, colors)


def check_2048_square_image(dtype):
    """Forward + backward at 2048 x 2048; run in a child process by the test below."""
    verts, faces = screen_space_sphere(2, colors=False)   # 320 faces, radius 0.8
    # alpha only, small cut-off footprint (D >= 1e-4 within ~1e-3 NDC of a face): a few seconds
    s, out, g = run(verts, faces, image_size=(2048, 2048), sigma=1e-7, dist_eps=1e-4, outputs=("alpha",),
                    dtype=dtype)
    check_ranges(s, out)
    a = out.alpha[0]
    x, y = pixel_xy(np.arange(2048)[None, :], np.arange(2048)[:, None], 2048, 2048)
    r = np.hypot(x, y)
    # inside the silhouette every pixel is inside a face (D = 1) or on a shared edge / vertex
    # (at least two faces at D >= 1/2): alpha >= 3/4; beyond the sphere's radius nothing
    assert a[r < 0.7].min() >= 0.75 - 1e-6, a[r < 0.7].min()
    assert a[r > 0.805].max() == 0.0
    # the front faces tile the silhouette: pixels with alpha > 1/2 (pixel side 1/1024 NDC)
    # cover their total area, up to the perimeter's pixel quantisation
    tri = verts[faces][..., :2]
    area2 = ((tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1])
             - (tri[:, 2, 0] - tri[:, 0, 0]) * (tri[:, 1, 1] - tri[:, 0, 1]))
    assert (a > 0.5).sum() / 1024 ** 2 == pytest.approx(area2[area2 > 0].sum() / 2, rel=2e-3)
    assert np.abs(g["vertices"]).max() > 0


@pytest.mark.parametrize("dtype", DTYPES)
def test_2048_square_image(dtype):
    # in a child process: a crash in the OpenCL driver must fail this test, not end the session
    code = f"import test_hard_cases as t; t.check_2048_square_image({dtype!r}); print('done')"
    proc = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).parent, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("done"), (
        f"2048x2048 {dtype} forward+backward: exit code {proc.returncode}"
        f" ({_signal_name(proc.returncode)})\n{proc.stderr[-3000:]}")


def _signal_name(code):
    return signal.Signals(-code).name if code < 0 else "no signal"


# ---- 0 and 200k faces ------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("color_agg", ["softmax", "hard"])
@pytest.mark.parametrize("outputs", [ALL, ("alpha", "depth")])
def test_zero_faces(dtype, color_agg, outputs):
    verts, _, colors = overlap_scene(9)
    s, out, g = run(verts, np.zeros((0, 3), np.int64), colors, image_size=(5, 7), background=BG,
                    color_agg=color_agg, outputs=outputs, dtype=dtype)
    np.testing.assert_array_equal(out.alpha, 0.0)
    np.testing.assert_array_equal(out.depth, s.far)
    assert out.alpha.shape == out.depth.shape == (1, 5, 7)
    assert g["vertices"].shape == verts.shape
    np.testing.assert_array_equal(g["vertices"], 0.0)
    if "rgb" in outputs:
        np.testing.assert_allclose(out.rgb, np.broadcast_to(np.array(BG, dtype), (1, 5, 7, 3)), rtol=0)
        assert g["colors"].shape == colors.shape
        np.testing.assert_array_equal(g["colors"], 0.0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_200k_faces(dtype):
    n = 200_000
    rng = np.random.default_rng(10)
    centres = rng.uniform(-1.05, 1.05, (n, 1, 2))
    tri = centres + rng.uniform(0.003, 0.01) * np.array([[0.0, 1.0], [-0.87, -0.5], [0.87, -0.5]])
    verts = np.concatenate([tri + rng.normal(0, 1e-3, tri.shape), rng.uniform(2, 5, (n, 3, 1))], -1)
    verts = verts.reshape(-1, 3)
    faces = np.arange(3 * n).reshape(-1, 3)
    faces[::2] = faces[::2, ::-1]          # half of them clockwise: drawn double-sided
    s, out, g = run(verts, faces, image_size=(256, 256), sigma=1e-6, dist_eps=1e-3, outputs=("alpha",),
                    double_sided=True, dtype=dtype)
    check_ranges(s, out)
    assert out.alpha.mean() > 0.5   # 200k faces of ~4e-5 NDC^2 each cover most of the 4 NDC^2
    assert np.count_nonzero(g["vertices"]) > 0
