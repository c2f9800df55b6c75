"""Per-call time of Renderer.forward + backward in the face fit's setting.

The face fit (fitting.recipes.face) calls the renderer ~220 times per fit: the demo face mesh
(15,490 faces), float64, rgb + alpha, vertex shading under an SH light, gradients for vertices,
albedo, light and camera, and a region of interest (the face's tiles only). This script renders
that scene at each size, times `--calls` forward + backward pairs after one warm-up call and
prints the median wall and CPU ms per call and the median of each SoftRasterizer stage
(stage_ms; measured in separate calls, which wait for the device at every stage boundary).

    .venv/bin/python scripts/profile_render_calls.py --sizes 128,256 --calls 30
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))     # the repository's fitting package
from fitting.models.face_loaders import load_demo_face_model
from softras_cl.raster.settings import RasterSettings
from softras_cl.scene.camera import Camera
from softras_cl.scene.renderer import Renderer
from softras_cl.scene.shading import SHLight

GRADS = ("vertices", "albedo", "light", "camera")
DISTANCE = 0.6          # metres from the camera to the face


def face_scene(size: int, dtype: str):
    """(renderer, forward kwargs, cotangent) of the demo face filling most of a size^2 image."""
    model = load_demo_face_model()
    shape = model.shape(np.zeros(model.n_id), np.zeros(model.n_exp))[0]
    world = shape - shape.mean(0) + [0.0, 0.0, -DISTANCE]
    focal = 0.9 * size * DISTANCE / np.ptp(shape[:, 1])
    K = [[focal, 0, size / 2 - 0.5], [0, focal, size / 2 - 0.5], [0, 0, 1]]
    camera = Camera.from_opencv(K, np.diag([1.0, -1.0, -1.0]), np.zeros(3), (size, size))
    settings = RasterSettings(image_size=(size, size), outputs=("rgb", "alpha"), dtype=dtype,
                              near=0.5 * DISTANCE, far=2.0 * DISTANCE, sigma=1e-5, gamma=1e-4)
    renderer = Renderer(settings, shading="vertex")
    sh = np.zeros((3, 9))
    sh[:, 0] = 0.8
    inputs = dict(vertices=world, faces=model.faces, cameras=camera,
                  albedo=np.full(world.shape, 0.6), light=SHLight(sh))
    alpha = renderer.forward(**inputs).alpha[0]
    inputs["roi"] = alpha > 0.5
    rng = np.random.default_rng(0)
    return renderer, inputs, rng.standard_normal((1, size, size, 3)) * inputs["roi"][None, :, :, None]


def one_call(renderer, inputs, cot) -> tuple[float, float]:
    """(wall s, CPU s) of one forward + backward."""
    t, c = time.perf_counter(), time.process_time()
    out = renderer.forward(**inputs, grads=GRADS)
    renderer.backward(out, grad_rgb=cot)
    return time.perf_counter() - t, time.process_time() - c


def profile(size: int, dtype: str, calls: int) -> dict:
    renderer, inputs, cot = face_scene(size, dtype)
    one_call(renderer, inputs, cot)
    times = [one_call(renderer, inputs, cot) for _ in range(calls)]
    raster = next(iter(renderer._rasterizers.values()))
    stages = []
    for _ in range(calls):
        raster.stage_ms = {}
        one_call(renderer, inputs, cot)
        stages.append(raster.stage_ms)
    raster.stage_ms = None
    return dict(size=size, dtype=dtype, faces=len(inputs["faces"]), roi_pixels=int(inputs["roi"].sum()),
                wall_ms=1e3 * statistics.median(t[0] for t in times),
                cpu_ms=1e3 * statistics.median(t[1] for t in times),
                stage_ms={k: round(statistics.median(s.get(k, 0.0) for s in stages), 3) for k in stages[0]})


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", default="128,256")
    p.add_argument("--dtype", default="float64", choices=("float32", "float64"))
    p.add_argument("--calls", type=int, default=30)
    args = p.parse_args()
    print(f"load average {os.getloadavg()}")
    for size in (int(s) for s in args.sizes.split(",")):
        print(json.dumps(profile(size, args.dtype, args.calls)))
    print(f"load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
