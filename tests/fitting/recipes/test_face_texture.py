"""Detail texture of a face fit (fitting/recipes/face_texture.py) and the report's pictures
(fitting/reports/face.py): clean renders of the fitted demo face, uv layout, un-lighting of a
face rendered with a known texture and light, symmetry fill and the textured OBJ."""
from types import SimpleNamespace

import numpy as np
import pytest

from softras_cl.bench.face import random_truth
from softras_cl.fitting.keypoints import ibug68
from softras_cl.fitting.recipes import face
from softras_cl.fitting.recipes import face_texture as ft
from softras_cl.fitting.reports import face as report
from softras_cl.scene.renderer import Renderer
from softras_cl.scene.rotation import axis_angle_to_matrix, matrix_to_axis_angle

SIZE = 160


@pytest.fixture(scope="module")
def demo():
    from softras_cl.fitting.models.face_loaders import load_demo_face_model

    return load_demo_face_model()


@pytest.fixture(scope="module")
def layout(demo):
    return ft.face_uv_layout(demo, 256)


def synthetic_fit(model, values, size=SIZE):
    """What estimate_texture reads of a FaceFit, for a photo drawn with ``values`` (full photo =
    working image)."""
    scene = face.FaceScene(model, (size, size), depth_range=face.depth_range(values["translation"]))
    return SimpleNamespace(values=values, scene=scene, crop=face.Crop(0.0, 0.0, 1.0))


def truth(model, seed, yaw_deg=None, **changes):
    values = random_truth(model, np.random.default_rng(seed), SIZE)
    if yaw_deg is not None:
        values["rotation"] = matrix_to_axis_angle(axis_angle_to_matrix([0.0, np.radians(yaw_deg), 0.0]))
        values["translation"][:2] = 0.0
    return dict(values, **changes)


def smooth_texture(size, symmetric=False):
    """(size, size, 3) linear RGB, low-frequency pattern in [0.2, 0.8]."""
    v, u = np.mgrid[0:size, 0:size] / size
    if symmetric:
        u = np.abs(u - 0.5)
    return 0.5 + 0.3 * np.stack([np.sin(9 * u + 2 * v), np.cos(7 * v - 3 * u), np.sin(5 * u * v + 4 * v)], -1)


def face_ids(scene, values, double_sided=True):
    """(H, W) int: the nearest triangle at each pixel (z-buffer, both orientations), -1 none."""
    n_faces = len(scene.model.faces)
    settings = scene.settings.replace(sigma=1e-9, gamma=1e-4, color_agg="hard", alpha_agg="hard",
                                      double_sided=double_sided)
    ids = np.zeros((n_faces, 1, 1, 3))
    ids[:, 0, 0, 0] = np.arange(1, n_faces + 1)
    world, _ = scene.geometry(values)
    out = Renderer(settings, shading="none").forward(world, scene.model.faces, scene.camera(values["focal"][0]),
                                                      face_textures=ids)
    return np.rint(out.rgb[0][..., 0]).astype(int) - 1


def front_facing(scene, values) -> np.ndarray:
    """(F,) bool: triangles counter-clockwise on screen (pixels: y down, so negative area)."""
    world, _ = scene.geometry(values)
    p, _ = scene.camera(values["focal"][0]).project_pixels(world)
    a, b, c = (p[scene.model.faces[:, k]] for k in range(3))
    return ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])) < 0


def outline(scene, values, erode=1) -> np.ndarray:
    """(H, W) bool: inside the face's outline, eroded by ``erode`` px: the fitted landmarks'
    jaw-and-brows polygon, within the filled silhouette of the mesh drawn with both
    orientations (where the polygon's chords cut past the mesh's open jaw border, the pixels
    beyond it are the photo's, not a crack)."""
    from scipy.ndimage import binary_erosion, binary_fill_holes
    from skimage.draw import polygon

    world, _ = scene.geometry(values)
    points, _ = scene.camera(values["focal"][0]).project_pixels(scene.model.landmarks(world)[0])
    pts = points[list(ibug68.FACE_OUTLINE)]
    inside = np.zeros(scene.image_size, bool)
    inside[polygon(pts[:, 1], pts[:, 0], inside.shape)] = True
    inside &= binary_fill_holes(face_ids(scene, values) >= 0)
    return binary_erosion(inside, iterations=erode)


