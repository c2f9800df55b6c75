"""Per-evaluation cost of the face objective's parts (docs/notes/face_host.md), one tree.

    .venv/bin/softras-cl -q fit-face examples/data/astronaut.png --landmarks examples/data/landmarks/astronaut.pts --out /tmp/fit
    .venv/bin/python scripts/face_host_parts.py /tmp/fit/params.npz --evals 100 > after.json

Builds the astronaut's objective as fit-face does and evaluates it at the fitted values of a
fit-face output (params.npz) in the landmark stage and the last photometric stage. Parts are
the main-thread CPU milliseconds (time.thread_time: OpenCL threads and time spent waiting for
a core left out) of the named functions, inclusive; "total" is wall time and "total_cpu" the
process's CPU time. Prints one JSON line of per-stage medians over the evaluations. To compare
two trees, run it in each (PYTHONPATH = the tree) in turn, several times (A B A B ...).
"""
from __future__ import annotations

import os
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")      # as the softras-cl command line runs numpy

import argparse
import collections
import json
import time
from pathlib import Path

import numpy as np

from softras_cl.fitting import losses
from softras_cl.fitting.model_cache import load_model
from softras_cl.fitting.detection import resolve_landmarks
from softras_cl.fitting.recipes import face
from softras_cl.io.images import read_image
from softras_cl.raster.rasterizer import SoftRasterizer
from softras_cl.scene import camera, renderer, shading

DATA = Path(__file__).resolve().parents[1] / "examples" / "data"
BLOCKS = ("id", "exp", "albedo", "sh", "rotation", "translation", "focal")
PARTS = {"raster": [(SoftRasterizer, "forward"), (SoftRasterizer, "backward")],
         "shade_vertices": [(shading, "shade_vertices")], "shade_vertices_vjp": [(shading, "shade_vertices_vjp")],
         "geometry": [(face.FaceScene, "geometry")], "geometry_vjp": [(face.FaceScene, "geometry_vjp")],
         "landmark_term": [(face.FaceObjective, "landmark_term")],
         "camera.project": [(camera.Camera, "project")], "camera.project_vjp": [(camera.Camera, "project_vjp")],
         "robust_loss": [(losses, "image_geman_mcclure")] + ([(losses.GemanMcClure, "__call__")]
                                                             if hasattr(losses, "GemanMcClure") else []),
         "Renderer.forward": [(renderer.Renderer, "forward")], "Renderer.backward": [(renderer.Renderer, "backward")]}


def timed(spent: dict):
    """Wrap every function of PARTS so that its main-thread CPU time adds up in spent[part]."""
    for part, targets in PARTS.items():
        for owner, name in targets:
            def wrapper(*args, _fn=getattr(owner, name), _part=part, **kwargs):
                start = time.thread_time()
                try:
                    return _fn(*args, **kwargs)
                finally:
                    spent[_part] += time.thread_time() - start
            setattr(owner, name, wrapper)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("params", help="params.npz of a fit-face run on the astronaut")
    parser.add_argument("--evals", type=int, default=100, help="evaluations per stage (default 100)")
    args = parser.parse_args()
    photo = read_image(DATA / "astronaut.png")[..., :3]
    points = resolve_landmarks(str(DATA / "astronaut.png"), str(DATA / "landmarks" / "astronaut.pts"))[0].points
    config = face.FaceFitConfig()
    objective, _, _ = face.prepare_fit(photo, points, load_model("face", None, None), config)
    stages = {s.name: s for s in face.default_stages(config, fit_focal=True)}
    fitted = np.load(args.params)
    values = {k: np.asarray(fitted[k], np.float64) for k in BLOCKS}
    spent = collections.defaultdict(float)
    timed(spent)
    out = {}
    for name in ("landmarks", list(stages)[-1]):
        objective(values, stages[name])                 # the stage's start: region, scale
        rows = collections.defaultdict(list)
        for _ in range(args.evals):
            spent.clear()
            wall, cpu, main_cpu = time.perf_counter(), time.process_time(), time.thread_time()
            objective(values, stages[name])
            rows["total"].append(time.perf_counter() - wall)
            rows["total_cpu"].append(time.process_time() - cpu)
            rows["main thread cpu"].append(time.thread_time() - main_cpu)
            rows["host (main thread cpu - raster)"].append(rows["main thread cpu"][-1] - spent["raster"])
            for part in PARTS:
                rows[part].append(spent[part])
        out[name] = {k: 1e3 * float(np.median(v)) for k, v in rows.items()}
    out["load_1min"] = os.getloadavg()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
