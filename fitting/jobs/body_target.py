"""Reading the inputs of a body fit: the target image and its 2D joints (used by `softras-cl
fit-body` for one target and by softras_cl.fitting.batch for many)."""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

__all__ = ["read_joints", "read_target"]


def read_joints(path, n_joints: int) -> tuple[np.ndarray, np.ndarray]:
    """2D joints file -> (points (J, 2) float64 pixels, weights (J,) float64).

    Text: one row per model joint, 'x y' or 'x y weight' (whitespace or commas; '#' comments;
    0-based pixel centres, x right, y down; weight 0 = not seen, its x y may be nan). .npy: an
    (J, 2) or (J, 3) array. ValueError naming the file on anything else or a wrong row count.
    """
    path = Path(path)
    try:
        rows = np.load(path) if path.suffix.lower() == ".npy" else np.loadtxt(
            io.StringIO(path.read_text().replace(",", " ")), ndmin=2)
    except (OSError, ValueError) as e:
        raise ValueError(f"joints file {path}: cannot read it ({e})") from e
    rows = _numbers(rows, f"joints file {path}", "rows 'x y' or 'x y weight'")
    if rows.ndim != 2 or rows.shape[1] not in (2, 3):
        raise ValueError(f"joints file {path}: expected rows 'x y' or 'x y weight', got shape {rows.shape}")
    if len(rows) != n_joints:
        raise ValueError(f"joints file {path}: has {len(rows)} joints, the model has {n_joints}")
    weights = rows[:, 2] if rows.shape[1] == 3 else np.ones(n_joints)
    return rows[:, :2], weights


def read_target(path, silhouette: bool) -> np.ndarray:
    """The target as fit_body takes it: an image file (sRGB, decoded to linear; RGBA keeps its
    alpha) or an .npy of linear values; with ``silhouette`` an (H, W) mask (the alpha channel
    when there is one, else the mean of the colour channels). float64."""
    from softras_cl.io.images import read_image

    path = Path(path)
    if path.suffix.lower() == ".npy":
        try:
            img = np.load(path)
        except (OSError, ValueError) as e:
            raise ValueError(f"cannot read target {path}: {e}") from e
        img = _numbers(img, f"target {path}", "an (H, W) mask or an (H, W, 3|4) linear image")
    else:
        img = read_image(path)
    if silhouette and img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[..., 3] if img.shape[2] == 4 else img.mean(-1)
    return img


def _numbers(values: np.ndarray, what: str, expected: str) -> np.ndarray:
    """``values`` (an array read from a file) as float64; ValueError naming ``what`` and the
    ``expected`` content when they are not numbers (strings, objects, ...)."""
    if not (np.issubdtype(values.dtype, np.number) or values.dtype == np.bool_):
        raise ValueError(f"{what}: expected numbers ({expected}), got an array of dtype "
                         f"{values.dtype} and shape {values.shape}")
    return np.asarray(values, np.float64)


def parse_background(text: str) -> tuple[float, float, float]:
    """'r,g,b' -> (r, g, b) floats; ValueError naming the option otherwise."""
    try:
        background = tuple(float(c) for c in str(text).split(","))
    except ValueError:
        background = ()
    if len(background) != 3:
        raise ValueError(f"--background must be 'r,g,b', got {text!r}")
    return background
