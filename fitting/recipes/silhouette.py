"""Mesh fitting to multi-view silhouettes (paper sec. 4.1 as optimisation).

An icosphere template is deformed to match the silhouettes of a target seen by several cameras.
The deformed vertices are

    vertices = scale * template + offsets        (blocks "scale" (1,) and "offsets" (V, 3))

and the objective, minimised by :func:`fitting.solver.fit` under a sigma/gamma schedule, is

    w_iou  * sum over views of (1 - IoU_b) * H * W       (losses.silhouette_iou per view)
  + w_lap  * losses.laplacian(vertices, faces)
  + w_flat * losses.flatten(vertices, faces)

Only alpha is rendered (``outputs=("alpha",)``, occupancy aggregation, ``shading="none"``, no
colour input); dL/d alpha goes to ``Renderer.backward(grad_alpha=...)`` and the vertex gradient
to the blocks. The IoU term is multiplied by the pixel count of a view so that it is in "pixels"
(as fitting/rigid.py uses sums, not means): nlopt's L-BFGS sizes its first step from the
gradient, and a term of order 1 gives first steps far too small to move a vertex.

Defaults (tuned on 10 views of 64x64 and the 642-vertex icosphere; the IoU term grows with the
pixel count, the Laplacian's size depends on the template's resolution): DEFAULT_WEIGHTS, three
stages with sigma 1e-3, 1e-4, 1e-5 (gamma 1e-4) of 60 evaluations each, offsets scaled by 0.03 for the
optimiser, float64, double-sided faces (see :func:`silhouette_settings`), binary target masks
(see :func:`target_silhouettes`). Stronger regularisers than the IoU needs keep the hidden parts
of the surface (that no silhouette constrains) smooth, which is what the 3D metrics measure.

Metrics to a target mesh: :func:`chamfer_distance` (points sampled on both surfaces) and
:func:`volume_iou` (inside tests on a common grid, by ray parity; both meshes must be closed).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from softras_cl.scene.camera import Camera
from softras_cl.scene.meshes import icosphere
from softras_cl.scene.renderer import Renderer
from softras_cl.raster.settings import RasterSettings
from softras_cl.fitting import losses
from softras_cl.fitting.params import Block, ParamSet
from softras_cl.fitting.solver import Stage, fit

__all__ = ["orbit_cameras", "silhouette_settings", "target_silhouettes", "default_stages",
           "silhouette_objective", "deformed_vertices", "fit_to_silhouettes", "sample_surface",
           "chamfer_distance", "volume_iou", "DEFAULT_WEIGHTS"]

# Loss weights: the IoU term is in pixels (see the module docstring); the regularisers are in
# world units (laplacian: squared lengths; flatten: dimensionless per edge).
DEFAULT_WEIGHTS = {"iou": 1.0, "laplacian": 1.0e4, "flatten": 30.0}


# ---------------------------------------------------------------------------------------------
# scene
# ---------------------------------------------------------------------------------------------

def orbit_cameras(n_views: int = 10, size: int = 64, distance: float = 4.0, fov_deg: float = 35.0,
                  elevation_deg: float = 30.0) -> list[Camera]:
    """``n_views`` look-at cameras on a circle around the origin, alternately above and below
    the equator by ``elevation_deg`` (so the top and bottom are seen too), square images."""
    cams = []
    for k in range(int(n_views)):
        azim = 2.0 * math.pi * k / n_views
        elev = math.radians(elevation_deg) * (1.0 if k % 2 == 0 else -1.0)
        eye = distance * np.array([math.cos(elev) * math.sin(azim), math.sin(elev),
                                   math.cos(elev) * math.cos(azim)])
        cams.append(Camera.look_at(eye, (0.0, 0.0, 0.0), fov_deg=fov_deg, image_size=(size, size)))
    return cams


def silhouette_settings(size, sigma: float = 1e-5, gamma: float = 1e-4, dtype: str = "float64",
                        double_sided: bool = True, **changes) -> RasterSettings:
    """Alpha-only raster settings (occupancy aggregation) for an image of ``size`` (an int for a
    square image or (H, W)). float64 by default: float32 image noise stalls line searches.
    double_sided by default: with front faces only, a pixel on the edge between two faces gets
    alpha 1 - 0.5^2 = 0.75 at small sigma, and the IoU gradient of those seams crumples the
    mesh; the back faces behind fill them in (and a face flipped by a step still counts)."""
    hw = (int(size), int(size)) if np.ndim(size) == 0 else tuple(int(n) for n in size)
    return RasterSettings(image_size=hw, sigma=sigma, gamma=gamma, outputs=("alpha",),
                          alpha_agg="occupancy", dtype=dtype, double_sided=double_sided, **changes)


def _alpha_settings(settings: RasterSettings) -> RasterSettings:
    return settings.replace(outputs=("alpha",), alpha_agg="occupancy")


def target_silhouettes(vertices, faces, cameras: Sequence[Camera], settings: RasterSettings,
                       hard: bool = True) -> np.ndarray:
    """Silhouettes (B, H, W) float64 of the mesh seen by each camera (alpha only).

    hard=True (default): binary masks (``alpha_agg="hard"``, both face orientations), i.e. ideal
    observed silhouettes. hard=False: the soft occupancy alpha of ``settings`` as they are; note
    that at small sigma it dips to ~0.75 on pixels lying on edges between two faces, so the soft
    IoU of a soft image with itself is not 0."""
    s = settings.replace(outputs=("alpha",), alpha_agg="hard", double_sided=True) if hard \
        else _alpha_settings(settings)
    renderer = Renderer(s, shading="none")
    out = renderer.forward(np.asarray(vertices, np.float64), np.asarray(faces), list(cameras))
    return np.asarray(out.alpha, np.float64)


def default_stages(sigmas=(1e-3, 1e-4, 1e-5), iters=(60, 60, 60), gamma: float = 1e-4,
                   weights: dict | None = None, free=("scale", "offsets")) -> list[Stage]:
    """One stage per sigma (coarse to fine) with the same weights (DEFAULT_WEIGHTS by default)
    and free blocks; ``iters`` is the evaluation budget of each stage."""
    weights = dict(DEFAULT_WEIGHTS if weights is None else weights)
    if len(sigmas) != len(iters):
        raise ValueError(f"sigmas ({len(sigmas)}) and iters ({len(iters)}) differ in length")
    return [Stage(f"sigma{s:.0e}", tuple(free), dict(weights), sigma=float(s), gamma=float(gamma),
                  max_iters=int(n), ftol_rel=1e-9, xtol_rel=1e-10)
            for s, n in zip(sigmas, iters)]


# ---------------------------------------------------------------------------------------------
# objective
# ---------------------------------------------------------------------------------------------

def deformed_vertices(template_vertices: np.ndarray, values: dict) -> np.ndarray:
    """scale * template + offsets (missing blocks: scale 1, offsets 0)."""
    v = np.asarray(template_vertices, np.float64)
    scale = float(np.asarray(values.get("scale", 1.0)).reshape(-1)[0])
    return scale * v + values.get("offsets", 0.0)


def silhouette_objective(target_alphas, cameras: Sequence[Camera], template_vertices, faces,
                         settings: RasterSettings):
    """Objective for solver.fit over the blocks "offsets" (V, 3) and optionally "scale" (1,).

    Terms (weighted by ``stage.weights``, a missing weight is 0): "iou" (per-view IoU losses
    summed over views, times H * W), "laplacian" and "flatten" (of the deformed vertices). The
    stage's sigma and gamma are those of its renders (None: those of ``settings``)."""
    target = np.asarray(target_alphas, np.float64)
    cameras = list(cameras)
    if target.ndim != 3 or target.shape[0] != len(cameras):
        raise ValueError(f"target_alphas: expected shape ({len(cameras)}, H, W) for "
                         f"{len(cameras)} cameras, got {target.shape}")
    if target.shape[1:] != tuple(settings.image_size):
        raise ValueError(f"target_alphas: images {target.shape[1:]} do not match "
                         f"settings.image_size {tuple(settings.image_size)}")
    template = np.asarray(template_vertices, np.float64)
    faces = np.asarray(faces)
    topo = losses.mesh_topology(faces, len(template))
    renderer = Renderer(_alpha_settings(settings), shading="none")
    n_pix = float(target.shape[1] * target.shape[2])

    def objective(values: dict, stage: Stage):
        w = stage.weights
        verts = deformed_vertices(template, values)
        terms, g_v, weighted = {}, np.zeros_like(verts), {}
        w_iou = float(w.get("iou", 0.0))
        if w_iou > 0.0:
            out = renderer.forward(verts, faces, cameras, grads=("vertices",), sigma=stage.sigma, gamma=stage.gamma)
            alpha = out.alpha.astype(np.float64)
            value, g_alpha = 0.0, np.empty_like(alpha)
            for b in range(len(cameras)):
                v_b, g_b = losses.silhouette_iou(alpha[b], target[b])
                value += v_b
                g_alpha[b] = g_b["pred"]
            g_alpha *= w_iou * n_pix
            g_v += renderer.backward(out, grad_alpha=g_alpha.astype(out.alpha.dtype))["vertices"]
            weighted["iou"] = w_iou * n_pix * value
        mesh_weights = {k: float(w.get(k, 0.0)) for k in ("laplacian", "flatten")}
        if mesh_weights["laplacian"] > 0.0:
            terms["laplacian"] = losses.laplacian(verts, topo)
        if mesh_weights["flatten"] > 0.0:
            terms["flatten"] = losses.flatten(verts, topo)
        total, grads, reg = losses.weighted_sum(terms, mesh_weights)
        weighted.update(reg)
        if "vertices" in grads:
            g_v += grads["vertices"]
        total += weighted.get("iou", 0.0)
        block_grads = {"offsets": g_v}
        if "scale" in values:
            block_grads["scale"] = np.array([float((g_v * template).sum())])
        return float(total), block_grads, weighted

    return objective


