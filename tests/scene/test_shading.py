"""Normals and lighting (softras_cl/scene/shading.py, docs/scene.md): hand-computed values, every vjp
against central finite differences in float64, SH order/constants, and bad input."""
import numpy as np
import pytest

from softras_cl.scene import shading
from softras_cl.scene.shading import (LambertLight, PhongLight, SHLight, face_normals, face_normals_vjp,
                                sh_ambient, shade_faces, shade_faces_vjp, shade_vertices,
                                shade_vertices_vjp, vertex_normals, vertex_normals_vjp)

pytestmark = pytest.mark.filterwarnings("error")   # no divide-by-zero / invalid-value warnings

H = 1e-6
RTOL = 1e-6

# Unit cube, 12 counter-clockwise triangles seen from outside, and their outward normals.
CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                   [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=float)
CUBE_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                   [3, 7, 6], [3, 6, 2], [0, 4, 7], [0, 7, 3], [1, 2, 6], [1, 6, 5]])
CUBE_N = np.repeat([[0, 0, -1], [0, 0, 1], [0, -1, 0], [0, 1, 0], [-1, 0, 0], [1, 0, 0]], 2, 0)


# ----------------------------------------------------------------------------- helpers

def numeric_grad(fun, x, cotangent):
    """Central finite differences (step H) of sum(cotangent * fun(x)) with respect to every entry
    of x; outputs are differenced before the sum, so large unrelated outputs add no round-off."""
    x = np.array(x, dtype=np.float64)
    grad = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        plus, minus = x.copy(), x.copy()
        plus[idx] += H
        minus[idx] -= H
        grad[idx] = np.sum(cotangent * (fun(plus) - fun(minus))) / (2 * H)
    return grad


def check_vjp(forward, inputs, grads, cotangent, names=None):
    """Compares grads[name] with finite differences of sum(cotangent * forward(**inputs))."""
    for name in names or inputs:
        fd = numeric_grad(lambda val: forward(**dict(inputs, **{name: val})), inputs[name],
                          cotangent)
        got = np.asarray(grads[name], dtype=np.float64)
        assert got.shape == fd.shape, name
        np.testing.assert_allclose(got, fd, rtol=RTOL, atol=1e-8 * (1 + np.abs(fd).max()),
                                   err_msg=name)


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def octahedron(rng, batch=2, jitter=0.15):
    """Jittered octahedron (6 vertices, 8 outward counter-clockwise faces), batched."""
    axes = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    faces = []
    for sx in (0, 1):
        for sy in (2, 3):
            for sz in (4, 5):
                flip = (sx == 1) ^ (sy == 3) ^ (sz == 5)
                faces.append([sx, sz, sy] if flip else [sx, sy, sz])
    rotation, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rotation *= np.sign(np.linalg.det(rotation))   # proper rotation: keeps faces outward
    vertices = axes @ rotation.T + rng.uniform(-jitter, jitter, (batch, 6, 3))
    return vertices, np.array(faces)


def far_from_kinks(values, margin=0.05):
    return np.all(np.abs(values) > margin)


def phong_points(rng, light, n=24, batch=2):
    """Random (non-unit) normals and view directions with n.l and n.h away from 0 (FD-safe)."""
    l_hat = unit(np.asarray(getattr(light, "direction", (0.0, 1.0, 0.0))))
    out = []
    while len(out) < batch * n:
        nrm = unit(rng.normal(size=3)) * rng.uniform(0.7, 1.3)
        view = rng.normal(size=3) * rng.uniform(0.5, 2.0)
        h = unit(l_hat + unit(view))
        if abs(nrm @ l_hat) > 0.05 and abs(nrm @ h) > 0.05:
            out.append((nrm, view))
    nrm, view = (np.array([o[k] for o in out]).reshape(batch, n, 3) for k in (0, 1))
    return nrm, view, rng.uniform(0.1, 1.0, (batch, n, 3))


