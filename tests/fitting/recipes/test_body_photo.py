"""Bodies from photos: the keypoint map on the model, the new objective terms' gradients, the
stages, and (with mediapipe) detection of a rendered person, the no-person error and a fit of a
synthetic photo. The input kinds and the EXIF field of view: tests/fitting/jobs."""
import numpy as np
import pytest

from softras_cl.errors import InputError
from softras_cl.fitting.recipes import body
from softras_cl.fitting.keypoints.pose33 import KEYPOINT_MAP, head_landmarks, keypoint_layout
from softras_cl.fitting.recipes.body_photo import BodyPhotoObjective, camera_distance, keypoint_weights, photo_stages
from softras_cl.fitting.solver import TOO_CLOSE_LOSS, Stage


def test_every_keypoint_of_the_map_lands_on_a_demo_body_point(demo_body_model):
    layout = keypoint_layout(demo_body_model)
    assert len(layout.names) == len(KEYPOINT_MAP)
    rest = layout.points(demo_body_model.rest_joints(np.zeros(demo_body_model.n_betas)), demo_body_model.v_template)
    named = dict(zip(layout.names, rest))
    # the subject's left at +x, the face at +z, the nose in front of the ears, above the shoulders
    for side, sign in (("left", 1), ("right", -1)):
        for part in ("shoulder", "elbow", "wrist", "hand", "hip", "knee", "ankle", "ear"):
            assert sign * named[f"{side}_{part}"][0] > 0, f"{side}_{part}"
    assert named["nose"][2] > named["left_ear"][2] + 0.05
    assert named["nose"][1] > named["left_shoulder"][1] + 0.1
    assert abs(named["left_ear"][1] - named["nose"][1]) < 0.1
    assert layout.torso.sum() == 4


def test_a_model_without_a_head_joint_leaves_the_face_points_out(demo_body_model):
    class Headless:
        joint_names = [n if n != "head" else "skull" for n in demo_body_model.joint_names]
        weights, v_template, n_betas = demo_body_model.weights, demo_body_model.v_template, demo_body_model.n_betas
        rest_joints = demo_body_model.rest_joints

    layout = keypoint_layout(Headless())
    assert head_landmarks(Headless()) == {} and "nose" not in layout.names and "left_knee" in layout.names


def test_weights_drop_unseen_and_outside_keypoints(demo_body_model):
    layout = keypoint_layout(demo_body_model)
    points = np.full((33, 2), 50.0)
    visibility = np.full(33, 0.9)
    visibility[25] = 0.1                                # left knee: not sure
    points[27] = (50.0, 120.0)                          # left ankle below a 100 px tall photo
    w = dict(zip(layout.names, keypoint_weights(layout, points, visibility, (100, 100))))
    assert w["left_knee"] == 0 and w["left_ankle"] == 0
    assert w["right_knee"] == pytest.approx(0.9)
    assert w["left_hip"] == pytest.approx(0.9 * layout.weights[layout.names.index("left_hip")])
    visibility[17] = 0.4                                # the left pinky: the hand as seen as its less seen point
    assert dict(zip(layout.names, keypoint_weights(layout, points, visibility, (100, 100))))["left_hand"] == \
        pytest.approx(0.4 * layout.weights[layout.names.index("left_hand")])


def _objective(model, size=(40, 32), faces=None):
    rng = np.random.default_rng(3)
    layout = keypoint_layout(model)
    config = body.BodyFitConfig(size=40, dtype="float64")
    scene = body.BodyScene(model, size, config)
    target = body.prepare_target(np.pad(np.ones((20, 10)), ((10, 10), (11, 11))), 40, (0, 0, 0), None, None,
                                 model.n_joints)
    keypoints = rng.uniform(5, 30, (len(layout.names), 2))
    weights = rng.uniform(0.2, 1.0, len(layout.names))
    depth = rng.normal(0.0, 0.3, len(layout.names))
    return BodyPhotoObjective(scene, target, layout, keypoints, weights, robust_px=4.0, faces=faces, depth=depth)


