"""Body fitting recipe (fitting/body.py): exact objective gradients, the hinge limits, input
checks, the schedule, and recovery of a known pose from its image and joints."""
import re

import numpy as np
import pytest
from softras_cl.fitting.models.mesh_lod import coarse_faces
from softras_cl.fitting.recipes import body
from softras_cl.fitting.solver import Stage

ALL_TERMS = dict(image=100.0, silhouette=10.0, joints=0.25, pose_prior=1.0, shape_prior=1.0,
                 translation_prior=1.0, limits=100.0)


@pytest.fixture(scope="module")
def model(demo_body_model):
    return demo_body_model


def _index(model, name):
    return model.joint_names.index(name) - 1


def random_values(model, rng):
    values = body.rest_values(model)
    values["betas"] = rng.normal(0, 0.5, model.n_betas)
    values["body_pose"] = rng.normal(0, 0.15, values["body_pose"].shape)
    values["body_pose"][_index(model, "left_elbow")] = [0.0, 0.9, 0.0]     # past the limits
    values["body_pose"][_index(model, "right_knee")] = [-0.4, 0.1, 0.3]
    values["global_rotation"] = np.array([0.05, 0.2, -0.03])
    values["translation"] = np.array([0.03, -0.02, 0.05])
    return values


def synthetic_target(model, values, size):
    """(image (size, size, 3) hard-rendered part colours, 2D joints (J, 2))."""
    scene = body.BodyScene(model, (size, size), body.BodyFitConfig(size=size))
    state, _ = scene.pose(values)
    image = scene.composite(scene.render(state.vertices, 1e-6, 1e-4, color_agg="hard", alpha_agg="hard"))
    return image, scene.camera.project_pixels(state.joints)[0]


@pytest.mark.parametrize("weights, robust, coarse", [
    (ALL_TERMS, 3.0, None), (ALL_TERMS, None, None), (ALL_TERMS, None, 3.0),
    (dict(joints=0.25, pose_prior=1.0, limits=100.0), None, None)],
    ids=["image stage, robust joints", "image stage", "image stage, coarse mesh", "joint stage"])
def test_objective_gradient_matches_central_differences(model, weights, robust, coarse):
    rng = np.random.default_rng(3)
    size = 32
    image, joints = synthetic_target(model, body.rest_values(model), size)
    scene = body.BodyScene(model, (size, size), body.BodyFitConfig(size=size))
    scene.settings = scene.settings.replace(dist_eps=1e-9)    # a tiny cut-off: smooth for differences
    target = body.prepare_target(image, size, joints=np.clip(joints + rng.normal(0, 2, joints.shape), 0, size - 1),
                                 joint_weights=rng.uniform(0.5, 1.5, model.n_joints), n_joints=model.n_joints)
    faces = None if coarse is None else coarse_faces(model.v_template, model.faces, coarse)
    objective = body.BodyObjective(scene, target, robust_px=robust, faces=faces)
    stage = Stage("s", ("betas",), weights, sigma=1e-4, gamma=1e-2)
    values = random_values(model, rng)
    _, grads, terms = objective(values, stage)
    assert set(terms) == set(weights)
    picks = [("betas", (0,)), ("betas", (7,)), ("global_rotation", (0,)), ("global_rotation", (1,)),
             ("translation", (0,)), ("translation", (2,)), ("body_pose", (_index(model, "left_elbow"), 1)),
             ("body_pose", (_index(model, "right_knee"), 0)), ("body_pose", (_index(model, "spine2"), 2)),
             ("body_pose", (_index(model, "right_shoulder"), 2))]
    for name, i in picks:
        h = 1e-6
        plus, minus = {**values, name: values[name].copy()}, {**values, name: values[name].copy()}
        plus[name][i] += h
        minus[name][i] -= h
        fd = (objective(plus, stage)[0] - objective(minus, stage)[0]) / (2 * h)
        assert grads[name][i] == pytest.approx(fd, rel=1e-5, abs=1e-4 * max(1.0, abs(fd))), (name, i)


