"""The device-resident Renderer (pyopencl arrays in and out) against the numpy path: images and
every gradient group for vertex, face, pixel and unlit shading, Lambert and SH lights, batched
views, several cameras, float64 and float32; the stages whose arithmetic is the numpy path's
(normals and their vjp, sums onto vertices) bit for bit; bad input raising the numpy path's
errors.

Tolerances, relative to each array's largest magnitude:
- float64: 1e-12. The numpy path multiplies small matrices with BLAS (`verts @ R.T` in the
  projection, `g_cam @ R` in its vjp, `normals @ light`, the SH irradiance `basis @ M.T`) and sums
  parameter gradients with np.sum / einsum (pairwise); the device adds the same terms left to
  right. Those differ by an ulp or so, which the rasteriser's exp/log carry to ~1e-14 (measured:
  at most 7e-14 on these scenes).
- float32: 1e-5. The scene stages run in float64 on both paths and are rounded to float32 at the
  rasteriser's input; an ulp of float64 difference flips a float32 rounding only when a value lies
  within it of a rounding boundary (no flip on these scenes: images identical, gradients within
  1e-15), and one flip moves an input by 6e-8 relative.
"""
import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pytest

from softras_cl import RasterSettings
from softras_cl.scene import shading as sh
from softras_cl.scene.camera import Camera
from softras_cl.scene.device_render import face_normals_device, normals_vjp_device, project
from softras_cl.scene.renderer import Renderer
from support.sphere_scene import LIGHTS, sphere_scene, two_cameras

H, W = 18, 22
GROUPS = ("vertices", "albedo", "camera", "light")
TOLERANCE = {"float64": 1e-12, "float32": 1e-5}


def settings(dtype="float64", **kw):
    return RasterSettings(**{**dict(image_size=(H, W), sigma=1e-3, gamma=1e-2, dist_eps=0.0, near=0.5, far=10.0,
                                    outputs=("rgb", "alpha", "depth"), dtype=dtype), **kw})


def on_device(queue, arrays: dict) -> dict:
    return {n: a if a is None else cla.to_device(queue, np.ascontiguousarray(a)) for n, a in arrays.items()}


def download(value):
    """Device arrays -> numpy, through dicts and lists."""
    if isinstance(value, cla.Array):
        return value.get()
    if isinstance(value, dict):
        return {k: download(v) for k, v in value.items()}
    if isinstance(value, list):
        return [download(v) for v in value]
    return value


def render(s, shading, device, vertices, faces, cams, albedo, light, grads=GROUPS, seed=1, **run):
    """(images, gradients) of one forward (with the call's ``run`` values: sigma, gamma, near,
    far) and backward, downloaded; the device path's results checked to be pyopencl arrays
    (images, vertices, albedo) and numpy (camera, light)."""
    renderer = Renderer(s, shading=shading)
    args = dict(vertices=vertices, faces=faces, albedo=albedo)
    if device:
        args = on_device(renderer.queue, args)
    out = renderer.forward(args["vertices"], args["faces"], cams, albedo=args["albedo"], light=light, grads=grads,
                           **run)
    batch = out.rgb.shape[0]
    rng = np.random.default_rng(seed)
    cot = dict(grad_rgb=rng.normal(size=(batch, H, W, 3)), grad_alpha=rng.normal(size=(batch, H, W)),
               grad_depth=0.1 * rng.normal(size=(batch, H, W)))
    if device:
        cot = on_device(renderer.queue, cot)
    g = renderer.backward(out, **cot)
    images = {n: getattr(out, n) for n in ("rgb", "alpha", "depth")}
    if device:
        assert all(isinstance(a, cla.Array) for a in images.values())
        assert all(isinstance(g[n], cla.Array) for n in ("vertices", "albedo") if n in g)
        assert not any(isinstance(v, cla.Array) for n in ("camera", "light") if n in g
                       for v in (g[n].values() if isinstance(g[n], dict) else [x for d in g[n] for x in d.values()]))
    return download(images), download(g)


