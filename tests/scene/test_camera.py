"""Cameras (docs/scene.md): projection conventions, exact vjps vs finite differences,
and bad input raising ValueError that names the argument."""
import math
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from softras_cl.scene.camera import Camera

RNG = np.random.default_rng(7)
SIZES = [(64, 64), (48, 80), (90, 50)]          # (H, W): square, wide, tall
H_FD = 1e-6


def ndc_of_pixel(u, v, image_size):
    """docs/scene.md: pixel (u, v) (0 = centre of the first pixel) -> NDC x, y."""
    h, w = image_size
    s = min(h, w)
    return (2 * (u + 0.5) - w) / s, (h - 2 * (v + 0.5)) / s


def screen(cam, pts):
    return cam.project(np.asarray(pts, float))[0][0]


# ---- look_at -----------------------------------------------------------------------------------
LOOKS = [((0, 0, 5), (0, 0, 0), (0, 1, 0)),
         ((3, 2, -4), (0.5, -0.2, 0.1), (0, 1, 0)),
         ((1, -6, 0.5), (0, 0, 0), (0, 0, 1)),
         ((0, 0, -5), (0, 0, 0), (1, 1, 0))]


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("eye,target,up", LOOKS)
def test_look_at_orientation(eye, target, up, size):
    cam = Camera.look_at(eye, target, up, fov_deg=40, image_size=size)
    eye, target, up = (np.asarray(a, float) for a in (eye, target, up))
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, fwd)
    dist = np.linalg.norm(target - eye)
    s = screen(cam, [target, target + 0.3 * true_up, target + 0.3 * right, target + 0.3 * up])
    np.testing.assert_allclose(s[0], [0, 0, dist], atol=1e-12)
    assert s[1, 1] > 0.05 and abs(s[1, 0]) < 1e-12          # up appears up
    assert s[2, 0] > 0.05 and abs(s[2, 1]) < 1e-12          # camera's right appears right
    assert s[3, 1] > 0.05                                  # the given up vector too
    np.testing.assert_allclose(cam.center(), eye, atol=1e-12)


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("fov", [10.0, 30.0, 90.0, 150.0])
def test_look_at_fov_spans_shorter_side(size, fov):
    eye, target = np.array([2.0, 1.0, 4.0]), np.array([0.0, 0.5, 0.0])
    cam = Camera.look_at(eye, target, (0, 1, 0), fov_deg=fov, image_size=size)
    R = cam.rotation_matrix()
    tan = math.tan(math.radians(fov) / 2)
    # points on the fov's edge, at depth 3 along the camera axis, to the right/left/up/down
    rays = [(tan, 0, 1), (-tan, 0, 1), (0, -tan, 1), (0, tan, 1)]   # camera frame, y down
    pts = np.array([eye + 3.0 * R.T @ np.array(r) for r in rays])
    s = screen(cam, pts)
    h, w = size
    edge_x, edge_y = w / min(h, w), h / min(h, w)      # image edges in NDC; the shorter one is 1
    np.testing.assert_allclose(s[:, 0], [1, -1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(s[:, 1], [0, 0, 1, -1], atol=1e-12)
    shorter_edge = edge_x if w <= h else edge_y
    assert shorter_edge == 1.0                         # so the fov edge is the shorter side's edge
    np.testing.assert_allclose(s[:, 2], 3.0, atol=1e-12)


def test_look_at_intrinsics():
    cam = Camera.look_at((0, 0, 5), (0, 0, 0), fov_deg=60, image_size=(100, 200))
    assert cam.fx == cam.fy == pytest.approx(50 / math.tan(math.radians(30)))
    assert (cam.cx, cam.cy) == (99.5, 49.5)
    assert cam.projection == "perspective" and cam.image_size == (100, 200)


# ---- from_opencv -------------------------------------------------------------------------------
def random_opencv(size):
    h, w = size
    K = np.array([[300.0 + 50 * RNG.random(), 0, w / 2 + 3 * RNG.standard_normal()],
                  [0, 280.0 + 50 * RNG.random(), h / 2 + 3 * RNG.standard_normal()], [0, 0, 1]])
    R = Rotation.from_rotvec(RNG.standard_normal(3)).as_matrix()
    t = np.array([0.1, -0.2, 6.0])
    return K, R, t


@pytest.mark.parametrize("size", SIZES)
def test_from_opencv_matches_hand_projection(size):
    K, R, t = random_opencv(size)
    cam = Camera.from_opencv(K, R, t, size)
    pts = RNG.standard_normal((2, 7, 3))
    s, _ = cam.project(pts)
    X = pts @ R.T + t
    u = K[0, 0] * X[..., 0] / X[..., 2] + K[0, 2]
    v = K[1, 1] * X[..., 1] / X[..., 2] + K[1, 2]
    x, y = ndc_of_pixel(u, v, size)
    np.testing.assert_allclose(s, np.stack([x, y, X[..., 2]], -1), atol=1e-12)
    np.testing.assert_allclose(cam.rotation_matrix(), R, atol=1e-12)
    np.testing.assert_allclose(cam.translation, t)


@pytest.mark.parametrize("size", SIZES)
def test_pixel_centre_convention(size):
    """u = 0 is the centre of pixel column 0: x_ndc = (2 * 0.5 - W) / s; v = H - 1 likewise."""
    h, w = size
    K = np.array([[100.0, 0, 10.0], [0, 100.0, 20.0], [0, 0, 1]])
    cam = Camera.from_opencv(K, np.eye(3), np.zeros(3), size)
    # X/Z chosen so that u = 0 and v = H - 1
    s = screen(cam, [[-10.0 / 100 * 2, (h - 1 - 20.0) / 100 * 2, 2.0]])
    s_min = min(h, w)
    np.testing.assert_allclose(s[0, :2], [(2 * 0.5 - w) / s_min, (h - 2 * (h - 0.5)) / s_min], atol=1e-12)


def test_from_opencv_accepts_column_t():
    K, R, t = random_opencv((32, 32))
    cam = Camera.from_opencv(K, R, t.reshape(3, 1), (32, 32))
    np.testing.assert_allclose(cam.translation, t)


def test_look_at_agrees_with_hand_built_opencv():
    """Eye at (0, 0, -5) looking at +z with +y up: camera x = world -x, y = world -y."""
    size = (60, 80)
    la = Camera.look_at((0, 0, -5), (0, 0, 0), (0, 1, 0), fov_deg=50, image_size=size)
    f = 30 / math.tan(math.radians(25))
    K = np.array([[f, 0, 39.5], [0, f, 29.5], [0, 0, 1]])
    cv = Camera.from_opencv(K, np.diag([-1.0, -1.0, 1.0]), [0, 0, 5.0], size)
    pts = RNG.standard_normal((3, 9, 3))
    np.testing.assert_allclose(la.project(pts)[0], cv.project(pts)[0], atol=1e-12)


def test_look_at_roundtrips_through_from_opencv():
    la = Camera.look_at((1, 2, 3), (0.2, 0, -0.4), (0, 1, 0), fov_deg=35, image_size=(40, 70))
    K = np.array([[la.fx, 0, la.cx], [0, la.fy, la.cy], [0, 0, 1]])
    cv = Camera.from_opencv(K, la.rotation_matrix(), la.translation, la.image_size)
    pts = RNG.standard_normal((2, 5, 3)) * 0.5
    np.testing.assert_allclose(la.project(pts)[0], cv.project(pts)[0], atol=1e-12)


# ---- orthographic ------------------------------------------------------------------------------
@pytest.mark.parametrize("size", SIZES)
def test_orthographic_scale(size):
    cam = Camera.orthographic((0, 0, 10), (0, 0, 0), (0, 1, 0), scale=2.5, image_size=size)
    assert cam.projection == "orthographic"
    h, w = size
    s = screen(cam, [[2.5, 0, 0], [0, 2.5, 0], [-2.5, -2.5, 4], [0, 0, 12]])   # last: behind
    np.testing.assert_allclose(s[:, 2], [10, 10, 6, -2], atol=1e-12)
    np.testing.assert_allclose(s[:, :2], [[1, 0], [0, 1], [-1, -1], [0, 0]], atol=1e-12)
    # a point at the image's right edge of the longer side: W/s in NDC
    s2 = screen(cam, [[2.5 * w / min(h, w), 2.5 * h / min(h, w), 0]])
    np.testing.assert_allclose(s2[0, :2], [w / min(h, w), h / min(h, w)], atol=1e-12)


# ---- finite differences ------------------------------------------------------------------------
def fd_gradient(f, x, h=H_FD):
    """Central differences of scalar f at x (any shape, float64)."""
    g = np.zeros_like(x)
    for i in np.ndindex(x.shape):
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        g[i] = (f(xp) - f(xm)) / (2 * h)
    return g


def assert_grad(analytic, fd, rtol=1e-6):
    scale = max(1.0, float(np.abs(fd).max()))
    np.testing.assert_allclose(analytic, fd, rtol=rtol, atol=rtol * scale)


# ---- project_vjp -------------------------------------------------------------------------------
def cameras():
    yield Camera.look_at((0.5, 1.0, 4.0), (0, 0, 0), (0, 1, 0), fov_deg=45, image_size=(30, 50))
    yield Camera.look_at((0, 0, 5), (0, 0, 0), (0, 1, 0), fov_deg=45, image_size=(50, 30))  # |omega| = pi
    yield Camera(np.zeros(3), np.array([0.1, 0.2, 5.0]), 40.0, 45.0, 15.0, 12.0, (24, 32))
    yield Camera(np.array([1e-9, -2e-9, 0]), np.array([0.1, 0.2, 5.0]), 40.0, 45.0, 15.0, 12.0, (24, 32))
    yield Camera.orthographic((1.0, 2.0, 3.0), (0, 0, 0), (0, 1, 0), scale=1.5, image_size=(40, 30))
    yield Camera(np.array([0.3, -0.4, 0.2]), np.array([0, 0, 5.0]), 9.0, 11.0, 20.0, 14.0, (32, 40),
                 "orthographic")


CAMERA_IDS = ["look_at", "look_at_pi", "zero_rot", "tiny_rot", "ortho_look_at", "ortho_direct"]


def _assert_point_and_pose_grads(g: dict, key: str, cam, loss, points: np.ndarray) -> None:
    """g[key] (the gradient of `points` (..., 3)), g["rotation"] and g["translation"] equal central
    differences of loss(camera, points) (a float; points defaulting to `points`)."""
    assert_grad(g[key], fd_gradient(lambda p: loss(cam, p), points))
    assert_grad(g["rotation"], fd_gradient(lambda w: loss(cam.with_params(rotation=w)), cam.rotation.copy()))
    assert_grad(g["translation"], fd_gradient(lambda t: loss(cam.with_params(translation=t)),
                                              cam.translation.copy()))


@pytest.mark.parametrize("cam", list(cameras()), ids=CAMERA_IDS)
@pytest.mark.parametrize("batched", [True, False], ids=["B2", "unbatched"])
def test_project_vjp_vs_fd(cam, batched):
    verts = RNG.uniform(-1, 1, (2, 6, 3)) if batched else RNG.uniform(-1, 1, (6, 3))
    out, ctx = cam.project(verts)
    G = RNG.standard_normal(out.shape)
    g = cam.project_vjp(ctx, G)
    assert g["vertices"].shape == verts.shape
    assert g["rotation"].shape == g["translation"].shape == (3,) and g["focal"].shape == (2,)

    def loss(c, v=verts):
        return np.sum(G * c.project(v)[0])

    _assert_point_and_pose_grads(g, "vertices", cam, loss, verts)
    assert_grad(g["focal"], fd_gradient(lambda f: loss(cam.with_params(fx=f[0], fy=f[1])), cam.focal))
    vertices_only = cam.project_vjp(ctx, G, camera=False)      # the camera's gradients skipped
    assert list(vertices_only) == ["vertices"] and np.array_equal(vertices_only["vertices"], g["vertices"])
    focal_only = cam.project_vjp(ctx, G, camera="focal")      # rotation and translation skipped
    assert sorted(focal_only) == ["focal", "vertices"]
    assert all(np.array_equal(focal_only[k], g[k]) for k in focal_only)


def test_project_vjp_rejects_an_unknown_camera_choice():
    cam = next(cameras())
    out, ctx = cam.project(RNG.uniform(-1, 1, (4, 3)))
    with pytest.raises(ValueError, match="camera must be True, False or 'focal'"):
        cam.project_vjp(ctx, np.zeros(out.shape), camera="rotation")


def test_project_vjp_accepts_unbatched_cotangent():
    cam = next(cameras())
    verts = RNG.uniform(-1, 1, (4, 3))
    out, ctx = cam.project(verts)
    G = RNG.standard_normal((4, 3))
    np.testing.assert_allclose(cam.project_vjp(ctx, G)["vertices"], cam.project_vjp(ctx, G[None])["vertices"])


# ---- view directions ---------------------------------------------------------------------------
@pytest.mark.parametrize("cam", list(cameras()), ids=CAMERA_IDS)
def test_view_direction_and_vjp(cam):
    pts = RNG.uniform(-1, 1, (2, 5, 3))
    d, ctx = cam.view_direction(pts)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
    if cam.projection == "perspective":
        to_cam = cam.center() - pts
        np.testing.assert_allclose(np.sum(d * to_cam, -1), np.linalg.norm(to_cam, axis=-1))
    else:   # the camera axis, pointing back at the camera
        np.testing.assert_allclose(d, np.broadcast_to(-cam.rotation_matrix()[2], d.shape), atol=1e-12)
    G = RNG.standard_normal(d.shape)
    g = cam.view_direction_vjp(ctx, G)

    def loss(c, p=pts):
        return np.sum(G * c.view_direction(p)[0])

    _assert_point_and_pose_grads(g, "points", cam, loss, pts)


# ---- immutability / with_params ----------------------------------------------------------------
def test_with_params_copies():
    cam = Camera.look_at((0, 0, 5), (0, 0, 0))
    new = cam.with_params(fx=100.0, translation=np.array([0, 0, 6.0]))
    assert new.fx == 100.0 and cam.fx != 100.0 and cam.translation[2] == 5.0
    assert new.fy == cam.fy and new.image_size == cam.image_size
    with pytest.raises(ValueError):
        cam.rotation[0] = 1.0


# ---- bad input ---------------------------------------------------------------------------------
def raises(*names, match=None):
    """pytest.raises(ValueError) whose message names every argument in `names` (whole words)."""
    class _Check:
        def __enter__(self):
            self.ctx = pytest.raises(ValueError, match=match)
            return self.ctx.__enter__()

        def __exit__(self, *exc_info):
            suppressed = self.ctx.__exit__(*exc_info)
            if suppressed:
                msg = str(self.ctx.excinfo.value)
                for name in names:
                    assert re.search(rf"\b{re.escape(name)}\b", msg), f"message does not name {name!r}: {msg!r}"
            return suppressed
    return _Check()


@pytest.mark.parametrize("up", [(0, 0, -1), (0, 0, 3), (0, 1e-9, 1), (0, 0, 0)])
def test_up_parallel_to_view(up):
    with raises("up"):
        Camera.look_at((0, 0, 5), (0, 0, 0), up)
    with raises("up"):
        Camera.orthographic((0, 0, 5), (0, 0, 0), up, 1.0)


def test_eye_equals_target():
    with raises("eye", "target"):
        Camera.look_at((1, 2, 3), (1, 2, 3))
    with raises("eye", "target"):
        Camera.orthographic((1, 2, 3), (1, 2, 3), (0, 1, 0), 1.0)


@pytest.mark.parametrize("fov", [0.0, -10.0, 180.0, 200.0, float("nan"), float("inf"), "30", None])
def test_fov_out_of_range(fov):
    with raises("fov_deg"):
        Camera.look_at((0, 0, 5), (0, 0, 0), fov_deg=fov)


@pytest.mark.parametrize("name,value", [("eye", (0, 0)), ("eye", (0, np.nan, 1)), ("target", "abc"),
                                        ("up", (0, 1, 0, 0)), ("up", (np.inf, 1, 0))])
def test_look_at_bad_vectors(name, value):
    kw = dict(eye=(0, 0, 5), target=(0, 0, 0), up=(0, 1, 0))
    kw[name] = value
    with raises(name):
        Camera.look_at(**kw)


@pytest.mark.parametrize("size", [(0, 10), (10,), (10, 10, 3), (10.0, 10), (True, 5), "ab", None, (-1, 4)])
def test_bad_image_size(size):
    with raises("image_size"):
        Camera.look_at((0, 0, 5), (0, 0, 0), image_size=size)
    with raises("image_size"):
        Camera.from_opencv(np.diag([10.0, 10.0, 1.0]), np.eye(3), np.zeros(3), size)


@pytest.mark.parametrize("scale", [0.0, -1.0, float("nan")])
def test_orthographic_bad_scale(scale):
    with raises("scale"):
        Camera.orthographic((0, 0, 5), (0, 0, 0), (0, 1, 0), scale)


@pytest.mark.parametrize("name,value", [("fx", 0.0), ("fx", -3.0), ("fy", 0.0), ("fy", float("nan")),
                                        ("cx", float("inf")), ("rotation", np.zeros(4)),
                                        ("translation", [0, 0, np.nan]), ("projection", "fisheye")])
def test_camera_bad_fields(name, value):
    kw = dict(rotation=np.zeros(3), translation=np.zeros(3), fx=10.0, fy=10.0, cx=4.0, cy=4.0,
              image_size=(8, 8), projection="perspective")
    kw[name] = value
    with raises(name):
        Camera(**kw)


@pytest.mark.parametrize("fx", [0.0, -1.0])
def test_with_params_rechecks(fx):
    with raises("fx"):
        Camera.look_at((0, 0, 5), (0, 0, 0)).with_params(fx=fx)


GOOD_K = np.array([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]])


@pytest.mark.parametrize("K", [
    np.eye(2), np.zeros((3, 4)),
    [[100.0, 0.5, 32], [0, 100, 32], [0, 0, 1]],      # skew
    [[100.0, 0, 32], [0.1, 100, 32], [0, 0, 1]],
    [[100.0, 0, 32], [0, 100, 32], [0, 0, 2]],        # last row not (0, 0, 1)
    [[0.0, 0, 32], [0, 100, 32], [0, 0, 1]],          # zero / negative focal lengths
    [[100.0, 0, 32], [0, -100, 32], [0, 0, 1]],
    [[100.0, 0, np.nan], [0, 100, 32], [0, 0, 1]]])
def test_from_opencv_bad_K(K):
    with raises("K"):
        Camera.from_opencv(K, np.eye(3), np.zeros(3), (64, 64))


@pytest.mark.parametrize("R", [np.eye(2), 2 * np.eye(3), np.diag([1.0, 1.0, -1.0]), np.ones((3, 3))])
def test_from_opencv_bad_R(R):
    with raises("R"):
        Camera.from_opencv(GOOD_K, R, np.zeros(3), (64, 64))


@pytest.mark.parametrize("t", [np.zeros(2), np.zeros((1, 3)), np.zeros((3, 2)), [0, 0, np.inf]])
def test_from_opencv_bad_t(t):
    with raises("t"):
        Camera.from_opencv(GOOD_K, np.eye(3), t, (64, 64))


CAM = Camera.look_at((0, 0, 5), (0, 0, 0), image_size=(16, 16))


@pytest.mark.parametrize("verts", [np.zeros((4, 2)), np.zeros(3), np.zeros((1, 2, 4, 3)), np.zeros((0, 3)),
                                   np.zeros((2, 0, 3)), np.zeros((4, 3), np.int64), np.array([[0, 0, np.nan]]),
                                   np.array([[[0, 0, 0], [np.inf, 0, 0]]]), [["a", "b", "c"]]])
def test_project_bad_vertices(verts):
    with raises("vertices"):
        CAM.project(verts)


def test_project_vertices_behind_camera():
    verts = np.zeros((2, 5, 3))
    verts[1, 2] = (0, 0, 5)          # at the camera centre: Z = 0
    verts[1, 4] = (0, 0, 9)          # behind: Z = -4
    with raises("vertices", match=r"behind the camera: 2 of them with Z <= 0; first at index \(1, 2\)"):
        CAM.project(verts)
    with raises("vertices", match=r"behind the camera: 2 of them with Z <= 0; first at index 2\b"):
        CAM.project(verts[1])
    ortho = Camera.orthographic((0, 0, 5), (0, 0, 0), (0, 1, 0), 1.0)
    assert np.isfinite(ortho.project(verts)[0]).all()     # orthographic: no such restriction


@pytest.mark.parametrize("grad", [np.zeros((1, 5, 3)), np.zeros((2, 5, 3)), np.zeros((2, 4)),
                                  np.full((2, 4, 3), np.nan), np.zeros((2, 4, 3), np.int64)])
def test_project_vjp_bad_cotangent(grad):
    _, ctx = CAM.project(np.zeros((2, 4, 3)))
    with raises("grad_screen"):
        CAM.project_vjp(ctx, grad)


def test_view_direction_bad_points():
    with raises("points"):
        CAM.view_direction(np.zeros((3, 2)))
    _, ctx = CAM.view_direction(np.ones((2, 3)))
    with raises("grad_dirs"):
        CAM.view_direction_vjp(ctx, np.zeros((3, 3)))


def test_project_pixels_vjp_vs_fd():
    rng = np.random.default_rng(3)
    cam = Camera.look_at([0.3, 0.2, 4.0], [0, 0, 0], image_size=(40, 56))
    pts = rng.normal(scale=0.5, size=(7, 3))
    G = rng.normal(size=(7, 2))
    uv, ctx = cam.project_pixels(pts)
    g = cam.project_pixels_vjp(ctx, G)
    h = 1e-6
    fd = np.zeros_like(pts)
    for i in np.ndindex(pts.shape):
        d = np.zeros_like(pts)
        d[i] = h
        fd[i] = (np.sum(G * cam.project_pixels(pts + d)[0]) - np.sum(G * cam.project_pixels(pts - d)[0])) / (2 * h)
    np.testing.assert_allclose(g["vertices"], fd, rtol=1e-6, atol=1e-8)
    f_fd = (np.sum(G * cam.with_params(fx=cam.fx + h, fy=cam.fy + h).project_pixels(pts)[0])
            - np.sum(G * cam.with_params(fx=cam.fx - h, fy=cam.fy - h).project_pixels(pts)[0])) / (2 * h)
    np.testing.assert_allclose(g["focal"].sum(), f_fd, rtol=1e-6)
    focal_only = cam.project_pixels_vjp(ctx, G, camera="focal")
    assert sorted(focal_only) == ["focal", "vertices"]
    assert all(np.array_equal(focal_only[k], g[k]) for k in focal_only)


def test_project_pixels_rejects_batches_and_bad_cotangents():
    cam = Camera.look_at([0, 0, 4.0], [0, 0, 0])
    with pytest.raises(ValueError, match="points must have shape"):
        cam.project_pixels(np.zeros((2, 3, 3)))
    _, ctx = cam.project_pixels(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="grad_uv must have shape"):
        cam.project_pixels_vjp(ctx, np.zeros((3, 3)))



# ---- pixel projection (landmarks, 2D joints) ---------------------------------------------------
@pytest.mark.parametrize("size", [(64, 64), (48, 80)])
def test_project_pixels_matches_pinhole_formula(size):
    cam = Camera.from_opencv([[70.0, 0, 30.5], [0, 60.0, 20.0], [0, 0, 1]], np.eye(3), [0.1, -0.2, 3.0], size)
    pts = np.array([[0.0, 0.0, 0.0], [0.3, -0.4, 1.0], [-0.5, 0.2, -1.0]])
    uv, _ = cam.project_pixels(pts)
    X = pts + [0.1, -0.2, 3.0]
    np.testing.assert_allclose(uv, np.stack([70 * X[:, 0] / X[:, 2] + 30.5, 60 * X[:, 1] / X[:, 2] + 20.0], -1),
                               atol=1e-10)


def test_look_at_names_a_bad_fov_before_looking_at_the_eye():
    """A 0 degree fov (which puts an infinitely distant eye in a caller's framing) is named as such."""
    with pytest.raises(ValueError, match=re.escape("fov_deg must be in (0, 180) degrees, got 0")):
        Camera.look_at((np.inf, 0.0, 0.0), (0.0, 0.0, 0.0), fov_deg=0)


def test_orbit_camera_at_the_poles_matches_the_limit():
    """The CLI's orbit camera takes elevation +-90 (up chosen for it) and agrees with 89.999."""
    from softras_cl.cli.view import orbit_camera

    for pole in (90.0, -90.0):
        at = orbit_camera(30.0, pole, 30.0, (32, 32)).rotation_matrix()
        near = orbit_camera(30.0, pole - np.sign(pole) * 1e-3, 30.0, (32, 32)).rotation_matrix()
        np.testing.assert_allclose(at, near, atol=1e-4)
    old = Camera.look_at(orbit_camera(30.0, 20.0, 30.0, (32, 32)).center(), (0.0, 0.0, 0.0), fov_deg=30.0,
                         image_size=(32, 32))
    np.testing.assert_allclose(orbit_camera(30.0, 20.0, 30.0, (32, 32)).rotation_matrix(),
                               old.rotation_matrix(), atol=1e-12)     # same camera as up = +y


def test_rotation_is_made_once_and_handed_out_as_a_copy():
    """A camera keeps its rotation matrix (one render asks for it several times); what
    rotation_matrix() returns is the caller's to change."""
    cam = Camera.look_at([1.0, 2.0, 3.0], [0.0, 0.0, 0.0])
    pts = np.array([[0.1, 0.2, 0.3], [-0.2, 0.1, 0.0]])
    screen, center = cam.project(pts)[0], cam.center()
    R = cam.rotation_matrix()
    np.testing.assert_allclose(R, Rotation.from_rotvec(cam.rotation.copy()).as_matrix(), atol=1e-14)
    R[:] = 0.0
    np.testing.assert_array_equal(cam.project(pts)[0], screen)
    np.testing.assert_array_equal(cam.center(), center)
    moved = cam.with_params(rotation=cam.rotation + 0.1)
    assert not np.allclose(moved.rotation_matrix(), cam.rotation_matrix())
