"""Face fitting recipe (fitting/face.py): exact objective gradients, closed-form initialisers,
input checks, and recovery of a synthetic face from its photo and noisy landmarks."""
import dataclasses
import re

import numpy as np
import pytest

from softras_cl.scene.rotation import axis_angle_to_matrix
from softras_cl.fitting.keypoints import ibug68
from softras_cl.fitting.recipes import face, face_settings
from softras_cl.bench.face import aligned_rmse, synthetic_face
from softras_cl.fitting.solver import Stage
from softras_cl.scene.shading import sh_ambient
from support.gradients import central_differences
from support.toy_face import spread_landmarks, toy_face_model

ALL_TERMS = dict(landmarks=0.3, photo=1.0, id_prior=1.0, exp_prior=1.0, albedo_prior=1.0, sh_white=2.0)


@pytest.fixture(scope="module")
def toy():
    return toy_face_model()


def toy_values(model, rng, focal=90.0):
    return dict(id=rng.normal(size=model.n_id) * 0.5, exp=rng.normal(size=model.n_exp) * 0.5,
                albedo=rng.normal(size=model.n_albedo) * 0.5, sh=sh_ambient(0.8) + rng.normal(0, 0.1, (3, 9)),
                rotation=np.radians([10.0, -20.0, 5.0]), translation=np.array([0.01, -0.005, -0.6]),
                focal=np.array([focal]))


@pytest.mark.parametrize("weights, robust_scale", [
    (ALL_TERMS, 1.0), (ALL_TERMS, None), (dict(photo=1.0, focal_prior=0.5), 1.0),
    (dict(landmarks=1.0, id_prior=2.0, exp_prior=0.5), 1.0)],
    ids=["photometric stage, robust", "photometric stage, squares", "photo term alone, robust", "landmark stage"])
def test_objective_gradient_matches_central_differences(toy, weights, robust_scale):
    """Every block, focal included (its vjp runs through the camera), in float64."""
    rng = np.random.default_rng(1)
    scene = face.FaceScene(toy, (40, 40))
    values = toy_values(toy, rng)
    landmarks = spread_landmarks(40) + rng.normal(0, 1, (68, 2))     # the face region: most of the face
    objective = face.FaceObjective(scene, rng.random((40, 40, 3)) * 0.5, landmarks,
                                   focal0=80.0, robust_scale=robust_scale)
    stage = Stage("photo-1", ("id",), weights, sigma=1e-3, gamma=1e-2)
    loss, grads, terms = objective(values, stage)
    assert set(terms) == set(weights)
    if "photo" in weights:
        assert objective.mask.sum() > 200
    if "photo" in weights and robust_scale is not None:     # pixels on both sides of the scale
        error = np.linalg.norm(scene.render(values, 1e-3, 1e-2).rgb[0] - objective.image, axis=-1)[objective.mask]
        assert 0.2 < (error > objective.photo_scale).mean() < 0.8
    for name, v in values.items():
        # a step small enough not to cross the rasteriser's cut-off of a face's reach
        # (D < dist_eps is skipped: a jump of ~1e-10 in the loss; at 1e-6 it showed)
        fd = central_differences(objective, values, stage, name, step=1e-7)
        g = grads.get(name, np.zeros_like(v))
        np.testing.assert_allclose(g, fd, rtol=2e-5, atol=2e-5 * np.abs(fd).max() + 1e-9, err_msg=name)


def test_face_region_is_fixed_within_a_stage_and_renewed_per_stage(toy):
    rng = np.random.default_rng(2)
    scene = face.FaceScene(toy, (40, 40))
    values = toy_values(toy, rng)
    objective = face.FaceObjective(scene, np.zeros((40, 40, 3)), spread_landmarks(40))
    stage = Stage("photo-1", ("id",), dict(photo=1.0), sigma=1e-4, gamma=1e-3)
    objective(values, stage)
    first = objective.mask.copy()
    assert 0 < first.sum() < first.size
    moved = dict(values, translation=values["translation"] + [0.03, 0, 0])
    objective(moved, stage)
    np.testing.assert_array_equal(objective.mask, first)
    objective(moved, Stage("photo-2", ("id",), dict(photo=1.0), sigma=1e-4, gamma=1e-3))
    assert not np.array_equal(objective.mask, first)


def test_face_region_is_the_render_inside_the_landmark_outline_less_eyes_and_mouth(toy):
    rng = np.random.default_rng(2)
    scene = face.FaceScene(toy, (40, 40))
    values = toy_values(toy, rng)
    landmarks = spread_landmarks(40)
    rendered = scene.render(values, 1e-4, 1e-3).alpha[0] > 0.5
    full = face.FaceObjective(scene, np.zeros((40, 40, 3)), landmarks, mask_erosion=0)
    region = full.face_region(values, 1e-4, 1e-3)
    holes = full._outlined(ibug68.OPENINGS, landmarks)
    assert holes[11, 10] and holes[29, 18] and holes.sum() <= 60  # an eye, the mouth: small boxes
    assert np.array_equal(region, rendered & ~holes)
    assert region.sum() > 100
    landmarks[0:17, 1] = 20.0                                     # jaw line raised to mid-image
    lower = face.FaceObjective(scene, np.zeros((40, 40, 3)), landmarks, mask_erosion=0)
    assert not lower.face_region(values, 1e-4, 1e-3)[25:].any()


def test_initial_pose_recovers_a_distant_pose(toy):
    R = axis_angle_to_matrix(np.radians([15.0, -25.0, 8.0]))
    translation = np.array([0.05, -0.02, -30.0])
    scene = face.FaceScene(toy, (200, 200))
    focal = 6000.0                                     # far away: nearly orthographic
    values = dict(rotation=np.radians([15.0, -25.0, 8.0]), translation=translation)
    points = toy.mean_shape[::7]
    uv, _ = scene.camera(focal).project_pixels(points @ R.T + translation)
    rotation, t = face.initial_pose(points, uv, focal, scene.principal)
    angle = np.degrees(np.arccos(np.clip((np.trace(axis_angle_to_matrix(rotation).T @ R) - 1) / 2, -1, 1)))
    assert angle < 0.5
    np.testing.assert_allclose(t, values["translation"], rtol=0.01, atol=2e-3)