def test_joint_limits_penalise_hyperextension_only_and_have_exact_gradients(model):
    rows, frames, rest = body.hinge_frames(model)
    assert [model.joint_names[r + 1] for r in rows] == ["left_knee", "right_knee", "left_elbow", "right_elbow"]
    assert np.all(rest[2:] > 0.5) and np.all(np.abs(rest[:2]) < 0.3)     # the demo's bent elbows
    pose = np.zeros((model.n_joints - 1, 3))
    assert body.joint_limits(pose, rows, frames, rest)[0] == 0.0
    for r, f in zip(rows, frames):                  # flexing is free, bending backwards is not
        flexed, hyper = pose.copy(), pose.copy()
        flexed[r] = f.T @ [1.0, 0.0, 0.0]
        hyper[r] = f.T @ [-1.0, 0.0, 0.0]
        assert body.joint_limits(flexed, rows, frames, rest)[0] == 0.0
        assert body.joint_limits(hyper, rows, frames, rest)[0] > 0.0
    rng = np.random.default_rng(0)
    pose = rng.normal(0, 0.8, pose.shape)
    value, g = body.joint_limits(pose, rows, frames, rest)
    assert value > 0
    for r in rows:
        for c in range(3):
            plus, minus = pose.copy(), pose.copy()
            plus[r, c] += 1e-6
            minus[r, c] -= 1e-6
            fd = (body.joint_limits(plus, rows, frames, rest)[0] - body.joint_limits(minus, rows, frames, rest)[0]) / 2e-6
            assert g["coeffs"][r, c] == pytest.approx(fd, rel=1e-6, abs=1e-8)
    others = np.setdiff1d(np.arange(len(pose)), rows)
    assert np.all(g["coeffs"][others] == 0.0)


def test_part_colors_keep_red_for_the_right_hand(model):
    colors = body.part_colors(model)
    hand = model.part_labels == model.part_names.index("right_hand")
    assert np.allclose(colors[hand], body.RIGHT_HAND_RED)
    assert np.all(np.abs(colors[~hand] - body.RIGHT_HAND_RED).max(1) > 0.3)


@pytest.mark.parametrize("target, joints, match", [
    (np.zeros((40, 40, 2)), None, "target must be"),
    (np.zeros((10, 40, 3)), None, "at least 16"),
    (np.zeros((40, 40, 3)), None, "empty"),
    ("body", np.zeros((23, 2)), r"joints must have shape \(24, 2\)"),
    ("body", np.full((24, 2), 500.0), "outside"),
])
def test_bad_targets_and_joints_are_rejected(model, target, joints, match):
    if isinstance(target, str):
        target = synthetic_target(model, body.rest_values(model), 40)[0]
    with pytest.raises(ValueError, match=match):
        body.prepare_target(target, 40, joints=joints, n_joints=model.n_joints)


def test_the_schedule_is_followed(model, monkeypatch):
    seen, drawn = [], []
    render = body.BodyScene.render

    def recording(self, vertices, sigma, gamma, *args, **kwargs):
        seen.append((sigma, gamma))
        drawn.append(len(self.model.faces if kwargs.get("faces") is None else kwargs["faces"]))
        return render(self, vertices, sigma, gamma, *args, **kwargs)

    monkeypatch.setattr(body.BodyScene, "render", recording)
    stages_seen = []
    image, joints = synthetic_target(model, body.rest_values(model), 32)
    config = body.BodyFitConfig(size=32, joint_iters=3, image_stages=((1e-4, 1e-2, 3), (3e-5, 3e-3, 3), (1e-5, 1e-3, 3)))
    fit = body.fit_body(image, model, config, joints=joints, progress=False,
                        observer=lambda values, stage: stages_seen.append(stage.name))
    assert list(dict.fromkeys(stages_seen)) == ["joints", "image-1", "image-2", "image-3"]
    fitting_renders = [s for s in seen if s != (1e-6, 1e-4)]        # not the sharp initial render
    assert list(dict.fromkeys(fitting_renders)) == [(1e-4, 1e-2), (3e-5, 3e-3), (1e-5, 1e-3)]
    assert len(fitting_renders) == len(stages_seen) - stages_seen.count("joints")
    # the image stages draw the coarse face list, the initial sharp render the model's own
    coarse = len(coarse_faces(model.v_template, model.faces, config.coarse_mesh))
    assert {n for s, n in zip(seen, drawn) if s != (1e-6, 1e-4)} == {coarse} and coarse < len(model.faces) / 4
    assert {n for s, n in zip(seen, drawn) if s == (1e-6, 1e-4)} == {len(model.faces)}
    assert set(fit.result.outcomes) == {"joints", "image-1", "image-2", "image-3"}


