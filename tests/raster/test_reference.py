"""Tests of the dense numpy reference rasteriser on its own, against hand-computed expectations."""
import math

import numpy as np
import pytest

from softras_cl.raster.reference import pixel_centers, soft_rasterize
from softras_cl.raster.settings import RasterSettings

# CCW right triangle, legs on x = -1 and y = -1, hypotenuse x + y = 0.1
BIG = np.array([[-1.0, -1.0, 2.0], [1.1, -1.0, 2.0], [-1.0, 1.1, 2.0]])
# CCW right triangle, legs on x = -1 and y = -1, hypotenuse x + y = 0
HALF = np.array([[-1.0, -1.0, 2.0], [1.0, -1.0, 2.0], [-1.0, 1.0, 2.0]])
ONE_FACE = np.array([[0, 1, 2]])
RGB = np.eye(3)  # vertex colours red, green, blue


def sigmoid(x):
    return 1.0 / (1.0 + math.exp(-x))


def render(vertices, faces, colors=None, **kw):
    kw.setdefault("outputs", ("rgb", "alpha", "depth"))
    return soft_rasterize(np.asarray(vertices, float), np.asarray(faces), RasterSettings(**kw), colors=colors)


def test_pixel_centres_non_square():
    p = pixel_centers(3, 5)  # H = 3, W = 5, s = 3
    assert p.shape == (3, 5, 2)
    for r in range(3):
        for i in range(5):
            assert p[r, i, 0] == pytest.approx((2 * (i + 0.5) - 5) / 3)
            assert p[r, i, 1] == pytest.approx((3 - 2 * (r + 0.5)) / 3)
    assert p[0, 0, 0] == pytest.approx(-4 / 3) and p[0, 0, 1] == pytest.approx(2 / 3)  # top-left


@pytest.mark.parametrize("row, col", [(0, 0), (0, 4), (2, 3), (1, 2)])
def test_tiny_triangle_lights_one_pixel_of_non_square_image(row, col):
    x, y = (2 * (col + 0.5) - 5) / 3, (3 - 2 * (row + 0.5)) / 3
    tri = [[x - 0.1, y - 0.1, 2], [x + 0.1, y - 0.1, 2], [x, y + 0.1, 2]]
    out = render(tri, ONE_FACE, image_size=(3, 5), sigma=1e-9, outputs=("alpha",))
    expected = np.zeros((1, 3, 5))
    expected[0, row, col] = 1.0
    np.testing.assert_allclose(out["alpha"], expected, atol=1e-12)
    assert out["rgb"] is None and out["depth"] is None


def test_big_triangle_alpha_rgb_depth():
    bg = (0.2, 0.3, 0.4)
    out = render(BIG, ONE_FACE, RGB, image_size=(4, 4), sigma=1e-10, gamma=1e-4, background=bg)
    p = pixel_centers(4, 4)
    inside = (p[..., 0] + p[..., 1]) <= 0.1  # the hypotenuse is the only edge near the image
    np.testing.assert_allclose(out["alpha"][0], inside.astype(float), atol=1e-12)
    np.testing.assert_allclose(out["rgb"][0][~inside], np.broadcast_to(bg, (np.sum(~inside), 3)), atol=1e-12)
    np.testing.assert_allclose(out["depth"][0], np.where(inside, 2.0, 100.0), atol=1e-9)
    # pixel (row 2, col 1) is at (-0.25, -0.25): b1 = b2 = 0.75 / 2.1, b0 = 0.6 / 2.1
    np.testing.assert_allclose(out["rgb"][0, 2, 1], [0.6 / 2.1, 0.75 / 2.1, 0.75 / 2.1], atol=1e-9)


def test_single_sided_drops_clockwise_face():
    cw = BIG[[0, 2, 1]]
    cw_colors = RGB[[0, 2, 1]]
    kw = dict(image_size=(4, 4), sigma=1e-6, gamma=1e-3)
    ccw = render(BIG, ONE_FACE, RGB, **kw)
    dropped = render(cw, ONE_FACE, cw_colors, **kw)
    kept = render(cw, ONE_FACE, cw_colors, double_sided=True, **kw)
    assert np.all(dropped["alpha"] == 0) and np.all(dropped["rgb"] == 0) and np.all(dropped["depth"] == 100)
    for name in ("rgb", "alpha", "depth"):
        np.testing.assert_allclose(kept[name], ccw[name], atol=1e-12)
    assert ccw["alpha"].max() > 0.5