def assert_close(expected, actual, rtol, what=""):
    """Nested dicts/lists of arrays equal in shape and dtype and within rtol of the largest
    magnitude."""
    if isinstance(expected, dict):
        assert expected.keys() == actual.keys(), what
        for k in expected:
            assert_close(expected[k], actual[k], rtol, f"{what}/{k}")
        return
    if isinstance(expected, (list, tuple)):
        assert len(expected) == len(actual), what
        for i, (e, a) in enumerate(zip(expected, actual)):
            assert_close(e, a, rtol, f"{what}/{i}")
        return
    expected, actual = np.asarray(expected), np.asarray(actual)
    assert expected.shape == actual.shape and expected.dtype == actual.dtype, (what, expected.shape, actual.shape)
    scale = max(np.abs(expected).max(), 1e-300)
    assert np.isfinite(actual).all(), what
    assert np.abs(expected - actual).max() <= rtol * scale, (what, np.abs(expected - actual).max() / scale)


def assert_parity(s, shading, vertices, faces, cams, albedo, light, grads=GROUPS, **run):
    host = render(s, shading, False, vertices, faces, cams, albedo, light, grads, **run)
    dev = render(s, shading, True, vertices, faces, cams, albedo, light, grads, **run)
    assert_close(host, dev, TOLERANCE[s.dtype])
    return host, dev


CASES = [(shading, light) for shading in ("vertex", "face", "pixel") for light in ("lambert", "sh")]


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("shading,light", CASES, ids=[f"{a}-{b}" for a, b in CASES])
def test_device_renderer_matches_numpy(shading, light, dtype):
    v, f, albedo = sphere_scene()
    assert_parity(settings(dtype), shading, v, f, two_cameras((H, W)), albedo, LIGHTS[light])


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_unlit_device_renderer_matches_numpy(dtype):
    v, f, albedo = sphere_scene()
    assert_parity(settings(dtype), "none", v, f, two_cameras((H, W)), albedo, None, ("vertices", "albedo", "camera"))


def test_batched_meshes_one_camera_and_focal():
    """(B, V, 3) meshes and (B, V, 3) albedo under one camera (its gradient summed over the
    views), and the focal group alone."""
    v, f, albedo = sphere_scene()
    rng = np.random.default_rng(7)
    verts = np.stack([v, v + rng.normal(scale=0.02, size=v.shape), 0.9 * v])
    albedos = np.stack([albedo, albedo[::-1], np.full_like(albedo, 0.5)])
    cam = two_cameras((H, W))[0]
    for grads in (GROUPS, ("focal",), ("vertices", "focal")):
        assert_parity(settings(), "vertex", verts, f, cam, albedos, LIGHTS["sh"], grads)


def test_several_cameras_orthographic_and_opencv():
    v, f, albedo = sphere_scene(3)
    cams = [Camera.orthographic((0.2, 0.3, 3.0), (0, 0, 0), scale=0.9, image_size=(H, W)),
            Camera.orthographic((-2.0, 0.5, 1.0), (0, 0, 0), scale=1.1, image_size=(H, W))]
    s = settings(perspective_correct=False)
    assert_parity(s, "face", v, f, cams, albedo, LIGHTS["lambert"])
    R = Camera.look_at((0.4, 0.5, 3.0), (0, 0, 0), image_size=(H, W)).rotation_matrix()
    cv = Camera.from_opencv([[30.0, 0, 10.0], [0, 28.0, 8.5], [0, 0, 1]], R, -R @ np.array([0.4, 0.5, 3.0]), (H, W))
    assert_parity(settings(), "vertex", v, f, [cv, two_cameras((H, W))[1], cv], albedo, LIGHTS["sh"],
                  ("vertices", "camera", "light", "focal"))


