"""Render docs/demo_body.png: the demo body model's rest pose (part colours and joints, front and
side), a posed example, and +-2 std of the first shape components, with the project renderer.

    .venv/bin/python scripts/render_demo_body.py --out docs/demo_body.png
"""
from __future__ import annotations

import argparse
import colorsys
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from softras_cl.fitting.models.body_loaders import load_demo_body_model

from softras_cl.scene.camera import Camera
from softras_cl.scene.renderer import Renderer
from softras_cl.raster.settings import RasterSettings

SIZE = (480, 320)  # (H, W)


def part_colors(model) -> np.ndarray:
    """Per-vertex albedo (V, 3): one hue per body part."""
    n = len(model.part_names)
    palette = np.array([colorsys.hsv_to_rgb((k * 0.618) % 1.0, 0.55, 0.9) for k in range(n)])
    return palette[model.part_labels]


def render(model, state, albedo, eye) -> tuple[np.ndarray, np.ndarray]:
    """(image (H, W, 3) linear RGB on white, joint pixels (J, 2)) seen from ``eye``."""
    centre = np.array([0.0, 0.9, 0.0])
    cam = Camera.look_at(eye=centre + eye, target=centre, fov_deg=21, image_size=SIZE)
    renderer = Renderer(RasterSettings(image_size=SIZE, sigma=2e-6, background=(1, 1, 1)),
                        shading="vertex")
    out = renderer.forward(state.vertices, model.faces, cam, albedo=albedo)
    return out.rgb[0], cam.project_pixels(state.joints)[0]


def panels(model):
    """(title, state, view offset, draw joints) for each panel."""
    zero_pose, zero = np.zeros((model.n_joints - 1, 3)), np.zeros(3)
    idx = {n: i - 1 for i, n in enumerate(model.joint_names)}
    pose = zero_pose.copy()
    pose[idx["right_shoulder"]] = [0, 0, -1.9]   # right arm raised sideways (subject's right: -x)
    pose[idx["right_elbow"]] = [0, -0.8, 0]
    pose[idx["left_hip"]] = [-1.0, 0, 0]          # left thigh forward
    pose[idx["left_knee"]] = [1.4, 0, 0]          # left knee bent
    pose[idx["spine2"]] = [0, 0.3, 0]
    pose[idx["head"]] = [0.2, 0.4, 0]
    betas = np.zeros(model.n_betas)
    out = [("rest: parts, joints", model.forward(betas, zero_pose, zero, zero)[0], (0, 0, 5), True),
           ("rest, side", model.forward(betas, zero_pose, zero, zero)[0], (5, 0, 0), True),
           ("posed", model.forward(betas, pose, zero, zero)[0], (2.5, 0.5, 4.3), True)]
    for k in range(3):
        for s in (-2, 2):
            b = betas.copy()
            b[k] = s
            out.append((f"beta {k + 1} = {s:+d}", model.forward(b, zero_pose, zero, zero)[0],
                        (0, 0, 5), False))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("docs/demo_body.png"))
    args = ap.parse_args(argv)
    model = load_demo_body_model()
    albedo = part_colors(model)
    items = panels(model)
    fig, axes = plt.subplots(3, 3, figsize=(7.2, 10.5))
    for ax, (title, state, eye, joints) in zip(axes.ravel(), items):
        image, uv = render(model, state, albedo, np.array(eye, dtype=float))
        ax.imshow(np.clip(image, 0, 1) ** (1 / 2.2))
        if joints:
            ax.scatter(uv[:, 0], uv[:, 1], s=6, c="k")
            for j, p in enumerate(model.parents[1:], start=1):
                ax.plot(uv[[p, j], 0], uv[[p, j], 1], "k-", lw=0.6)
        ax.set_title(title, fontsize=10)
        ax.axis("off")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(args.out)


if __name__ == "__main__":
    main()