@pytest.mark.parametrize("metric, inside_d2, outside_d2", [
    ("barycentric", 0.25 ** 2, 0.5 ** 2),  # min b: 0.25 at (-0.5, -0.5); -0.5 at (0.5, 0.5)
    ("euclidean", 0.5 ** 2, 0.5),  # to x = -1 / y = -1; to the hypotenuse x + y = 0
])
def test_distance_metric_values(metric, inside_d2, outside_d2):
    sigma = 0.7
    out = render(HALF, ONE_FACE, image_size=(2, 2), sigma=sigma, metric=metric, dist_eps=0.0, outputs=("alpha",))
    assert out["alpha"][0, 1, 0] == pytest.approx(sigmoid(inside_d2 / sigma), rel=1e-12)  # (-0.5, -0.5)
    assert out["alpha"][0, 0, 1] == pytest.approx(sigmoid(-outside_d2 / sigma), rel=1e-12)  # (0.5, 0.5)


def test_softmax_tiny_gamma_picks_nearer_face():
    near_tri, far_tri = BIG.copy(), BIG.copy()
    near_tri[:, 2], far_tri[:, 2] = 3.0, 7.0
    verts = np.concatenate([far_tri, near_tri])  # the farther face comes first
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    colors = np.array([[0, 1, 0]] * 3 + [[1, 0, 0]] * 3, float)
    for agg in ("softmax", "hard"):
        out = render(verts, faces, colors, image_size=(4, 4), sigma=1e-10, gamma=1e-5, color_agg=agg)
        np.testing.assert_allclose(out["rgb"][0, 3, 0], [1, 0, 0], atol=1e-12)
        assert out["depth"][0, 3, 0] == pytest.approx(3.0, abs=1e-9)


def test_hard_ties_take_lowest_face_index():
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    colors = np.array([[0, 1, 0]] * 3 + [[1, 0, 0]] * 3, float)
    out = render(np.concatenate([BIG, BIG]), faces, colors, image_size=(4, 4), color_agg="hard")
    np.testing.assert_array_equal(out["rgb"][0, 3, 0], [0, 1, 0])


def test_softmax_weights_by_hand():
    # pixel (row 1, col 0) at (-0.5, -0.5): inside HALF (d2 0.25), outside the flipped copy (d2 0.5)
    other = np.array([[1.0, 1.0, 5.0], [-1.0, 1.0, 5.0], [1.0, -1.0, 5.0]])
    verts, faces = np.concatenate([HALF, other]), np.array([[0, 1, 2], [3, 4, 5]])
    colors = np.array([[1, 0, 0]] * 3 + [[0, 0, 1]] * 3, float)
    sigma, gamma, eps, bg = 0.5, 0.3, 0.02, (0.0, 1.0, 0.0)
    out = render(verts, faces, colors, image_size=(2, 2), sigma=sigma, gamma=gamma, eps=eps, near=1.0,
                 far=10.0, background=bg, dist_eps=0.0)
    d1, d2 = sigmoid(0.25 / sigma), sigmoid(-0.5 / sigma)
    e1, e2, eb = d1 * math.exp((10 - 2) / 9 / gamma), d2 * math.exp((10 - 5) / 9 / gamma), math.exp(eps / gamma)
    total = e1 + e2 + eb
    np.testing.assert_allclose(out["rgb"][0, 1, 0], [e1 / total, eb / total, e2 / total], rtol=1e-12)
    assert out["depth"][0, 1, 0] == pytest.approx((2 * e1 + 5 * e2 + 10 * eb) / total, rel=1e-12)
    assert out["alpha"][0, 1, 0] == pytest.approx(1 - (1 - d1) * (1 - d2), rel=1e-12)


def test_occupancy_and_sum_alpha():
    verts, faces = np.concatenate([HALF, HALF]), np.array([[0, 1, 2], [3, 4, 5]])
    kw = dict(image_size=(2, 2), sigma=0.4, dist_eps=0.0, outputs=("alpha",))
    d_out, d_in = sigmoid(-0.5 / 0.4), sigmoid(0.25 / 0.4)  # at (0.5, 0.5) and (-0.5, -0.5)
    occ = render(verts, faces, alpha_agg="occupancy", **kw)["alpha"][0]
    assert occ[0, 1] == pytest.approx(1 - (1 - d_out) ** 2, rel=1e-12)
    assert occ[1, 0] == pytest.approx(1 - (1 - d_in) ** 2, rel=1e-12)
    total = render(verts, faces, alpha_agg="sum", **kw)["alpha"][0]
    assert total[0, 1] == pytest.approx(2 * d_out, rel=1e-12)
    assert total[1, 0] == 1.0  # 2 * d_in > 1 is clamped
    hard = render(verts, faces, alpha_agg="hard", **kw)["alpha"][0]
    np.testing.assert_array_equal(hard, [[1, 0], [1, 1]])


