"""One face over several photos (fitting/recipes/face_views.py): the joint objective's gradients
against central differences, shared priors counted once, and one photo = the single-photo fit."""
import dataclasses

import numpy as np
import pytest

from softras_cl.bench.face import synthetic_face
from softras_cl.errors import InputError
from softras_cl.fitting.recipes import face, face_views
from softras_cl.fitting.solver import Stage
from softras_cl.scene.shading import sh_ambient
from support.gradients import central_differences
from support.toy_face import toy_face_model

ALL_TERMS = dict(landmarks=0.3, photo=1.0, id_prior=1.0, exp_prior=1.0, albedo_prior=1.0, sh_white=2.0,
                 focal_prior=1.0)
PER_VIEW = ("exp", "sh", "rotation", "translation", "focal")


@pytest.fixture(scope="module")
def toy():
    return toy_face_model()


def _objective(model, rng, size, focal0=80.0):
    scene = face.FaceScene(model, (size, size))
    return face.FaceObjective(scene, rng.random((size, size, 3)) * 0.5, rng.random((68, 2)) * (size - 8) + 4,
                              focal0=focal0)


def _joint_values(model, rng, n_views, same_camera=False):
    values = dict(id=rng.normal(size=model.n_id) * 0.5, albedo=rng.normal(size=model.n_albedo) * 0.5)
    for k in range(n_views):
        values.update({f"exp.{k}": rng.normal(size=model.n_exp) * 0.5,
                       f"sh.{k}": sh_ambient(0.8) + rng.normal(0, 0.1, (3, 9)),
                       f"rotation.{k}": np.radians([10.0, -20.0 + 25 * k, 5.0]),
                       f"translation.{k}": np.array([0.01, -0.005 + 0.01 * k, -0.6]),
                       f"focal.{k}": np.array([90.0 + 5 * k])})
    if same_camera:
        values = {name: v for name, v in values.items() if not name.startswith("focal.")}
        values["focal"] = np.array([93.0])
    return values


@pytest.mark.parametrize("same_camera", [False, True])
def test_joint_gradient_matches_central_differences(toy, same_camera):
    """Two photos of different sizes, every term on: the shared blocks' gradients add up (with
    same_camera the shared focal's too, photo 1 at 0.7 of photo 0's focal)."""
    rng = np.random.default_rng(3)
    objective = face_views.FaceViewsObjective([_objective(toy, rng, 36), _objective(toy, rng, 28, 56.0)],
                                              same_camera)
    values = _joint_values(toy, rng, 2, same_camera)
    stage = Stage("photo-1", ("id",), ALL_TERMS, sigma=1e-3, gamma=1e-2)
    loss, grads, terms = objective(values, stage)
    assert set(terms) == set(ALL_TERMS) and np.isclose(sum(terms.values()), loss)
    for name in values:
        fd = central_differences(objective, values, stage, name)
        np.testing.assert_allclose(grads[name], fd, rtol=2e-5, atol=2e-5 * np.abs(fd).max() + 1e-9, err_msg=name)


