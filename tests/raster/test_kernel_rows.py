"""The forward kernel's rows per work-item (rasterizer.FWD_ROWS, the kernel's SR_ROWS): every
choice renders every row exactly once, so images, saved state and gradients are bit-identical to
one row per work-item, which itself matches the float64 reference. Heights that are not a
multiple of the rows, a region of interest per batch item and a batch of two catch a row skipped
or counted twice."""
import numpy as np
import pytest

from softras_cl import SoftRasterizer
from softras_cl.cl.layout import TILE_H
from softras_cl.raster import rasterizer, reference
from tests.raster.test_raster import random_scene, settings

ROWS = [r for r in (1, 2, 4, 8) if TILE_H % r == 0]


def _render(rows, monkeypatch, s, vertices, faces, colors, roi=None):
    """Images and gradients (random cotangents) with `rows` rows per forward work-item."""
    monkeypatch.setattr(rasterizer, "FWD_ROWS", rows)
    raster = SoftRasterizer(s)
    out = raster.forward(vertices, faces, grads=("vertices", "colors"), roi=roi, **colors)
    rng = np.random.default_rng(5)
    cot = {f"grad_{n}": rng.normal(size=getattr(out, n).shape) for n in s.outputs}
    return out, raster.backward(out, **cot)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("height", [13, 22])
def test_rows_per_work_item_render_every_row_once(dtype, height, monkeypatch):
    s = settings(dtype=dtype, image_size=(height, 18), dist_eps=1e-4, sigma=1e-3)
    vertices, faces, colors = random_scene(3, n_vertices=20, n_faces=30)
    roi = np.zeros((2, height, 18), bool)
    roi[0, 3:11, 2:9] = True
    roi[1, 9:, 10:] = True
    ref = reference.soft_rasterize(vertices, faces, s, **colors)
    for mask in (None, roi):
        results = [_render(rows, monkeypatch, s, vertices, faces, colors, mask) for rows in ROWS]
        (out1, g1) = results[0]
        if mask is None and dtype == "float64":
            for name in s.outputs:
                np.testing.assert_allclose(getattr(out1, name), ref[name], rtol=1e-9, atol=1e-9, err_msg=name)
        for rows, (out, g) in zip(ROWS[1:], results[1:]):
            for name in s.outputs:
                assert np.array_equal(getattr(out, name), getattr(out1, name)), (rows, name)
            for name in g1:
                assert np.array_equal(g[name], g1[name]), (rows, name)