def test_float32_device_inputs_match_float32_numpy_inputs():
    v, f, albedo = sphere_scene()
    v32, a32 = v.astype(np.float32), albedo.astype(np.float32)
    assert_parity(settings(), "vertex", v32, f.astype(np.int32), two_cameras((H, W)), a32, LIGHTS["lambert"])


def test_degenerate_faces_and_a_vertex_in_no_face():
    """A zero-area face (zero normal, no NaN) and a vertex no face uses (zero normal, zero
    gradient)."""
    v, f, albedo = sphere_scene()
    v = np.concatenate([v, [[5.0, 5.0, 0.0]]])              # vertex 42: in no face
    albedo = np.concatenate([albedo, [[0.3, 0.3, 0.3]]])
    f = np.concatenate([f, [[0, 0, 1], [2, 3, 3]]])        # zero-area faces
    for shading in ("vertex", "face", "pixel"):
        host, dev = assert_parity(settings(), shading, v, f, two_cameras((H, W)), albedo, LIGHTS["sh"])
        assert np.array_equal(dev[1]["vertices"][42], np.zeros(3)) and np.array_equal(dev[1]["albedo"][42], np.zeros(3))


def test_reruns_are_bit_identical():
    v, f, albedo = sphere_scene()
    first, second = (render(settings(), "vertex", True, v, f, two_cameras((H, W)), albedo, LIGHTS["sh"])
                     for _ in range(2))
    assert_close(first, second, 0.0)


# ---- stages whose arithmetic is the numpy path's: the same bits ------------------------------
def _state(renderer, v, f, cams):
    tools = renderer.device_tools
    state = project(tools, cams, cla.to_device(renderer.queue, v))
    state.incidence = tools.incidence.get(cla.to_device(renderer.queue, f), len(v))
    return tools, state


@pytest.mark.parametrize("per_vertex", [True, False])
def test_normals_and_their_vjp_are_the_numpy_paths_bits(per_vertex):
    v, f, _ = sphere_scene()
    f = np.concatenate([f, [[0, 0, 1]]])
    v = np.concatenate([v, [[1.0, 1.0, 1.0]]])
    cams = two_cameras((H, W))
    renderer = Renderer(settings())
    tools, state = _state(renderer, v, f, cams)
    normals = state.normals = face_normals_device(tools, state, per_vertex)
    batch_v = np.broadcast_to(v, (2,) + v.shape)
    expected, ctx = (sh.vertex_normals if per_vertex else sh.face_normals)(batch_v, f)
    assert normals.unit.get().tobytes() == np.ascontiguousarray(expected).reshape(-1, 3).tobytes()
    grad = np.random.default_rng(2).normal(size=expected.shape)
    g_dev = normals_vjp_device(tools, state, cla.to_device(renderer.queue, grad.reshape(-1, 3)))
    g_np = (sh.vertex_normals_vjp if per_vertex else sh.face_normals_vjp)(ctx, grad)["vertices"]
    assert g_dev.get().tobytes() == np.ascontiguousarray(g_np).tobytes()


def test_the_incidence_follows_faces_changed_in_place():
    v, f, albedo = sphere_scene()
    renderer = Renderer(settings(), shading="vertex")
    faces = cla.to_device(renderer.queue, f)
    dv, da = cla.to_device(renderer.queue, v), cla.to_device(renderer.queue, albedo)
    cams = two_cameras((H, W))
    renderer.forward(dv, faces, cams, albedo=da)
    flipped = np.ascontiguousarray(f[:, ::-1])
    faces.set(flipped)
    out = renderer.forward(dv, faces, cams, albedo=da)
    expected = Renderer(settings(), shading="vertex").forward(v, flipped, cams, albedo=albedo)
    np.testing.assert_allclose(out.rgb.get(), expected.rgb, rtol=0, atol=1e-12)


