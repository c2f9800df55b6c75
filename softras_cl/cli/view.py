"""Options shared by `softras-cl render`, `compare` and `demo`: a mesh file seen by a look-at
camera, the argparse types that check numbers as they are parsed, and the checks a command
makes before any kernel runs (a mesh that can draw something, a request that fits memory)."""
from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

logger = logging.getLogger(__name__)


# ---- argparse types: a bad value is an argparse error (exit 2) naming the option ----------------
def _number(text: str, what: str = "a finite number") -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """A finite number."""
    return _number(text)


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _number(text, "a finite number > 0")
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text}")
    return value


def fov_degrees(text: str) -> float:
    """A field of view in (0, 180) degrees."""
    value = _number(text)
    if not 0 < value < 180:
        raise argparse.ArgumentTypeError(f"must be in (0, 180) degrees, got {text}")
    return value


def elevation_degrees(text: str) -> float:
    """An elevation in [-90, 90] degrees."""
    value = _number(text)
    if not -90 <= value <= 90:
        raise argparse.ArgumentTypeError(f"must be in [-90, 90] degrees (beyond, use --azimuth "
                                         f"+ 180 and 180 - elevation), got {text}")
    return value


def triple(text: str) -> tuple[float, float, float]:
    """One number (used for all three) or three comma-separated finite numbers."""
    try:
        parts = [float(p) for p in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected one number or three comma-separated numbers, "
                                         f"got {text!r}") from None
    if len(parts) == 1:
        parts *= 3
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected one number or three comma-separated numbers, got {text!r}")
    if not all(math.isfinite(p) for p in parts):
        raise argparse.ArgumentTypeError(f"must be finite numbers, got {text!r}")
    return tuple(parts)


def add_view_options(p: argparse.ArgumentParser, size: int) -> None:
    p.add_argument("mesh", type=Path, help="mesh file: OBJ, PLY, GLB/GLTF or OFF (colours, UVs, textures kept)")
    p.add_argument("--size", type=positive_int, default=size,
                   help=f"image width and height in pixels (default {size})")
    p.add_argument("--width", type=positive_int, help="image width in pixels (overrides --size)")
    p.add_argument("--height", type=positive_int, help="image height in pixels (overrides --size)")
    p.add_argument("--azimuth", type=finite_float, default=30.0,
                   help="camera azimuth in degrees around +y, 0 = looking from +z (default 30)")
    p.add_argument("--elevation", type=elevation_degrees, default=20.0,
                   help="camera elevation in degrees, -90 to 90 (default 20); at +-90 the camera "
                        "looks straight down (up) and the image's up is the horizontal direction "
                        "away from (towards) the azimuth")
    p.add_argument("--fov", type=fov_degrees, default=30.0,
                   help="field of view in degrees across the shorter image side, 0 to 180 (default 30)")
    p.add_argument("--no-normalize", action="store_true",
                   help="keep the mesh's own coordinates (default: centre it and scale it into the unit sphere)")


def image_size(args) -> tuple[int, int]:
    """(height, width) from --size, --width and --height."""
    return (args.height if args.height is not None else args.size,
            args.width if args.width is not None else args.size)


