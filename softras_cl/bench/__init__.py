"""`softras-cl bench`: one module per benchmark, each adding its subcommand to `bench`.

raster (the soft rasteriser: speed, memory, accuracy), render (the whole differentiable render
path), pose, face and body (the fitting recipes on synthetic targets with known answers), interop
(the PyTorch and JAX bridges' overhead over the numpy call), batch (photos per minute of many
fits against Dask workers and threads), track (the face tracker on synthetic talking-head videos),
landmarks (face detection and 68 landmarks on Mitsuba photos with known points).
"""
from __future__ import annotations

from importlib import import_module

# benchmark name -> module whose register(which) adds it; each module imports its heavy
# dependencies inside its runner, so building the parser stays light.
BENCHMARKS = {"raster": "raster", "render": "render", "pose": "pose", "face": "face", "body": "body",
              "interop": "interop", "batch": "batch",
              "face-views": "face_views", "body-photo": "body_photo", "track": "track",
              "peers": "peers", "landmarks": "landmarks"}


def register(sub) -> None:
    """Add `bench` with every benchmark of BENCHMARKS to the `softras-cl` subparsers `sub`."""
    bench = sub.add_parser("bench", help="benchmarks (speed, memory, accuracy)",
                           description="Benchmarks of softras-cl; results go to --out as JSON and PNG.")
    which = bench.add_subparsers(dest="benchmark", metavar="BENCHMARK", required=True,
                                 help="one of: " + ", ".join(BENCHMARKS))
    for module in BENCHMARKS.values():
        import_module(f"softras_cl.bench.{module}").register(which)
