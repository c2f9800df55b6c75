"""Is the soft rasteriser deterministic on this device? The same forward+backward, three times.

    python scripts/gpu_check_determinism.py --out FILE.json [--faces N] [--size S] [--layouts L,...]

The scene is `softras-cl bench raster`'s (icosphere of N faces at S x S pixels, fixed random
cotangents; default the bench scene, 20480 faces at 1024^2). For each kernel layout (none given:
the rasteriser's default) it runs forward+backward twice on one rasteriser and once on a fresh
one, hashes the images and gradients (SHA-256 of rgb, alpha, dL/dvertices, dL/dcolors) and
writes FILE.json: {device, faces, size, runs: [{layout, hashes, identical}], identical}.
Exit code 0 when every layout gave bit-identical results, 1 when one did not.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

from softras_cl.bench.raster import make_scene, run_once, settings_for
from softras_cl.provenance import opencl_device
from softras_cl.raster.rasterizer import SoftRasterizer

BENCH_SCENE = (20480, 1024)     # (faces, image size) of the raster bench's headline row


def result_hash(out, grads: dict) -> str:
    """SHA-256 (hex) over the bytes of rgb, alpha and the vertex and colour gradients."""
    h = hashlib.sha256()
    for array in (out.rgb, out.alpha, grads["vertices"], grads["colors"]):
        h.update(array.tobytes())
    return h.hexdigest()


def layout_hashes(scene, settings) -> list[str]:
    """Hashes of three forward+backward runs: two on one rasteriser, one on a fresh one."""
    first = SoftRasterizer(settings)
    hashes = [result_hash(*run_once(first, scene)[2:]) for _ in range(2)]
    hashes.append(result_hash(*run_once(SoftRasterizer(settings), scene)[2:]))
    return hashes


def check(faces: int, size: int, layouts: list[str]) -> dict:
    """The report written to --out (see the module docstring)."""
    scene = make_scene(faces, size)
    runs = []
    for layout in layouts or [None]:
        settings = settings_for(size) if layout is None else settings_for(size, layout=layout)
        hashes = layout_hashes(scene, settings)
        runs.append(dict(layout=layout, hashes=hashes, identical=len(set(hashes)) == 1))
    return dict(device=opencl_device(), faces=faces, size=size, runs=runs,
                identical=all(r["identical"] for r in runs))


def layout_list(text: str) -> list[str]:
    """'cpu,gpu' -> ['cpu', 'gpu']; '' -> [] (the rasteriser's default layout)."""
    return [t.strip() for t in text.split(",") if t.strip()]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="JSON file to write")
    p.add_argument("--faces", type=int, default=BENCH_SCENE[0], help="icosphere face count 20*4**s")
    p.add_argument("--size", type=int, default=BENCH_SCENE[1], help="image size in pixels")
    p.add_argument("--layouts", type=layout_list, default=[],
                   help="kernel layouts, comma-separated (default: the rasteriser's own choice)")
    args = p.parse_args(argv)
    if args.size < 1:
        p.error(f"--size must be >= 1, got {args.size}")
    report = check(args.faces, args.size, args.layouts)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(dict(identical=report["identical"],
                          runs=[(r["layout"], r["identical"]) for r in report["runs"]])))
    return 0 if report["identical"] else 1


if __name__ == "__main__":
    sys.exit(main())
