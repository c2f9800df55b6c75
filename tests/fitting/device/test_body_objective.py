"""The device body objective (fitting.device.body_objective) against the numpy BodyObjective and
BodyPhotoObjective it replaces, in float64: loss, every gradient block and every term within
1e-10 relative at random parameters, for colour and silhouette targets (all faces and the
coarse mesh, a care mask, a model with pose blendshapes) and the photo objective's terms;
reruns bit-identical; a float32 raster within 1e-5; its gradient against central differences;
its parts (skinning, image terms) against their numpy counterparts, at the edges (an empty
union).

1e-10 is the bound the device objective is held to; measured: at most 9.8e-14 relative to each
array's largest magnitude on these scenes (sums run in other orders than numpy's).
"""
import numpy as np
import pyopencl.array as cla
import pytest

from softras_cl.fitting import losses
from softras_cl.fitting.device.body_objective import DeviceBodyEvaluation, DeviceBodyImages
from softras_cl.fitting.device.body_model import DeviceSkin
from softras_cl.fitting.models.body_model import BodyModel
from softras_cl.fitting.models.mesh_lod import coarse_faces
from softras_cl.fitting.recipes import body, body_photo
from softras_cl.fitting.solver import TOO_CLOSE_LOSS, Stage
from support.gradients import central_differences

RELATIVE = 1e-10
ALL_TERMS = dict(image=100.0, silhouette=10.0, joints=0.25, pose_prior=1.0, shape_prior=1.0,
                 translation_prior=1.0, limits=100.0)
SIZE = 32


@pytest.fixture(scope="module")
def queue():
    from softras_cl.cl.device import get_context, select_device

    return get_context(select_device())[1]


@pytest.fixture(scope="module")
def posed_model(demo_body_model):
    """The demo body with random pose blendshapes (SMPL's posedirs layout; the demo has none)."""
    m = demo_body_model
    posedirs = np.random.default_rng(0).normal(0, 0.01, (m.n_vertices, 3, 9 * (m.n_joints - 1)))
    return BodyModel(m.v_template, m.shapedirs, m.J_regressor, m.parents, m.weights, m.faces, m.joint_names,
                     posedirs=posedirs, part_labels=m.part_labels, part_names=m.part_names)


def random_values(model, rng) -> dict:
    values = body.rest_values(model)
    values["betas"] = rng.normal(0, 0.5, model.n_betas)
    values["body_pose"] = rng.normal(0, 0.15, values["body_pose"].shape)
    values["global_rotation"] = np.array([0.05, 0.2, -0.03]) + rng.normal(0, 0.02, 3)
    values["translation"] = np.array([0.03, -0.02, 0.05]) + rng.normal(0, 0.01, 3)
    return values


def target_of(model, rng, kind: str) -> body.BodyTarget:
    """A hard render of the rest pose as a colour target with its joints ("colour"), or its
    silhouette with a care mask that leaves a band out ("silhouette")."""
    scene = body.BodyScene(model, (SIZE, SIZE), body.BodyFitConfig(size=SIZE))
    state, _ = scene.pose(body.rest_values(model))
    out = scene.render(state.vertices, 1e-6, 1e-4, color_agg="hard", alpha_agg="hard")
    if kind == "colour":
        joints = scene.camera.project_pixels(state.joints)[0] + rng.normal(0, 1.5, (model.n_joints, 2))
        return body.prepare_target(scene.composite(out), SIZE, joints=np.clip(joints, 0, SIZE - 1),
                                   joint_weights=rng.uniform(0.5, 1.5, model.n_joints), n_joints=model.n_joints)
    target = body.prepare_target(out.alpha[0], SIZE)
    care = np.ones((SIZE, SIZE))
    care[:, 20:25] = 0.0
    care[3:9] = 0.5
    return body.BodyTarget(None, target.alpha, None, None, 1.0, (SIZE, SIZE), care)


def pair(model, target, cls_host=body.BodyObjective, cls_device=body.DeviceBodyObjective, **options):
    """(numpy objective, device objective) on scenes of their own."""
    scenes = [body.BodyScene(model, (SIZE, SIZE), body.BodyFitConfig(size=SIZE)) for _ in range(2)]
    return cls_host(scenes[0], target, **options), cls_device(scenes[1], target, **options)


def assert_same(host_result, device_result):
    (loss_h, grads_h, terms_h), (loss_d, grads_d, terms_d) = host_result, device_result
    assert loss_d == pytest.approx(loss_h, rel=RELATIVE)
    assert set(terms_d) == set(terms_h) and set(grads_d) == set(grads_h)
    for name in terms_h:
        assert terms_d[name] == pytest.approx(terms_h[name], rel=RELATIVE, abs=1e-300), name
    for name, g in grads_h.items():
        np.testing.assert_allclose(grads_d[name], g, rtol=0, atol=RELATIVE * np.abs(g).max(), err_msg=name)