# ---------------------------------------------------------------------------------------------
# clean pictures
# ---------------------------------------------------------------------------------------------

def assert_clean(scene, values):
    """No background and no back face at any pixel inside the face outline of the report's
    render (every sample of the supersampled picture covered)."""
    inside = outline(scene, values, erode=report.SUPERSAMPLE)
    assert inside.sum() > 1000
    _, alpha = report.draw(scene, values, 1, openings=False)
    ids = face_ids(scene, values)
    assert (alpha[inside] == 1.0).all(), f"{int((alpha[inside] < 1).sum())} background pixels"
    assert (ids[inside] >= 0).all()
    back = ~front_facing(scene, values)[ids[inside]]
    assert not back.any(), f"{int(back.sum())} pixels show a back face"


@pytest.mark.parametrize("seed, yaw", [(0, None), (3, 25.0), (7, -30.0)])
def test_demo_face_renders_without_background_or_back_faces_inside_its_outline(demo, seed, yaw):
    values = truth(demo, seed, yaw)
    values["exp"] = np.clip(values["exp"] * 1.5, -3, 3)              # strong expressions fold the lips
    scene = face.FaceScene(demo, (SIZE * report.SUPERSAMPLE,) * 2, alpha_agg="hard",
                           depth_range=face.depth_range(values["translation"]))
    values = dict(values, focal=values["focal"] * report.SUPERSAMPLE)
    assert_clean(scene, values)


def test_the_check_finds_a_hole_and_back_faces(demo):
    """The clean-picture check fails on a mesh with triangles removed or flipped."""
    values = truth(demo, 0, 0.0)
    scene = face.FaceScene(demo, (SIZE,) * 2, alpha_agg="hard", depth_range=face.depth_range(values["translation"]))
    centre = np.argmin(np.linalg.norm(scene.model.mean_shape - [0.03, -0.04, 0.0], axis=1))
    near = np.linalg.norm(scene.model.mean_shape[demo.faces].mean(1) - scene.model.mean_shape[centre], axis=1) < 0.01
    for faces in (demo.faces[~near], np.where(near[:, None], demo.faces[:, ::-1], demo.faces)):
        model = demo.__class__(**{**demo._fields(), "faces": faces, "landmark_faces": None, "landmark_bary": None,
                                     "dense_faces": None, "dense_bary": None, "dense_use": None})
        model.landmarks = demo.landmarks                                # the outline of the intact face
        broken = face.FaceScene(model, (SIZE,) * 2, alpha_agg="hard", depth_range=face.depth_range(values["translation"]))
        with pytest.raises(AssertionError):
            assert_clean(broken, values)


def test_openings_show_the_photo_through_eyes_and_mouth(demo):
    values = truth(demo, 1, 0.0)
    values["exp"][:] = 0.0
    values["exp"][0] = 2.5                                             # jaw open
    scene = face.FaceScene(demo, (SIZE,) * 2, alpha_agg="hard", depth_range=face.depth_range(values["translation"]))
    holes = report.opening_mask(scene, values)
    _, alpha = report.draw(scene, values, 1)
    _, covered = report.draw(scene, values, 1, openings=False)
    assert holes.sum() > 50
    assert (alpha[holes] == 0).all() and (covered[holes] == 1).all()
    assert (alpha[~holes] == covered[~holes]).all()


# ---------------------------------------------------------------------------------------------
# uv layout
# ---------------------------------------------------------------------------------------------

def test_layout_interpolates_the_uvs_back_to_each_texel_centre(layout):
    s = layout.size
    rows, cols = np.nonzero(layout.covered)
    uv = layout.interpolate(layout.uvs)[rows, cols]
    np.testing.assert_allclose(uv[:, 0], (cols + 0.5) / s, atol=1e-6)
    np.testing.assert_allclose(uv[:, 1], 1.0 - (rows + 0.5) / s, atol=1e-6)
    np.testing.assert_allclose(layout.bary[layout.covered].sum(-1), 1.0, atol=1e-9)
    assert (layout.bary[layout.covered] >= -1e-9).all()
    assert 0.5 < layout.covered.mean() < 0.8
    assert (layout.uvs >= ft.UV_MARGIN - 1e-9).all() and (layout.uvs <= 1 - ft.UV_MARGIN + 1e-9).all()


