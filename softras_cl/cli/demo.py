"""`softras-cl demo`: render the built-in screen-space icosphere to a PNG.

The sphere (softras_cl.scene.meshes.screen_space_sphere: radius 0.8, centred, depth 2 to 3.6) is drawn
with smooth per-vertex colours by the soft rasteriser over a white background,
converted from linear RGB to sRGB and written as an 8-bit RGB PNG.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from softras_cl.cli.view import check_command_memory, output_folder, positive_float, positive_int
from softras_cl.io.outputs import atomic_path

DESCRIPTION = ("Render the built-in screen-space icosphere with per-vertex colours, composited on white, "
               "to an sRGB PNG; prints the path and the time taken.")
DEFAULT_OUT = Path("out") / "demo.png"
# 20 * 4**8 = 1,310,720 faces: about 1.1 GB and 15 s on 2 cores at 512^2, with faces already
# smaller than a pixel at that size; every further subdivision quadruples time and memory
# (9: ~4 GB, about a minute), and at 20 building the sphere alone needs terabytes.
MAX_SUBDIVISIONS = 8
# Peak bytes per pixel after rendering (float64 sRGB encoding and the PNG), measured at 2048^2
# and 4096^2 with max RSS.
BYTES_PER_PIXEL = 190


def render_demo(out: str | Path = DEFAULT_OUT, size: int = 512, subdivisions: int = 3,
                sigma: float = 1e-5, gamma: float = 1e-4, device=None) -> dict:
    """Render the icosphere at size x size pixels and write it to `out` (parents created).

    Returns dict(path=Path, seconds=total time (imports, set-up, rendering, saving),
    render_seconds=rasteriser forward time (incl. the kernel build on first use),
    faces=int, image=(size, size, 3) float sRGB in [0, 1] as written).
    """
    start = time.perf_counter()     # includes the (slow) imports: the time a user waits
    import matplotlib.image
    import numpy as np

    from softras_cl.srgb import to_srgb

    from softras_cl.scene.meshes import screen_space_sphere
    from softras_cl.raster.rasterizer import SoftRasterizer
    from softras_cl.raster.settings import RasterSettings

    verts, faces, colors = screen_space_sphere(subdivisions)
    # The background colour is part of the softmax aggregation (eq. 8), so rgb is already the
    # mesh over a white page; no alpha compositing (that would show the occupancy's faint
    # alpha ~ 3/4 seams along shared edges, eq. 13).
    settings = RasterSettings(image_size=(size, size), sigma=sigma, gamma=gamma,
                              background=(1.0, 1.0, 1.0), outputs=("rgb",))
    raster = SoftRasterizer(settings, device=device)
    t0 = time.perf_counter()
    rendered = raster.forward(verts, faces, colors=colors)
    render_seconds = time.perf_counter() - t0
    linear = rendered.rgb[0].astype(np.float64)
    srgb = np.clip(to_srgb(np.clip(linear, 0.0, 1.0)), 0.0, 1.0)
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        matplotlib.image.imsave(tmp, (np.round(srgb * 255)).astype(np.uint8), format="png")
    return dict(path=path, seconds=time.perf_counter() - start, render_seconds=render_seconds,
                faces=len(faces), image=srgb)


def _subdivisions(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not 0 <= value <= MAX_SUBDIVISIONS:
        raise argparse.ArgumentTypeError(
            f"must be an integer in [0, {MAX_SUBDIVISIONS}] (20 * 4**{MAX_SUBDIVISIONS} = "
            f"{20 * 4 ** MAX_SUBDIVISIONS:,} faces, already smaller than a pixel at 512^2; each step "
            f"quadruples time and memory), got {text}")
    return value


def _run(args: argparse.Namespace) -> int:
    from softras_cl.raster.settings import RasterSettings

    settings = RasterSettings(image_size=(args.size, args.size), sigma=args.sigma, gamma=args.gamma,
                              background=(1.0, 1.0, 1.0), outputs=("rgb",))
    check_command_memory("demo", settings, 20 * 4 ** args.faces, BYTES_PER_PIXEL)
    output_folder(args.out)
    result = render_demo(args.out, size=args.size, subdivisions=args.faces, sigma=args.sigma,
                         gamma=args.gamma)
    print(f"wrote {result['path']} ({args.size}x{args.size}, {result['faces']} faces) in "
          f"{result['seconds']:.2f} s (rasteriser {result['render_seconds'] * 1000:.1f} ms)")
    return 0


def register(sub) -> None:
    """Add the `demo` subcommand to the `softras-cl` subparsers."""
    p = sub.add_parser("demo", help="render a built-in icosphere to a PNG", description=DESCRIPTION)
    p.add_argument("--out", type=Path, default=DEFAULT_OUT,
                   help=f"where to write the PNG (default: {DEFAULT_OUT}); folders are created")
    p.add_argument("--size", type=positive_int, default=512,
                   help="image width and height in pixels (default: 512)")
    p.add_argument("--faces", type=_subdivisions, default=3, metavar="SUBDIVISIONS",
                   help=f"icosphere subdivisions, 0 to {MAX_SUBDIVISIONS}: 20 * 4**SUBDIVISIONS faces "
                        "(default: 3, 1280 faces)")
    p.add_argument("--sigma", type=positive_float, default=1e-5,
                   help="sharpness of the probability maps, squared NDC units (default: 1e-5)")
    p.add_argument("--gamma", type=positive_float, default=1e-4,
                   help="sharpness of the softmax colour aggregation (default: 1e-4)")
    p.set_defaults(func=_run)
