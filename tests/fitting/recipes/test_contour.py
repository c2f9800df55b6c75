"""Contour landmarks that slide (fitting.recipes.contour): mesh edges, the occluding contour, the
choice of a candidate and its gradient plumbing, on meshes with known answers."""
import math
import re

import numpy as np
import pytest

from softras_cl.fitting.recipes import contour
from softras_cl.fitting.models.face_model import FaceModel


def test_mesh_edges_give_each_edge_its_one_or_two_faces():
    faces = np.array([[0, 1, 2], [0, 2, 3]])            # a quad split along 0-2
    edges = contour.mesh_edges(faces)
    by_edge = {tuple(v): set(f) for v, f in zip(edges.vertices.tolist(), edges.faces.tolist())}
    assert by_edge == {(0, 1): {0, -1}, (1, 2): {0, -1}, (0, 2): {0, 1}, (2, 3): {1, -1}, (0, 3): {1, -1}}
    assert (edges.faces[:, 0] >= 0).all()           # an open border's missing face is the second


def test_front_facing_is_the_side_of_the_outward_normal_towards_the_eye():
    vertices = np.array([[0, 0, -1], [1, 0, -1], [0, 1, -1]], float)       # normal +z
    faces = np.array([[0, 1, 2], [0, 2, 1]])
    assert contour.front_facing(vertices, faces, np.zeros(3)).tolist() == [True, False]
    assert contour.front_facing(vertices, faces, np.array([0.0, 0.0, -3.0])).tolist() == [False, True]


@pytest.mark.parametrize("front, on", [
    ([True, False], {(0, 1), (1, 2), (0, 2)}),      # the fold 0-2 and face 0's open border
    ([False, True], {(0, 2), (2, 3), (0, 3)}),
    ([True, True], {(0, 1), (1, 2), (2, 3), (0, 3)}),
    ([False, False], set()),
])
def test_contour_is_where_faces_turn_away_and_the_open_border_of_faces_turned_towards(front, on):
    edges = contour.mesh_edges(np.array([[0, 1, 2], [0, 2, 3]]))
    found = contour.contour_edges(np.array(front), edges)
    assert {tuple(v) for v in edges.vertices[found].tolist()} == on


def _cylinder(n_around: int = 72, rings: int = 3, radius: float = 0.1):
    """A closed-around, open-ended vertical cylinder (faces counter-clockwise from outside) of
    ``rings`` vertex rings at y = -0.05, 0, 0.05: (vertices (V, 3), faces (F, 3), angles)."""
    angles = 2 * np.pi * np.arange(n_around) / n_around
    ys = np.linspace(-0.05, 0.05, rings)
    vertices = np.array([[radius * math.sin(a), y, radius * math.cos(a)] for y in ys for a in angles])
    faces = []
    for r in range(rings - 1):
        for k in range(n_around):
            a, b = r * n_around + k, r * n_around + (k + 1) % n_around
            faces += [[a, b, b + n_around], [a, b + n_around, a + n_around]]
    return vertices, np.array(faces), angles


def _cylinder_model(landmark_face: int):
    vertices, faces, angles = _cylinder()
    empty = np.zeros((0, len(vertices), 3))
    model = FaceModel(vertices, empty, [], empty, [], np.full(vertices.shape, 0.5), empty, [], faces,
                      [landmark_face], [[1 / 3, 1 / 3, 1 / 3]])
    return model, angles


def _pinhole(points):
    """A pinhole camera at the origin looking down -z, focal 100 px: (pixels, depths)."""
    return 100.0 * points[:, :2] / -points[:, 2:3], -points[:, 2]


def test_a_point_turned_away_slides_to_the_silhouette_of_a_cylinder():
    """Camera at the origin, cylinder (radius r) centred at distance d: the silhouette lies at
    the tangent angle acos(r / d) from the direction of the camera, and projects to
    x = f r sin / (d - r cos) pixels."""
    model, angles = _cylinder_model(landmark_face=2 * 36)       # middle of the back (angle pi)
    d, r = 0.5, 0.1
    world = model.mean_shape + [0.0, 0.0, -d]
    sliding = contour.ContourLandmarks.of(model, [0], [np.arange(len(world))])
    tangent = math.acos(r / d)
    silhouette_x = 100.0 * r * math.sin(tangent) / (d - r * math.cos(tangent))
    for side in (1.0, -1.0):
        target = np.array([[side * 60.0, 1.0]])
        choice = sliding.choose(world, _pinhole, target)
        fixed, _ = model.landmarks(world)
        point = sliding.points_3d(world, fixed, choice)[0]
        angle = math.atan2(abs(point[0]), point[2] + d)
        assert abs(angle - tangent) <= 2 * np.pi / 72          # on the silhouette's column of edges
        pixel, _ = _pinhole(point[None])
        assert pixel[0, 0] == pytest.approx(side * silhouette_x, abs=0.2)
        assert pixel[0, 1] == pytest.approx(1.0, abs=1e-9)     # the nearest point of a vertical edge
        assert 0.0 < choice.t[0] < 1.0