def test_initial_light_reproduces_the_shading_of_a_render(toy):
    """The light of a face is not identifiable coefficient by coefficient (its normals barely
    span the sphere), so the test is on what matters: the render under the estimated light
    matches the image, 5x better than the best uniform light does."""
    rng = np.random.default_rng(3)
    scene = face.FaceScene(toy, (96, 96))
    values = toy_values(toy, rng, focal=220.0)
    values["sh"] = sh_ambient(0.7)
    values["sh"][:, 1:4] += [0.1, 0.2, 0.15]
    out = scene.render(values, 1e-6, 1e-4)
    inside = out.alpha[0] > 0.99
    image = out.rgb[0]

    def error(sh):
        return np.abs(scene.render(dict(values, sh=sh), 1e-6, 1e-4).rgb[0] - image)[inside].mean()

    estimate = face.initial_light(scene, values, image, ridge=1e-4)
    uniform = face.initial_light(scene, values, image, ridge=1e6)      # pulled to a uniform light
    assert np.allclose(uniform[:, 1:], 0, atol=1e-3)
    assert error(estimate) < 0.2 * error(uniform)
    assert error(estimate) < 0.01


def test_prepare_photo_crops_around_the_landmarks_and_maps_pixel_centres():
    rng = np.random.default_rng(0)
    photo = rng.random((300, 200, 3))
    lmk = np.column_stack([rng.uniform(80, 120, 68), rng.uniform(140, 180, 68)])
    lmk[0], lmk[1] = (80, 140), (120, 180)                 # extent 40 px: a 80 px square
    image, points, crop = face.prepare_photo(photo, lmk, 40)
    assert image.shape == (40, 40, 3) and crop.scale == 0.5
    assert (crop.x0, crop.y0) == (60.0, 120.0)
    np.testing.assert_allclose(points[0], [(80 + 0.5 - 60) * 0.5 - 0.5, (140 + 0.5 - 120) * 0.5 - 0.5])
    np.testing.assert_allclose(crop.to_full(points), lmk)
    np.testing.assert_allclose(image.mean(), photo[120:200, 60:140].mean(), atol=1e-3)
    full, kept, same = face.prepare_photo(photo, lmk, 400)     # never enlarged
    assert same.scale == 1.0 and full.shape == (80, 80, 3)
    np.testing.assert_array_equal(full, photo[120:200, 60:140])


def test_prepare_photo_pads_a_face_at_the_border_with_edge_pixels():
    photo = np.zeros((100, 100, 3))
    photo[:, 0] = 1.0
    lmk = np.column_stack([np.linspace(0, 30, 68), 40 + 20 * (np.arange(68) % 2)])   # spans an area
    image, points, crop = face.prepare_photo(photo, lmk, 200)
    assert crop.x0 < 0 and image.shape == (60, 60, 3)
    assert np.all(image[:, :int(-crop.x0) + 1] == 1.0)       # columns left of the photo repeat its edge


@pytest.mark.parametrize("photo, lmk, match", [
    (np.zeros((10, 10)), np.zeros((68, 2)), r"photo must be an \(H, W, 3\)"),
    (np.full((10, 10, 3), np.nan), np.zeros((68, 2)), "photo contains NaN"),
    (np.zeros((10, 10, 3)), np.zeros((5, 2)), r"landmarks must have shape \(68, 2\)"),
    (np.zeros((10, 10, 3)), np.full((68, 2), 12.0), "landmark 0 at .* is outside the 10x10 photo"),
])
def test_prepare_photo_rejects_bad_input(photo, lmk, match):
    with pytest.raises(ValueError, match=match):
        face.prepare_photo(photo, lmk, 64)


def test_model_without_68_landmarks_is_refused_before_fitting(toy):
    bare = toy.with_landmarks(np.zeros(0, np.int32), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="defines 0 landmarks"):
        face.fit_face(np.zeros((32, 32, 3)), np.zeros((68, 2)), bare)


def test_budgets_and_photo_weight_are_validated_and_applied():
    with pytest.raises(ValueError, match="budget must be one of"):
        face.FaceFitConfig.from_budget("quick")
    with pytest.raises(ValueError, match="photo_weight must be > 0"):
        face.FaceFitConfig.from_budget("fast", photo_weight=0.0)
    config = face.FaceFitConfig.from_budget("fast", photo_weight=30.0, size=64)
    assert config.weights["photo"] == 30.0 and config.size == 64
    assert config.photo_stages == face.BUDGETS["fast"]["photo_stages"]
    default = face.FaceFitConfig()
    assert default.weights["photo"] == 100.0 and default.robust_scale == face.ROBUST_SCALE == 2.0
    assert default.landmark_weight_photo == 5.0
    assert default.detected_landmark_weight_photo == face_settings.DETECTED_LANDMARK_WEIGHT_PHOTO == 0.2
    with pytest.raises(ValueError, match="detected_landmark_weight_photo must be >= 0"):
        face.FaceFitConfig(detected_landmark_weight_photo=-1.0)


def test_a_detectors_landmarks_weigh_their_own_weight_in_the_photometric_stages():
    config = face.FaceFitConfig(dense_weight=0.1)
    from_file = face.default_stages(config, fit_focal=True)
    detected = face.default_stages(config, fit_focal=True, detected=True)
    lm = config.weights["landmarks"]
    assert from_file[0].weights == detected[0].weights and from_file[0].weights["landmarks"] == lm
    for a, b in zip(from_file[1:], detected[1:]):
        assert a.weights["landmarks"] == lm * config.landmark_weight_photo
        assert b.weights["landmarks"] == lm * config.detected_landmark_weight_photo
        assert b.weights["dense"] == b.weights["landmarks"] * config.dense_weight
        assert {k: v for k, v in a.weights.items() if k not in ("landmarks", "dense")} == \
            {k: v for k, v in b.weights.items() if k not in ("landmarks", "dense")}


@pytest.mark.parametrize("on_face_mesh, weight", [(False, "landmark_weight_photo"),
                                                   (True, "detected_landmark_weight_photo")])