LIGHTS = {
    "lambert": lambda rng: LambertLight(rng.uniform(0.1, 0.6, 3), rng.uniform(0.2, 0.8, 3),
                                        rng.normal(size=3) * 1.7),
    "phong": lambda rng: PhongLight(rng.uniform(0.1, 0.6, 3), rng.uniform(0.2, 0.8, 3),
                                    rng.normal(size=3) * 1.7, rng.uniform(0.1, 0.5, 3), 7.3),
    "phong_p_below_1": lambda rng: PhongLight(0.3, 0.6, rng.normal(size=3), 0.4, 0.6),
    "sh": lambda rng: SHLight(rng.normal(size=(3, 9))),
}


def light_forward(light):
    """forward(normals, albedo, view_dirs, **light params) -> colours, rebuilding the light."""
    def forward(normals, albedo, view_dirs=None, **params):
        return type(light)(**params).shade(normals, albedo, view_dirs)[0]
    return forward


# ----------------------------------------------------------------------------- normals

def test_cube_face_normals_are_outward_axes():
    normals, _ = face_normals(CUBE_V[None], CUBE_F)
    np.testing.assert_allclose(normals[0], CUBE_N, atol=1e-15)
    centroids = CUBE_V[CUBE_F].mean(1) - 0.5
    assert np.all(np.sum(normals[0] * centroids, -1) > 0)


def test_axis_aligned_triangle_normal():
    tri = np.array([[[0, 0, 0], [2, 0, 0], [0, 3, 0]]], float)
    normals, _ = face_normals(tri, [[0, 1, 2]])
    np.testing.assert_array_equal(normals, [[[0, 0, 1]]])
    normals, _ = face_normals(tri, [[0, 2, 1]])   # clockwise: flipped
    np.testing.assert_array_equal(normals, [[[0, 0, -1]]])


def test_cube_vertex_normals_by_hand():
    normals, _ = vertex_normals(CUBE_V[None], CUBE_F)
    s3, s6 = 1 / np.sqrt(3), 1 / np.sqrt(6)
    np.testing.assert_allclose(normals[0, 6], [s3, s3, s3], atol=1e-15)
    np.testing.assert_allclose(normals[0, 0], [-s3, -s3, -s3], atol=1e-15)
    # vertex 1 = (1, 0, 0): one bottom and one front triangle, two right triangles
    np.testing.assert_allclose(normals[0, 1], [2 * s6, -s6, -s6], atol=1e-15)


def test_vertex_normals_are_area_weighted_and_zero_when_unused():
    verts = np.array([[[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0, 1], [5, 5, 5]]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])   # cross products (0, 0, 4) and (2, 0, 0)
    normals, _ = vertex_normals(verts, faces)
    expected = [[1, 0, 2] / np.sqrt(5), [0, 0, 1], [1, 0, 2] / np.sqrt(5), [1, 0, 0], [0, 0, 0]]
    np.testing.assert_allclose(normals[0], expected, atol=1e-15)