def test_mirror_image_of_the_demo_face_is_the_flipped_texture(demo, layout):
    from scipy.spatial import cKDTree

    mean = demo.mean_shape
    _, mirror = cKDTree(mean).query(mean * [-1.0, 1.0, 1.0])
    # the mirror table is the nearest vertex (up to 0.76 mm off): within 2 texels of 512
    np.testing.assert_allclose(layout.uvs[mirror, 0], 1.0 - layout.uvs[:, 0], atol=4e-3)
    np.testing.assert_allclose(layout.uvs[mirror, 1], layout.uvs[:, 1], atol=4e-3)


# ---------------------------------------------------------------------------------------------
# un-lighting and fill
# ---------------------------------------------------------------------------------------------

def photo_with_texture(model, values, texture, layout, size=SIZE):
    """(the FaceFit stand-in, photo (size, size, 3)): the face drawn with ``texture`` (S, S, 3)
    under its SH light (over a green background), the focal length scaled to the size."""
    values = dict(values, focal=values["focal"] * size / SIZE)
    fit = synthetic_fit(model, values, size)
    scene = face.FaceScene(model, (size, size), alpha_agg="hard", depth_range=face.depth_range(values["translation"]))
    rgb, alpha = ft.render_textured(scene, values, SimpleNamespace(albedo=texture, layout=layout), 1e-7, 1e-4)
    return fit, rgb + (1.0 - alpha[..., None]) * np.array([0.1, 0.5, 0.2])


@pytest.mark.parametrize("seed, yaw", [(2, None), (4, 20.0)])
def test_unlit_texture_matches_the_known_albedo_where_seen(demo, layout, seed, yaw):
    """A face rendered by softras-cl with a known smooth texture under a known SH light: where
    the estimate is confident (>= 0.5), photo / shading recovers the texture in linear RGB with
    a median error under 0.01 and 99% of texels within 0.03 (the rest: texels read between
    photo pixels across a crease of the shading, e.g. the eyelids, and texels whose uv triangle
    overlaps another's, around the lip slit and nostrils)."""
    values = truth(demo, seed, yaw)
    known = smooth_texture(layout.size)
    fit, photo = photo_with_texture(demo, values, known, layout, size=320)   # ~ a texel a pixel
    tex = ft.estimate_texture(fit, photo, layout=layout)
    sure = tex.confidence >= 0.5
    assert sure.sum() > 0.3 * layout.covered.sum()
    for estimate in (tex.observed, tex.albedo):
        error = np.abs(estimate - known)[sure].max(-1)
        assert np.median(error) < 0.01 and np.percentile(error, 99) < 0.03, np.percentile(error, [50, 99, 100])
    assert not tex.seen[~layout.covered].any() and (tex.confidence[~tex.seen] == 0).all()


def test_unlighting_divides_by_the_light(demo, layout):
    """The same face under a light twice as bright gives the same texture (to 1e-6 where seen),
    whereas a photo with a wrong light would not."""
    values = truth(demo, 2)
    known = smooth_texture(layout.size) * 0.5
    fit, photo = photo_with_texture(demo, values, known, layout)
    brighter = dict(values, sh=2.0 * values["sh"])
    fit2, photo2 = photo_with_texture(demo, brighter, known, layout)
    a = ft.estimate_texture(fit, photo, layout=layout)
    b = ft.estimate_texture(fit2, photo2, layout=layout)
    seen = a.seen & b.seen
    np.testing.assert_allclose(a.observed[seen], b.observed[seen], atol=1e-6)
    wrong = ft.estimate_texture(fit, photo2, layout=layout)
    assert np.median(np.abs(wrong.observed[seen] - a.observed[seen])) > 0.1


def test_blend_uses_the_mirror_texel_then_the_model():
    rng = np.random.default_rng(0)
    observed, model = rng.random((8, 8, 3)), rng.random((8, 8, 3))
    weight = np.zeros((8, 8))
    weight[:, :3] = 1.0                   # left seen, right (its mirror) not, middle neither
    out = ft.blend_sources(observed, weight, model)
    np.testing.assert_allclose(out[:, :3], observed[:, :3])
    np.testing.assert_allclose(out[:, 5:], observed[:, 2::-1])
    np.testing.assert_allclose(out[:, 3:5], model[:, 3:5])
    weight[:, 5:] = 0.5                   # half seen: half its own, half the mirror's
    out = ft.blend_sources(observed, weight, model)
    np.testing.assert_allclose(out[:, 5:], 0.5 * observed[:, 5:] + 0.5 * observed[:, 2::-1])