def test_fit_face_weighs_a_detectors_landmarks_as_detected(demo, monkeypatch, on_face_mesh, weight):
    class Stop(Exception):
        pass

    seen = {}

    def capture(params, objective, stages, **kwargs):
        seen["stages"] = stages
        raise Stop

    monkeypatch.setattr(face, "fit", capture)
    sample = synthetic_face(demo, np.random.default_rng(0), 128)
    config = face.FaceFitConfig.from_budget("fast", size=128)
    with pytest.raises(Stop):
        face.fit_face(sample["photo"], sample["landmarks"], demo, config, progress=False,
                      face_mesh_landmarks=on_face_mesh)
    assert seen["stages"][1].weights["landmarks"] == config.weights["landmarks"] * getattr(config, weight)


@pytest.mark.parametrize("on_face_mesh, robust", [(False, None), (True, face_settings.DETECTED_LANDMARK_ROBUST)])
def test_fit_face_makes_a_detectors_landmark_term_robust(demo, monkeypatch, on_face_mesh, robust):
    """A detector's landmarks go through Geman-McClure at detected_landmark_robust deviations
    (the objective and its half-size copy), a file's through plain squares; None turns it off."""
    class Stop(Exception):
        pass

    seen = []

    def capture(params, objective, stages, **kwargs):
        seen.append(objective)
        raise Stop

    monkeypatch.setattr(face, "fit", capture)
    sample = synthetic_face(demo, np.random.default_rng(0), 128)
    for config in (face.FaceFitConfig.from_budget("fast", size=128),
                   face.FaceFitConfig.from_budget("fast", size=128, detected_landmark_robust=None)):
        with pytest.raises(Stop):
            face.fit_face(sample["photo"], sample["landmarks"], demo, config, progress=False,
                          face_mesh_landmarks=on_face_mesh)
    assert seen[0].landmark_robust == robust and seen[0].photo_level(1.0).landmark_robust == robust
    assert seen[1].landmark_robust is None


def test_robust_landmark_objective_gradient_matches_central_differences(toy):
    """The landmark stage with landmark_robust at 1 deviation (the landmarks' 1 px noise puts
    points on both sides of it), in float64."""
    rng = np.random.default_rng(2)
    scene = face.FaceScene(toy, (40, 40))
    values = toy_values(toy, rng)
    landmarks = spread_landmarks(40) + rng.normal(0, 1, (68, 2))
    objective = face.FaceObjective(scene, rng.random((40, 40, 3)) * 0.5, landmarks, focal0=80.0,
                                   landmark_robust=1.0)
    stage = Stage("landmarks", ("id",), dict(landmarks=1.0, id_prior=2.0, exp_prior=0.5), sigma=1e-3, gamma=1e-2)
    _, grads, _ = objective(values, stage)
    for name, v in values.items():
        fd = central_differences(objective, values, stage, name, step=1e-7)
        g = grads.get(name, np.zeros_like(v))
        np.testing.assert_allclose(g, fd, rtol=2e-5, atol=2e-5 * np.abs(fd).max() + 1e-9, err_msg=name)


@pytest.fixture(scope="module")
def demo():
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    return load_demo_face_model().truncated(8, 8, 4)


@pytest.mark.slow
def test_synthetic_demo_face_is_recovered(demo, tmp_path):
    """A face drawn from the (truncated) demo model's prior, rendered at 128^2 with 1-2 px
    landmark noise, is fitted from the photo and landmarks alone. Stated tolerances: landmark
    error under 1.5 px against the noise-free points, shape RMSE (up to scale) under half the
    mean face's, PSNR in the face region above 30 dB (sRGB)."""
    from softras_cl.fitting.reports.face import camera_matrices

    sample = synthetic_face(demo, np.random.default_rng(5), size=128)
    config = face.FaceFitConfig.from_budget("fast", size=128)
    fit = face.fit_face(sample["photo"], sample["landmarks"], demo, config, out_dir=tmp_path, progress=False)
    truth = sample["truth"]
    true_shape, _ = demo.shape(truth["id"], truth["exp"])
    rmse = aligned_rmse(demo.shape(fit.values["id"], fit.values["exp"])[0], true_shape)
    baseline = aligned_rmse(demo.mean_shape, true_shape)
    points = fit.crop.to_full(fit.fitted_landmarks())
    landmark_error = np.linalg.norm(points - sample["clean_landmarks"], axis=1).mean()
    metrics = fit.metrics()
    assert landmark_error < 1.5
    assert rmse < 0.5 * baseline
    assert metrics["psnr_face_db"] > 30.0
    assert (tmp_path / "checkpoint.npz").exists() and (tmp_path / "loss_curve.png").exists()
    cam = camera_matrices(fit, sample["photo"].shape[:2])      # the exported camera of the photo
    X = demo.landmarks(demo.shape(fit.values["id"], fit.values["exp"])[0])[0] @ cam["R"].T + cam["t"]
    x = X @ cam["K"].T
    world, _ = fit.scene.geometry(fit.values)        # the model's fixed points, as the export has them
    fixed = fit.scene.camera(fit.values["focal"][0]).project_pixels(demo.landmarks(world)[0])[0]
    np.testing.assert_allclose(x[:, :2] / x[:, 2:], fit.crop.to_full(fixed), atol=1e-6)
    assert [h["stage"] for h in fit.result.history][0] == "landmarks"
    # resuming the finished fit runs no stage and gives the same fit, drawn at its own depth
    again = face.fit_face(sample["photo"], sample["landmarks"], demo, config, out_dir=tmp_path, progress=False,
                          resume=True)
    assert all(np.array_equal(again.values[k], fit.values[k]) for k in fit.values)
    settings = again.scene.settings
    assert (settings.near, settings.far) == face.depth_range(again.values["translation"])
    assert again.metrics()["psnr_face_db"] > 30.0


