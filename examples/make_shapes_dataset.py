#!/usr/bin/env python
"""A procedural shape data set for single-view reconstruction, rendered by softras-cl.

    python examples/make_shapes_dataset.py --out out/single_view          # the default set
    python examples/make_shapes_dataset.py --train 6 --test 2 --views 4 --size 32   # tiny

Four categories of closed meshes in one canonical frame (y up), each a primitive under random
non-rigid deformations (anisotropic scale, taper, bend, twist, a smooth low-frequency ripple),
centred and scaled to a bounding-sphere radius in [0.5, 0.8]:

    box        trimesh box, subdivided
    cylinder   trimesh cylinder (axis y), subdivided
    ellipsoid  icosphere
    cone       trimesh cone (axis y), subdivided

Every shape is seen from `views` random look-at cameras (azimuth uniform, elevation 10-40 deg,
distance 3.2, fov 30 deg): a shaded input image (Lambert, grey albedo, black background) and a
hard silhouette, both rendered by softras-cl. Ground-truth occupancy on a 32^3 grid over
[-1, 1]^3 comes from `voxelize` (winding numbers along +z rays, see there). Everything is
deterministic from the seed; `load_or_make` caches the set as one .npz under the output folder,
named by its parameters.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from pathlib import Path

import numpy as np
import trimesh

from softras_cl import RasterSettings
from softras_cl.io.outputs import atomic_path
from softras_cl.scene.camera import Camera
from softras_cl.scene.meshes import icosphere
from softras_cl.scene.renderer import Renderer

CATEGORIES = ("box", "cylinder", "ellipsoid", "cone")
CAMERA_DISTANCE = 3.2
FOV_DEG = 30.0
GRID = 32            # voxel grid resolution over [-1, 1]^3 (the paper's 32^3)
GRID_EXTENT = 1.0


# ---------------------------------------------------------------------------------------------
# shapes
# ---------------------------------------------------------------------------------------------

def _y_up(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Rotate a z-axis primitive so that its axis is y (keeps the winding)."""
    mesh.apply_transform(trimesh.transformations.rotation_matrix(-math.pi / 2, [1, 0, 0]))
    return mesh


def primitive(category: str, rng: np.random.Generator) -> trimesh.Trimesh:
    """A closed, outward-wound primitive of `category` with random proportions, fine enough
    (edges <= 0.08) for smooth deformations."""
    if category == "box":
        mesh = trimesh.creation.box(extents=rng.uniform(0.6, 1.4, 3))
    elif category == "cylinder":
        mesh = _y_up(trimesh.creation.cylinder(radius=rng.uniform(0.3, 0.6),
                                               height=rng.uniform(0.6, 1.6), sections=32))
    elif category == "ellipsoid":
        v, f = icosphere(3, 1.0)
        mesh = trimesh.Trimesh(v * rng.uniform(0.4, 0.8, 3), f, process=False)
    elif category == "cone":
        mesh = _y_up(trimesh.creation.cone(radius=rng.uniform(0.35, 0.7),
                                           height=rng.uniform(0.8, 1.6), sections=32))
    else:
        raise ValueError(f"category must be one of {CATEGORIES}, got {category!r}")
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=0.08)
    return trimesh.Trimesh(v, f, process=True)


