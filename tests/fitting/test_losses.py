"""Fitting losses: exact gradients vs central finite differences, hand-checked values,
input validation, weighted_sum."""
import numpy as np
import pytest

from softras_cl.fitting import losses
from softras_cl.scene.meshes import icosphere

H = 1e-6
RTOL = 1e-6


def fd_grad(f, x):
    """Central finite differences (step H) of scalar f at float64 array x."""
    x = np.array(x, dtype=np.float64)
    g = np.empty_like(x)
    flat, gflat = x.reshape(-1), g.reshape(-1)
    for k in range(flat.size):
        old = flat[k]
        flat[k] = old + H
        fp = f(x)
        flat[k] = old - H
        fm = f(x)
        flat[k] = old
        gflat[k] = (fp - fm) / (2 * H)
    return g


def check_grad(loss, x, key, **kw):
    """loss(x, **kw) -> (value, grads); compare grads[key] with finite differences."""
    value, grads = loss(x, **kw)
    assert isinstance(value, float)
    assert set(grads) == {key}
    g = grads[key]
    assert g.shape == np.shape(x) and g.dtype == np.float64
    fd = fd_grad(lambda y: loss(y, **kw)[0], x)
    # rel 1e-6; the tiny absolute floor covers components that are zero up to FD roundoff.
    np.testing.assert_allclose(g, fd, rtol=RTOL, atol=1e-9 * max(1.0, np.abs(fd).max()))
    return value, g


def grid_mesh(nx, ny, z=None):
    """Regular planar grid (nx x ny vertices, unit spacing), every cell split along the same
    diagonal; z: optional (ny, nx) heights."""
    xs, ys = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float))
    zs = np.zeros_like(xs) if z is None else z
    v = np.stack([xs, ys, zs], -1).reshape(-1, 3)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    f = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.int32)
    return v, f


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


# ---------------------------------------------------------------- gradients vs finite differences

@pytest.mark.parametrize("shape", [(5, 4), (4, 5, 3)])
@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("loss", [losses.image_l2, losses.image_l1])
def test_image_grads(rng, loss, shape, masked):
    pred = rng.uniform(0, 1, shape)
    off = rng.uniform(0.05, 0.5, shape) * rng.choice([-1, 1], shape)   # no ties for L1
    mask = rng.uniform(0, 1, shape[:2]) * (rng.uniform(size=shape[:2]) > 0.3) if masked else None
    check_grad(lambda p, mask=None: loss(p, pred + off, mask), pred, "pred", mask=mask)


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("loss", [losses.silhouette_iou, losses.silhouette_l2])
def test_silhouette_grads(rng, loss, masked):
    pred = rng.uniform(0, 1, (6, 7))
    target = (rng.uniform(size=(6, 7)) > 0.5).astype(float) * rng.uniform(0.5, 1, (6, 7))
    mask = rng.uniform(0, 1, (6, 7)) * (rng.uniform(size=(6, 7)) > 0.3) if masked else None
    check_grad(lambda p: loss(p, target, mask=mask), pred, "pred")


@pytest.mark.parametrize("robust_sigma", [None, 0.7, 3.0])
@pytest.mark.parametrize("weighted", [False, True])
def test_landmark_grads(rng, robust_sigma, weighted):
    pts = rng.normal(0, 2, (7, 2))
    target = rng.normal(0, 2, (7, 2))
    w = rng.uniform(0, 2, 7) if weighted else None
    check_grad(losses.landmarks_2d, pts, "points", target=target, weights=w,
               robust_sigma=robust_sigma)


@pytest.mark.parametrize("scale", [0.5, 2.0, 30.0])
def test_robust_landmark_grads(rng, scale):
    pts, target, w = rng.normal(0, 2, (7, 2)), rng.normal(0, 2, (7, 2)), rng.uniform(0, 2, 7)

    def loss(p):
        value, g = losses.landmarks_2d_robust(p - target, w, scale)
        return value, {"points": g}

    check_grad(loss, pts, "points")