def test_degenerate_faces_give_zero_normals_and_zero_gradients():
    verts = np.array([[[0, 0, 0], [1, 1, 1], [2, 2, 2], [0, 1, 0], [7, 7, 7]]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    fn, fctx = face_normals(verts, faces)
    np.testing.assert_array_equal(fn[0, 0], 0.0)
    g = face_normals_vjp(fctx, np.ones_like(fn))["vertices"]
    assert np.all(np.isfinite(g))
    np.testing.assert_array_equal(g[0, 1], 0.0)   # vertex 1 is only in the degenerate face
    vn, vctx = vertex_normals(verts, faces)
    np.testing.assert_array_equal(vn[0, 4], 0.0)
    g = vertex_normals_vjp(vctx, np.ones_like(vn))["vertices"]
    assert np.all(np.isfinite(g)) and np.all(g[0, 4] == 0)


@pytest.mark.parametrize("kind", ["face", "vertex"])
@pytest.mark.parametrize("batched_faces", [False, True])
def test_normals_vjp_fd(kind, batched_faces):
    rng = np.random.default_rng(1)
    verts, faces = octahedron(rng)
    if batched_faces:
        faces = np.stack([faces, faces[:, [1, 2, 0]]])
    fwd, vjp = {"face": (face_normals, face_normals_vjp),
                "vertex": (vertex_normals, vertex_normals_vjp)}[kind]
    out, ctx = fwd(verts, faces)
    cot = rng.normal(size=out.shape)
    grads = vjp(ctx, cot)
    check_vjp(lambda vertices: fwd(vertices, faces)[0], dict(vertices=verts), grads, cot)
    again = vjp(fwd(verts, faces)[1], cot)["vertices"]
    np.testing.assert_array_equal(again, grads["vertices"])   # deterministic scatter


def _sum_onto_vertices(per_corner, faces, n_vertices):
    """(B, F, 3, K) corner values summed onto (B, V, K) with np.add.at, face after face and
    corner after corner: the order of sums that fits' answers depend on, to the bit."""
    out = np.zeros((len(per_corner), n_vertices, per_corner.shape[-1]))
    for b in range(len(out)):
        np.add.at(out[b], faces[b].reshape(-1), per_corner[b].reshape(-1, per_corner.shape[-1]))
    return out


def _vertex_normals_reference(verts, faces, cot):
    """Vertex normals and their vjp for the cotangent cot, in plain numpy."""
    tri = np.stack([v[f] for v, f in zip(verts, faces)])               # (B, F, 3, 3)
    e1, e2 = tri[:, :, 1] - tri[:, :, 0], tri[:, :, 2] - tri[:, :, 0]
    cross = np.cross(e1, e2)
    total = _sum_onto_vertices(np.repeat(cross[:, :, None], 3, axis=2), faces, verts.shape[1])
    length = np.linalg.norm(total, axis=-1, keepdims=True)
    used = length > 0
    normals = np.where(used, total / np.where(used, length, 1.0), 0.0)
    proj = cot - normals * np.sum(normals * cot, -1, keepdims=True)
    g_total = np.where(used, proj / np.where(used, length, 1.0), 0.0)
    corners = np.stack([g[f] for g, f in zip(g_total, faces)])
    g_cross = corners[:, :, 0] + corners[:, :, 1] + corners[:, :, 2]
    g1, g2 = np.cross(e2, g_cross), np.cross(g_cross, e1)
    g_verts = _sum_onto_vertices(np.stack([-(g1 + g2), g1, g2], axis=2), faces, verts.shape[1])
    return normals, g_verts


@pytest.mark.parametrize("all_used", [False, True])
@pytest.mark.parametrize("batched_faces", [False, True])
def test_vertex_normals_and_vjp_equal_plain_numpy_to_the_bit(batched_faces, all_used):
    """all_used: every vertex has a non-zero normal (the unmasked division); else some
    vertices are unused and some faces degenerate (zero lengths)."""
    rng = np.random.default_rng(7)
    verts = rng.normal(size=(2, 40, 3))
    if all_used:
        faces = np.concatenate([[np.roll(np.arange(40), -k) for k in range(3)][i][:, None]
                                for i in range(3)], axis=1)
        faces = np.concatenate([faces, rng.integers(0, 40, size=(50, 3))])
        faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    else:
        faces = rng.integers(0, 36, size=(90, 3))      # vertices 36-39 unused
        faces[:4, 1] = faces[:4, 0]                    # degenerate faces
    faces = np.stack([faces, faces[::-1, [1, 2, 0]]]) if batched_faces else faces
    cot = rng.normal(size=verts.shape)
    normals, ctx = vertex_normals(verts, faces)
    ref_normals, ref_grad = _vertex_normals_reference(verts, np.broadcast_to(faces, (2,) + faces.shape[-2:]), cot)
    assert (np.linalg.norm(ref_normals, axis=-1) > 0).all() == all_used
    np.testing.assert_array_equal(normals, ref_normals)
    np.testing.assert_array_equal(vertex_normals_vjp(ctx, cot)["vertices"], ref_grad)


def test_normals_follow_faces_changed_in_place():
    verts, faces = octahedron(np.random.default_rng(3))
    first = vertex_normals(verts, faces)[0]
    faces[:] = faces[:, [0, 2, 1]]                 # every face turned over
    np.testing.assert_array_equal(vertex_normals(verts, faces)[0], -first)
    with pytest.raises(ValueError, match="faces"):
        faces[0, 0] = 99
        vertex_normals(verts, faces)


# ----------------------------------------------------------------------------- lights

def test_lambert_default_is_paper_setting_by_hand():
    light = LambertLight()
    normals = np.array([[[0, 1, 0], [0, -1, 0], [0.6, 0.8, 0]]])
    albedo = np.array([[[1, 1, 1], [1, 0.5, 0.2], [0.5, 0.5, 0.5]]])
    colors, _ = light.shade(normals, albedo)
    np.testing.assert_allclose(colors, [[[1, 1, 1], [0.5, 0.25, 0.1],
                                          [0.45, 0.45, 0.45]]], atol=1e-15)


def test_phong_by_hand():
    light = PhongLight(ambient=0.0, directional=0.0, direction=(0, 0, 1), specular=(1, 0.5, 0),
                       shininess=2.0)
    n = np.array([[[0.0, 0.0, 1.0]]])
    v = np.array([[[0.0, 3.0, 0.0]]])   # not unit: normalised inside; h = (0, 1, 1)/sqrt(2)
    colors, _ = light.shade(n, np.ones((1, 1, 3)), v)
    np.testing.assert_allclose(colors, [[[0.5, 0.25, 0.0]]], atol=1e-15)


@pytest.mark.parametrize("name", sorted(LIGHTS))
def test_light_shade_vjp_fd(name):
    rng = np.random.default_rng(7)
    light = LIGHTS[name](rng)
    normals, view, albedo = phong_points(rng, light)
    inputs = dict(normals=normals, albedo=albedo, **light.params())
    if isinstance(light, PhongLight):
        inputs["view_dirs"] = view
    colors, ctx = light.shade(normals, albedo, inputs.get("view_dirs"))
    cot = rng.normal(size=colors.shape)
    grads = light.shade_vjp(ctx, cot)
    assert set(grads) == set(inputs)
    check_vjp(light_forward(light), inputs, grads, cot)


def test_lambert_param_gradients_use_both_sides_of_the_terminator():
    rng = np.random.default_rng(3)
    light = LIGHTS["lambert"](rng)
    normals, _, albedo = phong_points(rng, light)
    cos = normals @ unit(light.direction)
    assert np.any(cos > 0) and np.any(cos < 0)
    colors, ctx = light.shade(normals, albedo)
    np.testing.assert_allclose(colors[cos < 0], albedo[cos < 0] * light.ambient, atol=1e-15)
    grads = light.shade_vjp(ctx, np.ones_like(colors))
    np.testing.assert_array_equal(grads["normals"][cos < 0], 0.0)


@pytest.mark.parametrize("shininess", [0.0, 0.5, 32.0])
def test_phong_guard_no_nan_where_n_dot_h_is_not_positive(shininess):
    light = PhongLight(direction=(0, 1, 0), specular=1.0, shininess=shininess)
    n = np.array([[[0, -1.0, 0], [1.0, 0, 0], [0, 0, 0]]])   # n.h < 0, n.h == 0, zero normal
    v = np.array([[[0, 1.0, 0], [0, 1.0, 0], [0, 1.0, 0]]])
    colors, ctx = light.shade(n, np.ones_like(n), v)
    grads = light.shade_vjp(ctx, np.ones_like(colors))
    np.testing.assert_allclose(colors, 0.5, atol=1e-15)   # ambient only, no specular
    for g in grads.values():
        assert np.all(np.isfinite(g))
    assert grads["shininess"] == 0.0


# ----------------------------------------------------------------------------- spherical harmonics

Y_BY_HAND = [lambda x, y, z: 0.282095, lambda x, y, z: 0.488603 * y, lambda x, y, z: 0.488603 * z,
             lambda x, y, z: 0.488603 * x, lambda x, y, z: 1.092548 * x * y,
             lambda x, y, z: 1.092548 * y * z, lambda x, y, z: 0.315392 * (3 * z * z - 1),
             lambda x, y, z: 1.092548 * x * z, lambda x, y, z: 0.546274 * (x * x - y * y)]
A_BY_HAND = [np.pi] + [2 * np.pi / 3] * 3 + [np.pi / 4] * 5


def test_sh_ambient_is_constant():
    rng = np.random.default_rng(0)
    normals, albedo = unit(rng.normal(size=(2, 30, 3))), rng.uniform(size=(2, 30, 3))
    for grey in (1.0, 0.3, (0.2, 0.5, 0.9)):
        colors, _ = SHLight.ambient(grey).shade(normals, albedo)
        np.testing.assert_allclose(colors, albedo * np.broadcast_to(grey, 3), rtol=1e-12)
    np.testing.assert_array_equal(SHLight.ambient(0.3).coefficients, sh_ambient(0.3))


@pytest.mark.parametrize("i", range(9))
def test_sh_single_coefficient_gives_a_l_times_y_i(i):
    rng = np.random.default_rng(i)
    n = unit(rng.normal(size=3))
    for channel in range(3):
        coefficients = np.zeros((3, 9))
        coefficients[channel, i] = 1.0
        colors, _ = SHLight(coefficients).shade(n[None, None], np.ones((1, 1, 3)))
        expected = np.zeros(3)
        expected[channel] = A_BY_HAND[i] * Y_BY_HAND[i](*n)
        np.testing.assert_allclose(colors[0, 0], expected, rtol=1e-14, atol=1e-15)


def test_sh_directional_light_by_hand():
    """Coefficients L_i = Y_i(d) (a unit directional light projected on the basis): by the
    addition theorem, E(n) = 1/4 + (1/2) cos + (5/16) P2(cos), so 17/16 at n = d, 1/16 at n = -d,
    3/32 at n perpendicular to d."""
    d = unit(np.array([0.3, -0.5, 0.8]))
    light = SHLight(np.tile([y(*d) for y in Y_BY_HAND], (3, 1)))
    perp = unit(np.cross(d, [1.0, 0, 0]))
    normals = np.array([[d, -d, perp]])
    colors, _ = light.shade(normals, np.ones_like(normals))
    np.testing.assert_allclose(colors[0, :, 0], [17 / 16, 1 / 16, 3 / 32], rtol=2e-5)
    np.testing.assert_allclose(colors[0, :, 1], colors[0, :, 2])


def test_sh_coefficient_layouts():
    c = np.arange(27.0).reshape(3, 9)
    np.testing.assert_array_equal(SHLight(c.ravel()).coefficients, c)
    np.testing.assert_array_equal(SHLight(c[1]).coefficients, np.tile(c[1], (3, 1)))


# ----------------------------------------------------------------------------- scene helpers

def mesh_setup(seed, light_name, margin=0.05):
    """A jittered octahedron whose vertex and face normals are all FD-safe for the light."""
    rng = np.random.default_rng(seed)
    light = LIGHTS[light_name](rng)
    centre = np.array([0.4, 0.7, 3.0]) + rng.normal(size=(2, 3)) * 0.3
    for _ in range(200):
        verts, faces = octahedron(rng)
        if not isinstance(light, LambertLight):   # SH: smooth, no kinks
            return rng, light, verts, faces, centre
        l_hat = unit(np.asarray(light.direction))
        ok = True
        for normals, points in ((vertex_normals(verts, faces)[0], verts),
                                (face_normals(verts, faces)[0], verts[:, faces].mean(2))):
            h = unit(l_hat + unit(centre[:, None] - points))
            ok &= far_from_kinks(normals @ l_hat, margin)
            ok &= far_from_kinks(np.sum(normals * h, -1), margin) or type(light) is LambertLight
        if ok:
            return rng, light, verts, faces, centre
    raise AssertionError("no FD-safe mesh found")


@pytest.mark.parametrize("light_name", sorted(LIGHTS))
@pytest.mark.parametrize("kind", ["vertices", "faces"])
@pytest.mark.parametrize("batched_camera", [False, True])
def test_shade_mesh_vjp_fd(light_name, kind, batched_camera):
    rng, light, verts, faces, centre = mesh_setup(11, light_name)
    camera = centre if batched_camera else centre[0]
    fwd, vjp = {"vertices": (shade_vertices, shade_vertices_vjp),
                "faces": (shade_faces, shade_faces_vjp)}[kind]
    albedo = rng.uniform(0.1, 1.0, (2, verts.shape[1] if kind == "vertices" else len(faces), 3))
    colors, ctx = fwd(verts, faces, albedo, light, camera)
    cot = rng.normal(size=colors.shape)
    grads = vjp(ctx, cot)
    inputs = dict(vertices=verts, albedo=albedo, camera_center=camera, **light.params())
    assert set(grads) == set(inputs)

    def forward(vertices, albedo, camera_center, **params):
        return fwd(vertices, faces, albedo, type(light)(**params), camera_center)[0]
    check_vjp(forward, inputs, grads, cot)


def test_shade_vertices_without_camera_matches_direct_shading():
    rng, light, verts, faces, _ = mesh_setup(2, "sh")
    albedo = rng.uniform(size=verts.shape)
    colors, ctx = shade_vertices(verts, faces, albedo, light)
    normals, _ = vertex_normals(verts, faces)
    np.testing.assert_allclose(colors, light.shade(normals, albedo)[0], rtol=1e-15)
    assert "camera_center" not in shade_vertices_vjp(ctx, np.ones_like(colors))


# ----------------------------------------------------------------------------- bad input

@pytest.mark.parametrize("make, name", [
    (lambda: SHLight(np.zeros(26)), "coefficients"),
    (lambda: SHLight(np.zeros((9, 3))), "coefficients"),
    (lambda: SHLight(np.full((3, 9), np.nan)), "coefficients"),
    (lambda: LambertLight(ambient=(1.0, 2.0)), "ambient"),
    (lambda: LambertLight(directional=(0.5, np.nan, 0.5)), "directional"),
    (lambda: LambertLight(direction=(0, 0, 0)), "direction"),
    (lambda: LambertLight(direction=(0, 1)), "direction"),
    (lambda: PhongLight(shininess=-1.0), "shininess"),
    (lambda: PhongLight(shininess=np.nan), "shininess"),
    (lambda: PhongLight(shininess=(1.0, 2.0)), "shininess"),
    (lambda: PhongLight(specular=np.ones(4)), "specular"),
    (lambda: SHLight.ambient((1.0, 1.0)), "grey"),
])
def test_bad_light_parameters(make, name):
    with pytest.raises(ValueError, match=name):
        make()


def test_bad_shading_inputs():
    verts, faces = CUBE_V[None], CUBE_F
    with pytest.raises(ValueError, match="vertices"):
        face_normals(CUBE_V, faces)
    with pytest.raises(ValueError, match="faces"):
        vertex_normals(verts, faces + 1)
    with pytest.raises(ValueError, match="faces"):
        face_normals(verts, faces.astype(float))
    with pytest.raises(ValueError, match="albedo"):
        LambertLight().shade(np.ones((1, 4, 3)), np.ones((1, 5, 3)))
    with pytest.raises(ValueError, match="view_dirs"):
        PhongLight().shade(np.ones((1, 4, 3)), np.ones((1, 4, 3)))
    with pytest.raises(ValueError, match="camera_center"):
        shade_vertices(verts, faces, np.ones((1, 8, 3)), PhongLight())
    with pytest.raises(ValueError, match="camera_center"):
        shade_faces(verts, faces, np.ones((1, 12, 3)), LambertLight(), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="albedo"):
        shade_faces(verts, faces, np.ones((1, 8, 3)), LambertLight())
    with pytest.raises(ValueError, match="light"):
        shade_vertices(verts, faces, np.ones((1, 8, 3)), (0.5, 0.5))


def test_module_constants_match_docs():
    assert (shading.SH_Y0, shading.SH_Y1, shading.SH_Y2, shading.SH_Y2_ZZ, shading.SH_Y2_XXYY) == (
        0.282095, 0.488603, 1.092548, 0.315392, 0.546274)
    np.testing.assert_array_equal(shading.SH_A, A_BY_HAND)