def fit_to_silhouettes(target_alphas, cameras: Sequence[Camera], template=None, stages=None,
                       out_dir=None, progress: bool = False, settings: RasterSettings | None = None,
                       offset_scale: float = 0.03, fit_scale: bool = True,
                       max_offset: float = 1.0):
    """Deform ``template`` = (vertices (V, 3), faces (F, 3)) (default: an icosphere of 3
    subdivisions and radius 0.6) to match ``target_alphas`` (B, H, W) seen by ``cameras``.

    stages: list of solver Stages (default :func:`default_stages`); their ``free`` may name
    "offsets" and "scale". settings: base raster settings (default
    ``silhouette_settings(H x W)``, float64); each stage's sigma/gamma override them.
    offset_scale: the offsets block's optimiser scale (world units per unit of x).
    fit_scale: add the global "scale" block (a stage naming it must have it on).
    max_offset: bound on each offset coordinate (world units); scale is bounded to [0.25, 2].
    Returns ``(fitted vertices (V, 3), FitResult)``."""
    target = np.asarray(target_alphas, np.float64)
    if template is None:
        template = icosphere(3, 0.6)
    tv, tf = np.asarray(template[0], np.float64), np.asarray(template[1])
    if settings is None:
        settings = silhouette_settings(target.shape[1:])
    if stages is None:
        stages = default_stages(free=("scale", "offsets") if fit_scale else ("offsets",))
    # Bounds keep every line-search trial point in front of the cameras: |offset| <= max_offset
    # and scale in [0.25, 2] for a template of the scene's size.
    blocks = [Block("offsets", np.zeros_like(tv), lower=-max_offset, upper=max_offset,
                    scale=offset_scale)]
    if fit_scale:
        blocks.insert(0, Block("scale", np.ones(1), lower=0.25, upper=2.0, scale=0.1))
    params = ParamSet(blocks)
    objective = silhouette_objective(target, cameras, tv, tf, settings)
    result = fit(params, objective, stages, out_dir=out_dir, progress=progress)
    return deformed_vertices(tv, result.values), result


