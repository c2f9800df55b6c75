"""fitting.keypoints.plausibility and fitting.metrics.check_face_result: landmarks that cannot be a
face's iBUG points, and face fits that cannot be right, are refused; real faces at any roll,
mirrored or turned, are not."""
import re

import numpy as np
import pytest

from support.landmark_layouts import mirrored, rolled, shuffled
from softras_cl.errors import InputError, ResultError
from softras_cl.fitting.keypoints.plausibility import check_distinct_landmarks, check_landmark_layout, layout_faults
from softras_cl.fitting.metrics import MAX_LANDMARK_ERROR, MIN_FACE_PIXELS, check_face_result, finite_metrics
from softras_cl.io.landmarks import read_landmarks

PHOTOS = {"astronaut": 512, "grace_hopper": 512}       # name -> photo width


@pytest.fixture(scope="module", params=sorted(PHOTOS))
def shipped(request, examples_landmarks):
    """(landmarks (68, 2) of a shipped photo, the photo's width)."""
    return read_landmarks(examples_landmarks / f"{request.param}.pts"), PHOTOS[request.param]


def test_shipped_faces_pass_at_every_roll_and_mirrored(shipped):
    points, width = shipped
    for degrees in range(0, 360, 15):
        assert layout_faults(rolled(points, degrees)) == [], degrees
        assert layout_faults(rolled(mirrored(points, width), degrees)) == [], degrees


@pytest.mark.parametrize("seed", range(5))
def test_shuffled_landmarks_are_refused_as_out_of_order(shipped, seed):
    with pytest.raises(ResultError, match="not in the iBUG 300-W 68-point order .shuffled") as caught:
        check_landmark_layout(shuffled(shipped[0], seed))
    assert "the jaw line (0-16) crosses itself" in str(caught.value)


def test_landmarks_mirrored_without_renumbering_are_refused_as_mirrored(shipped):
    points, width = shipped
    flipped = np.column_stack([width - 1 - points[:, 0], points[:, 1]])      # same numbers
    for degrees in (0, 90, 180):                                            # upside down too
        with pytest.raises(ResultError, match="they are mirrored"):
            check_landmark_layout(rolled(flipped, degrees))


def test_each_layout_fault_is_named(shipped):
    points = shipped[0]
    eyes_swapped = points.copy()
    eyes_swapped[36:42], eyes_swapped[42:48] = points[42:48], points[36:42]
    assert layout_faults(eyes_swapped) == ["the eyes (36-41, 42-47) are in the wrong order across the face"]
    eyes_low = points.copy()
    eyes_low[36:48] += points[48:68].mean(0) - points[36:48].mean(0) + [0, 5]   # below the mouth
    assert "the eyes are not above the mouth" in layout_faults(eyes_low)
    zigzag = points.copy()
    zigzag[1:16:2] = points[2:17:2]                   # odd jaw points moved onto the next even one's
    zigzag[2:17:2] = points[1:16:2]                   # place and back: the line folds at each
    assert any(f.startswith("the jaw line (0-16) crosses itself") for f in layout_faults(zigzag))


def test_synthetic_faces_turned_and_rolled_with_noisy_landmarks_pass(demo_face_model):
    """Landmarks of the demo model's random faces (bench face's parameters) turned up to 60
    degrees of yaw and 30 of pitch, any roll, with 2 px of noise: none is refused (measured:
    none of 400; 4 of 400 beyond, at 80 and 40 degrees)."""
    from softras_cl.bench.face import random_truth
    from softras_cl.fitting.recipes.face import FaceScene
    from softras_cl.scene.rotation import axis_angle_to_matrix, matrix_to_axis_angle

    rng = np.random.default_rng(5)
    scene = FaceScene(demo_face_model, (256, 256))
    for _ in range(60):
        truth = random_truth(demo_face_model, rng, 256)
        yaw, pitch, roll = np.radians([rng.uniform(-60, 60), rng.uniform(-30, 30), rng.uniform(-180, 180)])
        turn = (axis_angle_to_matrix([0, 0, roll]) @ axis_angle_to_matrix([0, yaw, 0])
                @ axis_angle_to_matrix([pitch, 0, 0]))
        truth["rotation"] = matrix_to_axis_angle(turn)
        world, _ = scene.geometry(truth)
        points, _ = scene.camera(truth["focal"][0]).project_pixels(demo_face_model.landmarks(world)[0])
        assert layout_faults(points + rng.normal(0, 2.0, points.shape)) == []


