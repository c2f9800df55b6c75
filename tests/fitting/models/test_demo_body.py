"""The shipped demo body model (fitting/models/data/demo_body.npz) is complete and sane."""
import numpy as np
import pytest
from softras_cl.fitting.models.body_loaders import (
    SMPL_JOINT_NAMES,
)


@pytest.fixture(scope="module")
def model(demo_body_model):
    return demo_body_model


def test_sizes_and_tree(model):
    assert 4000 <= model.n_vertices <= 8000 and model.n_betas >= 10
    assert model.joint_names == list(SMPL_JOINT_NAMES)
    assert model.parents[0] == -1
    assert all(0 <= model.parents[j] < j for j in range(1, model.n_joints))
    assert model.faces.dtype == np.int32 and model.faces.max() < model.n_vertices


def test_single_closed_surface(model):
    edges = np.sort(model.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2), "every edge shared by exactly two faces"
    assert np.array_equal(np.unique(model.faces), np.arange(model.n_vertices))


def test_weights_and_regressor_rows(model):
    assert np.all(model.weights >= 0)
    np.testing.assert_allclose(model.weights.sum(axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.asarray(model.J_regressor.sum(axis=1)).ravel(), 1.0, atol=1e-9)
    assert np.all(model.weights.max(axis=0) > 0.4), "every joint drives some vertices"


def test_rest_joints_inside_and_symmetric(model):
    rest = model.rest_joints(np.zeros(model.n_betas))
    lo, hi = model.v_template.min(axis=0), model.v_template.max(axis=0)
    assert np.all((rest > lo) & (rest < hi))
    assert model.v_template[:, 1].min() == pytest.approx(0.0, abs=1e-9)  # soles at y = 0
    assert 1.5 < hi[1] < 1.9  # an adult, in metres
    for j, name in enumerate(model.joint_names):
        if name.startswith("left_"):
            r = model.joint_names.index("right_" + name[5:])
            np.testing.assert_allclose(rest[j] * [-1, 1, 1], rest[r], atol=0.01, err_msg=name)
            assert rest[j, 0] > 0.02  # the subject's left is +x (facing +z)
        elif not name.startswith("right_"):
            assert abs(rest[j, 0]) < 0.01, name
    head, pelvis = rest[model.joint_names.index("head")], rest[0]
    ankle = rest[model.joint_names.index("left_ankle")]
    assert head[1] > pelvis[1] > ankle[1]
    nose = model.v_template[np.argmax(model.v_template[:, 2] * (model.v_template[:, 1] > 1.4))]
    assert nose[2] > head[2], "faces +z"


def test_posed_forward_moves_the_right_vertices(model):
    pose = np.zeros((model.n_joints - 1, 3))
    elbow = model.joint_names.index("right_elbow")
    pose[elbow - 1] = [0.0, 1.0, 0.0]
    betas = np.zeros(model.n_betas)
    betas[:3] = [1.0, -1.0, 0.5]
    rest = model.forward(betas, np.zeros_like(pose), np.zeros(3), np.zeros(3))[0].vertices
    posed, _ = model.forward(betas, pose, np.zeros(3), np.zeros(3))
    assert np.all(np.isfinite(posed.vertices))
    moved = np.linalg.norm(posed.vertices - rest, axis=1) > 1e-3
    parts = set(np.array(model.part_names)[model.part_labels[moved]])
    assert {"right_forearm", "right_hand"} <= parts <= {"right_forearm", "right_hand",
                                                         "right_upper_arm"}
    forearm = model.part_labels == model.part_names.index("right_forearm")
    assert np.all(moved[model.part_labels == model.part_names.index("right_hand")])
    assert moved[forearm].mean() > 0.5


def test_shape_components_unit_variance_scale(model):
    """Betas of +-2 change the height by centimetres to decimetres, not metres."""
    heights = []
    for s in (-2.0, 2.0):
        b = np.zeros(model.n_betas)
        b[0] = s
        v = model.shaped_vertices(b)
        heights.append(np.ptp(v[:, 1]))
    assert 0.05 < abs(heights[1] - heights[0]) < 1.0


def test_part_labels_cover_all_vertices(model):
    assert 10 <= len(model.part_names) <= 16
    assert model.part_labels.shape == (model.n_vertices,)
    counts = np.bincount(model.part_labels, minlength=len(model.part_names))
    assert np.all(counts > 20), dict(zip(model.part_names, counts))
