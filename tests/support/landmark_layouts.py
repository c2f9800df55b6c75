"""iBUG 300-W landmark sets turned the ways a photo can be: rolled, mirrored (with the points
renumbered, as a detector run on the mirrored photo gives them), shuffled."""
from __future__ import annotations

import numpy as np

#: IBUG_MIRROR[i]: the point that stands where point i does once the face is mirrored (jaw,
#: brows, nostrils, eyes and mouth swap sides; the nose bridge and the mouth's middle stay).
IBUG_MIRROR = np.r_[16 - np.arange(17), 26 - np.arange(10), 27, 28, 29, 30, 35, 34, 33, 32, 31,
                    45, 44, 43, 42, 47, 46, 39, 38, 37, 36, 41, 40,
                    54, 53, 52, 51, 50, 49, 48, 59, 58, 57, 56, 55, 64, 63, 62, 61, 60, 67, 66, 65]


def mirrored(points, width: int) -> np.ndarray:
    """Landmarks (68, 2) of a photo ``width`` pixels wide -> those of its mirror image, renumbered."""
    points = np.asarray(points, np.float64)
    return np.column_stack([width - 1 - points[:, 0], points[:, 1]])[IBUG_MIRROR]


def rolled(points, degrees: float, centre=None) -> np.ndarray:
    """Landmarks (68, 2) turned by ``degrees`` in the image plane about ``centre`` (default: their mean)."""
    points = np.asarray(points, np.float64)
    centre = points.mean(0) if centre is None else np.asarray(centre, np.float64)
    a = np.radians(degrees)
    turn = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return centre + (points - centre) @ turn.T


def shuffled(points, seed: int) -> np.ndarray:
    """The 68 rows in a random order."""
    return np.asarray(points)[np.random.default_rng(seed).permutation(len(points))]