@pytest.mark.parametrize("term", ["keypoints", "torso", "depth"])
def test_keypoint_terms_match_central_differences(demo_body_model, term):
    objective = _objective(demo_body_model)
    rng = np.random.default_rng(0)
    values = body.rest_values(demo_body_model)
    values["body_pose"] = rng.normal(0, 0.1, values["body_pose"].shape)
    values["translation"] = np.array([0.02, -0.1, 0.1])
    stage = Stage("s", ("body_pose", "translation"), {term: 1.0})
    _, grads, _ = objective(values, stage)
    for block, index in (("translation", (1,)), ("body_pose", (15, 2)), ("global_rotation", (1,))):
        step = 1e-6
        plus, minus = {k: v.copy() for k, v in values.items()}, {k: v.copy() for k, v in values.items()}
        plus[block][index] += step
        minus[block][index] -= step
        numeric = (objective(plus, stage)[0] - objective(minus, stage)[0]) / (2 * step)
        assert grads[block][index] == pytest.approx(numeric, rel=1e-5, abs=1e-6), (block, index)


def test_stages_follow_the_objective():
    names = lambda stages: [s.name for s in stages]
    assert names(photo_stages("fast")) == ["torso", "pose", "silhouette-1"]
    assert names(photo_stages("fast", "keypoints")) == ["torso", "pose"]
    mask = photo_stages("default", "mask")
    assert names(mask) == ["silhouette-1", "silhouette-2"] and all("keypoints" not in s.weights for s in mask)
    torso = photo_stages("default")[0]
    assert set(torso.free) == {"global_rotation", "translation"} and set(torso.weights) == {"torso", "translation_prior"}
    assert all(s.sigma is not None and "silhouette" in s.weights for s in photo_stages("default")[2:])
    assert all(s.weights["depth"] > 0 for s in photo_stages("default")[1:])
    with pytest.raises(InputError, match="objective must be one of"):
        photo_stages("fast", "both")


def test_camera_distance_puts_the_model_torso_on_the_detected_one(demo_body_model):
    layout = keypoint_layout(demo_body_model)
    rest = layout.points(demo_body_model.rest_joints(np.zeros(demo_body_model.n_betas)), demo_body_model.v_template)
    focal, depth = 200.0, 4.0
    pixels = rest[:, :2] * focal / depth                # a frontal (orthographic-like) view at 4 m
    weights = np.ones(len(layout.names))
    # the torso's 3D length includes its small forward lean, which a frontal view does not show
    assert camera_distance(demo_body_model, layout, pixels, weights, focal) == pytest.approx(depth, rel=0.01)
    weights[layout.names.index("left_hip")] = 0         # hips unseen: from the shoulder width
    assert camera_distance(demo_body_model, layout, pixels, weights, focal) == pytest.approx(depth, rel=1e-9)
    assert camera_distance(demo_body_model, layout, 2 * pixels, weights, focal) == pytest.approx(depth / 2)
    weights[layout.names.index("left_shoulder")] = 0
    assert camera_distance(demo_body_model, layout, pixels, weights, focal) is None


@pytest.fixture(scope="module")
def synthetic(demo_body_model):
    from softras_cl.bench.body_photo import synthetic_photo

    return synthetic_photo(demo_body_model, np.random.default_rng(1), 256, 30.0)


@pytest.mark.detect
def test_detects_a_rendered_person_where_it_is(demo_body_model, synthetic):
    from softras_cl.fitting.detection.people import detect_person
    from softras_cl.fitting.keypoints import pose33

    found = detect_person(synthetic["image"])
    layout = keypoint_layout(demo_body_model)
    truth = synthetic["camera"].project_pixels(layout.points(synthetic["joints_3d"], synthetic["vertices"]))[0]
    points, visibility = layout.detected(found.keypoints, found.visibility)
    seen = visibility > 0.5
    error = np.linalg.norm(points - truth, axis=1)[seen]
    assert seen.sum() >= 10 and np.median(error) < 8.0, error
    mask = found.mask > 0.5
    iou = (mask & synthetic["mask"]).sum() / (mask | synthetic["mask"]).sum()
    assert iou > 0.7 and found.people == 1 and len(pose33.NAMES) == 33
    assert found.box[2] > 30 and found.box[3] > 80


@pytest.mark.detect
def test_no_person_is_an_error_naming_the_photo():
    import skimage.data

    from softras_cl.errors import ResultError
    from softras_cl.fitting.detection.people import NoPersonError, detect_person

    with pytest.raises(NoPersonError, match="no person found in coffee.png") as raised:
        detect_person(skimage.data.coffee(), "coffee.png")
    assert isinstance(raised.value, ResultError)