@pytest.mark.parametrize("changes, says", [
    (dict(size=1), "size must be an integer >= 32"),
    (dict(size=0), "size must be an integer >= 32"),
    (dict(focal=0.0), "focal must be > 0, got 0.0"),
    (dict(focal=float("inf")), "focal must be a finite number, got inf"),
    (dict(fov_deg=180.0), "fov_deg must be in (0, 180) degrees, got 180.0"),
    (dict(photo_stages=((0.0, 1e-3, 10),)), "photo_stages[0] sigma must be > 0"),
    (dict(weights=dict(photo=float("nan"))), "weights['photo'] must be a finite number"),
    (dict(dtype="float16"), "dtype must be 'float32' or 'float64'"),
    (dict(contour_landmarks="slide"), "contour_landmarks must be one of 'sliding', 'fixed', got 'slide'"),
    (dict(detected_landmark_weights="yes"), "detected_landmark_weights must be True or False, got 'yes'"),
    (dict(robust_scale=0.0), "robust_scale must be > 0, got 0.0"),
    (dict(robust_scale=float("nan")), "robust_scale must be a finite number"),
    (dict(stall_window=-1), "stall_window must be an integer >= 0 (evaluations; 0: no convergence stop)"),
    (dict(stall_window=2.0), "stall_window must be an integer >= 0"),
    (dict(photo_stages=((1e-4, 1e-3, 10, -1e-3),)), "photo_stages[0] stall_rel must be >= 0, got -0.001"),
    (dict(photo_stages=((1e-4, 1e-3),)), "photo_stages[0] must be (sigma, gamma, evaluations) or"),
    (dict(coarse_sigma=0.0), "coarse_sigma must be > 0, got 0.0"),
    (dict(coarse_mesh=-2.0), "coarse_mesh must be > 0, got -2.0"),
    (dict(coarse_mesh=float("inf")), "coarse_mesh must be a finite number"),
    (dict(dense_weight=-0.5), "dense_weight must be >= 0 (0: no dense landmark term), got -0.5"),
    (dict(landmark_map="ibug"), "landmark_map must be one of 'auto', 'model', 'face-mesh', got 'ibug'"),
    (dict(dense_weight=float("nan")), "dense_weight must be a finite number"),
])
def test_face_config_names_a_bad_field(changes, says):
    from softras_cl.errors import InputError

    with pytest.raises(InputError, match=re.escape(says)):
        face.FaceFitConfig(**changes)


@pytest.mark.parametrize("lmk, says", [
    (np.column_stack([np.linspace(20, 80, 68), np.linspace(30, 90, 68)]), "the landmarks lie on a line"),
    (np.full((68, 2), 50.0), r"all 68 landmarks lie within 0 pixels of \(50, 50\): they are \(nearly\) identical"),
    (np.random.default_rng(1).uniform(40, 50, (68, 2)), "fitting needs a face at least 16 pixels across"),
])
def test_prepare_photo_refuses_landmarks_spanning_no_area(lmk, says):
    with pytest.raises(ValueError, match=says):
        face.prepare_photo(np.zeros((100, 100, 3)), lmk, 64)


def test_prepare_photo_names_a_nan_landmark():
    lmk = np.random.default_rng(0).uniform(10, 90, (68, 2))
    lmk[7, 1] = np.nan
    with pytest.raises(ValueError, match=re.escape("landmarks contains NaN or Inf (1 non-finite value(s), "
                                                   "first at index (7, 1))")):
        face.prepare_photo(np.zeros((100, 100, 3)), lmk, 64)


@pytest.mark.parametrize("robust_scale, coarse_mesh", [(None, None), (1.0, None), (None, 2.0), (1.0, 2.0)])
def test_coarse_stage_gradient_matches_central_differences_and_sums_like_full_resolution(toy, robust_scale,
                                                                                        coarse_mesh):
    rng = np.random.default_rng(3)
    scene = face.FaceScene(toy, (64, 64))
    values = toy_values(toy, rng)
    image = rng.random((64, 64, 3)) * 0.5
    objective = face.FaceObjective(scene, image, spread_landmarks(64), mask_erosion=0, robust_scale=robust_scale,
                                   coarse_mesh=coarse_mesh)
    stage = Stage("photo-1", ("id",), dict(photo=1.0), sigma=1e-3, gamma=1e-2)
    level = objective.photo_level(stage.sigma)
    assert level is not objective and level.image.shape == (32, 32, 3)
    if coarse_mesh is None:
        assert level.scene.faces is toy.faces
    else:                               # the model's vertices, fewer and larger triangles
        assert len(level.scene.faces) < 0.5 * len(toy.faces) and level.scene.faces.max() < toy.n_vertices
    np.testing.assert_allclose(level.image[3, 5], image[6:8, 10:12].mean(axis=(0, 1)))
    assert face.FaceObjective(scene, image, level.target, coarse_sigma=None).photo_level(1.0) is not level
    loss, grads, _ = objective(values, stage)
    assert level.mask.sum() > 100 and objective.mask is None
    assert (level.photo_scale is None) == (robust_scale is None)
    for name in ("focal", "translation", "albedo"):
        # a step small enough not to cross a face's cut-off (see the test above)
        fd = central_differences(objective, values, stage, name, step=1e-7)
        np.testing.assert_allclose(grads[name], fd, rtol=2e-5, atol=2e-5 * np.abs(fd).max() + 1e-9, err_msg=name)
    # a half-size pixel counts for four: on a smooth photo the sum is near the full-resolution one
    y, x = np.mgrid[0:64, 0:64] / 64.0
    smooth = np.stack([0.2 + 0.3 * x, 0.4 - 0.2 * y, 0.3 + 0.1 * x * y], -1)
    coarse = face.FaceObjective(scene, smooth, objective.target, mask_erosion=0,
                                robust_scale=robust_scale, coarse_mesh=coarse_mesh)(values, stage)[0]
    full = face.FaceObjective(scene, smooth, objective.target, mask_erosion=0, coarse_sigma=None,
                              robust_scale=robust_scale)(values, stage)[0]
    assert 0.8 < coarse / full < 1.25


def test_photometric_stages_fit_focal_with_its_prior_unless_focal_is_given():
    config = face.FaceFitConfig()
    for stage in face.default_stages(config, fit_focal=True):
        assert "focal" in stage.free and stage.weights["focal_prior"] == config.weights["focal_prior"]
    for stage in face.default_stages(config, fit_focal=False):
        assert "focal" not in stage.free and "focal_prior" not in stage.weights


