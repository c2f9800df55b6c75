"""Contour landmarks that slide: the model point of an outline landmark is re-chosen on the
fitted mesh's occluding contour.

A photo's jaw line (iBUG points 0-16, and any other outline point) follows what is visible: on
the side of a face turned away from the camera it is the silhouette of the cheek, which moves
over the surface as the head turns, not a fixed point of the model. Each such landmark gets a
set of candidate vertices, computed once from the model's mean shape (:func:`jaw_candidates`):
the half of the face, in the frontal view, on the landmark's side of the face's centre (every
depth: from the front of the face round the cheek towards the ear, the underside of the chin
for the chin). At each evaluation (:meth:`ContourLandmarks.choose`):

- while the landmark's fixed point lies on a face turned towards the camera it stays the
  landmark (frontal faces, and the side of a face turned towards the camera, where the jaw's
  edge is visible);
- once that face is turned away, the landmark is the point of the occluding contour (the
  edges between a face turned towards the camera and one turned away, and the open border
  edges of a face turned towards it), on an edge between two of its candidates, whose
  projection lies nearest the image landmark; with no such edge it stays the fixed point.

The choice (which edge, and where along it) is piecewise smooth in the parameters; the
landmark's gradient flows through the two vertices of its edge (their dependence on shape,
expression and pose) with the position along the edge held, which is exact: at the nearest
point the loss does not change along the edge. A point on the edge rather than its nearer
vertex matters: the demo face's vertices lie 2-3 pixels apart along a 256-pixel photo's jaw.
The candidate sets are data (:class:`ContourLandmarks` takes any), so dense outline points
can use the same mechanism.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softras_cl.fitting.keypoints import ibug68

__all__ = ["ContourLandmarks", "ContourChoice", "jaw_candidates", "mesh_edges", "front_facing", "contour_edges"]


@dataclass(frozen=True)
class MeshEdges:
    """The mesh's edges: vertices (E, 2) int, faces (E, 2) int: the one or two faces of each
    edge, -1 for the missing second face of an open border edge."""
    vertices: np.ndarray
    faces: np.ndarray


def mesh_edges(faces) -> MeshEdges:
    """The edges of a triangle list faces (F, 3) int with the faces on either side."""
    faces = np.asarray(faces, np.int64)
    n = len(faces)
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(n), 3)
    key = np.sort(pairs, axis=1)
    unique, inverse, count = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    first = np.searchsorted(inverse[order], np.arange(len(unique)))
    edge_faces = np.full((len(unique), 2), -1, np.int64)
    edge_faces[:, 0] = owner[order[first]]
    two = count >= 2
    edge_faces[two, 1] = owner[order[first[two] + 1]]
    return MeshEdges(unique, edge_faces)


def front_facing(vertices, faces, eye) -> np.ndarray:
    """(F,) bool: faces (F, 3) of vertices (V, 3) whose outward normal (counter-clockwise seen
    from outside) points towards the camera centre ``eye`` (3,)."""
    # (3, F, 3): each corner's points contiguous; np.take is ~2.5x faster than vertices[faces]
    # on the demo face's 15k faces, with the same arithmetic per face
    corner = np.take(np.asarray(vertices, np.float64), np.asarray(faces).T, axis=0)
    normal = np.cross(corner[1] - corner[0], corner[2] - corner[0])
    centroid = (corner[0] + corner[1] + corner[2]) / 3.0
    return np.einsum("fc,fc->f", normal, np.asarray(eye, np.float64) - centroid) > 0


def contour_edges(front: np.ndarray, edges: MeshEdges) -> np.ndarray:
    """(E,) bool: the edges of the occluding contour: between a face turned towards the camera
    and one turned away, and open border edges of a face turned towards it. front (F,) bool
    from :func:`front_facing`."""
    a = front[edges.faces[:, 0]]
    border = edges.faces[:, 1] < 0
    b = np.where(border, False, front[edges.faces[:, 1]])
    return (a != b) | (border & a)


@dataclass(frozen=True)
class ContourChoice:
    """Where the sliding points are: edge (N,) int, an index into the model's MeshEdges (-1:
    the point stays the model's fixed landmark); t (N,) float64 in [0, 1], the position along
    that edge from its first vertex (0) to its second (1)."""
    edge: np.ndarray
    t: np.ndarray

    @property
    def slid(self) -> np.ndarray:
        """(N,) bool: the points that slid."""
        return self.edge >= 0


@dataclass(frozen=True)
class ContourLandmarks:
    """Landmarks that slide on the occluding contour, with their candidates.

    model: the FaceModel (its faces and its landmarks' faces); points (N,) int: which of the
    model's landmarks slide; candidates: N int arrays of vertex indices, one per point; edges:
    the model's MeshEdges; candidate_edges (N, E) bool: the edges with both vertices among a
    point's candidates.
    """
    model: object
    points: np.ndarray
    candidates: tuple
    edges: MeshEdges
    candidate_edges: np.ndarray

    @classmethod
    def of(cls, model, points, candidates) -> "ContourLandmarks":
        """ContourLandmarks of ``model`` for landmark indices points (N,) and N candidate
        vertex index arrays (checked: one non-empty set per point, indices in range)."""
        points = np.asarray(points, np.int64).reshape(-1)
        if len(candidates) != len(points):
            raise ValueError(f"candidates: expected one vertex set per point ({len(points)}), got {len(candidates)}")
        if points.size and (points.min() < 0 or points.max() >= model.n_landmarks):
            raise ValueError(f"points must index the model's {model.n_landmarks} landmarks, got {points.tolist()}")
        sets = tuple(np.asarray(c, np.int64).reshape(-1) for c in candidates)
        for i, c in enumerate(sets):
            if c.size == 0 or c.min() < 0 or c.max() >= model.n_vertices:
                raise ValueError(f"candidates[{i}] must be a non-empty set of vertex indices "
                                 f"below {model.n_vertices}")
        edges = mesh_edges(model.faces)
        within = np.array([np.isin(edges.vertices, c).all(axis=1) for c in sets]).reshape(len(sets), -1)
        return cls(model, points, sets, edges, within)

    def choose(self, world, project, targets) -> ContourChoice:
        """Where each point slides to: the point of a candidate contour edge whose projection
        lies nearest its image landmark; edge -1 where it stays the model's fixed landmark (its
        face turned towards the camera, or no candidate edge on the contour).

        world (V, 3) vertices in the camera's world frame, the camera centre at the origin;
        project: (M, 3) world points -> ((M, 2) pixels, (M,) depths along the optical axis),
        a pinhole camera; targets (L, 2) the image landmarks in those pixels (all L of the
        model's landmarks; the points' rows are used). A segment projects to a segment, so the
        nearest point is found in the image and mapped back to the edge with the depths: its
        projection is exactly that point, and the loss's derivative along the edge is zero
        there (unless at an end), so the choice adds nothing to the gradient.
        """
        world = np.asarray(world, np.float64)
        front = front_facing(world, self.model.faces, np.zeros(3))
        edge, t = np.full(len(self.points), -1, np.int64), np.zeros(len(self.points))
        turned = np.nonzero(~front[self.model.landmark_faces[self.points]])[0]
        on_contour = np.nonzero(contour_edges(front, self.edges))[0] if turned.size else turned
        if on_contour.size:
            pixels, depth = project(world[self.edges.vertices[on_contour].reshape(-1)])
            segments = (pixels[0::2], pixels[1::2], depth[0::2], depth[1::2])
            for i in turned:
                candidates = np.nonzero(self.candidate_edges[i, on_contour])[0]
                if candidates.size:
                    k, t[i] = _nearest_on_segments([part[candidates] for part in segments],
                                                   targets[self.points[i]])
                    edge[i] = on_contour[candidates[k]]
        return ContourChoice(edge, t)

    def points_3d(self, world, fixed, choice: ContourChoice) -> np.ndarray:
        """(L, 3): the model's fixed landmarks fixed (L, 3) with the sliding points' rows
        replaced by their points on the edges of world (V, 3) (choice from :meth:`choose`)."""
        out = np.array(fixed, np.float64)
        slid = choice.slid
        ends = self.edges.vertices[choice.edge[slid]]
        t = choice.t[slid, None]
        world = np.asarray(world, np.float64)
        out[self.points[slid]] = (1.0 - t) * world[ends[:, 0]] + t * world[ends[:, 1]]
        return out

    def points_3d_vjp(self, grad, choice: ContourChoice) -> tuple[np.ndarray, np.ndarray]:
        """grad (L, 3) = dL/d(points_3d) -> (the part for the fixed landmarks (L, 3): the slid
        rows zeroed, for the model's landmarks_vjp; the part for the world vertices (V, 3))."""
        grad = np.asarray(grad, np.float64)
        slid = choice.slid
        fixed = grad.copy()
        fixed[self.points[slid]] = 0.0
        ends = self.edges.vertices[choice.edge[slid]]
        t, g = choice.t[slid, None], grad[self.points[slid]]
        g_world = np.zeros((self.model.n_vertices, 3))
        np.add.at(g_world, ends[:, 0], (1.0 - t) * g)
        np.add.at(g_world, ends[:, 1], t * g)
        return fixed, g_world


def _nearest_on_segments(segments, target) -> tuple[int, float]:
    """(which of K edges, its t): the edge whose projection passes nearest target (2,), and
    where along it in 3D (t in [0, 1] from its first vertex). segments: the edges' first and
    second ends projected, (K, 2) pixels each, and their depths, (K,) each."""
    a, b, depth_a, depth_b = segments
    ab = b - a
    s = np.clip(np.einsum("kc,kc->k", target - a, ab) / np.maximum(np.einsum("kc,kc->k", ab, ab), 1e-300), 0, 1)
    k = int(np.argmin(np.sum((a + s[:, None] * ab - target) ** 2, axis=1)))
    # image fraction s -> 3D fraction t: the projection of (1 - t) A + t B lies at
    # s = t w_B / ((1 - t) w_A + t w_B) along the image segment (w the depths)
    w_a, w_b = depth_a[k], depth_b[k]
    return k, float(s[k] * w_a / (s[k] * w_a + (1.0 - s[k]) * w_b))


def jaw_candidates(model, points=ibug68.JAW) -> ContourLandmarks:
    """ContourLandmarks for the model's jaw-line landmarks ``points`` (iBUG 0-16 by default, in
    order along the jaw), candidates from the mean shape (see the module docstring): for each
    point with outward normal n of the jaw line in the frontal (x, y) view (perpendicular to
    the line through its neighbours), the vertices v with (v - c) . n >= 0, c the centroid of
    all the landmarks (x, y).

    Measured on the face bench's faces at 45-75 degrees of yaw (256 px), at the true
    parameters: the sliding points lie 0.24 px (mean over the jaw) from the silhouette
    landmarks (0.38 px at the nearest contour vertex instead of the nearest point of an
    edge), the fixed points 6.9 px; narrower sets (a band across the jaw line through the
    fixed point, 1-6 edge lengths wide, or the outer 65% of the half) missed the silhouette
    where the band's plane does not hold the line of sight: 7.9-4.7 px (nearest vertex)."""
    points = np.asarray(points, np.int64)
    fixed, _ = model.landmarks(model.mean_shape)
    xy, centre = fixed[points, :2], fixed[:, :2].mean(axis=0)
    candidates = []
    for i in range(len(points)):
        t = xy[min(i + 1, len(points) - 1)] - xy[max(i - 1, 0)]
        n = np.array([t[1], -t[0]])
        if np.dot(xy[i] - centre, n) < 0:
            n = -n
        candidates.append(np.nonzero((model.mean_shape[:, :2] - centre) @ n >= 0)[0])
    return ContourLandmarks.of(model, points, candidates)