def test_a_point_turned_towards_the_camera_stays_the_fixed_point():
    model, _ = _cylinder_model(landmark_face=0)                  # front of the cylinder
    world = model.mean_shape + [0.0, 0.0, -0.5]
    sliding = contour.ContourLandmarks.of(model, [0], [np.arange(len(world))])
    choice = sliding.choose(world, _pinhole, np.zeros((1, 2)))
    assert choice.edge.tolist() == [-1]
    fixed, _ = model.landmarks(world)
    np.testing.assert_array_equal(sliding.points_3d(world, fixed, choice), fixed)


def test_points_3d_and_its_vjp_route_each_row_to_its_edge():
    model, _ = _cylinder_model(landmark_face=2 * 36)
    world = model.mean_shape + [0.0, 0.0, -0.5]
    sliding = contour.ContourLandmarks.of(model, [0], [np.arange(72, 144)])
    fixed, _ = model.landmarks(world)
    edge = 5
    a, b = sliding.edges.vertices[edge]
    choice = contour.ContourChoice(np.array([edge]), np.array([0.25]))
    np.testing.assert_allclose(sliding.points_3d(world, fixed, choice), [0.75 * world[a] + 0.25 * world[b]])
    grad = np.array([[1.0, 2.0, 3.0]])
    g_fixed, g_world = sliding.points_3d_vjp(grad, choice)
    assert not g_fixed.any()
    np.testing.assert_allclose(g_world[[a, b]], [[0.75, 1.5, 2.25], [0.25, 0.5, 0.75]])
    assert np.abs(g_world).sum() == pytest.approx(6.0)
    g_fixed, g_world = sliding.points_3d_vjp(grad, contour.ContourChoice(np.array([-1]), np.zeros(1)))
    assert g_fixed.tolist() == grad.tolist() and not g_world.any()


def test_the_point_on_an_edge_projects_to_the_nearest_image_point_under_perspective():
    """An edge slanted in depth: the chosen t maps to the image point nearest the target,
    not to the same fraction of the 3D edge."""
    model, _ = _cylinder_model(landmark_face=2 * 36)
    world = model.mean_shape + [0.0, 0.0, -0.5]
    world[[0, 1]] = [[0.0, 0.0, -0.3], [0.1, 0.0, -0.6]]         # an edge from near to far
    target = np.array([10.0, 3.0])
    (a, b), (depth_a, depth_b) = _pinhole(world[[0, 1]])
    k, t = contour._nearest_on_segments((a[None], b[None], depth_a[None], depth_b[None]), target)
    pixel, _ = _pinhole(((1 - t) * world[0] + t * world[1])[None])
    s = np.dot(target - a, b - a) / np.dot(b - a, b - a)
    np.testing.assert_allclose(pixel[0], a + s * (b - a), atol=1e-9)
    assert k == 0 and abs(t - s) > 0.05


@pytest.mark.parametrize("points, candidates, says", [
    ([0], [], "candidates: expected one vertex set per point (1), got 0"),
    ([3], [[0]], "points must index the model's 1 landmarks"),
    ([0], [[]], "candidates[0] must be a non-empty set of vertex indices below 216"),
    ([0], [[216]], "candidates[0] must be a non-empty set of vertex indices below 216"),
])
def test_candidate_sets_are_checked(points, candidates, says):
    model, _ = _cylinder_model(landmark_face=0)
    with pytest.raises(ValueError, match=re.escape(says)):
        contour.ContourLandmarks.of(model, points, candidates)


