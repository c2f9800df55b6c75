"""Options shared by `softras-cl render` and `softras-cl compare`: a mesh file seen by a look-at camera."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


def triple(text: str) -> tuple[float, float, float]:
    parts = [float(p) for p in text.split(",")]
    if len(parts) == 1:
        parts *= 3
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected one number or three comma-separated numbers, got {text!r}")
    return tuple(parts)


def add_view_options(p: argparse.ArgumentParser, size: int) -> None:
    p.add_argument("mesh", type=Path, help="mesh file: OBJ, PLY, GLB/GLTF or OFF (colours, UVs, textures kept)")
    p.add_argument("--size", type=int, default=size, help=f"image width and height in pixels (default {size})")
    p.add_argument("--width", type=int, help="image width in pixels (overrides --size)")
    p.add_argument("--height", type=int, help="image height in pixels (overrides --size)")
    p.add_argument("--azimuth", type=float, default=30.0,
                   help="camera azimuth in degrees around +y, 0 = looking from +z (default 30)")
    p.add_argument("--elevation", type=float, default=20.0, help="camera elevation in degrees (default 20)")
    p.add_argument("--fov", type=float, default=30.0,
                   help="field of view in degrees across the shorter image side (default 30)")
    p.add_argument("--no-normalize", action="store_true",
                   help="keep the mesh's own coordinates (default: centre it and scale it into the unit sphere)")


def load_view(args):
    """(mesh, camera) from the shared options; the camera frames the unit sphere."""
    import numpy as np

    from softras_cl.scene.camera import Camera
    from softras_cl.io.meshes import load_mesh

    mesh = load_mesh(args.mesh)
    if not args.no_normalize:
        mesh = mesh.normalized()
    h, w = args.height or args.size, args.width or args.size
    distance = 1.0 / np.sin(np.radians(args.fov) / 2) / 0.8
    az, el = np.radians(args.azimuth), np.radians(args.elevation)
    eye = distance * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    return mesh, Camera.look_at(eye, (0.0, 0.0, 0.0), fov_deg=args.fov, image_size=(h, w))


def make_light(args):
    from softras_cl.scene import shading

    if args.light == "lambert":
        return shading.LambertLight(args.ambient, args.directional, args.light_dir)
    if args.light == "phong":
        return shading.PhongLight(args.ambient, args.directional, args.light_dir,
                                  specular=args.specular, shininess=args.shininess)
    if args.light == "sh":
        return shading.SHLight.ambient(args.ambient[0])
    return None