@pytest.mark.detect
@pytest.mark.slow
def test_fit_of_a_synthetic_photo_beats_the_rest_pose(demo_body_model, synthetic):
    from softras_cl.bench.body_photo import evaluate
    from softras_cl.fitting.detection.people import detect_person
    from softras_cl.fitting.recipes.body_photo import fit_body_photo

    detection = detect_person(synthetic["image"])
    fit = fit_body_photo((256, 256), detection, demo_body_model, body.BodyFitConfig(), "fast", progress=False)
    metrics, scores = fit.metrics(), evaluate(fit, synthetic)
    assert metrics["keypoint_error_px_full"] < 12.0 and scores["mask_iou"] > 0.75
    assert scores["pa_mpjpe_mm"] < 110.0


def test_an_empty_person_mask_is_a_result_error(demo_body_model):
    from softras_cl.errors import ResultError
    from softras_cl.fitting.detection.people import PersonDetection
    from softras_cl.fitting.recipes.body_photo import fit_body_photo

    empty = PersonDetection(np.full((33, 2), 20.0), np.ones(33), np.zeros((40, 40)), np.array([0, 0, 1, 1.0]),
                            1.0, 1, "test")
    with pytest.raises(ResultError, match="person mask is empty"):
        fit_body_photo((40, 40), empty, demo_body_model, body.BodyFitConfig(size=32), "fast", progress=False)


def test_a_regions_pass_whose_mask_agrees_with_the_selfie_mask_is_kept(monkeypatch):
    from softras_cl.fitting.detection import people

    selfie = np.zeros((100, 100), bool)
    selfie[20:80, 40:60] = True                           # the person-like region
    region = people.person_regions(selfie)[0]

    def pose_at(box, points_value):
        """A fake pose: keypoints all at ``points_value``, its mask the box (x0, y0, x1, y1)."""
        mask = np.zeros((100, 100))
        mask[box[1]:box[3], box[0]:box[2]] = 1.0
        return np.full((33, 2), float(points_value)), np.ones(33), mask, np.zeros(33)

    # tight: right, loose: wrong (keypoints inside the crops, each pass told by their value)
    passes = {0.1: pose_at((40, 20, 60, 80), 50), 0.25: pose_at((20, 10, 90, 95), 51)}
    monkeypatch.setattr(people, "_pose_in", lambda crop, x0, y0, shape: passes[
        min(passes, key=lambda m: abs(people._crop(shape, region, m)[0] - x0))])
    wrong_whole = pose_at((0, 0, 100, 100), 52)
    found, how = people._largest_in_regions(np.zeros((100, 100, 3), np.uint8), [region], selfie, wrong_whole)
    assert found[0][0, 0] == 50 and how == "a person-like region's crop (margin 0.1)"
    passes[0.1] = None                                    # no pose on the tight crop: the better of the others
    found, how = people._largest_in_regions(np.zeros((100, 100, 3), np.uint8), [region], selfie, wrong_whole)
    assert found[0][0, 0] == 51 and "margin 0.25" in how


def test_a_crop_that_cut_the_person_off_is_grown_to_its_keypoints(monkeypatch):
    """The selfie region stops at the hips; on its crops the pose model's mask stops in a straight
    line at the crop's bottom edge while its keypoints go on below: the crop grown to hold them
    is run, and its pass is kept although it agrees less with the (legless) selfie region."""
    from softras_cl.fitting.detection import people

    selfie = np.zeros((100, 100), bool)
    selfie[20:50, 40:60] = True
    region = people.person_regions(selfie)[0]
    keypoints = np.stack([np.full(33, 50.0), np.linspace(20, 90, 33)], 1)     # down to y = 90

    def pose_in(crop, x0, y0, shape):
        """The person's mask, rows 20..90, as far as the crop reaches."""
        mask = np.zeros((100, 100))
        mask[20:min(90, y0 + crop.shape[0]), 40:60] = 1.0
        return keypoints, np.ones(33), mask, np.zeros(33)

    monkeypatch.setattr(people, "_pose_in", pose_in)
    found, how = people._largest_in_regions(np.zeros((100, 100, 3), np.uint8), [region], selfie, None)
    assert "grown to its keypoints" in how and (found[2][85, 50] == 1)
    # keypoints inside the crop: a mask along its edge alone cuts nothing off, the tight crop stays
    keypoints = np.stack([np.full(33, 50.0), np.linspace(20, 50, 33)], 1)
    found, how = people._largest_in_regions(np.zeros((100, 100, 3), np.uint8), [region], selfie, None)
    assert how == "a person-like region's crop (margin 0.1)"


