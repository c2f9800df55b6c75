"""The device face objective (fitting.device.face_objective) against the numpy FaceObjective it
replaces, in float64: loss, every gradient block and every term within 1e-10 relative at random
parameters, for the landmark stage (sliding jaw), photometric stages (robust and plain squares,
full and half resolution with the coarse mesh) and the dense term; reruns bit-identical; its
gradient against central differences; its device parts (bases, pose, photometric term) against
their numpy counterparts.

1e-10 is the bound the device objective is held to; measured: at most 2.1e-14 relative to each
array's largest magnitude on these scenes. The device adds sums left to right
in chunks where numpy calls BLAS or pairwise sums (see the test of the renderer's device path).
"""
import numpy as np
import pytest

from softras_cl.fitting import losses
from softras_cl.fitting.device.model import DeviceFaceModel
from softras_cl.fitting.device.photo import DevicePhotoLoss
from softras_cl.fitting.recipes import face
from softras_cl.fitting.recipes.contour import jaw_candidates
from softras_cl.fitting.solver import Stage
from softras_cl.scene.shading import sh_ambient
from support.gradients import central_differences
from support.toy_face import spread_landmarks, toy_face_model

RELATIVE = 1e-10
PHOTO = dict(landmarks=0.3, photo=1.0, id_prior=1.0, exp_prior=1.0, albedo_prior=1.0, sh_white=2.0,
             focal_prior=0.5)
LANDMARKS = dict(landmarks=1.0, id_prior=1.0, exp_prior=1.0, focal_prior=1.0)


@pytest.fixture(scope="module")
def demo():
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    return load_demo_face_model().truncated(8, 8, 4)


def random_values(model, rng, yaw_deg: float = 0.0) -> dict:
    return dict(id=rng.normal(size=model.n_id) * 0.5, exp=rng.normal(size=model.n_exp) * 0.5,
                albedo=rng.normal(size=model.n_albedo) * 0.5, sh=sh_ambient(0.8) + rng.normal(0, 0.1, (3, 9)),
                rotation=np.radians([8.0, yaw_deg, -4.0]) + rng.normal(0, 0.02, 3),
                translation=np.array([0.004, -0.01, -0.55]) + rng.normal(0, 0.003, 3),
                focal=np.array([150.0 + rng.normal(0, 5)]))


def landmarks_of(objective, values) -> np.ndarray:
    """The model's landmarks as they project at values, moved by a pixel or two."""
    points, _ = objective.landmark_points(values, objective.scene.geometry(values)[0])
    return points + np.random.default_rng(5).normal(0, 1.5, points.shape)


def objectives(model, size: int, values, **options):
    """(numpy FaceObjective, DeviceFaceObjective) on one photo and its landmarks."""
    rng = np.random.default_rng(7)
    scene = face.FaceScene(model, (size, size), depth_range=face.depth_range(values["translation"]))
    probe = face.FaceObjective(scene, np.zeros((size, size, 3)), np.zeros((68, 2)))
    target = landmarks_of(probe, values)
    photo = scene.render(values, 1e-4, 1e-3).rgb[0] + rng.normal(0, 0.05, (size, size, 3))
    host = face.FaceObjective(scene, photo, target, focal0=140.0, **options)
    device_scene = face.FaceScene(model, (size, size), depth_range=face.depth_range(values["translation"]))
    return host, face.DeviceFaceObjective(device_scene, photo, target, focal0=140.0, **options)


def assert_same(host_result, device_result):
    (loss_h, grads_h, terms_h), (loss_d, grads_d, terms_d) = host_result, device_result
    assert loss_d == pytest.approx(loss_h, rel=RELATIVE)
    assert set(terms_d) == set(terms_h) and set(grads_d) == set(grads_h)
    for name in terms_h:
        assert terms_d[name] == pytest.approx(terms_h[name], rel=RELATIVE), name
    for name, g in grads_h.items():
        scale = np.abs(g).max()
        np.testing.assert_allclose(grads_d[name], g, rtol=0, atol=RELATIVE * scale, err_msg=name)


@pytest.mark.parametrize("weights, robust_scale, coarse_mesh, sigma", [
    (PHOTO, 1.0, None, 1e-5), (PHOTO, None, None, 1e-5), (PHOTO, 1.0, 2.0, 1e-4), (PHOTO, None, 2.0, 1e-4),
    (dict(photo=1.0), 1.0, None, 3e-5), (LANDMARKS, 1.0, None, 0.0)],
    ids=["photo robust", "photo squares", "coarse level robust", "coarse level squares", "photo term alone",
         "landmark stage"])