def test_robust_landmark_values():
    """Each point's squared residual in its deviations, u2 = w r^2: well below the scale c the
    plain term, at u = c half of c^2, at most c^2 with no pull; no points: 0."""
    residuals, w = np.array([[3e-4, 4e-4], [3.0, 4.0], [3e6, 4e6]]), np.array([4.0, 0.25, 1.0])
    value, g = losses.landmarks_2d_robust(residuals[:1], w[:1], 2.0)
    plain, g_plain = losses.landmarks_2d(residuals[:1], np.zeros((1, 2)), weights=w[:1])
    assert value == pytest.approx(plain, rel=1e-6) and np.allclose(g, g_plain["points"], rtol=1e-6)
    assert losses.landmarks_2d_robust(residuals[1:2], w[1:2], 2.5)[0] == pytest.approx(2.5 ** 2 / 2)
    value, g = losses.landmarks_2d_robust(residuals[2:], w[2:], 2.0)
    assert value == pytest.approx(4.0, rel=1e-11) and np.abs(g).max() < 1e-11
    value, g = losses.landmarks_2d_robust(np.zeros((0, 2)), np.zeros(0), 2.0)
    assert value == 0.0 and g.shape == (0, 2)


@pytest.mark.parametrize("sigma_kind", ["scalar", "per-coefficient"])
def test_gaussian_prior_grad(rng, sigma_kind):
    c = rng.normal(0, 1, (3, 4))
    sigma = 0.7 if sigma_kind == "scalar" else rng.uniform(0.5, 2, (3, 4))
    check_grad(losses.gaussian_prior, c, "coeffs", sigma=sigma)
    check_grad(losses.gaussian_prior, c, "coeffs", sigma=rng.uniform(0.5, 2, 4), mean=0.3)


def test_sh_white_grad_and_values(rng):
    check_grad(losses.sh_white, rng.normal(0, 1, (3, 9)), "coeffs")
    grey = np.tile(rng.normal(0, 1, 9), (3, 1))
    assert losses.sh_white(grey)[0] == 0.0
    tinted = grey.copy()
    tinted[0, 0] += 3.0                       # red ambient raised by 3: spread 3 * (2/3, -1/3, -1/3)
    assert losses.sh_white(tinted)[0] == pytest.approx(9.0 * (4 + 1 + 1) / 9)
    with pytest.raises(ValueError, match="shape \\(3, 9\\)"):
        losses.sh_white(np.zeros(27))


def random_meshes(rng):
    v, f = icosphere(1)
    v = v + rng.normal(0, 0.05, v.shape)            # closed, every edge interior
    gv, gf = grid_mesh(4, 5, rng.normal(0, 0.3, (5, 4)))
    gv = gv + rng.normal(0, 0.1, gv.shape)          # open: boundary edges and vertices
    return [(v, f), (gv, gf)]


@pytest.mark.parametrize("loss", [losses.laplacian, losses.flatten, losses.edge_length])
def test_mesh_grads(rng, loss):
    for v, f in random_meshes(rng):
        value, g = check_grad(lambda x: loss(x, f), v, "vertices")
        assert value > 0
        # Translation invariance: the gradient sums to zero.
        np.testing.assert_allclose(g.sum(0), 0, atol=1e-9 * np.abs(g).max())


def test_flatten_degenerate_is_finite():
    """A collinear opposite vertex and a zero-length edge give finite values and gradients."""
    f = np.array([[0, 1, 2], [1, 0, 3]])                # one interior edge (0, 1)
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, 0, 0]], float)
    value, g = losses.flatten(v, f)                     # u_b = 0: cos guarded to 0
    assert value == pytest.approx(1.0) and np.isfinite(g["vertices"]).all()
    v[3] = [0.5, 1e-7, 1e-7]                            # nearly collinear
    value, g = losses.flatten(v, f)
    assert np.isfinite(value) and np.isfinite(g["vertices"]).all()
    v[1] = v[0]                                         # edge (0, 1) of zero length
    value, g = losses.flatten(v, f)
    assert np.isfinite(value) and np.isfinite(g["vertices"]).all()
    v[:] = 0                                            # everything collapsed
    value, g = losses.flatten(v, f)
    assert value == pytest.approx(1.0) and np.isfinite(g["vertices"]).all()


# ---------------------------------------------------------------- values by hand