def test_photometric_stages_carry_the_configured_convergence_stop_and_coarse_level(toy):
    config = face.FaceFitConfig(stall_window=7, coarse_sigma=3e-5,
                                photo_stages=((1e-4, 3e-3, 50, 2e-3), (1e-5, 1e-3, 40), (3e-6, 1e-3, 30, 1e-4)))
    landmarks, *photo = face.default_stages(config, fit_focal=True)
    assert landmarks.stall_window == 0 and [s.max_iters for s in photo] == [50, 40, 30]
    assert [(s.stall_window, s.stall_rel) for s in photo] == [(7, 2e-3), (0, 0.0), (7, 1e-4)]
    off = face.default_stages(dataclasses.replace(config, stall_window=0), fit_focal=True)
    assert all(s.stall_window == 0 for s in off)
    rng = np.random.default_rng(7)
    photo, lmk = rng.random((120, 100, 3)), np.column_stack([rng.uniform(30, 70, 68), rng.uniform(40, 80, 68)])
    objective = face.prepare_fit(photo, lmk, toy, dataclasses.replace(config, size=64))[0]
    assert objective.photo_level(3e-5) is not objective and objective.photo_level(1e-5) is objective


def test_robust_scale_is_a_multiple_of_the_median_error_fixed_within_a_stage(toy):
    rng = np.random.default_rng(4)
    scene = face.FaceScene(toy, (40, 40))
    values = toy_values(toy, rng)
    image = rng.random((40, 40, 3)) * 0.5
    objective = face.FaceObjective(scene, image, spread_landmarks(40), robust_scale=1.5)
    stage = Stage("photo-1", ("id",), dict(photo=1.0), sigma=1e-4, gamma=1e-3)
    objective(values, stage)
    error = np.linalg.norm(scene.render(values, 1e-4, 1e-3).rgb[0] - image, axis=-1)[objective.mask]
    assert objective.photo_scale == pytest.approx(1.5 * np.median(error), rel=1e-12)
    objective(dict(values, albedo=values["albedo"] + 1.0), stage)
    assert objective.photo_scale == pytest.approx(1.5 * np.median(error), rel=1e-12)
    rendered = scene.render(values, 1e-4, 1e-3).rgb[0]
    exact = face.FaceObjective(scene, rendered, spread_landmarks(40), robust_scale=1.5)
    exact(values, Stage("photo-2", ("id",), dict(photo=1.0), sigma=1e-4, gamma=1e-3))
    assert exact.photo_scale == face.MIN_ROBUST_SCALE           # a perfect fit: the floor
    squares = face.FaceObjective(scene, image, spread_landmarks(40), robust_scale=None)
    squares(values, stage)
    assert squares.photo_scale is None


def test_robust_photo_term_ignores_an_occluder_that_biases_squares(toy):
    """A dark band over a fifth of the face (a shadow, a glasses frame): the light fitted with
    the plain squared error darkens to explain it; the robust term leaves it out."""
    from softras_cl.fitting.solver import fit

    rng = np.random.default_rng(6)
    scene = face.FaceScene(toy, (40, 40))
    truth = toy_values(toy, rng)
    truth["sh"] = sh_ambient(0.8)
    clean = scene.render(truth, 1e-4, 1e-3).rgb[0]
    photo = clean.copy()
    band = np.zeros((40, 40), bool)
    band[14:20] = True
    photo[band] = 0.02
    start = dict(truth, sh=truth["sh"] * 1.1)
    errors = {}
    for robust_scale in (None, 2.0):
        objective = face.FaceObjective(scene, photo, spread_landmarks(40), robust_scale=robust_scale)
        assert 0.1 < band[objective.face_region(start, 1e-4, 1e-3)].mean() < 0.3
        params = face.face_params(toy, truth["focal"][0], truth["rotation"], truth["translation"], start["sh"])
        params.set({name: truth[name] for name in ("id", "exp", "albedo")})
        stages = [Stage(f"photo-{k}", ("sh",), dict(photo=1.0), sigma=1e-4, gamma=1e-3, max_iters=40)
                  for k in (1, 2)]
        values = fit(params, objective, stages, progress=False).values
        region = objective.face_region(truth, 1e-4, 1e-3)    # the light is judged by what it draws
        errors[robust_scale] = np.abs(scene.render(values, 1e-4, 1e-3).rgb[0] - clean)[region].mean()
    assert errors[None] > 0.03                      # measured 0.07 (colours ~0.3)
    assert errors[2.0] < 0.003                      # measured 0.0002


def test_prepare_fit_starts_from_the_cropped_photo_and_the_field_of_view_focal(toy):
    rng = np.random.default_rng(7)
    photo = rng.random((120, 100, 3))
    lmk = np.column_stack([rng.uniform(30, 70, 68), rng.uniform(40, 80, 68)])
    config = face.FaceFitConfig(size=48, fov_deg=40.0)
    objective, crop, params = face.prepare_fit(photo, lmk, toy, config)
    image, target, same_crop = face.prepare_photo(photo, lmk, 48)
    assert crop == same_crop
    np.testing.assert_array_equal(objective.image, image)
    np.testing.assert_array_equal(objective.target, target)
    focal = 0.5 * 120 / np.tan(np.radians(20.0)) * crop.scale
    start = params.values()
    assert start["focal"][0] == pytest.approx(focal) and objective.focal0 == pytest.approx(focal)
    assert objective.robust_scale == config.robust_scale
    assert np.all(start["id"] == 0) and start["sh"].shape == (3, 9)


def test_scene_camera_of_each_focal_is_the_opencv_camera_of_it(toy):
    from softras_cl.scene.camera import Camera

    scene = face.FaceScene(toy, (40, 30), principal=(14.0, 21.5))
    points = np.array([[0.01, 0.02, -0.5], [-0.03, 0.0, -0.6]])
    for focal in (90.0, 120.0, 90.0):
        K = [[focal, 0.0, 14.0], [0.0, focal, 21.5], [0.0, 0.0, 1.0]]
        expected = Camera.from_opencv(K, face.CAMERA_ROTATION, np.zeros(3), (40, 30))
        cam = scene.camera(focal)
        assert (cam.fx, cam.fy, cam.cx, cam.cy, cam.image_size) == (focal, focal, 14.0, 21.5, (40, 30))
        np.testing.assert_array_equal(cam.project_pixels(points)[0], expected.project_pixels(points)[0])
    assert scene.camera(90.0) is cam                     # the last one is kept