@pytest.mark.parametrize("kind, coarse, posedirs", [
    ("colour", None, False), ("colour", 3.0, False), ("silhouette", 3.0, False), ("colour", 3.0, True)],
    ids=["colour, all faces", "colour, coarse mesh", "silhouette with care mask", "pose blendshapes"])
def test_device_objective_equals_the_numpy_one(demo_body_model, posed_model, kind, coarse, posedirs):
    model = posed_model if posedirs else demo_body_model
    rng = np.random.default_rng(1)
    target = target_of(model, rng, kind)
    faces = None if coarse is None else coarse_faces(model.v_template, model.faces, coarse)
    host, device = pair(model, target, robust_px=3.0 if kind == "colour" else None, faces=faces)
    weights = ALL_TERMS if kind == "colour" else dict(silhouette=10.0, pose_prior=1.0, limits=100.0)
    stage = Stage("image-1", ("betas",), weights, sigma=1e-4, gamma=1e-2)
    values = random_values(model, rng)
    for _ in range(3):                        # buffers made at the first, reused after
        assert_same(host(values, stage), device(values, stage))
        values = dict(values, betas=values["betas"] + rng.normal(0, 0.1, model.n_betas),
                      body_pose=values["body_pose"] + rng.normal(0, 0.05, values["body_pose"].shape))
    assert device.render_changes == ({} if kind == "colour" else {"outputs": ("alpha",)})


def photo_pair(model, rng):
    from softras_cl.fitting.keypoints.pose33 import keypoint_layout

    layout = keypoint_layout(model)
    target = target_of(model, rng, "silhouette")
    n = len(layout.names)
    args = (layout, rng.uniform(5, 27, (n, 2)), rng.uniform(0.2, 1.0, n), 4.0)
    options = dict(faces=coarse_faces(model.v_template, model.faces, 3.0), depth=rng.normal(0.0, 0.3, n))
    scenes = [body.BodyScene(model, (SIZE, SIZE), body.BodyFitConfig(size=SIZE)) for _ in range(2)]
    return (body_photo.BodyPhotoObjective(scenes[0], target, *args, **options),
            body_photo.DeviceBodyPhotoObjective(scenes[1], target, *args, **options))


def test_device_photo_objective_equals_the_numpy_one(demo_body_model):
    """The photo objective's silhouette stage: its keypoint, torso and depth terms read surface
    vertices posed on the host beside the device's drawn ones."""
    rng = np.random.default_rng(2)
    host, device = photo_pair(demo_body_model, rng)
    weights = dict(body_settings_weights(), torso=0.5)
    stage = Stage("silhouette-1", ("betas",), weights, sigma=1e-4, gamma=1e-2)
    values = random_values(demo_body_model, rng)
    assert_same(host(values, stage), device(values, stage))
    assert device.posed(False).subset.ids.size > 0            # the keypoints' surface vertices


def body_settings_weights() -> dict:
    from softras_cl.fitting.recipes.body_settings import PHOTO_WEIGHTS

    return dict(PHOTO_WEIGHTS)


def test_stages_without_a_render_are_the_numpy_objectives_own(demo_body_model):
    """The joint stage draws nothing: the device objective gives the numpy one's bits."""
    rng = np.random.default_rng(3)
    host, device = pair(demo_body_model, target_of(demo_body_model, rng, "colour"), robust_px=3.0)
    stage = Stage("joints", ("betas",), dict(joints=0.25, pose_prior=1.0, limits=100.0))
    values = random_values(demo_body_model, rng)
    (loss_h, grads_h, terms_h), (loss_d, grads_d, terms_d) = host(values, stage), device(values, stage)
    assert loss_d == loss_h and terms_d == terms_h
    assert all(np.array_equal(grads_d[k], g) for k, g in grads_h.items())
    assert device._drawn is None


def test_device_objective_reruns_bit_identically(demo_body_model):
    rng = np.random.default_rng(4)
    _, device = pair(demo_body_model, target_of(demo_body_model, rng, "colour"),
                     faces=coarse_faces(demo_body_model.v_template, demo_body_model.faces, 3.0))
    stage = Stage("image-1", ("betas",), ALL_TERMS, sigma=1e-4, gamma=1e-2)
    values = random_values(demo_body_model, rng)
    first, second = device(values, stage), device(values, stage)
    assert first[0] == second[0] and first[2] == second[2]
    assert all(np.array_equal(g, second[1][k]) for k, g in first[1].items())