@pytest.mark.detect
def test_detects_a_person_whose_legs_the_selfie_mask_misses(demo_body_model):
    """bench body-photo seed 2, photo 18 (over the rocket): the selfie mask stops at the hips and
    the region's crops cut the legs off (person mask IoU 0.64 with the truth, PA-MPJPE 174 mm);
    the grown crop finds the whole person."""
    from softras_cl.bench.body_photo import synthetic_photo
    from softras_cl.fitting.detection.people import detect_person

    rng = np.random.default_rng(2)
    for _ in range(18):
        sample = synthetic_photo(demo_body_model, rng, 256, 30.0)
    assert sample["background"] == "rocket"
    found = detect_person(sample["image"])
    mask = found.mask > 0.5
    assert "grown" in found.note and (mask & sample["mask"]).sum() / (mask | sample["mask"]).sum() > 0.85


@pytest.mark.detect
def test_detects_the_person_in_front_of_the_coffee_cup(demo_body_model):
    """The whole photo and the loose crop take the cup for part of a smaller person there (median
    keypoint error ~90 px); the tight crop finds the person (bench body-photo seed 0, photo 2)."""
    from softras_cl.bench.body_photo import synthetic_photo
    from softras_cl.fitting.detection.people import detect_person

    rng = np.random.default_rng(0)
    synthetic_photo(demo_body_model, rng, 256, 30.0)
    sample = synthetic_photo(demo_body_model, rng, 256, 30.0)
    assert sample["background"] == "coffee"
    found = detect_person(sample["image"])
    layout = keypoint_layout(demo_body_model)
    truth = sample["camera"].project_pixels(layout.points(sample["joints_3d"], sample["vertices"]))[0]
    error = np.linalg.norm(layout.detected(found.keypoints, found.visibility)[0] - truth, axis=1)
    assert np.median(error) < 10.0 and "margin 0.1" in found.note, (np.median(error), found.note)
    mask = found.mask > 0.5
    assert (mask & sample["mask"]).sum() / (mask | sample["mask"]).sum() > 0.8


def test_the_depth_term_is_zero_at_the_detected_depths_and_grows_away_from_them(demo_body_model):
    objective = _objective(demo_body_model)
    values = body.rest_values(demo_body_model)
    stage = Stage("s", ("body_pose",), {"depth": 1.0})
    state, _ = objective.scene.pose(values)
    axis = objective.scene.camera.rotation_matrix()[2]
    depth = objective.layout.points(state.joints, state.vertices) @ axis
    objective.depth = depth - depth[objective.hips].mean()
    assert objective(values, stage)[0] == pytest.approx(0.0, abs=1e-12)
    objective.depth = objective.depth + np.where(objective.layout.torso, 0.0, 0.2)   # limbs 20 cm further
    assert objective(values, stage)[0] > 1.0
    objective.depth = None                              # a detection without depths: no term
    assert objective(values, stage)[0] == 0.0


def test_photo_params_keep_the_body_within_half_the_camera_distance(demo_body_model):
    from softras_cl.fitting.recipes.body_photo import photo_params

    scene = body.BodyScene(demo_body_model, (40, 32), body.BodyFitConfig(size=40, distance=4.0))
    values = body.rest_values(demo_body_model)
    values["translation"] = np.array([0.1, -0.2, 9.0])            # a start behind the camera
    params = photo_params(demo_body_model, values, scene)
    lower, upper = params.block_bounds("translation")
    assert np.allclose(lower, -2.0) and np.allclose(upper, 2.0)
    assert np.allclose(params.values()["translation"], [0.1, -0.2, 2.0])
    lower, upper = body.body_params(demo_body_model, values).block_bounds("translation")   # the body recipe's: free
    assert np.all(np.isinf(lower)) and np.all(np.isinf(upper))


