"""OpenCL soft rasteriser against the dense float64 reference (forward) and against central finite
differences in float64 (backward), on random meshes with overlapping and occluded faces."""
import numpy as np
import pyopencl as cl
import pytest

from softras_cl import RasterSettings, SoftRasterizer
from softras_cl.raster import reference

OUTPUTS = ("rgb", "alpha", "depth")
H, W = 13, 18  # non-square, not a multiple of the 8-pixel tile


def random_scene(seed, batch=2, n_vertices=12, n_faces=10, texture="vertex"):
    """Screen-space triangles spread over the image at depths 2..4 (they overlap and occlude)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-1.1, 1.1, (batch, n_vertices, 2)) * [W / H, 1.0]
    z = rng.uniform(2.0, 4.0, (batch, n_vertices, 1))
    vertices = np.concatenate([xy, z], -1)
    faces = rng.integers(0, n_vertices, (n_faces, 3))
    faces = faces[np.array([len(set(f)) == 3 for f in faces])]
    colors = {
        "vertex": dict(colors=rng.uniform(0, 1, (batch, n_vertices, 3))),
        "face": dict(face_textures=rng.uniform(0, 1, (batch, len(faces), 3, 3, 3))),
        "uv": dict(texture_image=rng.uniform(0, 1, (batch, 5, 7, 3)),
                   uvs=rng.uniform(-0.1, 1.1, (batch, n_vertices, 2))),
    }[texture]
    return vertices, faces, colors


def settings(**kw):
    base = dict(image_size=(H, W), sigma=2e-3, gamma=3e-2, dist_eps=0.0, near=1.0, far=10.0,
                double_sided=True, outputs=OUTPUTS, dtype="float64", background=(0.2, 0.3, 0.4))
    base.update(kw)
    return RasterSettings(**base)


VARIANTS = [
    dict(),
    dict(metric="barycentric"),
    dict(alpha_agg="sum", sigma=1e-4),
    dict(perspective_correct=False),
    dict(double_sided=False),
    dict(color_agg="hard", alpha_agg="hard"),
    dict(texture="face"),
    dict(texture="uv"),
    dict(texture="uv", metric="barycentric", perspective_correct=False),
    dict(outputs=("alpha",)),
    dict(outputs=("depth",)),
]


# kernel work layouts (RasterSettings.layout): both run on any device, so both are tested here
LAYOUTS = ("cpu", "gpu")


def _ids(variants):
    return [",".join(f"{k}={v}" for k, v in d.items()) or "default" for d in variants]


def _variant_scene(variant: dict, layout: str, seed: int):
    """(settings of `variant` on `layout`, vertices (B, V, 3), faces (F, 3), the colour input by
    name: {} when the variant draws no rgb) of random_scene(seed)."""
    s = settings(layout=layout, **variant)
    vertices, faces, colors = random_scene(seed, texture=s.texture)
    return s, vertices, faces, colors if "rgb" in s.outputs else {}


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("variant", VARIANTS, ids=_ids(VARIANTS))
def test_forward_matches_reference_float64(variant, layout):
    s, vertices, faces, colors = _variant_scene(variant, layout, 0)
    out = SoftRasterizer(s).forward(vertices, faces, **colors)
    ref = reference.soft_rasterize(vertices, faces, s, **colors)
    for name in s.outputs:
        got, want = getattr(out, name), ref[name]
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * max(1.0, np.abs(want).max()),
                                   err_msg=name)
    assert 0.01 < ref["alpha" if "alpha" in s.outputs else s.outputs[0]].std()  # scene not empty


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("gamma", [3e-2, 1e-4])
def test_float32_matches_float64(gamma, layout):
    """float32 kernels within 1e-4 of the float64 reference at gamma = 3e-2. At gamma = 1e-4 the
    exponent zn / gamma (up to 1e4) carries float32's rounding (1e4 * 6e-8 = 6e-4 relative) into
    the softmax weights, so there the stated tolerance is 2e-3."""
    s = settings(dtype="float32", gamma=gamma, layout=layout)
    vertices, faces, colors = random_scene(1)
    out = SoftRasterizer(s).forward(vertices, faces, **colors)
    ref = reference.soft_rasterize(vertices, faces, s, **colors)
    tol = 1e-4 if gamma > 1e-3 else 2e-3
    np.testing.assert_allclose(out.rgb, ref["rgb"], atol=tol)
    np.testing.assert_allclose(out.alpha, ref["alpha"], atol=tol)
    np.testing.assert_allclose(out.depth, ref["depth"], rtol=tol)


def test_cutoff_error_is_bounded_by_dist_eps():
    """Skipping pairs with D < dist_eps changes alpha by at most about (faces) * dist_eps."""
    vertices, faces, colors = random_scene(2)
    exact = SoftRasterizer(settings()).forward(vertices, faces, **colors)
    cut = SoftRasterizer(settings(dist_eps=1e-4)).forward(vertices, faces, **colors)
    err = np.abs(exact.alpha - cut.alpha).max()
    assert 0 < err <= len(faces) * 1e-4


def test_sharp_limit_equals_hard_zbuffer_away_from_edges():
    """At sigma=1e-9, gamma=1e-8 the soft image is the z-buffer image except at edge pixels."""
    vertices, faces, colors = random_scene(3)
    sharp = dict(sigma=1e-9, gamma=1e-8, dist_eps=1e-4)
    soft = SoftRasterizer(settings(**sharp)).forward(vertices, faces, **colors)
    hard = SoftRasterizer(settings(color_agg="hard", alpha_agg="hard", **sharp)).forward(
        vertices, faces, **colors)
    tri = reference.gather_corners(vertices, np.broadcast_to(faces, (2, *faces.shape)))
    d2 = reference.squared_edge_distance(reference.pixel_centers(H, W), tri).min(-1)
    interior = d2 > (1e-3) ** 2       # farther than 1e-3 NDC from every edge
    assert interior.mean() > 0.8
    np.testing.assert_allclose(soft.rgb[interior], hard.rgb[interior], atol=1e-6)
    np.testing.assert_allclose(soft.alpha[interior], hard.alpha[interior], atol=1e-6)
    np.testing.assert_allclose(soft.depth[interior], hard.depth[interior], rtol=1e-6)


# ---- adjoints against central finite differences -------------------------------------------
def _cotangents(s, seed, batch=2):
    rng = np.random.default_rng(seed)
    shapes = dict(rgb=(batch, H, W, 3), alpha=(batch, H, W), depth=(batch, H, W))
    return {f"grad_{n}": rng.normal(size=shapes[n]) * (0.1 if n == "depth" else 1.0) for n in s.outputs}


def _loss(raster, vertices, faces, colors, cot):
    out = raster.forward(vertices, faces, **colors)
    return sum((getattr(out, name[5:]) * g).sum() for name, g in cot.items())


def _central_difference(f, x, indices, h=1e-6):
    grad = np.zeros(len(indices))
    for n, i in enumerate(indices):
        xp, xm = x.copy(), x.copy()
        xp.flat[i] += h
        xm.flat[i] -= h
        grad[n] = (f(xp) - f(xm)) / (2 * h)
    return grad


def _color_key(s):
    return {"vertex": "colors", "face": "face_textures", "uv": "texture_image"}[s.texture]


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("variant", VARIANTS, ids=_ids(VARIANTS))
def test_gradients_match_finite_differences(variant, layout):
    s, vertices, faces, colors = _variant_scene(variant, layout, 4)
    raster = SoftRasterizer(s)
    cot = _cotangents(s, 5)
    grads = ("vertices", "colors") if colors else ("vertices",)
    g = raster.backward(raster.forward(vertices, faces, grads=grads, **colors), **cot)

    idx = np.arange(vertices.size)
    num = _central_difference(lambda v: _loss(raster, v, faces, colors, cot), vertices, idx)
    assert np.abs(num).max() > 1e-3
    np.testing.assert_allclose(g["vertices"].ravel(), num, rtol=0, atol=1e-6 * np.abs(num).max())

    if colors:
        key = _color_key(s)
        c = colors[key]
        idx = np.random.default_rng(6).choice(c.size, min(c.size, 60), replace=False)
        f = lambda x: _loss(raster, vertices, faces, {**colors, key: x}, cot)
        num = _central_difference(f, c, idx)
        assert g["colors"].shape == c.shape
        np.testing.assert_allclose(g["colors"].ravel()[idx], num, rtol=0, atol=1e-6 * np.abs(num).max())


def test_occluded_faces_receive_gradients():
    """A face entirely hidden behind a nearer one still gets position and depth gradients
    (eq. 11-12), which a z-buffer renderer cannot give."""
    front = [[-0.8, -0.8, 2.0], [0.8, -0.8, 2.0], [0.0, 0.8, 2.0]]
    back = [[-0.3, -0.3, 3.0], [0.3, -0.3, 3.0], [0.0, 0.3, 3.0]]
    vertices = np.array(front + back)
    faces = np.array([[0, 1, 2], [3, 4, 5]])
    colors = np.array([[1.0, 0, 0]] * 3 + [[0, 0, 1.0]] * 3)
    s = settings(image_size=(16, 16), sigma=1e-4, gamma=0.1)
    raster = SoftRasterizer(s)
    out = raster.forward(vertices, faces, colors=colors, grads=("vertices",))
    g = raster.backward(out, grad_rgb=np.ones_like(out.rgb))["vertices"]
    assert np.abs(g[3:, :2]).max() > 1e-6    # hidden face: x, y
    assert np.abs(g[3:, 2]).max() > 1e-6     # hidden face: depth


@pytest.mark.parametrize("layout", LAYOUTS)
def test_results_are_bit_identical_run_to_run(layout):
    for texture in ("vertex", "face", "uv"):
        s = settings(texture=texture, dtype="float32", dist_eps=1e-4, layout=layout)
        vertices, faces, colors = random_scene(7, texture=texture)
        raster = SoftRasterizer(s)
        cot = _cotangents(s, 8)
        runs = []
        for _ in range(3):
            out = raster.forward(vertices, faces, grads=("vertices", "colors"), **colors)
            runs.append((out.rgb, out.alpha, out.depth, *raster.backward(out, **cot).values()))
        for later in runs[1:]:
            for a, b in zip(runs[0], later):
                assert np.array_equal(a, b)


def test_unbatched_inputs_give_unbatched_gradients():
    vertices, faces, colors = random_scene(9, batch=1)
    s = settings()
    raster = SoftRasterizer(s)
    out = raster.forward(vertices[0], faces, colors=colors["colors"][0], grads=("vertices", "colors"))
    assert out.rgb.shape == (1, H, W, 3)
    g = raster.backward(out, **_cotangents(s, 1, batch=1))
    assert g["vertices"].shape == vertices[0].shape and g["colors"].shape == (12, 3)


def test_memory_grows_with_bins_not_pixels_times_faces():
    """Buffers are per pixel, per face and per (tile, face) bin entry: doubling the face count
    of a fixed-footprint mesh does not multiply the bin entries by the tile count."""
    from softras_cl.scene.meshes import screen_space_sphere
    s = RasterSettings(image_size=(256, 256))
    counts = []
    for sub in (3, 4):
        v, f, c = screen_space_sphere(sub)
        out = SoftRasterizer(s).forward(v, f, colors=c, grads=("vertices",))
        counts.append((len(f), out.saved.bins.n_entries))
    (f3, e3), (f4, e4) = counts
    tiles = (256 // 8) ** 2
    assert e3 < 0.05 * f3 * tiles and e4 < 0.05 * f4 * tiles
    assert e4 / e3 < 4.0   # 4x faces, each smaller: fewer than 4x entries


def test_unused_outputs_are_neither_computed_nor_allocated():
    vertices, faces, _ = random_scene(10)
    out = SoftRasterizer(settings(outputs=("alpha",))).forward(vertices, faces, grads=("vertices",))
    assert out.rgb is None and out.depth is None
    assert set(out.saved.images) == {"alpha"}
    assert out.saved.state.color is None     # no softmax normaliser without rgb/depth


def test_fast_math_variant_stays_close_to_exact_maths():
    """-cl-fast-relaxed-math is an accuracy knob; in float32 it stays within 1e-4 here."""
    vertices, faces, colors = random_scene(11)
    exact = SoftRasterizer(settings(dtype="float32")).forward(vertices, faces, **colors)
    fast = SoftRasterizer(settings(dtype="float32", fast_math=True)).forward(vertices, faces, **colors)
    for name in OUTPUTS:
        np.testing.assert_allclose(getattr(fast, name), getattr(exact, name), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("lighting", ["lambert", "sh"])
def test_per_pixel_lighting_forward_and_gradients(lighting, layout):
    """Albedo and normals interpolated per pixel and lit in the kernel: forward against the
    reference, and gradients for positions, albedo, normals and the 27 light parameters
    against finite differences."""
    s = settings(lighting=lighting, layout=layout)
    vertices, faces, colors = random_scene(12)
    rng = np.random.default_rng(13)
    normals = rng.normal(size=(2, 12, 3))
    light = (np.r_[0.3, 0.4, 0.2, 0.6, 0.5, 0.7, 0.48, 0.6, 0.64, np.zeros(18)] if lighting == "lambert"
             else rng.normal(scale=0.4, size=27))
    inputs = dict(colors=colors["colors"], normals=normals, light=light)
    raster = SoftRasterizer(s)
    out = raster.forward(vertices, faces, grads=("vertices", "colors"), **inputs)
    ref = reference.soft_rasterize(vertices, faces, s, **inputs)
    np.testing.assert_allclose(out.rgb, ref["rgb"], rtol=1e-9, atol=1e-9)
    cot = _cotangents(s, 14)
    g = raster.backward(out, **cot)
    assert set(g) == {"vertices", "colors", "normals", "light"}
    loss = lambda **kw: _loss(raster, kw.pop("v", vertices), faces, {**inputs, **kw}, cot)
    for key, value in (("v", vertices), ("colors", inputs["colors"]), ("normals", normals), ("light", light)):
        idx = np.random.default_rng(15).choice(value.size, min(value.size, 30), replace=False)
        num = _central_difference(lambda x: loss(**{key: x}), value, idx)
        got = g["vertices" if key == "v" else key].ravel()[idx]
        np.testing.assert_allclose(got, num, rtol=0, atol=1e-6 * np.abs(num).max(), err_msg=key)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_flat_face_colors_fast_path(layout):
    """R = 1 face textures (flat colour per face) take a lookup-free path in both kernels."""
    s = settings(texture="face", layout=layout)
    vertices, faces, _ = random_scene(16)
    textures = np.random.default_rng(17).uniform(0, 1, (2, len(faces), 1, 1, 3))
    raster = SoftRasterizer(s)
    out = raster.forward(vertices, faces, face_textures=textures, grads=("vertices", "colors"))
    ref = reference.soft_rasterize(vertices, faces, s, face_textures=textures)
    np.testing.assert_allclose(out.rgb, ref["rgb"], rtol=1e-9, atol=1e-9)
    cot = _cotangents(s, 18)
    g = raster.backward(out, **cot)
    f = lambda x: _loss(raster, vertices, faces, {"face_textures": x}, cot)
    num = _central_difference(f, textures, np.arange(textures.size))
    np.testing.assert_allclose(g["colors"].ravel(), num, rtol=0, atol=1e-6 * np.abs(num).max())


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_region_of_interest_renders_its_tiles_bit_identically(dtype, layout):
    """roi: pixels in the tiles holding the region are bit-identical to a full render, the rest
    is background; with cotangents zero outside those tiles the gradients are bit-identical too."""
    from softras_cl.raster.binning import roi_tiles

    s = settings(dtype=dtype, dist_eps=1e-4, sigma=1e-3, image_size=(40, 45), layout=layout)
    vertices, faces, colors = random_scene(11, n_vertices=30, n_faces=60)
    h, w = s.image_size
    roi = np.zeros((h, w), bool)
    roi[9:23, 5:19] = True
    raster = SoftRasterizer(s)
    g = raster.grid
    in_tiles = np.repeat(np.repeat(roi_tiles(roi, 1, g, s).reshape(g.nty, g.ntx), 8, 0), g.tile_w, 1)[:h, :w]
    assert in_tiles.sum() > roi.sum() and not in_tiles.all()
    full = raster.forward(vertices, faces, grads=("vertices", "colors"), **colors)
    part = raster.forward(vertices, faces, grads=("vertices", "colors"), roi=roi, **colors)
    for a, b, bg in ((full.rgb, part.rgb, s.background), (full.alpha, part.alpha, 0.0), (full.depth, part.depth, s.far)):
        assert np.array_equal(a[:, in_tiles], b[:, in_tiles])
        assert np.all(b[:, ~in_tiles] == np.asarray(bg, b.dtype))
    rng = np.random.default_rng(3)
    cot = {f"grad_{n}": rng.normal(size=(2, h, w, 3) if n == "rgb" else (2, h, w)) for n in s.outputs}
    cot = {k: np.where(roi[None, :, :, None] if v.ndim == 4 else roi[None], v, 0.0) for k, v in cot.items()}
    g_full, g_part = raster.backward(full, **cot), raster.backward(part, **cot)
    for k in g_full:
        assert np.array_equal(g_full[k], g_part[k]), k
    with pytest.raises(ValueError, match="roi"):
        raster.forward(vertices, faces, roi=np.ones((h, w + 1), bool), **colors)


LANE_VARIANTS = [dict(), dict(texture="face"), dict(texture="uv"), dict(color_agg="hard", alpha_agg="sum", sigma=1e-4)]


@pytest.mark.parametrize("variant", LANE_VARIANTS, ids=_ids(LANE_VARIANTS))
def test_float32_lane_widths_render_the_same_images(variant):
    """8 and 16 floats per kernel vector: on a CPU device bit-identical images (the same
    arithmetic per pixel); where a compiler scalarises the vectors it may fuse multiply-adds
    differently per width (NVIDIA's OpenCL: up to 3 ulp), so elsewhere within 1e-6 of the largest
    value. Gradients equal up to float32 rounding (their per-tile sums group the pixels differently)."""
    s = settings(dtype="float32", dist_eps=1e-4, layout="cpu", **variant)
    vertices, faces, colors = random_scene(4, texture=s.texture)
    rng = np.random.default_rng(1)
    results = []
    for lanes in (8, 16):
        raster = SoftRasterizer(s, lanes=lanes)
        assert raster.grid.tile_w == lanes
        out = raster.forward(vertices, faces, grads=("vertices", "colors"), **colors)
        cot = {f"grad_{n}": np.random.default_rng(2).standard_normal(getattr(out, n).shape) for n in s.outputs}
        results.append((out, raster.backward(out, **cot)))
    (out8, g8), (out16, g16) = results
    on_cpu = raster.device.type & cl.device_type.CPU
    for name in s.outputs:
        a8, a16 = getattr(out8, name), getattr(out16, name)
        np.testing.assert_allclose(a16, a8, rtol=0, atol=0 if on_cpu else 1e-6 * np.abs(a8).max(), err_msg=name)
    for name in g8:
        np.testing.assert_allclose(g16[name], g8[name], rtol=1e-5, atol=1e-5 * np.abs(g8[name]).max())


def test_lanes_must_suit_the_dtype():
    with pytest.raises(ValueError, match=r"lanes must be one of \(4,\) for dtype='float64', got 8"):
        SoftRasterizer(settings(layout="cpu"), lanes=8)
    with pytest.raises(ValueError, match=r"lanes must be one of \(8, 16\) for dtype='float32', got 4"):
        SoftRasterizer(settings(dtype="float32", layout="cpu"), lanes=4)


@pytest.mark.parametrize("variant", [dict(), dict(color_agg="hard", alpha_agg="sum", sigma=1e-4),
                                     dict(outputs=("alpha",))], ids=_ids([{}, {"hard": 1}, {"alpha": 1}]))
@pytest.mark.parametrize("layout", LAYOUTS)
def test_rows_without_cotangents_are_skipped_exactly(variant, layout):
    """The backward skips rows whose cotangents are all zero: each output's cotangent is non-zero
    on its own rows only (a skip that ignored one output's plane would lose its rows), batch item
    1 has a whole tile row of zeros but for one pixel (a check of one lane would lose it), and
    everything zero gives exactly zero gradients."""
    s, vertices, faces, colors = _variant_scene(variant, layout, 4)
    raster = SoftRasterizer(s)
    cot = _cotangents(s, 5)
    for k, g in enumerate(cot.values()):
        g[:, [r for r in range(H) if r % 3 != k]] = 0.0
        g[1, :8] = 0.0
    lone = next(iter(cot.values()))
    lone[1, 5, 13] = 1.0
    grads = ("vertices", "colors") if colors else ("vertices",)
    g = raster.backward(raster.forward(vertices, faces, grads=grads, **colors), **cot)
    num = _central_difference(lambda v: _loss(raster, v, faces, colors, cot), vertices, np.arange(vertices.size))
    assert np.abs(num).max() > 1e-3
    np.testing.assert_allclose(g["vertices"].ravel(), num, rtol=0, atol=1e-6 * np.abs(num).max())
    zero = raster.backward(raster.forward(vertices, faces, grads=grads, **colors),
                           **{n: np.zeros_like(c) for n, c in cot.items()})
    assert all(not v.any() for v in zero.values())
