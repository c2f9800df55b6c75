"""examples/single_view_reconstruction.py and examples/make_shapes_dataset.py: the voxel IoU
against known answers, the data set's meshes and determinism, the torch regularisers against
the numpy ones in softras_cl.fitting.losses, learning through the renderer on a fixed batch,
and a --quick run end to end."""
from __future__ import annotations

import importlib
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture(scope="module")
def shapes():
    sys.path.insert(0, str(EXAMPLES))
    try:
        yield importlib.import_module("make_shapes_dataset")
    finally:
        sys.path.remove(str(EXAMPLES))


@pytest.fixture(scope="module")
def example(shapes):
    pytest.importorskip("torch")
    sys.path.insert(0, str(EXAMPLES))
    try:
        yield importlib.import_module("single_view_reconstruction")
    finally:
        sys.path.remove(str(EXAMPLES))


def _grid_points(shapes):
    c = shapes.grid_centres()
    return np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)


def test_voxel_iou_of_two_offset_cubes_is_one_third(shapes):
    a = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    b = a.copy()
    b.apply_translation((0.5, 0.0, 0.0))
    va, vb = shapes.voxelize(a.vertices, a.faces), shapes.voxelize(b.vertices, b.faces)
    assert va.sum() == 16 ** 3                      # side 1 = 16 cells of 1/16
    assert shapes.voxel_iou(va, vb) == pytest.approx(1.0 / 3.0)
    assert shapes.voxel_iou(va, va) == 1.0


def test_voxelize_sphere_matches_the_ball_and_ignores_winding(shapes):
    v, f = trimesh.creation.icosphere(4, 0.7).vertices, trimesh.creation.icosphere(4, 0.7).faces
    vox = shapes.voxelize(v, f)
    ball = (np.linalg.norm(_grid_points(shapes), axis=1) < 0.7).reshape(vox.shape)
    assert shapes.voxel_iou(vox, ball) > 0.97
    assert np.array_equal(shapes.voxelize(v, f[:, ::-1]), vox)      # inside-out: same cells


def test_voxelize_is_indexed_x_y_z(shapes):
    box = trimesh.creation.box(extents=(1.0, 0.5, 0.25))
    vox = shapes.voxelize(box.vertices, box.faces)
    assert [int(vox.any((1, 2)).sum()), int(vox.any((0, 2)).sum()), int(vox.any((0, 1)).sum())] \
        == [16, 8, 4]


@pytest.mark.parametrize("category", ["box", "cylinder", "ellipsoid", "cone"])
def test_shapes_are_closed_and_voxelize_like_trimesh_contains(shapes, category):
    v, f = shapes.make_shape(category, np.random.default_rng(3))
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert np.linalg.norm(v, axis=1).max() <= 0.8 + 1e-9
    contains = mesh.contains(_grid_points(shapes)).reshape((shapes.GRID,) * 3)
    assert np.array_equal(shapes.voxelize(v, f), contains)


def test_dataset_is_deterministic_and_split(shapes):
    a = shapes.make_dataset(2, 1, views=2, size=16, seed=5)
    b = shapes.make_dataset(2, 1, views=2, size=16, seed=5)
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    assert a["images"].shape == (12, 2, 16, 16, 3) and a["images"].dtype == np.uint8
    assert a["split"].sum() == 4 and np.array_equal(np.bincount(a["category"]), [3, 3, 3, 3])
    assert a["masks"].any((2, 3)).all()             # every shape is seen in every view
    v, f = shapes.mesh(a, 7)
    assert np.array_equal(shapes.voxelize(v, f), a["voxels"][7])


@pytest.mark.torch
def test_torch_regularisers_equal_the_numpy_losses(example):
    import torch
    from softras_cl.fitting import losses
    from softras_cl.scene.meshes import icosphere

    v, f = icosphere(2, 0.6)
    rng = np.random.default_rng(0)
    verts = v + 0.05 * rng.normal(size=(2,) + v.shape)
    reg = example.MeshRegularisers(f, len(v))
    t = torch.tensor(verts, dtype=torch.float64)
    want_lap = np.mean([losses.laplacian(x, f)[0] for x in verts])
    want_flat = np.mean([losses.flatten(x, f)[0] for x in verts])
    assert reg.laplacian(t).item() == pytest.approx(want_lap, rel=1e-9)
    assert reg.flatten(t).item() == pytest.approx(want_flat, rel=1e-9)


@pytest.mark.torch
def test_iou_loss_is_zero_for_equal_masks_and_one_for_disjoint(example):
    import torch

    a = torch.zeros(2, 4, 4)
    a[:, :2] = 1.0
    assert example.iou_loss(a, a).item() == 0.0
    assert example.iou_loss(a, 1.0 - a).item() == 1.0


@pytest.mark.torch
@pytest.mark.slow
def test_quick_run_writes_finite_results(example, tmp_path):
    assert example.main(["--quick", "--out", str(tmp_path)]) == 0
    for name in ("results.json", "figure.png", "model.pt"):
        assert (tmp_path / name).stat().st_size > 0, name
    doc = json.loads((tmp_path / "results.json").read_text())
    assert set(doc["table"]) == {"box", "cylinder", "ellipsoid", "cone", "mean"}
    for row in doc["table"].values():
        for method in ("prediction", "template", "retrieval_image", "retrieval_view"):
            assert 0.0 <= row[method] <= 1.0 and math.isfinite(row[method])
    assert doc["steps"] == 8 and doc["train_seconds"] > 0
    assert all(math.isfinite(h["loss"]) for h in doc["history"])
    assert doc["provenance"]["config"]["quick"] is True


@pytest.mark.torch
@pytest.mark.slow
def test_network_learns_a_fixed_batch_through_the_renderer(example, shapes):
    """Gradients reach the network's weights through softras_cl.torch: on one fixed batch
    (2 shapes, 4 views each, 32x32), 12 Adam steps halve the silhouette loss (0.64 -> 0.15
    when written)."""
    import torch
    from softras_cl.scene.meshes import icosphere

    torch.manual_seed(0)
    data = shapes.make_dataset(1, 0, views=4, size=32, seed=1)
    pick = np.array([0, 3])                                 # a box and a cone
    template = icosphere(3, example.TEMPLATE_RADIUS)
    model = example.Reconstructor(template[0], 32)
    renderer = example.Renderer(example.raster_settings(32, 1e-4, 1e-4), shading="none")
    cams = [c for s in pick for c in shapes.cameras(data["eyes"][s], 32)]
    images = example.as_input(data["images"][pick, 0])
    target = torch.from_numpy(data["masks"][pick].reshape(-1, 32, 32)).float()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    losses = []
    for _ in range(12):
        verts = model(images).repeat_interleave(4, 0)
        loss = example.iou_loss(renderer(verts, template[1], cams).alpha, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0], losses