def test_stages_draw_with_one_rasteriser_per_scene_at_their_depth_range(toy):
    """A coarse and two full-resolution stages of other sigma, gamma and depth range: each scene
    keeps one renderer with one rasteriser, whose outputs carry the stage's settings; a stage
    start fits the depth range of both scenes to the face."""
    rng = np.random.default_rng(5)
    scene = face.FaceScene(toy, (64, 64))
    values = toy_values(toy, rng)
    objective = face.FaceObjective(scene, rng.random((64, 64, 3)) * 0.5, spread_landmarks(64))
    stages = [Stage("photo-1", ("id",), dict(photo=1.0), sigma=1e-3, gamma=1e-2),
              Stage("photo-2", ("id",), dict(photo=1.0), sigma=3e-5, gamma=1e-3),
              Stage("photo-3", ("id",), dict(photo=1.0), sigma=1e-5, gamma=3e-3)]
    for k, stage in enumerate(stages):
        moved = dict(values, translation=values["translation"] * (1 + 0.1 * k))
        objective(moved, stage)
        near, far = face.depth_range(moved["translation"])
        level = objective.photo_level(stage.sigma)
        out = level.scene.render(moved, stage.sigma, stage.gamma, grads=("vertices",))
        drawn = out.saved.raster_out.saved.settings
        assert (drawn.sigma, drawn.gamma, drawn.near, drawn.far) == (stage.sigma, stage.gamma, near, far)
        for s in (scene, objective.photo_level(1.0).scene):
            assert (s.settings.near, s.settings.far) == (near, far)
    for s in (scene, objective.photo_level(1.0).scene):
        assert len(s.renderer._rasterizers) == 1


class RecordingContour:
    """A ContourLandmarks that keeps every choice it makes."""

    def __init__(self, contour):
        self.contour, self.choices = contour, []

    def choose(self, *args):
        chosen = self.contour.choose(*args)
        self.choices.append(chosen)
        return chosen

    def __getattr__(self, name):
        return getattr(self.contour, name)


def _turned_face(model, yaw_deg: float = 55.0, size: int = 128) -> dict:
    """A synthetic face of the demo model turned by yaw_deg, its hidden jaw points on the
    silhouette (the bench's own rule, independent of the fit's)."""
    from softras_cl.bench.face import photograph, random_truth

    truth = random_truth(model, np.random.default_rng(2), size)
    truth["rotation"] = np.radians([5.0, yaw_deg, -3.0])
    return photograph(model, truth, np.random.default_rng(3), size, silhouette=True)


def test_sliding_landmark_gradient_matches_central_differences_where_the_choice_holds(demo):
    """The landmark stage's objective with the jaw sliding, float64, at a pose where part of the
    jaw is turned away: every block against central differences, the choice the same in every
    evaluation of them."""
    from softras_cl.fitting.recipes.contour import jaw_candidates

    sample = _turned_face(demo)
    values = dict(sample["truth"], id=sample["truth"]["id"] * 0.5, exp=sample["truth"]["exp"] * 0.5)
    recording = RecordingContour(jaw_candidates(demo))
    scene = face.FaceScene(demo, (128, 128))
    objective = face.FaceObjective(scene, sample["photo"], sample["landmarks"], focal0=values["focal"][0],
                                   contour=recording)
    stage = Stage("landmarks", ("id",), dict(landmarks=1.0, id_prior=1.0, exp_prior=1.0, focal_prior=1.0))
    _, grads, _ = objective(values, stage)
    chosen = recording.choices[0].edge
    assert (chosen >= 0).sum() >= 4 and (chosen < 0).sum() >= 4          # some slide, some stay
    for name in ("id", "exp", "rotation", "translation", "focal"):
        fd = central_differences(objective, values, stage, name, step=1e-6)
        np.testing.assert_allclose(grads[name], fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max(), err_msg=name)
    assert all(np.array_equal(c.edge, chosen) for c in recording.choices)    # the same edges


def test_sliding_jaw_points_find_the_silhouette_the_fixed_ones_miss(demo):
    """At the true parameters of a turned face, the sliding jaw points project within 1 px
    (mean) of silhouette landmarks placed from the truth's render, the fixed points over 2 px
    away; the other landmarks are the same either way."""
    sample = _turned_face(demo)
    scene = face.FaceScene(demo, (128, 128))
    world, _ = scene.geometry(sample["truth"])
    clean = sample["clean_landmarks"]
    errors = {}
    for contour_landmarks in face_settings.CONTOUR_LANDMARKS:
        config = face.FaceFitConfig(size=128, contour_landmarks=contour_landmarks)
        objective, _, _ = face.prepare_fit(sample["photo"], sample["landmarks"], demo, config)
        assert (objective.contour is None) == (contour_landmarks == "fixed")
        objective = face.FaceObjective(scene, sample["photo"], clean, contour=objective.contour)
        points, _ = objective.landmark_points(sample["truth"], world)
        errors[contour_landmarks] = np.linalg.norm(points - clean, axis=1)
    assert errors["sliding"][:17].mean() < 1.0 < 2.0 < errors["fixed"][:17].mean()
    np.testing.assert_array_equal(errors["sliding"][17:], errors["fixed"][17:])


def _dense_targets(model, values, size: int, rng=None) -> np.ndarray:
    """The model's dense points at ``values`` projected into a size x size image (468, 2), plus
    1 px noise with ``rng``."""
    scene = face.FaceScene(model, (size, size))
    world, _ = scene.geometry(values)
    points = scene.camera(values["focal"][0]).project_pixels(model.dense_points(world)[0])[0]
    return points if rng is None else points + rng.normal(0, 1.0, points.shape)


@pytest.mark.parametrize("stage_weights", [
    dict(landmarks=1.0, dense=0.3, id_prior=1.0, exp_prior=1.0, focal_prior=1.0),
    dict(dense=1.0)], ids=["landmark stage with the dense term", "dense term alone"])