def orbit_camera(azimuth: float, elevation: float, fov: float, size: tuple[int, int]):
    """Camera on the sphere around the origin that frames the unit sphere (80 % of the shorter
    side), at azimuth/elevation degrees. Its up vector is world +y projected onto the image
    plane, written out so that it stays defined at elevation +-90 (straight down or up), where
    it is the horizontal direction away from (towards) the azimuth."""
    import numpy as np

    from softras_cl.scene.camera import Camera

    distance = 1.0 / np.sin(np.radians(fov) / 2) / 0.8
    az, el = np.radians(azimuth), np.radians(elevation)
    eye = distance * np.array([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    up = np.array([-np.sin(el) * np.sin(az), np.cos(el), -np.sin(el) * np.cos(az)])
    if abs(elevation) == 90:
        logger.info("elevation %g: the camera looks straight %s; image up is world %s",
                    elevation, "down" if elevation > 0 else "up", np.round(up, 6).tolist())
    return Camera.look_at(eye, (0.0, 0.0, 0.0), up=up, fov_deg=fov, image_size=size)


def load_view(args):
    """(mesh, camera) from the shared options; the camera frames the unit sphere."""
    from softras_cl.io.meshes import load_mesh

    mesh = load_mesh(args.mesh)
    if not args.no_normalize:
        mesh = mesh.normalized()
    return mesh, orbit_camera(args.azimuth, args.elevation, args.fov, image_size(args))


def zero_area_faces(mesh) -> int:
    """How many faces of `mesh` have (nearly) zero area: |cross| <= 1e-12 x the squared extent."""
    import numpy as np

    tri = mesh.vertices[mesh.faces]
    doubled = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    extent = float(np.ptp(mesh.vertices[np.unique(mesh.faces)], axis=0).max())
    return int((doubled <= 1e-12 * max(extent, 1e-300) ** 2).sum())


def check_drawable(mesh, name) -> None:
    """ResultError if every face of `mesh` has zero area (nothing can be drawn)."""
    from softras_cl.errors import ResultError

    if zero_area_faces(mesh) == mesh.n_faces:
        raise ResultError(f"every face of {name} ({mesh.n_faces}) has zero area (degenerate "
                          "triangles): there is nothing to draw")


def check_command_memory(command: str, settings, n_faces: int, post_bytes_per_pixel: float,
                         device=None) -> None:
    """ResourceError before anything is allocated if `command` at settings.image_size cannot
    fit: the rasteriser's estimate (softras_cl.raster.memory) or what the command does with the
    image afterwards (`post_bytes_per_pixel`, measured per command), whichever is larger. The
    message says what it needs, what there is and the largest --size that fits."""
    from softras_cl.cl.device import select_device
    from softras_cl.errors import ResourceError
    from softras_cl.raster.memory import available_host_memory, check_memory, memory_estimate

    h, w = settings.image_size
    estimate = memory_estimate(settings, 1, n_faces)
    post = int(post_bytes_per_pixel * h * w)
    estimate = estimate.plus_host(max(0, post - estimate.shared), f"{command} at {w} x {h}")
    device = device if device is not None else select_device()
    logger.info("%s needs ~%.2f GB (rasteriser %.2f GB, image output %.2f GB)", estimate.what,
                estimate.shared / 2 ** 30, (estimate.shared - max(0, post - estimate.shared)) / 2 ** 30,
                post / 2 ** 30)
    try:
        check_memory(estimate, device, advice="use a smaller --size")
    except ResourceError as e:
        free = available_host_memory()
        if free is None:
            raise
        side = _largest_side(settings, n_faces, post_bytes_per_pixel, free, device)
        raise ResourceError(f"{e}" + (f" (at most {side} x {side} fits now)" if side >= 1 else "")) from None


def _largest_side(settings, n_faces: int, post: float, free: int, device) -> int:
    """The largest square --size whose estimate fits `free` bytes and the device's limits."""
    from softras_cl.raster.memory import memory_estimate

    def fits(n: int) -> bool:
        e = memory_estimate(settings.replace(image_size=(n, n)), 1, n_faces)
        return (max(e.shared, post * n * n) <= free and e.largest_buffer <= device.max_mem_alloc_size
                and e.device <= device.global_mem_size)

    lo, hi = 0, 1 << 17
    while lo < hi:
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if fits(mid) else (lo, mid - 1)
    return lo


def output_folder(path: Path, option: str = "--out") -> Path:
    """Create the folder of an output file; OutputError (exit 3) naming `option` if it cannot be."""
    from softras_cl.errors import OutputError

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(f"{option} {path}: cannot create its folder: {e.strerror or e}") from None
    return path


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