def test_device_objective_equals_the_numpy_one(demo, weights, robust_scale, coarse_mesh, sigma):
    rng = np.random.default_rng(11)
    values = random_values(demo, rng, yaw_deg=50.0)           # part of the jaw slides
    host, device = objectives(demo, 96, values, robust_scale=robust_scale, coarse_mesh=coarse_mesh,
                              contour=jaw_candidates(demo))
    stage = Stage("photo-1", ("id",), weights, sigma=sigma, gamma=1e-3)
    choice = host.landmark_points(values, host.scene.geometry(values)[0])[1].choice
    assert 3 <= choice.slid.sum() < len(choice.slid)                # some jaw points slide, some stay
    for step in range(3):                     # the stage's set-up, then evaluations elsewhere
        assert_same(host(values, stage), device(values, stage))
        values = dict(values, id=values["id"] + rng.normal(0, 0.1, demo.n_id),
                      rotation=values["rotation"] + rng.normal(0, 0.01, 3),
                      albedo=values["albedo"] + rng.normal(0, 0.1, demo.n_albedo))
    if "photo" in weights:
        level = device.photo_level(sigma)
        assert level.mask.sum() > 100
        assert (level is not device) == (sigma >= face.COARSE_SIGMA)
        assert level.device_model is device.device_model            # one upload per fit


@pytest.mark.parametrize("weights", [LANDMARKS, PHOTO], ids=["landmark stage", "photo stage"])
def test_device_robust_landmark_term_equals_the_numpy_one(demo, weights):
    """landmark_robust (Geman-McClure at 1 deviation: the landmarks' 1.5 px noise puts points on
    both sides of it) on the device against the numpy objective, and its effect: a loss below
    the squared distances'."""
    rng = np.random.default_rng(17)
    values = random_values(demo, rng, yaw_deg=30.0)
    host, device = objectives(demo, 96, values, contour=jaw_candidates(demo), landmark_robust=1.0)
    plain, _ = objectives(demo, 96, values, contour=jaw_candidates(demo))
    stage = Stage("photo-1", ("id",), weights, sigma=1e-5, gamma=1e-3)
    for _ in range(2):
        assert_same(host(values, stage), device(values, stage))
        values = dict(values, rotation=values["rotation"] + rng.normal(0, 0.01, 3))
    robust_value = host.landmark_term(values, host.scene.geometry(values).world)[0]
    assert 0 < robust_value < plain.landmark_term(values, plain.scene.geometry(values).world)[0]


def test_device_objective_with_the_dense_term_equals_the_numpy_one(demo):
    rng = np.random.default_rng(12)
    values = random_values(demo, rng)
    host, device = objectives(demo, 96, values)
    dense = host.scene.camera(values["focal"][0]).project_pixels(demo.dense_points(host.scene.geometry(values)[0])[0])[0]
    host.dense_target = device.dense_target = dense + rng.normal(0, 1.0, dense.shape)
    stage = Stage("photo-1", ("id",), dict(PHOTO, dense=0.5), sigma=1e-5, gamma=1e-3)
    assert_same(host(values, stage), device(values, stage))


def test_device_objective_reruns_bit_identically(demo):
    values = random_values(demo, np.random.default_rng(13), yaw_deg=30.0)
    _, device = objectives(demo, 64, values, contour=jaw_candidates(demo))
    stage = Stage("photo-1", ("id",), PHOTO, sigma=1e-5, gamma=1e-3)
    first, second = device(values, stage), device(values, stage)
    assert first[0] == second[0]
    for name, g in first[1].items():
        assert np.array_equal(g, second[1][name]), name