def test_dense_landmark_gradient_matches_central_differences(demo, stage_weights):
    """The objective with the dense term, float64: every block of the landmark stage against
    central differences; the unused points (dense_use False) add nothing."""
    sample = _turned_face(demo, yaw_deg=20.0)
    rng = np.random.default_rng(4)
    values = dict(sample["truth"], id=sample["truth"]["id"] * 0.5, exp=sample["truth"]["exp"] * 0.5)
    dense = _dense_targets(demo, sample["truth"], 128, rng)
    scene = face.FaceScene(demo, (128, 128))
    objective = face.FaceObjective(scene, sample["photo"], sample["landmarks"], focal0=values["focal"][0],
                                   contour=None, dense=dense)
    stage = Stage("landmarks", ("id",), stage_weights)
    loss, grads, terms = objective(values, stage)
    assert set(terms) == set(stage_weights) and terms["dense"] > 0
    for name in ("id", "exp", "rotation", "translation", "focal"):
        fd = central_differences(objective, values, stage, name, step=1e-6)
        np.testing.assert_allclose(grads[name], fd, rtol=1e-6, atol=1e-6 * np.abs(fd).max(), err_msg=name)
    unused = dense.copy()
    unused[~demo.dense_use] += 50.0
    moved = face.FaceObjective(scene, sample["photo"], sample["landmarks"], focal0=values["focal"][0],
                               contour=None, dense=unused)
    assert moved(values, stage)[0] == loss


def test_dense_term_is_the_sum_of_squared_pixel_distances_of_the_used_points(demo):
    """Targets moved by 2 px along x from the model's own projection cost 4 px^2 per used point."""
    values = _turned_face(demo, yaw_deg=10.0)["truth"]
    exact = _dense_targets(demo, values, 128)
    objective = face.FaceObjective(face.FaceScene(demo, (128, 128)), np.zeros((128, 128, 3)),
                                   spread_landmarks(128), dense=exact + [2.0, 0.0])
    value, _ = objective.dense_term(values, objective.scene.geometry(values)[0])
    assert value == pytest.approx(4.0 * demo.dense_use.sum(), rel=1e-9)


def test_dense_weight_adds_the_dense_term_to_every_landmark_stage_relative_to_the_68():
    config = face.FaceFitConfig(dense_weight=0.5)
    stages = face.default_stages(config, fit_focal=True)
    for stage in stages:
        assert stage.weights["dense"] == pytest.approx(0.5 * stage.weights["landmarks"])
    assert all("dense" not in s.weights for s in face.default_stages(face.FaceFitConfig(), fit_focal=True))


def test_dense_targets_move_into_working_and_half_resolution_pixels_with_the_crop(demo):
    """prepare_fit maps the photo's dense points like the 68 landmarks; the half-size objective
    holds them halved like its landmarks."""
    sample = _turned_face(demo, yaw_deg=10.0)
    dense = _dense_targets(demo, sample["truth"], 128, np.random.default_rng(1))
    config = face.FaceFitConfig(size=64, dense_weight=1.0, coarse_sigma=1e-9)
    objective, crop, _ = face.prepare_fit(sample["photo"], sample["landmarks"], demo, config, dense)
    np.testing.assert_allclose(objective.dense_target, crop.to_work(dense))
    np.testing.assert_allclose(objective.target, crop.to_work(sample["landmarks"]))
    without, _, _ = face.prepare_fit(sample["photo"], sample["landmarks"], demo, face.FaceFitConfig(size=64), dense)
    assert without.dense_target is None


def test_dense_weight_without_dense_points_or_a_dense_model_is_refused_before_fitting(demo, toy, tmp_path):
    from softras_cl.errors import InputError

    sample = _turned_face(demo, yaw_deg=10.0)
    config = face.FaceFitConfig(size=64, dense_weight=1.0)
    with pytest.raises(InputError, match="needs the photo's dense points: MediaPipe Face Mesh's 468"):
        face.fit_face(sample["photo"], sample["landmarks"], demo, config, out_dir=tmp_path)
    with pytest.raises(InputError, match="needs a face model with dense points"):
        face.fit_face(sample["photo"], sample["landmarks"], toy, config, out_dir=tmp_path,
                      dense=np.zeros((468, 2)))
    with pytest.raises(InputError, match=re.escape("dense points must have shape (468, 2), got (478, 2)")):
        face.fit_face(sample["photo"], sample["landmarks"], demo, config, out_dir=tmp_path,
                      dense=np.zeros((478, 2)))
    assert list(tmp_path.iterdir()) == []


def test_detected_dense_is_the_face_mesh_points_without_the_iris():
    from types import SimpleNamespace

    mesh = np.arange(478 * 2, dtype=np.float64).reshape(478, 2)
    np.testing.assert_array_equal(face.detected_dense(SimpleNamespace(dense=mesh)), mesh[:468])
    assert face.detected_dense(None) is None                        # landmarks from a file
    assert face.detected_dense(SimpleNamespace(dense=None)) is None   # a dlib candidate


def _landmark_points(model) -> np.ndarray:
    return model.landmarks(model.mean_shape)[0]


@pytest.mark.parametrize("landmark_map, on_mesh, tied", [
    ("auto", True, True), ("face-mesh", False, True), ("auto", False, False), ("model", True, False)])
def test_landmark_map_ties_mediapipes_landmarks_to_its_face_mesh_points(landmark_map, on_mesh, tied):
    """"face-mesh" (and "auto" for MediaPipe's landmarks): landmark i is the model's Face Mesh
    point MP468_TO_IBUG68[i] where the correspondence uses it, the model's own point elsewhere;
    otherwise the model's own 68 points."""
    from softras_cl.fitting.keypoints.face_mesh import MP468_TO_IBUG68
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    model = load_demo_face_model()
    points = _landmark_points(face.landmark_model(model, landmark_map, on_mesh))
    own = _landmark_points(model)
    if not tied:
        np.testing.assert_array_equal(points, own)
        return
    mesh = model.dense_points(model.mean_shape)[0][MP468_TO_IBUG68]
    used = model.dense_use[MP468_TO_IBUG68]
    assert 50 <= used.sum() < 68
    np.testing.assert_allclose(points[used], mesh[used], atol=1e-12)
    np.testing.assert_array_equal(points[~used], own[~used])
    assert np.linalg.norm(points - own, axis=1)[used].mean() > 1e-3     # metres: they do differ


def test_landmark_map_face_mesh_needs_a_model_with_face_mesh_points(toy):
    from softras_cl.errors import InputError

    assert face.landmark_model(toy, "auto", True) is toy
    with pytest.raises(InputError, match="landmark_map 'face-mesh' needs a face model with MediaPipe Face "
                                         "Mesh's 468 points"):
        face.landmark_model(toy, "face-mesh")