@pytest.mark.parametrize("perspective", [True, False])
def test_depth_and_color_interpolation(perspective):
    tri = HALF.copy()
    tri[:, 2] = [2.0, 4.0, 8.0]
    for agg in ("softmax", "hard"):
        out = render(tri, ONE_FACE, RGB, image_size=(2, 2), sigma=1e-10, gamma=1e-6, color_agg=agg,
                     perspective_correct=perspective)
        b = np.array([0.5, 0.25, 0.25])  # at pixel (-0.5, -0.5)
        if perspective:
            z = 1.0 / np.sum(b / tri[:, 2])
            weights = b / tri[:, 2] * z
        else:
            z, weights = np.sum(b * tri[:, 2]), b
        assert out["depth"][0, 1, 0] == pytest.approx(z, rel=1e-9)
        np.testing.assert_allclose(out["rgb"][0, 1, 0], weights, rtol=1e-9)
    # outside pixel (0.5, 0.5): b = (-0.5, 0.75, 0.75), clipped and renormalised to (0, 0.5, 0.5)
    out = render(tri, ONE_FACE, RGB, image_size=(2, 2), sigma=1.0, gamma=1e-6, perspective_correct=perspective)
    if perspective:
        z, weights = 1.0 / (0.5 / 4 + 0.5 / 8), [0.0, 2 / 3, 1 / 3]
    else:
        z, weights = 0.5 * 4 + 0.5 * 8, [0.0, 0.5, 0.5]
    assert out["depth"][0, 0, 1] == pytest.approx(z, rel=1e-9)
    np.testing.assert_allclose(out["rgb"][0, 0, 1], weights, rtol=1e-9, atol=1e-12)


def test_depth_range_skips_pairs_and_drops_faces():
    tri = HALF.copy()
    tri[:, 2] = [0.5, 0.5, 4.0]  # straddles near = 1: not dropped, but Z < 1 at some pixels
    out = render(tri, ONE_FACE, RGB, image_size=(2, 2), sigma=1e-10, gamma=1e-6, alpha_agg="occupancy")
    # (-0.5, -0.5) is inside, b = (.5, .25, .25), Z = 1 / (1 + .5 + 1/16) < near: skipped
    assert out["alpha"][0, 1, 0] == 0.0 and out["depth"][0, 1, 0] == 100.0
    # (-0.5, 0.5) is on the hypotenuse (D = 0.5), b = (0, .25, .75), Z = 1 / (.5 + .1875) >= near: kept
    assert out["alpha"][0, 0, 0] == pytest.approx(0.5, rel=1e-12)
    assert out["depth"][0, 0, 0] == pytest.approx(1 / 0.6875, rel=1e-9)
    for z in ([0.0, 2, 2], [-1, 2, 2], [0.5, 0.6, 0.9], [101, 102, 200]):
        tri[:, 2] = z
        out = render(tri, ONE_FACE, RGB, image_size=(2, 2), sigma=1.0, alpha_agg="sum", dist_eps=0.0)
        assert np.all(out["alpha"] == 0)


def test_face_texture_nearest_texel():
    tex = np.arange(2 * 2 * 3, dtype=float).reshape(1, 1, 2, 2, 3)
    settings = RasterSettings(image_size=(2, 2), sigma=1e-10, texture="face", color_agg="hard", outputs=("rgb",))
    out = soft_rasterize(HALF, ONE_FACE, settings, face_textures=tex)
    # (-0.5, -0.5): a = (0.5, 0.25, 0.25) -> i = floor(0.5 * 2) = 1, j = floor(0.25 * 2) = 0
    np.testing.assert_array_equal(out["rgb"][0, 1, 0], tex[0, 0, 1, 0])
    # (0.5, -0.5): b = (0, 0.75, 0.25) -> i = 0, j = min(floor(1.5), 1) = 1
    np.testing.assert_array_equal(out["rgb"][0, 1, 1], tex[0, 0, 0, 1])


def test_uv_bilinear_sampling():
    image = np.random.default_rng(0).random((1, 4, 4, 3))
    uvs = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    settings = RasterSettings(image_size=(2, 2), sigma=1e-10, texture="uv", color_agg="hard", outputs=("rgb",))
    out = soft_rasterize(HALF, ONE_FACE, settings, texture_image=image, uvs=uvs)
    # (-0.5, -0.5): uv = (0.25, 0.25) -> fx = 0.5, fy = 2.5: the mean of rows 2-3, columns 0-1
    np.testing.assert_allclose(out["rgb"][0, 1, 0], image[0, 2:4, 0:2].mean(axis=(0, 1)), rtol=1e-12)
    # every vertex at uv (0, 1), the top-left corner: clamp-to-edge gives texel [0, 0]
    out = soft_rasterize(HALF, ONE_FACE, settings, texture_image=image, uvs=np.tile([0.0, 1.0], (3, 1)))
    np.testing.assert_allclose(out["rgb"][0, 1, 0], image[0, 0, 0], rtol=1e-12)