def test_a_body_too_near_the_camera_is_refused_before_any_device_work(demo_body_model):
    rng = np.random.default_rng(5)
    _, device = pair(demo_body_model, target_of(demo_body_model, rng, "colour"))
    values = dict(body.rest_values(demo_body_model), translation=np.array([0.0, 0.0, 3.6]))
    stage = Stage("image-1", ("betas",), ALL_TERMS, sigma=1e-4, gamma=1e-2)
    assert device(values, stage) == (TOO_CLOSE_LOSS, {}, {"too_close": TOO_CLOSE_LOSS})
    assert device._drawn is None


def test_device_objective_gradient_matches_central_differences(posed_model):
    rng = np.random.default_rng(6)
    target = target_of(posed_model, rng, "colour")
    scene = body.BodyScene(posed_model, (SIZE, SIZE), body.BodyFitConfig(size=SIZE))
    scene.settings = scene.settings.replace(dist_eps=1e-9)    # a tiny cut-off: smooth for differences
    objective = body.DeviceBodyObjective(scene, target, robust_px=3.0,
                                         faces=coarse_faces(posed_model.v_template, posed_model.faces, 3.0))
    stage = Stage("image-1", ("betas",), ALL_TERMS, sigma=1e-4, gamma=1e-2)
    values = random_values(posed_model, rng)
    _, grads, _ = objective(values, stage)
    for name in ("betas", "global_rotation", "translation"):
        fd = central_differences(objective, values, stage, name, step=1e-6)
        np.testing.assert_allclose(grads[name], fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max(), err_msg=name)
    rows = values["body_pose"][[0, 3, 17]]
    picks = {**values, "rows": rows}
    fd = central_differences(lambda v, s: objective(dict(v, body_pose=_with_rows(values["body_pose"], v["rows"])), s),
                             picks, stage, "rows", step=1e-6)
    np.testing.assert_allclose(grads["body_pose"][[0, 3, 17]], fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())


def _with_rows(pose: np.ndarray, rows: np.ndarray) -> np.ndarray:
    out = pose.copy()
    out[[0, 3, 17]] = rows
    return out


def test_device_skin_equals_the_numpy_posing(posed_model, queue):
    """DeviceSkin's vertices against BodyModel.forward's, and its cotangent sums through
    forward_vjp(skin=) against forward_vjp of the same vertices posed on the host."""
    rng = np.random.default_rng(7)
    values = random_values(posed_model, rng)
    ids = np.sort(rng.choice(posed_model.n_vertices, 500, replace=False))
    state, ctx = posed_model.forward(*(values[k] for k in ("betas", "body_pose", "global_rotation", "translation")),
                                     subset=posed_model.subset(ids))
    skin = DeviceSkin(posed_model, ids, queue)
    vertices, v_posed, transforms = skin.forward(values, ctx)
    np.testing.assert_allclose(vertices.get(), state.vertices, rtol=0, atol=1e-14 * np.abs(state.vertices).max())
    g = rng.normal(size=state.vertices.shape)
    expected = posed_model.forward_vjp(ctx, g)
    none = posed_model.subset(np.zeros(0, np.int64))
    _, ctx_none = posed_model.forward(*(values[k] for k in ("betas", "body_pose", "global_rotation", "translation")),
                                      subset=none)
    sums = [a.get() for a in skin.vjp(cla.to_device(queue, g), v_posed, transforms)]
    got = posed_model.forward_vjp(ctx_none, skin=skin.cotangents(*sums))
    for name, value in expected.items():
        np.testing.assert_allclose(got[name], value, rtol=0, atol=1e-12 * np.abs(value).max(), err_msg=name)


class _Images:
    """A device render's images, as DeviceBodyImages reads them."""

    def __init__(self, queue, alpha, rgb):
        self.alpha = cla.to_device(queue, alpha[None])
        self.rgb = cla.to_device(queue, rgb[None])