@pytest.mark.parametrize("points, says", [
    (np.full((68, 2), 40.0), "all 68 landmarks lie within 0 pixels of (40, 40): they are (nearly) identical"),
    (40 + np.random.default_rng(0).uniform(0, 0.5, (68, 2)), "they are (nearly) identical"),
    (np.repeat(np.random.default_rng(0).uniform(0, 80, (30, 2)), [3] * 8 + [2] * 22, axis=0),
     "only 30 of the 68 landmarks are distinct points"),
])
def test_identical_landmarks_are_named_as_such(points, says):
    with pytest.raises(InputError, match=re.escape(says)):
        check_distinct_landmarks(points)


def test_a_closed_mouth_is_not_identical_landmarks(shipped):
    points = shipped[0].copy()
    points[65:68] = points[61:64]                     # inner lips on each other
    check_distinct_landmarks(points)


def _face_metrics(face_pixels, error_fraction, extent=64.0):
    landmarks = np.array([[0.0, 0.0], [extent, extent / 2]] + [[extent / 2, extent / 2]] * 66)
    return dict(face_pixels=face_pixels, landmark_error_px=error_fraction * extent), landmarks


@pytest.mark.parametrize("face_pixels, error_fraction, says", [
    (MIN_FACE_PIXELS - 1, 0.03, f"its face region is {MIN_FACE_PIXELS - 1} pixel"),
    (1, 0.03, "its face region is 1 pixel"),
    (2000, MAX_LANDMARK_ERROR * 1.1, "its landmark error is 0.17 of the face's extent"),
    (3, 0.31, "its face region is 3 pixel.*; its landmark error is 0.31"),
])
def test_a_face_result_that_cannot_be_right_is_refused(face_pixels, error_fraction, says):
    metrics, landmarks = _face_metrics(face_pixels, error_fraction)
    with pytest.raises(ResultError, match=f"the fit cannot be right: {says}.*Likely cause: landmarks"):
        check_face_result(metrics, landmarks, "out/fit")


@pytest.mark.parametrize("face_pixels, error_fraction", [(MIN_FACE_PIXELS, 0.03), (66, MAX_LANDMARK_ERROR)])
def test_a_face_result_at_the_limits_passes(face_pixels, error_fraction):
    check_face_result(*_face_metrics(face_pixels, error_fraction), "out/fit")


@pytest.fixture(scope="module")
def astronaut(examples_data, examples_landmarks):
    from softras_cl.io.images import read_image

    return read_image(examples_data / "astronaut.png")[..., :3], read_landmarks(examples_landmarks / "astronaut.pts")


def _fit(photo, points, model, size):
    from softras_cl.fitting.recipes.face import FaceFitConfig, fit_face

    return fit_face(photo, points, model, FaceFitConfig.from_budget("fast", size=size), progress=False)


def test_finite_metrics_passes_a_real_fit(astronaut, demo_face_model, tmp_path):
    metrics = finite_metrics(_fit(*astronaut, demo_face_model, 32), tmp_path, ("psnr_face_db",))
    assert metrics["face_pixels"] >= 4 * MIN_FACE_PIXELS          # measured 66


def test_fit_face_refuses_shuffled_landmarks_before_fitting(astronaut, demo_face_model, monkeypatch):
    from softras_cl.fitting.recipes import face

    monkeypatch.setattr(face, "fit", lambda *a, **k: pytest.fail("the fit ran"))
    with pytest.raises(ResultError, match="shuffled"):
        _fit(astronaut[0], shuffled(astronaut[1], 0), demo_face_model, 32)


def test_finite_metrics_refuses_the_fit_of_shuffled_landmarks(astronaut, demo_face_model, monkeypatch, tmp_path):
    """Past the layout check, the shuffled landmarks' fit (a face region of 1 pixel, an error of
    0.32 of the face: measured) is refused by the result check, in the single-photo and batch path."""
    from softras_cl.fitting.recipes import face

    monkeypatch.setattr(face, "check_landmark_layout", lambda points: None)
    fit = _fit(astronaut[0], shuffled(astronaut[1], 0), demo_face_model, 128)
    with pytest.raises(ResultError, match=f"the fit cannot be right: its face region is .*{tmp_path}"):
        finite_metrics(fit, tmp_path, ("psnr_face_db",))