def deform(vertices: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Random smooth non-rigid deformation of (V, 3) float64 vertices (y up): taper, bend,
    twist about y, a low-frequency ripple along a random direction. Mild enough to keep the
    primitives free of self-intersections. Returns (V, 3) float64."""
    v = np.asarray(vertices, np.float64).copy()
    height = max(np.ptp(v[:, 1]), 1e-6)
    y = (v[:, 1] - v[:, 1].mean()) / height                        # about [-0.5, 0.5]
    v[:, [0, 2]] *= (1.0 + rng.uniform(-0.5, 0.5) * y)[:, None]     # taper
    v[:, 0] += rng.uniform(-0.5, 0.5) * height * y ** 2            # bend in x
    v[:, 2] += rng.uniform(-0.3, 0.3) * height * y ** 2            # bend in z
    angle = rng.uniform(-0.6, 0.6) * y                             # twist
    c, s = np.cos(angle), np.sin(angle)
    v[:, 0], v[:, 2] = c * v[:, 0] - s * v[:, 2], s * v[:, 0] + c * v[:, 2]
    k = rng.normal(size=3)
    k *= rng.uniform(2.0, 4.0) / np.linalg.norm(k)
    v += rng.uniform(0.0, 0.04) * np.sin(v @ k + rng.uniform(0, 2 * np.pi))[:, None] * k / np.linalg.norm(k)
    return v


def make_shape(category: str, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One shape: (vertices (V, 3) float64, faces (F, 3) int64), centred on its bounding box,
    bounding-sphere radius uniform in [0.5, 0.8], the scale anisotropic within that."""
    mesh = primitive(category, rng)
    v = deform(mesh.vertices * rng.uniform(0.8, 1.25, 3), rng)
    v -= 0.5 * (v.min(0) + v.max(0))
    v *= rng.uniform(0.5, 0.8) / np.linalg.norm(v, axis=1).max()
    return v, np.asarray(mesh.faces, np.int64)


# ---------------------------------------------------------------------------------------------
# cameras and rendering
# ---------------------------------------------------------------------------------------------

def random_eyes(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float64 camera positions at CAMERA_DISTANCE: azimuth uniform, elevation 10-40 deg."""
    azim = rng.uniform(0.0, 2.0 * np.pi, n)
    elev = np.radians(rng.uniform(10.0, 40.0, n))
    return CAMERA_DISTANCE * np.stack([np.cos(elev) * np.sin(azim), np.sin(elev),
                                       np.cos(elev) * np.cos(azim)], 1)


def cameras(eyes: np.ndarray, size: int) -> list[Camera]:
    """Look-at cameras (towards the origin, y up) at `eyes` (N, 3), square images of `size`."""
    return [Camera.look_at(tuple(e), (0.0, 0.0, 0.0), fov_deg=FOV_DEG, image_size=(size, size))
            for e in np.asarray(eyes, np.float64)]


def silhouette_renderer(size: int) -> Renderer:
    """Hard binary silhouettes (both face orientations): alpha (B, size, size)."""
    return Renderer(RasterSettings(image_size=(size, size), outputs=("alpha",), alpha_agg="hard",
                                   double_sided=True), shading="none")


def shaded_renderer(size: int) -> Renderer:
    """Sharp Lambert-shaded images (the paper's light: ambient 0.5, directional 0.5 from +y):
    rgb (B, size, size, 3) on black."""
    return Renderer(RasterSettings(image_size=(size, size), sigma=1e-6, gamma=1e-5,
                                   outputs=("rgb", "alpha")), shading="vertex")


def render_views(vertices, faces, eyes, size: int, renderers=None) -> tuple[np.ndarray, np.ndarray]:
    """Input images (N, size, size, 3) uint8 (linear grey-albedo Lambert shading, 0-255) and
    hard silhouettes (N, size, size) bool of one mesh from the cameras at `eyes` (N, 3)."""
    shaded, hard = renderers or (shaded_renderer(size), silhouette_renderer(size))
    cams = cameras(eyes, size)
    v = np.asarray(vertices, np.float64)
    rgb = shaded.forward(v, faces, cams, albedo=np.full((len(v), 3), 0.8)).rgb
    alpha = hard.forward(v, faces, cams).alpha
    return np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8), alpha > 0.5


# ---------------------------------------------------------------------------------------------
# voxels
# ---------------------------------------------------------------------------------------------

def grid_centres(n: int = GRID, extent: float = GRID_EXTENT) -> np.ndarray:
    """(n,) float64 cell centres of a regular grid over [-extent, extent]."""
    return -extent + (np.arange(n) + 0.5) * (2.0 * extent / n)


def voxelize(vertices, faces, n: int = GRID, extent: float = GRID_EXTENT) -> np.ndarray:
    """Occupancy (n, n, n) bool, indexed [x, y, z], of the cell centres of a grid over
    [-extent, extent]^3 inside a closed triangle mesh: vertices (V, 3) float, faces (F, 3) int.

    For every (x, y) column a ray goes up +z; each face it crosses adds the sign of the face
    normal's z (+1 leaving an outward-wound solid, -1 entering), so the sum over crossings above
    a centre is its winding number: a cell is inside when |winding| >= 1. This needs a closed
    mesh (watertight), but not a consistently outward winding as a whole (an inside-out mesh
    gives -1) and tolerates self-intersections (overlaps count once). Columns are moved by
    ~1e-6 cells so that rays miss edges and vertices lying exactly on grid lines."""
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]      # (F, 3, 3)
    centres = grid_centres(n, extent)
    h = 2.0 * extent / n
    shift = np.array([1.1e-6, 1.7e-6]) * h
    counts = np.zeros((n, n, n + 1), np.int64)                     # [x, y, centres below]
    for f, ix, iy in _face_columns(tri, centres[0] + shift, h, n):
        _add_crossings(tri[f], centres[ix] + shift[0], centres[iy] + shift[1], centres, h,
                       counts, ix, iy)
    winding = np.cumsum(counts[..., ::-1], axis=-1)[..., ::-1][..., 1:]   # crossings above
    return np.abs(winding) >= 1


def _face_columns(tri, first, h, n):
    """Yield (face indices, column x indices, column y indices) (each (K,) int64) covering
    every grid column inside each face's xy bounding box, one offset in the box at a time."""
    lo = np.clip(np.ceil((tri[:, :, :2].min(1) - first) / h), 0, n).astype(np.int64)
    hi = np.clip(np.floor((tri[:, :, :2].max(1) - first) / h), -1, n - 1).astype(np.int64)
    span = hi - lo + 1                                               # (F, 2), <= 0: no column
    if not (span > 0).all(1).any():
        return
    for dx in range(int(span[:, 0].max())):
        for dy in range(int(span[:, 1].max())):
            f = np.nonzero((span[:, 0] > dx) & (span[:, 1] > dy))[0]
            yield f, lo[f, 0] + dx, lo[f, 1] + dy


def _add_crossings(tri, px, py, centres, h, counts, ix, iy) -> None:
    """For faces tri (K, 3, 3) and one ray each at (px, py) (K,): where the ray crosses the
    face, add the sign of its normal's z to counts[ix, iy, number of centres below]."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]                 # 2 * signed xy area = n_z
    dx, dy = px - tri[:, 0, 0], py - tri[:, 0, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (dx * e2[:, 1] - dy * e2[:, 0]) / det
        w = (e1[:, 0] * dy - e1[:, 1] * dx) / det
        hit = (np.abs(det) > 1e-14) & (u >= 0) & (w >= 0) & (u + w <= 1)
    z = tri[hit, 0, 2] + u[hit] * e1[hit, 2] + w[hit] * e2[hit, 2]
    below = np.clip(np.ceil((z - centres[0]) / h), 0, len(centres)).astype(np.int64)
    np.add.at(counts, (ix[hit], iy[hit], below), np.sign(det[hit]).astype(np.int64))


def voxel_iou(a: np.ndarray, b: np.ndarray) -> float:
    """IoU of two occupancy grids (same shape, bool); 1.0 when both are empty."""
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else 1.0


# ---------------------------------------------------------------------------------------------
# the data set
# ---------------------------------------------------------------------------------------------

def make_dataset(n_train: int, n_test: int, views: int, size: int, seed: int = 0,
                 progress: bool = False) -> dict:
    """The data set as a dict of numpy arrays, S = len(CATEGORIES) * (n_train + n_test) shapes:
    images (S, views, size, size, 3) uint8, masks (S, views, size, size) bool, eyes (S, views, 3)
    float64, voxels (S, GRID, GRID, GRID) bool, category (S,) int64 (index into CATEGORIES),
    split (S,) bool (True: held out), vertices (sum V, 3) float64 and faces (sum F, 3) int64 of
    all meshes concatenated, with vertex_offsets and face_offsets (S + 1,) int64."""
    rng = np.random.default_rng(seed)
    renderers = (shaded_renderer(size), silhouette_renderer(size))
    rows = []
    for k, category in enumerate(CATEGORIES):
        for i in range(n_train + n_test):
            v, f = make_shape(category, rng)
            eyes = random_eyes(views, rng)
            images, masks = render_views(v, f, eyes, size, renderers)
            rows.append((v, f, eyes, images, masks, voxelize(v, f), k, i >= n_train))
        if progress:
            print(f"  {category}: {n_train} train + {n_test} held-out shapes", flush=True)
    v, f, eyes, images, masks, voxels, cat, split = zip(*rows)
    return dict(images=np.stack(images), masks=np.stack(masks), eyes=np.stack(eyes),
                voxels=np.stack(voxels), category=np.array(cat, np.int64),
                split=np.array(split, bool), vertices=np.concatenate(v),
                faces=np.concatenate(f), vertex_offsets=np.cumsum([0] + [len(x) for x in v]),
                face_offsets=np.cumsum([0] + [len(x) for x in f]))


def mesh(data: dict, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Shape s of a data set: (vertices (V, 3) float64, faces (F, 3) int64)."""
    vo, fo = data["vertex_offsets"], data["face_offsets"]
    return data["vertices"][vo[s]:vo[s + 1]], data["faces"][fo[s]:fo[s + 1]]


def load_or_make(folder, n_train: int, n_test: int, views: int, size: int, seed: int = 0,
                 progress: bool = False) -> tuple[dict, Path]:
    """The data set cached in `folder` as shapes_<key>.npz (key: a hash of the parameters and
    the version of this recipe); made and written atomically when missing. Returns (data, path)."""
    params = dict(recipe=1, categories=CATEGORIES, n_train=n_train, n_test=n_test, views=views,
                  size=size, seed=seed, grid=GRID)
    key = hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest()[:12]
    path = Path(folder) / f"shapes_{key}.npz"
    if path.exists():
        with np.load(path) as z:
            return {k: z[k] for k in z.files}, path
    data = make_dataset(n_train, n_test, views, size, seed, progress)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **data)
    return data, path


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--out", default="out/single_view", help="folder of the cached .npz")
    p.add_argument("--train", type=int, default=200, help="training shapes per category")
    p.add_argument("--test", type=int, default=25, help="held-out shapes per category")
    p.add_argument("--views", type=int, default=12, help="random views per shape")
    p.add_argument("--size", type=int, default=64, help="image size in pixels (square)")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    data, path = load_or_make(a.out, a.train, a.test, a.views, a.size, a.seed, progress=True)
    print(f"{path}: {len(data['split'])} shapes, {a.views} views of {a.size}x{a.size}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