@pytest.mark.parametrize("case", ["random", "empty union", "float32 render"])
def test_device_image_terms_equal_the_numpy_losses(queue, case):
    """The silhouette (soft IoU with care weights, times the pixel count) and image terms (the
    composite's squared errors) and their weighted cotangents; an empty union (no render, no
    target) stays finite."""
    from softras_cl.fitting.device.body_kernels import BODY_KERNELS
    from softras_cl.scene.device_kernels import SceneKernels

    rng = np.random.default_rng(8)
    kernels = SceneKernels(queue.context, queue, extra=BODY_KERNELS)
    alpha, rgb = rng.random((12, 10)), rng.random((12, 10, 3))
    target_alpha, target_rgb, care = rng.random((12, 10)), rng.random((12, 10, 3)), rng.random((12, 10))
    if case == "empty union":
        alpha, target_alpha = np.zeros((12, 10)), np.zeros((12, 10))
    background = np.array([0.1, 0.2, 0.3])
    target = body.BodyTarget(target_rgb, target_alpha, None, None, 1.0, (12, 10), care)
    images = DeviceBodyImages(kernels, target, background)
    dtype = np.float32 if case == "float32 render" else np.float64
    alpha, rgb = alpha.astype(dtype).astype(np.float64), rgb.astype(dtype).astype(np.float64)
    sums, g_alpha, g_rgb = images(_Images(queue, alpha.astype(dtype), rgb.astype(dtype)), 3.0, 7.0)
    terms = images.terms(sums.get())
    iou, g_iou = losses.silhouette_iou(alpha, target_alpha, mask=care)
    comp = rgb * alpha[..., None] + (1.0 - alpha[..., None]) * background
    squares = float(((comp - target_rgb) ** 2).sum())
    assert terms["silhouette"][0] == pytest.approx(iou * alpha.size, rel=1e-13, abs=1e-300)
    assert terms["image"][0] == pytest.approx(squares, rel=1e-13)
    g_comp = 2.0 * (comp - target_rgb)
    want_alpha = 3.0 * g_iou["pred"] * alpha.size + 7.0 * (g_comp * (rgb - background)).sum(-1)
    assert np.isfinite(g_alpha.get()).all()
    np.testing.assert_allclose(g_alpha.get()[0], want_alpha, rtol=1e-12, atol=1e-12 * np.abs(want_alpha).max())
    np.testing.assert_allclose(g_rgb.get()[0], 7.0 * g_comp * alpha[..., None], rtol=1e-13, atol=1e-15)


def test_fits_run_on_the_objective_their_config_names(demo_body_model, monkeypatch):
    """BodyFitConfig.objective: "device" draws through DeviceBodyEvaluation (fit_body and the
    photo fit's objective class), "host" never does; "auto" is the host on a CPU device."""
    calls = []
    draw = DeviceBodyEvaluation.draw
    monkeypatch.setattr(DeviceBodyEvaluation, "draw", lambda self, *a: calls.append(1) or draw(self, *a))
    rng = np.random.default_rng(9)
    target = target_of(demo_body_model, rng, "colour")
    image = target.rgb
    short = dict(size=SIZE, joint_iters=2, image_stages=((1e-4, 1e-2, 3),))
    for where, drawn in (("device", True), ("host", False)):
        calls.clear()
        fit = body.fit_body(image, demo_body_model, body.BodyFitConfig(objective=where, **short), progress=False)
        assert bool(calls) == drawn and np.isfinite(fit.result.history[-1]["loss"])
    scene = body.BodyScene(demo_body_model, (SIZE, SIZE), body.BodyFitConfig(size=SIZE))
    assert body_photo.photo_objective_class("device", scene) is body_photo.DeviceBodyPhotoObjective
    assert body_photo.photo_objective_class("host", scene) is body_photo.BodyPhotoObjective
    if scene.renderer.device.type & 2:        # cl.device_type.CPU
        assert body.objective_class("auto", scene) is body.BodyObjective


def test_a_float32_raster_gives_the_numpy_objective_within_its_rounding(demo_body_model):
    """BodyFitConfig(dtype="float32"): both objectives render in float32 (the scene's stages in
    float64, rounded at the rasteriser's input), so they agree to the renderer's float32
    tolerance (1e-5 relative; measured at most 3.4e-7 here), not to float64's."""
    rng = np.random.default_rng(10)
    target = target_of(demo_body_model, rng, "colour")
    config = body.BodyFitConfig(size=SIZE, dtype="float32")
    host, device = (cls(body.BodyScene(demo_body_model, (SIZE, SIZE), config), target, 3.0)
                    for cls in (body.BodyObjective, body.DeviceBodyObjective))
    stage = Stage("image-1", ("betas",), ALL_TERMS, sigma=1e-4, gamma=1e-2)
    values = random_values(demo_body_model, rng)
    (loss_h, grads_h, _), (loss_d, grads_d, _) = host(values, stage), device(values, stage)
    assert loss_d == pytest.approx(loss_h, rel=1e-5)
    for name, g in grads_h.items():
        np.testing.assert_allclose(grads_d[name], g, rtol=0, atol=1e-5 * np.abs(g).max(), err_msg=name)
