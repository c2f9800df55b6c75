"""`bench body-photo`'s pieces that need no detector: the Procrustes error, the dressed synthetic
person and the targets' verdicts."""
import numpy as np
import pytest

from softras_cl.bench.body_photo import clothing_colors, procrustes_error, synthetic_photo, targets_reached
from softras_cl.scene.rotation import axis_angle_to_matrix


def test_procrustes_error_ignores_a_similarity_and_sees_a_bend():
    rng = np.random.default_rng(0)
    true = rng.normal(size=(24, 3))
    moved = 1.7 * true @ axis_angle_to_matrix([0.3, -1.1, 0.4]).T + [1.0, -2.0, 0.5]
    assert procrustes_error(moved, true) == pytest.approx(0.0, abs=1e-12)
    bent = true.copy()
    bent[5] += [0.3, 0.0, 0.0]
    assert 0.005 < procrustes_error(bent, true) < 0.05
    assert procrustes_error(true * [1, 1, -1], true) > 0.1        # a mirror is not a rotation


def test_a_synthetic_photo_is_a_dressed_person_over_a_photo(demo_body_model):
    sample = synthetic_photo(demo_body_model, np.random.default_rng(2), 96, 30.0)
    image, mask = sample["image"], sample["mask"]
    assert image.shape == (96, 96, 3) and image.dtype == np.uint8 and 0.05 < mask.mean() < 0.6
    assert image[~mask].std() > 5                                 # a real photo behind, not a flat colour
    colors = clothing_colors(demo_body_model, np.random.default_rng(2))
    assert len(np.unique(colors.round(3), axis=0)) >= 5           # skin, shirt, trousers, shoes, hair, eyes...


def test_targets_compare_full_with_keypoints_only():
    summary = dict(full=dict(pa_mpjpe_mm=55.0, median_seconds=4.0), keypoints=dict(pa_mpjpe_mm=70.0))
    assert targets_reached(summary) == dict(pa_mpjpe_le_60mm=True, median_le_5s=True,
                                            better_than_keypoints_only_mm=15.0)
    assert targets_reached(dict(full=dict(pa_mpjpe_mm=61.0, median_seconds=6.0)))["pa_mpjpe_le_60mm"] is False