@pytest.mark.slow
def test_a_small_synthetic_fit_recovers_a_known_pose(model):
    truth = body.rest_values(model)
    truth["body_pose"][_index(model, "left_shoulder")] = [0.0, 0.0, 0.5]      # arm raised sideways
    truth["body_pose"][_index(model, "right_shoulder")] = [0.0, 0.0, -0.4]
    truth["body_pose"][_index(model, "spine2")] = [0.0, 0.0, 0.15]
    truth["translation"] = np.array([0.05, 0.0, 0.0])
    size = 48
    image, joints = synthetic_target(model, truth, size)
    config = body.BodyFitConfig.from_budget("fast", size=size)
    fit = body.fit_body(image, model, config, joints=joints, progress=False)
    scene = fit.scene
    error = 1e3 * np.linalg.norm(scene.pose(fit.values)[0].joints - scene.pose(truth)[0].joints, axis=1)
    start = 1e3 * np.linalg.norm(scene.pose(body.rest_values(model))[0].joints - scene.pose(truth)[0].joints, axis=1)
    metrics = fit.metrics()
    assert error.mean() < 40.0 and error.mean() < 0.5 * start.mean()      # mm
    assert metrics["silhouette_iou"] > 0.85 and metrics["joint_error_px"] < 1.0


@pytest.mark.parametrize("changes, says", [
    (dict(distance=0.0), "distance must be > 0, got 0.0"),
    (dict(distance=-3.0), "distance must be > 0, got -3.0"),
    (dict(fov_deg=0.0), "fov_deg must be in (0, 180) degrees, got 0.0"),
    (dict(height=float("nan")), "height must be a finite number, got nan"),
    (dict(robust_px=-1.0), "robust_px must be > 0, got -1.0"),
    (dict(coarse_mesh=0.0), "coarse_mesh must be > 0, got 0.0"),
    (dict(size=4), "size must be an integer >= 16"),
    (dict(background=(0.0, 1.0)), "background must be 3 numbers"),
    (dict(objective="gpu"), "objective must be one of 'auto', 'host', 'device', got 'gpu'"),
])
def test_body_config_names_a_bad_field(changes, says):
    from softras_cl.errors import InputError

    with pytest.raises(InputError, match=re.escape(says)):
        body.BodyFitConfig(**changes)


def test_prepare_target_refuses_an_infinite_mask_before_clipping():
    mask = np.zeros((32, 32))
    mask[8:24, 8:24] = 1.0
    mask[2, 5] = np.inf
    with pytest.raises(ValueError, match=re.escape("target contains NaN or Inf (1 non-finite value(s), "
                                                   "first at index (2, 5))")):
        body.prepare_target(mask, 32)


def test_prepare_target_names_a_nan_joint_as_such():
    mask = np.zeros((32, 32))
    mask[8:24, 8:24] = 1.0
    joints = np.full((3, 2), 10.0)
    joints[1, 0] = np.nan
    with pytest.raises(ValueError, match=re.escape("joint 1 is [nan, 10.0]: a seen joint (weight > 0) needs "
                                                   "finite pixel coordinates")):
        body.prepare_target(mask, 32, joints=joints, n_joints=3)
    body.prepare_target(mask, 32, joints=joints, joint_weights=[1.0, 0.0, 1.0], n_joints=3)  # unseen: fine


