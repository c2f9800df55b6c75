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


def test_a_mitsuba_photo_is_the_same_person_lit_by_a_sun(demo_body_model, tmp_path):
    from softras_cl.bench.body_photo import cached_mitsuba_photo, mitsuba_photo
    from softras_cl.io.images import write_image
    from softras_cl.srgb import to_srgb
    from softras_cl.validate.mitsuba import mitsuba_available
    from softras_cl.validate.mitsuba_face import silhouette_iou

    if not mitsuba_available():
        pytest.skip("Mitsuba 3 is not installed")
    sample = synthetic_photo(demo_body_model, np.random.default_rng(2), 96, 30.0)
    render = mitsuba_photo(demo_body_model, sample, 96, 8, seed=5)
    assert silhouette_iou(render["alpha"], sample["mask"]) > 0.85          # same pose, shape and camera
    image = np.round(255 * to_srgb(render["image"])).astype(np.uint8)
    mask = sample["mask"]
    assert np.abs(image[~mask & (render["alpha"] == 0)].astype(int) - sample["image"][~mask & (render["alpha"] == 0)]).max() <= 1
    assert np.abs(image[mask].astype(float) - sample["image"][mask]).mean() > 8   # lit and shaded otherwise
    cached = cached_mitsuba_photo(demo_body_model, sample, 96, 8, 5, tmp_path)
    assert np.abs(cached.astype(int) - image).max() <= 1                   # the PNG holds the render
    write_image(tmp_path / "mitsuba_5.png", np.zeros((96, 96, 3)))
    assert cached_mitsuba_photo(demo_body_model, sample, 96, 8, 5, tmp_path).max() == 0     # read, not re-rendered
    assert cached_mitsuba_photo(demo_body_model, sample, 96, 4, 5, tmp_path)[mask].max() > 0  # another spp: rendered


def test_a_bad_renderer_is_named_before_any_work(tmp_path):
    import argparse

    from softras_cl.bench.body_photo import register
    from softras_cl.errors import InputError

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["body-photo", "--renderer", "blender", "--out", str(tmp_path / "out")])
    with pytest.raises(InputError, match=r"--renderer must be one of softras, mitsuba, got 'blender'"):
        args.func(args)
    assert not (tmp_path / "out").exists()
