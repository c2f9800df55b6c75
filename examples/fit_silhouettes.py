#!/usr/bin/env python
"""Fit an icosphere to the silhouettes of a target mesh seen by several cameras.

    python examples/fit_silhouettes.py                      # the bean, 10 views of 64x64
    python examples/fit_silhouettes.py --target capsule --views 12 --size 96 --out out/capsule

Builds a closed target mesh, renders its binary silhouettes from look-at cameras on an orbit
(alternately 30 degrees above and below the equator), deforms an icosphere (global scale plus
per-vertex offsets) by minimising the summed soft-IoU loss plus Laplacian and flatten
regularisers with nlopt L-BFGS under a sigma schedule (fitting/recipes/silhouette.py), then prints the
Chamfer distance and volume IoU to the target of the template before and of the fit after.

Writes to --out: fitted.ply (the fitted mesh), target.ply, comparison.png (target vs fitted
silhouettes for a few views, their difference, shaded renders, the loss curve), and the solver's
checkpoint.npz, history.json and loss_curve.png.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from softras_cl.fitting.recipes import silhouette as sil
from softras_cl.scene.meshes import icosphere
from softras_cl.io.meshes import save_mesh


def _rotation(axis, degrees) -> np.ndarray:
    from softras_cl.scene.rotation import axis_angle_to_matrix
    axis = np.asarray(axis, float)
    return axis_angle_to_matrix(axis / np.linalg.norm(axis) * math.radians(degrees))


def bean() -> tuple[np.ndarray, np.ndarray]:
    """A bent, lopsided ellipsoid, about 1.8 x 1.05 x 1.0 (the default).

    An icosphere of 4 subdivisions stretched along x, one end fatter than the other, its long
    axis bent down."""
    v, f = icosphere(4, 1.0)
    x, y, z = v.T
    fat = 1.0 + 0.2 * x
    return np.stack([0.9 * x, 0.5 * y * fat + 0.3 * x ** 2 - 0.15, 0.5 * z * fat], 1), f


def _trimesh_shape(mesh, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(mesh.vertices, float) @ rotation.T
    return v - 0.5 * (v.min(0) + v.max(0)), np.asarray(mesh.faces)


def capsule():
    """A capsule (radius 0.4, 1.8 long) tilted 30 degrees out of the horizontal."""
    import trimesh
    m = trimesh.creation.capsule(height=1.0, radius=0.4, count=[24, 24])
    return _trimesh_shape(m, _rotation((0, 0, 1), 30) @ _rotation((0, 1, 0), 90))


def box():
    """A 1.4 x 0.7 x 0.9 box turned 25 degrees about y and 15 degrees about x."""
    import trimesh
    m = trimesh.creation.box(extents=(1.4, 0.7, 0.9))
    return _trimesh_shape(m, _rotation((1, 0, 0), 15) @ _rotation((0, 1, 0), 25))


def cylinder():
    """A standing cylinder (radius 0.45, height 1.2) tipped 40 degrees about z."""
    import trimesh
    m = trimesh.creation.cylinder(radius=0.45, height=1.2, sections=48)
    return _trimesh_shape(m, _rotation((0, 0, 1), 40) @ _rotation((1, 0, 0), 90))


TARGETS = {"bean": bean, "capsule": capsule, "box": box, "cylinder": cylinder}


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description="Deform an icosphere to match the silhouettes of a target mesh (soft IoU + "
                    "Laplacian + flatten, nlopt L-BFGS with a sigma schedule); report Chamfer "
                    "distance and volume IoU before and after; save the fitted mesh and a "
                    "comparison image.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--target", choices=sorted(TARGETS), default="bean",
                   help="closed target shape. " + " ".join(
                       f"{k}: {fn.__doc__.splitlines()[0]}" for k, fn in sorted(TARGETS.items())))
    p.add_argument("--views", type=int, default=10, help="number of cameras on the orbit")
    p.add_argument("--size", type=int, default=64, help="silhouette image size in pixels (square)")
    p.add_argument("--out", type=Path, default=Path("out/fit_silhouettes"),
                   help="output folder (fitted.ply, target.ply, comparison.png, solver files)")
    p.add_argument("--subdivisions", type=int, default=3,
                   help="icosphere template subdivisions (3: 642 vertices)")
    p.add_argument("--radius", type=float, default=0.6, help="icosphere template radius")
    p.add_argument("--sigmas", type=float, nargs="+", default=[1e-3, 1e-4, 1e-5],
                   help="sigma of each stage, coarse to fine (squared NDC units)")
    p.add_argument("--iters", type=int, default=60,
                   help="objective evaluations per stage (line-search points included)")
    p.add_argument("--laplacian", type=float, default=sil.DEFAULT_WEIGHTS["laplacian"],
                   help="Laplacian regulariser weight")
    p.add_argument("--flatten", type=float, default=sil.DEFAULT_WEIGHTS["flatten"],
                   help="flatten regulariser weight")
    p.add_argument("--progress", action="store_true", help="show the solver's progress bar")
    args = p.parse_args(argv)
    for name in ("views", "size", "iters"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be >= 1")
    if args.subdivisions < 0 or args.radius <= 0 or min(args.sigmas) <= 0:
        p.error("--subdivisions must be >= 0, --radius and --sigmas > 0")
    return args


def comparison_image(path: Path, target_alpha, fitted_alpha, template_alpha, history_path: Path,
                     shaded: list, n_show: int = 4) -> None:
    """Rows: target, template (before), fitted silhouettes and the fit's error (red: missing,
    blue: extra) for n_show views; shaded target and fit; the loss curve."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n_views = len(target_alpha)
    show = np.unique(np.linspace(0, n_views - 1, min(n_show, n_views)).round().astype(int))
    cols = len(show)
    fig = plt.figure(figsize=(2.1 * max(cols, 4), 2.1 * 5 + 2.6))
    grid = fig.add_gridspec(6, max(cols, 4), height_ratios=[1, 1, 1, 1, 1, 1.25])
    rows = [("target", target_alpha), ("template (before)", template_alpha),
            ("fitted", fitted_alpha)]
    for r, (label, images) in enumerate(rows):
        for c, k in enumerate(show):
            ax = fig.add_subplot(grid[r, c])
            ax.imshow(images[k], cmap="gray", vmin=0, vmax=1, interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(label)
            if r == 0:
                ax.set_title(f"view {k}")
    for c, k in enumerate(show):
        t, f = target_alpha[k], np.clip(fitted_alpha[k], 0, 1)
        err = np.ones(t.shape + (3,))
        err[..., 1] -= np.abs(t - f)
        err[..., 0] -= np.clip(f - t, 0, 1)        # extra (fit outside the target): blue
        err[..., 2] -= np.clip(t - f, 0, 1)        # missing (target not covered): red
        ax = fig.add_subplot(grid[3, c])
        ax.imshow(np.clip(err, 0, 1), interpolation="nearest")
        ax.set_xticks([]), ax.set_yticks([])
        if c == 0:
            ax.set_ylabel("error")
    for c, (label, image) in enumerate(shaded[:max(cols, 4)]):
        ax = fig.add_subplot(grid[4, c])
        ax.imshow(image)
        ax.set_xticks([]), ax.set_yticks([])
        ax.set_title(label, fontsize=9)
    ax = fig.add_subplot(grid[5, :])
    hist = json.loads(history_path.read_text())["history"]
    loss = np.array([e["loss"] for e in hist])
    ax.semilogy(loss, lw=1, label="total")
    for term in sorted({t for e in hist for t in e["terms"]}):
        ax.semilogy([e["terms"].get(term, np.nan) for e in hist], lw=0.8, label=term)
    stages = [e["stage"] for e in hist]
    for i in range(1, len(stages)):
        if stages[i] != stages[i - 1]:
            ax.axvline(i, color="k", lw=0.6, ls="--")
    ax.set_xlabel("objective evaluation (stages: " + ", ".join(dict.fromkeys(stages)) + ")")
    ax.set_ylabel("loss")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def shaded_views(meshes: list, size: int = 160) -> list:
    """Face-shaded renders (sRGB uint8) of each (label, vertices, faces) from two directions."""
    from softras_cl.scene.camera import Camera
    from softras_cl.srgb import to_srgb
    from softras_cl.scene.renderer import Renderer
    from softras_cl.raster.settings import RasterSettings
    settings = RasterSettings(image_size=(size, size), sigma=1e-7, gamma=1e-5, double_sided=True,
                              outputs=("rgb", "alpha"), background=(1.0, 1.0, 1.0))
    renderer = Renderer(settings, shading="face")
    out = []
    for azim, elev in ((30.0, 20.0), (120.0, 35.0)):
        a, e = math.radians(azim), math.radians(elev)
        eye = 3.6 * np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])
        cam = Camera.look_at(eye, (0.0, 0.0, 0.0), fov_deg=35.0, image_size=(size, size))
        for label, v, f in meshes:
            rgb = renderer.forward(v, f, cam, albedo=np.full((len(v), 3), 0.7)).rgb[0]
            out.append((f"{label}, azim {azim:.0f}", np.clip(to_srgb(np.clip(rgb, 0, 1)), 0, 1)))
    return out