def test_device_objective_gradient_matches_central_differences():
    model = toy_face_model()
    rng = np.random.default_rng(1)
    values = dict(id=rng.normal(size=model.n_id) * 0.5, exp=rng.normal(size=model.n_exp) * 0.5,
                  albedo=rng.normal(size=model.n_albedo) * 0.5, sh=sh_ambient(0.8) + rng.normal(0, 0.1, (3, 9)),
                  rotation=np.radians([10.0, -20.0, 5.0]), translation=np.array([0.01, -0.005, -0.6]),
                  focal=np.array([90.0]))
    objective = face.DeviceFaceObjective(face.FaceScene(model, (40, 40)), rng.random((40, 40, 3)) * 0.5,
                                    spread_landmarks(40) + rng.normal(0, 1, (68, 2)), focal0=80.0, robust_scale=1.0,
                                    contour=jaw_candidates(model))
    stage = Stage("photo-1", ("id",), dict(PHOTO, focal_prior=0.5), sigma=1e-3, gamma=1e-2)
    _, grads, _ = objective(values, stage)
    assert objective.mask.sum() > 200
    for name in values:
        fd = central_differences(objective, values, stage, name, step=1e-7)
        np.testing.assert_allclose(grads[name], fd, rtol=2e-5, atol=2e-5 * np.abs(fd).max() + 1e-9, err_msg=name)


def test_device_model_parts_equal_the_numpy_model(demo):
    from softras_cl.cl.device import get_context, select_device

    queue = get_context(select_device())[1]
    device = DeviceFaceModel(demo, queue)
    rng = np.random.default_rng(3)
    values = random_values(demo, rng)
    geometry = device.geometry(values)
    world, ctx = face.FaceScene(demo, (8, 8)).geometry(values)
    np.testing.assert_allclose(geometry.world.get(), world, rtol=0, atol=1e-14 * np.abs(world).max())
    g_world = rng.normal(size=world.shape)
    import pyopencl.array as cla

    expected = face.FaceScene(demo, (8, 8)).geometry_vjp(ctx, g_world)
    got, _ = device.geometry_vjp(geometry, cla.to_device(queue, g_world), {})
    for name, g in expected.items():
        np.testing.assert_allclose(got[name], g, rtol=0, atol=1e-13 * np.abs(g).max(), err_msg=name)
    albedo = demo.albedo(values["albedo"])[0]
    np.testing.assert_allclose(device.albedo(values["albedo"]).get(), albedo, rtol=0, atol=1e-14)
    g_albedo = rng.normal(size=albedo.shape)
    np.testing.assert_allclose(device.albedo_vjp(cla.to_device(queue, g_albedo)).get(),
                               demo.albedo_vjp(demo.albedo(values["albedo"])[1], g_albedo)["coeffs"],
                               rtol=1e-13, atol=0)


@pytest.mark.parametrize("scale", [None, 0.05, 1e-30, 1e30])
def test_device_photo_loss_equals_the_numpy_losses(scale):
    """Geman-McClure and plain squares, scales from tiny (every pixel saturates) to huge; an
    empty region gives 0."""
    import pyopencl.array as cla
    from softras_cl.cl.device import get_context, select_device
    from softras_cl.fitting.device.kernels import FIT_KERNELS
    from softras_cl.scene.device_kernels import SceneKernels

    queue = get_context(select_device())[1]
    kernels = SceneKernels(queue.context, queue, extra=FIT_KERNELS)
    rng = np.random.default_rng(4)
    target, pred = rng.random((20, 30, 3)), rng.random((20, 30, 3))
    mask = rng.random((20, 30)) < 0.4
    loss = DevicePhotoLoss(kernels, target, mask, scale)
    total, grad = loss(cla.to_device(queue, pred[None]), grad_scale=3.0)
    value = float(total.get()[0, 0]) / loss.total
    if scale is None:
        expected, g = losses.image_l2(pred, target, mask)
    else:
        expected, g = losses.GemanMcClure(target, scale, mask)(pred)
    assert np.isfinite(value) and value == pytest.approx(expected, rel=1e-13)
    np.testing.assert_allclose(grad.get()[0], 3.0 * g["pred"], rtol=1e-13, atol=1e-300)
    empty = DevicePhotoLoss(kernels, target, np.zeros((20, 30), bool), scale)
    assert empty(cla.to_device(queue, pred[None]))[0].get()[0, 0] == 0.0


def test_the_joint_objective_of_device_views_equals_that_of_numpy_views(demo):
    """`--same-person` on the device: the joint objective (fitting.recipes.face_views) over two
    device objectives equals it over their numpy twins, shared blocks summed over the views."""
    from softras_cl.fitting.recipes import face_views

    rng = np.random.default_rng(14)
    values = [random_values(demo, rng, yaw_deg=yaw) for yaw in (-20.0, 35.0)]
    pairs = [objectives(demo, 64, v, contour=jaw_candidates(demo)) for v in values]
    joint = dict(id=values[0]["id"], albedo=values[0]["albedo"])
    for k, v in enumerate(values):
        joint.update({f"{name}.{k}": v[name] for name in ("exp", "sh", "rotation", "translation", "focal")})
    stage = Stage("photo-1", ("id",), PHOTO, sigma=1e-5, gamma=1e-3)
    host = face_views.FaceViewsObjective([h for h, _ in pairs])
    device = face_views.FaceViewsObjective([d for _, d in pairs])
    assert_same(host(joint, stage), device(joint, stage))


