"""Render the docs figures of the shipped demo face model with softras-cl's own renderer.

    python scripts/render_demo_face_docs.py [--model fitting/models/data/demo_face.npz]

writes docs/demo_face_landmarks.png (front and 3/4 view, Lambert shading, the 68 iBUG landmarks
numbered; a landmark hidden in a view is drawn hollow) and docs/demo_face_components.png (mean
and +-2 std of the first identity and expression components).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from softras_cl.scene.camera import Camera
from softras_cl.scene.renderer import Renderer
from softras_cl.raster.settings import RasterSettings
from softras_cl.scene.shading import LambertLight

ROOT = Path(__file__).resolve().parents[1]
LIGHT = LambertLight(ambient=0.35, directional=0.65, direction=(0.3, 0.5, 1.0))
FRONT, THREE_QUARTER = (0.0, 0.0, 0.6), (-0.42, 0.06, 0.42)


def render(verts, faces, albedo, eye, size):
    """(H, W, 3) linear RGB on white, (H, W) depth, and the camera of one view."""
    settings = RasterSettings(image_size=(size, size), sigma=1e-7, gamma=1e-5, near=0.05,
                              far=10.0, background=(1.0, 1.0, 1.0),
                              outputs=("rgb", "alpha", "depth"))
    cam = Camera.look_at(eye=eye, target=(0.0, -0.015, 0.0), fov_deg=28, image_size=(size, size))
    out = Renderer(settings, shading="vertex").forward(verts, faces, cam, albedo=albedo,
                                                       light=LIGHT)
    return out.rgb[0], out.depth[0], cam


def landmark_points(model) -> np.ndarray:
    tri = model["faces"][model["landmark_faces"]]
    return np.einsum("lk,lkd->ld", model["landmark_bary"], model["mean_shape"][tri])


def to_srgb8(rgb) -> Image.Image:
    c = np.clip(rgb, 0.0, 1.0)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return Image.fromarray(np.round(255 * s).astype(np.uint8))


def draw_landmarks(img: Image.Image, points, depth, cam) -> Image.Image:
    """Numbered dots at the landmarks; hollow where the surface in front hides them."""
    uv, _ = cam.project_pixels(points)
    z = (points @ cam.rotation_matrix().T + cam.translation)[:, 2]
    draw, font = ImageDraw.Draw(img), ImageFont.load_default()
    for k, ((u, v), zk) in enumerate(zip(uv, z)):
        iu, iv = round(u), round(v)
        hidden = zk > depth[iv, iu] + 2e-3
        draw.ellipse([u - 2.5, v - 2.5, u + 2.5, v + 2.5], outline=(200, 0, 0),
                     fill=None if hidden else (230, 20, 20))
        draw.text((u + 3, v - 11), str(k), fill=(0, 0, 160), font=font)
    return img


def landmarks_figure(model, path: Path, size=640) -> None:
    pts = landmark_points(model)
    panels = []
    for eye in (FRONT, THREE_QUARTER):
        rgb, depth, cam = render(model["mean_shape"], model["faces"], model["albedo_mean"], eye,
                                 size)
        panels.append(draw_landmarks(to_srgb8(rgb), pts, depth, cam))
    out = Image.new("RGB", (size * len(panels), size), "white")
    for i, p in enumerate(panels):
        out.paste(p, (i * size, 0))
    out.save(path)


def components_figure(model, path: Path, size=220, n_id=3, n_exp=4) -> None:
    """Rows: identity 1..n_id, expression 1..n_exp; columns: -2 std, mean, +2 std (grey)."""
    grey = np.full_like(model["mean_shape"], 0.7)
    rows = [("id", k) for k in range(n_id)] + [("exp", k) for k in range(n_exp)]
    grid = []
    for kind, k in rows:
        step = 2.0 * model[f"{kind}_std"][k] * model[f"{kind}_basis"][k]
        grid.append(np.concatenate([render(model["mean_shape"] + s * step, model["faces"], grey,
                                           FRONT, size)[0] for s in (-1, 0, 1)], 1))
    img = to_srgb8(np.concatenate(grid, 0))
    draw, font = ImageDraw.Draw(img), ImageFont.load_default()
    for r, (kind, k) in enumerate(rows):
        draw.text((4, r * size + 4), f"{kind} {k + 1}", fill=(0, 0, 0), font=font)
        for c, label in enumerate(("-2 std", "mean", "+2 std")):
            draw.text((c * size + size - 50, r * size + 4), label, fill=(0, 0, 0), font=font)
    img.save(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, default=ROOT / "fitting/models/data/demo_face.npz")
    ap.add_argument("--docs", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    with np.load(args.model) as f:
        model = {k: f[k].astype(np.float64) if f[k].dtype.kind == "f" else f[k] for k in f.files}
    landmarks_figure(model, args.docs / "demo_face_landmarks.png")
    components_figure(model, args.docs / "demo_face_components.png")


if __name__ == "__main__":
    main()
