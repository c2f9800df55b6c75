"""`softras-cl render MESH`: a mesh file rendered to a PNG."""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from softras_cl.io.outputs import atomic_path, check_output_file
from softras_cl.cli.view import (add_view_options, check_command_memory, check_drawable, finite_float,
                                 load_view, make_light, positive_float, triple)

# Peak bytes per pixel of the whole command after rendering, measured (max RSS, 2048^2 and
# 4096^2): the float64 copies and sRGB encoding of write_image dominate (rgb 183, rgba 219,
# the depth PNG +8).
BYTES_PER_PIXEL = dict(rgb=190, rgba=230, depth=20)


def _run_render(args: argparse.Namespace) -> int:
    import numpy as np

    from softras_cl.errors import ResultError
    from softras_cl.io.images import write_image
    from softras_cl.scene.renderer import Renderer
    from softras_cl.raster.settings import RasterSettings

    _check_image_paths(args)
    mesh, camera = load_view(args)
    check_drawable(mesh, args.mesh.name)
    outputs = ("rgb", "alpha", "depth") if args.depth_out else ("rgb", "alpha")
    settings = RasterSettings(image_size=tuple(camera.image_size), sigma=args.sigma, gamma=args.gamma,
                              dist_eps=args.dist_eps, background=args.background, outputs=outputs,
                              double_sided=args.double_sided, dtype=args.dtype, near=0.1, far=100.0)
    per_pixel = BYTES_PER_PIXEL["rgba" if args.transparent else "rgb"] + BYTES_PER_PIXEL["depth"] * bool(args.depth_out)
    check_command_memory("render", settings, mesh.n_faces, per_pixel)
    check_output_file(args.out, "--out")
    if args.depth_out:
        check_output_file(args.depth_out, "--depth-out")
    textured = mesh.texture is not None and mesh.uvs is not None
    albedo = mesh.colors if mesh.colors is not None else np.full(mesh.vertices.shape, 0.7)
    start = time.perf_counter()
    if textured or args.light == "none":
        color = dict(texture_image=mesh.texture[None], uvs=mesh.uvs) if textured else dict(albedo=albedo)
        out = Renderer(settings, shading="none").forward(mesh.vertices, mesh.faces, camera, **color)
    else:
        out = Renderer(settings, shading=args.shading).forward(mesh.vertices, mesh.faces, camera,
                                                               albedo=albedo, light=make_light(args))
    seconds = time.perf_counter() - start
    if not (out.alpha[0] > 0.5).any():
        raise ResultError(f"nothing was drawn: no pixel of {args.mesh.name} is covered (the mesh is "
                          f"outside the view{'' if args.double_sided else ' or faces away: try --double-sided'}); "
                          f"{args.out} not written")
    image = out.rgba()[0] if args.transparent else out.rgb[0]
    write_image(args.out, image.astype(np.float64))
    if args.depth_out:
        _write_depth(args.depth_out, out.depth[0], out.alpha[0])
    print(f"wrote {args.out} ({camera.image_size[1]}x{camera.image_size[0]}, {len(mesh.faces)} faces, "
          f"{'textured, unlit' if textured else args.light}): rendered in {seconds * 1000:.0f} ms, "
          f"{time.perf_counter() - start:.1f} s with writing")
    return 0


def _check_image_paths(args: argparse.Namespace) -> None:
    """--out (and --depth-out) must name image files: InputError for a folder or an extension
    that is no image format, before the mesh is read (whether the files can be written is
    checked before rendering, by check_output_file)."""
    from softras_cl.errors import InputError
    from softras_cl.io.images import image_format

    image_format(args.out, alpha=args.transparent, what="--out")
    if args.depth_out is not None and args.depth_out.is_dir():
        raise InputError(f"--depth-out {args.depth_out} is a folder: expected a .png file path")


def _write_depth(path: Path, depth, alpha) -> None:
    """Depth as a grey PNG, near = white, far = black, over the pixels with alpha > 0.5."""
    import matplotlib.image
    import numpy as np

    inside = alpha > 0.5
    shown = np.where(inside, depth, np.nan)
    with atomic_path(path) as tmp:
        matplotlib.image.imsave(tmp, shown, cmap="gray_r", format="png")


def register(sub) -> None:
    p = sub.add_parser("render", help="render a mesh file to a PNG",
                       description="Render a mesh with the soft rasteriser from a look-at camera, lit "
                                   "by the paper's Lambert light (or Phong / SH ambient), to an sRGB PNG. "
                                   "Textured meshes are drawn unlit from their texture.")
    add_view_options(p, 512)
    p.add_argument("--out", type=Path, default=Path("out/render.png"), help="output PNG (default out/render.png)")
    p.add_argument("--light", choices=("lambert", "phong", "sh", "none"), default="lambert",
                   help="lighting: lambert (ambient + directional), phong (+ Blinn-Phong specular), "
                        "sh (constant SH ambient of --ambient), none (unlit colours); default lambert")
    p.add_argument("--shading", choices=("vertex", "face"), default="vertex",
                   help="evaluate lighting per vertex (smooth) or per face (flat); default vertex")
    p.add_argument("--ambient", type=triple, default=(0.5,) * 3, help="ambient light, grey or r,g,b (default 0.5)")
    p.add_argument("--directional", type=triple, default=(0.5,) * 3,
                   help="directional light intensity, grey or r,g,b (default 0.5)")
    p.add_argument("--light-dir", type=triple, default=(0.0, 1.0, 0.0),
                   help="direction towards the light, x,y,z world (default 0,1,0: from above)")
    p.add_argument("--specular", type=triple, default=(0.2,) * 3, help="Phong specular intensity (default 0.2)")
    p.add_argument("--shininess", type=positive_float, default=32.0, help="Phong exponent (default 32)")
    p.add_argument("--sigma", type=positive_float, default=1e-5, help="probability-map sharpness, squared NDC (default 1e-5)")
    p.add_argument("--gamma", type=positive_float, default=1e-4, help="aggregation sharpness (default 1e-4)")
    p.add_argument("--dist-eps", type=finite_float, default=1e-4, help="cut-off on the probability map (default 1e-4)")
    p.add_argument("--background", type=triple, default=(1.0,) * 3, help="background colour, linear (default 1 = white)")
    p.add_argument("--double-sided", action="store_true", help="draw back faces too (for open meshes)")
    p.add_argument("--transparent", action="store_true", help="write RGBA with the soft alpha instead of RGB")
    p.add_argument("--depth-out", type=Path, help="also write the depth map as a grey PNG here")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32", help="kernel precision (default float32)")
    p.set_defaults(func=_run_render)