def test_image_values():
    pred = np.array([[0.0, 1.0], [2.0, 3.0]])
    target = np.zeros((2, 2))
    assert losses.image_l2(pred, target)[0] == pytest.approx((0 + 1 + 4 + 9) / 4)
    assert losses.image_l1(pred, target)[0] == pytest.approx(6 / 4)
    mask = np.array([[1, 0], [0, 1]], bool)
    assert losses.image_l2(pred, target, mask)[0] == pytest.approx(9 / 2)
    assert losses.image_l1(pred, target, mask)[0] == pytest.approx(3 / 2)
    # An (H, W) mask on an (H, W, C) image: mean over masked pixels and all channels.
    rgb = np.stack([pred, 2 * pred, 3 * pred], -1)
    assert losses.image_l1(rgb, np.zeros_like(rgb), mask)[0] == pytest.approx(3 * 6 / 6)
    # A (1, 1, C) channel weighting broadcasts.
    assert losses.image_l1(rgb, np.zeros_like(rgb), np.array([[[1, 0, 0]]]))[0] \
        == pytest.approx(6 / 4)
    # All-zero mask: 0 and zero gradient. Subgradient 0 where pred == target.
    value, g = losses.image_l2(pred, target, np.zeros((2, 2)))
    assert value == 0 and not g["pred"].any()
    assert losses.image_l1(target, target)[1]["pred"].tolist() == [[0, 0], [0, 0]]


def test_silhouette_iou_values():
    a = np.array([[1, 1, 0, 0]], float)
    b = np.array([[0, 0, 1, 1]], float)
    c = np.array([[0, 1, 1, 0]], float)
    assert losses.silhouette_iou(a, a)[0] == 0.0                      # identical
    assert losses.silhouette_iou(a, b)[0] == pytest.approx(1.0, abs=1e-6)   # disjoint
    assert losses.silhouette_iou(a, c)[0] == pytest.approx(2 / 3, abs=1e-6)
    # Empty union: 0 loss and a finite gradient.
    z = np.zeros((3, 3))
    value, g = losses.silhouette_iou(z, z)
    assert value == 0.0 and np.isfinite(g["pred"]).all()
    # Soft values: 1 - sum(pt) / sum(p + t - pt).
    p, t = np.array([0.5, 0.25]), np.array([1.0, 0.0])
    assert losses.silhouette_iou(p, t, eps=1e-300)[0] == pytest.approx(1 - 0.5 / 1.25)
    # a mask leaves pixels out of both sums: a, c agree where the mask is 1
    assert losses.silhouette_iou(a, c, mask=np.array([[0, 1, 0, 1]]))[0] == pytest.approx(0.0, abs=1e-6)
    assert losses.silhouette_iou(a, c, mask=np.array([[2, 1, 1, 1]]))[0] == pytest.approx(3 / 4, abs=1e-6)
    assert losses.silhouette_l2(a, b)[0] == pytest.approx(1.0)
    assert losses.silhouette_l2(a, c)[0] == pytest.approx(0.5)


def test_landmarks_values():
    pts = np.array([[0.0, 0.0], [3.0, 4.0]])
    value, g = losses.landmarks_2d(pts, np.zeros((2, 2)), weights=[1.0, 2.0])
    assert value == pytest.approx((0 + 2 * 25) / 2)
    np.testing.assert_allclose(g["points"], [[0, 0], [2 * 3, 2 * 4]])   # 2 w d / N
    # Geman-McClure: r = sigma gives rho = 1/2.
    assert losses.landmarks_2d(pts[1:], np.zeros((1, 2)), robust_sigma=5.0)[0] == pytest.approx(0.5)
    # Saturation: a huge residual costs ~ its weight and pulls with ~ zero force.
    far = np.array([[1e6, 0.0]])
    value, g = losses.landmarks_2d(far, np.zeros((1, 2)), weights=[3.0], robust_sigma=1.0)
    assert value == pytest.approx(3.0, rel=1e-11)
    assert np.abs(g["points"]).max() < 1e-11
    near = losses.landmarks_2d(np.array([[1.0, 0.0]]), np.zeros((1, 2)), weights=[3.0],
                               robust_sigma=1.0)
    assert np.abs(near[1]["points"]).max() > 1e5 * np.abs(g["points"]).max()
    assert losses.landmarks_2d(np.zeros((0, 2)), np.zeros((0, 2)))[0] == 0.0


def test_gaussian_prior_values():
    value, g = losses.gaussian_prior(np.array([1.0, 2.0]), np.array([1.0, 2.0]))
    assert value == pytest.approx(2.0)
    np.testing.assert_allclose(g["coeffs"], [2.0, 1.0])
    assert losses.gaussian_prior(np.array([3.0]), 2.0, mean=1.0)[0] == pytest.approx(1.0)