def _person(layout, mask_rows):
    """A detection of a standing stick person 100 px tall in a 120 x 80 photo, its mask the rows
    ``mask_rows`` (a slice) of its box."""
    from softras_cl.fitting.detection.people import PersonDetection

    keypoints = np.zeros((33, 2))
    heights = {11: 30, 12: 30, 13: 45, 14: 45, 15: 58, 16: 58, 17: 62, 18: 62, 19: 62, 20: 62, 23: 60, 24: 60,
               25: 80, 26: 80, 27: 100, 28: 100, 31: 104, 32: 104, 0: 14, 7: 12, 8: 12}
    for k, y in heights.items():
        keypoints[k] = (40 + (6 if k % 2 else -6), y)
    mask = np.zeros((120, 80))
    mask[mask_rows, 30:51] = 1.0
    return PersonDetection(keypoints, np.ones(33), mask, np.array([30, 10, 21, 100.0]), 1.0, 1, "test",
                           np.zeros(33))


def test_mask_misses_names_the_keypoints_far_outside_the_mask(demo_body_model):
    from softras_cl.fitting.recipes.body_photo import mask_misses

    layout = keypoint_layout(demo_body_model)
    used = np.ones(len(layout.names))
    whole = _person(layout, slice(5, 110))
    assert mask_misses(layout, whole.keypoints, used, whole.mask) == []
    legless = _person(layout, slice(5, 65))              # cut at the hips: knees, ankles, feet far outside
    legs = {"left_knee", "right_knee", "left_ankle", "right_ankle", "left_foot", "right_foot"}
    assert set(mask_misses(layout, legless.keypoints, used, legless.mask)) == legs
    unseen = np.array([0.0 if name in ("left_ankle", "left_foot") else 1.0 for name in layout.names])
    assert set(mask_misses(layout, legless.keypoints, unseen, legless.mask)) == legs - {"left_ankle", "left_foot"}


def test_limb_care_leaves_out_the_missed_limbs_outside_the_mask(demo_body_model):
    from softras_cl.fitting.recipes.body_photo import limb_care, mask_misses

    layout = keypoint_layout(demo_body_model)
    legless = _person(layout, slice(5, 65))
    points, weights = layout.detected(legless.keypoints, legless.visibility)
    missed = mask_misses(layout, legless.keypoints, weights, legless.mask)
    care = limb_care(layout, points, weights, missed, legless.mask)
    assert care.shape == legless.mask.shape and set(np.unique(care)) == {0.0, 1.0}
    assert (care[legless.mask > 0.5] == 1).all()                 # the mask is trusted where it is
    assert care[80, 34] == 0 and care[100, 46] == 0              # beside the knee, on the ankle
    assert care[100, 5] == 1 and care[20, 75] == 1               # far from the legs
    # only the missed limbs: with the right leg seen inside the mask, its pixels stay
    left_only = limb_care(layout, points, weights, [m for m in missed if m.startswith("left")], legless.mask)
    assert care[100, 34] == 0 and left_only[100, 34] == 1 and left_only[100, 46] == 0


def test_a_mask_that_misses_the_legs_is_not_trusted_around_them(demo_body_model):
    from dataclasses import replace

    from softras_cl.fitting.recipes.body_photo import fit_body_photo

    layout = keypoint_layout(demo_body_model)
    config = body.BodyFitConfig(size=32)
    whole = fit_body_photo((120, 80), _person(layout, slice(5, 110)), demo_body_model, config, "fast", progress=False)
    assert any(name.startswith("silhouette") for name in whole.result.outcomes) and not whole.mask_misses
    assert whole.target.care is None
    legless = fit_body_photo((120, 80), _person(layout, slice(5, 65)), demo_body_model, config, "fast", progress=False)
    assert any(name.startswith("silhouette") for name in legless.result.outcomes)
    assert legless.metrics()["mask_misses"] == 6 and len(legless.mask_misses) == 6
    care = legless.target.care
    assert care.shape == legless.target.alpha.shape and 0 < (care == 0).mean() < 0.5
    assert (care[legless.target.alpha > 0.5] == 1).all()
    hidden_legs = replace(_person(layout, slice(5, 65)), visibility=np.where(np.arange(33) >= 25, 0.1, 1.0))
    hidden = fit_body_photo((120, 80), hidden_legs, demo_body_model, config, "fast", progress=False)
    assert any(name.startswith("silhouette") for name in hidden.result.outcomes) and not hidden.mask_misses
    assert hidden.target.care is None