def test_jaw_candidates_hold_each_side_of_the_face(demo_face_model):
    sliding = contour.jaw_candidates(demo_face_model)
    assert sliding.points.tolist() == list(range(17))
    x = demo_face_model.mean_shape[:, 0]
    fixed, _ = demo_face_model.landmarks(demo_face_model.mean_shape)
    for j in (1, 3, 13, 15):       # the sides: (nearly all of) one half of the face each
        side = np.sign(fixed[j, 0])
        assert np.mean(np.sign(x[sliding.candidates[j]] - fixed[:, 0].mean()) == side) > 0.9
        assert np.isin(demo_face_model.faces[demo_face_model.landmark_faces[j]], sliding.candidates[j]).all()
    chin = sliding.candidates[8]                  # the chin: the lower part, both sides
    assert demo_face_model.mean_shape[chin, 1].max() <= fixed[:, 1].mean() + 1e-12
    assert x[chin].min() < 0 < x[chin].max()


def _whole_mesh_front_facing(vertices, faces, eye):
    """front_facing as it was first written (a (F, 3, 3) gather of the whole triangle list)."""
    tri = np.asarray(vertices, np.float64)[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centroid = (tri[:, 0] + tri[:, 1] + tri[:, 2]) / 3.0
    return np.einsum("fc,fc->f", normal, np.asarray(eye, np.float64) - centroid) > 0


def _whole_mesh_choice(sliding, world, project, targets):
    """The choice straight from its definition: every face's facing, every contour edge, then
    each turned point's nearest candidate."""
    front = _whole_mesh_front_facing(world, sliding.model.faces, np.zeros(3))
    on_contour = np.nonzero(contour.contour_edges(front, sliding.edges))[0]
    edge, t = np.full(len(sliding.points), -1), np.zeros(len(sliding.points))
    for i, point in enumerate(sliding.points):
        candidates = on_contour[sliding.candidate_edges[i, on_contour]]
        if front[sliding.model.landmark_faces[point]] or not candidates.size:
            continue
        pixels, depth = project(world[sliding.edges.vertices[candidates].reshape(-1)])
        k, t[i] = contour._nearest_on_segments((pixels[0::2], pixels[1::2], depth[0::2], depth[1::2]),
                                               targets[point])
        edge[i] = candidates[k]
    return front, edge, t


def test_the_choice_on_the_demo_face_is_the_whole_mesh_choice_bit_for_bit(demo_face_model):
    """Random shapes and poses (frontal, turned either way, seen from behind) with the fit's
    camera: the same faces turned, and the same edge and t for every point as the reference
    (front_facing and contour_edges over the whole mesh, one point at a time)."""
    from softras_cl.fitting.recipes.face import CAMERA_ROTATION
    from softras_cl.scene.camera import Camera
    from softras_cl.scene.rotation import axis_angle_to_matrix

    model = demo_face_model
    sliding = contour.jaw_candidates(model)
    camera = Camera.from_opencv([[700.0, 0.0, 128.0], [0.0, 700.0, 128.0], [0.0, 0.0, 1.0]], CAMERA_ROTATION,
                                np.zeros(3), (256, 256))
    project = lambda p: (camera.project_pixels(p)[0], -p[:, 2])
    rng = np.random.default_rng(7)
    slid = np.zeros(len(sliding.points), bool)
    for yaw in (0, 30, -30, 60, -60, 180):
        for _ in range(2):
            angles = np.radians([rng.uniform(-15, 15), yaw + rng.uniform(-5, 5), rng.uniform(-8, 8)])
            shape, _ = model.shape(rng.normal(size=model.n_id), rng.normal(size=model.n_exp))
            world = shape @ axis_angle_to_matrix(angles).T + [rng.uniform(-0.05, 0.05), 0.0, -0.6]
            fixed, _ = model.landmarks(world)
            targets = camera.project_pixels(fixed)[0] + rng.normal(scale=4.0, size=(len(fixed), 2))
            front, edge, t = _whole_mesh_choice(sliding, world, project, targets)
            np.testing.assert_array_equal(contour.front_facing(world, model.faces, np.zeros(3)), front)
            choice = sliding.choose(world, project, targets)
            np.testing.assert_array_equal(choice.edge, edge)
            assert choice.t.tobytes() == t.tobytes()
            slid |= choice.slid
            if yaw == 180:                          # from behind: the jaw's sides turned away
                assert not front[model.landmark_faces[sliding.points[[0, 1, 2, 3, 13, 14, 15, 16]]]].any()
    assert slid[:8].any() and slid[9:].any()          # points slid on both sides of the chin