def test_laplacian_values():
    v, f = grid_mesh(6, 5)
    delta = losses.laplacian_coordinates(v, f)
    interior = np.ones((5, 6), bool)
    interior[[0, -1], :] = interior[:, [0, -1]] = False
    np.testing.assert_allclose(delta[interior.ravel()], 0, atol=1e-12)
    assert np.abs(delta[~interior.ravel()]).max() > 0.1           # boundary is not ~0
    value, _ = losses.laplacian(v, f)
    assert value == pytest.approx((delta ** 2).sum())
    # Single triangle: each vertex's neighbours are the two others.
    tri = np.array([[0.0, 0, 0], [2, 0, 0], [0, 2, 0]])
    d = tri - (tri.sum(0) - tri) / 2
    assert losses.laplacian(tri, [[0, 1, 2]])[0] == pytest.approx((d ** 2).sum())
    # An isolated vertex (in no face) contributes nothing and gets no gradient.
    v4 = np.vstack([tri, [[5.0, 5, 5]]])
    value, g = losses.laplacian(v4, [[0, 1, 2]])
    assert value == pytest.approx((d ** 2).sum()) and not g["vertices"][3].any()


def test_flatten_values():
    v, f = grid_mesh(5, 4)
    assert losses.flatten(v, f)[0] == pytest.approx(0.0, abs=1e-20)
    v_tilted = v @ np.array([[1, 0, 0], [0, 0.6, 0.8], [0, -0.8, 0.6]])   # a rotated plane
    assert losses.flatten(v_tilted, f)[0] == pytest.approx(0.0, abs=1e-20)
    # Fold along the grid line x = 2 at a right angle: z = |x - 2|. The 3 edges on the fold
    # line have cos = 0, every other interior edge stays flat: total 3 * (0 + 1)^2.
    xs = np.tile(np.arange(5.0), (4, 1))
    v_fold, _ = grid_mesh(5, 4, np.abs(xs - 2))
    assert losses.flatten(v_fold, f)[0] == pytest.approx(3.0, rel=1e-10)
    # Gentler fold z = k|x - 2|: cos = (k^2 - 1) / (k^2 + 1).
    k = 0.3
    v_fold, _ = grid_mesh(5, 4, k * np.abs(xs - 2))
    expect = 3 * ((k * k - 1) / (k * k + 1) + 1) ** 2
    assert losses.flatten(v_fold, f)[0] == pytest.approx(expect, rel=1e-10)
    # Two triangles folded onto each other: cos = 1, loss 4. Orientation does not matter.
    two = np.array([[0.0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, 1, 0.0]])
    assert losses.flatten(two, [[0, 1, 2], [1, 0, 3]])[0] == pytest.approx(4.0)
    square = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    assert losses.flatten(square, [[0, 1, 2], [0, 2, 3]])[0] == pytest.approx(0.0, abs=1e-20)
    assert losses.flatten(square, [[0, 1, 2], [0, 3, 2]])[0] == pytest.approx(0.0, abs=1e-20)
    # Single face: no interior edge.
    value, g = losses.flatten(square, [[0, 1, 2]])
    assert value == 0.0 and not g["vertices"].any()


def test_edge_length_values():
    tri = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert losses.edge_length(tri, [[0, 1, 2]])[0] == pytest.approx(1 + 1 + 2)
    square = np.vstack([tri, [[1.0, 1, 0]]])
    # Shared diagonal counted once: 4 sides + diagonal.
    assert losses.edge_length(square, [[0, 1, 3], [0, 3, 2]])[0] == pytest.approx(4 + 2)


def test_topology():
    v, f = icosphere(2)
    topo = losses.mesh_topology(f, len(v))
    assert len(topo.edges) == 3 * len(f) // 2 and len(topo.interior) == len(topo.edges)
    assert (topo.degree[:12] == 5).all() and (topo.degree[12:] == 6).all()
    assert losses.mesh_topology(f.copy(), len(v)) is topo                 # cached by content
    # A topology object can be passed in place of faces.
    assert losses.edge_length(v, topo)[0] == losses.edge_length(v, f)[0]
    gv, gf = grid_mesh(4, 3)
    gt = losses.mesh_topology(gf, len(gv))
    n_edges = 3 * 3 + 4 * 2 + 3 * 2                                      # rows, columns, diagonals
    n_boundary = 2 * 3 + 2 * 2
    assert len(gt.edges) == n_edges and len(gt.interior) == n_edges - n_boundary