def main(argv=None) -> int:
    args = parse_args(argv)
    t0 = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    target_v, target_f = TARGETS[args.target]()
    template = icosphere(args.subdivisions, args.radius)
    cameras = sil.orbit_cameras(args.views, args.size)
    settings = sil.silhouette_settings(args.size)
    target_alpha = sil.target_silhouettes(target_v, target_f, cameras, settings)
    weights = dict(sil.DEFAULT_WEIGHTS, laplacian=args.laplacian, flatten=args.flatten)
    stages = sil.default_stages(sigmas=args.sigmas, iters=[args.iters] * len(args.sigmas),
                                weights=weights)
    print(f"target {args.target}: {len(target_v)} vertices, {len(target_f)} faces; template "
          f"icosphere {len(template[0])} vertices; {args.views} views of {args.size}x{args.size}; "
          f"stages " + ", ".join(f"sigma {s.sigma:g} x {s.max_iters}" for s in stages))

    t_fit = time.perf_counter()
    fitted_v, result = sil.fit_to_silhouettes(target_alpha, cameras, template, stages,
                                              out_dir=args.out, progress=args.progress,
                                              settings=settings)
    t_fit = time.perf_counter() - t_fit

    target = (target_v, target_f)
    fitted = (fitted_v, template[1])
    before = dict(chamfer=sil.chamfer_distance(template, target),
                  viou=sil.volume_iou(template, target))
    after = dict(chamfer=sil.chamfer_distance(fitted, target), viou=sil.volume_iou(fitted, target))

    hard = sil.silhouette_settings(args.size)
    fitted_alpha = sil.target_silhouettes(*fitted, cameras, hard)
    template_alpha = sil.target_silhouettes(*template, cameras, hard)
    save_mesh(args.out / "fitted.ply", *fitted)
    save_mesh(args.out / "target.ply", *target)
    shaded = shaded_views([("target", *target), ("fitted", *fitted)])
    comparison_image(args.out / "comparison.png", target_alpha, fitted_alpha, template_alpha,
                     args.out / "history.json", shaded)

    def iou2d(a):
        a, t = a > 0.5, target_alpha > 0.5
        return float(np.mean((a & t).sum((1, 2)) / np.maximum((a | t).sum((1, 2)), 1)))

    print(f"fit: {len(result.history)} evaluations in {t_fit:.1f} s; outcomes "
          + ", ".join(f"{k} {v}" for k, v in result.outcomes.items())
          + f"; scale {float(result.values['scale'][0]):.3f}")
    print(f"{'':10s}{'Chamfer':>10s}{'volume IoU':>12s}{'mean 2D IoU':>13s}")
    print(f"{'before':10s}{before['chamfer']:10.4f}{before['viou']:12.3f}{iou2d(template_alpha):13.3f}")
    print(f"{'after':10s}{after['chamfer']:10.4f}{after['viou']:12.3f}{iou2d(fitted_alpha):13.3f}")
    print(f"wrote {args.out / 'fitted.ply'}, {args.out / 'comparison.png'}; "
          f"total time {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