def _whole_body(objective):
    """``objective`` posing every vertex and drawing colours too at every evaluation: the
    reference its subsets and alpha-only renders must match."""
    faces = objective.scene.model.faces if objective.faces is None else np.asarray(objective.faces, np.int32)
    objective.posed = lambda renders: body._Posed(None, faces, objective.scene.colors)
    objective.render_changes = {}
    return objective


def _assert_same_evaluation(got, want):
    """The same loss and terms, bit for bit, and gradients (the betas' within 1e-14 of their
    largest: BodyModel.subset's shorter sums)."""
    assert got[0] == want[0] and got[2] == want[2] and set(got[1]) == set(want[1])
    for name, value in want[1].items():
        np.testing.assert_allclose(got[1][name], value, rtol=0, atol=1e-14 * np.abs(value).max() if name == "betas" else 0)


@pytest.mark.parametrize("coarse", [None, 3.0], ids=["all faces", "coarse mesh"])
def test_posing_only_the_vertices_read_gives_the_whole_body(demo_body_model, coarse):
    """Every stage of a photo fit (keypoint stages pose the landmarks alone, silhouette stages
    the drawn faces' vertices and render alpha alone), at random shapes and poses, and with the
    body so near the camera that its joints and reach cannot tell (posed whole to decide) or
    through it (refused)."""
    from softras_cl.fitting.models.mesh_lod import coarse_faces

    model = demo_body_model
    faces = None if coarse is None else coarse_faces(model.v_template, model.faces, coarse)
    fast, whole = _objective(model, faces=faces), _whole_body(_objective(model, faces=faces))
    assert fast.render_changes == {"outputs": ("alpha",)}
    rng = np.random.default_rng(5)
    scene, stages = fast.scene, photo_stages("default")
    axis, offset = scene.camera.rotation_matrix()[2], float(scene.camera.translation[2])
    for place in ("there", "moved", "near", "through"):
        values = body.rest_values(model)
        values.update(betas=rng.normal(0, 1, model.n_betas), body_pose=rng.normal(0, 0.3, values["body_pose"].shape),
                      global_rotation=rng.normal(0, 0.3, 3), translation=np.array([0.05, -0.1, 0.0]))
        nearest = float((scene.pose(values)[0].vertices @ axis).min()) + offset      # metres to the camera
        values["translation"][2] += {"there": 0.0, "moved": 0.1, "near": nearest - 0.05, "through": nearest + 0.1}[place]
        for stage in stages:
            _assert_same_evaluation(fast(values, stage), whole(values, stage))
        state, ctx = scene.pose(values, fast.posed(False).subset)
        clear = scene.clear_of_camera(state.joints, model.reach(values["betas"], ctx.rot_local))
        assert clear == (place in ("there", "moved"))
        assert (fast(values, stages[0])[2] == {"too_close": TOO_CLOSE_LOSS}) == (place == "through")


def test_the_layout_on_a_subset_reads_the_same_points(demo_body_model):
    layout = keypoint_layout(demo_body_model)
    landmarks = layout.vertices[layout.vertices >= 0]
    ids = np.union1d(landmarks, [0, 100, 5000])
    state, _ = body.BodyScene(demo_body_model, (40, 32)).pose(body.rest_values(demo_body_model))
    on_rows = layout.on_rows(ids)
    assert np.array_equal(on_rows.points(state.joints, state.vertices[ids]), layout.points(state.joints, state.vertices))
    grad = np.random.default_rng(0).normal(size=(len(layout.names), 3))
    g_joints, g_rows = on_rows.points_vjp(grad, demo_body_model.n_joints, len(ids))
    want_joints, want_vertices = layout.points_vjp(grad, demo_body_model.n_joints, demo_body_model.n_vertices)
    assert np.array_equal(g_joints, want_joints) and np.array_equal(g_rows, want_vertices[ids])
    with pytest.raises(ValueError, match="surface landmarks"):
        layout.on_rows(np.setdiff1d(ids, landmarks[:1]))
    with pytest.raises(ValueError, match="surface landmarks"):
        layout.on_rows(np.zeros(0, np.int64))