# ---------------------------------------------------------------- validation

@pytest.mark.parametrize("call, name", [
    (lambda: losses.image_l2(np.zeros((2, 2)), np.zeros((2, 3))), "target"),
    (lambda: losses.image_l1(np.full((2, 2), np.nan), np.zeros((2, 2))), "pred"),
    (lambda: losses.image_l2(np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((3, 3))), "mask"),
    (lambda: losses.image_l2(np.zeros((2, 2)), np.zeros((2, 2)), -np.ones((2, 2))), "mask"),
    (lambda: losses.silhouette_iou(np.zeros((2, 2)), np.ones((2, 2)) * np.inf), "target"),
    (lambda: losses.silhouette_iou(np.zeros((2, 2)), np.zeros((2, 2)), eps=0), "eps"),
    (lambda: losses.silhouette_iou(np.zeros((2, 2)), np.zeros((2, 2)), mask=-np.ones((2, 2))), "mask"),
    (lambda: losses.silhouette_iou(np.zeros((2, 2)), np.zeros((2, 2)), mask=np.ones((3, 2))), "mask"),
    (lambda: losses.landmarks_2d(np.zeros((3, 3)), np.zeros((3, 3))), "points"),
    (lambda: losses.landmarks_2d(np.zeros((3, 2)), np.zeros((2, 2))), "target"),
    (lambda: losses.landmarks_2d(np.zeros((3, 2)), np.zeros((3, 2)), [1, -1, 1]), "weights"),
    (lambda: losses.landmarks_2d(np.zeros((3, 2)), np.zeros((3, 2)), [1, 1]), "weights"),
    (lambda: losses.landmarks_2d(np.zeros((3, 2)), np.zeros((3, 2)), robust_sigma=-1), "robust_sigma"),
    (lambda: losses.gaussian_prior(np.zeros(3), -1.0), "sigma"),
    (lambda: losses.gaussian_prior(np.zeros(3), np.ones(4)), "sigma"),
    (lambda: losses.gaussian_prior([0.0, np.nan], 1.0), "coeffs"),
    (lambda: losses.laplacian(np.zeros((3, 2)), [[0, 1, 2]]), "vertices"),
    (lambda: losses.laplacian(np.zeros((3, 3)), [[0, 1, 3]]), "faces"),
    (lambda: losses.flatten(np.zeros((3, 3)), [[0, 1, 1]]), "faces"),
    (lambda: losses.edge_length(np.zeros((3, 3)), [[0.0, 1.0, 2.0]]), "faces"),
    (lambda: losses.edge_length(np.zeros((3, 3)), [0, 1, 2]), "faces"),
    (lambda: losses.weighted_sum({"a": (1.0, {})}, {"a": -1.0}), "weights['a']"),
    (lambda: losses.weighted_sum({"a": (1.0, {})}, {"a": float("nan")}), "weights['a']"),
    (lambda: losses.weighted_sum({}, {"b": 1.0}), "weights['b']"),
])
def test_invalid_inputs(call, name):
    with pytest.raises(ValueError) as info:
        call()
    assert str(info.value).startswith(name)


# ---------------------------------------------------------------- weighted_sum

def test_weighted_sum():
    v = np.arange(6.0).reshape(2, 3)
    terms = {
        "a": (2.0, {"vertices": np.ones((2, 3)), "pred": np.full((2, 2), 3.0)}),
        "b": (5.0, {"vertices": v}),
        "zero": (7.0, {"vertices": np.full((2, 3), np.nan)}),     # weight 0: not read
        "unweighted": (1e9, {"other": np.ones(1)}),               # no weight: skipped
    }
    before = {k: (val, {kk: a.copy() for kk, a in g.items()}) for k, (val, g) in terms.items()}
    total, grads, weighted = losses.weighted_sum(terms, {"a": 0.5, "b": 2.0, "zero": 0.0})
    assert total == pytest.approx(0.5 * 2 + 2 * 5)
    assert weighted == {"a": pytest.approx(1.0), "b": pytest.approx(10.0)}
    assert set(grads) == {"vertices", "pred"}
    np.testing.assert_allclose(grads["vertices"], 0.5 + 2 * v)
    np.testing.assert_allclose(grads["pred"], 1.5)
    for k, (_, g) in before.items():                               # inputs untouched
        for kk, a in g.items():
            np.testing.assert_array_equal(terms[k][1][kk], a)
    # Works end to end with real losses on the same mesh.
    mv, mf = icosphere(1)
    t2 = {"lap": losses.laplacian(mv, mf), "edge": losses.edge_length(mv, mf)}
    total, grads, _ = losses.weighted_sum(t2, {"lap": 3.0, "edge": 0.25})
    assert total == pytest.approx(3 * t2["lap"][0] + 0.25 * t2["edge"][0])
    np.testing.assert_allclose(grads["vertices"],
                               3 * t2["lap"][1]["vertices"] + 0.25 * t2["edge"][1]["vertices"])
    # Mismatched shapes under the same key.
    with pytest.raises(ValueError, match="vertices"):
        losses.weighted_sum({"a": (1.0, {"vertices": np.ones((2, 3))}),
                             "b": (1.0, {"vertices": np.ones((3, 3))})}, {"a": 1, "b": 1})