def test_side_turned_away_is_filled_from_its_mirror_image(demo, layout):
    """A face turned 50 degrees hides one cheek; with a left-right symmetric known texture the
    hidden side's texels (unseen, their mirror seen with full confidence) come back from the
    mirror: median error under 0.01, 95% within 0.03 (the mirror texel is the flip u -> 1 - u,
    up to 2 texels off the mirrored vertex)."""
    values = truth(demo, 6, 50.0)
    known = smooth_texture(layout.size, symmetric=True)
    fit, photo = photo_with_texture(demo, values, known, layout)
    tex = ft.estimate_texture(fit, photo, layout=layout)
    mirrored_sure = (tex.confidence[:, ::-1] >= 0.3) & ~tex.seen & layout.covered
    assert mirrored_sure.sum() > 0.05 * layout.covered.sum()
    error = np.abs(tex.albedo - known)[mirrored_sure].max(-1)
    assert np.median(error) < 0.01 and np.percentile(error, 95) < 0.03, np.percentile(error, [50, 95, 99, 100])
    neither = layout.covered & ~tex.seen & ~tex.seen[:, ::-1]
    np.testing.assert_allclose(tex.albedo[neither], np.clip(tex.model[neither], 0, 1), atol=1e-9)


# ---------------------------------------------------------------------------------------------
# textured OBJ
# ---------------------------------------------------------------------------------------------

def test_textured_obj_round_trips_and_renders_the_same(demo, layout, tmp_path):
    from softras_cl.io.meshes import load_mesh

    values = truth(demo, 2)
    known = smooth_texture(layout.size)
    shape = demo.shape(values["id"], values["exp"])[0]
    report.save_textured_obj(tmp_path / "face_textured.obj", shape, demo.faces, layout.uvs, known)
    assert {p.name for p in tmp_path.iterdir()} == {"face_textured.obj", "face_textured.mtl", "face_textured.png"}
    mesh = load_mesh(tmp_path / "face_textured.obj")
    np.testing.assert_allclose(mesh.vertices, shape, atol=1e-7)
    np.testing.assert_array_equal(mesh.faces, demo.faces)
    np.testing.assert_allclose(mesh.uvs, layout.uvs, atol=1e-6)
    assert mesh.texture.shape == known.shape
    np.testing.assert_allclose(mesh.texture, known, atol=0.01)     # 8-bit sRGB steps
    scene = face.FaceScene(demo, (SIZE, SIZE), alpha_agg="hard", depth_range=face.depth_range(values["translation"]))
    ours = ft.render_textured(scene, values, SimpleNamespace(albedo=known, layout=layout), 1e-7, 1e-4)[0]
    theirs = ft.render_textured(scene, values, SimpleNamespace(albedo=mesh.texture, layout=SimpleNamespace(uvs=mesh.uvs)),
                                1e-7, 1e-4)[0]
    np.testing.assert_allclose(theirs, ours, atol=0.02)


@pytest.mark.parametrize("textured", [False, True])
def test_face_drawn_in_its_window_equals_the_whole_image_drawn(demo, layout, textured):
    """draw renders only the window around the face (sigma rescaled to the window's NDC
    units): the same picture as rendering the whole image, zeros outside; render_over is the
    photo outside the window."""
    values = truth(demo, 2, 15.0)
    fit = synthetic_fit(demo, values)
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.1, 0.9, (200, 260, 3))
    texture = ft.estimate_texture(fit, photo, layout=layout) if textured else None
    scene, sampled = report._sampled(fit, photo.shape[:2])
    k = report.SUPERSAMPLE
    rows, cols = report.face_window(scene, sampled, k)
    assert 0 < rows.stop - rows.start < 200 and 0 < cols.stop - cols.start < 260
    whole = report._draw_all(scene, sampled, k, texture, True, report.SHARP)
    drawn = report.draw(scene, sampled, k, texture)
    assert whole[1].sum() > 1000
    for a, b in zip(drawn, whole):
        assert np.abs(a - b).max() < 1e-9
    over = report.render_over(fit, photo, texture=texture)
    assert np.abs(over - report.composite(whole, photo)).max() < 1e-9
    outside = np.ones(photo.shape[:2], bool)
    outside[rows, cols] = False
    assert (over[outside] == photo[outside]).all()