def test_scene_draws_every_sigma_with_one_rasteriser_and_other_settings_with_their_own(model):
    """Renders at several (sigma, gamma) share the scene's renderer and its one rasteriser;
    render(**changes) (e.g. hard aggregation for targets) uses a renderer of its own, made once."""
    scene = body.BodyScene(model, (32, 32), body.BodyFitConfig(size=32))
    state, _ = scene.pose(body.rest_values(model))
    for sigma, gamma in ((1e-4, 1e-2), (1e-5, 1e-3), (1e-6, 1e-4)):
        out = scene.render(state.vertices, sigma, gamma, grads=("vertices",))
        drawn = out.saved.raster_out.saved.settings
        assert (drawn.sigma, drawn.gamma) == (sigma, gamma) and out.saved.renderer is scene.renderer
    hard = [scene.render(state.vertices, 1e-6, 1e-4, color_agg="hard", alpha_agg="hard") for _ in range(2)]
    assert set(np.unique(hard[0].alpha)) <= {0.0, 1.0}
    assert len(scene.renderer._rasterizers) == 1 and len(scene._variants) == 1
    assert scene.renderer.settings.color_agg == "softmax"


@pytest.mark.parametrize("coarse", [None, 3.0], ids=["all faces", "coarse mesh"])
def test_posing_only_the_drawn_vertices_gives_the_whole_body(model, coarse):
    """A colour target (rgb drawn) with the coarse mesh's vertices posed alone, a joint stage
    with none, against posing every vertex: the same loss and terms bit for bit, the same
    gradients (the betas' within 1e-14 of their largest)."""
    rng = np.random.default_rng(4)
    size = 32
    image, joints = synthetic_target(model, body.rest_values(model), size)
    scene = body.BodyScene(model, (size, size), body.BodyFitConfig(size=size))
    target = body.prepare_target(image, size, joints=joints, n_joints=model.n_joints)
    faces = None if coarse is None else coarse_faces(model.v_template, model.faces, coarse)
    fast, whole = body.BodyObjective(scene, target, 3.0, faces=faces), body.BodyObjective(scene, target, 3.0, faces=faces)
    drawn = model.faces if faces is None else faces
    whole.posed = lambda renders: body._Posed(None, drawn, scene.colors)
    assert fast.render_changes == {} and fast.posed(False).subset.ids.size == 0
    assert (fast.posed(True).subset is None) == (coarse is None)
    values = random_values(model, rng)
    for stage in (Stage("image", ("betas",), ALL_TERMS, sigma=1e-4, gamma=1e-2),
                  Stage("joints", ("betas",), dict(joints=0.25, pose_prior=1.0, limits=100.0))):
        got, want = fast(values, stage), whole(values, stage)
        assert got[0] == want[0] and got[2] == want[2] and set(got[1]) == set(want[1])
        for name, value in want[1].items():      # the betas' sums are shorter (BodyModel.subset)
            np.testing.assert_allclose(got[1][name], value, rtol=0, atol=1e-14 * np.abs(value).max() if name == "betas" else 0)


@pytest.mark.parametrize("robust", [None, 3.0])
def test_unchecked_landmark_loss_and_priors_equal_the_checked_ones_bit_for_bit(model, robust):
    """The body objective's terms (losses' unchecked forms, on its own arrays) against the
    checked functions, on the body's pose sigmas and a zero weight."""
    from softras_cl.fitting import losses

    rng = np.random.default_rng(8)
    points, target = rng.normal(0, 20, (19, 2)), rng.normal(0, 20, (19, 2))
    weights = rng.uniform(0, 1, 19)
    weights[3] = 0.0
    value, grad = losses.landmarks_2d_unchecked(points - target, weights, robust)
    want_value, want = losses.landmarks_2d(points, target, weights, robust)
    assert value == want_value and np.array_equal(grad, want["points"])
    assert losses.landmarks_2d_unchecked(np.zeros((0, 2)), np.zeros(0), robust)[0] == 0.0
    pose, sigmas = rng.normal(0, 0.3, (model.n_joints - 1, 3)), body.pose_sigmas(model)
    for block, sigma in ((pose, sigmas), (rng.normal(size=model.n_betas), 1.0), (rng.normal(size=3), body.TRANSLATION_SIGMA)):
        value, grad = losses.gaussian_prior_unchecked(block, sigma)
        want_value, want = losses.gaussian_prior(block, sigma)
        assert value == want_value and np.array_equal(grad, want["coeffs"])