# ---------------------------------------------------------------- robust image term

@pytest.mark.parametrize("shape", [(5, 4), (4, 5, 3)])
@pytest.mark.parametrize("masked", [False, True])
def test_geman_mcclure_grads_on_both_sides_of_the_scale(rng, shape, masked):
    pred, target = rng.random(shape), rng.random(shape)
    r = np.abs(pred - target) if len(shape) == 2 else np.linalg.norm(pred - target, axis=-1)
    scale = float(np.median(r))                              # half the pixels beyond the scale
    mask = rng.random(shape[:2]) * (rng.random(shape[:2]) > 0.3) if masked else None
    check_grad(losses.image_geman_mcclure, pred, "pred", target=target, scale=scale, mask=mask)


def _gm_exact(r, s):
    """Exact rational mean of r2 s^2 / (s^2 + r2) over the pixels of r (N, C), and its
    gradient wrt the first pixel's first channel: 2 r s^4 / (s^2 + r2)^2 / N."""
    from fractions import Fraction as F

    s2 = F(s) ** 2
    r2 = [sum(F(x) ** 2 for x in px) for px in r]
    value = sum(q * s2 / (s2 + q) for q in r2) / len(r)
    grad = 2 * F(r[0][0]) * s2 * s2 / (s2 + r2[0]) ** 2 / len(r)
    return float(value), float(grad)


def test_geman_mcclure_values_match_exact_arithmetic():
    r = np.array([[[0.1, -0.2, 0.05], [1.0, 0.0, 0.0]], [[0.0, 0.0, 0.0], [3.0, -4.0, 12.0]]])
    for s in (0.01, 0.3, 1.0, 100.0):
        value, g = losses.image_geman_mcclure(r, np.zeros_like(r), s)
        exact, g00 = _gm_exact(r.reshape(-1, 3).tolist(), s)
        assert value == pytest.approx(exact, rel=1e-14)
        assert g["pred"][0, 0, 0] == pytest.approx(g00, rel=1e-14)
    # far below the scale it is the per-pixel sum of squares, far above it s^2 per pixel
    small = losses.image_geman_mcclure(r, np.zeros_like(r), 1e6)[0]
    assert small == pytest.approx(3 * losses.image_l2(r, np.zeros_like(r))[0], rel=1e-9)
    big = np.full((2, 2, 3), 1e3)
    assert losses.image_geman_mcclure(big, np.zeros_like(big), 1e-3)[0] == pytest.approx(1e-6, rel=1e-9)
    mask = np.array([[1.0, 0.0], [0.0, 0.0]])          # only pixel (0, 0) counts
    assert losses.image_geman_mcclure(r, np.zeros_like(r), 0.3, mask)[0] == pytest.approx(
        _gm_exact([r[0, 0].tolist()], 0.3)[0], rel=1e-14)
    assert losses.image_geman_mcclure(r, np.zeros_like(r), 0.3, np.zeros((2, 2))) == (0.0, {"pred": pytest.approx(0 * r)})