# ---------------------------------------------------------------------------------------------
# metrics
# ---------------------------------------------------------------------------------------------

def _trimesh(mesh):
    import trimesh
    if isinstance(mesh, trimesh.Trimesh):
        return mesh
    v, f = mesh
    return trimesh.Trimesh(vertices=np.asarray(v, np.float64), faces=np.asarray(f), process=False)


def sample_surface(mesh, count: int = 20000, seed: int = 0) -> np.ndarray:
    """(count, 3) points uniformly on the surface of ``mesh`` (a trimesh.Trimesh or a
    (vertices, faces) pair), with a fixed seed (trimesh.sample.sample_surface)."""
    import trimesh
    points, _ = trimesh.sample.sample_surface(_trimesh(mesh), int(count), seed=seed)
    return np.asarray(points, np.float64)


def chamfer_distance(a_points, b_points, count: int = 20000, seed: int = 0) -> float:
    """Symmetric Chamfer distance ``(mean_a d(a, B) + mean_b d(b, A)) / 2`` (plain distances,
    world units) between point sets (N, 3) and (M, 3); a mesh (trimesh.Trimesh or (vertices,
    faces)) given instead is sampled with :func:`sample_surface` (``count``, ``seed``)."""
    from scipy.spatial import cKDTree

    def points(x):
        if isinstance(x, np.ndarray) and x.ndim == 2 and x.shape[1] == 3:
            return np.asarray(x, np.float64)
        return sample_surface(x, count, seed)

    a, b = points(a_points), points(b_points)
    if len(a) == 0 or len(b) == 0:
        raise ValueError("chamfer_distance: empty point set")
    d_ab, _ = cKDTree(b).query(a)
    d_ba, _ = cKDTree(a).query(b)
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def _corners(mesh) -> np.ndarray:
    """The triangles of ``mesh`` (a trimesh.Trimesh or a (vertices, faces) pair) as (F, 3, 3)
    float64 corner positions."""
    v, f = (mesh.vertices, mesh.faces) if hasattr(mesh, "faces") else mesh
    return np.asarray(v, np.float64)[np.asarray(f)]