def test_dist_eps_cut_off():
    # at (0.5, 0.5) D = sigmoid(-0.5 / 0.1) = 0.0067
    kw = dict(image_size=(2, 2), sigma=0.1, gamma=10.0, background=(0.5, 0.5, 0.5))
    cut = render(HALF, ONE_FACE, RGB, dist_eps=0.01, **kw)
    assert cut["alpha"][0, 0, 1] == 0.0 and cut["depth"][0, 0, 1] == 100.0
    np.testing.assert_array_equal(cut["rgb"][0, 0, 1], [0.5, 0.5, 0.5])
    kept = render(HALF, ONE_FACE, RGB, dist_eps=0.001, **kw)
    assert kept["alpha"][0, 0, 1] == pytest.approx(sigmoid(-5.0), rel=1e-12)
    assert not np.allclose(kept["rgb"][0, 0, 1], 0.5)


def test_zero_faces_give_background():
    bg = (0.1, 0.2, 0.3)
    for agg in ("softmax", "hard"):
        out = render(HALF, np.zeros((0, 3), int), RGB, image_size=(3, 2), background=bg, color_agg=agg)
        np.testing.assert_array_equal(out["alpha"], 0.0)
        np.testing.assert_array_equal(out["depth"], 100.0)
        np.testing.assert_allclose(out["rgb"], np.broadcast_to(bg, (1, 3, 2, 3)), rtol=1e-15)


def test_batch_axes_broadcast():
    second = HALF * [1, -1, 1]  # mirrored: clockwise, so dropped single-sided
    verts = np.stack([BIG, second])
    batched = render(verts, ONE_FACE, RGB, image_size=(3, 4), sigma=1e-3, double_sided=True)
    for k in range(2):
        single = render(verts[k], ONE_FACE, RGB, image_size=(3, 4), sigma=1e-3, double_sided=True)
        for name in ("rgb", "alpha", "depth"):
            np.testing.assert_allclose(batched[name][k], single[name][0], rtol=1e-15)
    per_batch_faces = render(verts, np.stack([ONE_FACE, ONE_FACE]), np.stack([RGB, RGB]), image_size=(3, 4),
                             sigma=1e-3, double_sided=True)
    for name in ("rgb", "alpha", "depth"):
        np.testing.assert_array_equal(per_batch_faces[name], batched[name])


@pytest.mark.parametrize("metric", ["euclidean", "barycentric"])
@pytest.mark.parametrize("color_agg", ["softmax", "hard"])
@pytest.mark.parametrize("alpha_agg", ["occupancy", "sum", "hard"])
@pytest.mark.parametrize("sigma, gamma", [(1e-10, 1e-8), (1.0, 10.0), (1e-10, 10.0), (1.0, 1e-8)])
def test_extremes_stay_finite(metric, color_agg, alpha_agg, sigma, gamma):
    rng = np.random.default_rng(1)
    verts = np.concatenate([
        rng.uniform(-1.5, 1.5, (12, 2)), 10.0 ** rng.uniform(-6, 6, (12, 1))], axis=1)
    verts[3:6] = [[0.2, 0.2, 2.0], [0.2, 0.2, 2.0], [0.5, 0.5, 3.0]]  # zero-area face
    verts[6:9, 2] = [0.0, -1.0, 5.0]  # a face with z <= 0
    verts[9:12] = [[-1, -1, 1e-6], [1, -1, 1e6], [-1, 1, 1e-6]]  # huge depth ratio
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11], [0, 2, 1], [11, 1, 3]])
    settings = RasterSettings(image_size=(5, 7), sigma=sigma, gamma=gamma, near=1e-7, far=1e7, dist_eps=0.0,
                              metric=metric, color_agg=color_agg, alpha_agg=alpha_agg, double_sided=True,
                              outputs=("rgb", "alpha", "depth"))
    with np.errstate(over="raise", divide="raise", invalid="raise"):  # underflow to 0 is fine
        out = soft_rasterize(verts, faces, settings, colors=rng.random((12, 3)))
    for name in ("rgb", "alpha", "depth"):
        assert np.all(np.isfinite(out[name])), name
    assert np.all((out["alpha"] >= 0) & (out["alpha"] <= 1))
    assert np.all((out["depth"] >= 1e-7) & (out["depth"] <= 1e7 * (1 + 1e-12)))