@pytest.mark.parametrize("shape", [(6, 5), (6, 5, 3)])
@pytest.mark.parametrize("mask_kind", ["none", "bool", "weights", "empty"])
def test_geman_mcclure_equals_the_whole_image_formula_to_the_bit(rng, shape, mask_kind):
    """Evaluated on the masked pixels alone, the value and gradient are those of the formula
    over the whole image (mask times kernel, summed over every pixel): the same bits, so fits
    give the same answers."""
    pred, target = rng.random(shape), rng.random(shape)
    mask = {"none": None, "bool": rng.random(shape[:2]) > 0.5, "empty": np.zeros(shape[:2]),
            "weights": rng.random(shape[:2]) * (rng.random(shape[:2]) > 0.3)}[mask_kind]
    s = 0.4
    r = (pred - target).reshape(shape[:2] + (-1,))
    m = np.ones(shape[:2]) if mask is None else mask.astype(float)
    z2 = np.square(r / s).sum(axis=-1)
    w = 1.0 / (1.0 + z2)
    rho = np.where(z2 <= 1.0, np.square(r).sum(axis=-1) * w, (s * s) * (1.0 - w))
    total = m.sum()
    value = (m * rho).sum() / total if total else 0.0
    grad = ((m / total)[..., None] * ((2.0 * w * w)[..., None] * r) if total else 0 * r).reshape(shape)
    for got, g in (losses.image_geman_mcclure(pred, target, s, mask), losses.GemanMcClure(target, s, mask)(pred)):
        assert got == value
        np.testing.assert_array_equal(g["pred"], grad)
    got, g = losses.GemanMcClure(target, s, mask)(pred, grad_scale=37.0)    # the caller's weight
    assert got == value
    np.testing.assert_array_equal(g["pred"], grad * 37.0)


def test_prepared_geman_mcclure_checks_its_inputs():
    loss = losses.GemanMcClure(np.zeros((4, 4, 3)), 0.5, np.ones((4, 4)))
    with pytest.raises(ValueError, match="pred: shape"):
        loss(np.zeros((4, 5, 3)))
    with pytest.raises(ValueError, match="pred contains NaN"):
        loss(np.full((4, 4, 3), np.nan))
    with pytest.raises(ValueError, match="target: expected"):
        losses.GemanMcClure(np.zeros(4), 0.5)
    with pytest.raises(ValueError, match="mask"):
        losses.GemanMcClure(np.zeros((4, 4, 3)), 0.5, np.ones((3, 3)))


@pytest.mark.parametrize("scale", [1e-300, 1e-150, 1e-8, 1.0, 1e8, 1e150])
@pytest.mark.parametrize("residual", [0.0, 1e-300, 1e-150, 1e-8, 1.0, 1e8, 1e150])
def test_geman_mcclure_is_finite_and_exact_at_extreme_residuals_and_scales(residual, scale):
    r = np.array([[[residual, -residual, 0.5 * residual]]])
    value, g = losses.image_geman_mcclure(r, np.zeros_like(r), scale)
    assert np.isfinite(value) and np.isfinite(g["pred"]).all()
    exact, g00 = _gm_exact(r.reshape(-1, 3).tolist(), scale)
    tiny = 1e-290                          # below this float64 keeps few digits (subnormals)
    assert value == pytest.approx(exact, rel=1e-12, abs=tiny)
    assert g["pred"][0, 0, 0] == pytest.approx(g00, rel=1e-12, abs=tiny)


@pytest.mark.parametrize("call, says", [
    (lambda: losses.image_geman_mcclure(np.zeros(4), np.zeros(4), 1.0), "pred: expected an (H, W) or (H, W, C)"),
    (lambda: losses.image_geman_mcclure(np.zeros((2, 2)), np.zeros((2, 2)), 0.0), "scale must be > 0"),
    (lambda: losses.image_geman_mcclure(np.zeros((2, 2)), np.zeros((2, 2)), -1.0), "scale must be > 0"),
    (lambda: losses.image_geman_mcclure(np.zeros((2, 2)), np.zeros((2, 2)), np.nan), "scale contains NaN"),
    (lambda: losses.image_geman_mcclure(np.zeros((2, 2)), np.zeros((2, 2)), np.ones(2)), "scale: expected a scalar"),
    (lambda: losses.image_geman_mcclure(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)), 1.0), "target"),
    (lambda: losses.image_geman_mcclure(np.zeros((2, 2, 3)), np.zeros((2, 2, 3)), 1.0, np.ones((3, 3))), "mask"),
    (lambda: losses.image_geman_mcclure(np.zeros((2, 2, 3)), np.zeros((2, 2, 3)), 1.0, -np.ones((2, 2))), "mask"),
])
def test_geman_mcclure_rejects_bad_input(call, says):
    with pytest.raises(ValueError) as info:
        call()
    assert str(info.value).startswith(says)