def _upward_crossings(corners: np.ndarray, xs, ys, zs, chunk: int = 64) -> np.ndarray:
    """(len(xs), len(ys), len(zs)) int: how many triangles (``corners`` (F, 3, 3)) a ray from
    each grid point (xs[i], ys[j], zs[k]) straight up (+z) crosses. A column through an edge or a
    corner of the triangles' xy projections counts it for one triangle only (the top-left rule
    on triangles turned counter-clockwise), so a closed surface is crossed an odd number of
    times from inside; triangles seen edge-on from above are skipped."""
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    seen = area != 0
    a, b, c, turn = a[seen], b[seen], c[seen], (area[seen] < 0)[:, None]
    b, c = np.where(turn, c, b), np.where(turn, b, c)
    px, py = (g.ravel() for g in np.meshgrid(xs, ys, indexing="ij"))
    # steps[p, k] - steps[p, k + 1]: the crossings above zs[k] of column p, summed below
    steps = np.zeros((len(px), len(zs) + 1), np.int64)
    for s in range(0, len(a), chunk):
        ta, tb, tc = a[s:s + chunk, None], b[s:s + chunk, None], c[s:s + chunk, None]
        weights, covered = [], True
        for u, v in ((tb, tc), (tc, ta), (ta, tb)):          # the edge facing each corner
            dx, dy = v[..., 0] - u[..., 0], v[..., 1] - u[..., 1]
            w = dx * (py - u[..., 1]) - dy * (px - u[..., 0])
            top_left = (dy < 0) | ((dy == 0) & (dx < 0))
            weights.append(w)
            covered = covered & ((w > 0) | ((w == 0) & top_left))
        t, col = np.nonzero(covered)
        w0, w1, w2 = (w[t, col] for w in weights)
        z = (w0 * ta[t, 0, 2] + w1 * tb[t, 0, 2] + w2 * tc[t, 0, 2]) / (w0 + w1 + w2)
        np.add.at(steps, (col, 0), 1)
        np.add.at(steps, (col, np.searchsorted(zs, z)), -1)   # grid points below z see it
    return np.cumsum(steps[:, :-1], axis=1).reshape(len(xs), len(ys), len(zs))


def volume_iou(mesh_a, mesh_b, resolution: int = 48, padding: float = 0.02) -> float:
    """Volume IoU of two closed meshes (trimesh.Trimesh or (vertices, faces)): inside tests of a
    ``resolution``^3 grid of cell centres spanning both meshes' joint bounding box (grown by
    ``padding`` of its size), a point being inside when a ray from it crosses the surface an odd
    number of times. 1 for identical solids. numpy only (the same answers as trimesh's
    ``contains`` on the example's and the tests' meshes, without its ray engines)."""
    a, b = _corners(mesh_a), _corners(mesh_b)
    both = np.concatenate([a.reshape(-1, 3), b.reshape(-1, 3)])
    lo, hi = both.min(0), both.max(0)
    pad = padding * (hi - lo).max()
    lo, hi = lo - pad, hi + pad
    n = int(resolution)
    axes = [lo[i] + (np.arange(n) + 0.5) * (hi[i] - lo[i]) / n for i in range(3)]
    in_a, in_b = (_upward_crossings(m, *axes) % 2 == 1 for m in (a, b))
    union = np.count_nonzero(in_a | in_b)
    return float(np.count_nonzero(in_a & in_b) / union) if union else 1.0