@pytest.mark.parametrize("on_mesh", [True, False])
def test_fit_face_ties_the_landmarks_as_their_detector_asks(demo, on_mesh):
    """fit_face's face_mesh_landmarks reaches landmark_map "auto": the fit's scene model, its
    fitted landmarks and its outputs use the tied points."""
    sample = _turned_face(demo, yaw_deg=10.0, size=64)
    config = face.FaceFitConfig(size=64, landmark_iters=5, photo_stages=(), contour_landmarks="fixed")
    fit = face.fit_face(sample["photo"], sample["landmarks"], demo, config, progress=False, face_mesh_landmarks=on_mesh)
    expected = face.landmark_model(demo, "auto", on_mesh)
    np.testing.assert_array_equal(_landmark_points(fit.scene.model), _landmark_points(expected))
    world, _ = fit.scene.geometry(fit.values)
    projected, _ = fit.scene.camera(fit.values["focal"][0]).project_pixels(expected.landmarks(world)[0])
    np.testing.assert_allclose(fit.fitted_landmarks(), projected, atol=1e-9)


@pytest.mark.parametrize("on_mesh", [True, False])
def test_points_a_face_mesh_tie_leaves_at_the_models_own_have_no_weight(demo, on_mesh):
    """tied_landmarks: with the Face Mesh tie, the 11 points its correspondence does not use (they
    keep the model's own point, far from MediaPipe's) weigh 0 in the landmark term, in the fit's
    objective and in its half-resolution copy; otherwise the weights are landmark_weights(). The
    detector's measured weights off (detected_landmark_weights False): the tie's weights as before."""
    from softras_cl.fitting.keypoints.face_mesh import MP468_TO_IBUG68

    tied, weights = face.tied_landmarks(demo, "auto", on_mesh, measured=False)
    unused = ~demo.dense_use[MP468_TO_IBUG68]
    expected = face.landmark_weights()
    if on_mesh:
        assert unused.sum() == 11
        expected[unused] = 0.0
    np.testing.assert_array_equal(weights, expected)
    sample = _turned_face(demo, yaw_deg=10.0, size=64)
    config = face.FaceFitConfig(size=64, landmark_iters=3, photo_stages=(), contour_landmarks="fixed",
                                detected_landmark_weights=False)
    fit = face.fit_face(sample["photo"], sample["landmarks"], demo, config, progress=False, face_mesh_landmarks=on_mesh)
    np.testing.assert_array_equal(fit.objective.landmark_weights, expected)
    np.testing.assert_array_equal(fit.objective._half_size().landmark_weights, expected)


def test_detected_landmark_weights_follow_the_measured_noise(demo):
    """detected_landmark_weights: 1 / sigma^2 of the measured table on the used points, 0 elsewhere,
    the same total as landmark_weights() over the used points; mirror-image points alike; the
    eyes weigh more than the brows, the brows more than the jaw."""
    from softras_cl.fitting.keypoints import ibug68
    from softras_cl.fitting.keypoints.face_mesh import MP468_TO_IBUG68
    from softras_cl.fitting.recipes.face_settings import DETECTED_LANDMARK_SIGMA_MM

    sigma = DETECTED_LANDMARK_SIGMA_MM
    assert sigma.shape == (ibug68.COUNT,) and np.all(sigma > 0)
    used = demo.dense_use[MP468_TO_IBUG68]
    w = face.detected_landmark_weights(used)
    assert np.all(w[~used] == 0.0) and np.all(w[used] > 0.0)
    assert w.sum() == pytest.approx(face.landmark_weights()[used].sum(), rel=1e-12)
    np.testing.assert_allclose(w[used] * sigma[used] ** 2, (w[used] * sigma[used] ** 2)[0], rtol=1e-12)
    mirror = np.r_[16:-1:-1, 26:16:-1, 27:31, 35:30:-1, 45:41:-1, 47:45:-1, 39:35:-1, 41:39:-1,
                   54:47:-1, 59:54:-1, 64:59:-1, 67:64:-1]
    np.testing.assert_array_equal(sigma, sigma[mirror])
    eyes, brows, jaw = (np.array([i for i in r if used[i]]) for r in (range(36, 48), ibug68.BROWS, ibug68.JAW))
    assert w[eyes].mean() > w[brows].mean() > w[jaw].mean()


@pytest.mark.parametrize("on_mesh, landmark_map", [(True, "auto"), (True, "face-mesh"), (False, "face-mesh"),
                                                    (False, "auto")])
def test_only_a_detectors_landmarks_get_the_measured_weights(demo, on_mesh, landmark_map):
    """fit_face weighs landmarks a detector found on Face Mesh's points by their measured noise
    (FaceFitConfig.detected_landmark_weights, the default), in the objective and its half-resolution
    copy; a file's landmarks keep today's weights, tied to Face Mesh's points or not."""
    from softras_cl.fitting.keypoints.face_mesh import MP468_TO_IBUG68

    used = demo.dense_use[MP468_TO_IBUG68]
    tied, weights = face.tied_landmarks(demo, landmark_map, on_mesh, measured=True)
    _, today = face.tied_landmarks(demo, landmark_map, on_mesh, measured=False)
    if on_mesh:
        np.testing.assert_array_equal(weights, face.detected_landmark_weights(used))
        assert not np.array_equal(weights, today)
    else:
        np.testing.assert_array_equal(weights, today)
        expected = np.where(used, face.landmark_weights(), 0.0) if landmark_map == "face-mesh" else face.landmark_weights()
        np.testing.assert_array_equal(today, expected)
    sample = _turned_face(demo, yaw_deg=10.0, size=64)
    config = face.FaceFitConfig(size=64, landmark_iters=3, photo_stages=(), contour_landmarks="fixed",
                                landmark_map=landmark_map)
    assert config.detected_landmark_weights is True
    fit = face.fit_face(sample["photo"], sample["landmarks"], demo, config, progress=False, face_mesh_landmarks=on_mesh)
    np.testing.assert_array_equal(fit.objective.landmark_weights, weights)
    np.testing.assert_array_equal(fit.objective._half_size().landmark_weights, weights)