@pytest.mark.parametrize("sigma", [1e-5, 3e-4])     # the working size; the half-size copies (coarse mesh)
def test_device_photos_rendered_together_equal_each_device_photo_alone(demo, sigma):
    """face_views.photo_terms on device objectives (the photos of one size drawn as one batch,
    the third, smaller one alone) equals each device objective's own photometric term to the
    bit, and the joint device objective the joint numpy one within 1e-10."""
    from softras_cl.fitting.recipes import face_views

    rng = np.random.default_rng(16)
    values = [random_values(demo, rng, yaw_deg=yaw) for yaw in (-20.0, 35.0, 10.0)]
    joint = dict(id=values[0]["id"], albedo=values[0]["albedo"])
    for k, v in enumerate(values):
        joint.update({f"{name}.{k}": v[name] for name in ("exp", "sh", "rotation", "translation", "focal")})
    made = [[objectives(demo, size, v) for size, v in zip((64, 64, 48), values)] for _ in range(2)]
    together, alone = ([d for _, d in pairs] for pairs in made)
    host = face_views.FaceViewsObjective([h for h, _ in made[0]])
    views = [host.view_values(joint, k) for k in range(len(values))]
    stage = Stage("photo-1", ("id",), PHOTO, sigma=sigma, gamma=1e-3)
    got = face_views.photo_terms(together, views, [o.geometry(v).world for o, v in zip(together, views)], stage)
    want = [o.photo(v, o.geometry(v).world, stage) for o, v in zip(alone, views)]
    for (value, grads), (want_value, want_grads) in zip(got, want, strict=True):
        assert value == want_value and value > 0
        for name, g in want_grads.items():
            g, g_got = (a.get() if hasattr(a, "get") else a for a in (g, grads[name]))
            assert np.array_equal(g_got, g), name
    assert_same(host(joint, stage), face_views.FaceViewsObjective(together)(joint, stage))


def test_a_fit_runs_on_the_objective_its_config_names(demo):
    """FaceFitConfig.objective: "device" fits with DeviceFaceObjective (a short schedule, to
    its end, finite), "host" with the numpy one; "auto" takes the numpy one on a CPU device."""
    from softras_cl.bench.face import synthetic_face

    sample = synthetic_face(demo, np.random.default_rng(15), 96)
    short = dict(size=96, landmark_iters=5, photo_stages=((1e-4, 3e-3, 4), (1e-5, 1e-3, 4)))
    for where, expected in (("device", face.DeviceFaceObjective), ("host", face.FaceObjective)):
        fit = face.fit_face(sample["photo"], sample["landmarks"], demo, face.FaceFitConfig(objective=where, **short),
                            progress=False)
        assert type(fit.objective) is expected
        assert all(np.isfinite(v).all() for v in fit.values.values()) and fit.metrics()["psnr_face_db"] > 10
    scene = face.FaceScene(demo, (8, 8))
    cpu = scene.renderer.device.type & 2      # cl.device_type.CPU
    assert face.objective_class("auto", scene) is (face.FaceObjective if cpu else face.DeviceFaceObjective)
    with pytest.raises(face.InputError, match="objective must be one of"):
        face.FaceFitConfig(objective="gpu")


def test_device_objective_answers_a_face_behind_the_camera(demo):
    """A solver's point that puts the face behind the camera: the device objective answers it as
    the numpy one does (fitting.solver.too_close_result), before any device work."""
    from softras_cl.fitting.solver import TOO_CLOSE_LOSS

    values = random_values(demo, np.random.default_rng(31))
    host, device = objectives(demo, 48, values)
    behind = dict(values, translation=np.array([0.0, 0.0, 0.05]))
    for weights in (PHOTO, LANDMARKS):
        stage = Stage("photo-1", ("id",), weights, sigma=1e-5, gamma=1e-3)
        assert device(behind, stage) == host(behind, stage) == (TOO_CLOSE_LOSS, {}, {"too_close": TOO_CLOSE_LOSS})
