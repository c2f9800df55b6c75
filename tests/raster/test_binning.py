"""Tile binning (softras_cl.raster.binning.bin_faces) against a per-face loop over tiles."""
import numpy as np
import pytest

from softras_cl import RasterSettings
from softras_cl.raster.binning import bin_faces, face_setup, tile_grid
from softras_cl.raster.inputs import check_inputs


def binned(size, lanes, batch=2, n_faces=300, seed=0):
    rng = np.random.default_rng(seed)
    vertices = np.concatenate([rng.uniform(-1, 1, (batch, 3 * n_faces, 2)),
                               rng.uniform(2, 3, (batch, 3 * n_faces, 1))], -1)
    centres = rng.uniform(-1, 1, (batch, n_faces, 1, 2))
    vertices[..., :2] = (centres + 0.02 * vertices[..., :2].reshape(batch, n_faces, 3, 2)).reshape(batch, -1, 2)
    s = RasterSettings(image_size=(size, size), sigma=1e-4, dtype="float64" if lanes == 4 else "float32",
                       double_sided=True, outputs=("alpha",))
    mesh = check_inputs(s, vertices, np.arange(3 * n_faces).reshape(-1, 3))
    geom, drawable = face_setup(mesh, s)
    g = tile_grid(s, lanes)
    return bin_faces(geom, drawable, batch, n_faces, s, g), g, batch


@pytest.mark.parametrize("size, lanes", [(256, 16), (2048, 4)], ids=["16-bit tile ids", "wider tile ids"])
def test_tiles_list_their_faces_in_face_order_and_slots_invert_the_lists(size, lanes):
    """Both sort paths (up to 2^16 tiles, and more: 2 x 512 x 256 here) give each tile its faces
    in increasing order, and face_slots maps every face-major entry to a tile-list entry of the
    same face, each once."""
    bins, g, batch = binned(size, lanes)
    n_tiles = batch * g.ntx * g.nty
    assert (n_tiles <= 2 ** 16) == (size == 256)
    assert len(bins.tile_start) == n_tiles + 1 and len(bins.tile_faces) == bins.n_entries > 1000
    tile_of = np.repeat(np.arange(n_tiles), np.diff(bins.tile_start))
    same_tile = tile_of[1:] == tile_of[:-1]
    assert np.all(bins.tile_faces[1:][same_tile] > bins.tile_faces[:-1][same_tile])
    assert sorted(bins.face_slots.tolist()) == list(range(bins.n_entries))
    face_of = np.repeat(np.arange(len(bins.face_start) - 1), np.diff(bins.face_start))
    assert np.array_equal(bins.tile_faces[bins.face_slots], face_of)


def test_roi_tiles_remembers_the_last_mask_and_still_checks_each():
    from softras_cl.raster.binning import RoiTiles, roi_tiles

    s = RasterSettings(image_size=(20, 30), outputs=("alpha",))
    g = tile_grid(s, 8)
    tiles = RoiTiles(g, s)
    mask = np.zeros((20, 30), bool)
    mask[3:5, 2:4] = True
    first = tiles(mask, 1)
    assert np.array_equal(first, roi_tiles(mask, 1, g, s)) and tiles(mask.copy(), 1) is first
    mask[15, 25] = True                     # changed in place: a new answer
    assert np.array_equal(tiles(mask, 1), roi_tiles(mask, 1, g, s)) and first.sum() == 1
    assert tiles(mask, 2).shape == (2 * g.ntx * g.nty,) and tiles(None, 1) is None
    with pytest.raises(ValueError, match="roi must be a bool mask"):
        tiles(mask.astype(int), 2)