def test_shared_priors_count_once_and_the_rest_adds_up(toy):
    """The same photo twice at the same values: twice the single objective, less one identity
    and one albedo prior."""
    rng = np.random.default_rng(4)
    single = _objective(toy, rng, 32)
    twin = face.FaceObjective(single.scene, single.image, single.target, focal0=single.focal0)
    values = _joint_values(toy, rng, 1)
    both = dict(values, **{f"{b}.1": values[f"{b}.0"] for b in PER_VIEW})
    stage = Stage("photo-1", ("id",), ALL_TERMS, sigma=1e-3, gamma=1e-2)
    one, g_one, t_one = face_views.FaceViewsObjective([single])(values, stage)
    two, g_two, t_two = face_views.FaceViewsObjective([single, twin])(both, stage)
    once = t_one["id_prior"] + t_one["albedo_prior"]
    assert once > 0
    np.testing.assert_allclose(two, 2 * one - once, rtol=1e-12)
    assert t_two["id_prior"] == t_one["id_prior"] and t_two["exp_prior"] == 2 * t_one["exp_prior"]
    prior_grad = {"id": 2 * values["id"], "albedo": 2 * values["albedo"]}   # d/dc of sum c^2
    for b in face_views.SHARED:
        np.testing.assert_allclose(g_two[b], 2 * g_one[b] - prior_grad[b], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(g_two["sh.1"], g_one["sh.0"], rtol=1e-12)


def test_shared_focal_scales_per_photo_and_its_prior_counts_once(toy):
    """same_camera: photo k sees the shared focal times its focal0 ratio; one focal prior."""
    rng = np.random.default_rng(6)
    views = [_objective(toy, rng, 32), _objective(toy, rng, 32, 40.0)]
    values = _joint_values(toy, rng, 2, same_camera=True)
    objective = face_views.FaceViewsObjective(views, same_camera=True)
    np.testing.assert_array_equal(objective.focal_scales, [1.0, 0.5])
    np.testing.assert_array_equal(objective.view_values(values, 1)["focal"], values["focal"] * 0.5)
    stage = Stage("photo-1", ("id",), ALL_TERMS, sigma=1e-3, gamma=1e-2)
    separate = dict(values, **{"focal.0": values["focal"], "focal.1": values["focal"] * 0.5})
    shared_loss, _, shared_terms = objective(values, stage)
    loss, _, terms = face_views.FaceViewsObjective(views)(separate, stage)
    assert terms["focal_prior"] > 0
    assert shared_terms["focal_prior"] == pytest.approx(terms["focal_prior"] / 2, rel=1e-12)
    assert shared_loss == pytest.approx(loss - terms["focal_prior"] / 2, rel=1e-12)


def test_one_photo_objective_is_the_single_photo_objective(toy):
    rng = np.random.default_rng(5)
    single = _objective(toy, rng, 32)
    values = _joint_values(toy, rng, 1)
    plain = {b: values[face_views.view_block(b, 0)] for b in face_views.FaceViewsObjective.BLOCKS}
    stage = Stage("photo-1", ("id",), ALL_TERMS, sigma=1e-3, gamma=1e-2)
    loss, grads, terms = face_views.FaceViewsObjective([single])(values, stage)
    loss1, grads1, terms1 = single(plain, stage)
    assert loss == loss1 and terms == terms1
    for b, g in grads1.items():
        np.testing.assert_array_equal(grads[face_views.view_block(b, 0)], g)


def _twin_objectives(model, sizes, values, robust):
    """Two lists of objectives made alike, one per size: photo k a random image with the model's
    landmarks at its ``values`` (joint values) as its landmarks, so that its face region holds
    the face (a stage's first photometric call changes an objective, so each way of evaluating
    gets its own list)."""
    made = []
    for _ in range(2):
        rng = np.random.default_rng(len(sizes))
        objectives = []
        for k, size in enumerate(sizes):
            scene = face.FaceScene(model, (size, size))
            view = {b: values[face_views.view_block(b, k)] for b in face_views.FaceViewsObjective.BLOCKS}
            points = scene.camera(view["focal"][0]).project_pixels(model.landmarks(scene.geometry(view)[0])[0])[0]
            objectives.append(face.FaceObjective(scene, rng.random((size, size, 3)) * 0.5, points, focal0=70.0 + size,
                                                 robust_scale=face.ROBUST_SCALE if robust else None,
                                                 mask_erosion=0))    # the toy's region is a few pixels wide
        made.append(objectives)
    return made


@pytest.mark.parametrize("sizes, sigma, robust", [
    ((36, 36, 36), 1e-3, True),           # one batch of three at the working size
    ((36, 28, 36), 1e-3, False),          # two sizes: two renders, plain squares
    ((72, 72), 1e-3, True),               # at or above COARSE_SIGMA: the half-size copies, coarse mesh
    ((72, 72), 1e-5, True),               # below it: the working size
])
def test_photos_rendered_together_give_each_photos_own_term_to_the_bit(toy, sizes, sigma, robust):
    """photo_terms (one render of the photos that can share it) against each photo's own
    FaceObjective.photo, and the joint objective against its photos' objectives summed one by
    one: equal to the bit, at two evaluations of a stage (its start, then within it)."""
    rng = np.random.default_rng(11)
    start = _joint_values(toy, rng, len(sizes))
    for k, size in enumerate(sizes):
        start[f"focal.{k}"] = start[f"focal.{k}"] * size / 36
    together, alone = _twin_objectives(toy, sizes, start, robust)
    for evaluation in range(2):
        values = {name: v + evaluation * rng.normal(scale=0.01, size=v.shape) for name, v in start.items()}
        views = [face_views.FaceViewsObjective(together).view_values(values, k) for k in range(len(sizes))]
        stage = Stage("photo-1", ("id",), ALL_TERMS, sigma=sigma, gamma=1e-2)
        worlds = [o.scene.geometry(v)[0] for o, v in zip(together, views)]
        got = face_views.photo_terms(together, views, worlds, stage)
        want = [o.photo(v, w, stage) for o, v, w in zip(alone, views, worlds)]
        assert (together[0].photo_level(sigma) is together[0]) == (sigma < face.COARSE_SIGMA or sizes[0] < 64)
        for (value, grads), (want_value, want_grads) in zip(got, want, strict=True):
            assert value == want_value and value > 0, evaluation
            assert grads.keys() == want_grads.keys()
            for name, g in want_grads.items():
                assert np.array_equal(grads[name], g), (name, evaluation)


def test_joint_objective_is_its_photos_objectives_summed(toy):
    """The joint loss, gradients and terms: each photo's objective (evaluated alone) summed in
    photo order, to the bit."""
    values = _joint_values(toy, np.random.default_rng(12), 2)
    together, alone = _twin_objectives(toy, (36, 36), values, True)
    stage = Stage("photo-1", ("id",), ALL_TERMS, sigma=1e-3, gamma=1e-2)
    joint = face_views.FaceViewsObjective(together)
    loss, grads, terms = joint(values, stage)
    want_loss, want_grads, want_terms = 0.0, {}, {}
    for k, objective in enumerate(alone):
        value, g, t = objective(joint.view_values(values, k), joint.view_stage(stage, k))
        want_loss += value
        for name, grad in g.items():
            key = face_views.view_block(name, k)
            want_grads[key] = want_grads[key] + grad if key in want_grads else grad
        for name, v in t.items():
            want_terms[name] = want_terms.get(name, 0.0) + v
    assert loss == want_loss and terms == want_terms
    assert grads.keys() == want_grads.keys()
    for name, g in want_grads.items():
        assert np.array_equal(grads[name], g), name


@pytest.fixture(scope="module")
def demo():
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    return load_demo_face_model().truncated(6, 4, 3)


TINY = dict(landmark_iters=15, photo_stages=((1e-4, 3e-3, 6), (1e-5, 1e-3, 6)))


@pytest.mark.parametrize("same_camera, on_mesh", [(False, False), (True, False), (False, True)])
def test_one_photo_fit_is_the_single_photo_fit(demo, same_camera, on_mesh):
    """Same parameter layout, stages and objective: the fitted values and every evaluation's
    loss are those of fit_face (one photo's camera is its own with same_camera too; landmarks
    MediaPipe found are tied to its Face Mesh points in both)."""
    sample = synthetic_face(demo, np.random.default_rng(7), size=64)
    config = face.FaceFitConfig(size=64, **TINY)
    single = face.fit_face(sample["photo"], sample["landmarks"], demo, config, progress=False,
                           face_mesh_landmarks=on_mesh)
    joint = face_views.fit_face_views([sample["photo"]], [sample["landmarks"]], demo, config, progress=False,
                                      same_camera=same_camera, face_mesh_landmarks=[on_mesh])
    assert [h["loss"] for h in joint.result.history] == [h["loss"] for h in single.result.history]
    for b, v in single.values.items():
        np.testing.assert_array_equal(joint.views[0].values[b], v, err_msg=b)
    assert joint.metrics()["psnr_face_db"] == single.metrics()["psnr_face_db"]


def test_joint_fit_of_three_photos_shares_identity_and_albedo(demo, tmp_path):
    rng = np.random.default_rng(8)
    photos = [synthetic_face(demo, rng, size=64) for _ in range(3)]
    config = face.FaceFitConfig(size=64, **TINY)
    fit = face_views.fit_face_views([p["photo"] for p in photos], [p["landmarks"] for p in photos], demo,
                                    config, out_dir=tmp_path, progress=False)
    assert {"id", "albedo", "exp.2", "focal.2"} <= set(fit.values) and "exp" not in fit.values
    for view in fit.views:
        np.testing.assert_array_equal(view.values["id"], fit.values["id"])
    assert not np.array_equal(fit.views[0].values["rotation"], fit.views[1].values["rotation"])
    metrics = fit.metrics()
    assert len(metrics["views"]) == 3
    assert metrics["landmark_error_px"] == pytest.approx(np.mean([m["landmark_error_px"] for m in metrics["views"]]))
    assert np.load(tmp_path / "checkpoint.npz")["exp.2"].shape == (demo.n_exp,)


def test_joint_stages_free_every_photos_blocks():
    stages = face.default_stages(face.FaceFitConfig(), fit_focal=True)
    joint = face_views.joint_stages(stages, 2)
    assert joint[0].free == ("rotation.0", "rotation.1", "translation.0", "translation.1", "focal.0", "focal.1",
                             "id", "exp.0", "exp.1")
    assert [dataclasses.replace(s, free=()) for s in joint] == [dataclasses.replace(s, free=()) for s in stages]


def test_one_landmark_array_per_photo_is_required(demo):
    sample = synthetic_face(demo, np.random.default_rng(9), size=64)
    with pytest.raises(InputError, match="landmarks must hold one .* 2 photos, got 1"):
        face_views.fit_face_views([sample["photo"]] * 2, [sample["landmarks"]], demo, progress=False)
    with pytest.raises(InputError, match="at least one photo"):
        face_views.fit_face_views([], [], demo, progress=False)


def test_same_camera_needs_one_photo_size_and_a_fitted_focal(demo):
    sample = synthetic_face(demo, np.random.default_rng(9), size=64)
    photos, landmarks = [sample["photo"], sample["photo"][:, :60]], [sample["landmarks"]] * 2
    with pytest.raises(InputError, match=r"same_camera needs photos of one size .* got sizes \[\(60, 64\), \(64, 64\)\]"):
        face_views.fit_face_views(photos, landmarks, demo, progress=False, same_camera=True)
    with pytest.raises(InputError, match="same_camera fits one focal length .* config.focal gives it"):
        face_views.fit_face_views(photos[:1] * 2, landmarks, demo, face.FaceFitConfig(focal=100.0), progress=False,
                                  same_camera=True)


def test_a_photo_whose_landmarks_cannot_be_a_face_is_refused(demo):
    from softras_cl.errors import ResultError
    from support.landmark_layouts import shuffled

    sample = synthetic_face(demo, np.random.default_rng(9), size=64)
    landmarks = [sample["landmarks"], shuffled(sample["landmarks"], 0)]
    with pytest.raises(ResultError, match="not in the iBUG 300-W 68-point order"):
        face_views.fit_face_views([sample["photo"]] * 2, landmarks, demo, progress=False)


def test_the_joint_fit_weighs_detected_landmarks_as_its_config_says(demo):
    """detected_landmark_weights reaches each view of the joint fit: on, a detector's points
    weigh by their measured noise; off, as a file's (the tie's unused points at 0)."""
    sample = synthetic_face(demo, np.random.default_rng(7), size=64)
    weights = {}
    for measured in (True, False):
        config = face.FaceFitConfig(size=64, detected_landmark_weights=measured, **TINY)
        view = face_views.prepare_view(sample["photo"], sample["landmarks"], demo, config, face_mesh_landmarks=True)
        weights[measured] = view.objective.landmark_weights
    expected_on = face.tied_landmarks(demo, "auto", True, True)[1]
    expected_off = face.tied_landmarks(demo, "auto", True, False)[1]
    np.testing.assert_array_equal(weights[True], expected_on)
    np.testing.assert_array_equal(weights[False], expected_off)
    assert not np.array_equal(expected_on, expected_off)


def test_model_radius_bound_holds_for_any_coefficients(toy):
    """FaceModel.radius_bound: no vertex is farther from the model's origin, whatever the
    coefficients (the mean alone: the bound is the farthest mean vertex itself)."""
    rng = np.random.default_rng(21)
    for scale in (0.0, 1.0, 3.0, 10.0):
        c_id, c_exp = rng.normal(size=toy.n_id) * scale, rng.normal(size=toy.n_exp) * scale
        farthest = np.linalg.norm(toy.shape(c_id, c_exp)[0], axis=1).max()
        bound = toy.radius_bound(c_id, c_exp)
        assert farthest <= bound + 1e-12
        if scale == 0.0:
            assert bound == pytest.approx(farthest, rel=1e-12)


def test_a_face_too_close_to_the_camera_is_answered_not_projected(toy):
    """A point of the solver that puts a vertex nearer the camera than MIN_DEPTH, or behind it
    (a long line-search step), gets too_close_result: the objective answers instead of stopping the
    fit with "vertices are behind the camera". FaceScene.too_close against the placed shape's
    own nearest vertex, over distances from a metre to behind the camera (the bound's short cut
    and the exact test both)."""
    from softras_cl.fitting.solver import MIN_DEPTH, TOO_CLOSE_LOSS

    rng = np.random.default_rng(22)
    objective = _objective(toy, rng, 36)
    values = {name.split(".")[0]: v for name, v in _joint_values(toy, rng, 1).items()}
    for z in np.linspace(-1.0, 0.2, 49):
        placed = dict(values, translation=np.array([0.01, 0.0, z]))
        nearest = -objective.scene.geometry(placed)[0][:, 2].max()
        assert objective.scene.too_close(placed) == (nearest < MIN_DEPTH), z
    stage = Stage("photo-1", ("id",), ALL_TERMS, sigma=1e-3, gamma=1e-2)
    behind = dict(values, translation=np.array([0.0, 0.0, 0.05]))
    assert objective(behind, stage) == (TOO_CLOSE_LOSS, {}, {"too_close": TOO_CLOSE_LOSS})
    in_view = objective(values, stage)
    assert in_view[0] < TOO_CLOSE_LOSS and "too_close" not in in_view[2]
    joint = face_views.FaceViewsObjective([objective, _objective(toy, rng, 36)])
    two = _joint_values(toy, rng, 2)
    assert joint(dict(two, **{"translation.1": np.array([0.0, 0.0, 0.05])}), stage)[0] == TOO_CLOSE_LOSS
    assert joint(two, stage)[0] < TOO_CLOSE_LOSS
