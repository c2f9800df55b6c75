"""STAND-IN peer worker for the tests of `softras-cl bench peers` -- not PyTorch3D.

It speaks the protocol of softras_cl/bench/peer_pytorch3d.py (see its docstring) so that the
harness runs end to end in CI without the peer environment, but it renders with softras-cl's
own dense numpy reference (softras_cl.raster.reference, float64) and takes the gradients by
central finite differences of that reference. Its images follow softras-cl's conventions, so it
reports no pixel where the barycentric clippings differ, and its pair count as unknown (-1).

STANDIN_BREAK (environment) makes it wrong on purpose, for the tests that the harness notices:
"sigma" renders with twice the sigma, "mirror" mirrors the images left-right, "crash" exits
with an error before it is ready.
"""
from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

from softras_cl.bench.peers import import_scene
from softras_cl.raster import reference as ref

FD_STEP = 1e-6


def render(scene, settings) -> tuple[np.ndarray, np.ndarray]:
    """(rgb (H, W, 3), alpha (H, W)) of the float64 reference, broken as STANDIN_BREAK says."""
    out = ref.soft_rasterize(scene.vertices, scene.faces, settings, colors=scene.colors)
    rgb, alpha = out["rgb"][0], out["alpha"][0]
    if os.environ.get("STANDIN_BREAK") == "mirror":
        rgb, alpha = rgb[:, ::-1], alpha[:, ::-1]
    return rgb, alpha


def losses(scene, settings, vertices) -> tuple[float, float]:
    """(sum(rgb * grad_rgb) + sum(alpha * grad_alpha), sum(alpha * grad_alpha)) at `vertices`."""
    scene.vertices = vertices
    rgb, alpha = render(scene, settings)
    silhouette = float(np.sum(alpha * scene.grad_alpha[0]))
    return float(np.sum(rgb * scene.grad_rgb[0])) + silhouette, silhouette


def gradients(scene, settings) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of both losses with respect to every vertex coordinate, (V, 3) each.

    The faces not drawn at the base point (the sphere's edge-on faces have zero area) are left
    out, as an analytic gradient does: a step would turn some of them front-facing, a jump of
    the loss that central differences would turn into a huge slope.
    """
    base, all_faces = scene.vertices.copy(), scene.faces
    scene.faces = all_faces[ref.drawn_faces(base[all_faces][None], settings)[0]]
    grad, grad_silhouette = np.zeros_like(base), np.zeros_like(base)
    for index in np.ndindex(base.shape):
        plus, minus = base.copy(), base.copy()
        plus[index] += FD_STEP
        minus[index] -= FD_STEP
        (lp, sp), (lm, sm) = losses(scene, settings, plus), losses(scene, settings, minus)
        grad[index], grad_silhouette[index] = (lp - lm) / (2 * FD_STEP), (sp - sm) / (2 * FD_STEP)
    scene.vertices, scene.faces = base, all_faces
    return grad, grad_silhouette


def main(scene_path: str, out_path: str) -> int:
    if os.environ.get("STANDIN_BREAK") == "crash":
        sys.exit("stand-in peer: crashing on purpose (STANDIN_BREAK=crash)")
    scene, settings, _ = import_scene(scene_path)
    if os.environ.get("STANDIN_BREAK") == "sigma":
        settings = settings.replace(sigma=2 * settings.sigma)
    print("ready 0", flush=True)
    for line in sys.stdin:
        if line.strip() == "quit":
            break
        t0, c0 = time.perf_counter(), time.process_time()
        rgb, alpha = render(scene, settings)
        t1, c1 = time.perf_counter(), time.process_time()
        print(f"done {t1 - t0:.9f} {t1 - t0:.9f} {c1 - c0:.9f} {c1 - c0:.9f}", flush=True)
    grad, grad_silhouette = gradients(scene, settings)
    np.savez(out_path, rgb=rgb, alpha=alpha, grad_vertices=grad, grad_silhouette=grad_silhouette,
             clipping_differs=np.zeros(alpha.shape, bool), pairs=-1, saturated_pixels=0,
             info=json.dumps(dict(renderer="STAND-IN: softras_cl.raster.reference (float64, finite differences)")))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