def test_unchecked_values_skip_the_value_checks_but_not_the_camera_check():
    """check_values=False (a fit's objective passing its own arrays): an infinite albedo is not
    looked for (it reaches the image), nor a NaN cotangent in backward; vertices behind the
    camera or not finite are refused all the same, the gradients are those of a checked call,
    and a face array object seen before is taken as unchanged (its incidence lists reused
    without comparing contents)."""
    v, f, albedo = sphere_scene()
    cams = two_cameras((H, W))
    renderer = Renderer(settings(), shading="vertex")
    dev = on_device(renderer.queue, dict(v=v, f=f, a=np.where(albedo > 0.85, np.inf, albedo), albedo=albedo))
    with pytest.raises(ValueError, match="albedo"):
        renderer.forward(dev["v"], dev["f"], cams, albedo=dev["a"])
    assert np.isinf(renderer.forward(dev["v"], dev["f"], cams, albedo=dev["a"], check_values=False).rgb.get()).any()
    for case in ("behind the camera", "NaN vertex"):
        bad, _, _ = BAD[case](v, f, albedo)
        with pytest.raises(ValueError, match="behind the camera|finite"):
            renderer.forward(cla.to_device(renderer.queue, bad), dev["f"], cams, albedo=dev["albedo"],
                             check_values=False)
    checked = renderer.forward(v, f, cams, albedo=albedo, grads=GROUPS)
    out = renderer.forward(dev["v"], dev["f"], cams, albedo=dev["albedo"], grads=GROUPS, check_values=False)
    np.testing.assert_allclose(out.rgb.get(), checked.rgb, rtol=0, atol=1e-12)
    g_rgb = np.random.default_rng(2).normal(size=checked.rgb.shape)
    got = download(renderer.backward(out, grad_rgb=cla.to_device(renderer.queue, g_rgb)))
    want = renderer.backward(checked, grad_rgb=g_rgb)
    for name in ("vertices", "albedo"):
        np.testing.assert_allclose(got[name], want[name], rtol=0, atol=1e-12 * np.abs(want[name]).max())
    bad_cotangent = cla.to_device(renderer.queue, np.where(g_rgb > 2.0, np.nan, g_rgb))
    unchecked = renderer.forward(dev["v"], dev["f"], cams, albedo=dev["albedo"], grads=("vertices",),
                                 check_values=False)
    assert np.isnan(renderer.backward(unchecked, grad_rgb=bad_cotangent)["vertices"].get()).any()
    checked_device = renderer.forward(dev["v"], dev["f"], cams, albedo=dev["albedo"], grads=("vertices",))
    with pytest.raises(ValueError, match="grad_rgb"):
        renderer.backward(checked_device, grad_rgb=bad_cotangent)
    flipped = cla.to_device(renderer.queue, np.ascontiguousarray(f[:, ::-1]))     # new contents: a new list
    renderer.forward(dev["v"], flipped, cams, albedo=dev["albedo"], check_values=False)
    flipped.set(f)                                       # changed in place: a checked call sees it
    assert renderer.device_tools.incidence.get(flipped, len(v), unchanged=True).faces.get().tolist() == f[:, ::-1].tolist()
    assert renderer.device_tools.incidence.get(flipped, len(v)).faces.get().tolist() == f.tolist()


# ---- bad input: the numpy path's errors ------------------------------------------------------
def _error(renderer, v, f, cams, albedo, light=None):
    with pytest.raises((ValueError, TypeError)) as info:
        renderer.forward(v, f, cams, albedo=albedo, light=light)
    return type(info.value), str(info.value)


