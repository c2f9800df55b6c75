"""Test pictures made from the shipped astronaut photo, with the shipped 68 points moved to where
the face went: a small face in a large frame, two faces, the photo turned by quarter turns."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

DATA = Path(__file__).resolve().parents[2] / "examples" / "data"
#: the astronaut's head with a margin (x0, y0, x1, y1): what is pasted
HEAD = (150, 40, 310, 230)


def read_pts(path: Path) -> np.ndarray:
    """Own minimal iBUG .pts reader: (68, 2) 0-based pixel coordinates (the file is 1-based)."""
    lines = [line.strip() for line in path.read_text().splitlines() if line.strip()]
    assert lines[0] == "version: 1" and lines[1].replace(" ", "") == "n_points:68"
    assert lines[2] == "{" and lines[-1] == "}"
    pts = np.array([[float(v) for v in line.split()] for line in lines[3:-1]])
    assert pts.shape == (68, 2)
    return pts - 1.0


def astronaut() -> tuple[np.ndarray, np.ndarray]:
    """(the photo (512, 512, 3) uint8, its shipped (68, 2) points)."""
    image = np.asarray(Image.open(DATA / "astronaut.png").convert("RGB"))
    return image, read_pts(DATA / "landmarks" / "astronaut.pts")


def nme(points, reference) -> float:
    """Mean distance between (68, 2) points and the reference over the reference's
    outer-eye-corner distance (points 36 and 45, the 300-W normalisation)."""
    return float(np.linalg.norm(points - reference, axis=1).mean()
                 / np.linalg.norm(reference[45] - reference[36]))


def background(width: int, height: int, seed: int = 0) -> Image.Image:
    """A faceless background: skimage's coffee photo stretched to the size, with noise."""
    import skimage.data

    coffee = np.asarray(Image.fromarray(skimage.data.coffee()).resize((width, height)), dtype=np.int16)
    noise = np.random.default_rng(seed).integers(-20, 21, coffee.shape)
    return Image.fromarray(np.clip(coffee + noise, 0, 255).astype(np.uint8))


def paste_heads(canvas: Image.Image, placements) -> tuple[np.ndarray, list[np.ndarray]]:
    """Paste the astronaut's HEAD at each (x, y, width) of `placements` (resized to that width):
    (the picture (H, W, 3) uint8, the shipped points moved to each pasted head)."""
    photo, points = astronaut()
    head = Image.fromarray(photo).crop(HEAD)
    moved = []
    for x, y, width in placements:
        scale = width / head.width
        canvas.paste(head.resize((width, round(head.height * scale)), Image.LANCZOS), (x, y))
        # pixel centre c of the photo -> (c + 0.5 - HEAD corner) * scale + paste corner - 0.5
        moved.append((points + 0.5 - HEAD[:2]) * scale + [x, y] - 0.5)
    return np.asarray(canvas), moved


def small_face_in_large_frame() -> tuple[np.ndarray, np.ndarray]:
    """The head 80 px wide (the face about 50 px) in a 1600x1200 frame: (picture, its points)."""
    picture, (points,) = paste_heads(background(1600, 1200), [(1013, 707, 80)])
    return picture, points


def tiny_face_in_large_frame() -> tuple[np.ndarray, np.ndarray]:
    """The head 44 px wide (the face about 28 px) in a 1600x1200 frame: (picture, its points)."""
    picture, (points,) = paste_heads(background(1600, 1200), [(1013, 707, 44)])
    return picture, points


def two_faces() -> tuple[np.ndarray, list[np.ndarray]]:
    """The head 240 px and 120 px wide in a 900x600 frame: (picture, [large's, small's points])."""
    return paste_heads(background(900, 600, seed=1), [(60, 80, 240), (600, 300, 120)])


def turned(image: np.ndarray, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """np.rot90(image, k) and the points moved with it (0-based pixel centres), computed one
    quarter turn at a time: a turn maps pixel (row r, column c) of an (H, W) image to
    (W - 1 - c, r)."""
    for _ in range(k % 4):
        width = image.shape[1]
        image = np.rot90(image)
        points = np.stack([points[:, 1], width - 1 - points[:, 0]], axis=1)
    return np.ascontiguousarray(image), points