BAD = {
    "behind the camera": lambda v, f, a: (v + np.array([0.4, 0.5, 3.0]), f, a),
    "NaN vertex": lambda v, f, a: (np.where(np.arange(v.size).reshape(v.shape) == 7, np.nan, v), f, a),
    "face index": lambda v, f, a: (v, np.where(f == 5, len(v), f), a),
    "albedo shape": lambda v, f, a: (v, f, a[:-1]),
    "albedo NaN": lambda v, f, a: (v, f, np.where(a > 0.85, np.inf, a)),
    "faces shape": lambda v, f, a: (v, f[:, :2], a),
    "float faces": lambda v, f, a: (v, f.astype(np.float64), a),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_raises_the_numpy_error(case):
    v, f, albedo = BAD[case](*sphere_scene())
    cams = two_cameras((H, W))
    renderer = Renderer(settings(), shading="vertex")
    expected = _error(renderer, v, f, cams, albedo)
    dev = on_device(renderer.queue, dict(v=v, f=f, a=albedo))
    assert _error(renderer, dev["v"], dev["f"], cams, dev["a"]) == expected
    if case == "behind the camera":
        assert "behind the camera" in expected[1]


def test_other_context_and_phong_light_are_refused():
    v, f, albedo = sphere_scene()
    renderer = Renderer(settings(), shading="vertex")
    other = cl.CommandQueue(cl.Context([renderer.device]))
    with pytest.raises(ValueError, match="vertices is a pyopencl array of another OpenCL context"):
        renderer.forward(cla.to_device(other, v), f, two_cameras((H, W)), albedo=albedo)
    with pytest.raises(ValueError, match="PhongLight needs numpy inputs"):
        renderer.forward(cla.to_device(renderer.queue, v), f, two_cameras((H, W)), albedo=albedo,
                         light=LIGHTS["phong"])


@pytest.mark.parametrize("shading", ["vertex", "face"])
@pytest.mark.parametrize("light", ["lambert", "sh"])
def test_one_light_per_view_matches_numpy(shading, light):
    """A list of lights, one per view: the device path's images and gradients (the light's
    stacked over the views) against the numpy path's."""
    v, f, albedo = sphere_scene()
    rng = np.random.default_rng(9)
    if light == "sh":
        lights = [sh.SHLight(LIGHTS["sh"].coefficients + rng.normal(scale=0.1, size=(3, 9))) for _ in range(2)]
    else:
        lights = [sh.LambertLight(ambient=rng.uniform(0.1, 0.4, 3), directional=rng.uniform(0.4, 0.8, 3),
                                  direction=rng.normal(size=3)) for _ in range(2)]
    host, _ = assert_parity(settings(), shading, v, f, two_cameras((H, W)), albedo, lights)
    assert all(g.shape[0] == 2 for g in host[1]["light"].values())


def test_one_depth_range_per_view_matches_numpy():
    """near and far per view: the device path's images and gradients against the numpy path's."""
    v, f, albedo = sphere_scene()
    host, _ = assert_parity(settings(), "vertex", v, f, two_cameras((H, W)), albedo, LIGHTS["sh"],
                            near=[2.4, 1.8], far=[3.3, 2.7])
    shared, _ = render(settings(), "vertex", False, v, f, two_cameras((H, W)), albedo, LIGHTS["sh"], near=2.4, far=3.3)
    assert not np.array_equal(shared["depth"][1], host[0]["depth"][1])


@pytest.mark.parametrize("run, says", [
    (dict(near=[2.4, 1.8, 1.0], far=3.3), r"near holds 3 values \(one per view\), but the batch has 2 views"),
    (dict(near=[2.4, 1.8], far=[3.3, 1.5]), r"far\[1\] must be finite and > near\[1\]"),
    (dict(sigma=-1.0), "sigma must be a finite number > 0"),
])
def test_bad_call_values_are_refused_before_any_device_kernel(monkeypatch, run, says):
    """A call's sigma, gamma, near and far (near and far per view) are checked before the
    device path projects anything."""
    from softras_cl.scene import device_render

    v, f, albedo = sphere_scene()
    renderer = Renderer(settings(), shading="vertex")
    monkeypatch.setattr(device_render, "project", lambda *a: pytest.fail("a kernel ran before the check"))
    with pytest.raises(ValueError, match=says):
        renderer.forward(cla.to_device(renderer.queue, v), f, two_cameras((H, W)), albedo=albedo, **run)
